"""Landmark refinement by predicted appearance: the fix's landmarks registered on their DEM rendering.

A crater detector measures a rim's centre to a few pixels (under a grazing Sun the lit and shadowed
walls pull it); with 3-8 landmarks that scatter is what limits a known-attitude fix, above all in
altitude. Once the landmarks are identified and a first fix is made, the lander knows more than a
circle per landmark: its DEM (the one the landmark map was measured in), the Sun and its approximate
pose. So each identified landmark's neighbourhood is predicted as the camera should see it, and
registered on the frame:

1. A square of the landmark's tangent plane (half-width ``window_diameters`` x D, ``samples`` per
   side) is sampled from the DEM (bicubic, on the sphere: curvature included), with a coarse far
   field around it for distant occluders.
2. Its I/F is the project's Hapke model (:func:`crater_core.hapke.shade_np`) times the visible
   fraction of the solar disc above the horizon along the Sun's azimuth
   (:func:`crater_core.horizon.horizon_maps`, :func:`~crater_core.horizon.disc_fraction_above`):
   the renderer's physics, without the sub-DEM detail a DEM cannot know.
3. The samples are projected into the frame with the current fix and the frame is read there, shifted
   by every whole pixel within ``search_px``; the shift of highest normalised cross-correlation (NCC),
   refined to a sub-pixel by a parabola through its neighbours, moves the landmark's predicted pixel.
   A peak on the search border or below ``min_ncc`` leaves the landmark's detector observation as it was.
4. The camera centre is solved again from the moved observations (:func:`.fix.solve_position`) and the
   whole is repeated ``iterations`` times.

The registration measures the image of the landmark's 3-D rim-centre point directly, so the
ellipse-centre correction of the plain fix is not needed for a refined landmark.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from crater_core import geometry
from crater_core.horizon import Terrain, disc_fraction_above, horizon_maps, texel_centres

# After the first solve the predictions sit within a pixel of their images: later passes search +-3 px.
FOLLOW_UP_SEARCH_PX = 3


@dataclasses.dataclass(frozen=True)
class RefineParams:
    """Settings of the appearance refinement (chosen on development frames: docs/navigation.md, section 9)."""

    window_diameters: float = 0.75  # half-width of the predicted window, in landmark diameters
    samples: int = 64  # predicted samples per side of the window
    search_px: int = 10  # largest shift searched (px, each way)
    min_ncc: float = 0.5  # a weaker peak leaves the detector's observation
    iterations: int = 2
    far_radius_km: float = 150.0  # far-field occluders around the landmark (1 deg Sun, 2.6 km relief)
    far_spacing_m: float = 1600.0  # the polar DEMs' base pixel


def _tangent_grid(dem, lat: float, lon: float, half_m: float, n: int, what: str):
    """ENU (of (lat, lon)) points of the DEM surface under an n x n tangent-plane grid of half-width
    ``half_m`` at :func:`~crater_core.horizon.texel_centres` (row 0 north, column 0 west)."""
    from crater_synth.terrain.grid import sphere_points

    e, nn = texel_centres(half_m, n)
    dirs, plat, plon = sphere_points(e, nn, lat, lon)
    h = dem.sample(plat, plon, spacing_m=2.0 * half_m / n, what=what).heights
    return geometry.mc_to_enu(dirs * (geometry.MOON_RADIUS_M + h)[..., None], lat, lon)


def _normals(xyz: np.ndarray) -> np.ndarray:
    east = np.gradient(xyz, axis=1)
    north = -np.gradient(xyz, axis=0)  # rows run southwards
    nrm = np.cross(east, north)
    return nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)


def predict_window(dem, landmark, to_sun_mc, camera_mc, hapke, params: RefineParams = RefineParams()):
    """(MC points (n, n, 3), predicted I/F (n, n)) of ``landmark``'s window seen from ``camera_mc``."""
    lat, lon = float(landmark.lat), float(landmark.lon)
    half = params.window_diameters * landmark.diameter_km * 1000.0
    n = int(params.samples)
    near = _tangent_grid(dem, lat, lon, half, n, f"landmark {landmark.id} window")
    far_n = 2 * int(math.ceil(params.far_radius_km * 1000.0 / params.far_spacing_m)) + 1
    far = _tangent_grid(dem, lat, lon, far_n * params.far_spacing_m / 2.0, far_n, f"landmark {landmark.id} far field")
    basis = geometry.enu_basis(lat, lon)
    to_sun = basis @ np.asarray(to_sun_mc, dtype=np.float64)
    elevation = math.asin(max(-1.0, min(1.0, float(to_sun[2]))))
    azimuth = math.degrees(math.atan2(to_sun[0], to_sun[1])) % 360.0
    slope = horizon_maps(Terrain(near, far), azimuth, [half], n)[0, 0]
    lit = disc_fraction_above(elevation, np.arctan(slope))
    cam = geometry.mc_to_enu(np.asarray(camera_mc, dtype=np.float64), lat, lon)
    view = cam - near
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    from crater_core.hapke import shade_np

    nrm = _normals(near)
    shade = np.where(nrm @ to_sun > 0.0, shade_np(nrm, to_sun, view, hapke), 0.0)
    return geometry.enu_to_mc(near, lat, lon), np.nan_to_num(shade * lit, nan=0.0)


