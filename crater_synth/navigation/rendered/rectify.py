"""Detection on an oblique rendered frame through its ground plane: the frame is resampled onto the plane
under its boresight, seen from straight above, the detector runs there, and each crater found there is
projected back into the frame as the exact image of its rim circle.

Why: a crater seen 30-45 degrees off nadir is an ellipse foreshortened by cos(angle) along the view, and
a detector trained mostly on round rims misses many of them (docs/navigation/detectors.md, "oblique
views"). A lander knows its attitude (star tracker, IMU) well enough to undo the foreshortening of the
ground plane; relief and curvature across the footprint are not undone.

- **Plane**: through the point where the boresight meets the ground (the view's target, ``range_m`` along
  the boresight), level with the Moon there (normal along the radius of the sphere the frame's ENU is
  set on), axes :func:`crater_core.geometry.plane_basis` (east and north for a level plane).
- **Grid**: the plane's pixels are the frame's ground sample at its centre across the view (range /
  focal length), cover the footprint of the frame's four corners, and hold at most ``MAX_AREA_RATIO``
  times the frame's pixels (coarser where the footprint is longer).
- **Resampling**: OpenCV's ``warpPerspective`` (bilinear) through the plane-to-frame homography
  (:func:`crater_core.geometry._plane_to_image_homography`); the plane outside the footprint is filled with
  the frame's median and a crater whose centre lies nearer to that fill than the border rule allows
  (``border_r`` x its radius) is dropped, as at the frame's own edges.
- **Back**: a circle found on the plane is the rim circle (centre on the plane, radius in metres); its
  image is :func:`crater_core.geometry.project_circles`, and the detection is that ellipse's centre and
  semi-major axis (what the labels' ``a`` is), kept when its centre lies in the frame.

A frame less than ``MIN_OFF_NADIR_DEG`` off nadir is detected as it is.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from crater_core import geometry
from crater_core.geometry import CameraPose
from crater_synth.navigation.detectors.classical import Detection, detect
from crater_synth.navigation.rendered.training_rows import off_nadir_deg

MAX_AREA_RATIO = 4.0  # the plane image holds at most this many times the frame's pixels
# A frame nearer nadir than this is detected as it is. Chosen on the validation fields of the highland set
# (docs/history.md): the plane gains F1 at 30-45 degrees (+0.046, recall +0.11) and ties or loses below,
# where the resampling costs more precision than the foreshortening does recall.
MIN_OFF_NADIR_DEG = 30.0


def frame_pose(row: dict) -> CameraPose:
    """The rendered frame's camera (``camera_enu`` of its row)."""
    cam = row["camera_enu"]
    return CameraPose(
        position=np.asarray(cam["position_m"], np.float64),
        rotation=np.asarray(cam["rotation"], np.float64),
        fov_deg=float(cam["fov_deg"]),
    )


def ground_plane(row: dict, pose: CameraPose) -> tuple[np.ndarray, np.ndarray]:
    """(point, unit normal) in ENU of the plane under the boresight: the view's target, level with the
    sphere of the frame's ENU (its centre at (0, 0, -R))."""
    point = pose.position + float(row["view"]["range_m"]) * pose.forward
    normal = point - np.array([0.0, 0.0, -geometry.MOON_RADIUS_M])
    return point, normal / np.linalg.norm(normal)


def _shift(d: float) -> np.ndarray:
    return np.array([[1.0, 0.0, d], [0.0, 1.0, d], [0.0, 0.0, 1.0]])


