"""The two Blender backends: the bpy module of this Python (the default) and a Blender binary
(``render.blender=PATH``: ``blender --background --python blender_gen/worker.py -- JOB``; Debian's 3.4 in
CI). The same tiny sweep through both, in fast and in direct mode, must give

- the same manifest labels (everything but the pixel statistics and the file checksum);
- the same geometry: depth within 1e-4 relative; unit normals within 1e-4 (relative to their unit
  length) plus the half-precision step they are stored with, at one sample per pixel (both Cycles
  versions then sample every pixel at the same point, so this compares the scenes, not the sampling
  patterns);
- I/F and lit within the fast-vs-direct tolerances (docs/renderer.md) at the documented 16 samples,
  where the two Cycles versions draw different sub-pixel and solar-disc samples;
- datasets that `crater-synth verify` accepts, whose EXR headers name the Blender that ran.

Skipped, with the reason, where no supported `blender` binary is installed (`make test-deps` installs
Debian's as root); .ci/run sets CRATER_SYNTH_REQUIRE_BLENDER=1 so that CI fails instead of skipping.
A missing or too-old binary is one clear error (tested without any Blender: a stand-in script).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from blender_gen import compat
from crater_core import exr, schema

from helpers import render as cr
from helpers.cli import TINY, run_cli

pytestmark = pytest.mark.integration  # end-to-end: make test-integration

MODES = ("fast", "direct")
# Manifest keys measured from the pixels (they differ as the pixels do), and the render identity, which
# holds render.blender on purpose: a dataset resumed with the other backend renders again rather than mix
# two renderers' pixels (docs/manifest.md). Every other key is a label.
PIXEL_KEYS = {"sha256", "mean_if", "lit_fraction"}
IDENTITY_KEYS = {"render_digest"}
GEOMETRY_RTOL = 1e-4
# At 16 samples the normal pass is a pixel average over each version's own sample pattern: the
# fast-vs-direct geometry tolerance (tests/test_render_physics.py) bounds the mean difference.
NORMAL_MEAN_TOL_16SPP = 2e-3


@pytest.fixture(scope="module")
def sweep(blender_exe, tiny_data_dir, tmp_path_factory):
    """``sweep(backend, mode, samples)``: the TINY sweep rendered once by ``backend`` ("module" or
    "binary"), each backend with its own horizon-map cache; returns the dataset directory."""
    root = tmp_path_factory.mktemp("backends")
    done: dict[tuple, Path] = {}

    def run(backend: str, mode: str, samples: int) -> Path:
        key = (backend, mode, samples)
        if key not in done:
            out = root / f"{backend}-{mode}-{samples}"
            extra = [f"render.blender={blender_exe}"] if backend == "binary" else []
            proc = run_cli(
                "dataset",
                *TINY,
                f"data_dir={tiny_data_dir}",
                f"out_dir={out}",
                f"render.mode={mode}",
                f"render.samples={samples}",
                f"render.horizon_cache_dir={root / (backend + '-horizon')}",
                *extra,
            )
            assert proc.returncode == 0, proc.stderr[-4000:]
            done[key] = out
        return done[key]

    return run


def _rows(dataset: Path) -> dict[str, dict]:
    return {r["path"]: r for r in schema.dataset_rows(dataset)}


def _pairs(sweep, mode: str, samples: int):
    a, b = sweep("module", mode, samples), sweep("binary", mode, samples)
    rows_a, rows_b = _rows(a), _rows(b)
    assert sorted(rows_a) == sorted(rows_b) and len(rows_a) == 4
    for path in sorted(rows_a):
        yield rows_a[path], rows_b[path], exr.read_exr(a / path), exr.read_exr(b / path)


@pytest.mark.parametrize("mode", MODES)
def test_same_labels(sweep, mode):
    for samples in (1, 16):
        for row_a, row_b, _, _ in _pairs(sweep, mode, samples):
            labels_a = {k: v for k, v in row_a.items() if k not in PIXEL_KEYS | IDENTITY_KEYS}
            labels_b = {k: v for k, v in row_b.items() if k not in PIXEL_KEYS | IDENTITY_KEYS}
            assert row_a["render_digest"] != row_b["render_digest"]  # the backend is part of the identity
            assert labels_a == labels_b, {
                k: (labels_a.get(k), labels_b.get(k)) for k in labels_a if labels_a.get(k) != labels_b.get(k)
            }


@pytest.mark.parametrize("mode", MODES)
def test_same_geometry(sweep, mode):
    for row, _, (a, _), (b, _) in _pairs(sweep, mode, 1):
        np.testing.assert_allclose(b["depth"], a["depth"], rtol=GEOMETRY_RTOL, err_msg=row["path"])
        for c in ("N.X", "N.Y", "N.Z"):
            # one step of the stored half (in the larger value's binade): two float32 values closer than
            # 1e-4 can round to neighbouring halves
            step = np.spacing(np.maximum(np.abs(a[c]), np.abs(b[c])).astype(np.float16)).astype(np.float32)
            # relative to the normal's length (1): a component near 0 has no relative precision of its own
            excess = np.abs(b[c] - a[c]) - (GEOMETRY_RTOL + step)
            assert excess.max() <= 0.0, (row["path"], c, float(excess.max()))
    for row, _, (a, _), (b, _) in _pairs(sweep, mode, 16):
        np.testing.assert_allclose(b["depth"], a["depth"], rtol=GEOMETRY_RTOL, err_msg=row["path"])
        for c in ("N.X", "N.Y", "N.Z"):
            assert np.abs(b[c] - a[c]).mean() < NORMAL_MEAN_TOL_16SPP, (row["path"], c)


@pytest.mark.parametrize("mode", MODES)
def test_radiance_within_fast_vs_direct_tolerances(sweep, mode):
    for row, _, (a, _), (b, _) in _pairs(sweep, mode, 16):
        ref, test = a["IF"], b["IF"]
        lit_px = ref[a["lit"] > 0.5]
        assert lit_px.size > 0.05 * ref.size, row["path"]
        med = float(np.median(lit_px))
        diff = np.abs(test - ref)
        assert abs(test.mean() / ref.mean() - 1.0) < cr.FAST_MEAN_TOL, (row["path"], test.mean(), ref.mean())
        assert diff.mean() / med < cr.FAST_MAD_TOL, (row["path"], diff.mean() / med)
        assert (diff > 0.1 * med).mean() < cr.FAST_OUTLIER_TOL, row["path"]
        assert np.abs(a["lit"] - b["lit"]).mean() < cr.LIT_MAD_TOL, row["path"]


@pytest.mark.parametrize("mode", MODES)
def test_verify_passes_and_headers_name_the_blender(sweep, blender_exe, mode):
    from crater_synth.dataset.dispatch import blender_binary

    version = blender_binary(blender_exe)[1]
    out = sweep("binary", mode, 1)
    proc = run_cli("verify", out)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for _, _, (_, header_a), (_, header_b) in _pairs(sweep, mode, 1):
        assert header_b["crater_synth:blender"] == version
        assert header_a["crater_synth:blender"] != ""  # the bpy module's version
        assert "blender" not in header_b["crater_synth:render"]  # the binary's path is not a render setting


# ------------------------------------------------------------------------------------------------
# A missing or too-old binary: one clear line, no worker started (no Blender needed)
# ------------------------------------------------------------------------------------------------
def _error_lines(proc) -> list[str]:
    return [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]


def test_missing_blender_binary_is_one_clear_error(tmp_path, tiny_data_dir):
    missing = tmp_path / "no-blender"
    proc = run_cli(
        "dataset", *TINY, f"data_dir={tiny_data_dir}", f"out_dir={tmp_path / 'out'}", f"render.blender={missing}"
    )
    assert proc.returncode == 2, proc.stderr
    (line,) = _error_lines(proc)
    assert f"render.blender={missing}: no such file" in line and "3.4 or newer" in line, line
    assert not list((tmp_path / "out").rglob("*.exr"))


def test_too_old_blender_binary_is_one_clear_error(tmp_path, tiny_data_dir):
    old = tmp_path / "blender"
    old.write_text('#!/bin/sh\necho "Blender 2.93.18"\necho "\tbuild date: 2023-05-01"\n')
    old.chmod(0o755)
    proc = run_cli(
        "dataset", *TINY, f"data_dir={tiny_data_dir}", f"out_dir={tmp_path / 'out'}", f"render.blender={old}"
    )
    assert proc.returncode == 2, proc.stderr
    (line,) = _error_lines(proc)
    assert "Blender 2.93.18, too old" in line and "supported: Blender 3.4 or newer" in line, line
    assert "3.4.1" in line and "5.0.1" in line  # the versions actually tested
    assert not list((tmp_path / "out").rglob("*.exr")) and not list((tmp_path / "out").rglob("*.json"))


def test_version_parsing_and_limits():
    assert compat.parse_version("Blender 3.4.1\n\tbuild date: 2023") == (3, 4, 1)
    assert compat.parse_version("5.0.1") == (5, 0, 1)
    assert compat.parse_version("Blender 4.2") == (4, 2)
    assert compat.parse_version("no version here") is None
    assert compat.version_problem((3, 4, 1), "x") is None
    assert compat.version_problem((5, 0, 1), "x") is None
    assert "Blender 3.3.0, too old" in compat.version_problem((3, 3, 0), "x")
    assert "cannot tell its Blender version" in compat.version_problem(None, "x")


def test_worker_without_openimageio_is_one_clear_error(tmp_path):
    """A Blender binary's Python without OpenImageIO (Debian: python3-openimageio not installed): the
    worker's first and only stdout line says what to install, exit 2, before any job is read."""
    code = (
        "import runpy, sys; sys.modules['OpenImageIO'] = None; "  # hides the module: its import fails
        f"sys.argv = ['worker', {str(tmp_path / 'job.json')!r}]; "
        "runpy.run_module('blender_gen.worker', run_name='__main__')"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=cr.REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    (line,) = proc.stdout.splitlines()
    assert line.startswith("ERROR ") and "lacks OpenImageIO" in line and "python3-openimageio" in line, line
