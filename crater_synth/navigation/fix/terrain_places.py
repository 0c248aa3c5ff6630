"""Lost-in-space places from the terrain: a nadir view of the ground correlated with the lander's DEM shaded
under the frame's Sun, over the whole polar map (``nav.lost_in_space.terrain_places``).

The pair vote (:mod:`.lost_in_space`) offers the places its craters agree on, so it offers nothing where the
detector finds too few of the map's landmarks. A lander that carries the DEM its map was measured in, and knows
its attitude (star tracker) and the Sun (ephemeris), can predict what the whole pole looks like under that Sun:
the sunlit slopes, and at a low Sun the long shadows that dominate a polar image. The frame, resampled onto the
ground at a known scale (the altimeter) and turned to the map's axes (the attitude), is then a template of that
prediction, and where it correlates best is where the camera may be. Those places go to the same confirmation
by appearance as the vote's (:func:`crater_synth.navigation.rendered.lost_in_space.confirmed_six_dof`): a place
offered here is a hypothesis, never a fix.

The prediction (:func:`shaded_map`) is the project's physics at the DEM's scale: the Hapke radiance factor
(:func:`crater_core.hapke.shade_np`) of the DEM's facets, times the visible fraction of the solar disc above
the horizon towards the Sun (:func:`crater_core.horizon.disc_fraction_above`). The Sun's rays are parallel:
one Moon-fixed direction, whose elevation above each point's horizon follows from the point's own vertical
(so a pole-wide map at a 2 degree Sun has the Sun 10 degrees apart across it). Its map direction is taken as
one for the whole map (the polar stereographic plane is within 10 degrees of every tangent plane it covers,
and the Sun is near every horizon, so its horizontal direction turns by far less than a degree). The horizon
is marched along that direction on the stereographic grid, the Moon's curvature included (an occluder at
distance t is lowered by t^2 / 2R), out to :data:`HORIZON_REACH_KM`. The matching is OpenCV's normalised
correlation (``TM_CCOEFF_NORMED``) with the footprint as its mask: the gain and offset between a rendered or
real I/F and the prediction do not matter.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import cv2
import numpy as np

from crater_core import geometry
from crater_core.hapke import radiance_factor_np
from crater_core.horizon import disc_fraction_above
from crater_synth.navigation.detectors.template import hapke_params
from crater_synth.navigation.fix.refine import lander_dem
from crater_synth.navigation.georef import stereo_forward, stereo_inverse

HORIZON_REACH_KM = 150.0  # occluders this far towards the Sun: 2.6 km of relief at a 1 degree Sun (refine's far field)
# The march takes every grid step to this many, then every 2nd to twice as far, then every 4th: a crest
# missed between samples 2-4 pixels apart at that distance moves a horizon by under a tenth of a degree.
MARCH_DENSE_STEPS = 32
NO_OCCLUDER = -1.0e6  # height outside the DEM: below any ray


class MapGrid(NamedTuple):
    """The polar stereographic grid the DEM is shaded on: ``heights`` (m above the sphere, float32),
    ``normals`` and ``up`` (unit, Moon-centred, (h, w, 3)), its ``pixel_m``, and ``x0``/``y1`` (map metres of
    its left and top edges)."""

    pole: str
    pixel_m: float
    x0: float
    y1: float
    heights: np.ndarray
    normals: np.ndarray
    up: np.ndarray


class ShadedMap(NamedTuple):
    """The DEM's predicted I/F on a :class:`MapGrid` (float32), with that grid's placement."""

    image: np.ndarray
    pixel_m: float
    x0: float
    y1: float


@functools.lru_cache(maxsize=2)
def map_grid(pole: str, pixel_m: float) -> MapGrid:
    """The lander DEM's (:func:`.refine.lander_dem`) whole extent on a stereographic grid of ``pixel_m``: its
    heights, and its facets' normals from the Moon-centred points (curvature included)."""
    dem = lander_dem(pole)
    left, bottom, right, top = dem.bounds
    nx, ny = int((right - left) // pixel_m) - 2, int((top - bottom) // pixel_m) - 2
    x0, y1 = left + pixel_m, top - pixel_m
    xs = x0 + (np.arange(nx) + 0.5) * pixel_m
    ys = y1 - (np.arange(ny) + 0.5) * pixel_m
    lat, lon = stereo_inverse(xs[None, :], ys[:, None], pole)
    heights = dem.sample(lat, lon, spacing_m=pixel_m, what=f"the {pole} pole's shaded map").heights
    up = geometry.latlon_to_mc(lat, lon, 0.0)
    up /= np.linalg.norm(up, axis=-1, keepdims=True)
    points = up * (geometry.MOON_RADIUS_M + heights)[..., None]
    normals = np.cross(np.gradient(points, axis=1), -np.gradient(points, axis=0))  # along +x, along +y
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    if np.einsum("...k,...k->...", normals, up).mean() < 0.0:
        normals = -normals
    return MapGrid(pole, float(pixel_m), float(x0), float(y1), heights.astype(np.float32), normals, up)


def sun_map_angle_deg(to_sun_mc: np.ndarray, pole: str) -> float:
    """The map direction (degrees anticlockwise from +x, y up) of the Sun's horizontal direction at the pole."""
    z = np.array([0.0, 0.0, 1.0 if pole == "north" else -1.0])
    s = np.asarray(to_sun_mc, dtype=np.float64)
    horiz = s - (s @ z) * z
    if np.linalg.norm(horiz) < 1e-9:
        raise ValueError("the Sun stands at the pole's zenith: it casts no direction")
    step = z * geometry.MOON_RADIUS_M + 1000.0 * horiz / np.linalg.norm(horiz)
    lat, lon, _ = geometry.mc_to_latlon(step[None, :])
    x, y = stereo_forward(lat, lon, pole)
    return math.degrees(math.atan2(float(y[0]), float(x[0])))


def horizon_slopes(heights: np.ndarray, pixel_m: float, angle_deg: float) -> np.ndarray:
    """tan of the horizon's elevation at each grid point towards map direction ``angle_deg`` (anticlockwise
    from +x), the Moon's curvature included; -1 where nothing rises within :data:`HORIZON_REACH_KM`.

    The grid is turned so that the direction runs along its rows (OpenCV: a positive angle turns the image
    anticlockwise), marched with shifted arrays, and turned back."""
    h, w = heights.shape
    side = int(math.ceil(math.hypot(h, w))) + 2
    turn = cv2.getRotationMatrix2D((w / 2.0, h / 2.0), -angle_deg, 1.0)
    turn[:, 2] += (side / 2.0 - w / 2.0, side / 2.0 - h / 2.0)
    z = cv2.warpAffine(
        heights.astype(np.float32), turn, (side, side), flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT, borderValue=NO_OCCLUDER,
    )  # fmt: skip
    slope = np.full_like(z, -1.0)
    reach = int(HORIZON_REACH_KM * 1000.0 / pixel_m)
    steps = [*range(1, MARCH_DENSE_STEPS + 1), *range(MARCH_DENSE_STEPS + 2, 2 * MARCH_DENSE_STEPS + 1, 2)]
    steps += list(range(2 * MARCH_DENSE_STEPS + 4, reach + 1, 4))
    for k in (s for s in steps if s <= reach):
        t = k * pixel_m
        drop = np.float32(t * t / (2.0 * geometry.MOON_RADIUS_M) / t)
        np.maximum(slope[:, :-k], (z[:, k:] - z[:, :-k]) / np.float32(t) - drop, out=slope[:, :-k])
    back = cv2.invertAffineTransform(turn)
    return cv2.warpAffine(slope, back, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


@functools.lru_cache(maxsize=4)
def _slopes(pole: str, pixel_m: float, angle_deg: float) -> np.ndarray:
    return horizon_slopes(map_grid(pole, pixel_m).heights, pixel_m, angle_deg)


def shaded_map(pole: str, pixel_m: float, to_sun_mc, to_viewer_mc=None) -> ShadedMap:
    """The lander DEM of ``pole`` shaded under the Moon-fixed Sun direction ``to_sun_mc`` (parallel rays: one
    (3,) vector) and seen from ``to_viewer_mc`` ((3,); None: each point from overhead), module docstring. The
    horizon map is kept for the Sun's map direction to the nearest degree (an arc's frames share it)."""
    grid = map_grid(pole, float(pixel_m))
    s = np.asarray(to_sun_mc, dtype=np.float64)
    s = s / np.linalg.norm(s)
    return _shade(grid, np.broadcast_to(s, grid.up.shape), to_viewer_mc, sun_map_angle_deg(s, pole))


def mosaic_shaded_map(pole: str, pixel_m: float, light_angle_deg: float, elevation_deg: float) -> ShadedMap:
    """The lander DEM of ``pole`` shaded as a mosaic shows it: every point lit from map direction
    ``light_angle_deg`` (anticlockwise from +x) at ``elevation_deg`` above its own horizon, and seen from
    overhead. A mosaic's images were taken on many orbits, so its Sun is not one parallel beam."""
    grid = map_grid(pole, float(pixel_m))
    a = math.radians(light_angle_deg)
    # The map direction as a Moon-centred vector: a step from the pole's point along it.
    lat, lon = stereo_inverse(np.array([0.0, 1000.0 * math.cos(a)]), np.array([0.0, 1000.0 * math.sin(a)]), pole)
    ends = geometry.latlon_to_mc(lat, lon, 0.0)
    step = ends[1] - ends[0]
    horiz = step - np.einsum("...k,k->...", grid.up, step)[..., None] * grid.up
    horiz /= np.linalg.norm(horiz, axis=-1, keepdims=True)
    el = math.radians(elevation_deg)
    sun = math.cos(el) * horiz + math.sin(el) * grid.up
    return _shade(grid, sun, None, float(light_angle_deg))


def _shade(grid: MapGrid, sun: np.ndarray, to_viewer_mc, angle_deg: float) -> ShadedMap:
    """I/F of ``grid``'s facets under per-point Sun directions ``sun`` (h, w, 3) whose map direction is
    ``angle_deg``: the Hapke radiance factor times the solar disc's visible fraction above the horizon."""
    view = grid.up if to_viewer_mc is None else np.broadcast_to(
        np.asarray(to_viewer_mc, dtype=np.float64) / np.linalg.norm(to_viewer_mc), grid.up.shape
    )  # fmt: skip
    slopes = _slopes(grid.pole, grid.pixel_m, float(round(angle_deg)))
    elevation = np.arcsin(np.clip(np.einsum("...k,...k->...", grid.up, sun), -1.0, 1.0))
    lit = disc_fraction_above(elevation, np.arctan(slopes))
    mu0 = np.einsum("...k,...k->...", grid.normals, sun)
    mu = np.einsum("...k,...k->...", grid.normals, view)
    radiance = radiance_factor_np(mu0, mu, np.einsum("...k,...k->...", sun, view), hapke_params())
    return ShadedMap((radiance * lit).astype(np.float32), grid.pixel_m, grid.x0, grid.y1)


def turned_template(image: np.ndarray, valid: np.ndarray, centre_uv, heading_deg: float):
    """(image, mask, the centre's pixel, pixel j spanning [j, j + 1)) of a ground view turned so that its +u axis
    points along map direction ``heading_deg`` (anticlockwise from the map's +x), on a canvas that holds it whole."""
    h, w = image.shape
    side_w = int(math.ceil(abs(w * math.cos(math.radians(heading_deg))) + abs(h * math.sin(math.radians(heading_deg)))))
    side_h = int(math.ceil(abs(w * math.sin(math.radians(heading_deg))) + abs(h * math.cos(math.radians(heading_deg)))))
    turn = cv2.getRotationMatrix2D((w / 2.0, h / 2.0), heading_deg, 1.0)
    turn[:, 2] += (side_w / 2.0 - w / 2.0, side_h / 2.0 - h / 2.0)
    out = cv2.warpAffine(image.astype(np.float32), turn, (side_w + 1, side_h + 1), flags=cv2.INTER_LINEAR)
    mask = cv2.warpAffine(valid.astype(np.uint8), turn, (side_w + 1, side_h + 1), flags=cv2.INTER_NEAREST)
    # OpenCV puts pixel centres at integers; ``centre_uv`` counts pixel j as [j, j + 1).
    centre = turn @ np.array([centre_uv[0] - 0.5, centre_uv[1] - 0.5, 1.0])
    return out, mask, (float(centre[0]) + 0.5, float(centre[1]) + 0.5)


def terrain_places(
    view: np.ndarray, valid: np.ndarray, view_pixel_m: float, centre_uv, heading_deg: float, shaded: ShadedMap,
    n: int, apart_km: float,
) -> list[tuple[complex, float]]:  # fmt: skip
    """The ``n`` map points (x + iy, m) where the ground ``view`` (a nadir image of ``view_pixel_m``, ``valid``
    inside its footprint, the point under the camera at pixel ``centre_uv``, its +u axis along map direction
    ``heading_deg``) correlates best with ``shaded``, at least ``apart_km`` apart, each with its correlation;
    none for a view too large for the map, with too small a footprint, or flat."""
    scale = view_pixel_m / shaded.pixel_m
    size = (max(1, round(view.shape[1] * scale)), max(1, round(view.shape[0] * scale)))
    small = cv2.resize(view.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    inside = cv2.resize(valid.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.99
    templ, mask, (cu, cv) = turned_template(small, inside, (centre_uv[0] * scale, centre_uv[1] * scale), heading_deg)
    if mask.sum() < 16 or templ.shape[0] >= shaded.image.shape[0] or templ.shape[1] >= shaded.image.shape[1]:
        return []
    if not np.std(templ[mask > 0]) > 1e-6:  # a flat view (all in shadow) correlates with nothing
        return []
    score = cv2.matchTemplate(shaded.image, templ, cv2.TM_CCOEFF_NORMED, mask=mask)
    score = np.where(np.isfinite(score), score, -1.0)
    radius = max(1, int(apart_km * 1000.0 / shaded.pixel_m))
    places = []
    for _ in range(n):
        r, c = np.unravel_index(int(np.argmax(score)), score.shape)
        best = float(score[r, c])
        if best <= -1.0:
            break
        x = shaded.x0 + (c + cu) * shaded.pixel_m
        y = shaded.y1 - (r + cv) * shaded.pixel_m
        places.append((complex(x, y), best))
        score[max(0, r - radius) : r + radius + 1, max(0, c - radius) : c + radius + 1] = -1.0
    return places
