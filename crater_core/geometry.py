"""Geometry shared by every stage: the one source of truth for frames, angles and projections.

Pure numpy + standard library, so it runs inside Blender, on the host and in ``train/``.

Conventions (see docs/geometry.md):
- Moon-centred Cartesian ("MC") frame: +z towards the north pole, +x towards (lat 0, lon 0),
  +y towards (lat 0, lon 90 E).
- Local east-north-up ("ENU") frame at a crater centre on the reference sphere: the Blender world
  frame (x = east, y = north, z = up, metres). "North" is geographic north everywhere: at a
  south-polar crater it points away from the pole, at a north-polar crater towards it.
- Azimuths are measured clockwise from local north (towards east), elevations above the local
  horizontal plane, both in degrees at the API boundary.
- Camera: Blender convention (looks along its local -Z, image up is local +Y). Pixel coordinates are
  (u right, v down) with the origin at the top-left corner of the full frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# IAU/LOLA lunar reference sphere radius (docs/specification.md; Archinal et al. 2018, IAU WGCCRE report).
MOON_RADIUS_M = 1_737_400.0
# Mean angular diameter of the Sun seen from the Moon (~1 AU): 2*atan(695,700 km / 149.6e6 km).
SUN_ANGULAR_DIAMETER_DEG = 0.533


# --------------------------------------------------------------------------------------------
# Sphere, polar stereographic projection, local frames
# --------------------------------------------------------------------------------------------
def latlon_to_mc(lat_deg, lon_deg, height_m=0.0, radius_m: float = MOON_RADIUS_M) -> np.ndarray:
    """Moon-centred Cartesian position (..., 3) of points at (lat, lon, height above the sphere)."""
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    r = radius_m + np.asarray(height_m, dtype=np.float64)
    cl = np.cos(lat)
    return np.stack(np.broadcast_arrays(r * cl * np.cos(lon), r * cl * np.sin(lon), r * np.sin(lat)), axis=-1)


def mc_to_latlon(points: np.ndarray, radius_m: float = MOON_RADIUS_M):
    """Inverse of :func:`latlon_to_mc`: returns (lat_deg, lon_deg, height_m)."""
    p = np.asarray(points, dtype=np.float64)
    r = np.linalg.norm(p, axis=-1)
    lat = np.degrees(np.arcsin(np.clip(p[..., 2] / r, -1.0, 1.0)))
    lon = np.degrees(np.arctan2(p[..., 1], p[..., 0]))
    return lat, lon, r - radius_m


def enu_basis(lat_deg: float, lon_deg: float) -> np.ndarray:
    """3x3 matrix whose rows are the unit east, north and up vectors (in MC) at (lat, lon)."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    east = np.array([-math.sin(lon), math.cos(lon), 0.0])
    north = np.array([-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)])
    up = np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])
    return np.stack([east, north, up])


def mc_to_enu(points: np.ndarray, lat0_deg: float, lon0_deg: float, radius_m: float = MOON_RADIUS_M) -> np.ndarray:
    """Express MC points in the ENU frame whose origin is (lat0, lon0) on the reference sphere."""
    origin = latlon_to_mc(lat0_deg, lon0_deg, 0.0, radius_m)
    return (np.asarray(points, dtype=np.float64) - origin) @ enu_basis(lat0_deg, lon0_deg).T


def enu_to_mc(points_enu: np.ndarray, lat0_deg: float, lon0_deg: float, radius_m: float = MOON_RADIUS_M) -> np.ndarray:
    """Inverse of :func:`mc_to_enu`."""
    origin = latlon_to_mc(lat0_deg, lon0_deg, 0.0, radius_m)
    return np.asarray(points_enu, dtype=np.float64) @ enu_basis(lat0_deg, lon0_deg) + origin


def curvature_drop_m(distance_m, radius_m: float = MOON_RADIUS_M):
    """Exact drop of the sphere below the tangent plane at horizontal distance d: R - sqrt(R^2 - d^2).

    For d << R this is d^2 / 2R (2.9 km at 100 km on the Moon).
    """
    d = np.asarray(distance_m, dtype=np.float64)
    return radius_m - np.sqrt(radius_m**2 - d**2)


POLES = ("south", "north")


def hemisphere(lat_deg: float) -> str:
    """``"north"`` for a latitude above the equator, else ``"south"`` (the pole a crater belongs to)."""
    return "north" if float(lat_deg) > 0.0 else "south"


