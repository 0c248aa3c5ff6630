"""Polar stereographic map frames of either pole for navigation: thin names over the one projection,
:func:`crater_core.geometry.polar_stereo_forward` / ``_inverse`` (lat_ts = +-90, lon0 = 0, k0 = 1,
R = 1737.4 km, as the LOLA/LROC polar products), plus the projection's point scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crater_core.geometry import MOON_RADIUS_M, POLES, polar_stereo_forward, polar_stereo_inverse
from crater_synth.errors import UserError


def check_pole(pole: str) -> str:
    """``pole`` if it is one of :data:`POLES`, else a ValueError naming it."""
    if pole not in POLES:
        raise ValueError(f"pole {pole!r}: choose one of {', '.join(POLES)}")
    return pole


def pole_of(lat_deg: float) -> str:
    """The pole whose map holds a point at latitude ``lat_deg`` (a frame's target, a camera's ground point)."""
    return "south" if lat_deg < 0 else "north"


def stereo_forward(lat_deg, lon_deg, pole: str = "south", radius_m: float = MOON_RADIUS_M):
    """(lat, lon) deg -> polar stereographic (x, y) m of ``pole``."""
    return polar_stereo_forward(lat_deg, lon_deg, check_pole(pole), radius_m)


def stereo_inverse(x, y, pole: str = "south", radius_m: float = MOON_RADIUS_M):
    """Polar stereographic (x, y) m of ``pole`` -> (lat, lon) deg."""
    return polar_stereo_inverse(x, y, check_pole(pole), radius_m)


def scale_factor(lat_deg, pole: str = "south"):
    """Point scale k of the polar stereographic projection (k0 = 1 at the pole): map length / true length.

    k = 2 / (1 + sin|lat|) (Snyder 1987, eq. 21-4 with k0 = 1): 1.000 at the pole, 1.031 at 70 deg.
    """
    check_pole(pole)
    return 2.0 / (1.0 + np.sin(np.radians(np.abs(np.asarray(lat_deg, dtype=np.float64)))))


def local_north_image_angle(x, y, pole: str = "south"):
    """Angle (radians, from image +u towards image +v, i.e. clockwise on a north-up map image) of local
    north (the direction of increasing latitude) at map points (x, y) of ``pole``'s polar stereographic
    plane, in a map image whose pixel (u, v) is (left + u p, top - v p).

    Local north points away from the pole at the south pole and towards it at the north pole
    (:func:`crater_core.geometry.noon_azimuth_deg`). The map is seen from above at both poles, so local
    east is 90 degrees clockwise of local north in the image at both: a direction at local azimuth
    ``alpha`` (clockwise from local north) lies at image angle ``local_north_image_angle + alpha``.
    """
    s = 1.0 if check_pole(pole) == "north" else -1.0
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    # Map direction of local north: -(x, y) (towards the pole) in the north, +(x, y) in the south;
    # image (du, dv) = (dx, -dy).
    return np.arctan2(s * y, -s * x)


class FrameError(UserError):
    """A frame cannot be navigated: no georeference, empty, outside the map."""


@dataclass(frozen=True)
class Georef:
    """Map georeference of a nadir orthographic frame: map point of pixel (u, v) is
    (left_m + u pixel_m, top_m - v pixel_m) in ``pole``'s polar stereographic projection (u, v continuous,
    origin at the top-left corner of the top-left pixel)."""

    pole: str
    left_m: float
    top_m: float
    pixel_m: float

    @classmethod
    def centred_on(cls, pole: str, x_m: float, y_m: float, shape, pixel_m: float) -> "Georef":
        """The georeference of a frame of ``shape`` (h, w) whose centre is map point (x_m, y_m)."""
        h, w = shape[:2]
        return cls(pole, float(x_m) - w / 2 * pixel_m, float(y_m) + h / 2 * pixel_m, pixel_m)

    def uv_to_xy(self, u, v):
        return self.left_m + np.asarray(u) * self.pixel_m, self.top_m - np.asarray(v) * self.pixel_m

    def xy_to_uv(self, x, y):
        return (np.asarray(x) - self.left_m) / self.pixel_m, (self.top_m - np.asarray(y)) / self.pixel_m

    def as_dict(self) -> dict:
        return {"pole": self.pole, "left_m": self.left_m, "top_m": self.top_m, "pixel_m": self.pixel_m}


@dataclass(frozen=True)
class Frame:
    """One evaluation frame: the image, where it was cut, and its truth georeference."""

    id: str
    split: str
    sector: int
    image: np.ndarray  # (H, W) uint8
    georef: Georef  # truth

    @property
    def centre_xy(self) -> tuple[float, float]:
        h, w = self.image.shape
        x, y = self.georef.uv_to_xy(w / 2.0, h / 2.0)
        return float(x), float(y)

    @property
    def centre_latlon(self) -> tuple[float, float]:
        lat, lon = stereo_inverse(*self.centre_xy, self.georef.pole)
        return float(lat), float(lon)


def check_frame(image: np.ndarray, what: str) -> np.ndarray:
    """``image`` as a float 2-D array, or one clear error: not 2-D, too small, or empty (no contrast)."""
    a = np.asarray(image)
    if a.ndim != 2 or min(a.shape) < 32:
        raise FrameError(f"{what}: expected a grey image of at least 32x32 px, got shape {a.shape}")
    a = a.astype(np.float32)
    if not np.isfinite(a).all():
        raise FrameError(f"{what}: the image has non-finite pixels")
    # Relative to the frame's own peak: an I/F frame (peak ~0.01-0.05) mostly in shadow is dark, not empty.
    if float(a.std()) <= 1e-3 * float(np.abs(a).max()):
        raise FrameError(f"{what}: the frame is empty (constant, no contrast to find craters in)")
    return a


def ground_distance_km(x1, y1, x2, y2, pole: str = "south") -> np.ndarray:
    """Ground distance (km) between nearby map points: map distance / scale factor at their midpoint."""

    lat, _ = stereo_inverse(0.5 * (np.asarray(x1) + x2), 0.5 * (np.asarray(y1) + y2), pole)
    return np.hypot(np.asarray(x1) - x2, np.asarray(y1) - y2) / scale_factor(lat, pole) / 1000.0
