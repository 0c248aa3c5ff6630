"""A perspective frame resampled onto the ground, so that a crater detector sees every crater as it would
from overhead (``nav.frames.ground_view``; docs/navigation/rendered.md, "Oblique frames").

An oblique frame foreshortens each rim into an ellipse, and its ground sample grows from the near edge to
the far one: at 38 degrees off nadir with a 30 degree field, the far edge's is about twice the boresight's.
A detector trained on nadir views then meets craters squashed across the tilt and, in the far field, at
radii below the smallest it searches for a landmark's size. With the attitude and the altimeter's range
known (what lost in space on rendered frames assumes, :mod:`.lost_in_space`), each point of the ground has
a known pixel: the frame is resampled onto a regular grid of the ground (azimuthal-equidistant about the
point under the camera, the coordinates :func:`ground_axes` define), at one ground sample everywhere, and
searched there like a mosaic window. The detections are then carried back into the frame's pixels, so
everything downstream (the rectification of detections, the pair vote, the 6-DOF fix, the scoring against
the frame's labels) is unchanged.

The ground is the sphere of the Moon's radius through the boresight's ground point, as for the detections
(:func:`.lost_in_space.rectify`): terrain relief displaces points by its height times the tangent of the
emission angle, a few pixels at most at the landmarks' scale.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

from crater_core.geometry import MOON_RADIUS_M
from crater_synth.errors import UserError
from crater_synth.navigation.detectors.classical import Detection, detect
from crater_synth.navigation.rendered.evaluate import cv_camera
from crater_synth.navigation.rendered.sunlight import row_to_sun

# The ground view's side is capped (pixels): a frame whose footprint reaches towards the horizon is sampled
# more coarsely rather than into an image of tens of megapixels.
MAX_SIDE_PX = 2048
# Frame border points cut with the ground to bound the footprint, per side.
BORDER_POINTS = 64


class GroundView(NamedTuple):
    """The frame resampled onto the ground: ``image`` (float32, the frame's values; outside the footprint the
    median of those inside), ``valid`` (inside the footprint), ``pixel_m`` (its ground sample) and
    ``origin_m`` (east, north) of its top-left corner about the point under the camera."""

    image: np.ndarray
    valid: np.ndarray
    pixel_m: float
    origin_m: tuple[float, float]


def camera_from_centre(row: dict, range_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(world -> camera rotation, K, the camera's position from the Moon's centre) of the frame ``row``, its
    boresight's ground point ``range_m`` ahead on the sphere of the Moon's radius (the frame's origin)."""
    rot = np.array(row["camera_enu"]["rotation"], dtype=np.float64)
    optics = row["pose"] if "pose" in row else row["camera_enu"]  # a navigation frame's row, or a detection frame's
    r_wc, k = cv_camera(rot, int(optics["width_px"]), float(optics["fov_deg"]))
    return r_wc, k, -range_m * r_wc[2] + np.array([0.0, 0.0, MOON_RADIUS_M])