def noon_azimuth_deg(lat_deg: float) -> float:
    """Local azimuth (clockwise from local north) towards the equator, where the Sun stands highest:
    0 (local north) in the southern hemisphere, 180 (local south) in the northern, where local north
    points at the pole (crater_core.illumination)."""
    return 180.0 if hemisphere(lat_deg) == "north" else 0.0


def _pole_sign(pole: str) -> float:
    if pole not in POLES:
        raise ValueError(f"pole must be one of {POLES}, got {pole!r}")
    return 1.0 if pole == "north" else -1.0


def polar_stereo_forward(lat_deg, lon_deg, pole: str = "south", radius_m: float = MOON_RADIUS_M):
    """Spherical polar stereographic (lat_ts = lat_0 = +-90, lon0 = 0, k0 = 1): (lat, lon) -> (x, y) m.

    Matches PROJ ``+proj=stere +lat_0=-90 +lon_0=0 +k=1 +R=1737400`` (``pole="south"``) and
    ``+proj=stere +lat_0=90 ...`` (``pole="north"``), the LOLA/LROC polar products. Both put lon 90 E
    on +x; lon 0 is on +y at the south pole and on -y at the north pole (the map is seen from above).
    """
    s = _pole_sign(pole)
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    rho = 2.0 * radius_m * np.tan(np.pi / 4.0 - s * lat / 2.0)
    return rho * np.sin(lon), -s * rho * np.cos(lon)


def polar_stereo_inverse(x, y, pole: str = "south", radius_m: float = MOON_RADIUS_M):
    """Inverse of :func:`polar_stereo_forward`: (x, y) m -> (lat_deg, lon_deg)."""
    s = _pole_sign(pole)
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    rho = np.hypot(x, y)
    lat = s * (np.pi / 2.0 - 2.0 * np.arctan(rho / (2.0 * radius_m)))
    lon = np.arctan2(x, -s * y)
    return np.degrees(lat), np.degrees(lon)


def south_polar_stereo_forward(lat_deg, lon_deg, radius_m: float = MOON_RADIUS_M):
    """:func:`polar_stereo_forward` at the south pole."""
    return polar_stereo_forward(lat_deg, lon_deg, "south", radius_m)


def south_polar_stereo_inverse(x, y, radius_m: float = MOON_RADIUS_M):
    """:func:`polar_stereo_inverse` at the south pole."""
    return polar_stereo_inverse(x, y, "south", radius_m)


# --------------------------------------------------------------------------------------------
# Sun and camera
# --------------------------------------------------------------------------------------------
def direction_from_elevation_azimuth(elevation_deg, azimuth_deg) -> np.ndarray:
    """Unit ENU vector pointing towards a target at (elevation, azimuth clockwise from north)."""
    el = np.radians(np.asarray(elevation_deg, dtype=np.float64))
    az = np.radians(np.asarray(azimuth_deg, dtype=np.float64))
    return np.stack(np.broadcast_arrays(np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)), axis=-1)


@dataclass(frozen=True)
class CameraPose:
    """A pinhole camera in the ENU frame (Blender convention: looks along local -Z, up is +Y)."""

    position: np.ndarray  # (3,) metres, ENU
    rotation: np.ndarray  # (3, 3) columns = camera x (right), y (up), z (backwards) in ENU
    fov_deg: float  # full horizontal == vertical field of view (square sensor)

    @property
    def forward(self) -> np.ndarray:
        return -self.rotation[:, 2]

    def focal_px(self, width_px: int) -> float:
        """Focal length in pixels for a square frame of ``width_px`` pixels."""
        return 0.5 * width_px / math.tan(math.radians(self.fov_deg) / 2.0)


def look_at_camera(
    elevation_deg: float, azimuth_deg: float, range_m: float, fov_deg: float, target=(0.0, 0.0, 0.0)
) -> CameraPose:
    """Camera at (elevation, azimuth, range) from ``target`` looking at it.

    Image "up" is the horizontal direction pointing away from the camera (the forward ground track);
    at nadir (elevation 90) it is the limit of that direction, so the image orientation is continuous
    in elevation and rotates with the camera azimuth.
    """
    target = np.asarray(target, dtype=np.float64)
    to_cam = direction_from_elevation_azimuth(elevation_deg, azimuth_deg)
    position = target + range_m * to_cam
    back = to_cam  # camera +Z points away from the scene
    away = -direction_from_elevation_azimuth(0.0, azimuth_deg)  # horizontal, away from the camera
    # Up vector in the image plane: component of the forward ground track orthogonal to the view axis.
    up = away - np.dot(away, back) * back
    up /= np.linalg.norm(up)
    right = np.cross(up, back)
    return CameraPose(position=position, rotation=np.stack([right, up, back], axis=1), fov_deg=float(fov_deg))


