"""Paths and inputs: a directory that cannot be made, an empty run directory, an unreadable
DEM -- each ONE `error:` line naming the key or path, exit status 2, and nothing half-written."""

import subprocess
import sys

import pytest
from click.testing import CliRunner

from helpers.cli import TINY, run_cli

TOY = dict(
    sun_elevations=(15.0, 30.0), sun_azimuths=(0.0,), cam_elevations=(90.0,), cam_azimuths=(0.0, 180.0), rim_px=32.0
)


def _one_error_line(proc) -> str:
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    return lines[0]


@pytest.mark.parametrize("command", ["dataset", "terrain"])
def test_data_dir_under_a_regular_file(tmp_path, command):
    (tmp_path / "a-file").write_text("x")
    data_dir, out = tmp_path / "a-file" / "data", tmp_path / "ds"
    proc = run_cli(command, *TINY, f"data_dir={data_dir}", f"out_dir={out}")
    assert _one_error_line(proc) == (
        f"error: data_dir={data_dir}: cannot create the directory: "
        f"{tmp_path / 'a-file'} is a regular file, not a directory"
    )
    assert (tmp_path / "a-file").read_text() == "x"
    assert not out.exists()  # nothing written: the output directory was not even made


def test_run_dir_under_a_regular_file_fails_before_caching(tmp_path):
    """`train` used to cache every crop first, then fail on run_dir with a traceback."""
    from train.toydata import write_toy_dataset

    write_toy_dataset(tmp_path / "toy", **TOY)
    (tmp_path / "a-file").write_text("x")
    run_dir, cache = tmp_path / "a-file" / "run", tmp_path / "cache"
    proc = run_cli(
        "train",
        f"train.dataset_dir={tmp_path / 'toy'}",
        f"run_dir={run_dir}",
        f"data_dir={tmp_path}",
        f"train.cache_dir={cache}",
        "train.num_threads=1",
        "train.progress=false",
        "realset.per_crater=2",
    )
    assert _one_error_line(proc) == (
        f"error: run_dir={run_dir}: cannot create the directory: "
        f"{tmp_path / 'a-file'} is a regular file, not a directory"
    )
    assert not cache.exists()


def test_report_of_an_empty_directory_is_an_error(tmp_path):
    from crater_synth.cli import main

    run = tmp_path / "typo_run"
    run.mkdir()
    res = CliRunner().invoke(main, ["report", str(run), f"train.dataset_dir={tmp_path}/none"])
    assert res.exit_code == 2, res.output
    assert res.stderr.splitlines() == [
        f"error: run directory {run} holds no run to report (none of metrics.json, loop_history.json, "
        "experiments.csv, train_summary.json, config.yaml, ablation.json, navigation/): "
        "run `crater-synth train run_dir=RUN_DIR` first, or give the run_dir it wrote"
    ]
    assert list(run.iterdir()) == []  # no page of "not run" sections


def test_dem_error_is_not_preceded_by_a_library_warning(tmp_path):
    """A GeoTIFF without georeferencing: rasterio warns (NotGeoreferencedWarning) before the DEM is
    refused; the error line must be the only line."""
    dem = tmp_path / "nogeo.tif"
    code = (
        "import numpy as np, rasterio, warnings; warnings.simplefilter('ignore');"
        f"d = rasterio.open({str(dem)!r}, 'w', driver='GTiff', width=16, height=16, count=1, dtype='int16');"
        "d.write(np.zeros((1, 16, 16), 'int16')); d.close()"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    proc = run_cli("terrain", *TINY, f"data_dir={tmp_path / 'data'}", f"dem.path={dem}")
    assert _one_error_line(proc) == f"error: DEM {dem} has no coordinate reference system"
    assert not list((tmp_path / "data").rglob("*.npz"))


def test_library_warnings_of_a_successful_command_are_kept(tmp_path):
    """Held back, not dropped: when the command succeeds they follow as `warning:` lines."""
    import warnings

    import click

    from crater_synth.cli_common import user_errors

    @click.command()
    @user_errors
    def noisy():
        warnings.warn("something odd", UserWarning, stacklevel=1)
        click.echo("result")

    res = CliRunner().invoke(noisy, [])
    assert res.exit_code == 0 and res.stdout == "result\n"
    assert res.stderr.splitlines() == ["warning: something odd"]