def _ncc(image: np.ndarray, u, v, predicted, offsets: np.ndarray) -> np.ndarray:
    """NCC of ``predicted`` with ``image`` read (bilinear) at array coordinates (u, v) + each offset (du, dv)."""
    from scipy.ndimage import map_coordinates

    su = (u[None, :] + offsets[:, :1]).ravel()
    sv = (v[None, :] + offsets[:, 1:]).ravel()
    vals = map_coordinates(image, [sv, su], order=1).reshape(len(offsets), -1)
    a = predicted - predicted.mean()
    b = vals - vals.mean(axis=1, keepdims=True)
    return (b @ a) / (np.linalg.norm(b, axis=1) * np.linalg.norm(a) + 1e-30)


def _square(centre, half: int, step: int) -> np.ndarray:
    s = np.arange(-half, half + 1) * step
    dv, du = np.meshgrid(s, s, indexing="ij")
    return np.column_stack([du.ravel(), dv.ravel()]) + np.asarray(centre)


def register(image: np.ndarray, uv: np.ndarray, predicted: np.ndarray, search_px: int):
    """(shift (du, dv) px, NCC) that best aligns ``predicted`` (values at pixels ``uv``, (..., 2), the
    continuous convention of :func:`.fix.project_pinhole`: pixel i spans [i, i + 1]) with ``image``.

    Whole-pixel shifts within ``search_px`` are searched (every second pixel first when the search is
    wider than 3 px, then every pixel around the best: the predicted windows hold DEM-scale relief, several
    pixels wide, so the correlation peak is too), and the peak is refined by a parabola through its
    neighbours. The shift is None when the peak lies on the search border, or when fewer than 16 samples
    stay in the frame under every shift (the same samples for every shift: NCCs comparable)."""
    h, w = image.shape
    u = uv[..., 0].ravel() - 0.5
    v = uv[..., 1].ravel() - 0.5
    reach = search_px + 2
    ok = (u >= reach) & (u <= w - 1 - reach) & (v >= reach) & (v <= h - 1 - reach)  # False for NaN
    p = np.asarray(predicted, dtype=np.float64).ravel()[ok]
    if ok.sum() < 16 or np.ptp(p) <= 0:
        return None, float("nan")
    img, u, v = np.asarray(image, dtype=np.float64), u[ok], v[ok]
    centre = np.zeros(2)
    if search_px > 3:
        half = search_px // 2
        coarse = _ncc(img, u, v, p, _square(centre, half, 2)).reshape(2 * half + 1, -1)
        i, j = np.unravel_index(int(np.argmax(coarse)), coarse.shape)
        if i in (0, 2 * half) or j in (0, 2 * half):
            return None, float(coarse[i, j])
        centre, search_px = np.array([2 * (j - half), 2 * (i - half)], dtype=float), 2
    surf = _ncc(img, u, v, p, _square(centre, search_px, 1)).reshape(2 * search_px + 1, -1)
    i, j = np.unravel_index(int(np.argmax(surf)), surf.shape)
    if i in (0, 2 * search_px) or j in (0, 2 * search_px):
        return None, float(surf[i, j])

    def vertex(m1, c0, p1):
        den = m1 - 2.0 * c0 + p1
        return 0.0 if den >= 0 else float(np.clip(0.5 * (m1 - p1) / den, -0.5, 0.5))

    ddu = vertex(surf[i, j - 1], surf[i, j], surf[i, j + 1])
    ddv = vertex(surf[i - 1, j], surf[i, j], surf[i + 1, j])
    return centre + np.array([j - search_px + ddu, i - search_px + ddv]), float(surf[i, j])


