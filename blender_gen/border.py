"""The render border of a crop, as Blender and Cycles will read it back (no bpy: unit-testable).

Blender stores ``render.border_*`` as float32 fractions of the frame and turns them back into pixels
by truncation (``disprect.xmin = (int)(border.xmin * winx)``; Cycles' buffer parameters do the same).
A border at an exact pixel edge, ``u0 / W``, can therefore come back as ``u0 - 1``
(``int(float32(113 / 437) * 437) == 112``): the EXR is one pixel wider or taller than the crop and,
when the first row or column moves, its content is shifted by a pixel. A value strictly inside the
pixel, ``(u0 + 0.5) / W``, truncates to ``u0`` whatever the rounding; ``1.0`` is kept exact for the
frame's far edge.
"""

from __future__ import annotations

import numpy as np


def border_fractions(crop, frame_width: int) -> tuple[float, float, float, float]:
    """(min_x, max_x, min_y, max_y) for ``render.border_*`` that select exactly the pixels
    u0 <= u < u1, v0 <= v < v1 (u right, v down from the top-left corner) of a square
    ``frame_width`` frame. Blender's border y runs up from the bottom edge."""
    u0, v0, u1, v1 = (int(c) for c in crop)
    w = int(frame_width)

    def inside(pixel_edge: int) -> float:
        return 1.0 if pixel_edge >= w else (pixel_edge + 0.5) / w

    return inside(u0), inside(u1), inside(w - v1), inside(w - v0)


def pixels_from_border(fraction: float, frame_width: int) -> int:
    """The pixel edge Blender derives from a border fraction: float32 product, truncated."""
    return int(np.float32(fraction) * np.float32(frame_width))
