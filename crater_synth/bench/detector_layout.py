"""``crater-synth bench --part detector-layout``: what the learned detector's network costs a training step and
a pyramid level in each memory layout and precision, on the same inputs in the same run.

- ``train_step``: one training step (forward, backward, AdamW) of :class:`train.crater_detector.CraterNet` on
  a batch the size the committed training draws (16 crops of 96 px), at width 16 (the committed models) and
  32, three ways: the standard layout in float32 (every model trained before
  ``nav.detector_train.channels_last``; the baseline), channels last in float32 (the default), and channels
  last with the bfloat16 forward pass (``nav.detector_train.precision=bf16``);
- ``level_output``: the committed model's maps on one 1024 x 1024 pyramid level (the largest ``detect`` runs
  on such a frame), the standard layout against channels last (as :func:`train.crater_detector.load_model`
  hands the model back), with the largest difference between their maps.

The network alone: a real training step also draws and augments its crops (~0.1 s on 2 cores,
``bench --part detector`` times the whole step). bfloat16 pays where the CPU has AVX-512 BF16 or AMX
(``cpu_bf16``, read from /proc/cpuinfo), and on GPUs.
"""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from crater_synth.navigation.detectors.learned import DEFAULT_MODEL
from train import crater_detector as cd
from train.crater_detector_inference import level_output
from train.detector_fit import autocast_forward

BATCH, CROP_PX = 16, 96  # nav.detector_train's batch and crop_px (configs/nav/detector_train/default.yaml)
LEVEL_PX = 1024
WAYS = (("nchw_fp32", False, "fp32"), ("nhwc_fp32", True, "fp32"), ("nhwc_bf16", True, "bf16"))


def _seconds(run, repeats: int) -> float:
    run()  # warm-up: oneDNN picks and caches its kernels on the first call
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def train_step_seconds(width: int, channels_last: bool, precision: str, repeats: int = 10) -> float:
    """Median seconds of one training step of a fresh width-``width`` network on a random batch."""
    torch.manual_seed(0)
    model = cd.CraterNet(width).to(memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    forward = autocast_forward(model, precision, "cpu")
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    x = torch.randn(BATCH, 1, CROP_PX, CROP_PX)

    def step():
        loss = forward(x).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()

    return _seconds(step, repeats)


def cpu_bf16() -> bool:
    """Whether this CPU has bfloat16 instructions (AVX-512 BF16 or AMX)."""
    try:
        flags = Path("/proc/cpuinfo").read_text(encoding="utf-8")
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def bench_detector_layout(repeats: int = 10) -> dict:
    """Seconds per training step and per 1024 x 1024 level in each layout and precision, with their ratios to
    the standard layout in float32."""
    torch.set_num_threads(os.cpu_count() or 1)
    steps = {}
    for width in (16, 32):
        base = None
        for name, channels_last, precision in WAYS:
            s = train_step_seconds(width, channels_last, precision, repeats)
            base = base or s
            steps[f"width{width}_{name}"] = {"s": round(s, 4), "speedup": round(base / s, 2)}
    image = np.random.default_rng(0).random((LEVEL_PX, LEVEL_PX)).astype(np.float32)
    maps, level = {}, {}
    for name, layout in (("nchw_fp32", torch.contiguous_format), ("nhwc_fp32", torch.channels_last)):
        model = cd.load_model(DEFAULT_MODEL)[0].to(memory_format=layout)
        level[name] = _seconds(lambda m=model: level_output(m, image), max(3, repeats // 3))
        maps[name] = level_output(model, image)
    return {
        "threads": torch.get_num_threads(),
        "cpu_bf16": cpu_bf16(),
        "batch": BATCH,
        "crop_px": CROP_PX,
        "train_step": steps,
        "level_output_1024": {
            "nchw_fp32_s": round(level["nchw_fp32"], 4),
            "nhwc_fp32_s": round(level["nhwc_fp32"], 4),
            "speedup": round(level["nchw_fp32"] / level["nhwc_fp32"], 2),
            "max_abs_map_difference": float(np.abs(maps["nchw_fp32"] - maps["nhwc_fp32"]).max()),
        },
    }