def ellipse_centre_fix(points, uv, radii_m, c_fix, r_wc, k, fov_deg: float, width: int, iterations: int = 2):
    """(camera centre, corrected observations): a detection measures the rim ellipse's centre, which
    perspective moves off the image of the rim's centre point; each observation ``uv`` (n, 2) of a rim
    centre ``points`` (n, 3, frame ENU; rims of ``radii_m`` on the sphere's tangent plane) is corrected by
    that offset at the current fix ``c_fix`` and the known-attitude position solved again, ``iterations``
    times."""
    from crater_synth.navigation.fix import project_pinhole, solve_position

    points, uv = np.asarray(points, dtype=np.float64), np.asarray(uv, dtype=np.float64)
    normals = points + np.array([0.0, 0.0, geometry.MOON_RADIUS_M])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    c, corrected = np.asarray(c_fix, dtype=np.float64), uv
    for _ in range(iterations):
        pose = geometry.CameraPose(position=c, rotation=np.stack([r_wc[0], -r_wc[1], -r_wc[2]], 1), fov_deg=fov_deg)
        ellipses = [geometry.project_circle(p, nrm, rad, pose, width) for p, nrm, rad in zip(points, normals, radii_m)]
        centres = np.array([[e.cu, e.cv] for e in ellipses])
        corrected = uv - (centres - project_pinhole(points, r_wc, c, k))
        c = solve_position(points, corrected, k, r_wc)
    return c, corrected


class Refiner:
    """The appearance refinement with a lander's DEM (:func:`lander_dem`) and the project's Hapke model."""

    def __init__(self, dem, params: RefineParams = RefineParams()):
        from crater_synth.navigation.template import hapke_params

        self.dem, self.params, self.hapke = dem, params, hapke_params()

    def refine(self, image, landmarks, observed_uv, points_enu, c_fix, r_wc, k, origin, to_sun_mc):
        """Camera centre (frame ENU) after registering each identified landmark's predicted window.

        ``landmarks``: the fix's landmarks; ``observed_uv`` (n, 2): their observations as the plain fix
        used them; ``points_enu`` (n, 3): their rim-centre points in the ENU frame of ``origin`` (lat,
        lon); ``c_fix``, ``r_wc``, ``k``: the plain fix's camera. Returns (centre, {"seconds": wall time,
        "landmarks": per-landmark records: NCC, shift, whether the registration replaced the observation,
        or why it was not tried}). The
        windows are predicted once, from the plain fix (a pixel or two of camera motion changes the view
        angle by microradians), and registered again after each solve."""
        from crater_synth.navigation.fix import project_pinhole, solve_position
        from crater_synth.terrain.dem import DemError

        t0 = time.perf_counter()
        p = self.params
        lat0, lon0 = origin
        c = np.asarray(c_fix, dtype=np.float64)
        cam_mc = geometry.enu_to_mc(c, lat0, lon0)
        windows = []
        for lm in landmarks:
            try:
                pts_mc, pred = predict_window(self.dem, lm, to_sun_mc, cam_mc, self.hapke, p)
                windows.append((geometry.mc_to_enu(pts_mc.reshape(-1, 3), lat0, lon0), pred.ravel()))
            except DemError as exc:  # the window or its far field leaves the DEM: keep the detection
                windows.append(str(exc))
        obs = np.asarray(observed_uv, dtype=np.float64)
        records: list[dict] = []
        for it in range(p.iterations):
            moved, records = obs.copy(), []
            search = p.search_px if it == 0 else FOLLOW_UP_SEARCH_PX
            for q, win in enumerate(windows):
                if isinstance(win, str):
                    records.append({"used": False, "reason": win})
                    continue
                pts, pred = win
                uv = np.full((len(pts), 2), np.nan)
                front = (pts - c) @ r_wc[2] > 0
                uv[front] = project_pinhole(pts[front], r_wc, c, k)
                shift, ncc = register(image, uv, pred, search)
                used = shift is not None and ncc >= p.min_ncc
                if used:
                    moved[q] = project_pinhole(points_enu[q : q + 1], r_wc, c, k)[0] + shift
                records.append(
                    {
                        "used": bool(used),
                        "ncc": round(ncc, 4),
                        "shift_px": None if shift is None else np.round(shift, 3).tolist(),
                    }
                )
            if sum(r["used"] for r in records) < 2:  # one landmark alone cannot move a position
                break
            c = solve_position(points_enu, moved, k, r_wc)
        return c, {"seconds": round(time.perf_counter() - t0, 3), "landmarks": records}


def lander_dem(pole: str):
    """The DEM a lander carries for ``pole``: the landmark map's DEM (``dem=lola_ldem256_<pole>``) with the
    finer layers its configuration stacks on it."""
    from crater_synth.config import load_settings
    from crater_synth.terrain.patch import open_dem_stack

    return open_dem_stack(load_settings([f"dem=lola_ldem256_{pole}"]))
