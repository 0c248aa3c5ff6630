"""Landmark refinement by predicted appearance: the fix's landmarks registered on their DEM rendering.

A crater detector measures a rim's centre to a few pixels (under a grazing Sun the lit and shadowed
walls pull it); with 3-8 landmarks that scatter is what limits a known-attitude fix, above all in
altitude. Once the landmarks are identified and a first fix is made, the lander knows more than a
circle per landmark: its DEM (the one the landmark map was measured in), the Sun and its approximate
pose. So each identified landmark's neighbourhood is predicted as the camera should see it, and
registered on the frame:

1. A square of the landmark's tangent plane (half-width ``window_diameters`` x D, ``samples`` per
   side), laid out with one axis towards the Sun, is sampled from the DEM (bicubic, on the sphere:
   curvature included), with a coarse far-field strip running ``far_radius_km`` towards the Sun for
   distant occluders.
2. Its I/F is the project's Hapke model (:func:`crater_core.hapke.shade_np`) times the visible
   fraction of the solar disc above the horizon along the Sun's azimuth
   (:func:`crater_core.horizon.horizon_maps`, :func:`~crater_core.horizon.disc_fraction_above`):
   the renderer's physics, without the sub-DEM detail a DEM cannot know.
3. The samples are projected into the frame with the current fix and the frame is read there, shifted
   by whole pixels within ``search_px`` (every second one, then every one around the best); the shift of
   highest normalised cross-correlation (NCC), refined to a sub-pixel by a parabola through its
   neighbours, moves the landmark's predicted pixel.
   A peak on the search border or below ``min_ncc`` leaves the landmark's detector observation as it was.
4. The camera centre is solved again from the moved observations (:func:`.fix.solve_position`) and the
   whole is repeated ``iterations`` times.
5. Appearance check (``verify``): when fewer than two of the fix's landmarks register, the frame
   contradicts the fix and the evaluation gives no fix (:meth:`Refiner.verified`).

The registration measures the image of the landmark's 3-D rim-centre point directly, so the
ellipse-centre correction of the plain fix is not needed for a refined landmark. A 6-DOF fix is refined the
same way, its attitude solved with its centre (``pose``), optionally weighted towards a believed attitude.

Length: one stage, the appearance refinement: the window terrain, its shading, the registration, the
:class:`Refiner`'s terrain cache and workers and the solves all work on one window model, kept together.
"""

from __future__ import annotations

import dataclasses
import math
import multiprocessing
import time
from collections import OrderedDict
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from crater_core import geometry
from crater_core.hapke import shade_np
from crater_core.horizon import Terrain, disc_fraction_above, horizon_maps, texel_centres
from crater_synth.config import load_settings
from crater_synth.navigation.detectors.template import hapke_params
from crater_synth.navigation.fix.pose import pose_with_attitude, project_pinhole, refine_pose, solve_position
from crater_synth.terrain.dem import DemError
from crater_synth.terrain.grid import sphere_points
from crater_synth.terrain.patch import open_dem_stack

# After the first solve the predictions sit within a pixel of their images: later passes search +-3 px.
FOLLOW_UP_SEARCH_PX = 3


@dataclasses.dataclass(frozen=True)
class RefineParams:
    """Settings of the appearance refinement (chosen on development frames: docs/navigation/rendered.md)."""

    window_diameters: float = 0.75  # half-width of the predicted window, in landmark diameters
    samples: int = 64  # predicted samples per side of the window
    search_px: int = 10  # largest shift searched (px, each way)
    min_ncc: float = 0.5  # a weaker peak leaves the detector's observation
    iterations: int = 2
    verify: bool = True  # no fix when fewer than two of its landmarks register (:meth:`Refiner.verified`)
    far_radius_km: float = 150.0  # far-field occluders around the landmark (1 deg Sun, 2.6 km relief)
    far_spacing_m: float = 1600.0  # the polar DEMs' base pixel


