"""The project's processes run their BLAS on one thread (crater_core/blas_threads.py): the host, through
``crater_synth``'s import (a value the user set is kept), and the Blender worker, through its module's
(always: its bytes must not depend on the thread count)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from helpers.cli import REPO

PROBE = (
    "import json, os, numpy, threadpoolctl; "
    "info = [i for i in threadpoolctl.threadpool_info() if i['internal_api'] == 'openblas']; "
    "print(json.dumps({'env': os.environ.get('OPENBLAS_NUM_THREADS'), 'threads': [i['num_threads'] for i in info]}))"
)


def probe(first_import: str, **env) -> dict:
    base = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    out = subprocess.run(
        [sys.executable, "-c", f"import {first_import}; {PROBE}"],
        cwd=REPO,
        env=base | env,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("first_import", ["crater_synth", "blender_gen.worker"])
def test_host_and_worker_load_numpy_with_one_blas_thread(first_import):
    got = probe(first_import)
    assert got["env"] == "1"
    assert got["threads"], "numpy's OpenBLAS not found by threadpoolctl"
    assert set(got["threads"]) == {1}, got


def test_the_host_keeps_a_thread_count_the_user_set():
    got = probe("crater_synth", OPENBLAS_NUM_THREADS="2")
    assert got["env"] == "2"
    assert set(got["threads"]) == {min(2, os.cpu_count() or 1)}, got


def test_the_worker_runs_one_blas_thread_whatever_the_environment_says():
    got = probe("blender_gen.worker", OPENBLAS_NUM_THREADS="2")
    assert got["env"] == "1"
    assert set(got["threads"]) == {1}, got


def test_without_it_numpy_would_start_more_threads_here():
    """The check above can fail: on a machine with several cores OpenBLAS's own default is more than one."""
    if (os.cpu_count() or 1) < 2:
        pytest.skip("one core: OpenBLAS starts one thread anyway")
    got = probe("sys")
    assert got["env"] is None
    assert max(got["threads"]) > 1, got
