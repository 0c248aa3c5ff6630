"""Logs: redirected to a file, progress is one newline-terminated line every few seconds with
the rate and the ETA -- never a carriage return -- while a terminal keeps its tqdm bar; the training
cache build reports progress even with `train.progress=false`; verify, export, nav-eval and train's SVM
and HOG stages report through the same class (a fake clock drives their lines, no sleeping)."""

import io
import os
import re
import subprocess

import pytest

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


# ------------------------------------------------------------------------------------------------
# Every long loop reports through crater_core.progress.Progress: driven here with a fake clock that
# moves 10 s per reading (so each step is past the 5 s interval and prints its line), no sleeping.
# ------------------------------------------------------------------------------------------------
ETA = re.compile(r", elapsed \d+:\d\d:\d\d, ETA \d+:\d\d:\d\d")


class FakeClock:
    def __init__(self, step_s: float = 10.0):
        self.t, self.step_s = 1000.0, step_s

    def __call__(self) -> float:
        self.t += self.step_s
        return self.t


@pytest.fixture
def fake_clock(monkeypatch):
    from crater_core import progress

    monkeypatch.delenv(progress.ENV_INTERVAL, raising=False)
    clock = FakeClock()
    monkeypatch.setattr(progress, "monotonic", clock)
    return clock


def _progress_lines(text: str, desc: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith(f"{desc}: ")]


def _assert_counted(text: str, desc: str, total: int, units: str) -> list[str]:
    """``desc``'s lines in ``text``: some with the count, rate and ETA, the last one with the total done."""
    lines = _progress_lines(text, desc)
    mid = [line for line in lines[:-1] if ETA.search(line)]
    count = re.compile(rf"{re.escape(desc)}: \d+/{total} {units} \(\d+ %\), [0-9.]+ {units}/s")
    assert mid and all(count.match(line) for line in mid), lines
    assert lines[-1].startswith(f"{desc}: {total}/{total} {units} (100 %)") and "done in" in lines[-1], lines
    return lines


def test_fake_clock_gives_a_line_per_step_with_rate_and_eta(fake_clock):
    from crater_core.progress import Progress

    stream = io.StringIO()
    with Progress(4, "job", "batch", stream=stream) as p:
        for _ in range(4):
            p.update(1, loss="0.5")
    lines = stream.getvalue().splitlines()
    # readings: start 1010; updates at 1020, 1030, 1040 (the 4th is the end: no mid line); close at 1060
    assert lines == [
        "job: 1/4 batches (25 %), 0.10 batches/s, elapsed 0:00:10, ETA 0:00:30, loss 0.5",
        "job: 2/4 batches (50 %), 0.10 batches/s, elapsed 0:00:20, ETA 0:00:20, loss 0.5",
        "job: 3/4 batches (75 %), 0.10 batches/s, elapsed 0:00:30, ETA 0:00:10, loss 0.5",
        "job: 4/4 batches (100 %), 0.08 batches/s, done in 0:00:50, loss 0.5",
    ]


def test_stage_lines_and_write(fake_clock):
    from crater_core.progress import Progress

    stream = io.StringIO()
    with Progress.stage("fit", 125.0, "a subset took 5 s", stream=stream):
        pass
    with Progress.stage("other", stream=stream):
        Progress(1, "inner", "step", stream=stream).write("a message")
    with pytest.raises(RuntimeError), Progress.stage("broken", stream=stream):
        raise RuntimeError
    assert stream.getvalue().splitlines() == [
        "fit: started, ETA 0:02:05 (a subset took 5 s)",
        "fit: done in 0:00:10",
        "other: started, no estimate",
        "a message",
        "other: done in 0:00:20",
        "broken: started, no estimate",
        "broken: failed after 0:00:10",
    ]
    silent = io.StringIO()
    with Progress.stage("quiet", 1.0, mode="off", stream=silent):
        Progress(1, "inner", "step", mode="off", stream=silent).write("not shown")
    assert silent.getvalue() == ""


def test_log_gets_lines_terminal_gets_the_bar(fake_clock):
    """The same calls: in a log (no TTY) newline-terminated lines only; on a TTY tqdm's bar, redrawn in
    place, and a message written through it lands on its own line."""
    from crater_core.progress import Progress

    class Tty(io.StringIO):
        def isatty(self):
            return True

    def drive(stream):
        with Progress(3, "loop", "item", stream=stream) as p:
            for _ in range(3):
                p.update(1, acc="0.9")
                p.write("note")
        return stream.getvalue()

    log = drive(io.StringIO())
    assert "\r" not in log and log.endswith("\n") and "\x1b" not in log
    assert [line for line in log.splitlines() if line != "note"] == _assert_counted(log, "loop", 3, "items")
    tty = drive(Tty())
    assert "\r" in tty and "3/3" in tty and "acc=0.9" in tty and "\nnote\n" in tty.replace("\r", "\n")


