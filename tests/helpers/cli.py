"""Helpers for the dataset tests: tiny render settings, a `crater-synth` runner, and dataset comparisons."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
# One render in ~0.05 s on 2 cores: a 48^2 near mesh, a coarse 60 km far field, no sub-DEM detail,
# 1 sample per pixel, 32 px crops, 128 px shadow maps. Later overrides of the same key win.
TINY = (
    "crater=shackleton",
    "sweep=smoke",
    "terrain.near_vertices=48",
    "terrain.far_radius_km=60",
    "terrain.far_spacing_km=6",
    "terrain.detail.enabled=false",
    "render.samples=1",
    "render.shadow_map_px=128",
    "render.roi_min_px=32",
    "render.workers=1",
)

# Training on the toy set (train/toydata.py) in seconds: 64 px inputs, one epoch, few HOG images, one thread.
QUICK_TRAIN = (
    "model.input_size=64",
    "train.batch_size=16",
    "train.max_epochs=1",
    "train.hog.max_train_images=50",
    "realset.per_crater=3",
    "train.num_threads=1",
    "train.progress=false",
)

# The smoke sweep with two camera elevations: 1 x 2 x 2 x 2 = 8 renders.
EIGHT = ("sweep.cam_elevation.count=2",)


# A nav-frames trajectory frame at tiny settings (64 px, fast mode, one sample, no sub-DEM detail): seconds.
TINY_NAV = (
    "trajectory=descent_ridge",
    "trajectory.width_px=64",
    "terrain.near_vertices=64",
    "terrain.far_spacing_km=8",
    "terrain.detail.enabled=false",
    "render.samples=1",
    "render.shadow_map_px=64",
    "render.workers=1",
    "render.mode=fast",
)


def run_nav_frames(data_dir, out, frames: str, *overrides, timeout: float = 240) -> subprocess.CompletedProcess:
    """`crater-synth nav-frames` with :data:`TINY_NAV` (later ``overrides`` win) for the frames ``frames``
    ("0,1")."""
    return run_cli(
        "nav-frames", *TINY_NAV, f"data_dir={data_dir}", *overrides, "--out", out, "--frames", frames, timeout=timeout
    )


def cli_command() -> list[str]:
    exe = Path(sys.executable).with_name("crater-synth")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "crater_synth.cli"]


def run_cli(*args, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([*cli_command(), *map(str, args)], capture_output=True, text=True, timeout=timeout, cwd=REPO)


def start_dataset(out, data_dir, *overrides) -> subprocess.Popen:
    """`crater-synth dataset` with :data:`TINY` in the background, in its own session (signals sent to
    the test runner do not reach it)."""
    return subprocess.Popen(
        [*cli_command(), "dataset", *TINY, f"data_dir={data_dir}", f"out_dir={out}", *overrides],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        start_new_session=True,
    )


def dataset_workers(out) -> list[int]:
    """Live (not zombie) Blender worker processes of the dataset ``out`` (their job files are under
    out/.jobs)."""
    needles = ("blender_gen.worker", str(Path(out) / ".jobs"))
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            cmd = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z" and all(n in cmd for n in needles):
            found.append(int(entry))
    return found


def summary(proc: subprocess.CompletedProcess) -> dict:
    """The JSON summary line `crater-synth dataset` prints last on stdout."""
    return json.loads(proc.stdout.strip().splitlines()[-1])


def exr_files(dataset_dir) -> list[Path]:
    """The dataset's EXRs (not the hidden temp files of an interrupted write)."""
    return sorted(p for p in Path(dataset_dir).glob("*/*.exr") if not p.name.startswith("."))


def assert_same_dataset(a, b) -> None:
    """Byte-identical manifests and EXRs."""
    a, b = Path(a), Path(b)
    assert (a / "manifest.jsonl").read_bytes() == (b / "manifest.jsonl").read_bytes()
    fa, fb = exr_files(a), exr_files(b)
    assert [p.relative_to(a) for p in fa] == [p.relative_to(b) for p in fb]
    for x, y in zip(fa, fb):
        assert x.read_bytes() == y.read_bytes(), x.relative_to(a)