def ground_axes(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(up, east, north) unit vectors at the point under the camera at ``q`` (from the Moon's centre, in the
    frame's axes): the azimuthal-equidistant ground coordinates' axes."""
    up = q / np.linalg.norm(q)
    east = np.array([1.0, 0.0, 0.0]) - up[0] * up
    east /= np.linalg.norm(east)
    return up, east, np.cross(up, east)


def rays_to_ground(rays: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ground points, distance along each ray, hit) of world-direction ``rays`` from ``q`` cut with the
    sphere of the Moon's radius (the nearer cut; a ray that misses it has hit False)."""
    half_b = rays @ q
    a = np.sum(rays**2, axis=1)
    disc = half_b**2 - a * (q @ q - MOON_RADIUS_M**2)
    t = (-half_b - np.sqrt(np.where(disc >= 0.0, disc, np.nan))) / a
    hit = np.isfinite(t) & (t > 0.0)
    return q + np.where(hit, t, 0.0)[:, None] * rays, t, hit


def ground_coords(points: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(east, north) in metres along the sphere about the point under the camera at ``q``, of ``points``."""
    up, east, north = ground_axes(q)
    e, n = points @ east, points @ north
    along = MOON_RADIUS_M * np.arctan2(np.hypot(e, n), points @ up) / np.maximum(np.hypot(e, n), 1e-9)
    return along * e, along * n


def sphere_points(east_m: np.ndarray, north_m: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The points of the sphere at azimuthal-equidistant ``east_m``, ``north_m`` about the point under ``q``
    (the inverse of :func:`ground_coords`)."""
    up, east, north = ground_axes(q)
    dist = np.hypot(east_m, north_m)
    ang = dist / MOON_RADIUS_M
    scale = np.where(dist > 0.0, np.sin(ang) / np.maximum(dist, 1e-9), 1.0 / MOON_RADIUS_M)
    horiz = (east_m * scale)[..., None] * east + (north_m * scale)[..., None] * north
    return MOON_RADIUS_M * (np.cos(ang)[..., None] * up + horiz)


def _project(points: np.ndarray, r_wc: np.ndarray, k: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pixel coordinates (u, v), depth along the optical axis) of ``points`` (Moon-centred, frame axes)."""
    cam = (points - q) @ r_wc.T
    z = cam[..., 2]
    zs = np.where(z > 0.0, z, np.nan)
    return np.stack([k[0, 0] * cam[..., 0] / zs + k[0, 2], k[1, 1] * cam[..., 1] / zs + k[1, 2]], axis=-1), z


def ground_view(image: np.ndarray, row: dict, range_m: float) -> GroundView:
    """The frame ``image`` of ``row`` resampled onto the ground (module docstring) at the ground sample at its
    boresight (``range_m`` / focal length), or coarser where the footprint would exceed :data:`MAX_SIDE_PX`;
    bilinear. A ground point hidden behind the limb or outside the frame is outside the footprint."""
    r_wc, k, q = camera_from_centre(row, range_m)
    h, w = image.shape
    s = np.linspace(0.0, 1.0, BORDER_POINTS)
    border = np.concatenate(
        [np.stack([s * w, np.zeros_like(s)], 1), np.stack([s * w, np.full_like(s, h)], 1),
         np.stack([np.zeros_like(s), s * h], 1), np.stack([np.full_like(s, w), s * h], 1)]
    )  # fmt: skip
    rays = np.linalg.solve(k, np.column_stack([border, np.ones(len(border))]).T).T @ r_wc
    pts, _, hit = rays_to_ground(rays, q)
    if not hit.any():
        raise UserError(f"frame {row.get('rel_path', '?')}: no pixel of it sees the ground")
    east_m, north_m = ground_coords(pts[hit], q)
    pixel_m = range_m / k[0, 0]
    span = max(float(np.ptp(east_m)), float(np.ptp(north_m)))
    pixel_m = max(pixel_m, span / MAX_SIDE_PX)
    e0, n1 = float(east_m.min()), float(north_m.max())
    nx = int(math.ceil((float(east_m.max()) - e0) / pixel_m))
    ny = int(math.ceil((n1 - float(north_m.min())) / pixel_m))
    ge = e0 + (np.arange(nx) + 0.5) * pixel_m
    gn = n1 - (np.arange(ny) + 0.5) * pixel_m
    ground = sphere_points(ge[None, :], gn[:, None], q)
    uv, z = _project(ground, r_wc, k, q)
    facing = np.sum((ground - q) * ground, axis=-1) < 0.0  # not behind the limb
    # OpenCV samples pixel centres at integers; the frame's pixel j spans [j, j + 1) in u.
    mx = (uv[..., 0] - 0.5).astype(np.float32)
    my = (uv[..., 1] - 0.5).astype(np.float32)
    valid = facing & (z > 0.0) & (mx >= 0.0) & (mx <= w - 1) & (my >= 0.0) & (my <= h - 1)
    src = np.asarray(image, dtype=np.float32)
    out = cv2.remap(
        src, np.where(valid, mx, -1.0).astype(np.float32), np.where(valid, my, -1.0).astype(np.float32),
        cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0,
    )  # fmt: skip
    out[~valid] = float(np.median(out[valid] if valid.any() else src))
    return GroundView(out, valid, float(pixel_m), (e0, n1))


def inside_footprint(dets, view: GroundView, margin: float = 1.0) -> list[Detection]:
    """The ground-view detections whose rim lies within the footprint: each centre at least ``margin`` x its
    radius from the nearest pixel outside it (a rim cut by the footprint's edge is as unreliable as one cut by
    a frame's border)."""
    if not dets:
        return []
    dist = cv2.distanceTransform(view.valid.astype(np.uint8), cv2.DIST_L2, 5)
    h, w = dist.shape
    i = np.clip(np.array([d.v for d in dets]).astype(int), 0, h - 1)
    j = np.clip(np.array([d.u for d in dets]).astype(int), 0, w - 1)
    ok = dist[i, j] >= margin * np.array([d.r for d in dets])
    return [d for d, keep in zip(dets, ok) if keep]


def to_frame(dets, view: GroundView, row: dict, range_m: float) -> list[Detection]:
    """Ground-view detections carried back into the frame's pixels: each centre projected, its radius the
    ground radius times the focal length over its depth along the optical axis (a rim's semi-major axis:
    the axis across the tilt is not foreshortened)."""
    if not dets:
        return []
    r_wc, k, q = camera_from_centre(row, range_m)
    u = np.array([d.u for d in dets])
    v = np.array([d.v for d in dets])
    pts = sphere_points(view.origin_m[0] + u * view.pixel_m, view.origin_m[1] - v * view.pixel_m, q)
    uv, z = _project(pts, r_wc, k, q)
    r = np.array([d.r for d in dets]) * view.pixel_m * k[0, 0] / z
    return [
        Detection(float(uv[i, 0]), float(uv[i, 1]), float(r[i]), d.score)
        for i, d in enumerate(dets)
        if z[i] > 0.0 and np.isfinite(uv[i]).all()
    ]


def ground_light(row: dict, range_m: float) -> float:
    """The image azimuth (radians, atan2(dv, du), v down) the light travels along in the frame's
    :func:`ground_view`: the Sun's ground direction under the camera (the view's rows run east, north up)."""
    _, _, q = camera_from_centre(row, range_m)
    _, east, north = ground_axes(q)
    travel = -row_to_sun(row)
    return math.atan2(-(travel @ north), travel @ east)


def detect_on_ground(image: np.ndarray, row: dict, range_m: float, params, what: str = "frame") -> list[Detection]:
    """The detector's craters (``params``, at its own scales) in the frame's :func:`ground_view` under its
    light (:func:`ground_light`), those whose rim lies within the footprint (:func:`inside_footprint`, the
    margin the detector's own border rule keeps at a frame's edge: ``params.border_r``) carried back into
    the frame's pixels (:func:`to_frame`)."""
    view = ground_view(image, row, range_m)
    dets, _ = detect(view.image, params, light_dir=ground_light(row, range_m), what=f"{what} on the ground")
    return to_frame(inside_footprint(dets, view, params.border_r), view, row, range_m)
