"""Synthetic landmark maps and the detections of a frame over them, for the lost-in-space tests."""

from __future__ import annotations

import math
from types import SimpleNamespace

from crater_synth.navigation.detectors.classical import Detection

PIXEL_M = 400.0
SHAPE = (512, 512)


def lis_map(rng, n=800, half_km=500.0):
    xy = rng.uniform(-half_km, half_km, (n, 2)) * 1000.0
    d = 10.0 + rng.pareto(1.8, n) * 8.0
    return [SimpleNamespace(x_m=float(x), y_m=float(y), diameter_km=float(min(k, 120.0))) for (x, y), k in zip(xy, d)]


def lis_frame(landmarks, centre_xy, heading_deg, rng, keep=0.6, clutter=25, noise_px=1.0):
    """Detections of the landmarks inside a frame whose pixel -> map similarity has the given centre and
    heading (pixel size PIXEL_M), a random subset kept, with centre and radius noise and clutter."""
    h, w = SHAPE
    a = PIXEL_M * complex(math.cos(math.radians(heading_deg)), math.sin(math.radians(heading_deg)))
    b = complex(*centre_xy) - a * (w / 2.0 - 1j * h / 2.0)
    dets = []
    for lm in landmarks:
        z = (complex(lm.x_m, lm.y_m) - b) / a
        u, v = z.real, -z.imag
        r = lm.diameter_km * 500.0 / PIXEL_M
        if 0 <= u < w and 0 <= v < h and rng.random() < keep:
            u, v = u + rng.normal(0, noise_px), v + rng.normal(0, noise_px)
            dets.append(Detection(u, v, r * rng.uniform(0.9, 1.1), 1.0))
    for _ in range(clutter):
        dets.append(Detection(rng.uniform(0, w), rng.uniform(0, h), rng.uniform(9, 60), 0.5))
    rng.shuffle(dets)
    return dets
