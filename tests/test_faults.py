"""Faults during a sweep, made for real (kill -9, truncated/bit-flipped/deleted files): the dataset
ends complete, verifies, and is byte-identical to an undisturbed run of the same config."""

import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from helpers.cli import assert_same_dataset, dataset_workers, exr_files, run_cli, start_dataset, summary

# 32 renders, direct mode at 16 spp: ~0.09 s each on 2 cores, so a Blender worker runs ~3 s after
# its first EXR: time to kill it mid-shard.
SLOW32 = (
    "render.mode=direct",
    "render.samples=16",
    "sweep.sun_azimuth.count=4",
    "sweep.cam_azimuth.count=4",
    "sweep.cam_elevation.count=2",
)
N32 = 32


@pytest.fixture(scope="module")
def reference32(tmp_path_factory, tiny_dataset):
    out = tmp_path_factory.mktemp("faults") / "ref"
    tiny_dataset(out, *SLOW32)
    assert len(exr_files(out)) == N32
    return out


@pytest.fixture(scope="module")
def reference4(tiny_smoke):
    return tiny_smoke


# -- helpers ------------------------------------------------------------------------------------
def _ppid(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def _wait_for(cond, what: str, timeout: float = 120, proc: subprocess.Popen | None = None):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            pytest.fail(f"sweep ended (exit {proc.returncode}) before {what}: {proc.stderr.read()[-2000:]}")
        time.sleep(0.01)
    pytest.fail(f"timed out waiting for {what}")


def _part_rows(out: Path) -> int:
    return sum(p.read_text().count("\n") for p in (out / "manifest.parts").glob("*.jsonl"))


def _kill_leftovers(out: Path) -> None:
    for pid in dataset_workers(out):  # orphans of a killed parent (started by this test's sweep)
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def _worker_runs(out: Path) -> int:
    """Blender worker processes that got as far as building their scene (from the job logs)."""
    return sum(p.read_text(errors="replace").count("scene ready") for p in (out / ".jobs").glob("*.log"))


def _assert_complete(out: Path, reference: Path) -> None:
    v = run_cli("verify", out)
    assert v.returncode == 0, v.stderr
    assert "0 orphan files" in v.stdout, v.stdout
    assert_same_dataset(reference, out)  # no missing, duplicate or different render


# -- (a) a Blender worker killed mid-shard --------------------------------------------------------
@pytest.mark.integration
def test_killed_blender_worker_is_retried(tmp_path, tiny_data_dir, reference32):
    out = tmp_path / "ds"
    proc = start_dataset(out, tiny_data_dir, *SLOW32)
    try:
        _wait_for(lambda: exr_files(out), "the first EXR", proc=proc)
        (victim,) = dataset_workers(out)
        os.kill(victim, signal.SIGKILL)
        done_at_kill = len(exr_files(out))
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        _kill_leftovers(out)
    assert proc.returncode == 0, stderr[-3000:]
    assert 0 < done_at_kill < N32
    assert _worker_runs(out) == 2  # the killed worker and its replacement
    s = summary(subprocess.CompletedProcess([], 0, stdout))
    assert (s["rendered"], s["manifest_rows"]) == (N32, N32)
    _assert_complete(out, reference32)


# -- (b) the whole sweep killed -------------------------------------------------------------------
@pytest.mark.integration
def test_killed_sweep_resumes(tmp_path, tiny_data_dir, tiny_dataset, reference32):
    out = tmp_path / "ds"
    proc = start_dataset(out, tiny_data_dir, *SLOW32)
    try:
        _wait_for(lambda: _part_rows(out) >= 3, "3 manifest rows", proc=proc)
        os.killpg(proc.pid, signal.SIGKILL)  # the host and its Blender worker: one process group
        proc.wait()
    finally:
        _kill_leftovers(out)
    assert not dataset_workers(out)
    assert not (out / "manifest.jsonl").exists()  # killed before the merge
    assert 3 <= _part_rows(out) < N32
    s = summary(tiny_dataset(out, *SLOW32))
    assert s["skipped_existing"] >= 3 and s["rendered"] + s["skipped_existing"] == N32
    assert s["manifest_rows"] == N32  # the killed run's rows reach the manifest too
    assert not list((out / "manifest.parts").glob("*.jsonl"))
    _assert_complete(out, reference32)


# -- (c) a corrupt EXR ------------------------------------------------------------------------------
def _truncate(f: Path):
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])


