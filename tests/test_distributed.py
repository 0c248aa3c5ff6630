"""The Dask launcher on a real cluster on 127.0.0.1 gives the same dataset as one process.

Two clusters: the local one `launcher=dask launcher.n_workers=2` starts (scheduler in the
`crater-synth` process, two worker processes), and the multi-node recipe of docs/distributed.md run on
one machine (`dask scheduler` + two `dask worker` processes, `launcher.address=tcp://...`).
"""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from helpers.cli import EIGHT, REPO, TINY, assert_same_dataset, exr_files, run_cli, summary

pytestmark = pytest.mark.integration  # end-to-end: make test-integration


@pytest.fixture(scope="module")
def single(tiny_eight):
    return tiny_eight


def _worker_pids(dataset_dir: Path) -> set[str]:
    """Processes that ran the dataset's shards: job logs are named <crater>-<host>-<pid>-<n>.log (the
    job files themselves are removed once their worker succeeds)."""
    return {p.stem.rsplit("-", 2)[1] for p in (dataset_dir / ".jobs").glob("*.log")}


def test_local_dask_cluster_matches_single_process(tmp_path, tiny_dataset, single):
    out = tmp_path / "dask"
    proc = tiny_dataset(out, *EIGHT, "launcher=dask", "launcher.n_workers=2", "launcher.shards=4")
    s = summary(proc)
    assert (s["launcher"], s["workers"], s["shards"], s["rendered"], s["manifest_rows"]) == ("dask", 2, 4, 8, 8)
    assert len(_worker_pids(out)) == 2  # both worker processes rendered shards
    assert str(os.getpid()) not in _worker_pids(out)
    logs = "".join(p.read_text(errors="replace") for p in (out / ".jobs").glob("*.log"))
    assert logs.count("scene ready") == 4  # one Blender worker per shard, none retried
    assert_same_dataset(single, out)
    assert run_cli("verify", out).returncode == 0


def _start(args: list[str], log: Path) -> subprocess.Popen:
    return subprocess.Popen(args, stdout=open(log, "wb"), stderr=subprocess.STDOUT, cwd=REPO, start_new_session=True)


def test_external_scheduler_and_workers(tmp_path, tiny_dataset, single):
    """docs/distributed.md's multi-node recipe, on one machine: `dask scheduler` on the head, one
    `dask worker ... --nworkers 1 --nthreads 1` per "node", then `launcher.address=`."""
    dask_cli = [str(Path(sys.executable).with_name("dask"))]
    sched_file = tmp_path / "scheduler.json"
    procs = [
        _start(
            [
                *dask_cli,
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--scheduler-file",
                str(sched_file),
            ],
            tmp_path / "scheduler.log",
        )
    ]
    try:
        for i in range(2):
            procs.append(
                _start(
                    [
                        *dask_cli,
                        "worker",
                        "--scheduler-file",
                        str(sched_file),
                        "--host",
                        "127.0.0.1",
                        "--nworkers",
                        "1",
                        "--nthreads",
                        "1",
                        "--no-dashboard",
                    ],
                    tmp_path / f"worker{i}.log",
                )
            )
        address = None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if sched_file.exists():
                try:
                    info = json.loads(sched_file.read_text())
                except ValueError:
                    info = {}
                if info.get("address"):
                    address = info["address"]
                    from distributed import Client

                    with Client(address, timeout="10s") as client:
                        client.wait_for_workers(2, timeout=60)
                    break
            time.sleep(0.2)
        assert address, (tmp_path / "scheduler.log").read_text()[-2000:]
        out = tmp_path / "dask"
        s = summary(tiny_dataset(out, *EIGHT, "launcher=dask", f"launcher.address={address}", "launcher.shards=2"))
        assert (s["workers"], s["shards"], s["rendered"]) == (2, 2, 8)
        assert len(_worker_pids(out)) == 2
        assert_same_dataset(single, out)
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    assert len(exr_files(out)) == 8


@pytest.mark.slow
def test_bench_distributed_reports_both_paths(tmp_path, tiny_data_dir):
    from crater_synth.bench.distributed import bench_distributed
    from crater_synth.config import compose

    cfg = compose(
        [*TINY, f"data_dir={tiny_data_dir}", *EIGHT, "launcher=dask", "launcher.n_workers=2", "launcher.shards=2"]
    )
    r = bench_distributed(cfg, work_dir=tmp_path)
    assert r["renders"] == 8 and r["identical_manifests"]
    assert r["single"]["renders_per_s"] > 0 and r["dask"]["renders_per_s"] > 0 and r["dask"]["workers"] == 2
    assert r["speedup_dask_over_single"] == pytest.approx(r["single"]["seconds"] / r["dask"]["seconds"], rel=0.05)
    assert r["single"]["worker_logs"]["renders"] == r["dask"]["worker_logs"]["renders"] == 8
    assert r["model"]["worker_start_s"] > 0 and r["model"]["per_render_s"] > 0
