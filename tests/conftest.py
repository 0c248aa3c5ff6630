"""Session fixtures shared by the dataset tests; the plain helpers live in tests/helpers/. Nothing here is
autouse."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

import crater_synth  # noqa: F401 - first: it sets the processes' one BLAS thread before numpy loads

from helpers.cli import TINY, run_cli


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
