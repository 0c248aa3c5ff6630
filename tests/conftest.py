"""Session fixtures shared by the dataset tests; the plain helpers live in tests/helpers/. Nothing here is
autouse."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

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
