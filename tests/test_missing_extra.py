"""A command whose pip extra is not installed ends with one line naming the extra and the pip command
(crater_synth/cli.py), and the render commands run with the render extra alone: no torch, Dask, pyarrow,
scikit-learn or Jinja2 (docs/install.md). The missing libraries are simulated in a fresh
interpreter (helpers/blocked.py); the real render-only install is checked by hand in docs/install.md."""

from __future__ import annotations

import pytest
from test_declared_deps import closure, imports

from crater_synth.cli import COMMAND_EXTRA, COMMANDS, EXTRA_MODULES, missing_extra

from helpers.blocked import cli_blocked, run_blocked
from helpers.cli import REPO, TINY

# What an install of the render extra alone lacks.
NOT_RENDER = set(EXTRA_MODULES["all"]) - set(EXTRA_MODULES["render"])
MODULES = {name: where.split(":")[0] for entries in COMMANDS.values() for name, where, _ in entries}
RENDER_COMMANDS = sorted(c for c, e in COMMAND_EXTRA.items() if e == "render")


def _one_error_line(proc, expected: str):
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert proc.stdout == ""
    assert proc.stderr.splitlines() == [f"error: {expected}"]


def test_the_line_names_the_command_the_extra_and_the_pip_command():
    assert missing_extra("train", "torch") == (
        f"`crater-synth train` needs the train extra (torch is not installed): pip install -e '{REPO}[train]'"
    )
    line = missing_extra("export", "pyarrow.parquet")
    assert line.startswith("`crater-synth export` needs the export extra (pyarrow is not installed)")


def test_a_module_outside_the_commands_extra_names_its_own_extra():
    """`dataset` needs the render extra, and Dask only for launcher=dask: the dask extra."""
    assert missing_extra("dataset", "distributed.scheduler").startswith(
        "`crater-synth dataset` needs the dask extra (distributed is not installed)"
    )


@pytest.mark.parametrize("module", [None, "no_such_library", "crater_synth.no_such_module"])
def test_a_module_of_no_extra_is_left_to_its_traceback(module):
    """Not an install to complete: a bug, shown as Python shows it."""
    assert missing_extra("train", module) is None


def test_missing_torch_stops_train_before_it_starts():
    """train imports torch only when it trains: the check before the command runs catches it at once."""
    proc = cli_blocked({"torch"}, "train", "run_dir=/nonexistent/never-made")
    _one_error_line(
        proc, f"`crater-synth train` needs the train extra (torch is not installed): pip install -e '{REPO}[train]'"
    )


def test_missing_pyarrow_at_import_is_the_same_line():
    """export imports pyarrow at its module's top: the loader turns that into the line."""
    proc = cli_blocked({"pyarrow"}, "export", "/nonexistent", "--format", "parquet")
    pip = f"pip install -e '{REPO}[export]'"
    _one_error_line(proc, f"`crater-synth export` needs the export extra (pyarrow is not installed): {pip}")


def test_missing_dask_for_the_dask_launcher(tmp_path):
    """Found while the command runs (launcher=dask), before any directory is made."""
    out = tmp_path / "ds"
    proc = cli_blocked({"distributed"}, "dataset", *TINY, "launcher=dask", f"out_dir={out}", f"data_dir={tmp_path}")
    _one_error_line(
        proc,
        f"`crater-synth dataset` needs the dask extra (distributed is not installed): pip install -e '{REPO}[dask]'",
    )
    assert not out.exists()


def test_missing_dask_for_a_sharded_detection_set(tmp_path):
    """detection-frames launcher=dask without Dask: one line naming the dask extra, no folder made."""
    out = tmp_path / "det"
    proc = cli_blocked({"distributed"}, "detection-frames", "--out", str(out), "--frames", "1", "launcher=dask")
    _one_error_line(
        proc,
        f"`crater-synth detection-frames` needs the dask extra (distributed is not installed): "
        f"pip install -e '{REPO}[dask]'",
    )
    assert not out.exists()


def test_help_needs_no_extra():
    proc = cli_blocked({"torch"}, "train", "--help")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("Usage: crater-synth train")


@pytest.mark.parametrize("command", RENDER_COMMANDS)
def test_render_commands_import_nothing_beyond_the_render_extra(command):
    """Every project module a render command may import loads without the other extras' libraries (the
    Blender worker's modules, which import bpy and run in the worker process, are checked by
    tests/test_declared_deps.py), and its help shows."""
    # the Dask launchers are imported only for launcher=dask (the dask extra)
    modules = closure(
        MODULES[command], stop={"crater_synth.dataset.dask_launcher", "crater_synth.dataset.detection_dask"}
    )
    host = sorted(m for m in modules if not imports(m)[1] & {"bpy", "mathutils"})
    code = f"import importlib\nfor m in {host!r}:\n    importlib.import_module(m)\n"
    code += f"from crater_synth.cli import main\nmain([{command!r}, '--help'], prog_name='crater-synth')\n"
    proc = run_blocked(NOT_RENDER, code)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.startswith(f"Usage: crater-synth {command}")


@pytest.mark.integration
def test_a_smoke_render_without_the_other_extras(tmp_path):
    """`crater-synth dataset` renders the four renders of sweep=smoke at the tiny settings with torch,
    Dask, pyarrow, scikit-learn and Jinja2 missing."""
    out = tmp_path / "ds"
    proc = cli_blocked(NOT_RENDER, "dataset", *TINY, f"data_dir={tmp_path / 'data'}", f"out_dir={out}", timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert '"rendered": 4' in proc.stdout
    assert len(list(out.rglob("*.exr"))) == 4


def test_bench_checks_the_extra_of_the_parts_it_runs(tmp_path):
    """`bench --part P` needs P's extra only: without Dask the detector part runs (here it finds no frames
    and says so), the distributed part, and the whole bench, end in the dask extra's line."""
    from crater_synth.bench.cli import PARTS
    from crater_synth.cli import BENCH_PART_EXTRA

    assert set(BENCH_PART_EXTRA) == set(PARTS) and set(BENCH_PART_EXTRA.values()) <= set(EXTRA_MODULES)
    frames = str(tmp_path / "none")
    proc = cli_blocked({"distributed"}, "bench", "--part", "detector", "--detector-frames", frames)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f"detector skipped: no frames at {frames}" in proc.stdout
    pip = f"pip install -e '{REPO}[dask]'"
    proc = cli_blocked({"distributed"}, "bench", "--part", "distributed")
    _one_error_line(proc, f"`crater-synth bench` needs the dask extra (distributed is not installed): {pip}")
    proc = cli_blocked({"distributed"}, "bench")
    assert proc.returncode == 2 and "needs the all extra (distributed is not installed)" in proc.stderr
