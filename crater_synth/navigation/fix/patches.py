"""Terrain patches: landmarks that are not craters, for frames in which too few craters can be found.

Below ~70 km a descent's frames hold one or two map craters of D >= 10 km, too few for a fix. The
appearance search (:mod:`.appearance`) does not need a crater: it predicts a window of the DEM's terrain
(Hapke shading and horizon shadows, :mod:`.refine`) and finds it by correlation. A *terrain patch* is such
a window placed where the frame is, not where a crater is: the prior camera's rays through a regular grid
of frame pixels meet the DEM's surface at points that become landmarks of ``source="patch"`` (their
3-D point the surface point, their "diameter" the window's size), searched for, identified and used by the
fix exactly as the craters are. This is terrain-relative navigation by image-to-map correlation (the
patch-matching of map-relative localisation), here a fallback: a frame is navigated with its craters
first, and with its patches only when the craters give no fix (:func:`..rendered.evaluate.evaluate_frame`).

A patch holds as much as the DEM resolves: at a 6-8 degree Sun the long shadows of the DEM's relief
make the texture the correlation finds. Frames rendered from the same DEM share its relief, so the
accuracy measured on them is an upper bound for a real camera's frames (docs/navigation/rendered.md);
on real mosaic windows (:func:`window_patches`, ``nav-eval --patches``) the same patches are placed on the
window's map grid and tested against the WAC's own images (docs/navigation/fix.md).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from crater_core import geometry
from crater_synth.navigation.fix.refine import RefineParams
from crater_synth.navigation.georef import stereo_inverse
from crater_synth.navigation.map.landmarks import Landmark, stereo_forward
from crater_synth.terrain.dem import DemError

PATCH_SOURCE = "patch"
GROUND_ITERATIONS = 12  # at most, ray / DEM-height iterations (they contract by ~slope x tan(off-nadir angle))
GROUND_TOLERANCE_M = 0.01  # stop when no height changes by more


@dataclasses.dataclass(frozen=True)
class PatchParams:
    """Where the patches are placed (set before any evaluation, not tuned: docs/navigation/rendered.md)."""

    grid: int = 4  # grid x grid frame points, at the centres of equal cells
    half_share: float = 0.1  # a patch window's half-width as a share of the frame's footprint

    def __post_init__(self):
        if not 1 <= int(self.grid) <= 16:
            raise ValueError(f"patch grid={self.grid}: expected 1 to 16 points each way")
        if not 0.01 <= float(self.half_share) <= 0.5:
            raise ValueError(f"patch half_share={self.half_share}: expected 0.01 to 0.5 of the footprint")


def ground_points(dem, c_enu: np.ndarray, dirs_enu: np.ndarray, origin: tuple[float, float]):
    """(lat, lon, height m) where rays from the camera centre ``c_enu`` along ``dirs_enu`` (N, 3), in the ENU
    frame of ``origin`` (lat, lon), meet the DEM's surface: the sphere raised to the DEM's height at the
    last intersection, iterated until the heights settle (curvature included). Rays that miss the Moon (or
    meet it behind the camera) give NaN."""
    lat0, lon0 = origin
    c_mc = geometry.enu_to_mc(np.asarray(c_enu, dtype=np.float64)[None], lat0, lon0)[0]
    d_mc = geometry.enu_to_mc(c_enu[None] + np.asarray(dirs_enu, dtype=np.float64), lat0, lon0) - c_mc
    d_mc /= np.linalg.norm(d_mc, axis=1, keepdims=True)
    height = np.zeros(len(d_mc))
    lat = lon = np.full(len(d_mc), np.nan)
    for _ in range(GROUND_ITERATIONS):
        b = d_mc @ c_mc
        disc = b * b - (c_mc @ c_mc - (geometry.MOON_RADIUS_M + height) ** 2)
        t = -b - np.sqrt(np.where(disc >= 0, disc, np.nan))  # the near intersection
        t = np.where(t > 0, t, np.nan)  # ahead of the camera only
        lat, lon = geometry.mc_to_latlon(c_mc + t[:, None] * d_mc)[:2]
        ok = np.isfinite(lat)
        if not ok.any():
            break
        new = np.zeros(len(d_mc))
        new[ok] = dem.sample(lat[ok], lon[ok], what="terrain patch points").heights
        done = np.nanmax(np.abs(new - height)[ok]) < GROUND_TOLERANCE_M
        height = new
        if done:
            break
    return lat, lon, height


def patch_landmarks(
    dem,
    c_prior: np.ndarray,
    r_wc: np.ndarray,
    k: np.ndarray,
    width: int,
    origin,
    pole: str,
    params: PatchParams = PatchParams(),
) -> list[Landmark]:
    """The terrain patches of a ``width`` px square frame seen from ``c_prior`` (ENU of ``origin``) with
    world->camera rotation ``r_wc`` and intrinsics ``k`` (:func:`.fix.project_pinhole`'s convention): one per
    cell of a ``params.grid`` square grid, at the ground point under the cell's centre, its window
    ``params.half_share`` of the footprint wide each way (the footprint at the points' median depth).
    Points off the Moon or off the DEM are left out."""
    centres = (np.arange(params.grid) + 0.5) / params.grid * width
    uu, vv = np.meshgrid(centres, centres)
    rays = np.column_stack([(uu.ravel() - k[0, 2]) / k[0, 0], (vv.ravel() - k[1, 2]) / k[1, 1], np.ones(uu.size)])
    try:
        lat, lon, height = ground_points(dem, c_prior, rays @ r_wc, origin)
    except DemError:  # the frame reaches past the DEM: patches only where it has data
        lat, lon, height = _ground_points_each(dem, c_prior, rays @ r_wc, origin)
    ok = np.isfinite(lat) & np.isfinite(height)
    if not ok.any():
        return []
    pts = geometry.mc_to_enu(geometry.latlon_to_mc(lat[ok], lon[ok], height[ok]), *origin)
    depth = float(np.median((pts - c_prior) @ r_wc[2]))
    return _patches(lat[ok], lon[ok], height[ok], params.half_share * width / k[0, 0] * depth, pole)


def window_patches(dem, georef, shape, params: PatchParams = PatchParams()) -> list[Landmark]:
    """The terrain patches of a map window (a north-up polar stereographic nadir frame of ``shape`` placed by
    ``georef``, :class:`.frames.Georef`, e.g. the prior's): one per cell of a ``params.grid`` square grid, at
    the map point under the cell's centre and the DEM's height there, its window ``params.half_share`` of
    the window's width wide each way. Points off the DEM are left out."""
    rows, cols = shape[:2]
    cells = (np.arange(params.grid) + 0.5) / params.grid
    uu, vv = np.meshgrid(cells * cols, cells * rows)
    x, y = georef.uv_to_xy(uu.ravel(), vv.ravel())
    lat, lon = (np.asarray(a, dtype=np.float64) for a in stereo_inverse(x, y, georef.pole))
    height = _heights(dem, lat, lon)
    ok = np.isfinite(height)
    return _patches(lat[ok], lon[ok], height[ok], params.half_share * cols * georef.pixel_m, georef.pole)


def _patches(lat, lon, height, half_m: float, pole: str) -> list[Landmark]:
    """Patch landmarks at (lat, lon, height) whose windows are ``half_m`` wide each way (the window is
    ``RefineParams.window_diameters`` landmark diameters wide each way). Each id names its place and size, so a
    Refiner's terrain cache never mixes two patches."""
    diameter_km = half_m / RefineParams().window_diameters / 1000.0
    out = []
    for la, lo, h in zip(lat, lon, height):
        x, y = stereo_forward(la, lo, pole)
        pid = f"patch:{la:.5f}:{lo:.5f}:{diameter_km:.3f}"
        out.append(
            Landmark(
                pid, "", float(la), float(lo), float(x), float(y), diameter_km, 0.0, float(h), 0.0, 0.0, PATCH_SOURCE
            )
        )
    return out


def _heights(dem, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """DEM heights at (lat, lon), NaN where a point lies off the DEM."""
    try:
        return np.asarray(dem.sample(lat, lon, what="terrain patch points").heights, dtype=np.float64)
    except DemError:  # some point is off the DEM: each one alone
        out = np.full(lat.shape, np.nan)
        for q in range(lat.size):
            try:
                one = dem.sample(lat[q : q + 1], lon[q : q + 1], what="terrain patch points").heights
                out[q] = float(np.ravel(one)[0])
            except DemError:
                continue
        return out


def _ground_points_each(dem, c_enu, dirs_enu, origin):
    """:func:`ground_points` one ray at a time, NaN for those that leave the DEM."""
    out = np.full((3, len(dirs_enu)), np.nan)
    for q in range(len(dirs_enu)):
        try:
            out[:, q] = np.ravel(ground_points(dem, c_enu, dirs_enu[q : q + 1], origin))
        except DemError:
            continue
    return out[0], out[1], out[2]