def _flip_bit(f: Path):
    data = bytearray(f.read_bytes())
    data[len(data) * 3 // 4] ^= 0x10  # inside the compressed pixel tiles
    f.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", [_truncate, _flip_bit], ids=["truncated", "bit-flipped"])
def test_corrupt_exr_is_detected_and_rerendered(tmp_path, tiny_dataset, reference4, damage):
    out = shutil.copytree(reference4, tmp_path / "ds")
    victim = exr_files(out)[1]
    damage(victim)
    v = run_cli("verify", out)
    assert v.returncode == 1
    faults = [line for line in v.stderr.splitlines() if line.startswith("fault:")]
    assert faults == [f"fault: {victim}: sha256 mismatch (corrupt or changed)"]
    assert "FAILED (1 faults)" in v.stdout
    s = summary(tiny_dataset(out))
    assert (s["rendered"], s["skipped_existing"]) == (1, 3)
    _assert_complete(out, reference4)


# -- (d) a manifest row whose file is gone ---------------------------------------------------------
def test_missing_file_is_rerendered(tmp_path, tiny_dataset, reference4):
    out = shutil.copytree(reference4, tmp_path / "ds")
    victim = exr_files(out)[2]
    victim.unlink()
    v = run_cli("verify", out)
    assert v.returncode == 1
    assert [line for line in v.stderr.splitlines() if line.startswith("fault:")] == [f"fault: {victim}: missing"]
    s = summary(tiny_dataset(out))
    assert (s["rendered"], s["skipped_existing"]) == (1, 3)
    _assert_complete(out, reference4)


# -- (e) a Dask worker process killed mid-task ------------------------------------------------------
@pytest.mark.integration
def test_killed_dask_worker_task_is_retried(tmp_path, tiny_data_dir, reference32):
    out = tmp_path / "ds"
    proc = start_dataset(out, tiny_data_dir, *SLOW32, "launcher=dask", "launcher.n_workers=2", "launcher.shards=2")
    try:
        _wait_for(lambda: exr_files(out), "the first EXR", proc=proc)
        blender = dataset_workers(out)
        assert blender
        dask_worker = _ppid(blender[0])
        assert dask_worker != proc.pid and _ppid(dask_worker) == proc.pid  # a worker process of the local cluster
        os.kill(dask_worker, signal.SIGKILL)
        done_at_kill = len(exr_files(out))
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        _kill_leftovers(out)
    assert proc.returncode == 0, stderr[-3000:]
    assert done_at_kill < N32
    assert _worker_runs(out) >= 3  # two shards + the rescheduled one
    s = summary(subprocess.CompletedProcess([], 0, stdout))
    assert s["manifest_rows"] == N32
    _assert_complete(out, reference32)


def test_parallel_verify_reports_what_serial_verify_reports(tmp_path, reference4, monkeypatch):
    """`verify` checks files in a process pool on big datasets: same faults, same order."""
    from crater_synth.dataset import verify

    out = shutil.copytree(reference4, tmp_path / "ds")
    files = exr_files(out)
    _truncate(files[1])
    files[2].unlink()
    serial = verify.verify_dataset(out, jobs=1)
    monkeypatch.setattr(verify, "PARALLEL_MIN_FILES_PER_JOB", 1)
    parallel = verify.verify_dataset(out, jobs=2)
    assert parallel["faults"] == serial["faults"] and len(serial["faults"]) == 2
    assert (parallel["rows"], parallel["ok"]) == (serial["rows"], False)