def _sun_frame(lat: float, lon: float, to_sun_mc) -> np.ndarray:
    """Rows: the unit vectors (MC) of a local frame at (lat, lon) whose y axis points to the Sun's azimuth
    (x to its right, z up): the Sun's rays then run along the frame's rows, so the far field needed for
    the shadows is a strip towards the Sun."""
    basis = geometry.enu_basis(lat, lon)
    east, north, up = basis
    e, n, _ = basis @ np.asarray(to_sun_mc, dtype=np.float64)
    phi = math.atan2(e, n)
    return np.stack([math.cos(phi) * east - math.sin(phi) * north, math.sin(phi) * east + math.cos(phi) * north, up])


def _surface(dem, lat: float, lon: float, frame: np.ndarray, x: np.ndarray, y: np.ndarray, spacing: float, what: str):
    """Local-frame (``frame``'s rows, origin on the sphere at (lat, lon)) points of the DEM surface below the
    tangent-plane offsets (x, y) m, projected radially (curvature included: the terrain grids' own
    :func:`crater_synth.terrain.grid.sphere_points`)."""
    # The frame's x and y axes in (east, north) components: the same tangent-plane points as ENU offsets.
    x_en, y_en = frame[:2] @ geometry.enu_basis(lat, lon)[:2].T
    dirs, plat, plon = sphere_points(x * x_en[0] + y * y_en[0], x * x_en[1] + y * y_en[1], lat, lon)
    h = dem.sample(plat, plon, spacing_m=spacing, what=what).heights
    return (dirs * (geometry.MOON_RADIUS_M + h)[..., None] - geometry.latlon_to_mc(lat, lon)) @ frame.T


def _normals(xyz: np.ndarray) -> np.ndarray:
    along_x = np.gradient(xyz, axis=1)
    along_y = -np.gradient(xyz, axis=0)  # rows run towards -y
    nrm = np.cross(along_x, along_y)
    return nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)


@dataclasses.dataclass(frozen=True)
class WindowTerrain:
    """A landmark's predicted window before shading: what depends on the Sun's azimuth but not on its
    elevation (:func:`window_terrain`), so several elevations share one DEM read."""

    origin_mc: np.ndarray  # the window's origin on the sphere below the landmark
    frame: np.ndarray  # rows: the Sun frame's unit vectors (MC), :func:`_sun_frame`
    near: np.ndarray  # (n, n, 3) window surface points in the Sun frame
    slope: np.ndarray  # (n, n) horizon slope towards the Sun


def window_terrain(dem, landmark, to_sun_mc, params: RefineParams = RefineParams()) -> WindowTerrain:
    """The DEM surface of ``landmark``'s window and its horizon towards the Sun's azimuth.

    Computed in the landmark's Sun frame (:func:`_sun_frame`): the window is the square of half-width
    ``window_diameters`` x D there, and the far field only the strip of the window's width (and two far
    cells) running ``far_radius_km`` towards the Sun: the occluders of the window's shadows."""
    lat, lon = float(landmark.lat), float(landmark.lon)
    half = params.window_diameters * landmark.diameter_km * 1000.0
    n = int(params.samples)
    frame = _sun_frame(lat, lon, to_sun_mc)
    x, y = texel_centres(half, n)
    near = _surface(dem, lat, lon, frame, x, y, 2.0 * half / n, f"landmark {landmark.id} window")
    fs = params.far_spacing_m
    side = math.ceil(half / fs) + 2
    fx, fy = np.meshgrid(
        np.arange(-side, side + 1) * fs, np.arange(-side, math.ceil(params.far_radius_km * 1000.0 / fs) + 1) * fs
    )
    far = _surface(dem, lat, lon, frame, fx, fy, fs, f"landmark {landmark.id} far field")
    slope = horizon_maps(Terrain(near, far), 0.0, [half], n)[0, 0]
    return WindowTerrain(geometry.latlon_to_mc(lat, lon), frame, near, slope)