def rectification(row: dict, shape: tuple[int, int]) -> dict:
    """The plane and its grid for a frame of ``shape``: ``to_plane`` (3 x 3: plane-image pixel, corner
    origin, to plane metres along :func:`crater_core.geometry.plane_basis`), ``to_frame`` (plane metres to
    frame pixels, corner origin), ``size`` (w, h) of the plane image, its ``gsd_m``, the plane's ``point``
    and ``normal``, the frame's ``pose`` and ``width_px``."""
    h, w = shape
    pose = frame_pose(row)
    width_px = int(row["camera_enu"].get("width_px") or w)
    point, normal = ground_plane(row, pose)
    # The plane's axes turned to the frame's own: x along the camera's right, y its up, both laid on the
    # plane, so that a nadir frame's plane image is the frame itself and an oblique one's footprint is a
    # trapezoid square to the grid (little fill). ``turn`` takes these axes' coordinates to plane_basis's.
    e1, e2 = geometry.plane_basis(normal)
    right = pose.rotation[:, 0] - np.dot(pose.rotation[:, 0], normal) * normal
    c, s = float(np.dot(right, e1)), float(np.dot(right, e2))
    c, s = c / math.hypot(c, s), s / math.hypot(c, s)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    to_frame = geometry._plane_to_image_homography(point, pose, width_px, normal)
    corners = np.array([[0.0, 0.0, 1.0], [w, 0.0, 1.0], [w, h, 1.0], [0.0, h, 1.0]])
    xy = corners @ np.linalg.inv(to_frame @ turn).T
    xy = xy[:, :2] / xy[:, 2:]
    gsd = float(row["view"]["range_m"]) / pose.focal_px(width_px)
    span = xy.max(0) - xy.min(0)
    gsd *= max(1.0, math.sqrt(span[0] * span[1] / (gsd * gsd * MAX_AREA_RATIO * w * h)))
    size = (int(math.ceil(span[0] / gsd)), int(math.ceil(span[1] / gsd)))
    # plane-image column j, row i (corner origin) -> turned plane axes (x0 + j g, y1 - i g): the frame's up
    to_plane = np.array([[gsd, 0.0, xy[:, 0].min()], [0.0, -gsd, xy[:, 1].max()], [0.0, 0.0, 1.0]])
    return {
        "to_plane": turn @ to_plane,  # to plane_basis coordinates, as project_circles reads them
        "to_frame": to_frame,
        "size": size,
        "gsd_m": gsd,
        "point": point,
        "normal": normal,
        "pose": pose,
        "width_px": width_px,
    }


def rectified_detect(image: np.ndarray, row: dict, params, what: str = "frame") -> list[Detection]:
    """The detector's craters in a rendered frame, found on its ground plane (module docstring) and given
    in frame pixels; a nadir frame's as :func:`detect` finds them."""
    if off_nadir_deg(row) < MIN_OFF_NADIR_DEG:
        return detect(image, params, light_dir=0.0, what=what)[0]
    rect = rectification(row, image.shape)
    size = rect["size"]
    # OpenCV's pixel coordinates are pixel centres; the project's have their origin at the corner.
    plane_to_frame_cv = _shift(-0.5) @ rect["to_frame"] @ rect["to_plane"] @ _shift(0.5)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    src = np.asarray(image, np.float32)
    fill = float(np.median(src))
    plane = cv2.warpPerspective(src, plane_to_frame_cv, size, flags=flags, borderValue=fill)
    nearest = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    valid = cv2.warpPerspective(np.ones_like(src, np.uint8), plane_to_frame_cv, size, flags=nearest, borderValue=0)
    found = detect(plane, params, light_dir=0.0, what=what)[0]
    if not found:
        return []
    u = np.array([d.u for d in found])
    v = np.array([d.v for d in found])
    r = np.array([d.r for d in found])
    # distance of each plane pixel to the fill outside the footprint
    reach = cv2.distanceTransform(valid, cv2.DIST_L2, 3)
    iu = np.clip(u.astype(int), 0, size[0] - 1)
    iv = np.clip(v.astype(int), 0, size[1] - 1)
    keep = reach[iv, iu] >= params.border_r * r
    xy = np.stack([u, v, np.ones_like(u)], 1) @ rect["to_plane"].T
    e1, e2 = geometry.plane_basis(rect["normal"])
    centres = rect["point"] + xy[:, :1] * e1 + xy[:, 1:2] * e2
    normals = np.broadcast_to(rect["normal"], centres.shape)
    cu, cv_, a, _, _ = geometry.project_circles(centres, normals, r * rect["gsd_m"], rect["pose"], rect["width_px"])
    h, w = image.shape
    keep &= (cu >= 0) & (cu < w) & (cv_ >= 0) & (cv_ < h)
    return [Detection(float(cu[k]), float(cv_[k]), float(a[k]), found[k].score) for k in np.nonzero(keep)[0]]
