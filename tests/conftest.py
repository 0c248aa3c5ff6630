"""Shared helpers for the dataset tests (test_distributed, test_faults, test_determinism,
test_bad_config): tiny render settings and a `crater-synth` runner. Nothing here is autouse."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
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


@pytest.fixture(scope="session")
def tiny_data_dir(tmp_path_factory) -> Path:
    """Terrain patches of the tiny settings, built once per session."""
    return tmp_path_factory.mktemp("crater_data")


@pytest.fixture(scope="session")
def tiny_dataset(tiny_data_dir):
    """``tiny_dataset(out_dir, *overrides, check=True)``: `crater-synth dataset` with :data:`TINY`."""

    def run(out_dir, *overrides, check: bool = True, timeout: float = 300) -> subprocess.CompletedProcess:
        proc = run_cli("dataset", *TINY, f"data_dir={tiny_data_dir}", f"out_dir={out_dir}", *overrides, timeout=timeout)
        if check:
            assert proc.returncode == 0, proc.stderr[-4000:]
        return proc

    return run


# Set (to 1) where a Blender binary must be present, as in CI (.ci/run): its tests then fail instead of skipping.
REQUIRE_BLENDER_ENV = "CRATER_SYNTH_REQUIRE_BLENDER"


@pytest.fixture(scope="session")
def blender_exe() -> str:
    """The `blender` binary on PATH, checked to be a supported version (crater_synth.dataset.dispatch);
    skips the test when there is none (fails instead with CRATER_SYNTH_REQUIRE_BLENDER=1)."""
    import shutil

    from crater_synth.dataset.dispatch import blender_binary
    from crater_synth.errors import RenderError

    required = os.environ.get(REQUIRE_BLENDER_ENV, "") not in ("", "0")
    exe = shutil.which("blender")
    if exe is None:
        reason = "no `blender` binary on PATH (`make test-deps` installs Debian's Blender when run as root)"
    else:
        try:
            return blender_binary(exe)[0]
        except RenderError as exc:
            reason = str(exc)
    if required:
        pytest.fail(f"{reason} ({REQUIRE_BLENDER_ENV} is set)")
    pytest.skip(reason)
