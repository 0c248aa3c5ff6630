"""``crater-synth bench --part detect``: what ``crater-synth detect`` costs a user (issue targets: <= 1 s per
1024 x 1024 frame, <= 4 s per 2592 x 1944 frame on 2 cores, peak RSS <= 2 GB).

The frames are synthetic (:func:`crater_frame`: Hapke-shaded bowls with cast shadows on flat ground, 8-bit,
seeded), never real images, so no held-out pixel is read and nothing is tuned on a test image. Every run is
the command itself in a child process with the default detector, timed from outside (wall, start-up
included) and from inside (the ``seconds`` of its summary: reading, detection and writing of the image),
its peak RSS the child's own (``os.wait4``). The folder mode (one process for ``FOLDER_FRAMES`` frames) is
set against the baseline a user would otherwise run: the command once per image, in the same run.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from crater_synth.navigation.detect_cmd import DEFAULT_DETECTOR, SUMMARY_NAME
from crater_synth.navigation.detectors.template import crater_heights, shade_heights

FRAMES = {"1024x1024": (1024, 1024), "2592x1944": (1944, 2592)}  # name -> (height, width)
OTHER_DETECTORS = ("classical", "template", "learned")
# The learned detector's inference views (docs/navigation/detectors.md): off by default for their cost,
# measured here at every frame size.
VIEWS = ("nav.detector.tta=4", "nav.detector.half_octaves=true")
FOLDER_FRAMES = 4  # 1024 x 1024 frames of the folder-mode comparison
CELL_PX = 128  # one crater per cell of the frame's grid
SUN_EL_DEG = 12.0
LIGHT_DEG = 35.0


def crater_frame(height: int, width: int, seed: int) -> np.ndarray:
    """An 8-bit nadir frame: one bowl crater (radius 0.08-0.35 of the cell: 10-45 px, jittered) per
    :data:`CELL_PX` cell, each shaded on its own patch (cast shadows included) and pasted on flat ground,
    plus mild noise."""
    rng = np.random.default_rng(seed)
    flat = float(shade_heights(np.zeros((3, 3)), math.radians(LIGHT_DEG), SUN_EL_DEG)[1, 1])
    frame = np.full((height, width), flat)
    for top in range(0, height - CELL_PX + 1, CELL_PX):
        for left in range(0, width - CELL_PX + 1, CELL_PX):
            r = float(rng.uniform(0.08, 0.35)) * CELL_PX
            cu, cv = rng.uniform(r + 0.06 * CELL_PX, CELL_PX - r - 0.06 * CELL_PX, 2)
            vv, uu = np.mgrid[0:CELL_PX, 0:CELL_PX] + 0.5
            z = crater_heights(np.hypot(uu - cu, vv - cv) / r, 0.2) * r
            frame[top : top + CELL_PX, left : left + CELL_PX] = shade_heights(z, math.radians(LIGHT_DEG), SUN_EL_DEG)
    frame = frame / frame.max() * 230.0 + 15.0 + rng.normal(0.0, 2.0, frame.shape)
    return np.clip(frame, 0, 255).astype(np.uint8)


def run_detect(log: Path, *args) -> dict:
    """``crater-synth detect ARGS`` in a child process (:func:`run_command`)."""
    return run_command(log, "detect", *args)


def run_command(log: Path, command: str, *args) -> dict:
    """``crater-synth COMMAND ARGS`` in a child process: wall seconds, peak RSS (MB) and its stdout's last line
    (stdout and stderr go to files ``log``.out/.err, so nothing blocks while the parent waits in wait4)."""
    cmd = [sys.executable, "-c", "import sys; from crater_synth.cli import main; sys.exit(main())", command]
    out, err = log.with_suffix(".out"), log.with_suffix(".err")
    t0 = time.perf_counter()
    with open(out, "wb") as fo, open(err, "wb") as fe:
        proc = subprocess.Popen([*cmd, *map(str, args)], stdout=fo, stderr=fe)
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        text = err.read_text(encoding="utf-8", errors="replace").strip()
        raise RuntimeError(f"{command} {' '.join(map(str, args))}: {text.splitlines()[-1] if text else status}")
    lines = out.read_text(encoding="utf-8").strip().splitlines()
    return {"wall_s": wall, "peak_rss_mb": round(usage.ru_maxrss / 1024.0, 1), "last": lines[-1] if lines else ""}


def bench_detect(work: Path) -> dict:
    """Seconds per frame and peak RSS at each size of :data:`FRAMES`; folder mode against one process per
    image on :data:`FOLDER_FRAMES` frames of 1024 x 1024."""
    work.mkdir(parents=True, exist_ok=True)
    # The load the machine carried before the run: the timings are this run's, on a machine maybe shared.
    load = [round(x, 2) for x in os.getloadavg()]
    result: dict = {"detector": DEFAULT_DETECTOR, "threads": os.cpu_count(), "load_average": load, "frames": {}}
    for i, (name, (h, w)) in enumerate(FRAMES.items()):
        image = work / f"frame_{name}.png"
        cv2.imwrite(str(image), crater_frame(h, w, i))
        run = run_detect(work / f"log_{name}", image, "--out", work / f"frame_{name}.geojson")
        summary = json.loads(run["last"])
        result["frames"][name] = {
            "seconds_per_frame": round(summary["seconds"], 3),  # inside the command: read, detect, write
            "wall_s": round(run["wall_s"], 2),  # the whole command, start-up included
            "peak_rss_mb": run["peak_rss_mb"],
            "craters": summary["craters"],
        }
    # The other detectors on the first frame, for reference (the command's time inside, per frame).
    first = work / f"frame_{next(iter(FRAMES))}.png"
    result["other_detectors"] = {
        name: json.loads(
            run_detect(work / f"log_{name}", first, "--out", work / f"{name}.csv", "--detector", name)["last"]
        )["seconds"]
        for name in OTHER_DETECTORS
    }
    result["views"] = {
        "overrides": list(VIEWS),
        "seconds_per_frame": {
            name: json.loads(
                run_detect(
                    work / f"log_views_{name}", work / f"frame_{name}.png", "--out", work / f"views_{name}.csv", *VIEWS
                )["last"]
            )["seconds"]
            for name in FRAMES
        },
    }
    folder = work / "folder"
    folder.mkdir(exist_ok=True)
    images = []
    for k in range(FOLDER_FRAMES):
        images.append(folder / f"frame_{k}.png")
        cv2.imwrite(str(images[-1]), crater_frame(1024, 1024, 100 + k))
    one = run_detect(work / "log_folder", folder, "--out", work / "folder_out")
    per_image = [run_detect(work / f"log_{p.stem}", p, "--out", work / f"single_{p.stem}.geojson") for p in images]
    baseline_s = sum(r["wall_s"] for r in per_image)
    summary = json.loads((work / "folder_out" / SUMMARY_NAME).read_text())
    result["folder"] = {
        "frames": FOLDER_FRAMES,
        "one_process_s": round(one["wall_s"], 2),
        "one_process_per_image_s": round(one["wall_s"] / FOLDER_FRAMES, 3),
        "inside_per_image_s": round(summary["seconds"] / FOLDER_FRAMES, 3),
        "peak_rss_mb": one["peak_rss_mb"],
        "process_per_image_s": round(baseline_s, 2),
        "speedup": round(baseline_s / one["wall_s"], 2),
    }
    return result