def test_verify_reports_files_with_eta(tmp_path, fake_clock):
    from click.testing import CliRunner

    from crater_synth.bench.export import make_dataset
    from crater_synth.dataset.verify import verify_command

    d = make_dataset(tmp_path / "ds", 3)  # benchmark files: labelled and sealed like renders
    res = CliRunner().invoke(verify_command, [str(d), "--jobs", "1"])
    assert "\r" not in res.stderr
    _assert_counted(res.stderr, "verify", 3, "files")
    assert res.stdout.startswith("verify OK: 3 rows"), res.output


def test_export_reports_samples_with_eta(tmp_path, fake_clock):
    from click.testing import CliRunner

    from crater_synth.bench.export import make_dataset
    from crater_synth.dataset.export import export_command

    d = make_dataset(tmp_path / "ds", 4)
    args = [str(d), "--format", "parquet", "--out", str(tmp_path / "pq"), "--row-group-rows", "1", "--shard-rows", "2"]
    res = CliRunner().invoke(export_command, args)
    assert res.exit_code == 0, res.output
    _assert_counted(res.stderr, "export", 4, "samples")


def test_nav_eval_windows_report_with_eta(fake_clock, capsys):
    """nav-eval's per-window loop (:func:`navigate_windows`, which ``evaluate_split`` runs) with a stub window."""
    from crater_synth.navigation.windows.evaluate import navigate_windows

    rows = navigate_windows([1, 2, 3], lambda f: {"window": f}, "nav-eval south test", progress=True)
    assert rows == [{"window": 1}, {"window": 2}, {"window": 3}]
    _assert_counted(capsys.readouterr().err, "nav-eval south test", 3, "windows")
    navigate_windows([1, 2], lambda f: {}, "nav-eval south test", progress=False)
    assert capsys.readouterr().err == ""


def test_svm_fit_stage_has_an_eta_from_a_subset(fake_clock, capsys):
    import numpy as np

    from crater_core.settings import SvmSettings
    from train.models import make_linear_svm
    from train.trainer import fit_svm

    rng = np.random.default_rng(0)
    X, y = rng.normal(size=(400, 8)).astype(np.float32), rng.integers(0, 3, 400)
    svm = make_linear_svm(SvmSettings(alpha=1e-3, max_iter=20, tol=1e-3), 0)
    fit_svm(svm, X, y, "lunarsvm_ex", "auto")
    svm.predict(X)  # fitted
    err = capsys.readouterr().err.splitlines()
    desc = "lunarsvm_ex: SVM fit on 400 crops x 8 features"
    assert re.fullmatch(rf"{desc}: started, ETA \d+:\d\d:\d\d \(a fit on 40 of them took [0-9.]+ s\)", err[0]), err
    assert err[1:] == [f"{desc}: done in 0:00:10"]


def test_train_svm_and_hog_stages_report(tmp_path, fake_clock, capsys):
    """train's SVM and HOG stages on a tiny toy dataset (an untrained LunarNet_ex): the features are
    counted per crop with rate and ETA, each fit is a stage with a start and an end line."""
    import torch

    from crater_synth.config import load_settings
    from train.data import build_datasets
    from train.models import LunarNetEx
    from train.toydata import write_toy_dataset
    from train.trainer import model_for, train_svms

    torch.set_num_threads(1)
    write_toy_dataset(
        tmp_path / "toy", sun_elevations=(15.0,), sun_azimuths=(0.0,), cam_elevations=(90.0,), cam_azimuths=(0.0, 180.0)
    )
    settings = load_settings(
        [
            f"train.dataset_dir={tmp_path / 'toy'}",
            f"data_dir={tmp_path}",
            f"run_dir={tmp_path}/run",
            f"train.cache_dir={tmp_path}/cache",
            "train.num_threads=1",
            "train.eval_batch_size=4",
        ]
    )
    data = build_datasets(settings, progress=False)
    capsys.readouterr()
    model = LunarNetEx(model_for(settings.model, data.class_names))
    out = train_svms(model, data, settings, progress=True)
    err = capsys.readouterr().err
    assert "\r" not in err
    n_train, n_val = len(data.train), len(data.val)
    _assert_counted(err, "lunarsvm_ex: FC1 features of the training crops", n_train, "crops")
    _assert_counted(err, "lunarsvm_ex: validation", n_val, "crops")
    _assert_counted(err, "hog_svm: HOG of the training crops", n_train, "crops")
    _assert_counted(err, "hog_svm: validation", n_val, "crops")
    for name in ("lunarsvm_ex", "hog_svm"):
        stage = [line for line in err.splitlines() if line.startswith(f"{name}: SVM fit on {n_train} crops")]
        assert len(stage) == 2 and "started" in stage[0] and "done in" in stage[1], err
        assert 0.0 <= out[name]["val_accuracy"] <= 1.0
