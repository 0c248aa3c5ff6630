"""``crater-synth bench --part detector``: what training the learned crater detector costs.

Runs ``crater-synth nav-detector-train`` on the rendered survey (``data/detector_frames/south``; rendered
by ``crater-synth nav-detector-frames`` or ``make nav-detector``), or on another frames folder that command
takes (``bench --detector-frames DIR``: a detection set), in child processes: once untimed (the disk cache),
then for a few and for more steps, with the committed training settings otherwise, or those of
``--detector-train KEY=VALUE`` (``nav.detector_train.*``), on ``--detector-device`` (cpu or cuda). The
difference of the two wall times over the difference of their steps is the time per training step; what
is left of the shorter run is the fixed cost (reading the frames, building the targets, scoring the
hold-out tracks, saving). Peak RSS is each
child's own (``os.wait4``). The committed model's 2000 steps are extrapolated from both. Nothing is
compared with a baseline here: the classical and template detectors have no training.
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
import time
from pathlib import Path

# Two lengths of run: far enough apart that the per-step time dominates their difference.
SHORT_STEPS = 20
LONG_STEPS = 120


def _train(frames_dir: Path, out: Path, steps: int, device: str, overrides: tuple[str, ...]) -> dict:
    cmd = [
        sys.executable,
        "-c",
        "import sys; from crater_synth.cli import main; sys.exit(main())",
        "nav-detector-train",
        str(frames_dir),
        "--out",
        str(out),
        "--device",
        device,
        *overrides,
        f"nav.detector_train.steps={steps}",
    ]
    log = out.with_suffix(".log")
    t0 = time.perf_counter()
    with open(log, "wb") as err:  # a file, not a pipe: nothing blocks while the parent waits in wait4
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        text = log.read_text(encoding="utf-8", errors="replace").strip()
        last = text.splitlines()[-1] if text else proc.returncode
        raise RuntimeError(f"nav-detector-train nav.detector_train.steps={steps}: {last}")
    return {"steps": steps, "wall_s": round(wall, 2), "peak_rss_mb": round(usage.ru_maxrss / 1024.0, 1)}


def bench_detector_training(
    frames_dir: Path, work: Path, full_steps: int, device: str = "cpu", overrides: tuple[str, ...] = ()
) -> dict:
    """Seconds per training step, fixed seconds, peak RSS and the extrapolated time of ``full_steps``, on
    ``device`` with the training settings ``overrides`` (``nav.detector_train.KEY=VALUE``)."""
    work.mkdir(parents=True, exist_ok=True)
    run = functools.partial(_train, frames_dir, device=device, overrides=overrides)
    run(work / "warm.pt", 1)  # not timed: the first run reads the frames from a cold disk cache
    short = run(work / "short.pt", SHORT_STEPS)
    long = run(work / "long.pt", LONG_STEPS)
    per_step = (long["wall_s"] - short["wall_s"]) / (LONG_STEPS - SHORT_STEPS)
    if per_step <= 0.0:
        raise RuntimeError(f"detector bench: {LONG_STEPS} steps took no longer than {SHORT_STEPS} (timing noise)")
    fixed = max(0.0, short["wall_s"] - SHORT_STEPS * per_step)
    return {
        "frames_dir": str(frames_dir),
        "device": device,
        "gpu": _gpu_name(device),
        "overrides": list(overrides),
        "threads": os.cpu_count(),
        "runs": [short, long],
        "s_per_step": round(per_step, 4),
        "fixed_s": round(fixed, 1),
        "peak_rss_mb": max(short["peak_rss_mb"], long["peak_rss_mb"]),
        "full_steps": full_steps,
        "full_training_s": round(fixed + full_steps * per_step, 1),
    }


def _gpu_name(device: str) -> str | None:
    if device != "cuda":
        return None
    import torch

    return torch.cuda.get_device_name(0)
