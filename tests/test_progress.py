"""Logs: redirected to a file, progress is one newline-terminated line every few seconds with
the rate and the ETA -- never a carriage return -- while a terminal keeps its tqdm bar; the training
cache build reports progress even with `train.progress=false`."""

import io
import os
import re
import subprocess

from helpers.cli import REPO, TINY, cli_command, summary

LINE = re.compile(
    r"^rendering \(fast\): (\d+)/8 renders \(\d+ %\), [0-9.]+ renders/s, "
    r"(elapsed \d:\d\d:\d\d, ETA (\d:\d\d:\d\d|\?)|done in \d:\d\d:\d\d)$"
)


def test_redirected_output_is_lines_with_rate_and_eta(tmp_path, tiny_data_dir):
    out = tmp_path / "ds"
    log = tmp_path / "stderr.log"
    env = os.environ | {"CRATER_SYNTH_PROGRESS_INTERVAL": "0.05"}  # a line per render here; 5 s by default
    with open(log, "wb") as err:
        proc = subprocess.run(
            [
                *cli_command(),
                "dataset",
                *TINY,
                f"data_dir={tiny_data_dir}",
                f"out_dir={out}",
                "sweep.cam_elevation.count=2",
            ],
            stdout=subprocess.PIPE,
            stderr=err,
            env=env,
            cwd=REPO,
            timeout=600,
        )
    assert proc.returncode == 0, log.read_text()[-3000:]
    assert summary(subprocess.CompletedProcess([], 0, proc.stdout.decode()))["rendered"] == 8
    raw = log.read_bytes()
    assert b"\r" not in raw and raw.endswith(b"\n")
    lines = raw.decode().splitlines()
    assert lines and all(LINE.match(line) for line in lines), lines
    assert lines[-1].startswith("rendering (fast): 8/8 renders (100 %)") and "done in" in lines[-1]
    assert len(lines) <= 8  # one per interval at most, not one per bar refresh


def test_default_interval_is_a_few_seconds(monkeypatch):
    from crater_core import progress

    monkeypatch.delenv(progress.ENV_INTERVAL, raising=False)
    stream = io.StringIO()
    p = progress.Progress(1000, "rendering (fast)", "render", stream=stream)
    for _ in range(999):
        p.update(1)
    assert stream.getvalue() == ""  # all within the first seconds: nothing yet
    p.update(1)
    p.close()
    assert stream.getvalue().count("\n") == 1 and "1000/1000 renders (100 %)" in stream.getvalue()
    assert 2.0 <= progress.DEFAULT_INTERVAL_S <= 10.0


def test_a_terminal_keeps_the_bar():
    from crater_core.progress import Progress

    class Tty(io.StringIO):
        def isatty(self):
            return True

    stream = Tty()
    with Progress(3, "rendering (fast)", "render", stream=stream) as p:
        for _ in range(3):
            p.update(1)
    assert "\r" in stream.getvalue() and "3/3" in stream.getvalue()  # tqdm's bar, redrawn in place


def test_cache_build_reports_progress_without_bars(tmp_path, capfd, monkeypatch):
    """`train.progress=false` turns the bars off, not the news: minutes of crop caching say how far
    they are (here every 0 s, so every file)."""
    from crater_core.schema import load_manifest
    from train.data import build_cache
    from train.preprocess import PreprocessConfig
    from train.toydata import write_toy_dataset

    monkeypatch.setenv("CRATER_SYNTH_PROGRESS_INTERVAL", "0")
    write_toy_dataset(
        tmp_path / "toy",
        sun_elevations=(15.0,),
        sun_azimuths=(0.0,),
        cam_elevations=(90.0,),
        cam_azimuths=(0.0, 180.0),
        rim_px=32.0,
    )
    rows = load_manifest(tmp_path / "toy")
    build_cache(rows, tmp_path / "toy", [1.0], PreprocessConfig(), tmp_path / "cache", progress=False)
    err = capfd.readouterr().err
    lines = err.splitlines()
    assert "\r" not in err and len(lines) == len(rows), err
    assert lines[0].startswith(f"cache crops: 1/{len(rows)} exrs (")
    assert lines[-1].startswith(f"cache crops: {len(rows)}/{len(rows)} exrs (100 %)") and "done in" in lines[-1]