def shade_window(terrain: WindowTerrain, to_sun_mc, camera_mc, hapke):
    """(MC points (n, n, 3), predicted I/F (n, n)) of a :func:`window_terrain` seen from ``camera_mc``
    under the Sun ``to_sun_mc`` (at the azimuth the terrain was computed for): Hapke shading times the
    visible fraction of the solar disc."""
    frame, near = terrain.frame, terrain.near
    to_sun = frame @ np.asarray(to_sun_mc, dtype=np.float64)
    elevation = math.asin(max(-1.0, min(1.0, float(to_sun[2]))))
    lit = disc_fraction_above(elevation, np.arctan(terrain.slope))
    cam = (np.asarray(camera_mc, dtype=np.float64) - terrain.origin_mc) @ frame.T
    view = cam - near
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    nrm = _normals(near)
    shade = np.where(nrm @ to_sun > 0.0, shade_np(nrm, to_sun, view, hapke), 0.0)
    return near @ frame + terrain.origin_mc, np.nan_to_num(shade * lit, nan=0.0)


def predict_window(dem, landmark, to_sun_mc, camera_mc, hapke, params: RefineParams = RefineParams()):
    """(MC points (n, n, 3), predicted I/F (n, n)) of ``landmark``'s window seen from ``camera_mc``
    (:func:`window_terrain`, then :func:`shade_window`)."""
    return shade_window(window_terrain(dem, landmark, to_sun_mc, params), to_sun_mc, camera_mc, hapke)


def ncc_at_offsets(image: np.ndarray, u, v, predicted, offsets: np.ndarray) -> np.ndarray:
    """NCC of ``predicted`` with ``image`` read (bilinear) at array coordinates (u, v) + each whole-pixel
    offset (du, dv). The offsets are whole pixels, so every shifted sample has the same bilinear weights:
    they are computed once and the four neighbours gathered per offset (indices clamped to the frame)."""
    h, w = image.shape
    iu, iv = np.floor(u).astype(np.intp), np.floor(v).astype(np.intp)
    fu, fv = u - iu, v - iv
    whole = np.rint(offsets).astype(np.intp)
    du, dv = whole[:, 0], whole[:, 1]
    flat = np.ascontiguousarray(image, dtype=np.float64).ravel()
    inside = (
        iu.min() + du.min() >= 0
        and iu.max() + du.max() <= w - 2
        and iv.min() + dv.min() >= 0
        and iv.max() + dv.max() <= h - 2
    )
    rows, row_of = np.unique(np.concatenate([dv, dv + 1]), return_inverse=True)
    if inside and rows.size < 2 * np.unique(dv).size:
        # A one-pixel grid: neighbouring offsets share image rows, so each (row, column) offset is
        # interpolated along the row once and the offsets combine those rows (the same arithmetic, in
        # the same order, as below: the same values to the bit, ~40 % fewer reads).
        cols, col_of = np.unique(du, return_inverse=True)
        base = (iv * w + iu)[None, None, :] + (rows[:, None] * w + cols[None, :])[..., None]
        along = flat[base] * (1.0 - fu) + flat[base + 1] * fu
        top, bottom = row_of[: du.size], row_of[du.size :]
        vals = along[top, col_of] * (1.0 - fv) + along[bottom, col_of] * fv
    else:
        if inside:
            base = (iv * w + iu)[None, :] + (dv * w + du)[:, None]  # every read inside: no clamping
        else:
            c = np.clip(iu[None, :] + whole[:, :1], 0, w - 2)
            r = np.clip(iv[None, :] + whole[:, 1:], 0, h - 2)
            base = r * w + c
        vals = (flat[base] * (1.0 - fu) + flat[base + 1] * fu) * (1.0 - fv) + (
            flat[base + w] * (1.0 - fu) + flat[base + w + 1] * fu
        ) * fv
    a = predicted - predicted.mean()
    b = vals - vals.mean(axis=1, keepdims=True)
    return (b @ a) / (np.linalg.norm(b, axis=1) * np.linalg.norm(a) + 1e-30)


def parabola_vertex(left: float, centre: float, right: float) -> float:
    """Offset (in [-0.5, 0.5] steps) of the peak of the parabola through three equally spaced samples whose
    middle one is the largest; 0 where they do not curve down."""
    den = left - 2.0 * centre + right
    return 0.0 if den >= 0 else float(np.clip(0.5 * (left - right) / den, -0.5, 0.5))


