"""Worker contract tests: EXR layout/header, RESULT lines, atomic overwrite, determinism, bad input."""

from __future__ import annotations

import hashlib
import json
import sys

import numpy as np
import OpenImageIO as oiio
import pytest

from crater_core import exr
from crater_core.schema import EXR_CHANNEL_TYPES, EXR_CHANNELS

from helpers import render as cr

RESULT_KEYS = {"index", "rel_path", "sha256", "lit_fraction", "mean_if", "seconds"}


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """Two renders (one per mode) of a bumpy plane, written twice to the same out dir."""
    tmp = tmp_path_factory.mktemp("contract")
    npz = cr.write_npz(tmp / "bumps.npz", cr.grid(20_000.0, 65, lambda x, y: 300 * np.sin(x / 2000) * np.cos(y / 3000)))
    items = [
        cr.item(
            0, 20.0, 30.0, 70.0, 120.0, range_m=15_000.0, frame_width=160, crop=[30, 41, 30 + 97, 41 + 70], name="bumps"
        ),
        cr.item(
            1, 5.0, 200.0, 90.0, 0.0, range_m=15_000.0, frame_width=160, crop=cr.central_crop(160, 64), name="bumps"
        ),
    ]
    out = {}
    for mode in ("direct", "fast"):
        job = cr.job(npz, items, tmp / "out" / mode, mode=mode, samples=4, shadow_map_px=128)
        first, p1 = cr.run_worker(job, tmp, f"{mode}-1")
        assert p1.returncode == 0, p1.stderr[-3000:]
        second, p2 = cr.run_worker(job, tmp, f"{mode}-2")
        assert p2.returncode == 0, p2.stderr[-3000:]
        out[mode] = {"job": job, "first": first, "second": second, "stdout": p1.stdout, "dir": tmp / "out" / mode}
    return out


@pytest.mark.parametrize("mode", ["direct", "fast"])
def test_exr_layout_and_header(small, mode):
    run = small[mode]
    for it in run["job"]["renders"]:
        path = run["dir"] / it["rel_path"]
        inp = oiio.ImageInput.open(str(path))
        assert inp is not None
        spec = inp.spec()
        assert (spec.tile_width, spec.tile_height) == (64, 64)
        assert set(spec.channelnames) == set(EXR_CHANNELS) and spec.nchannels == len(EXR_CHANNELS)
        stored = [str(t) for t in spec.channelformats] or [str(spec.format)] * spec.nchannels
        assert dict(zip(spec.channelnames, stored)) == EXR_CHANNEL_TYPES
        assert spec.get_string_attribute("compression") == exr.COMPRESSION
        u0, v0, u1, v1 = it["crop"]
        assert (spec.width, spec.height) == (u1 - u0, v1 - v0)
        inp.close()
        chans, header = exr.read_exr(str(path))
        assert all(np.isfinite(c).all() for c in chans.values())
        assert header["crater_synth:mode"] == mode
        assert header["crater_synth:sun_elevation"] == pytest.approx(it["sun_elevation"])
        assert header["crater_synth:cam_azimuth"] == pytest.approx(it["cam_azimuth"])
        assert json.loads(header["crater_synth:crop"]) == it["crop"]
        assert json.loads(header["crater_synth:hapke"]) == cr.HAPKE
        render_hdr = json.loads(header["crater_synth:render"])
        assert render_hdr["samples"] == 4 and render_hdr["mode"] == mode
        assert "threads" not in render_hdr  # execution-only: bytes must not depend on the worker layout
        for key, val in it["header"].items():  # the host's header entries are written verbatim
            assert header[key] == val
        assert "DateTime" not in header


