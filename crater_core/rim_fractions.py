"""How much of a projected crater rim a rendered frame shows lit, and how much nearer relief hides.

Shared by every frame that labels craters with their rims (navigation frames' landmarks, detection frames'
procedural craters): the rim points are sampled at their pixels in the frame's ``lit`` and ``depth``
channels (crater_core/schema.py ``EXR_CHANNELS``). numpy only.
"""

from __future__ import annotations

import numpy as np

from crater_core.geometry import Ellipse, plane_basis

RIM_POINTS = 90  # points on a projected rim where the lit channel is sampled
MIN_RIM_INSIDE = 0.5  # fractions only when at least this share of the rim lies in the frame


def rim_circle(centre, normal, radius_m: float, n: int = RIM_POINTS) -> np.ndarray:
    """(n, 3) points of the 3-D circle of ``radius_m`` about ``centre`` in the plane with ``normal``
    (in-plane axes :func:`crater_core.geometry.plane_basis`, the same circle ``project_circle`` images)."""
    e1, e2 = plane_basis(normal)
    theta = np.arange(n) * 2.0 * np.pi / n
    return np.asarray(centre, dtype=float) + radius_m * (np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2)


def rim_pixels(shape, rim_uv: np.ndarray, valid: np.ndarray | None = None):
    """(mask of the rim points inside a frame of ``shape`` (and ``valid``), their pixel rows, their pixel
    columns), or None when less than :data:`MIN_RIM_INSIDE` of the rim is inside."""
    h, w = shape
    inside = (rim_uv[:, 0] >= 0) & (rim_uv[:, 0] < w) & (rim_uv[:, 1] >= 0) & (rim_uv[:, 1] < h)
    if valid is not None:
        inside &= valid
    if inside.mean() < MIN_RIM_INSIDE:
        return None
    return inside, np.floor(rim_uv[inside, 1]).astype(int), np.floor(rim_uv[inside, 0]).astype(int)


def lit_rim_fraction(lit: np.ndarray, ellipse: Ellipse) -> float | None:
    """Mean of the ``lit`` channel (illuminated fraction of the solar disc) at :data:`RIM_POINTS` points
    of the projected rim inside the frame; None when less than :data:`MIN_RIM_INSIDE` of it is inside."""
    px = rim_pixels(lit.shape, ellipse.points(RIM_POINTS))
    return None if px is None else float(np.mean(lit[px[1], px[2]]))


def hidden_rim_fraction(depth: np.ndarray, rim_uv: np.ndarray, rim_depth: np.ndarray, margin_m: float):
    """Share of the rim points inside the frame that relief nearer to the camera hides: the rendered
    ``depth`` (distance along the view axis) at the point's pixel is nearer than the point's own
    ``rim_depth`` by more than ``margin_m``. None when less than :data:`MIN_RIM_INSIDE` of the rim is in
    the frame."""
    px = rim_pixels(depth.shape, rim_uv, rim_depth > 0)
    if px is None:
        return None
    inside, v, u = px
    return float(np.mean(depth[v, u] < rim_depth[inside] - margin_m))
