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
    return rim_circles(np.asarray(centre)[None], np.asarray(normal)[None], np.array([radius_m]), n)[0]


def rim_circles(centres, normals, radii, n: int = RIM_POINTS) -> np.ndarray:
    """:func:`rim_circle` of k circles at once ((k, 3) centres and normals, (k,) radii): (k, n, 3)."""
    e1, e2 = plane_basis(normals)
    theta = np.arange(n) * 2.0 * np.pi / n
    r = np.asarray(radii, dtype=float)[:, None, None]
    ring = np.cos(theta)[None, :, None] * e1[:, None, :] + np.sin(theta)[None, :, None] * e2[:, None, :]
    return np.asarray(centres, dtype=float)[:, None, :] + r * ring


def _inside(shape, rim_uv: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    h, w = shape
    inside = (rim_uv[..., 0] >= 0) & (rim_uv[..., 0] < w) & (rim_uv[..., 1] >= 0) & (rim_uv[..., 1] < h)
    return inside if valid is None else inside & valid


def _masked_means(channel: np.ndarray, rim_uv: np.ndarray, inside: np.ndarray, test=None) -> np.ndarray:
    """Per rim (rows of ``rim_uv`` (k, n, 2)), the mean of ``channel`` (or of ``test(values)``) at its points
    ``inside``; NaN for a rim with less than :data:`MIN_RIM_INSIDE` of its points inside."""
    h, w = channel.shape
    v = np.clip(np.floor(rim_uv[..., 1]), 0, h - 1).astype(int)
    u = np.clip(np.floor(rim_uv[..., 0]), 0, w - 1).astype(int)
    values = channel[v, u]
    values = values if test is None else test(values)
    count = inside.sum(axis=1)
    means = np.where(inside, values, 0.0).sum(axis=1) / np.maximum(count, 1)
    return np.where(inside.mean(axis=1) < MIN_RIM_INSIDE, np.nan, means)


def lit_rim_fraction(lit: np.ndarray, ellipse: Ellipse) -> float | None:
    """Mean of the ``lit`` channel (illuminated fraction of the solar disc) at :data:`RIM_POINTS` points
    of the projected rim inside the frame; None when less than :data:`MIN_RIM_INSIDE` of it is inside."""
    f = float(lit_rim_fractions(lit, ellipse.points(RIM_POINTS)[None])[0])
    return None if np.isnan(f) else f


def lit_rim_fractions(lit: np.ndarray, rim_uv: np.ndarray) -> np.ndarray:
    """:func:`lit_rim_fraction` of k projected rims at once, given as their (k, n, 2) rim points; NaN for None."""
    return _masked_means(lit, rim_uv, _inside(lit.shape, rim_uv, None))


def hidden_rim_fraction(depth: np.ndarray, rim_uv: np.ndarray, rim_depth: np.ndarray, margin_m: float):
    """Share of the rim points inside the frame that relief nearer to the camera hides: the rendered
    ``depth`` (distance along the view axis) at the point's pixel is nearer than the point's own
    ``rim_depth`` by more than ``margin_m``. None when less than :data:`MIN_RIM_INSIDE` of the rim is in
    the frame."""
    f = float(hidden_rim_fractions(depth, rim_uv[None], rim_depth[None], np.array([margin_m]))[0])
    return None if np.isnan(f) else f


def hidden_rim_fractions(depth: np.ndarray, rim_uv: np.ndarray, rim_depth: np.ndarray, margins: np.ndarray):
    """:func:`hidden_rim_fraction` of k rims at once: (k, n, 2) points, (k, n) depths, (k,) margins; NaN for None."""
    inside = _inside(depth.shape, rim_uv, rim_depth > 0)
    limit = rim_depth - np.asarray(margins, dtype=float)[:, None]
    return _masked_means(depth, rim_uv, inside, lambda d: d < limit)
