"""Session fixtures shared by the dataset tests; the plain helpers live in tests/helpers/. Nothing here is
autouse."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

import crater_synth  # noqa: F401 - first: it sets the processes' one BLAS thread before numpy loads

from helpers.cli import EIGHT, TINY, run_cli


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


def _files(root: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``root`` with its size and modification time."""
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*") if p.is_file()}


def _shared_dataset(tmp_path_factory, tiny_dataset, n: int, *overrides):
    """A :data:`TINY` dataset of ``n`` renders, rendered once and shared read-only; fails the session's
    teardown if a test changed it (a test that damages a dataset works on a ``shutil.copytree`` copy)."""
    from helpers.cli import exr_files

    # Named "smoke": the export's default output beside it is "<name>-<format>" (tests/test_export.py).
    out = tmp_path_factory.mktemp("shared_dataset") / "smoke"
    tiny_dataset(out, *overrides)
    assert len(exr_files(out)) == n
    before = _files(out)
    yield out
    assert _files(out) == before, f"a test changed the shared dataset {out}: work on a copy"


@pytest.fixture(scope="session")
def tiny_smoke(tmp_path_factory, tiny_dataset):
    """The tiny smoke sweep (one crater, 4 renders), rendered once per session; read-only."""
    yield from _shared_dataset(tmp_path_factory, tiny_dataset, 4)


@pytest.fixture(scope="session")
def tiny_eight(tmp_path_factory, tiny_dataset):
    """The :data:`EIGHT` sweep in one process (render.workers=1, render.threads=0), rendered once per
    session; read-only."""
    yield from _shared_dataset(tmp_path_factory, tiny_dataset, 8, *EIGHT)


@pytest.fixture(scope="session")
def nav_data_dir(tmp_path_factory) -> Path:
    """A data_dir shared by the nav-frames runs: their terrain patches and horizon maps are cached there by
    content key, so each distinct terrain is built once per session."""
    return tmp_path_factory.mktemp("nav_data")


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
