"""The output-folder contract (crater_synth/outfolder.py) for the writers of a shared run_dir (`train`,
`evaluate`, `loop`: crater_synth/evaluation/run_folder.py), the lock of `report` and `nav-frames-relabel`,
and the single-file writer `landmarks`. Training, rendering and map building are replaced by fakes that
write files as the real ones do, so every test runs in well under a second."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml
from click.testing import CliRunner

from crater_synth.evaluation import classifiers, closed_loop
from crater_synth.evaluation.run_folder import LOOP_FILES, run_writer
from crater_synth.navigation.map import cli as map_cli
from crater_synth.navigation.map import landmarks as lmap
from crater_synth.navigation.rendered.labels import nav_frames_relabel_command
from crater_synth.outfolder import LOCK_NAME, MARKERS, SHARED, OutFolder, file_lock
from crater_synth.report.build import report_command
from train.registry import ARTEFACTS, MODELS
from train.runs import EVALUATE_FILES, SUMMARY_FILE, TRAIN_FILES

from helpers.cli import QUICK_TRAIN

ARGS = ["train.progress=false"]
RUN_MARKER = SHARED["run"][0]
BUSY = "is being written by another crater-synth process (pid "
PNG = b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + b"\x00" * 13 + b"tEXtSoftware\x00Matplotlib version3" + b"\x00" * 64


def write_run(folder: Path, tag: str) -> dict[str, bytes]:
    """The files of one training run, as `train` writes them (the summary records each model's sha256)."""
    folder.mkdir(parents=True, exist_ok=True)
    files = {name: f"{tag} weights of {name}".encode() for name in ARTEFACTS}
    summary = {
        "run_id": tag,
        "class_names": ["a", "b"],
        "train_images": 4,
        "artefacts": {name: hashlib.sha256(data).hexdigest() for name, data in files.items()},
    }
    files[SUMMARY_FILE] = json.dumps(summary).encode()
    files["config.yaml"] = yaml.safe_dump({"train": {"seed": 0}, "sweep": {"name": tag}, "model": {}}).encode()
    metrics = {m: {"real_accuracy": 0.5, "val_accuracy": None} for m in MODELS}
    metrics.update(train_images=1, test_images=2, test_sources=["x"], limits="none", run_id=tag)
    files["metrics.json"] = json.dumps(metrics).encode()
    files["realset.jsonl"] = b"".join(json.dumps({f"pred_{m}": "a", "tag": tag}).encode() + b"\n" for m in MODELS)
    files.update({f"confusion_{m}.png": PNG + tag.encode() for m in MODELS})
    assert sorted(files) == sorted(TRAIN_FILES)
    for name, data in files.items():
        (folder / name).write_bytes(data)
    return files


def fake_train(settings, progress=None):
    files = write_run(Path(settings.run_dir), f"run-{os.urandom(4).hex()}")
    return json.loads(files["metrics.json"])


def fake_evaluate(settings, progress=None, kept=None):
    metrics = json.loads((Path(settings.run_dir) / "metrics.json").read_text())
    metrics["run_id"] = "evaluated"
    (Path(settings.run_dir) / "metrics.json").write_text(json.dumps(metrics))
    return metrics


def _no_training(*_a, **_k):
    pytest.fail("the training ran in a folder it must refuse")


def _train(run_dir, monkeypatch, fake=fake_train):
    monkeypatch.setattr(classifiers, "train_and_evaluate", fake)
    return CliRunner().invoke(classifiers.train_command, [f"run_dir={run_dir}", *ARGS])


def _listed(run_dir: Path) -> dict:
    return json.loads((run_dir / RUN_MARKER).read_text())["files"]


def _tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# -- train / evaluate / loop in a shared run_dir ---------------------------------------------------------


def test_a_users_own_file_of_a_runs_name_is_refused_and_untouched(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "lunarnet_ex.pt").write_bytes(b"my own weights")  # no summary records it: not a run's
    result = _train(run_dir, monkeypatch, _no_training)
    assert result.exit_code != 0
    (line,) = [x for x in result.output.splitlines() if x.strip()]
    assert f"holds {run_dir / 'lunarnet_ex.pt'}, which crater-synth did not write" in line
    assert _tree(run_dir) == {"lunarnet_ex.pt": b"my own weights"}  # no marker, no lock left


def test_a_users_metrics_file_is_refused_by_evaluate_too(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    write_run(run_dir, "old")
    (run_dir / "metrics.json").write_text("my notes, not metrics")
    monkeypatch.setattr(classifiers, "evaluate_saved", _no_training)
    result = CliRunner().invoke(classifiers.evaluate_command, [f"run_dir={run_dir}", *ARGS])
    assert result.exit_code != 0 and f"holds {run_dir / 'metrics.json'}" in result.output
    assert (run_dir / "metrics.json").read_text() == "my notes, not metrics"
    assert not (run_dir / RUN_MARKER).exists() and not (run_dir / LOCK_NAME).exists()


def test_other_commands_files_and_subfolders_are_left_alone(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    others = {
        "navigation/navigation.json": b'{"methods": {}}',  # make navigate-demo NAV_DEMO_DIR=RUN_DIR/navigation
        "navigation/frames_eval.json": b"{}",
        "experiments.csv": b"parameter,count\n",  # crater-synth experiments
        "notes.txt": b"the user's notes",
        "report/index.html": b"<html>crater-synth run report</html>",
        f"report/{MARKERS['report']}": b"{}",
        "previous/20250101T000000Z/metrics.json": b"{}",
    }
    for rel, data in others.items():
        (run_dir / rel).parent.mkdir(parents=True, exist_ok=True)
        (run_dir / rel).write_bytes(data)
    result = _train(run_dir, monkeypatch)
    assert result.exit_code == 0, result.output
    assert {rel: (run_dir / rel).read_bytes() for rel in others} == others
    assert sorted(_listed(run_dir)) == sorted(TRAIN_FILES)  # only the run's own names


def test_a_second_writer_is_refused_naming_the_holder(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    with run_writer(run_dir, TRAIN_FILES):  # a training still running
        result = _train(run_dir, monkeypatch, _no_training)
        assert result.exit_code != 0 and BUSY in result.output, result.output
        monkeypatch.setattr(closed_loop, "run_loop", _no_training)
        result = CliRunner().invoke(closed_loop.loop_command, [f"run_dir={run_dir}", *ARGS])
        assert result.exit_code != 0 and BUSY in result.output, result.output
    assert (run_dir / RUN_MARKER).is_file()  # the holder's marker stays


def test_a_rerun_replaces_its_own_files_and_lists_them(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    assert _train(run_dir, monkeypatch).exit_code == 0
    first = _tree(run_dir)
    result = _train(run_dir, monkeypatch)
    assert result.exit_code == 0, result.output
    second = _tree(run_dir)
    assert second[SUMMARY_FILE] != first[SUMMARY_FILE]
    listed = _listed(run_dir)
    for name in TRAIN_FILES:
        st = (run_dir / name).stat()
        assert listed[name] == [st.st_size, st.st_mtime_ns]
    # evaluate replaces the metrics train wrote: one marker for the run writers
    monkeypatch.setattr(classifiers, "evaluate_saved", fake_evaluate)
    result = CliRunner().invoke(classifiers.evaluate_command, [f"run_dir={run_dir}", *ARGS])
    assert result.exit_code == 0, result.output
    assert json.loads((run_dir / "metrics.json").read_text())["run_id"] == "evaluated"


def test_a_run_dir_from_before_markers_is_adopted_and_a_changed_file_proves_itself(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    write_run(run_dir, "old")  # no marker: proved by content (the summary records each model's sha256)
    result = _train(run_dir, monkeypatch)
    assert result.exit_code == 0, result.output
    assert sorted(_listed(run_dir)) == sorted(TRAIN_FILES)
    # a run killed between two renames: a listed file changed since, still a run's file by its content
    write_run(run_dir, "killed")
    assert _train(run_dir, monkeypatch).exit_code == 0
    # but not a model that its run's summary does not record
    (run_dir / "hog_svm.joblib").write_bytes(b"the user's svm")
    result = _train(run_dir, monkeypatch, _no_training)
    assert result.exit_code != 0 and f"holds {run_dir / 'hog_svm.joblib'}" in result.output
    assert (run_dir / "hog_svm.joblib").read_bytes() == b"the user's svm"


def test_a_refused_run_leaves_no_folder_where_there_was_none(tmp_path, monkeypatch):
    from crater_synth.errors import UserError

    run_dir = tmp_path / "a" / "run"

    def refused(settings, progress=None):
        raise UserError("train.dataset_dir=x holds no manifest")

    result = _train(run_dir, monkeypatch, refused)
    assert result.exit_code != 0 and "holds no manifest" in result.output
    assert not (tmp_path / "a").exists()


def test_train_into_its_own_dataset_folder_is_refused_and_nothing_is_written(tmp_path, monkeypatch):
    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / MARKERS["dataset"]).write_text("crater-synth dataset\n")
    monkeypatch.setattr(classifiers, "train_and_evaluate", _no_training)
    result = CliRunner().invoke(classifiers.train_command, [f"run_dir={ds}", f"train.dataset_dir={ds}", *ARGS])
    assert result.exit_code != 0 and "rendered dataset" in result.output
    assert sorted(p.name for p in ds.iterdir()) == [MARKERS["dataset"]]


LOOP_BASE = ["crater=shackleton", "sweep=smoke", "sweep.sun_elevation.values=null", "loop.sun_elevation_schedule=[1,2]"]


def _loop(tmp_path, run_dir, monkeypatch, *extra):
    monkeypatch.setattr(closed_loop, "build_dataset", lambda s, progress=None: {"rendered": 1, "skipped_existing": 0})
    monkeypatch.setattr(closed_loop, "train_and_evaluate", fake_train)
    monkeypatch.setattr(closed_loop, "plot_history", lambda hist, png: Path(png).write_bytes(PNG))
    args = [*LOOP_BASE, f"data_dir={tmp_path}/data", f"out_dir={tmp_path}/ds", f"run_dir={run_dir}", *extra]
    return CliRunner().invoke(closed_loop.loop_command, args)


def test_navigate_demo_then_loop_train_evaluate_share_the_run_dir(tmp_path, monkeypatch):
    """`make navigate-demo NAV_DEMO_DIR=RUN_DIR/navigation`, then `make demo` (loop, report) and a train and
    evaluate into the same RUN_DIR: each writer keeps its own files, none refuses another's."""
    run_dir = tmp_path / "run"
    nav = {"navigation/navigation.json": b'{"methods": {}}', "navigation/window_0.png": PNG}
    for rel, data in nav.items():
        (run_dir / rel).parent.mkdir(parents=True, exist_ok=True)
        (run_dir / rel).write_bytes(data)
    result = _loop(tmp_path, run_dir, monkeypatch)  # the rounds train in-process under the loop's hold
    assert result.exit_code == 0, result.output
    listed = _listed(run_dir)
    assert {"loop_history.json", "rounds/round0-sun1/lunarnet_ex.pt", "rounds/round1-sun2/round_identity.json"} <= set(
        listed
    )
    assert not any(rel.startswith("navigation/") for rel in listed)
    assert _loop(tmp_path, run_dir, monkeypatch).exit_code == 0  # a rerun reuses its rounds
    assert _train(run_dir, monkeypatch).exit_code == 0
    monkeypatch.setattr(classifiers, "evaluate_saved", fake_evaluate)
    assert CliRunner().invoke(classifiers.evaluate_command, [f"run_dir={run_dir}", *ARGS]).exit_code == 0
    assert {rel: (run_dir / rel).read_bytes() for rel in nav} == nav
    assert (run_dir / "loop_history.json").is_file()  # train and evaluate leave the loop's files alone


def test_a_loop_run_dir_from_before_markers_is_adopted_but_a_users_round_file_refused(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    assert _loop(tmp_path, run_dir, monkeypatch).exit_code == 0
    (run_dir / RUN_MARKER).unlink()  # as the previous version left it
    assert _loop(tmp_path, run_dir, monkeypatch).exit_code == 0
    assert set(_listed(run_dir)) >= {n for n in LOOP_FILES if (run_dir / n).exists()}
    (run_dir / RUN_MARKER).unlink()
    (run_dir / "rounds" / "round0-sun1" / "metrics.json").write_text("mine")
    result = _loop(tmp_path, run_dir, monkeypatch)
    assert result.exit_code != 0 and "round0-sun1/metrics.json, which crater-synth did not write" in result.output
    assert (run_dir / "rounds" / "round0-sun1" / "metrics.json").read_text() == "mine"


# -- report and nav-frames-relabel hold the lock ------------------------------------------------------------


def test_report_is_refused_while_a_run_writer_holds_the_run_dir(tmp_path):
    run_dir = tmp_path / "run"
    write_run(run_dir, "old")
    with run_writer(run_dir, TRAIN_FILES):
        result = CliRunner().invoke(report_command, [str(run_dir)])
        assert result.exit_code != 0 and BUSY in result.output, result.output
    assert not (run_dir / "report").exists()
    # and a run writer is refused while a report holds it
    holder = OutFolder(run_dir, "run", flag="RUN_DIR").lock()
    try:
        with pytest.raises(Exception, match="being written by another crater-synth process"):
            with run_writer(run_dir, TRAIN_FILES):
                pass
    finally:
        holder.release()


def test_nav_frames_relabel_is_refused_while_nav_frames_writes_the_folder(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "manifest.jsonl").write_text('{"trajectory": "t"}\n')
    holder = OutFolder(frames, "navframes", subject="t").claim()  # a nav-frames run, still rendering
    try:
        before = _tree(frames)
        result = CliRunner().invoke(nav_frames_relabel_command, [str(frames)])
        assert result.exit_code != 0 and BUSY in result.output, result.output
        assert _tree(frames) == before
    finally:
        holder.release()


# -- landmarks: a single-file writer ---------------------------------------------------------------------


def _fake_build(monkeypatch, calls):
    dem = SimpleNamespace(pixel_size_m=200.0)
    monkeypatch.setattr(map_cli, "open_dem_entry", lambda *a, **k: (dem, "0" * 64))
    monkeypatch.setattr(lmap, "dem_size_limits", lambda d: {"min_diameter_km": 10.0})
    monkeypatch.setattr(lmap, "parameters", lambda limits: dict(limits))
    lm = lmap.Landmark("L1", "A", -89.0, 10.0, 1.0, 2.0, 20.0, 1000.0, 100.0, 900.0, 0.9, "dem")

    def build(*a, **k):
        calls.append("build")
        return [lm], {"candidates": 1, "catalogue": {}}

    monkeypatch.setattr(lmap, "build_map", build)
    monkeypatch.setattr(map_cli, "catalogue_check", lambda *a, **k: {"source": "fake"})
    monkeypatch.setattr(map_cli, "catalogue_table", lambda c: "")
    monkeypatch.setattr(map_cli, "map_figure", lambda *a, **k: PNG + b"figure")


def _landmarks(out, figure, *extra):
    args = ["--out", str(out), "--figure", str(figure), *extra, "nav.landmarks.iau_check=false"]
    return CliRunner().invoke(map_cli.landmarks_command, args)


def test_landmarks_refuses_to_replace_a_file_it_did_not_write(tmp_path, monkeypatch):
    calls: list = []
    _fake_build(monkeypatch, calls)
    out, figure = tmp_path / "thesis.geojson", tmp_path / "figure.png"
    out.write_text('{"type": "FeatureCollection", "features": []}')
    result = _landmarks(out, tmp_path / "map.png")
    assert result.exit_code != 0 and "is not a landmark map crater-synth landmarks wrote" in result.output
    assert out.read_text() == '{"type": "FeatureCollection", "features": []}' and calls == []
    figure.write_text("a drawing")
    result = _landmarks(tmp_path / "map.geojson", figure)
    assert result.exit_code != 0 and "is not a map figure crater-synth wrote" in result.output
    assert figure.read_text() == "a drawing" and calls == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["figure.png", "thesis.geojson"]


def test_landmarks_refuses_an_output_that_is_its_input(tmp_path, monkeypatch):
    calls: list = []
    _fake_build(monkeypatch, calls)
    out, figure = tmp_path / "map.geojson", tmp_path / "map.png"
    assert _landmarks(out, figure).exit_code == 0
    before = out.read_bytes()
    result = _landmarks(out, figure, "--add-to", str(out), "nav.landmarks.dem_product=finer")
    assert result.exit_code != 0 and f"is also --out {out}" in result.output
    result = _landmarks(out, out)
    assert result.exit_code != 0 and f"--figure {out} is also --out {out}" in result.output
    assert out.read_bytes() == before and calls == ["build"]


def test_landmarks_replaces_its_own_map_atomically_and_refuses_a_concurrent_build(tmp_path, monkeypatch):
    calls: list = []
    _fake_build(monkeypatch, calls)
    out, figure = tmp_path / "maps" / "map.geojson", tmp_path / "maps" / "map.png"
    assert _landmarks(out, figure).exit_code == 0
    first_inode = out.stat().st_ino
    assert [lm.id for lm in lmap.read_map(out)[0]] == ["L1"]
    result = _landmarks(out, figure)
    assert result.exit_code == 0, result.output
    assert calls == ["build", "build"] and out.stat().st_ino != first_inode  # renamed over, not rewritten
    assert sorted(p.name for p in out.parent.iterdir()) == ["map.geojson", "map.png"]  # no temp, no lock left
    with file_lock(out, "--out"):  # another build of this map, still measuring
        result = _landmarks(out, figure)
    assert result.exit_code != 0 and f"--out {out} {BUSY}" in result.output and calls == ["build", "build"]
    result = _landmarks(tmp_path / "new" / "map.geojson", tmp_path / "new" / "map.png", "nav.landmarks.workers=0")
    assert result.exit_code != 0 and not (tmp_path / "new").exists()  # a refused build leaves no folder


# -- the proofs match what the real commands write ------------------------------------------------------


@pytest.mark.integration
def test_a_real_run_from_before_markers_is_adopted_by_train_and_evaluate(tmp_path):
    """`train` on the toy set (train/toydata.py, one epoch at 64 px), its marker removed as the previous
    version left it: every file proves itself a run's, so `evaluate` and a retrain replace them."""
    from crater_synth.cli import main
    from train.toydata import write_toy_dataset

    toy = tmp_path / "toy"
    write_toy_dataset(toy, sun_elevations=(15.0, 30.0), sun_azimuths=(0.0, 180.0), cam_azimuths=(0.0, 120.0, 240.0))
    run_dir = tmp_path / "run"
    args = [
        f"train.dataset_dir={toy}",
        f"data_dir={tmp_path}",
        f"run_dir={run_dir}",
        f"train.cache_dir={tmp_path / 'cache'}",
        *QUICK_TRAIN,
    ]
    assert CliRunner().invoke(main, ["train", *args]).exit_code == 0
    assert sorted(_listed(run_dir)) == sorted(TRAIN_FILES)
    (run_dir / RUN_MARKER).unlink()
    result = CliRunner().invoke(main, ["evaluate", *args])
    assert result.exit_code == 0, result.output
    assert sorted(_listed(run_dir)) == sorted(EVALUATE_FILES)  # evaluate keeps its own names only
    (run_dir / RUN_MARKER).unlink()
    before = json.loads((run_dir / SUMMARY_FILE).read_text())["run_id"]
    result = CliRunner().invoke(main, ["train", *args, "train.seed=1"])
    assert result.exit_code == 0, result.output
    assert sorted(_listed(run_dir)) == sorted(TRAIN_FILES)  # the models, config and summary proved too
    assert json.loads((run_dir / SUMMARY_FILE).read_text())["run_id"] != before


def test_the_figures_the_run_writers_draw_prove_themselves(tmp_path):
    import numpy as np

    from crater_synth.evaluation.run_folder import proved
    from train.plots import plot_confusion

    hist = {"threshold": 0.8, "rounds": [{"sun_elevation_count": 1, **{m: 0.5 for m in MODELS}}]}
    closed_loop.plot_history(hist, tmp_path / "loop_history.png")
    plot_confusion(tmp_path / "confusion_hog_svm.png", np.eye(2, dtype=int), ["a", "b"], "title")
    (tmp_path / "confusion_lunarnet_ex.png").write_bytes(b"\x89PNG\r\n\x1a\n a user's own PNG")
    assert [
        proved(tmp_path / n) for n in ("loop_history.png", "confusion_hog_svm.png", "confusion_lunarnet_ex.png")
    ] == [
        True,
        True,
        False,
    ]
