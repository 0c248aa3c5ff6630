"""Polar stereographic map frames of either pole for navigation: thin names over the one projection,
:func:`crater_core.geometry.polar_stereo_forward` / ``_inverse`` (lat_ts = +-90, lon0 = 0, k0 = 1,
R = 1737.4 km, as the LOLA/LROC polar products), plus the projection's point scale.
"""

from __future__ import annotations

import numpy as np

from crater_core.geometry import MOON_RADIUS_M, POLES, polar_stereo_forward, polar_stereo_inverse


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
