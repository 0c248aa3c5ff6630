"""The learned detector's second stage (train.crater_verifier): crops, labels, turns, model files, inference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_learned_detector import fake_detection_set

from crater_core.settings_nav import VerifierTrainSettings
from crater_synth.navigation.detectors import learned
from crater_synth.navigation.detectors.learned import DEFAULT_MODEL, DetectorModelFileError, LearnedSettings
from crater_synth.navigation.detectors.registry import CandidateInput
from crater_synth.navigation.rendered import verifier_train as vt
from train import crater_verifier as cv


@pytest.mark.parametrize("r", [3.0, 7.0, 20.0, 70.0])
def test_crops_sample_the_frame_at_the_circle_at_every_level(r):
    """On a ramp (pixel j holds j) a crop's column k holds the frame coordinate it samples: the centre u
    (pixel-edge coordinates) plus the offset along the crop's side, at level 0 and decimated levels alike."""
    image = np.tile(np.arange(1024, dtype=np.float32), (1024, 1))
    u, v = 500.25, 480.0
    got = cv.crops(image, [u], [v], [r])[0]
    side = 2 * cv.CONTEXT_R * r
    want = u - 0.5 + side * ((np.arange(cv.CROP_PX) + 0.5) / cv.CROP_PX - 0.5)
    level = max(0, math.floor(math.log2(side / cv.CROP_PX)))
    # OpenCV's bilinear remap weighs in 1/32 steps of a level pixel (2**level frame pixels)
    np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=2**level / 32)


def test_crops_of_no_candidate_and_at_the_border():
    image = np.random.default_rng(0).random((64, 64)).astype(np.float32)
    assert cv.crops(image, [], [], []).shape == (0, cv.CROP_PX, cv.CROP_PX)
    edge = cv.crops(image, [0.0], [0.0], [20.0])
    assert edge.shape == (1, cv.CROP_PX, cv.CROP_PX) and np.isfinite(edge).all()


def test_candidate_targets_label_craters_near_misses_and_hidden_rims():
    u, v, r = np.array([50.0, 150.0]), np.array([50.0, 50.0]), np.array([10.0, 20.0])
    hidden = np.array([False, True])
    cu = np.array([53.0, 50.0, 50.0, 150.0, 120.0])
    cv_ = np.array([50.0, 50.0, 56.0, 50.0, 120.0])
    cr = np.array([8.0, 20.0, 10.0, 20.0, 10.0])
    label, target = vt.candidate_targets(cu, cv_, cr, u, v, r, hidden)
    # a correctable candidate; one 2 x too large (near: neither); one 0.6 r off centre (near: neither);
    # a hidden rim's (neither); one far from every rim (none)
    assert label.tolist() == [1, -1, -1, -1, 0]
    np.testing.assert_allclose(target[0], [-3.0 / 8.0, 0.0, math.log(10.0 / 8.0)], rtol=1e-6)
    assert not target[1:].any()


@pytest.mark.parametrize(("k", "flip"), [(0, False), (1, False), (2, True), (3, True), (0, True)])
def test_turns_move_the_crater_with_its_offset(k, flip):
    """A dot whose pixel centre lies at offset (du, dv) from the crop centre (c / 2, pixel-edge coordinates)
    lies at the turned offset after the turn."""
    c = cv.CROP_PX
    x = torch.zeros(1, 1, c, c)
    i0, j0 = c // 2 - 3, c // 2 + 5
    x[0, 0, i0, j0] = 1.0
    off0 = torch.tensor([[j0 + 0.5 - c / 2, i0 + 0.5 - c / 2]])
    y, off = cv.dihedral_batch(x, off0, k, flip)
    i, j = np.unravel_index(int(torch.argmax(y)), (c, c))
    assert (j + 0.5 - c / 2, i + 0.5 - c / 2) == pytest.approx(tuple(off[0].tolist()))


def _model_file(tmp_path):
    torch.manual_seed(0)
    path = tmp_path / "verifier.pt"
    cv.save_model(path, cv.VerifierNet(8).eval(), {"trained_on": "test"})
    return path