def square_offsets(centre, half: int, step: int) -> np.ndarray:
    """(du, dv) offsets of a (2 half + 1)^2 grid of spacing ``step`` around ``centre``, row by row (dv outer)."""
    s = np.arange(-half, half + 1) * step
    dv, du = np.meshgrid(s, s, indexing="ij")
    return np.column_stack([du.ravel(), dv.ravel()]) + np.asarray(centre)


def samples_in_reach(shape: tuple, uv: np.ndarray, predicted: np.ndarray, search_px: int):
    """(u, v, values) of the predicted samples (pixels ``uv``, convention of :func:`register`; array
    coordinates u - 0.5) that stay in a frame of ``shape`` under every shift within ``search_px`` (the
    same samples for every shift, so their NCCs compare); None when fewer than 16 do or they are flat."""
    h, w = shape
    u = uv[..., 0].ravel() - 0.5
    v = uv[..., 1].ravel() - 0.5
    reach = search_px + 2
    ok = (u >= reach) & (u <= w - 1 - reach) & (v >= reach) & (v <= h - 1 - reach)  # False for NaN
    p = np.asarray(predicted, dtype=np.float64).ravel()[ok]
    if ok.sum() < 16 or np.ptp(p) <= 0:
        return None
    return u[ok], v[ok], p


def register(image: np.ndarray, uv: np.ndarray, predicted: np.ndarray, search_px: int):
    """(shift (du, dv) px, NCC) that best aligns ``predicted`` (values at pixels ``uv``, (..., 2), the
    continuous convention of :func:`.fix.project_pinhole`: pixel i spans [i, i + 1]) with ``image``.

    Whole-pixel shifts within ``search_px`` are searched (every second pixel first when the search is
    wider than 3 px, then every pixel around the best: the predicted windows hold DEM-scale relief, several
    pixels wide, so the correlation peak is too), and the peak is refined by a parabola through its
    neighbours. The shift is None when the peak lies on the search border, or when fewer than 16 samples
    stay in the frame under every shift (:func:`samples_in_reach`)."""
    inside = samples_in_reach(image.shape, uv, predicted, search_px)
    if inside is None:
        return None, float("nan")
    u, v, p = inside
    img = np.asarray(image, dtype=np.float64)
    centre = np.zeros(2)
    if search_px > 3:
        half = search_px // 2
        coarse = ncc_at_offsets(img, u, v, p, square_offsets(centre, half, 2)).reshape(2 * half + 1, -1)
        i, j = np.unravel_index(int(np.argmax(coarse)), coarse.shape)
        if i in (0, 2 * half) or j in (0, 2 * half):
            return None, float(coarse[i, j])
        centre, search_px = np.array([2 * (j - half), 2 * (i - half)], dtype=float), 2
    surf = ncc_at_offsets(img, u, v, p, square_offsets(centre, search_px, 1)).reshape(2 * search_px + 1, -1)
    i, j = np.unravel_index(int(np.argmax(surf)), surf.shape)
    if i in (0, 2 * search_px) or j in (0, 2 * search_px):
        return None, float(surf[i, j])
    ddu = parabola_vertex(surf[i, j - 1], surf[i, j], surf[i, j + 1])
    ddv = parabola_vertex(surf[i - 1, j], surf[i, j], surf[i + 1, j])
    return centre + np.array([j - search_px + ddu, i - search_px + ddv]), float(surf[i, j])


