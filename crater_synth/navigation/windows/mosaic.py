"""Real evaluation frames: windows of the LROC WAC polar mosaic treated as nadir frames.

Split rule (fixed before any evaluation, docs/navigation/protocol.md): the mosaic plane is cut into eight
45-degree longitude sectors about the pole, sector k = [45 k, 45 (k + 1)) deg east. Even sectors
(0-45, 90-135, 180-225, 270-315 E) are **validation**, odd sectors **test**. A window belongs to a
sector only when its whole footprint lies inside it, so validation and test windows never share a
pixel. Each of the mosaic's four quadrants (0-90, 90-180, ... E, each imaged under its own Sun, meeting
in seams along the 0/90/180/270 E meridians) holds one validation and one test sector, so both splits
see the same four illuminations.

North: the north mosaic (``lroc_wac_north``) is also four quadrants (0-90, 90-180, ... E) meeting at
the pole, and its windows are cut by the same geometry (512 px, stride 64, wholly inside one 45-degree
sector, so off the seams and off the polar cap). **Every north window is test** (split "test" whatever
its sector): no setting is chosen on the north; it is the held-out pole of the light-model choice made
on the south mosaic (docs/navigation/protocol.md).

The polar seams are excluded by the same rule: a window lying wholly inside one 45-degree sector
crosses no quadrant boundary (those are sector boundaries), and it is at least ~250 km from the pole,
away from the permanently shadowed, mixed-Sun cap where the quadrants meet.

Camera model of a mosaic window: the mosaic is an orthoimage in the polar stereographic projection,
so a window is an *orthographic nadir* frame of that map plane: pixel (u, v) (right, down, origin at
the window's top-left corner) sees map point x = left + (u) p, y = top - (v) p, p = 400 m/px (times
the projection's scale factor, <= 3 % here). The truth camera position is the map point under the
window centre.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from crater_synth.navigation.georef import Frame, FrameError, Georef, stereo_inverse
from data_manifest.products import get_product

SECTOR_DEG = 45.0
SPLIT_OF_SECTOR = {k: ("validation" if k % 2 == 0 else "test") for k in range(8)}  # south mosaic
# The split of a window by pole and sector: the south alternates, the north is test only.
SPLITS = {"south": SPLIT_OF_SECTOR, "north": {k: "test" for k in range(8)}}
WINDOW_PX = 512
STRIDE_PX = 64  # overlapping windows: more frames, correlated (every report says so)
MOSAIC_PRODUCTS = {"south": "lroc_wac_south", "north": "lroc_wac_north"}


def sector_of(x, y, pole: str = "south") -> np.ndarray:
    """45-degree longitude sector index (0..7) of map points of ``pole``'s polar stereographic plane
    (lon = atan2(x, y) at the south pole, atan2(x, -y) at the north: the core's projection)."""
    _, lon = stereo_inverse(np.asarray(x, dtype=float), np.asarray(y, dtype=float), pole)
    return np.floor((np.asarray(lon) % 360.0) / SECTOR_DEG).astype(int) % 8


@lru_cache(maxsize=2)
def load_mosaic_image(pole: str = "south"):
    """(image uint8 (H, W), half-extent m, pixel m, product id) of the pole's embedded WAC mosaic, read
    and checksummed through the registry (as the real test set reads it)."""
    from train.realset import embedded_product_path, read_gray

    product = MOSAIC_PRODUCTS[pole]
    p = get_product(product)
    path = embedded_product_path(product)  # verifies the sha256
    img = read_gray(path, keep_uint8=True)
    left, _, right, _ = (float(v) for v in p["extent_m"])
    return img, 0.5 * (right - left), float(p["pixel_size_m"]), product


def plan_windows(
    pole: str = "south", size: int = WINDOW_PX, stride: int = STRIDE_PX
) -> list[tuple[str, str, int, int, int]]:
    """Every window of the split rule: (id, split, sector, u0, v0), deterministic. South: even sectors
    validation, odd test; north: every window test (module docstring)."""
    if pole not in SPLITS:
        raise FrameError(f"pole {pole!r}: real evaluation windows exist for {', '.join(SPLITS)}")
    img, extent, pixel, _ = load_mosaic_image(pole)
    n = img.shape[0]
    out = []
    for v0 in range(0, n - size + 1, stride):
        for u0 in range(0, n - size + 1, stride):
            # The wedge is convex (45 deg < 180 deg), so the square is inside it when its corners are.
            us = np.array([u0, u0 + size, u0, u0 + size], dtype=float)
            vs = np.array([v0, v0, v0 + size, v0 + size], dtype=float)
            x, y = us * pixel - extent, extent - vs * pixel
            s = sector_of(x, y, pole)
            if np.all(s == s[0]) and np.all(np.hypot(x, y) > 0):
                k = int(s[0])
                out.append((f"{pole[0].upper()}{k}_{u0:04d}_{v0:04d}", SPLITS[pole][k], k, u0, v0))
    return out


def window_frame(pole: str, wid: str, split: str, sector: int, u0: int, v0: int, size: int = WINDOW_PX) -> Frame:
    img, extent, pixel, _ = load_mosaic_image(pole)
    geo = Georef(pole, -extent + u0 * pixel, extent - v0 * pixel, pixel)
    return Frame(wid, split, sector, np.ascontiguousarray(img[v0 : v0 + size, u0 : u0 + size]), geo)


def windows(
    split: str | None = None, pole: str = "south", size: int = WINDOW_PX, stride: int = STRIDE_PX
) -> list[Frame]:
    """The real evaluation frames of ``split`` (None: both)."""
    return [
        window_frame(pole, *w, size=size) for w in plan_windows(pole, size, stride) if split is None or w[1] == split
    ]
