"""Camera poses of navigation frames along a trajectory (pure numpy + standard library).

A trajectory (``trajectory.*``, :class:`crater_core.settings.TrajectorySettings`) is a great-circle
ground track from ``start`` to ``end`` flown at an altitude that runs linearly from the first to the
last frame. Each frame's camera:

- sits at ``altitude`` above the reference sphere (``geometry.MOON_RADIUS_M``) over its sub-camera
  point;
- looks along the boresight: nadir tilted by ``off_nadir_deg`` towards ``off_nadir_azimuth_deg``
  (clockwise from the direction of flight, so 90 is to the right of the track);
- has image up along the direction of flight (projected orthogonal to the boresight), the convention
  of ``geometry.look_at_camera`` ("image up is the forward ground track").

The frame is rendered on a terrain patch centred on the *target*: the boresight's intercept with the
reference sphere. Poses are Moon-centred (MC) here; :meth:`FramePose.pose_enu` expresses one in the
ENU frame of any patch origin (the renderer's world frame, ``crater_core.geometry``).

The Sun is a direction at infinity: ``physical`` is the unit vector to the sub-solar point (the
Sun's declination, the sub-solar latitude, stays within the lunar obliquity,
``crater_core.illumination.LUNAR_OBLIQUITY_DEG``); ``explicit`` is given as (elevation, azimuth)
above each frame's target point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from crater_core import geometry
from crater_core.errors import ContractError


class TrajectoryError(ContractError):
    """A trajectory whose frames cannot be rendered (a camera that sees the sky, a degenerate track)."""


@dataclass(frozen=True)
class FramePose:
    """One frame of a trajectory: camera pose (MC), field of view, frame size, target and Sun."""

    index: int
    position_mc: np.ndarray  # (3,) m
    rotation_mc: np.ndarray  # (3, 3) columns: camera right, up, back (Blender convention) in MC
    fov_deg: float
    width_px: int
    altitude_m: float
    subcam_lat: float
    subcam_lon: float
    heading_deg: float  # direction of flight at the sub-camera point, clockwise from local north
    target_lat: float  # boresight intercept with the reference sphere
    target_lon: float
    to_sun_mc: np.ndarray  # (3,) unit vector towards the Sun

    def pose_enu(self, lat0_deg: float, lon0_deg: float) -> geometry.CameraPose:
        """The camera in the ENU frame whose origin is (lat0, lon0) on the reference sphere."""
        basis = geometry.enu_basis(lat0_deg, lon0_deg)  # rows E, N, U in MC
        position = geometry.mc_to_enu(self.position_mc, lat0_deg, lon0_deg)
        return geometry.CameraPose(position=position, rotation=basis @ self.rotation_mc, fov_deg=self.fov_deg)

    def sun_enu(self, lat0_deg: float, lon0_deg: float) -> tuple[float, float]:
        """(elevation, azimuth) of the Sun, degrees, in the ENU frame at (lat0, lon0)."""
        return sun_elevation_azimuth(self.to_sun_mc, lat0_deg, lon0_deg)

    def ground_sample_m(self) -> float:
        """Ground size of the centre pixel (m): slant range to the target x pixel angle (nadir: altitude / f)."""
        target = geometry.latlon_to_mc(self.target_lat, self.target_lon)
        slant = float(np.linalg.norm(target - self.position_mc))
        return slant / focal_px(self.fov_deg, self.width_px)

    @classmethod
    def from_dict(cls, d: dict) -> FramePose:
        """The pose of an :meth:`as_dict` record (a manifest row's ``pose``), the same values."""
        return cls(
            index=int(d["index"]),
            position_mc=np.asarray(d["position_mc_m"], dtype=np.float64),
            rotation_mc=np.asarray(d["rotation_mc"], dtype=np.float64),
            fov_deg=float(d["fov_deg"]),
            width_px=int(d["width_px"]),
            altitude_m=float(d["altitude_m"]),
            subcam_lat=float(d["subcam_lat"]),
            subcam_lon=float(d["subcam_lon"]),
            heading_deg=float(d["heading_deg"]),
            target_lat=float(d["target_lat"]),
            target_lon=float(d["target_lon"]),
            to_sun_mc=np.asarray(d["to_sun_mc"], dtype=np.float64),
        )

    def as_dict(self) -> dict:
        """JSON-ready record (the manifest row's pose)."""
        return {
            "index": self.index,
            "position_mc_m": [float(v) for v in self.position_mc],
            "rotation_mc": [[float(v) for v in row] for row in self.rotation_mc],
            "fov_deg": self.fov_deg,
            "width_px": self.width_px,
            "altitude_m": self.altitude_m,
            "subcam_lat": self.subcam_lat,
            "subcam_lon": self.subcam_lon,
            "heading_deg": self.heading_deg,
            "target_lat": self.target_lat,
            "target_lon": self.target_lon,
            "to_sun_mc": [float(v) for v in self.to_sun_mc],
        }


def focal_px(fov_deg: float, width_px: int) -> float:
    """Pinhole focal length in pixels of a square frame (``geometry.CameraPose.focal_px``)."""
    return 0.5 * width_px / math.tan(math.radians(fov_deg) / 2.0)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def great_circle(start, end, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` evenly spaced unit vectors (MC) from ``start`` to ``end`` ((lat, lon) deg) along the shorter
    great circle, and the unit direction of travel at each. A single point (start == end) travels north."""
    a = geometry.latlon_to_mc(start[0], start[1], 0.0, 1.0)
    b = geometry.latlon_to_mc(end[0], end[1], 0.0, 1.0)
    omega = math.acos(max(-1.0, min(1.0, float(a @ b))))
    if omega > math.pi - 1e-6:
        raise TrajectoryError(f"trajectory start {list(start)} and end {list(end)} are antipodal: no unique track")
    t = np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(1)
    if omega < 1e-9:
        pts = np.repeat(a[None, :], n, axis=0)
        lat, lon = start
        travel = np.repeat(geometry.enu_basis(lat, lon)[1][None, :], n, axis=0)
        return pts, travel
    pts = (np.sin((1 - t) * omega)[:, None] * a + np.sin(t * omega)[:, None] * b) / math.sin(omega)
    normal = _unit(np.cross(a, b))
    travel = _unit(np.cross(normal[None, :], pts))
    return pts, travel


def ray_sphere(origin: np.ndarray, direction: np.ndarray, radius_m: float = geometry.MOON_RADIUS_M):
    """Nearest forward intercept of rays (..., 3) with the sphere, or NaN where a ray misses it."""
    origin = np.asarray(origin, dtype=np.float64)
    d = _unit(np.asarray(direction, dtype=np.float64))
    b = np.sum(origin * d, axis=-1)
    c = np.sum(origin * origin, axis=-1) - radius_m**2
    disc = b * b - c
    t = -b - np.sqrt(np.where(disc >= 0, disc, np.nan))
    t = np.where(t > 0, t, np.nan)
    return origin + t[..., None] * d


def camera_rotation(up_mc: np.ndarray, travel_mc: np.ndarray, off_nadir_deg: float, off_azimuth_deg: float):
    """Camera axes (columns right, up, back; MC) for a boresight tilted ``off_nadir_deg`` from nadir
    towards ``off_azimuth_deg`` clockwise from ``travel_mc``; image up follows the direction of travel."""
    f = _unit(travel_mc - (travel_mc @ up_mc) * up_mc)
    right_h = np.cross(f, up_mc)  # horizontal, to the right of the track
    az, tilt = math.radians(off_azimuth_deg), math.radians(off_nadir_deg)
    horizontal = math.cos(az) * f + math.sin(az) * right_h
    boresight = math.cos(tilt) * (-up_mc) + math.sin(tilt) * horizontal
    up = f - (f @ boresight) * boresight
    if np.linalg.norm(up) < 1e-9:  # looking along the track (not reachable below 60 deg tilt)
        up = -up_mc
    up = _unit(up)
    back = -boresight
    right = np.cross(up, back)
    return np.stack([right, up, back], axis=1)


def sun_direction_mc(subsolar_lat_deg: float, subsolar_lon_deg: float) -> np.ndarray:
    """Unit vector towards the Sun (at infinity) from its sub-solar point."""
    return geometry.latlon_to_mc(subsolar_lat_deg, subsolar_lon_deg, 0.0, 1.0)


def sun_elevation_azimuth(to_sun_mc: np.ndarray, lat_deg: float, lon_deg: float) -> tuple[float, float]:
    """(elevation, azimuth clockwise from north) in degrees of an MC direction seen at (lat, lon)."""
    e, n, u = geometry.enu_basis(lat_deg, lon_deg) @ np.asarray(to_sun_mc, dtype=np.float64)
    return math.degrees(math.asin(max(-1.0, min(1.0, u)))), math.degrees(math.atan2(e, n)) % 360.0


def frame_corners_mc(pose: FramePose) -> np.ndarray:
    """Ground points (MC, on the reference sphere) seen by the frame's four corner pixels; NaN rows
    where a corner sees the sky."""
    h = math.tan(math.radians(pose.fov_deg) / 2.0)
    cam = np.array([[-h, h, -1.0], [h, h, -1.0], [h, -h, -1.0], [-h, -h, -1.0]])
    return ray_sphere(np.repeat(pose.position_mc[None, :], 4, axis=0), cam @ pose.rotation_mc.T)


def footprint_half_width_m(pose: FramePose) -> float:
    """Half-width of the smallest square, in the target's ENU plane, that holds the frame's ground
    footprint (the corners on the reference sphere). Raises :class:`TrajectoryError` when a corner
    sees the sky."""
    corners = frame_corners_mc(pose)
    if not np.all(np.isfinite(corners)):
        raise TrajectoryError(
            f"frame {pose.index} sees beyond the horizon (altitude {pose.altitude_m / 1e3:.1f} km, "
            f"fov {pose.fov_deg:g} deg): lower trajectory.fov_deg or trajectory.off_nadir_deg"
        )
    enu = geometry.mc_to_enu(corners, pose.target_lat, pose.target_lon)
    return float(np.max(np.abs(enu[:, :2])))


def frame_poses(traj) -> list[FramePose]:
    """Every frame's :class:`FramePose` for a ``TrajectorySettings`` (or any object with its fields)."""
    pts, travel = great_circle(tuple(traj.start), tuple(traj.end), int(traj.frames))
    n = int(traj.frames)
    alts = np.linspace(traj.altitude_km[0], traj.altitude_km[-1], n) * 1000.0 if n > 1 else [traj.altitude_km[0] * 1e3]
    physical = traj.sun == "physical"
    s_phys = sun_direction_mc(traj.subsolar_lat_deg, traj.subsolar_lon_deg) if physical else None
    poses = []
    for i in range(n):
        up = pts[i]
        lat, lon, _ = geometry.mc_to_latlon(up * geometry.MOON_RADIUS_M)
        lat, lon = float(lat), float(lon)
        basis = geometry.enu_basis(lat, lon)
        heading = math.degrees(math.atan2(travel[i] @ basis[0], travel[i] @ basis[1])) % 360.0
        rot = camera_rotation(up, travel[i], traj.off_nadir_deg, traj.off_nadir_azimuth_deg)
        position = up * (geometry.MOON_RADIUS_M + float(alts[i]))
        hit = ray_sphere(position, -rot[:, 2])
        if not np.all(np.isfinite(hit)):
            raise TrajectoryError(f"frame {i}: the boresight misses the Moon; lower trajectory.off_nadir_deg")
        tlat, tlon, _ = geometry.mc_to_latlon(hit)
        tlat, tlon = float(tlat), float(tlon)
        if physical:
            to_sun = s_phys
        else:
            to_sun = geometry.direction_from_elevation_azimuth(traj.sun_elevation_deg, traj.sun_azimuth_deg)
            to_sun = to_sun @ geometry.enu_basis(tlat, tlon)  # ENU at the target -> MC
        poses.append(
            FramePose(
                index=i,
                position_mc=position,
                rotation_mc=rot,
                fov_deg=float(traj.fov_deg),
                width_px=int(traj.width_px),
                altitude_m=float(alts[i]),
                subcam_lat=lat,
                subcam_lon=lon,
                heading_deg=heading,
                target_lat=tlat,
                target_lon=tlon,
                to_sun_mc=np.asarray(to_sun, dtype=np.float64),
            )
        )
    for p in poses:
        footprint_half_width_m(p)  # every frame must see only ground
    return poses


__all__ = [
    "FramePose",
    "TrajectoryError",
    "camera_rotation",
    "focal_px",
    "footprint_half_width_m",
    "frame_corners_mc",
    "frame_poses",
    "great_circle",
    "ray_sphere",
    "sun_direction_mc",
    "sun_elevation_azimuth",
]