def rim_ellipses(points, radii_m, c, r_wc, fov_deg: float, width: int) -> list:
    """Image ellipses of rims of ``radii_m`` around the rim-centre ``points`` (n, 3; ENU of an origin on the
    reference sphere, the rims in their local horizontal planes) seen by a camera at ``c`` with
    world->camera rotation ``r_wc`` (the convention of :func:`.fix.project_pinhole`)."""
    points = np.asarray(points, dtype=np.float64)
    normals = points + np.array([0.0, 0.0, geometry.MOON_RADIUS_M])  # local up: from the Moon's centre
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    pose = geometry.CameraPose(position=c, rotation=np.stack([r_wc[0], -r_wc[1], -r_wc[2]], 1), fov_deg=fov_deg)
    if not len(points):
        return []
    arrays = geometry.project_circles(points, normals, np.asarray(radii_m, dtype=np.float64), pose, width)
    return [geometry.Ellipse(*(float(v) for v in e)) for e in zip(*arrays)]


def ellipse_centre_fix(points, uv, radii_m, c_fix, r_wc, k, fov_deg: float, width: int, iterations: int = 2):
    """(camera centre, corrected observations): a detection measures the rim ellipse's centre, which
    perspective moves off the image of the rim's centre point; each observation ``uv`` (n, 2) of a rim
    centre ``points`` (n, 3, frame ENU; rims of ``radii_m`` on the sphere's tangent plane) is corrected by
    that offset at the current fix ``c_fix`` and the known-attitude position solved again, ``iterations``
    times."""
    points, uv = np.asarray(points, dtype=np.float64), np.asarray(uv, dtype=np.float64)
    c, corrected = np.asarray(c_fix, dtype=np.float64), uv
    for _ in range(iterations):
        centres = np.array([[e.cu, e.cv] for e in rim_ellipses(points, radii_m, c, r_wc, fov_deg, width)])
        corrected = uv - (centres - project_pinhole(points, r_wc, c, k))
        c = solve_position(points, corrected, k, r_wc)
    return c, corrected


_POOL_REFINER = None  # a terrain worker's refiner (set by _pool_init in each worker process)


def _pool_init(dem, params) -> None:
    global _POOL_REFINER
    _POOL_REFINER = Refiner(dem, params)


def _pool_terrain(landmark, to_sun_mc):
    """A terrain worker's :func:`window_terrain`, or the :class:`DemError` it raised (returned, so the
    caller keeps it like its own)."""
    try:
        return window_terrain(_POOL_REFINER.dem, landmark, to_sun_mc, _POOL_REFINER.params)
    except DemError as exc:
        return exc


