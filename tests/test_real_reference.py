"""The reference trained on real images (the sim-to-real gap): real mosaic windows as training records,
fine-tuning from a model file, the north test tool's freezing checks, and the F1 ratio."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
from click.testing import CliRunner

from crater_synth.cli import main
from crater_synth.navigation.georef import Frame, Georef
from crater_synth.navigation.map.check import ListedCrater
from crater_synth.navigation.rendered import training_rows
from crater_synth.navigation.windows import training
from crater_synth.tools import detector_choice, detector_test
from train import crater_detector as cd


def test_a_window_record_is_decimated_with_its_catalogue_circles():
    """A 64 px window at 400 m/px: the image is averaged to 32 px at 800 m/px; a 16 km crater at pixel
    (20, 10) becomes a 10 px circle at (10, 5); a crater outside the window is left out."""
    image = np.arange(64 * 64, dtype=np.uint8).reshape(64, 64)
    geo = Georef("south", left_m=0.0, top_m=64 * 400.0, pixel_m=400.0)
    frame = Frame("S1_0000_0000", "test", 1, image, geo)
    listed = [ListedCrater(20 * 400.0, (64 - 10) * 400.0, 16.0), ListedCrater(-4000.0, 0.0, 30.0)]
    img, row = training.window_record(frame, listed)
    assert img.shape == (32, 32) and img[0, 0] == pytest.approx(np.mean(image[:2, :2].astype(float)))
    u, v, r, d, hidden = row["circles"]
    np.testing.assert_allclose([u[0], v[0], r[0], d[0]], [10.0, 5.0, 10.0, 16.0])
    assert u.size == 1 and not hidden.any() and row["ground_sample_m"] == 800.0
    # The training reads it as it reads a slimmed detection row.
    assert training_rows.label_circles(row, img.shape)[2].tolist() == [10.0]


def test_real_windows_come_from_the_spent_south_test_sectors_only():
    assert (training.REAL_TRAIN_POLE, training.REAL_TRAIN_SPLIT) == ("south", "test")


def _tiny_model(path):
    s = cd.DetectorTrainSettings(steps=1, batch=1, crop_px=32, width=4, threads=1)
    img = np.random.default_rng(0).random((64, 64)).astype(np.float32)
    samples = cd.level_samples(img, [30.0], [30.0], [8.0])
    result = cd.train_detector(samples, s)
    cd.save_model(path, result["model"], {"trained_on": "a test frame"})
    return samples


def test_fine_tuning_starts_from_the_init_model_and_says_so(tmp_path):
    init = tmp_path / "init.pt"
    samples = _tiny_model(init)
    start, _ = cd.load_model(init)
    s = cd.DetectorTrainSettings(steps=1, batch=1, crop_px=32, width=8, threads=1, lr=1e-12, init=str(init))
    result = cd.train_detector(samples, s)
    # The init's width (4), not the setting's (8); the weights barely move at lr 1e-12.
    assert result["model"].head.in_channels == 4
    for a, b in zip(start.parameters(), result["model"].parameters()):  # batch-norm statistics do move
        np.testing.assert_allclose(a.detach().numpy(), b.detach().numpy(), atol=1e-6)
    assert result["init"]["trained_on"] == "a test frame" and len(result["init"]["file_sha256"]) == 64
    with pytest.raises(ValueError, match="init"):
        cd.DetectorTrainSettings(arch="fcos", init=str(init))


@pytest.mark.parametrize(
    "args, message",
    [
        ([], "give FRAMES_DIR, --real-windows, or both"),
        (["--also", "x"], "--also needs FRAMES_DIR"),
        (["--real-windows"], "--real-windows needs --out"),
        (["--real-windows", "--out", "{out}", "nav.detector_train.init={tmp}/none.pt"], "none.pt: no such model file"),
        (["--real-windows", "--out", "{out}", "nav.detector_train.init={bad}"], "bad.pt: cannot be read"),
        (
            ["--real-windows", "--out", "{out}", "nav.detector_train.source_shares=[0.5,0.5]"],
            "one share per training source (1 given)",
        ),
    ],
)
def test_nav_detector_train_refuses_bad_real_window_requests_in_one_line(tmp_path, args, message):
    out = tmp_path / "m.pt"
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    (inputs / "bad.pt").write_bytes(b"not a model")
    args = [a.format(out=out, tmp=tmp_path, bad=inputs / "bad.pt") for a in args]
    r = CliRunner().invoke(main, ["nav-detector-train", *args])
    assert r.exit_code == 2 and message in r.output and len(r.output.strip().splitlines()) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["inputs"]


def test_the_north_test_refuses_an_uncommitted_choice_and_a_changed_model(tmp_path, monkeypatch):
    choice = tmp_path / "choice.json"
    model = tmp_path / "m.pt"
    model.write_bytes(b"weights")
    entry = {"model": str(model), "threshold": 0.3, "catalogue_15km": {}, "model_sha256": "0" * 64}
    choice.write_text(json.dumps({"chosen_per_model": [entry]}))
    assert not detector_test.committed_unchanged(choice)  # outside the repository: not committed
    with pytest.raises(SystemExit) as exc:
        detector_test.main(["--choice", str(choice), "--out", str(tmp_path / "t.json")])
    assert exc.value.code == 2 and not (tmp_path / "t.json").exists()
    monkeypatch.setattr(detector_test, "committed_unchanged", lambda path: True)
    with pytest.raises(SystemExit):
        detector_test.main(["--choice", str(choice), "--out", str(tmp_path / "t.json")])  # sha256 differs
    with pytest.raises(Exception, match="sha256 differs"):
        detector_test.frozen_choices(choice, [])
    entry["model_sha256"] = detector_test.model_sha256(str(model))
    choice.write_text(json.dumps({"chosen_per_model": [entry]}))
    assert detector_test.frozen_choices(choice, []) == [entry]
    with pytest.raises(Exception, match="no choice for other.pt"):
        detector_test.frozen_choices(choice, ["other.pt"])


def test_a_tracked_unchanged_file_counts_as_committed():
    tracked = subprocess.run(["git", "ls-files", "README.md"], capture_output=True, text=True).stdout.strip()
    if not tracked:
        pytest.skip("not a git checkout")
    assert detector_test.committed_unchanged(detector_test.SOURCE_ROOT / "README.md") == (
        subprocess.run(["git", "diff", "--quiet", "HEAD", "--", "README.md"]).returncode == 0
    )


def test_f1_ratios_to_the_reference():
    def run(name, f, bins):
        return {"model": name, "catalogue": {"f1_15km": f, "by_size_km": {"15-30": {"f1": bins}}}}

    runs = [run("real", 0.8, 0.5), run("synthetic", 0.6, 0.0), run("none", None, None)]
    r = detector_test.ratios(runs, "real")
    assert r == {
        "synthetic": {"f1_15km": 0.75, "by_size_km": {"15-30": 0.0}},
        "none": {"f1_15km": None, "by_size_km": {"15-30": None}},
    }
    scored = detector_test.with_f1(
        {"precision_15km": 0.9, "recall_15km": 0.45, "by_size_km": {"8-15": {"precision": None, "recall": 0.0}}}
    )
    assert scored["f1_15km"] == 0.6 and scored["by_size_km"]["8-15"]["f1"] is None


def test_the_north_test_refuses_a_changed_verifier(tmp_path, monkeypatch):
    """A verifier named in the chosen variant is checked like the model: a changed file is refused."""
    choice = tmp_path / "choice.json"
    model, verifier = tmp_path / "m.pt", tmp_path / "v.pt"
    model.write_bytes(b"weights")
    verifier.write_bytes(b"verifier")
    variant = [f"nav.detector.verifier={verifier}", "nav.detector.verify_threshold=0.5"]
    entry = {
        "model": str(model),
        "threshold": 0.1,
        "variant": variant,
        "variant_sha256": detector_choice.variant_sha256(variant),
        "catalogue_15km": {},
        "model_sha256": detector_test.model_sha256(str(model)),
    }
    choice.write_text(json.dumps({"chosen_per_model": [entry]}))
    monkeypatch.setattr(detector_test, "committed_unchanged", lambda path: True)
    assert detector_test.frozen_choices(choice, []) == [entry]
    verifier.write_bytes(b"another verifier")
    with pytest.raises(Exception, match="v.pt: not the file chosen"):
        detector_test.frozen_choices(choice, [])
    verifier.unlink()
    with pytest.raises(Exception, match="v.pt: cannot be read"):
        detector_test.frozen_choices(choice, [])
