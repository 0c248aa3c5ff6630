"""Polar stereographic map frames of either pole, on top of :mod:`crater_core.geometry`.

The LOLA/LROC polar products use the spherical polar stereographic projection (lat_ts = +-90, lon0 = 0,
k0 = 1, R = 1737.4 km). The south projection is ``crater_core.geometry.south_polar_stereo_*``; the north
one is its mirror image (PROJ ``+proj=stere +lat_0=90``: x = rho sin(lon), y = -rho cos(lon), with
rho = 2 R tan(pi/4 - lat/2)), i.e. the south formula applied to -lat with y negated.
"""

from __future__ import annotations

import numpy as np

from crater_core.geometry import MOON_RADIUS_M, south_polar_stereo_forward, south_polar_stereo_inverse

POLES = ("south", "north")


def check_pole(pole: str) -> str:
    """``pole`` if it is one of :data:`POLES`, else a ValueError naming it."""
    if pole not in POLES:
        raise ValueError(f"pole {pole!r}: choose one of {', '.join(POLES)}")
    return pole


def stereo_forward(lat_deg, lon_deg, pole: str = "south", radius_m: float = MOON_RADIUS_M):
    """(lat, lon) deg -> polar stereographic (x, y) m of ``pole``."""
    if check_pole(pole) == "south":
        return south_polar_stereo_forward(lat_deg, lon_deg, radius_m)
    x, y = south_polar_stereo_forward(-np.asarray(lat_deg, dtype=np.float64), lon_deg, radius_m)
    return x, -y


def stereo_inverse(x, y, pole: str = "south", radius_m: float = MOON_RADIUS_M):
    """Polar stereographic (x, y) m of ``pole`` -> (lat, lon) deg."""
    if check_pole(pole) == "south":
        return south_polar_stereo_inverse(x, y, radius_m)
    lat, lon = south_polar_stereo_inverse(x, -np.asarray(y, dtype=np.float64), radius_m)
    return -lat, lon


def scale_factor(lat_deg, pole: str = "south"):
    """Point scale k of the polar stereographic projection (k0 = 1 at the pole): map length / true length.

    k = 2 / (1 + sin|lat|) (Snyder 1987, eq. 21-4 with k0 = 1): 1.000 at the pole, 1.031 at 70 deg.
    """
    check_pole(pole)
    return 2.0 / (1.0 + np.sin(np.radians(np.abs(np.asarray(lat_deg, dtype=np.float64)))))