class Refiner:
    """The appearance refinement with a lander's DEM (:func:`lander_dem`) and the project's Hapke model.

    ``workers`` > 1: :meth:`prepare` computes the landmark terrains a frame needs in that many worker
    processes while the caller correlates the ones already done (the cold start of a frame whose landmarks
    are all new); the terrains are the same to the bit (the same function on the same inputs)."""

    # Landmark terrains kept (about 130 kB each): a trajectory's frames share one Sun, so each landmark's
    # DEM window and horizon are computed once for all the frames that see it.
    TERRAIN_CACHE_SIZE = 1024

    def __init__(self, dem, params: RefineParams = RefineParams(), workers: int = 1):
        if int(workers) < 1:
            raise ValueError(f"workers={workers} must be >= 1")
        self.dem, self.params, self.hapke = dem, params, hapke_params()
        self.workers = int(workers)
        self._terrains: OrderedDict = OrderedDict()
        self._pending: dict = {}  # key -> Future of a terrain being computed by a worker
        self._pool = None

    @staticmethod
    def _key(landmark, to_sun_mc) -> tuple:
        return (landmark.id, tuple(np.asarray(to_sun_mc, dtype=np.float64).tolist()))

    def prepare(self, jobs) -> None:
        """Start computing the terrains of ``jobs`` ((landmark, to_sun_mc) pairs) that are neither kept nor
        under way, in the worker processes; :meth:`terrain` then waits for each. Nothing with one worker
        (the terrains are computed when asked for)."""
        if self.workers < 2:
            return
        keyed = ((self._key(lm, sun), lm, sun) for lm, sun in jobs)
        missing = [(key, lm, sun) for key, lm, sun in keyed if key not in self._terrains and key not in self._pending]
        if len(missing) < 2:
            return
        if self._pool is None:
            # fork: the workers inherit the opened DEM stack (each reopens its raster handles).
            ctx = multiprocessing.get_context("fork")
            self._pool = ProcessPoolExecutor(
                self.workers, mp_context=ctx, initializer=_pool_init, initargs=(self.dem, self.params)
            )
        for key, lm, sun in missing:
            self._pending[key] = self._pool.submit(_pool_terrain, lm, sun)

    def close(self) -> None:
        """Stop the terrain workers (a refiner with workers starts them again when needed)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool, self._pending = None, {}

    def terrain(self, landmark, to_sun_mc) -> WindowTerrain:
        """:func:`window_terrain` of ``landmark`` with this refiner's DEM and settings, kept per landmark
        and Sun vector (least recently used dropped first); a window that leaves the DEM raises its
        :class:`~crater_synth.terrain.dem.DemError` again without reading it again."""
        key = self._key(landmark, to_sun_mc)
        if key in self._terrains:
            self._terrains.move_to_end(key)
        else:
            pending = self._pending.pop(key, None)
            if pending is not None:
                self._terrains[key] = pending.result()
            else:
                try:
                    self._terrains[key] = window_terrain(self.dem, landmark, to_sun_mc, self.params)
                except DemError as exc:
                    self._terrains[key] = exc
            if len(self._terrains) > self.TERRAIN_CACHE_SIZE:
                self._terrains.popitem(last=False)
        got = self._terrains[key]
        if isinstance(got, DemError):
            raise got
        return got

    def clear_terrains(self) -> None:
        """Forget the kept terrains (the benchmark's cold runs)."""
        for fut in self._pending.values():
            fut.cancel()
        self._pending.clear()
        self._terrains.clear()

    def predict(self, landmark, to_sun_mc, camera_mc):
        """:func:`predict_window` with this refiner's DEM, Hapke model and settings (:meth:`terrain`)."""
        return shade_window(self.terrain(landmark, to_sun_mc), to_sun_mc, camera_mc, self.hapke)

    def refine(
        self,
        image,
        landmarks,
        observed_uv,
        points_enu,
        c_fix,
        r_wc,
        k,
        origin,
        to_sun_mc,
        predicted=None,
        pose=False,
        attitude_prior=None,
    ):
        """Camera centre (frame ENU) after registering each identified landmark's predicted window.

        ``landmarks``: the fix's landmarks; ``observed_uv`` (n, 2): their observations as the plain fix
        used them; ``points_enu`` (n, 3): their rim-centre points in the ENU frame of ``origin`` (lat,
        lon); ``c_fix``, ``r_wc``, ``k``: the plain fix's camera. Returns (centre, {"seconds": wall time,
        "landmarks": per-landmark records: NCC, shift, whether the registration replaced the observation,
        or why it was not tried; "observed_px": the observations the centre was solved from}). The
        windows are predicted once, from the plain fix (a pixel or two of camera motion changes the view
        angle by microradians), and registered again after each solve; ``predicted`` (landmark id -> (MC
        points, I/F)) are predictions already made for this frame (:mod:`.appearance`), used as they are.
        ``pose``: the 6-DOF fix's refinement: each solve is of the attitude too (:func:`.fix.refine_pose`, from
        at least three registered landmarks), and the record adds the final world->camera ``rotation``;
        ``attitude_prior`` (the attitude the lander believes, its 1-sigma in radians): each 6-DOF solve is
        then weighted towards it (:func:`.fix.refine_pose`), against the observations' own scatter (the
        residuals of the solve without it, no less than ``PNP_MIN_SIGMA_PX``)."""
        t0 = time.perf_counter()
        p = self.params
        c = np.asarray(c_fix, dtype=np.float64)
        windows = self._predicted_windows(landmarks, predicted, to_sun_mc, geometry.enu_to_mc(c, *origin), origin)
        obs = np.asarray(observed_uv, dtype=np.float64)
        solved_from = obs  # the observations the returned centre was solved from
        records: list[dict] = []
        for it in range(p.iterations):
            search = p.search_px if it == 0 else FOLLOW_UP_SEARCH_PX
            moved, records = self._registered_observations(image, windows, obs, points_enu, c, r_wc, k, search)
            if sum(r["used"] for r in records) < (3 if pose else 2):  # one landmark alone cannot move a position
                break
            if pose:
                r_wc, c = self._solve_pose(points_enu, moved, k, r_wc, c, attitude_prior)
            else:
                c = solve_position(points_enu, moved, k, r_wc)
            solved_from = moved
        record = {
            "seconds": round(time.perf_counter() - t0, 3),
            "landmarks": records,
            "observed_px": np.round(solved_from, 4).tolist(),  # the last solve's observations: its residuals
        }
        if pose:
            record["rotation"] = np.asarray(r_wc, dtype=np.float64).tolist()
        return c, record

    def _predicted_windows(self, landmarks, predicted, to_sun_mc, cam_mc, origin) -> list:
        """Per landmark, its predicted window (ENU points of ``origin``, I/F), or why there is none (a
        window or its far field leaving the DEM: the detection is kept as it is)."""
        lat0, lon0 = origin
        windows = []
        for lm in landmarks:
            try:
                pts_mc, pred = (predicted or {}).get(lm.id) or self.predict(lm, to_sun_mc, cam_mc)
                windows.append((geometry.mc_to_enu(pts_mc.reshape(-1, 3), lat0, lon0), pred.ravel()))
            except DemError as exc:  # the window or its far field leaves the DEM: keep the detection
                windows.append(str(exc))
        return windows

    def _registered_observations(self, image, windows, obs, points_enu, c, r_wc, k, search: int):
        """Register each predicted window in ``image`` around where the camera (``c``, ``r_wc``, ``k``)
        projects it: (observations, each moved where its registration is good enough; per-landmark
        records)."""
        moved, records = obs.copy(), []
        for q, win in enumerate(windows):
            if isinstance(win, str):
                records.append({"used": False, "reason": win})
                continue
            pts, pred = win
            uv = np.full((len(pts), 2), np.nan)
            front = (pts - c) @ r_wc[2] > 0
            uv[front] = project_pinhole(pts[front], r_wc, c, k)
            shift, ncc = register(image, uv, pred, search)
            used = shift is not None and ncc >= self.params.min_ncc
            if used:
                moved[q] = project_pinhole(points_enu[q : q + 1], r_wc, c, k)[0] + shift
            records.append(
                {
                    "used": bool(used),
                    "ncc": round(ncc, 4),
                    "shift_px": None if shift is None else np.round(shift, 3).tolist(),
                }
            )
        return moved, records

    @staticmethod
    def _solve_pose(points_enu, moved, k, r_wc, c, attitude_prior):
        """The 6-DOF solve from the registered observations; with ``attitude_prior`` weighted towards it
        against the observations' own scatter (no less than ``PNP_MIN_SIGMA_PX``)."""
        r_wc, c = refine_pose(points_enu, moved, k, r_wc, c)
        if attitude_prior is not None:
            r_wc, c = pose_with_attitude(points_enu, moved, k, r_wc, c, *attitude_prior)
        return r_wc, c

    def verified(self, refinement: dict) -> tuple[bool, str]:
        """(fix stands, reason if not) after :meth:`refine`: a fix whose landmarks do not appear where it
        predicts them is no fix. Two registered landmarks are what the refinement needs to move a
        position; with fewer, the frame's appearance contradicts the fix, which the detector's circles
        alone could not tell (a wrong set of three can agree in pixel positions)."""
        used = sum(r["used"] for r in refinement["landmarks"])
        if self.params.verify and used < 2:
            n = len(refinement["landmarks"])
            return False, f"appearance check: {used} of {n} landmarks appear where the fix predicts them (need 2)"
        return True, ""


def lander_dem(pole: str):
    """The DEM a lander carries for ``pole``: the landmark map's DEM (``dem=lola_ldem256_<pole>``) with the
    finer layers its configuration stacks on it."""
    return open_dem_stack(load_settings([f"dem=lola_ldem256_{pole}"]))
