"""Training never uses a dataset that `verify` rejects, never mixes the models of two runs, and refuses
bad input up front with one line, leaving no run directory behind.

All on the procedural toy dataset (train/toydata.py), trained for one epoch at 64 px."""

import json
import shutil
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from crater_core import schema
from crater_synth.config import load_settings
from crater_synth.outfolder import LOCK_NAME, SHARED
from train.registry import ARTEFACTS
from train.toydata import write_toy_dataset

from helpers.cli import QUICK_TRAIN

torch.set_num_threads(1)
TOY = dict(
    sun_elevations=(15.0, 30.0),
    sun_azimuths=(0.0, 180.0),
    cam_elevations=(90.0,),
    cam_azimuths=(0.0, 120.0, 240.0),
    rim_px=24.0,
)
QUICK = list(QUICK_TRAIN)


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    d = tmp_path_factory.mktemp("toy_integrity")
    write_toy_dataset(d, **TOY)
    return d


def _overrides(dataset, tmp: Path, run: str = "run", *extra) -> list[str]:
    return [
        f"train.dataset_dir={dataset}",
        f"data_dir={tmp}",
        f"run_dir={tmp / run}",
        f"train.cache_dir={tmp / 'cache'}",
        *QUICK,
        *extra,
    ]


def _cli(*args):
    from crater_synth.cli import main

    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def _one_error(res, *needles: str) -> str:
    assert res.exit_code == 2, res.output
    lines = [line for line in res.output.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "Traceback" not in res.output, res.output
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


def _copy(toy: Path, tmp: Path) -> Path:
    d = tmp / "ds"
    shutil.copytree(toy, d)
    return d


def _rows(d: Path) -> list[dict]:
    return [json.loads(x) for x in (d / "manifest.jsonl").read_text().splitlines()]


def _write(d: Path, rows: list[dict]) -> None:
    (d / "manifest.jsonl").write_text("".join(schema.dumps_row(r) + "\n" for r in rows))


# -- no training on a dataset that verify rejects ---------------------------------------------------------
def test_train_refuses_a_duplicate_row_with_a_flipped_label(toy, tmp_path):
    d = _copy(toy, tmp_path)
    rows = _rows(d)
    _write(d, rows + [dict(rows[5], crater="de_gerlache" if rows[5]["crater"] != "de_gerlache" else "shoemaker")])
    res = _cli("train", *_overrides(d, tmp_path))
    _one_error(res, "duplicate path " + rows[5]["path"], "crater-synth verify")
    assert not (tmp_path / "run").exists()


def test_train_refuses_a_row_whose_label_the_exr_contradicts(toy, tmp_path):
    d = _copy(toy, tmp_path)
    rows = _rows(d)
    rows[4]["sun_azimuth"] = 90.0  # no duplicate, valid row, right sha256: only the header knows
    _write(d, rows)
    res = _cli("train", *_overrides(d, tmp_path))
    _one_error(res, f"{d / rows[4]['path']}: row sun_azimuth 90 but the EXR header says 180")
    assert not (tmp_path / "run").exists()


def test_train_refuses_a_relabelled_crater(toy, tmp_path):
    d = _copy(toy, tmp_path)
    rows = _rows(d)
    old = rows[0]["crater"]
    rows[0]["crater"] = new = next(r["crater"] for r in rows if r["crater"] != old)
    # the toy grid is the same for every crater: drop the true row of that render, or it is a duplicate
    rows = [r for r in rows if r is rows[0] or schema.row_key(r) != schema.row_key(rows[0])]
    assert sum(r["crater"] == new for r in rows) == 12
    _write(d, rows)
    _one_error(_cli("train", *_overrides(d, tmp_path)), f"row crater {rows[0]['crater']!r}", f"says {old!r}")


@pytest.mark.parametrize("how", ["dotdot", "absolute", "symlink"])
def test_train_refuses_a_file_outside_the_dataset(toy, tmp_path, how):
    d = _copy(toy, tmp_path)
    rows = _rows(d)
    outside = tmp_path / "outside.exr"
    shutil.copy(d / rows[2]["path"], outside)
    if how == "symlink":
        (d / rows[2]["path"]).unlink()
        (d / rows[2]["path"]).symlink_to(outside)
    else:
        rows[2]["path"] = "../outside.exr" if how == "dotdot" else str(outside)
        _write(d, rows)
    _one_error(_cli("train", *_overrides(d, tmp_path)), "leaves the dataset directory")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("bad", [b"null", b"42", b'{"crater": "\xff"}'], ids=["null", "number", "not-utf8"])
def test_train_names_an_unreadable_manifest_line(toy, tmp_path, bad):
    d = _copy(toy, tmp_path)
    raw = (d / "manifest.jsonl").read_bytes().splitlines()
    raw[6] = bad
    (d / "manifest.jsonl").write_bytes(b"\n".join(raw) + b"\n")
    _one_error(_cli("train", *_overrides(d, tmp_path)), f"{d / 'manifest.jsonl'}:7: unreadable row (")


# -- bad input refused up front, nothing left behind ----------------------------------------------------
def test_one_crater_training_is_refused_before_any_training(toy, tmp_path, monkeypatch):
    import train.trainer

    monkeypatch.setattr(train.trainer, "train_lunarnet", lambda *a, **k: pytest.fail("trained with one class"))
    res = _cli("train", *_overrides(toy, tmp_path / "x"), "crater=shackleton")
    _one_error(res, "crater=", "one crater (shackleton)", "at least two")
    assert not (tmp_path / "x").exists()


def test_a_cache_dir_that_is_a_file_names_the_key(toy, tmp_path):
    blocker = tmp_path / "cachefile"
    blocker.write_text("not a directory")
    res = _cli("train", *_overrides(toy, tmp_path), f"train.cache_dir={blocker}")
    _one_error(res, f"train.cache_dir={blocker}: cannot create the directory", "is a regular file")
    assert not (tmp_path / "run").exists()


def test_refused_train_and_evaluate_leave_no_run_dir(tmp_path):
    res = _cli("train", *_overrides(tmp_path / "nodata", tmp_path, "new/run"))
    _one_error(res, "no manifest.jsonl")
    res = _cli("evaluate", *_overrides(tmp_path / "nodata", tmp_path, "other/run"))
    _one_error(res, "no trained LunarNet_ex")
    assert not (tmp_path / "new").exists() and not (tmp_path / "other").exists()


def test_loop_checks_its_whole_schedule_before_round_0(toy, tmp_path, monkeypatch):
    from crater_synth.evaluation import closed_loop

    monkeypatch.setattr(closed_loop, "build_dataset", lambda *a, **k: pytest.fail("round 0 started"))
    res = _cli(
        "loop",
        *_overrides(toy, tmp_path),
        "sweep.sun_elevation.values=[1.0,2.0]",
        "loop.sun_elevation_schedule=[1,3]",
    )
    _one_error(res, "loop.sun_elevation_schedule asks for 3 sun elevations", "has only 2")
    assert not (tmp_path / "run").exists()


# -- no mixed models -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def two_runs(toy, tmp_path_factory):
    """Two finished runs of the toy set with different seeds."""
    tmp = tmp_path_factory.mktemp("two_runs")
    for seed in (0, 1):
        res = _cli("train", *_overrides(toy, tmp, f"run{seed}", f"train.seed={seed}"))
        assert res.exit_code == 0, res.output
    return tmp


def _files(run: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(run.iterdir()) if p.is_file()}


@pytest.mark.integration
def test_an_interrupted_retrain_leaves_the_previous_run_whole(toy, two_runs, tmp_path, monkeypatch):
    """Ctrl-C after LunarNet_ex has trained (and checkpointed): the run directory still holds the old
    run, file for file, and evaluates to the old metrics."""
    import train.trainer
    from train.pipeline import train_and_evaluate

    run = tmp_path / "run"
    shutil.copytree(two_runs / "run0", run)
    before = _files(run)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(train.trainer, "train_svms", interrupted)
    settings = load_settings(_overrides(toy, two_runs, "unused", f"run_dir={run}", "train.seed=7"))
    with pytest.raises(KeyboardInterrupt):
        train_and_evaluate(settings)
    monkeypatch.undo()
    assert _files(run) == before
    hidden = {p.name for p in run.iterdir() if p.name.startswith(".")}
    assert hidden <= {LOCK_NAME, SHARED["run"][0]}  # no staging left (the run_dir's lock and marker stay)
    res = _cli("evaluate", *_overrides(toy, two_runs, "unused", f"run_dir={run}"))
    assert res.exit_code == 0, res.output
    old = json.loads(before["metrics.json"])
    new = json.loads((run / "metrics.json").read_text())
    assert new["train_images"] == old["train_images"]
    assert {m: new[m]["confusion"] for m in ("lunarnet_ex", "lunarsvm_ex", "hog_svm")} == {
        m: old[m]["confusion"] for m in ("lunarnet_ex", "lunarsvm_ex", "hog_svm")
    }


@pytest.mark.integration
@pytest.mark.parametrize("artefact", ARTEFACTS)
def test_evaluate_refuses_models_of_two_runs(toy, two_runs, tmp_path, artefact):
    run = tmp_path / "mixed"
    shutil.copytree(two_runs / "run0", run)
    shutil.copy(two_runs / "run1" / artefact, run / artefact)
    before = _files(run)
    res = _cli("evaluate", *_overrides(toy, two_runs, "unused", f"run_dir={run}"))
    _one_error(res, f"{run} mixes the files of two training runs", artefact)
    assert _files(run) == before  # nothing rewritten


@pytest.mark.integration
def test_evaluate_refuses_models_from_before_run_ids_next_to_new_ones(toy, two_runs, tmp_path):
    """An old run (its files carry no run id) with one model of a new run copied in: refused too."""
    import joblib

    run = tmp_path / "legacy"
    shutil.copytree(two_runs / "run0", run)
    for name in ("lunarsvm_ex.joblib", "hog_svm.joblib"):
        doc = joblib.load(run / name)
        doc.pop("run_id")
        joblib.dump(doc, run / name)
    summary = json.loads((run / "train_summary.json").read_text())
    summary.pop("run_id")
    summary.pop("artefacts")
    (run / "train_summary.json").write_text(json.dumps(summary))
    res = _cli("evaluate", *_overrides(toy, two_runs, "unused", f"run_dir={run}"))
    _one_error(res, "mixes the files of two training runs")


@pytest.mark.integration
def test_a_published_run_records_one_run_id_everywhere(two_runs):
    import joblib

    run = two_runs / "run0"
    summary = json.loads((run / "train_summary.json").read_text())
    rid = summary["run_id"]
    assert torch.load(run / "lunarnet_ex.pt", weights_only=False)["run_id"] == rid
    assert {joblib.load(run / n)["run_id"] for n in ("lunarsvm_ex.joblib", "hog_svm.joblib")} == {rid}
    assert json.loads((run / "metrics.json").read_text())["run_id"] == rid
    assert set(summary["artefacts"]) == set(ARTEFACTS)
    assert summary["artefacts"]["lunarnet_ex.pt"] == schema.sha256_file(run / "lunarnet_ex.pt")
    other = json.loads((two_runs / "run1" / "train_summary.json").read_text())["run_id"]
    assert other != rid
