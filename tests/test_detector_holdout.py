"""python -m crater_synth.tools.detector_holdout: a detection set's held-out frames scored by off-nadir angle."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_learned_detector import fake_detection_set

from crater_synth.navigation.detectors.classical import Detection
from crater_synth.navigation.detectors.learned import DEFAULT_MODEL
from crater_synth.navigation.rendered import detector_train as dt
from crater_synth.tools import detector_holdout as dh


def test_counts_follow_the_labels_size_and_hidden_rule(tmp_path, monkeypatch):
    """Found labels, labels, matched and all detections of rims >= the minimum radius; an occluded label, a
    label centred off the frame and a detection matched to a hidden one count nowhere; an unmatched detection
    is a false one."""
    folder = fake_detection_set(tmp_path / "det", fields=2, frames=2)
    _, hold, _ = dh.detection_set_records(folder, 0.5)
    image, row = hold[0]
    labels = [
        lb["ellipse"] for lb in row["labels"] if 0 <= lb["ellipse"]["cu"] < 256 and 0 <= lb["ellipse"]["cv"] < 256
    ]
    assert row["labels"][0]["occluded"] and len(labels) >= 3
    dets = [Detection(u=e["cu"], v=e["cv"], r=e["a"], score=1.0) for e in labels[:3]]
    dets.append(Detection(u=5.0, v=5.0, r=max(e["a"] for e in labels), score=1.0))  # matches nothing
    monkeypatch.setattr(dt, "detect", lambda *a, **k: (dets, None))
    outside = dict(row["labels"][1], ellipse=dict(row["labels"][1]["ellipse"], cu=-4.0))
    row = dict(row, labels=[*row["labels"], outside])  # a rim whose centre is off the frame counts nowhere
    found, n_labels, true_pos, n_dets = dt.frame_counts(image, row, None, 0.0, 0.0, skip_hidden=True)
    assert (found, n_labels, true_pos, n_dets) == (2, len(labels) - 1, 2, 3)
    assert dt.frame_counts(image, row, None, 0.0, 0.0) == (3, len(labels), 3, 4)  # the training hold-out's rule
    big = min(e["a"] for e in labels[1:3]) + 1e-6  # only labels and detections at least this large
    n_big = sum(e["a"] >= big for e in labels[1:])
    assert dt.frame_counts(image, row, None, 0.0, big, skip_hidden=True)[1] == n_big


def test_main_scores_by_off_nadir_bin(tmp_path, capsys):
    """One run writes each model's recall and precision in all and per off-nadir bin of the held-out frames
    (the fake set's views: 0 and 30 degrees); a missing model file is one error line and no output."""
    folder = fake_detection_set(tmp_path / "det", fields=3, frames=2)
    out = tmp_path / "holdout.json"
    assert dh.main([str(folder), "--model", str(DEFAULT_MODEL), "--threshold", "0.2", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    run = result["runs"][0]
    assert result["set"]["holdout_fields"] == [2] and run["all"]["frames"] == 2
    assert run["0-1"]["frames"] == 1 and run["30-46"]["frames"] == 1 and "1-15" not in run
    assert run["all"]["labels"] == run["0-1"]["labels"] + run["30-46"]["labels"] > 0
    assert 0.0 <= run["all"]["recall"] <= 1.0
    bad = tmp_path / "bad.json"
    assert dh.main([str(folder), "--model", str(tmp_path / "none.pt"), "--out", str(bad)]) == 1
    assert "none.pt: no such model file" in capsys.readouterr().err and not bad.exists()


def test_a_hold_out_rendered_alone_is_scored_whole(tmp_path, capsys):
    """--held-out-share 1: every field of a folder holding only a set's held-out fields is scored; a share
    outside (0, 1] is refused before anything is read."""
    folder = fake_detection_set(tmp_path / "det", fields=3, frames=1)
    out = tmp_path / "holdout.json"
    args = [str(folder), "--model", str(DEFAULT_MODEL), "--threshold", "0.2", "--out", str(out)]
    assert dh.main([*args, "--held-out-share", "1"]) == 0
    result = json.loads(out.read_text())
    assert result["set"]["holdout_fields"] == [0, 1, 2] and result["runs"][0]["all"]["frames"] == 3
    with pytest.raises(SystemExit):
        dh.main([*args, "--held-out-share", "0"])
    assert "--held-out-share 0: must lie in (0, 1]" in capsys.readouterr().err


@pytest.mark.parametrize(("angle", "key"), [(0.0, "0-1"), (14.9, "1-15"), (45.0, "30-46"), (50.0, None)])
def test_off_nadir_bins(angle, key):
    assert dh.off_nadir_bin(angle, dh.DEFAULT_BINS) == key


def test_a_verifier_runs_every_learned_model_once_more(tmp_path, capsys):
    """--verifier adds one run of each learned model with that second stage; a missing verifier file is one
    error line and no output."""
    import torch

    from train import crater_verifier as cv

    folder = fake_detection_set(tmp_path / "det", fields=2, frames=2)
    torch.manual_seed(0)
    verifier = tmp_path / "v.pt"
    cv.save_model(verifier, cv.VerifierNet(4).eval(), {})
    out = tmp_path / "holdout.json"
    args = [str(folder), "--model", str(DEFAULT_MODEL), "--threshold", "0.1", "--verify-threshold", "0.0"]
    assert dh.main([*args, "--verifier", str(verifier), "--out", str(out)]) == 0
    plain, second = json.loads(out.read_text())["runs"]
    assert "verifier" not in plain and second["verifier"] == str(verifier) and len(second["verifier_sha256"]) == 64
    assert second["all"]["frames"] == plain["all"]["frames"] == 2
    bad = tmp_path / "bad.json"
    assert dh.main([*args, "--verifier", str(tmp_path / "none.pt"), "--out", str(bad)]) == 1
    assert "none.pt: no such model file" in capsys.readouterr().err and not bad.exists()


def test_recall_by_label_property_bins_the_counted_labels(monkeypatch):
    """Each bin's labels and recall come from the counted labels whose property falls in it (the last bin
    closed, a missing value in none); the bins add up to the whole, in all and per off-nadir bin."""
    degradation = [0.0, 0.1, 0.3, 0.6, 0.9, 1.0, 0.2]
    counted = np.array([1, 1, 1, 1, 1, 1, 0], bool)  # the last label is hidden or too small
    found = np.array([1, 0, 1, 0, 0, 1, 0], bool)
    radius = [5.0, 9.0, 9.0, 50.0, 6.0, 7.0, 30.0]
    labels = [
        {"degradation": d, "ellipse": {"a": r, "b": 0.9 * r}} | ({"lit_rim_fraction": 0.6} if i else {})
        for i, (d, r) in enumerate(zip(degradation, radius))
    ]
    monkeypatch.setattr(dh, "frame_matches", lambda *a, **k: (labels, counted, found & counted, 3, 4))
    rows = [(None, {"view": {"off_nadir_deg": 0.0}}), (None, {"view": {"off_nadir_deg": 35.0}})]
    out = dh.score_model(rows, None, 5.0, dh.DEFAULT_BINS)
    by = out["all"]["recall_by"]["degradation"]
    assert {k: v["labels"] for k, v in by.items()} == {"0-0.25": 4, "0.25-0.5": 2, "0.5-0.75": 2, "0.75-1": 4}
    assert by["0-0.25"]["recall"] == 0.5 and by["0.25-0.5"]["recall"] == 1.0 and by["0.5-0.75"]["recall"] == 0.0
    assert by["0.75-1"]["recall"] == 0.5 and out["all"]["recall"] == round(6 / 12, 4)
    radius_bins = out["all"]["recall_by"]["rim_radius_px"]
    assert radius_bins["5-8"] == {"labels": 6, "recall": round(4 / 6, 4)} and radius_bins[">=40"]["labels"] == 2
    assert out["all"]["recall_by"]["axis_ratio"]["0.85-0.95"]["labels"] == 12
    assert out["all"]["recall_by"]["lit_rim"]["0.5-0.75"]["labels"] == 10  # the first label has no lit fraction
    for split in out["30-46"]["recall_by"].values():
        assert sum(v["labels"] for v in split.values()) <= out["30-46"]["labels"] == 6
    assert out["all"]["precision"] == 0.75


@pytest.mark.parametrize(
    ("value", "index"), [(0.0, 0), (0.25, 1), (0.9, 3), (1.0, 3), (7.0, 3), (-1.0, 0), (None, -1), (float("nan"), -1)]
)
def test_value_bins(value, index):
    assert dh.value_bin(value, (0.0, 0.25, 0.5, 0.75, 1.0)) == index


def test_set_passes_detector_settings_and_refuses_unknown_ones(tmp_path, capsys):
    """--set KEY=VALUE reaches every model's settings (recorded in the output); an unknown key or a refused
    value is one error line and no output."""
    folder = fake_detection_set(tmp_path / "det", fields=2, frames=2)
    out = tmp_path / "holdout.json"
    args = [str(folder), "--model", str(DEFAULT_MODEL), "--threshold", "0.2"]
    assert dh.main([*args, "--set", "upsample_levels=1", "--set", "min_radius_px=3", "--out", str(out)]) == 0
    assert json.loads(out.read_text())["settings"] == {"upsample_levels": 1, "min_radius_px": 3}
    for bad, why in (("nope=1", "unexpected keyword argument 'nope'"), ("upsample_levels=5", "must be 0, 1 or 2")):
        assert dh.main([*args, "--set", bad, "--out", str(tmp_path / "bad.json")]) == 1
        assert why in capsys.readouterr().err and not (tmp_path / "bad.json").exists()
