"""A frame turned so that its light travels along +u (from the image's left to its right), for a learned
detector trained on frames turned alike (``nav.detector_train.sun_aligned``).

Why: a crater's look is set mostly by where the light comes from: the shadowed wall on the Sun's side, the
lit wall and rim opposite. A network that must find craters under any light direction learns every one of
those looks; a small one, trained briefly, learns each less well. A lander knows the direction (the Sun's
ephemeris and its own attitude), as the renderer does, so the frame can be turned to one light direction
before the network sees it, and the detections turned back. Only the mirror image along the light is then
a second view of the same physics (a mirror across it, or a quarter turn, would move the Sun).

Coordinates are continuous pixels, origin at the top-left corner (u right, v down), as the detectors' are.
The turned image is large enough to hold the whole frame; pixels outside it are NaN. OpenCV does the
resampling (bilinear): ``cv2.warpAffine`` takes pixel centres at integers, hence the half-pixel shifts.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

# A turned pixel is inside the frame when bilinear weights from inside sum to at least this: the edge row
# of pixels, which mixes frame and outside, is left out rather than darkened.
INSIDE_WEIGHT = 0.999


class Turned(NamedTuple):
    """A frame turned to the light: ``image`` (float32, NaN outside the frame), ``rotation`` (2 x 2: turned
    offsets = rotation @ frame offsets), the frame's centre and the turned image's centre (u, v)."""

    image: np.ndarray
    rotation: np.ndarray
    centre: tuple[float, float]
    turned_centre: tuple[float, float]

    def points(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Frame pixels (u, v) in the turned image."""
        du, dv = np.asarray(u, np.float64) - self.centre[0], np.asarray(v, np.float64) - self.centre[1]
        (a, b), (c, d) = self.rotation
        return a * du + b * dv + self.turned_centre[0], c * du + d * dv + self.turned_centre[1]

    def back(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Turned-image pixels (u, v) in the frame."""
        du = np.asarray(u, np.float64) - self.turned_centre[0]
        dv = np.asarray(v, np.float64) - self.turned_centre[1]
        (a, b), (c, d) = self.rotation  # the inverse of a rotation is its transpose
        return a * du + c * dv + self.centre[0], b * du + d * dv + self.centre[1]


def turn_to_light(image: np.ndarray, light_rad: float) -> Turned:
    """``image`` turned about its centre so that the light's travel direction ``light_rad`` (image azimuth,
    atan2(dv, du), v down) points along +u; bilinear, NaN where the turned image lies outside the frame."""
    if not math.isfinite(light_rad):
        raise ValueError(f"light direction {light_rad!r} is not a finite angle")
    a = np.asarray(image, dtype=np.float32)
    h, w = a.shape
    c, s = math.cos(-light_rad), math.sin(-light_rad)
    rot = np.array([[c, -s], [s, c]])
    big_h, big_w = turned_shape(a.shape, light_rad)
    centre, turned_centre = (w / 2.0, h / 2.0), (big_w / 2.0, big_h / 2.0)
    # continuous: p' = rot (p - centre) + turned_centre; OpenCV's pixel centres are p - 0.5
    shift = turned_centre - rot @ np.array(centre) + rot @ np.array([0.5, 0.5]) - 0.5
    m = np.column_stack([rot, shift]).astype(np.float64)
    out = cv2.warpAffine(np.nan_to_num(a), m, (big_w, big_h), flags=cv2.INTER_LINEAR, borderValue=0.0)
    inside = cv2.warpAffine(np.ones_like(a), m, (big_w, big_h), flags=cv2.INTER_LINEAR, borderValue=0.0)
    out[(inside < INSIDE_WEIGHT) | ~np.isfinite(out)] = np.nan
    return Turned(out, rot, centre, turned_centre)


def turned_shape(shape, light_rad: float) -> tuple[int, int]:
    """(rows, columns) of :func:`turn_to_light`'s image of a frame of ``shape``, without the frame: the
    bounding box of the turned frame (a training set read from disk plans its crops before reading)."""
    h, w = (int(n) for n in shape)
    c, s = abs(math.cos(light_rad)), abs(math.sin(light_rad))
    return int(math.ceil(w * s + h * c - 1e-9)), int(math.ceil(w * c + h * s - 1e-9))