def test_the_verifier_rescores_the_learned_candidates_and_a_bad_file_is_one_error(tmp_path):
    path = _model_file(tmp_path)
    model, meta = cv.load_model(path)
    assert meta["trained_on"] == "test" and model.width == 8
    rng = np.random.default_rng(1)
    image = rng.random((128, 128)).astype(np.float32)
    u, v, r, p = cv.verify(model, image, [40.0, 80.0], [60.0, 64.0], [10.0, 12.0])
    assert u.shape == v.shape == r.shape == p.shape == (2,) and ((p > 0) & (p < 1)).all() and (r > 0).all()
    frame = CandidateInput(image=image, spectrum=None, radii=None, light=float("nan"))
    base = dict(threshold=0.0, min_radius_px=4.5, max_radius_px=60.0)
    plain = learned.learned_candidates(frame, LearnedSettings(**base))
    kept = learned.learned_candidates(frame, LearnedSettings(**base, verifier=str(path), verify_threshold=0.0))
    assert len(kept[0]) <= len(plain[0]) and ((kept[3] > 0) & (kept[3] < 1)).all()
    assert (
        len(learned.learned_candidates(frame, LearnedSettings(**base, verifier=str(path), verify_threshold=1.0))[0])
        == 0
    )
    # kept where the detector put them, each scored by the geometric mean of its heat and probability
    geo = dict(base, verifier=str(path), verify_threshold=0.0, verify_refine=False, verify_score="geometric")
    u, v, r, s = learned.learned_candidates(frame, LearnedSettings(**geo))
    np.testing.assert_array_equal(np.stack([u, v, r]), np.stack(plain[:3]))
    np.testing.assert_allclose(s, np.sqrt(plain[3] * cv.verify(model, image, u, v, r)[3]), rtol=1e-5)
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a model")
    with pytest.raises(DetectorModelFileError, match="bad.pt"):
        learned.learned_candidates(frame, LearnedSettings(**base, verifier=str(bad)))
    with pytest.raises(ValueError, match="verify_threshold"):
        LearnedSettings(verify_threshold=1.5)


def test_examples_of_a_detection_set_and_a_short_training(tmp_path):
    """The examples of a set's training frames carry crater and non-crater labels with their targets, and a
    short training on them gives a loadable model."""
    folder = fake_detection_set(tmp_path / "det", fields=2, frames=2)
    ex = vt.build_examples(folder, DEFAULT_MODEL, frames=0, heat=0.05, seed=0)
    n = len(ex["label"])
    assert ex["images"].shape == (n, cv.CROP_PX, cv.CROP_PX) and ex["target"].shape == (n, 3)
    assert set(np.unique(ex["label"])) <= {0, 1} and (ex["label"] == 1).any() and (ex["label"] == 0).any()
    assert ex["what"]["frames"] == 2 and ex["what"]["holdout_fields"] == [1]
    s = VerifierTrainSettings(steps=3, batch=8, width=4)
    res = cv.train_verifier(ex["images"], ex["tops"], ex["label"], ex["target"], s)
    assert len(res["history"]) == 1 and math.isfinite(res["history"][0]["loss"])


def test_nav_verifier_train_writes_a_scored_model_and_names_a_short_set(tmp_path):
    from click.testing import CliRunner

    from crater_synth.cli import main

    folder = fake_detection_set(tmp_path / "det", fields=2, frames=2)
    out = tmp_path / "v.pt"
    short = ["nav.verifier_train.steps=2", "nav.verifier_train.batch=8", "nav.verifier_train.width=4"]
    r = CliRunner().invoke(
        main, ["nav-verifier-train", str(folder), "--out", str(out), *short, "nav.verifier_train.frames=0"]
    )
    assert r.exit_code == 0, r.output
    _, meta = cv.load_model(out)
    assert meta["holdout"]["with_verifier"]["frames"] == 2 and meta["set"]["frames"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["det", "v.pt"]
    r = CliRunner().invoke(main, ["nav-verifier-train", str(folder), "--out", str(tmp_path / "w.pt"), *short])
    assert r.exit_code != 0 and "nav.verifier_train.frames=2000" in r.output and not (tmp_path / "w.pt").exists()
