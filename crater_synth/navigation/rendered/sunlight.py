"""The light of a rendered frame: the direction towards its Sun (its row's ``sun_enu``) and the direction its
light travels across the image. A lander knows both from the Sun's ephemeris and its attitude; the renderer
records them. Kept apart from the evaluation so that training and the ground view read them without it.
"""

from __future__ import annotations

import math

import numpy as np

from crater_core import geometry


def row_to_sun(row: dict) -> np.ndarray:
    """The unit vector towards the Sun, in the frame's axes, of a rendered frame's row (``sun_enu``)."""
    return geometry.direction_from_elevation_azimuth(row["sun_enu"]["elevation_deg"], row["sun_enu"]["azimuth_deg"])


def light_direction(rotation: np.ndarray, to_sun: np.ndarray) -> float:
    """Image azimuth (radians, atan2(dv, du), v down) of the light's travel direction (away from the Sun)."""
    travel = -np.asarray(to_sun, dtype=np.float64)
    return math.atan2(-(travel @ rotation[:, 1]), travel @ rotation[:, 0])


def rendered_light(row: dict) -> float:
    """The image azimuth (radians, atan2(dv, du), v down) the light travels along in the frame of ``row``: its
    Sun seen by its camera (:func:`light_direction`); what a slimmed or streamed training row carries
    (``light_rad``). NaN for a row that names no Sun or camera."""
    if "light_rad" in row:
        return float(row["light_rad"])
    if "sun_enu" not in row or "camera_enu" not in row:
        return math.nan
    return light_direction(np.array(row["camera_enu"]["rotation"], dtype=np.float64), row_to_sun(row))