def project_points(points_enu: np.ndarray, pose: CameraPose, width_px: int, height_px: int | None = None):
    """Project ENU points into full-frame pixel coordinates (u right, v down, origin top-left corner).

    Returns (uv (..., 2), depth (...,)) where depth is the distance along the view axis.
    """
    height_px = width_px if height_px is None else height_px
    p = (np.asarray(points_enu, dtype=np.float64) - pose.position) @ pose.rotation  # camera coords
    depth = -p[..., 2]
    f = pose.focal_px(width_px)
    u = width_px / 2.0 + f * p[..., 0] / depth
    v = height_px / 2.0 - f * p[..., 1] / depth
    return np.stack([u, v], axis=-1), depth


def back_project_pixels(
    uv: np.ndarray, depth: np.ndarray, pose: CameraPose, width_px: int, height_px: int | None = None
):
    """ENU points seen at full-frame pixel coordinates ``uv`` (..., 2) with ``depth`` (...) metres along
    the view axis: the inverse of :func:`project_points` (a render's ``depth`` channel gives the ground
    point under every pixel, e.g. to sample a map-projected real image in the render's frame)."""
    height_px = width_px if height_px is None else height_px
    uv = np.asarray(uv, dtype=np.float64)
    d = np.asarray(depth, dtype=np.float64)
    f = pose.focal_px(width_px)
    cam = np.stack([(uv[..., 0] - width_px / 2.0) * d / f, -(uv[..., 1] - height_px / 2.0) * d / f, -d], axis=-1)
    return pose.position + cam @ pose.rotation.T


# --------------------------------------------------------------------------------------------
# Projected crater rim: a 3-D circle through a pinhole is exactly a conic (an ellipse here).
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Ellipse:
    """Ellipse in full-frame pixel coordinates: centre, semi-axes (a >= b) and angle of a (radians,
    from the +u axis towards +v)."""

    cu: float
    cv: float
    a: float
    b: float
    angle: float

    def as_dict(self) -> dict:
        return {"cu": self.cu, "cv": self.cv, "a": self.a, "b": self.b, "angle_rad": self.angle}

    def points(self, n: int = 256) -> np.ndarray:
        return ellipse_points(np.array([[self.cu, self.cv, self.a, self.b, self.angle]]), n)[0]


def ellipse_points(ellipses: np.ndarray, n: int = 256) -> np.ndarray:
    """(k, n, 2) points evenly spaced in parameter on k ellipses, rows (cu, cv, a, b, angle) as
    :class:`Ellipse`."""
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    cu, cv, a, b, angle = (np.asarray(ellipses, dtype=np.float64)[:, k, None] for k in range(5))
    ca, sa = np.cos(angle), np.sin(angle)
    x, y = a * np.cos(t), b * np.sin(t)
    return np.stack([cu + ca * x - sa * y, cv + sa * x + ca * y], axis=-1)


def plane_basis(normal) -> tuple[np.ndarray, np.ndarray]:
    """Two orthonormal in-plane axes (e1, e2) of the plane with unit ``normal``, right-handed with it;
    for the vertical normal (0, 0, 1) they are exactly east and north. ``normal`` (3,) or (n, 3)."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    ref = np.where((np.abs(n[..., :1]) < 0.9), [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    e1 = ref - np.sum(ref * n, axis=-1, keepdims=True) * n
    e1 = e1 / np.linalg.norm(e1, axis=-1, keepdims=True)
    return e1, np.cross(n, e1)


def _plane_to_image_homography(center_enu, pose: CameraPose, width_px: int, normal=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Homography mapping (x, y, 1) in the plane through ``center_enu`` with ``normal`` (in-plane axes
    :func:`plane_basis`) to pixels: (3, 3), or (n, 3, 3) for (n, 3) centres and normals."""
    f = pose.focal_px(width_px)
    # Projective intrinsics in (u, v) with v down: [u v 1]^T ~ K [Xc, Yc, -Zc]^T
    K = np.array([[f, 0.0, width_px / 2.0], [0.0, -f, width_px / 2.0], [0.0, 0.0, 1.0]])
    flip = np.diag([1.0, 1.0, -1.0])
    R_wc = pose.rotation.T  # world -> camera
    t = (np.asarray(center_enu, dtype=np.float64) - pose.position) @ R_wc.T
    e1, e2 = plane_basis(np.broadcast_to(normal, t.shape))
    # Plane points: world = center + x*e1 + y*e2  ->  camera = R_wc e1 x + R_wc e2 y + t
    M = np.stack([e1 @ R_wc.T, e2 @ R_wc.T, t], axis=-1)
    return K @ flip @ M