@pytest.mark.parametrize("mode", ["direct", "fast"])
def test_result_lines(small, mode):
    run = small[mode]
    lines = [ln for ln in run["stdout"].splitlines() if ln.strip()]
    assert all(ln.startswith("RESULT ") for ln in lines), lines  # Blender's own log goes to stderr
    for it in run["job"]["renders"]:
        r = run["first"][it["index"]]
        assert RESULT_KEYS <= set(r)
        assert r["rel_path"] == it["rel_path"]
        path = run["dir"] / it["rel_path"]
        assert r["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
        chans, _ = exr.read_exr(str(path))
        assert r["mean_if"] == pytest.approx(float(chans["IF"].mean()), rel=1e-4, abs=1e-9)
        assert r["lit_fraction"] == pytest.approx(float(chans["lit"].mean()), abs=1e-5)
        assert r["seconds"] > 0


@pytest.mark.parametrize("mode", ["direct", "fast"])
def test_overwrite_is_atomic_and_deterministic(small, mode):
    run = small[mode]
    for it in run["job"]["renders"]:
        assert run["first"][it["index"]]["sha256"] == run["second"][it["index"]]["sha256"]
    leftovers = [
        p.name for p in (run["dir"] / "bumps").iterdir() if not p.name.endswith(".exr") or p.name.startswith(".")
    ]
    assert leftovers == []


def _expect_error(tmp_path, npz_path, fragment):
    job = cr.job(str(npz_path), [cr.item(0, 10, 0, 90, 0, 15_000.0)], tmp_path / "out")
    results, proc = cr.run_worker(job, tmp_path, "bad", timeout=120)
    assert proc.returncode != 0
    assert results == {}
    errors = [ln for ln in proc.stdout.splitlines() if ln.startswith("ERROR ")]
    assert len(errors) == 1 and fragment in errors[0], proc.stdout + proc.stderr[-2000:]
    assert "\n" not in errors[0]


def test_missing_npz_is_a_clean_error(tmp_path):
    _expect_error(tmp_path, tmp_path / "nope.npz", "does not exist")


def test_corrupt_npz_is_a_clean_error(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"PK\x03\x04 this is not a zip archive" * 10)
    _expect_error(tmp_path, bad, "corrupt")


def test_npz_without_near_field_is_a_clean_error(tmp_path):
    bad = tmp_path / "empty.npz"
    np.savez(bad, far_xyz=np.zeros((3, 3, 3), np.float32))
    _expect_error(tmp_path, bad, "near_xyz")


def test_npz_with_nan_is_a_clean_error(tmp_path):
    near = cr.grid(1000.0, 5)
    near[2, 2, 2] = np.nan
    bad = tmp_path / "nan.npz"
    np.savez(bad, near_xyz=near)
    _expect_error(tmp_path, bad, "non-finite")


def test_crop_outside_frame_is_a_clean_error(tmp_path):
    npz = cr.write_npz(tmp_path / "flat.npz", cr.grid(20_000.0, 9))
    job = cr.job(npz, [cr.item(0, 10, 0, 90, 0, 15_000.0, frame_width=100, crop=[-5, 0, 50, 50])], tmp_path / "out")
    results, proc = cr.run_worker(job, tmp_path, "crop")
    assert proc.returncode != 0 and results == {}
    assert any(ln.startswith("ERROR ") and "crop" in ln for ln in proc.stdout.splitlines())


def test_script_form_adds_repo_to_path(tmp_path):
    """``python blender_gen/worker.py JOB`` (what ``blender --python`` runs) finds its package."""
    npz = cr.write_npz(tmp_path / "flat.npz", cr.grid(20_000.0, 9))
    job = cr.job(
        npz, [cr.item(0, 30, 0, 90, 0, 15_000.0, frame_width=64, crop=[16, 16, 48, 48])], tmp_path / "out", samples=1
    )
    results, proc = cr.run_worker(
        job, tmp_path, "script", argv=[sys.executable, str(cr.REPO / "blender_gen" / "worker.py")]
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert list(results) == [0]


def test_blender_binary_form(tmp_path, blender_exe):
    """``blender --background --python blender_gen/worker.py -- JOB`` (a Blender binary, not the bpy
    module) renders the job (skipped, with the reason, when no supported binary is installed)."""
    npz = cr.write_npz(tmp_path / "flat.npz", cr.grid(20_000.0, 9))
    job = cr.job(
        npz, [cr.item(0, 30, 0, 90, 0, 15_000.0, frame_width=64, crop=[16, 16, 48, 48])], tmp_path / "out", samples=1
    )
    results, proc = cr.run_worker(
        job,
        tmp_path,
        "blender",
        argv=[
            blender_exe,
            "--background",
            "--factory-startup",
            "--python",
            str(cr.REPO / "blender_gen" / "worker.py"),
            "--",
        ],
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert list(results) == [0]
    from crater_synth.dataset.dispatch import blender_binary

    version = blender_binary(blender_exe)[1]
    assert results[0]["blender"] == version
    chans, header = exr.read_exr(tmp_path / "out" / results[0]["rel_path"])
    assert set(chans) == set(EXR_CHANNELS) and header["crater_synth:blender"] == version
    # the same job through the bpy module: the same flat plane, lit by the same sun
    job["out_dir"] = str(tmp_path / "module")
    module_results, proc = cr.run_worker(job, tmp_path, "module")
    assert proc.returncode == 0, proc.stderr[-3000:]
    ref, _ = exr.read_exr(tmp_path / "module" / module_results[0]["rel_path"])
    np.testing.assert_allclose(chans["depth"], ref["depth"], rtol=1e-4)
    # one sample per pixel of the solar disc: Monte-Carlo noise (~1.5 % per pixel), not a bias
    assert abs(chans["IF"].mean() / ref["IF"].mean() - 1.0) < 0.005
    assert np.abs(chans["IF"] - ref["IF"]).mean() / np.median(ref["IF"]) < 0.01
    assert np.abs(chans["lit"] - ref["lit"]).mean() < 0.01
