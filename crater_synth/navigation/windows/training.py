"""Real mosaic windows as detector training records: the reference trained on real images.

The sim-to-real gap is measured as the ratio of two north-test F1 scores: the detector trained on
rendered frames only, and the same detector trained on **real** south WAC windows with the LU1319381
catalogue as labels. This module makes those real records, in the shape the training of
:mod:`..rendered.detector_train` reads (an image and a row whose ``circles`` are the labels' pixel circles).

- **Which windows**: the south mosaic's ``test`` split (odd sectors). Those sectors are spent as a test
  (docs/navigation/protocol.md), so they may train; the ``validation`` split (even sectors, no shared pixel)
  stays for choosing the reference's threshold, and the north windows for its one test. Every south window
  lies poleward of 60 degrees: no mid-latitude pixel is read.
- **Scale**: a window (400 m/px) is decimated to 800 m/px before its pyramid is built, because that is
  where the detector's search starts on a 400 m/px window, and because the catalogue lists craters from
  8 km only: at 400 m/px the network's rim band (6-12 px) holds 4.8-9.6 km craters, mostly unlisted, which
  would be trained as background.
- **Labels**: every catalogued crater whose centre lies in the window, a circle of radius D / 2; none is
  hidden (the catalogue says nothing of lighting).
"""

from __future__ import annotations

import numpy as np

from crater_synth.navigation.map.check import LU_SOURCE, catalogue_craters
from crater_synth.navigation.windows.mosaic import MOSAIC_PRODUCTS, SPLITS, windows

REAL_TRAIN_POLE = "south"  # the north windows are the test; they never train
REAL_TRAIN_SPLIT = "test"  # the south's spent test sectors; "validation" is kept for choosing
REAL_DECIMATION = 2  # 400 -> 800 m/px: the detector's first searched level (module docstring)


def window_record(frame, listed, decimation: int = REAL_DECIMATION) -> tuple[np.ndarray, dict]:
    """(image, row) of one mosaic window: the window decimated by ``decimation`` (area mean) and the circles
    of the catalogued craters ``listed`` whose centre lies in it, in the decimated pixels."""
    from train.crater_detector import decimate2

    image = np.asarray(frame.image, np.float32)
    for _ in range(int(np.log2(decimation))):
        image = decimate2(image)
    xs = np.array([c.x_m for c in listed], float)
    ys = np.array([c.y_m for c in listed], float)
    d = np.array([c.diameter_km for c in listed], float)
    u, v = frame.georef.xy_to_uv(xs, ys)
    h, w = frame.image.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    pixel_m = frame.georef.pixel_m * decimation
    circles = (
        u[inside] / decimation,
        v[inside] / decimation,
        d[inside] * 500.0 / pixel_m,
        d[inside],
        np.zeros(int(inside.sum()), bool),
    )
    row = {"index": frame.id, "rel_path": frame.id, "ground_sample_m": pixel_m, "circles": circles}
    return image, row


def real_window_records(pole: str = REAL_TRAIN_POLE, split: str = REAL_TRAIN_SPLIT) -> tuple[list, dict]:
    """(records, what they are) of every ``split`` window of ``pole``'s mosaic with its catalogue labels."""
    listed = catalogue_craters(pole)
    frames = windows(split, pole)
    what = {
        "kind": "real",
        "trained_on": (
            f"real LROC WAC {pole} mosaic windows ({MOSAIC_PRODUCTS[pole]}, {split} split: sectors "
            f"{sorted(k for k, s in SPLITS[pole].items() if s == split)}), LU1319381 catalogue labels "
            f"({LU_SOURCE}); a reference, not a synthetic-only model"
        ),
        "windows": len(frames),
        "decimation": REAL_DECIMATION,
    }
    return [window_record(f, listed) for f in frames], what