def project_horizontal_circle(center_enu, radius_m: float, pose: CameraPose, width_px: int) -> Ellipse:
    """Exact image of a horizontal circle (the crater rim) as an :class:`Ellipse` (full-frame pixels)."""
    return project_circle(center_enu, (0.0, 0.0, 1.0), radius_m, pose, width_px)


def project_circle(center_enu, normal_enu, radius_m: float, pose: CameraPose, width_px: int) -> Ellipse:
    """Exact image of the circle of ``radius_m`` about ``center_enu`` in the plane with ``normal_enu``
    (e.g. a crater rim far from the frame origin, level with its own local horizontal on the curved
    Moon) as an :class:`Ellipse` (full-frame pixels). The circle must lie wholly in front of the camera."""
    e = project_circles(
        np.asarray(center_enu)[None], np.asarray(normal_enu)[None], np.array([radius_m]), pose, width_px
    )
    return Ellipse(*(float(v[0]) for v in e))


def project_circles(centres, normals, radii, pose: CameraPose, width_px: int) -> tuple[np.ndarray, ...]:
    """:func:`project_circle` of n circles at once ((n, 3) centres and normals, (n,) radii): the arrays
    (cu, cv, a, b, angle), each (n,). Every circle must lie wholly in front of the camera."""
    H = _plane_to_image_homography(centres, pose, width_px, normals)
    r2 = np.asarray(radii, dtype=np.float64) ** 2
    C = np.zeros((len(r2), 3, 3))
    C[:, 0, 0] = C[:, 1, 1] = 1.0
    C[:, 2, 2] = -r2  # x^2 + y^2 - r^2 = 0
    Hinv = np.linalg.inv(H)
    Q = np.swapaxes(Hinv, 1, 2) @ C @ Hinv
    Q = 0.5 * (Q + np.swapaxes(Q, 1, 2))
    M = Q[:, :2, :2]
    centre = np.linalg.solve(M, -Q[:, :2, 2:3])[..., 0]
    F0 = Q[:, 2, 2] + np.sum(Q[:, :2, 2] * centre, axis=1)
    evals, evecs = np.linalg.eigh(M)
    semi = np.sqrt(-F0[:, None] / evals)  # ascending eigenvalues -> descending semi-axes
    major = np.argmax(semi, axis=1)
    vec = evecs[np.arange(len(r2)), :, major]
    return centre[:, 0], centre[:, 1], semi.max(axis=1), semi.min(axis=1), np.arctan2(vec[:, 1], vec[:, 0])


def roi_box(center_uv, major_axis_px: float, sigma: float) -> tuple[float, float, float, float]:
    """Square ROI (u0, v0, u1, v1), side = sigma x the rim ellipse's major axis (2a), centred on
    the projected crater centre (paper Fig. 4)."""
    half = 0.5 * sigma * major_axis_px
    cu, cv = float(center_uv[0]), float(center_uv[1])
    return (cu - half, cv - half, cu + half, cv + half)


def frame_width_for_roi(
    pose: CameraPose, rim_center_enu, rim_radius_m: float, min_roi_px: int, sigma_min: float
) -> int:
    """Smallest full-frame width (px) for which the sigma_min ROI box is at least ``min_roi_px`` wide.

    The ellipse scales linearly with the frame width at fixed FOV, so one projection suffices.
    """
    ref_width = 1000
    ell = project_horizontal_circle(rim_center_enu, rim_radius_m, pose, ref_width)
    side_at_ref = sigma_min * 2.0 * ell.a
    return int(math.ceil(min_roi_px * ref_width / side_at_ref - 1e-9))
