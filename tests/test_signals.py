"""Signals and leftovers: SIGTERM or SIGINT stops the Blender workers and leaves no scratch file
and no EXR without its manifest row; a host killed with -9 does not leave its workers rendering;
`verify` names orphan files and the next `dataset` run removes those of its own interrupted writes."""

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from helpers.cli import dataset_workers, exr_files, run_cli, start_dataset, summary

# 16 direct-mode renders at 16 spp, on 2 workers: time to interrupt the run mid-way.
SLOW16 = (
    "render.mode=direct",
    "render.samples=16",
    "sweep.sun_azimuth.count=4",
    "sweep.cam_azimuth.count=4",
    "render.workers=2",
)
N16 = 16
SCRATCH = re.compile(r"^crater_synth_(?:render|exr)_(\d+)_")


def _scratch_of(pids) -> list[str]:
    from crater_core.files import scratch_dir

    return [n for n in os.listdir(scratch_dir()) if (m := SCRATCH.match(n)) and int(m.group(1)) in set(pids)]


def _wait_for(cond, what: str, proc: subprocess.Popen, timeout: float = 180):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        if proc.poll() is not None:
            pytest.fail(f"sweep ended (exit {proc.returncode}) before {what}: {proc.stderr.read()[-2000:]}")
        time.sleep(0.02)
    pytest.fail(f"timed out waiting for {what}")


def _interrupt(out: Path, data_dir: Path, send) -> tuple[subprocess.Popen, str, list[int]]:
    """Start the sweep, wait for its first EXR and both workers' scratch files, call ``send(proc)``."""
    proc = start_dataset(out, data_dir, *SLOW16)
    try:
        _wait_for(lambda: exr_files(out), "the first EXR", proc)
        workers = _wait_for(
            lambda: (w := dataset_workers(out)) and len(_scratch_of(w)) == len(w) == 2 and w,
            "two workers with scratch files",
            proc,
        )
        send(proc)
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return proc, stderr, workers


def _assert_clean_stop(out: Path, workers: list[int]) -> None:
    assert not dataset_workers(out), "Blender workers still running after the host stopped"
    assert not _scratch_of(workers), "scratch files left in /dev/shm"
    v = run_cli("verify", out)
    assert v.returncode == 0, v.stderr
    assert "0 orphan files" in v.stdout, v.stdout + v.stderr  # every EXR on disk has its manifest row
    assert len(exr_files(out)) < N16


@pytest.mark.parametrize("how", ["SIGTERM", "SIGINT"])
def test_signal_stops_workers_and_leaves_nothing(tmp_path, tiny_data_dir, tiny_dataset, how):
    out = tmp_path / "ds"
    if how == "SIGTERM":  # e.g. a batch system ending the job: the host alone gets it
        send = lambda proc: os.kill(proc.pid, signal.SIGTERM)  # noqa: E731
    else:  # Ctrl-C: the terminal signals the whole foreground process group
        send = lambda proc: os.killpg(proc.pid, signal.SIGINT)  # noqa: E731
    proc, stderr, workers = _interrupt(out, tiny_data_dir, send)
    signum = getattr(signal, how)
    assert proc.returncode == 128 + signum, stderr[-3000:]
    assert stderr.splitlines()[-1] == f"error: interrupted by {how}: stopped; rerun the same command to resume"
    assert all("renders/s" in line for line in stderr.splitlines()[:-1]), stderr  # progress lines only
    _assert_clean_stop(out, workers)
    if how == "SIGTERM":
        s = summary(tiny_dataset(out, *SLOW16))  # and one rerun completes it
        assert s["rendered"] + s["skipped_existing"] == N16 and s["manifest_rows"] == N16


def test_host_killed_with_minus_9_does_not_leave_workers_rendering(tmp_path, tiny_data_dir):
    out = tmp_path / "ds"
    proc, _, workers = _interrupt(out, tiny_data_dir, lambda p: os.kill(p.pid, signal.SIGKILL))
    deadline = time.monotonic() + 60
    while (dataset_workers(out) or _scratch_of(workers)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not dataset_workers(out), "workers kept rendering for a dead host"
    assert not _scratch_of(workers), "the workers' scratch files are left in /dev/shm"


def test_verify_names_orphans_and_dataset_removes_only_its_own(tmp_path, tiny_dataset):
    """`verify` names every file no row names; `dataset` removes the temp files of its own interrupted
    writes and leaves a render-like file it never planned alone (it cannot prove it wrote it)."""
    out = tmp_path / "ds"
    tiny_dataset(out)
    first = exr_files(out)[0]
    orphan = first.with_name("se09.000_sa000.000_ce90.000_ca000.000.exr")  # an EXR no row names, not planned
    temp = first.with_name(f".{first.name}.k2j3h4.tmp.exr")  # an interrupted atomic write
    part_temp = out / ".manifest.jsonl.abc123.tmp"
    for f in (orphan, temp, part_temp):
        shutil.copy(first, f)
    v = run_cli("verify", out)
    assert v.returncode == 0, v.stderr
    named = sorted(line.split()[1] for line in v.stderr.splitlines() if line.startswith("orphan: "))
    assert named == sorted(str(f) for f in (orphan, temp, part_temp))
    assert "3 orphan files" in v.stdout
    proc = tiny_dataset(out)
    assert summary(proc)["rendered"] == 0
    assert f"warning: removed 2 temp file(s) of interrupted writes from {out}" in proc.stderr
    assert f"left 1 file(s) alone that no manifest row and no planned render names, e.g. {orphan}" in proc.stderr
    assert orphan.exists() and not temp.exists() and not part_temp.exists() and first.exists()
    v = run_cli("verify", out)
    assert v.returncode == 0 and "1 orphan files" in v.stdout, v.stdout + v.stderr


# A stand-in worker: one RESULT line per render of its job file, then exit.
_FAKE_WORKER = """
import json, sys
for item in json.load(open(sys.argv[1]))["renders"]:
    print("RESULT " + json.dumps({"index": item["index"]}), flush=True)
"""


def test_a_signal_while_a_result_is_recorded_waits_for_its_row(tmp_path, monkeypatch):
    """The CLI turns SIGTERM into an exception raised wherever the host is: one landing between a
    worker's RESULT line and its manifest row would leave an EXR no row names. It is held until the
    row is written, then stops the run."""
    from types import SimpleNamespace

    from crater_synth.cli_common import StopSignals
    from crater_synth.config import load_settings
    from crater_synth.dataset import dispatch
    from crater_synth.dataset.plan import CraterJob
    from crater_synth.errors import Interrupted

    monkeypatch.setattr(
        dispatch, "worker_command", lambda job_file, blender=None: [sys.executable, "-c", _FAKE_WORKER, str(job_file)]
    )
    crater = SimpleNamespace(name="fake", as_dict=dict)
    plans = [{"params": SimpleNamespace(index=i, indices=(i, 0, 0, 0)), "item": {"index": i}} for i in range(3)]
    job = CraterJob(crater=crater, npz=tmp_path / "none.npz", meta={}, plans=plans)
    s = load_settings(["render.workers=1"])
    begun, rows = [], []

    def on_result(_job, plan, _result):
        begun.append(plan["params"].index)
        os.kill(os.getpid(), signal.SIGTERM)  # arrives while the row is being written
        time.sleep(0.05)
        rows.append(plan["params"].index)

    with pytest.raises(Interrupted), StopSignals():
        dispatch.run_workers([job], s.render, s.hapke, tmp_path, on_result)
    assert rows and rows == begun  # every row begun was written before the run stopped
