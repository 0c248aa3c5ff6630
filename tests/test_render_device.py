"""``render.device``: a Cycles GPU backend that is absent is one error line, never a silent CPU render."""

from __future__ import annotations

import shutil

import pytest

from crater_core.settings import RENDER_DEVICES

from helpers.cli import TINY, run_cli


def test_nonsense_device_is_refused_by_the_settings(tmp_path):
    r = run_cli("config", "render.device=GPU")
    assert r.returncode != 0
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and "render.device" in err[0] and "GPU" in err[0], r.stderr


def test_every_backend_is_a_cycles_device_type():
    # Cycles' compute_device_type enum (CPU is the scene's own device); a name outside it would fail in the worker.
    assert RENDER_DEVICES[0] == "CPU"
    assert set(RENDER_DEVICES[1:]) == {"CUDA", "OPTIX", "HIP", "ONEAPI", "METAL"}


@pytest.mark.skipif(shutil.which("nvidia-smi") is not None, reason="a CUDA device may be here")
def test_absent_gpu_backend_is_one_error_and_no_render(tmp_path):
    out = tmp_path / "out"
    r = run_cli("dataset", *TINY, f"data_dir={tmp_path / 'data'}", f"out_dir={out}", "render.device=CUDA")
    assert r.returncode == 2, r.stdout + r.stderr
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "render.device=CUDA" in errors[0] and "no CUDA device" in errors[0], r.stderr
    assert not list(out.rglob("*.exr"))
    assert not (out / "manifest.jsonl").is_file() or (out / "manifest.jsonl").read_text() == ""
