"""Files: shareable permissions (0644 files, 0755 directories under umask 022), an fsync before
every rename that publishes a file, and a `.jobs/` directory that does not grow forever."""

import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers.cli import exr_files, run_cli

TOY = dict(
    sun_elevations=(15.0, 30.0), sun_azimuths=(0.0,), cam_elevations=(90.0,), cam_azimuths=(0.0, 180.0), rim_px=32.0
)


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def _modes(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): stat.S_IMODE(p.stat().st_mode) for p in [root, *root.rglob("*")]}


def _toy_cache(tmp_path, progress=False):
    """Build the training crop cache of a toy dataset (the real code path of `crater-synth train`)."""
    from crater_core.schema import load_manifest
    from train.data import build_cache
    from train.preprocess import PreprocessConfig
    from train.toydata import write_toy_dataset

    write_toy_dataset(tmp_path / "toy", **TOY)
    rows = load_manifest(tmp_path / "toy")
    return build_cache(rows, tmp_path / "toy", [1.0, 1.2], PreprocessConfig(), tmp_path / "cache", progress=progress)


def test_everything_written_is_shareable(tmp_path, tiny_data_dir, tiny_dataset, umask_022):
    out = tmp_path / "ds"
    tiny_dataset(out)  # (the CLI inherits this process's umask)
    assert run_cli("preview", out).returncode == 0
    _toy_cache(tmp_path)
    for root in (out, tmp_path / "cache"):
        modes = _modes(root)
        dirs = {k: oct(m) for k, m in modes.items() if (root / k).is_dir() and m != 0o755}
        files = {k: oct(m) for k, m in modes.items() if (root / k).is_file() and m != 0o644}
        assert not dirs and not files, (root, dirs, files)
    assert any(k.startswith("preview/") for k in _modes(out)) and len(exr_files(out)) == 4


def test_every_rename_is_preceded_by_an_fsync(tmp_path, monkeypatch):
    """A rename publishes a file: its bytes must be on disk first, or a crash can publish an empty or
    partial file under the final name."""
    synced, unsynced = set(), []

    real_fsync, real_replace, real_rename = os.fsync, os.replace, os.rename

    def fsync(fd):
        synced.add(os.path.realpath(f"/proc/self/fd/{fd}"))
        return real_fsync(fd)

    def check(src):
        src = os.path.realpath(src)
        paths = [src] + ([str(p) for p in Path(src).rglob("*") if p.is_file()] if os.path.isdir(src) else [])
        unsynced.extend(p for p in paths if p not in synced)

    def replace(src, dst, *a, **k):
        check(src)
        return real_replace(src, dst, *a, **k)

    def rename(src, dst, *a, **k):
        check(src)
        return real_rename(src, dst, *a, **k)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(os, "rename", rename)

    from crater_core import exr, schema
    from crater_synth.dataset.preview import contact_sheet

    schema.atomic_write_text(tmp_path / "a.json", "{}")
    chans = {c: np.full((8, 8), 0.5, np.float32) for c in schema.EXR_CHANNELS}
    exr.write_exr(tmp_path / "shackleton" / "r.exr", chans, {})
    row = {
        "path": "shackleton/r.exr",
        "sun_elevation": 1.6,
        "sun_azimuth": 0.0,
        "cam_elevation": 90.0,
        "cam_azimuth": 0.0,
        "lit_fraction": 1.0,
        "mean_if": 0.5,
        "sigma_boxes": {"1.0": [1, 1, 7, 7]},
        "rim_ellipse": {"cu": 4.0, "cv": 4.0, "a": 3.0, "b": 3.0, "angle_rad": 0.0},
    }
    contact_sheet([row], tmp_path, tmp_path / "preview" / "contact_shackleton.png", "t")
    _toy_cache(tmp_path)
    from crater_synth.evaluation.closed_loop import plot_history
    from crater_synth.evaluation.figure6 import plot_figure6

    plot_history(
        {
            "threshold": 0.85,
            "rounds": [{"sun_elevation_count": 2, "lunarnet_ex": 0.5, "lunarsvm_ex": 0.6, "hog_svm": 0.4}],
        },
        tmp_path / "loop_history.png",
    )
    plot_figure6(
        [{"parameter": "sun_elevation", "count": 2, "sigma": 1.0, "model": "lunarnet_ex", "real_accuracy": 0.5}],
        tmp_path / "figure6.png",
    )
    assert not unsynced, f"renamed without an fsync: {unsynced}"


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_jobs_directory_is_bounded(tmp_path, tiny_dataset):
    """Job files of finished workers go; logs of writers that have ended are kept for the last runs only."""
    from crater_synth.dataset.disk import KEEP_JOB_LOGS
    from crater_synth.dataset.manifest import writer_tag

    out = tmp_path / "ds"
    tiny_dataset(out)
    jobs = out / ".jobs"
    assert not list(jobs.glob("*.json")), "the job file of a worker that succeeded was kept"
    host, dead = writer_tag().rsplit("-", 1)[0], _dead_pid()
    for run in range(3 * KEEP_JOB_LOGS):  # earlier runs of a long-lived dataset
        for ext in ("json", "log"):
            f = jobs / f"shackleton-{host}-{dead}-{run}.{ext}"
            f.write_text("old run\n")
            os.utime(f, (1e9 + run, 1e9 + run))
    tiny_dataset(out)  # a resumed run: nothing to render, but it tidies up
    left = sorted(p.name for p in jobs.iterdir())
    assert len(left) <= KEEP_JOB_LOGS + 1, left  # the newest logs (+ this run's own log, if any)
    assert not [n for n in left if n.endswith(".json")]
    assert f"shackleton-{host}-{dead}-{3 * KEEP_JOB_LOGS - 1}.log" in left  # the newest are the ones kept
