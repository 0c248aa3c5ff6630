"""`crater-synth evaluate` keeps the metrics files it replaces in run_dir/previous/<UTC time>/."""

from __future__ import annotations

import os
import sys
import types

from click.testing import CliRunner

from train.runs import PREVIOUS_DIR, StagedRun

OLD_TIME = 1_700_000_000  # 2023-11-14T22:13:20Z
# An earlier evaluation's files, as `evaluate` writes them (evaluate replaces only files it can prove are a run's).
OLD_METRICS, OLD_REALSET = '{"lunarnet_ex": {"real_accuracy": 0.4}}', '{"pred_lunarnet_ex": "old"}\n'


def _old_run(run_dir):
    run_dir.mkdir(parents=True)
    for name, text in (("metrics.json", OLD_METRICS), ("realset.jsonl", OLD_REALSET), ("model.pt", "weights")):
        (run_dir / name).write_text(text)
        os.utime(run_dir / name, (OLD_TIME, OLD_TIME))


def _stage_new(stage):
    (stage / "metrics.json").write_text('{"new": 2}')
    (stage / "realset.jsonl").write_text("new\n")
    (stage / "confusion_hog_svm.png").write_bytes(b"png")


def test_keep_previous_moves_only_the_replaced_files_into_a_stamped_folder(tmp_path):
    run_dir = tmp_path / "run"
    _old_run(run_dir)
    staged = StagedRun(run_dir, keep_previous=True)
    with staged as stage:
        _stage_new(stage)
    kept = run_dir / PREVIOUS_DIR / "20231114T221320Z"
    assert staged.kept == kept
    assert sorted(p.name for p in kept.iterdir()) == ["metrics.json", "realset.jsonl"]
    assert (kept / "metrics.json").read_text() == OLD_METRICS
    assert (kept / "realset.jsonl").read_text() == OLD_REALSET
    assert (run_dir / "metrics.json").read_text() == '{"new": 2}'
    assert (run_dir / "model.pt").read_text() == "weights"
    assert sorted(p.name for p in (run_dir / PREVIOUS_DIR).iterdir()) == ["20231114T221320Z"]  # no temp left

    # Same stamp again (files written in the same second): a second folder, never a merge.
    for name in ("metrics.json", "realset.jsonl", "confusion_hog_svm.png"):
        os.utime(run_dir / name, (OLD_TIME, OLD_TIME))
    staged = StagedRun(run_dir, keep_previous=True)
    with staged as stage:
        _stage_new(stage)
    assert staged.kept == run_dir / PREVIOUS_DIR / "20231114T221320Z-2"
    assert (staged.kept / "metrics.json").read_text() == '{"new": 2}'
    assert (kept / "metrics.json").read_text() == OLD_METRICS


def test_nothing_is_kept_without_old_files_or_when_not_asked(tmp_path):
    staged = StagedRun(tmp_path / "fresh", keep_previous=True)
    with staged as stage:
        _stage_new(stage)
    assert staged.kept is None and not (tmp_path / "fresh" / PREVIOUS_DIR).exists()

    run_dir = tmp_path / "run"
    _old_run(run_dir)
    with StagedRun(run_dir) as stage:  # train's staging: replaces without keeping
        _stage_new(stage)
    assert not (run_dir / PREVIOUS_DIR).exists()


def test_a_failed_evaluation_keeps_nothing_and_leaves_the_old_files(tmp_path):
    run_dir = tmp_path / "run"
    _old_run(run_dir)
    try:
        with StagedRun(run_dir, keep_previous=True) as stage:
            _stage_new(stage)
            raise RuntimeError("boom")
    except RuntimeError:
        pass
    assert not (run_dir / PREVIOUS_DIR).exists()
    assert (run_dir / "metrics.json").read_text() == OLD_METRICS


def test_evaluate_command_keeps_the_old_metrics_and_says_where(tmp_path, monkeypatch):
    from crater_synth.evaluation import classifiers

    run_dir = tmp_path / "run"
    _old_run(run_dir)
    metrics = {m: {"real_accuracy": 0.5, "val_accuracy": None} for m in classifiers.MODELS}
    metrics.update(train_images=1, test_images=2, test_sources=["x"], limits="none")

    def fake_evaluate_run(settings, run_dir_, progress, out_dir):
        _stage_new(out_dir)
        return metrics

    fake = types.ModuleType("train.evaluate")
    fake.evaluate_run = fake_evaluate_run
    monkeypatch.setitem(sys.modules, "train.evaluate", fake)
    result = CliRunner().invoke(classifiers.evaluate_command, [f"run_dir={run_dir}", "train.progress=false"])
    assert result.exit_code == 0, result.output
    kept = run_dir / PREVIOUS_DIR / "20231114T221320Z"
    assert f"kept the previous metrics files in {kept}/" in result.output
    assert (kept / "metrics.json").read_text() == OLD_METRICS
    assert (run_dir / "metrics.json").read_text() == '{"new": 2}'
