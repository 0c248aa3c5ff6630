"""Concurrency: one writer per dataset (or per shard), tested with real processes.

A second `crater-synth dataset` on the same out_dir refuses at once with one `error:` line naming the
process that holds it, and renders nothing; shards of one sweep (`launcher.shard=i/n`) run side by side."""

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from helpers.cli import REPO, TINY, exr_files, run_cli, start_dataset

# 16 direct-mode renders at 16 spp: the first writer is busy for several seconds.
SLOW16 = ("render.mode=direct", "render.samples=16", "sweep.sun_azimuth.count=4", "sweep.cam_azimuth.count=4")
N16 = 16


def _wait_holding(proc: subprocess.Popen, lock: Path, timeout: float = 120) -> None:
    """Until ``proc`` has written its pid into ``lock`` (it holds the lock from then on)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if lock.is_file() and lock.read_text().startswith(f"pid {proc.pid} "):
            return
        if proc.poll() is not None:
            pytest.fail(f"first writer ended (exit {proc.returncode}) early: {proc.stderr.read()[-2000:]}")
        time.sleep(0.02)
    pytest.fail(f"timed out waiting for {lock}")


def _stop(*procs: subprocess.Popen) -> None:
    for p in procs:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except (PermissionError, ProcessLookupError):  # not a group leader
                p.kill()
            p.wait()


def _refusal(proc: subprocess.CompletedProcess) -> str:
    assert proc.returncode == 2, (proc.stdout, proc.stderr[-2000:])
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    return lines[0]


def test_second_writer_of_the_same_dataset_refuses(tmp_path, tiny_data_dir, tiny_dataset):
    out = tmp_path / "ds"
    first = start_dataset(out, tiny_data_dir, *SLOW16)
    try:
        _wait_holding(first, out / ".dataset.lock")
        # Freeze the first writer while the second tries: on a loaded machine the second's start-up can
        # otherwise outlast the first's 16 renders (it would then find a finished dataset, no lock).
        os.kill(first.pid, signal.SIGSTOP)
        try:
            second = run_cli("dataset", *TINY, f"data_dir={tiny_data_dir}", f"out_dir={out}", *SLOW16)
        finally:
            os.kill(first.pid, signal.SIGCONT)
        line = _refusal(second)
        assert line.startswith(
            f"error: dataset {out} is being written by another crater-synth process (pid {first.pid} on "
        ), line
        assert line.endswith("): wait for it to finish, or give another out_dir")
        assert first.poll() is None  # the first writer is untouched
        stdout, stderr = first.communicate(timeout=600)
    finally:
        _stop(first)
    assert first.returncode == 0, stderr[-3000:]
    assert len(exr_files(out)) == N16
    logs = "".join(p.read_text(errors="replace") for p in (out / ".jobs").glob("*.log"))
    assert logs.count("scene ready") == 1  # the first writer's one worker only: the second started none
    assert run_cli("verify", out).returncode == 0


@pytest.mark.integration
def test_shards_run_side_by_side_but_not_twice(tmp_path, tiny_data_dir):
    out = tmp_path / "ds"
    slow = (*SLOW16, "render.samples=48", "sweep.cam_elevation.count=2", "render.workers=1")  # 16 renders a shard
    shards = [start_dataset(out, tiny_data_dir, *slow, f"launcher.shard={i}/2") for i in range(2)]
    try:
        _wait_holding(shards[0], out / ".dataset-shard0of2.lock")
        # Both intruders at once, while the shards are busy.
        again = start_dataset(out, tiny_data_dir, *slow, "launcher.shard=0/2")
        whole = start_dataset(out, tiny_data_dir, *slow)
        refusals = [subprocess.CompletedProcess(p.args, p.wait(timeout=120), *p.communicate()) for p in (again, whole)]
        assert all(p.poll() is None for p in shards), "the shards ended before the intruders were refused"
        results = [p.communicate(timeout=600) for p in shards]
    finally:
        _stop(*shards)
    assert _refusal(refusals[0]).startswith(
        f"error: shard 0/2 of dataset {out} is being written by another crater-synth process (pid {shards[0].pid} on "
    )
    assert _refusal(refusals[1]) == (
        f"error: dataset {out} is being written by another crater-synth process "
        "(shards of a sweep, launcher.shard=i/n): wait for it to finish, or give "
        "another out_dir"
    )
    for p, (_, stderr) in zip(shards, results, strict=True):
        assert p.returncode == 0, stderr[-3000:]
    assert len(exr_files(out)) == 2 * N16
    v = run_cli("verify", out)
    assert v.returncode == 0 and f"verify OK: {2 * N16} rows" in v.stdout, v.stdout + v.stderr


def test_the_lock_dies_with_its_holder(tmp_path):
    """flock: a writer killed with -9 leaves no stale lock behind (the kernel drops it)."""
    import sys

    from crater_synth.dataset.disk import DatasetLock
    from crater_synth.errors import DatasetBusyError

    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from pathlib import Path; "
            "from crater_synth.dataset.disk import DatasetLock; "
            f"lock = DatasetLock(Path({str(tmp_path)!r})).acquire(); print('held', flush=True); "
            "time.sleep(600)",
        ],
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(DatasetBusyError, match=f"pid {holder.pid} on "):
            DatasetLock(tmp_path).acquire()
        holder.kill()
        holder.wait()
        with DatasetLock(tmp_path) as lock:  # free again at once
            assert lock.exclusive
    finally:
        _stop(holder)
