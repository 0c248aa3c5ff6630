"""Which Sun positions a crater really sees (the ``physical`` sweep; docs/validation.md).

The Sun's declination in the Moon's equatorial frame never exceeds the obliquity of the lunar
equator to the ecliptic, ε = 1.54° (Cassini's laws; 1.5424° in the IAU rotation model, Archinal et
al. 2018, Celest. Mech. Dyn. Astr. 130:22; docs/specification.md). At a crater at latitude φ the Sun's elevation
above the local horizon therefore depends on where it stands: towards the equator (local north at
a south-polar crater, local south at a north-polar one, where local north points at the pole) it can
reach (90° − |φ|) + ε; towards the pole it stays below ε − (90° − |φ|). For a small colatitude
c = 90° − |φ| this is θ_max(A) ≈ ε + c·cos(A − A_noon) for a Sun at azimuth A (clockwise from local
north), A_noon = 0° in the south and 180° in the north (``crater_core.geometry.noon_azimuth_deg``);
:func:`max_sun_elevation_deg` gives the exact value at either pole.

Pure numpy + math (crater_core).
"""

from __future__ import annotations

import numpy as np

# Obliquity of the lunar equator to the ecliptic (docs/specification.md; IAU WGCCRE, Archinal et al. 2018).
LUNAR_OBLIQUITY_DEG = 1.54


def sun_declination_deg(lat_deg, elevation_deg, azimuth_deg):
    """Declination (deg, in the Moon's equatorial frame) of a direction seen at local (elevation,
    azimuth clockwise from north) from latitude ``lat_deg``: asin(s · p), p = the north-pole axis in
    the local east-north-up frame, (0, cos φ, sin φ)."""
    lat, el, az = (np.radians(np.asarray(v, dtype=np.float64)) for v in (lat_deg, elevation_deg, azimuth_deg))
    s_dot_p = np.cos(el) * np.cos(az) * np.cos(lat) + np.sin(el) * np.sin(lat)
    return np.degrees(np.arcsin(np.clip(s_dot_p, -1.0, 1.0)))


def max_sun_elevation_deg(lat_deg, azimuth_deg, obliquity_deg: float = LUNAR_OBLIQUITY_DEG):
    """Highest elevation (deg) the Sun's centre ever reaches at local azimuth ``azimuth_deg`` seen from
    latitude ``lat_deg`` (the Sun's declination |δ| ≤ ``obliquity_deg``); may be negative where the
    Sun never rises in that direction.

    With s·p = a cos θ + b sin θ = R cos(θ − ψ) (a = cos A cos φ, b = sin φ, R = hypot(a, b),
    ψ = atan2(b, a)), the boundary δ = ∓ε of the southern (northern) hemisphere gives
    θ = ψ ± arccos(∓sin ε / R): the root in [−90°, 90°] is the maximum.
    """
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    az = np.radians(np.asarray(azimuth_deg, dtype=np.float64))
    sin_eps = np.sin(np.radians(obliquity_deg))
    a = np.cos(az) * np.cos(lat)
    b = np.sin(lat) + 0.0 * a
    r = np.hypot(a, b)
    psi = np.arctan2(b, a)
    south = b < 0.0
    # South: the Sun climbs until s·p falls to -sin ε; north: until s·p rises to +sin ε.
    theta = np.where(
        south, psi + np.arccos(np.clip(-sin_eps / r, -1.0, 1.0)), psi - np.arccos(np.clip(sin_eps / r, -1.0, 1.0))
    )
    return np.degrees(np.clip(theta, -np.pi / 2, np.pi / 2))
