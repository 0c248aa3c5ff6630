"""The learned crater detector (train/crater_detector.py, crater_synth/navigation/detectors/learned.py): targets,
augmentation geometry, pyramid bookkeeping, model files, a small learning run on shaded crater fields,
training from a survey directory, and its use through detect() and the CLI."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from crater_synth.dataset.detection import manifest_rows
from crater_synth.errors import UserError
from crater_synth.navigation.detectors import learned
from crater_synth.navigation.detectors.classical import detect
from crater_synth.navigation.detectors.template import crater_heights, shade_heights
from crater_synth.navigation.rendered import detector_train as learned_train
from crater_synth.navigation.rendered import training_rows
from crater_synth.navigation.settings import compose_nav
from train import crater_detector as cd
from train import crater_detector_inference as infer
from train import detector_fit
from train.model_files import DetectorModelError


# ------------------------------------------------------------------------------------------------
# Targets and geometry
# ------------------------------------------------------------------------------------------------
def test_level_targets_mark_band_craters_and_ignore_their_neighbours():
    t = cd.level_targets((64, 64), u=[20.3, 45.0, 10.0], v=[30.8, 45.0, 50.0], r=[8.0, 14.0, 3.0])
    # The band crater (r 8): heat 1 at the pixel holding its centre, offset and log-radius there.
    assert t["heat"][30, 20] == 1.0 and t["centre"].sum() == 1
    np.testing.assert_allclose(t["offset"][:, 30, 20], [20.3 - 20.5, 30.8 - 30.5], atol=1e-6)
    assert t["logr"][30, 20] == pytest.approx(math.log(8.0 / cd.BAND_LO_PX))
    # r 14 lies just above the band: its disc carries no loss, it is no positive either.
    assert t["weight"][45, 45] == 0.0 and t["heat"][45, 45] < 0.05
    # r 3 is far below the band: an ordinary negative.
    assert t["weight"][50, 10] == 1.0 and t["heat"][50, 10] < 0.05
    # A rim in shadow all round (hidden): no positive, and no loss over its whole disc.
    h = cd.level_targets((64, 64), u=[20.3], v=[30.8], r=[8.0], hidden=[True])
    assert h["centre"].sum() == 0 and h["heat"].max() == 0.0
    assert h["weight"][30, 20] == 0.0 and h["weight"][30, 27] == 0.0 and h["weight"][30, 30] == 1.0


@pytest.mark.parametrize("k", range(4))
@pytest.mark.parametrize("flip", [False, True])
def test_dihedral_moves_the_targets_and_turns_the_offsets(k, flip):
    """After a rotation/mirroring of a stacked sample, the centre pixel plus its offset is the crater's
    transformed position, and the brightness moved with it."""
    image = np.zeros((40, 56), np.float32)
    image[7, 31] = 1.0  # the brightness pixel under the crater centre (31.3, 7.8)
    u, v, h, w = 31.3, 7.8, 40, 56
    t = cd.dihedral(
        torch.from_numpy(
            cd.stack_sample(cd.LevelSample(image, np.array([u]), np.array([v]), np.array([8.0]), np.zeros(1, bool)), 32)
        ),
        k,
        flip,
    )
    for _ in range(k):
        u, v, h, w = v, w - u, w, h
    if flip:
        v = h - v
    i, j = (int(x) for x in torch.nonzero(t[cd._CENTRE])[0])
    assert (j + 0.5 + float(t[cd._DU, i, j]), i + 0.5 + float(t[cd._DV, i, j])) == pytest.approx((u, v), abs=1e-5)
    assert torch.nonzero(t[cd._IMG] == 1.0)[0].tolist() == [i, j]
    assert float(t[cd._HEAT, i, j]) == 1.0


def test_augmentation_standardises_the_valid_pixels_only():
    t = torch.zeros(2, 8, 32, 32)
    t[:, cd._IMG] = torch.rand(2, 32, 32)
    t[:, cd._VALID, :16, :] = 1.0
    s = cd.DetectorTrainSettings(noise=(0.0, 0.0))
    x = cd.augment(t, s, torch.Generator().manual_seed(0))
    valid = x[:, 0, :16]
    assert torch.allclose(valid.mean((1, 2)), torch.zeros(2), atol=1e-4)
    assert torch.allclose(valid.std((1, 2), unbiased=False), torch.ones(2), atol=1e-3)
    assert float(x[:, 0, 16:].abs().max()) == 0.0


def test_pyramid_levels_and_their_coordinates():
    levels = cd.pyramid(np.ones((256, 200)), first_level=1)
    assert [k for k, _ in levels] == [1, 2, 3]  # level 4 (16 x 12 px) is below MIN_LEVEL_PX
    assert levels[0][1].shape == (128, 100)
    samples = cd.level_samples(np.ones((64, 64)), [40.0], [20.0], [16.0])
    assert [(s.u[0], s.v[0], s.r[0]) for s in samples] == [(40.0, 20.0, 16.0), (20.0, 10.0, 8.0)]


def test_detect_pyramid_scales_level_peaks_back_to_frame_pixels(monkeypatch):
    """A peak at level pixel (10, 5) of level 2 with offset (0.25, -0.25) and radius 9 px is a crater at
    frame pixel (4 x 10.75, 4 x 5.25) of radius 36 px."""

    def fake_output(model, a, tta=1, sun_aligned=False):
        out = np.zeros((4,) + a.shape, np.float32)
        if a.shape[0] == 32:  # level 2 of a 128 px frame
            out[0, 5, 10] = 0.9
            out[1:3, 5, 10] = (0.25, -0.25)
            out[3, 5, 10] = math.log(9.0 / cd.BAND_LO_PX)
        return out

    monkeypatch.setattr(infer, "level_output", fake_output)
    u, v, r, s, level = infer.detect_pyramid(None, np.zeros((128, 128)), threshold=0.5)
    assert (u[0], v[0], r[0], s[0], level[0]) == pytest.approx((43.0, 21.0, 36.0, 0.9, 2))
    assert u.size == 1


def test_half_octaves_search_the_shrunk_frame_and_scale_back_to_frame_pixels(monkeypatch):
    """A peak at the middle of every level image, radius 6 px: in frame pixels, the frame's middle and
    6 x 2**level px in the octave pyramid, 6 x 2**level x sqrt(2) in the shrunk one (level k + 0.5)."""

    def fake_output(model, a, tta=1, sun_aligned=False):
        out = np.zeros((4,) + a.shape, np.float32)
        h, w = a.shape
        out[0, h // 2, w // 2] = 0.9
        out[1:3, h // 2, w // 2] = (w / 2 - w // 2 - 0.5, h / 2 - h // 2 - 0.5)
        return out

    monkeypatch.setattr(infer, "level_output", fake_output)
    u, v, r, _s, level = infer.detect_pyramid(None, np.zeros((128, 192)), threshold=0.5, half_octaves=True)
    assert sorted(level) == [0, 0.5, 1, 1.5, 2]  # the shrunk level 2 (22 px) is below MIN_LEVEL_PX
    # (an odd row dropped by the decimation moves a level's middle by under a frame pixel)
    np.testing.assert_allclose(u, 96.0, atol=1.0)
    np.testing.assert_allclose(v, 64.0, atol=1.0)
    np.testing.assert_allclose(r, 6.0 * 2.0**level, rtol=0.01)


def test_dihedral_views_averaged_over_the_whole_group_turn_with_the_image():
    """tta=8 averages the heat over all 8 views, so the heat of a turned image is the turned heat; tta=1 is
    the plain pass."""
    torch.manual_seed(0)
    model = cd.CraterNet(4).eval()
    a = np.random.default_rng(1).random((32, 32)).astype(np.float32)
    heat = infer.level_output(model, a, tta=8)[0]
    np.testing.assert_allclose(infer.level_output(model, np.rot90(a).copy(), tta=8)[0], np.rot90(heat), atol=1e-5)
    np.testing.assert_allclose(infer.level_output(model, a[:, ::-1].copy(), tta=8)[0], heat[:, ::-1], atol=1e-5)
    plain = infer.level_output(model, a)[0]
    with torch.no_grad():
        direct = torch.sigmoid(model(torch.from_numpy(cd.standardise(a))[None, None])[0, 0]).numpy()
    np.testing.assert_allclose(plain, direct, atol=1e-6)
    assert not np.allclose(plain, heat, atol=1e-4)
    with pytest.raises(ValueError, match="tta"):
        learned.LearnedSettings(tta=3)


def test_an_ensemble_averages_its_models_heat_and_radius_maps():
    """Two networks' maps averaged: the heat and log radius are the means of each model's (views averaged
    first), the offsets the first model's; one model, or a model with itself, is that model alone."""
    torch.manual_seed(0)
    a_model, b_model = cd.CraterNet(4).eval(), cd.CraterNet(4).eval()
    img = np.random.default_rng(2).random((32, 32)).astype(np.float32)
    a, b = infer.level_output(a_model, img, tta=2), infer.level_output(b_model, img, tta=2)
    both = infer.ensemble_output([a_model, b_model], img, tta=2)
    np.testing.assert_allclose(both[0], (a[0] + b[0]) / 2, atol=1e-6)
    np.testing.assert_allclose(both[3], (a[3] + b[3]) / 2, atol=1e-6)
    np.testing.assert_allclose(both[1:3], a[1:3])
    assert not np.allclose(both[0], a[0], atol=1e-4)
    np.testing.assert_allclose(infer.ensemble_output([a_model, a_model], img, tta=2), a, atol=1e-6)


def test_an_ensemble_names_its_model_files_and_refuses_a_missing_one(tmp_path):
    """``nav.detector.ensemble``: the committed model with itself finds what it finds alone; a missing file is
    one error naming it; the choice tool hashes every file an ensemble names."""
    from crater_synth.tools.detector_choice import file_sha256, variant_sha256

    img = crater_field(3, size=128, n=4)[0]
    alone = compose_nav(["nav/detector=learned-detect"]).detector
    committed = str(learned.DEFAULT_MODEL)
    twice = compose_nav(["nav/detector=learned-detect", f"nav.detector.ensemble=[{committed}]"]).detector
    assert twice.ensemble == (committed,)
    assert [(d.u, d.v, d.r) for d in detect(img, alone)[0]] == [(d.u, d.v, d.r) for d in detect(img, twice)[0]]
    missing = dataclasses.replace(alone, ensemble=(str(tmp_path / "gone.pt"),))
    with pytest.raises(learned.DetectorModelFileError, match="gone.pt"):
        detect(img, missing)
    other = tmp_path / "other.pt"
    cd.save_model(other, cd.CraterNet(4), {})
    hashed = variant_sha256(["nav.detector.tta=4", f"nav.detector.ensemble=[{committed},{other}]"])
    assert hashed == {committed: file_sha256(committed), str(other): file_sha256(other)}


def test_first_level_searches_the_wanted_radii_inside_a_band():
    assert learned.first_level(9.0) == 1  # a 400 m/px mosaic window: from 800 m/px, r >= 12 px
    for rmin in (5.0, 11.0, 30.0, 83.0):
        k = learned.first_level(rmin)
        # the wanted smallest radius lies in (or just below, within the 25 % match) the first band
        assert 0.75 * cd.BAND_LO_PX * 2**k / math.sqrt(2) <= rmin <= 0.75 * cd.BAND_LO_PX * 2**k * math.sqrt(2)


def test_first_level_goes_below_full_resolution_only_where_enlarging_is_allowed():
    """A 3 px rim sits in the band of the frame enlarged 2x (level -1); without upsample_levels the search
    still starts at full resolution, and never below -upsample_levels."""
    assert learned.first_level(3.0) == 0 and learned.first_level(3.0, upsample_levels=1) == -1
    assert learned.first_level(1.0, upsample_levels=1) == -1 and learned.first_level(1.0, upsample_levels=2) == -2
    assert learned.first_level(9.0, upsample_levels=2) == 1  # a larger smallest radius is unchanged


def test_an_enlarged_level_scales_back_to_frame_pixels(monkeypatch):
    """pyramid(first_level=-1) starts with the frame enlarged 2x (pixel corners kept: a pixel's value
    lands on its 2 x 2 block); a peak found there comes back at half its level coordinates and radius."""
    a = np.zeros((64, 96), np.float32)
    a[10, 20] = 1.0
    levels = cd.pyramid(a, first_level=-1)
    assert [k for k, _ in levels[:2]] == [-1, 0] and levels[0][1].shape == (128, 192)
    big = levels[0][1]
    assert np.unravel_index(np.argmax(big), big.shape) in {(20, 40), (20, 41), (21, 40), (21, 41)}
    assert np.array_equal(levels[1][1], a)

    def fake_output(model, level_image, tta=1, sun_aligned=False):
        out = np.zeros((4,) + level_image.shape, np.float32)
        if level_image.shape == (128, 192):
            out[0, 60, 100] = 0.9
            out[3, 60, 100] = math.log(8.0 / cd.BAND_LO_PX)
        return out

    monkeypatch.setattr(infer, "level_output", fake_output)
    u, v, r, _s, level = infer.detect_pyramid(None, a, threshold=0.5, first_level=-1)
    assert (u[0], v[0], r[0], level[0]) == pytest.approx((50.25, 30.25, 4.0, -1))


@pytest.mark.parametrize("first_level", [-2, -1, 0, 1])
def test_level_shapes_are_the_pyramids_without_the_image(first_level):
    """A set read from disk plans its samples from level_shapes: they are pyramid's, enlarged levels too."""
    a = np.zeros((70, 97), np.float32)
    assert cd.level_shapes(a.shape, first_level) == [im.shape for _, im in cd.pyramid(a, first_level)]
    assert cd.level_count(a.shape, first_level) == len(cd.pyramid(a, first_level))


# ------------------------------------------------------------------------------------------------
# Model files
# ------------------------------------------------------------------------------------------------
def test_model_file_round_trip_and_bad_files(tmp_path):
    model = cd.CraterNet(4)
    path = tmp_path / "m.pt"
    cd.save_model(path, model, {"note": "x"})
    loaded, meta = cd.load_model(path)
    assert meta == {"note": "x"}
    for k, v in model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k])
    assert not list(tmp_path.glob("*.tmp*"))  # atomic: no temp file left
    with pytest.raises(DetectorModelError, match="no such file"):
        cd.load_model(tmp_path / "missing.pt")
    broken = tmp_path / "broken.pt"
    broken.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(DetectorModelError, match="broken.pt"):
        cd.load_model(broken)
    foreign = tmp_path / "foreign.pt"
    torch.save(model.state_dict(), foreign)  # a bare state dict, not a model file
    with pytest.raises(DetectorModelError, match="not a crater-synth-detector"):
        cd.load_model(foreign)


def test_committed_model_loads_and_carries_its_provenance():
    _model, meta = cd.load_model(learned.DEFAULT_MODEL)
    assert meta["trained_on"].startswith("rendered survey frames only")
    assert meta["synthetic_holdout"]["frames"] > 0
    assert set(meta["train_tracks"]).isdisjoint(meta["holdout_tracks"])
    # `make nav-detector` (the training defaults) trains this model again: the same settings, steps among
    # them (the one-cycle schedule spans all steps, so a shorter run is not its checkpoint).
    defaults = dataclasses.asdict(cd.DetectorTrainSettings())
    for key in ("steps", "batch", "crop_px", "lr", "weight_decay", "width", "seed"):
        assert meta["settings"][key] == defaults[key], key


# ------------------------------------------------------------------------------------------------
# Learning on shaded crater fields
# ------------------------------------------------------------------------------------------------
def crater_field(seed: int, size: int = 128, n: int = 7):
    """A height field of analytic bowls (radii 5-28 px), Hapke-shaded at low Sun with cast shadows:
    (image, u, v, r)."""
    rng = np.random.default_rng(seed)
    z = np.zeros((size, size))
    jj, ii = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    us, vs, rs = [], [], []
    while len(rs) < n:
        r = float(np.exp(rng.uniform(np.log(5.0), np.log(28.0))))
        u, v = rng.uniform(r, size - r, 2)
        if any(math.hypot(u - a, v - b) < r + c for a, b, c in zip(us, vs, rs)):
            continue
        z += r * crater_heights(np.hypot(jj - u, ii - v) / r, 0.2)
        us.append(u)
        vs.append(v)
        rs.append(r)
    image = shade_heights(z, theta=float(rng.uniform(0, 2 * np.pi)), sun_el_deg=float(rng.uniform(8, 20)))
    return image.astype(np.float32), np.array(us), np.array(vs), np.array(rs)


@pytest.mark.integration
def test_a_short_training_run_learns_to_find_shaded_craters():
    samples = []
    for seed in range(12):
        img, u, v, r = crater_field(seed)
        samples.extend(cd.level_samples(img, u, v, r))
    s = cd.DetectorTrainSettings(steps=250, batch=8, crop_px=48, width=8, lr=5e-3, threads=2, noise=(0.0, 0.02))
    result = cd.train_detector(samples, s)
    assert result["history"][-1]["loss"] < 0.6 * result["history"][0]["loss"]
    found = total = hits = 0
    for seed in (100, 101, 102):
        img, u, v, r = crater_field(seed)
        du, dv, dr, _, _ = infer.detect_pyramid(result["model"], img, threshold=0.3)
        total += u.size
        found += du.size
        for a, b, c in zip(u, v, r):
            d = np.hypot(du - a, dv - b)
            hits += bool(np.any((d <= 0.5 * c) & (np.abs(dr / c - 1.0) <= 0.25)))
    assert hits / total >= 0.6, (hits, total, found)
    assert found <= 2 * total


# ------------------------------------------------------------------------------------------------
# Training from a survey directory, and use through detect() and the CLI
# ------------------------------------------------------------------------------------------------
def fake_survey(root, tracks: int = 3, frames: int = 2):
    """Survey track directories as ``nav-frames`` writes them (I/F EXR + labelled manifest rows)."""
    from crater_core import exr, schema

    for t in range(tracks):
        d = root / f"track_{t:03d}"
        rows = []
        for k in range(frames):
            img, u, v, r = crater_field(1000 + 10 * t + k)
            rel = f"frame_{k:04d}.exr"
            exr.write_exr(d / rel, {"IF": img}, channel_names=("IF",))
            rows.append(
                {
                    # the fields every nav-frames row carries (rendered.labels.FRAME_ROW_FIELDS); training
                    # reads the frame and its labels only
                    "trajectory": f"survey_{t:03d}",
                    "sha256": schema.sha256_file(d / rel),
                    "frame_origin": {"lat": -85.0, "lon": 0.0, "h_m": 0.0},
                    "pose": {},
                    "rel_path": rel,
                    "index": k,
                    "ground_sample_m": 800.0,
                    "landmarks": [
                        {
                            "id": f"L{i}",
                            "diameter_km": 2 * c * 0.8,
                            "ellipse": {"cu": a, "cv": b, "a": c, "b": c, "angle_rad": 0.0},
                        }
                        for i, (a, b, c) in enumerate(zip(u, v, r))
                    ],
                }
            )
        (d / "manifest.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    return root


def test_train_from_survey_holds_out_the_last_tracks_and_writes_a_usable_model(tmp_path):
    frames = fake_survey(tmp_path / "survey")
    out = tmp_path / "model.pt"
    s = cd.DetectorTrainSettings(steps=4, batch=2, crop_px=32, width=4, threads=1, checkpoints=(2,))
    summary = learned_train.train_from_survey(frames, out, s, holdout=1)
    assert summary["train_tracks"] == ["track_000", "track_001"] and summary["holdout_tracks"] == ["track_002"]
    assert summary["holdout"]["frames"] == 2
    assert out.is_file() and (tmp_path / "model.step2.pt").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.pt", "model.step2.pt", "survey"]
    params = dataclasses.replace(compose_nav(["nav/detector=learned"]).detector, model=str(out), threshold=0.0)
    dets, theta = detect(crater_field(5)[0], params)
    assert math.isnan(theta)  # no light needed without the rim fit
    assert all(params.min_radius_px <= d.r <= params.max_radius_px for d in dets)


def test_train_from_survey_refuses_too_few_tracks(tmp_path):
    from crater_synth.errors import UserError

    frames = fake_survey(tmp_path / "survey", tracks=1, frames=1)
    with pytest.raises(UserError, match="need more than"):
        learned_train.train_from_survey(frames, tmp_path / "m.pt", cd.DetectorTrainSettings(steps=1), holdout=1)
    assert not (tmp_path / "m.pt").exists()


def test_a_corrupt_model_file_is_one_error_line_and_detect_stops(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a model")
    params = learned.LearnedSettings(model=str(bad))
    with pytest.raises(learned.DetectorModelFileError, match="bad.pt: cannot be read"):
        detect(crater_field(1)[0], params)


def test_the_committed_model_finds_craters_in_a_shaded_field():
    """Trained on rendered DEM frames only, the committed model still finds analytic bowls."""
    img, u, v, r = crater_field(7, size=256, n=12)
    params = dataclasses.replace(compose_nav(["nav/detector=learned"]).detector, min_radius_px=4.5)
    dets, _ = detect(img, params)
    hits = sum(
        any(math.hypot(d.u - a, d.v - b) <= 0.5 * c and abs(d.r / c - 1.0) <= 0.25 for d in dets)
        for a, b, c in zip(u, v, r)
    )
    assert hits >= 0.5 * len(r), (hits, len(r), len(dets))


def test_a_method_run_alone_joins_the_poles_results_and_a_foreign_protocol_is_refused(tmp_path):
    from crater_synth.errors import UserError
    from crater_synth.navigation.windows.evaluate import add_methods

    protocol = {"pole": "north", "window_px": 512, "every": 1}
    old = {
        "methods": {"classical": {"splits": {}}},
        "regions": {
            "north": {"protocol": protocol, "landmark_map": {"landmarks": 845}, "methods": {"template": {"splits": {}}}}
        },
    }
    path = tmp_path / "navigation.json"
    path.write_text(json.dumps(old))
    new = {
        "protocol": {**protocol, "position_prior": "truth + 5 km"},
        "landmark_map": {"landmarks": 845},
        "methods": {"learned": {"splits": {"test": {"fix_rate": 0.9}}}},
    }
    merged = add_methods(path, "north", new)
    assert sorted(merged["regions"]["north"]["methods"]) == ["learned", "template"]
    assert merged["methods"] == old["methods"]  # the south entry untouched
    with pytest.raises(UserError, match="another protocol or map"):
        add_methods(path, "north", {**new, "landmark_map": {"landmarks": 1}})
    with pytest.raises(UserError, match="no south result"):
        add_methods(tmp_path / "missing.json", "south", new)


def test_navigate_a_real_window_with_the_learned_detector_and_refuse_a_bad_model(tmp_path):
    """`crater-synth navigate WINDOW nav/detector=learned` on a south mosaic window (development data) fixes
    it; a corrupt model file is one error line and writes no PNG; only the learned detector has a model."""
    from click.testing import CliRunner

    from crater_synth.cli import main
    from crater_synth.navigation.windows.mosaic import windows
    from crater_synth.navigation.windows.navigate import write_window

    frame = next(f for f in windows("validation", "south") if f.id == "S0_1536_0320")
    img = tmp_path / "w.png"
    write_window(img, frame)
    runner = CliRunner()
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"\x00" * 64)
    r = runner.invoke(main, ["navigate", str(img), "nav/detector=learned", f"nav.detector.model={bad}"])
    assert r.exit_code == 2 and "bad.pt: cannot be read" in r.output and len(r.output.strip().splitlines()) == 1
    assert not (tmp_path / "w.nav.png").exists()
    r = runner.invoke(main, ["navigate", str(img), "nav/detector=template", f"nav.detector.model={bad}"])
    assert r.exit_code == 2 and "nav.detector.model: unknown key" in r.output
    r = runner.invoke(main, ["navigate", str(img), "nav/detector=learned"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output.strip().splitlines()[-1])
    assert out["fix"] and out["error_km"] < 2.0 and out["light_azimuth_deg"] is None
    assert (tmp_path / "w.nav.png").is_file()
    # Every detection listed with its circle, confidence and landmark id (or "unknown"), beside the PNG.
    listed = json.loads((tmp_path / "w.nav.json").read_text())["detections"]
    assert out["detections_file"] == str(tmp_path / "w.nav.json") and len(listed) == out["detections"]
    assert sorted(d["landmark"] for d in listed if d["landmark"] != "unknown") == sorted(out["landmarks"])
    assert all({"u", "v", "r", "score"} <= set(d) for d in listed)


@pytest.mark.parametrize(
    "command, args, message",
    [
        ("nav-detector-train", ["nav.detector_train.steps=0"], "nav.detector_train.steps=0: must be >= 1"),
        (
            "nav-detector-train",
            ["nav.detector_train.steps=10", "nav.detector_train.checkpoints=[10]"],
            "nav.detector_train.checkpoints=[10]",
        ),
        ("nav-detector-train", ["nav.detector_train.step=10"], "nav.detector_train.step: unknown key"),
        (
            "nav-detector-train",
            ["nav.fix.min_inliers=3"],
            "nav.fix.min_inliers=3: this command's settings are nav.detector_train.",
        ),
        ("nav-verifier-train", ["nav.verifier_train.steps=0"], "nav.verifier_train.steps=0: must be >= 1"),
        ("nav-verifier-train", ["nav.verifier_train.heat=1.5"], "nav.verifier_train.heat=1.5: must lie in (0, 1)"),
        ("nav-verifier-train", ["nav.detector_train.steps=3"], "this command's settings are nav.verifier_train."),
    ],
)
def test_training_commands_refuse_nonsense_settings_before_reading_anything(tmp_path, command, args, message):
    """nav-detector-train and nav-verifier-train: one error line, nothing read or written."""
    from click.testing import CliRunner

    from crater_synth.cli import main

    r = CliRunner().invoke(main, [command, str(tmp_path / "none"), "--out", str(tmp_path / "m.pt"), *args])
    assert r.exit_code == 2 and message in r.output and len(r.output.strip().splitlines()) == 1
    assert not list(tmp_path.iterdir())


def test_detector_bench_takes_the_step_time_from_two_runs(monkeypatch, tmp_path):
    """`bench --part detector`: seconds per step from the difference of a short and a long run (after an
    untimed warm-up), the rest of the short run as fixed cost; timings that make no sense are one error."""
    from crater_synth.bench import detector as bd

    walls = {1: 30.0, bd.SHORT_STEPS: 12.0, bd.LONG_STEPS: 12.0 + 0.25 * (bd.LONG_STEPS - bd.SHORT_STEPS)}
    calls = []

    def fake_train(frames_dir, out, steps, device, overrides):
        calls.append((steps, device, overrides))
        return {"steps": steps, "wall_s": walls[steps], "peak_rss_mb": 1000.0 + steps}

    monkeypatch.setattr(bd, "_train", fake_train)
    r = bd.bench_detector_training(tmp_path, tmp_path / "w", 2000)
    assert calls == [(n, "cpu", ()) for n in (1, bd.SHORT_STEPS, bd.LONG_STEPS)]
    assert r["device"] == "cpu" and r["gpu"] is None and r["overrides"] == []
    assert r["s_per_step"] == pytest.approx(0.25) and r["fixed_s"] == pytest.approx(12.0 - 0.25 * bd.SHORT_STEPS)
    assert r["full_training_s"] == pytest.approx(r["fixed_s"] + 500.0, abs=0.1)
    assert r["peak_rss_mb"] == 1000.0 + bd.LONG_STEPS
    walls[bd.LONG_STEPS] = 11.0
    with pytest.raises(RuntimeError, match="timing noise"):
        bd.bench_detector_training(tmp_path, tmp_path / "w", 2000)


def test_bench_detector_skips_without_a_survey(monkeypatch, tmp_path):
    from click.testing import CliRunner

    from crater_synth.cli import main

    monkeypatch.chdir(tmp_path)  # the survey's default path is relative: none here
    res = CliRunner().invoke(main, ["bench", "--part", "detector", "--keep", str(tmp_path / "b")])
    assert res.exit_code == 0 and "detector skipped: no frames at data/detector_frames/south" in res.output


def test_bench_detector_passes_its_device_and_settings(monkeypatch, tmp_path):
    """`bench --part detector --detector-frames DIR --detector-device D --detector-train K=V`: the folder,
    device and settings reach every training run; a setting outside nav.detector_train is one error."""
    from click.testing import CliRunner

    from crater_synth.bench import cli as bench_cli
    from crater_synth.cli import main

    seen = []

    def fake_bench(frames_dir, work, full_steps, device, overrides):
        seen.append((frames_dir, device, overrides))
        return {"s_per_step": 0.1}

    monkeypatch.setattr(bench_cli, "bench_detector_training", fake_bench)
    args = ["bench", "--part", "detector", "--keep", str(tmp_path / "b"), "--detector-frames", str(tmp_path)]
    w = "nav.detector_train.loader_workers=4"
    res = CliRunner().invoke(main, [*args, "--detector-device", "cuda", "--detector-train", w])
    assert res.exit_code == 0, res.output
    assert seen == [(tmp_path, "cuda", (w,))] and 'detector {"s_per_step": 0.1}' in res.output
    res = CliRunner().invoke(main, [*args, "--detector-train", "render.samples=4"])
    assert res.exit_code == 2 and "not nav.detector_train.KEY=VALUE" in res.output and len(seen) == 1


def fake_detection_set(root, fields: int = 3, frames: int = 2, label_files: bool = False):
    """A detection set as ``detection-frames`` writes it (marked folder, I/F EXRs, rows with procedural
    labels and their field; ``label_files``: the labels in each frame's label file, as the command writes
    them today, else inline as it once did); the images are the synthetic crater fields of these tests."""
    from crater_core import exr
    from crater_core.detection_labels import label_file_name, write_label_file
    from crater_synth.dataset.detection_run import KIND
    from crater_synth.outfolder import OutFolder

    folder = OutFolder(root, KIND, subject="recipe test").claim()
    rows = []
    for f in range(fields):
        for k in range(frames):
            i = f * frames + k
            img, u, v, r = crater_field(2000 + i)
            rel = f"frame_{i:06d}.exr"
            exr.write_exr(root / rel, {"IF": img}, channel_names=("IF",))
            labels = [
                {
                    "source": "procedural",
                    "diameter_m": 2 * c * 60.0,
                    "ellipse": {"cu": a, "cv": b, "a": c, "b": c, "angle_rad": 0.0},
                    "lit_rim_fraction": 0.5,
                    "occluded": bool(n == 0),
                }
                for n, (a, b, c) in enumerate(zip(u, v, r))
            ]
            rows.append(
                {
                    "index": i,
                    "rel_path": rel,
                    "ground_sample_m": 60.0,
                    "terrain": {"field": f},
                    "view": {"off_nadir_deg": 30.0 * (k % 2)},
                    "labels": write_label_file(root / label_file_name(rel), labels, label_file_name(rel))
                    if label_files
                    else labels,
                }
            )
    (root / "manifest.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    folder.release()
    return root


def test_train_from_a_detection_set_holds_out_its_last_fields(tmp_path):
    """nav-detector-train on a detection set: the last fields are the synthetic hold-out, scored over the
    network's band of rim radii; an occluded label is neither positive nor negative."""
    frames = fake_detection_set(tmp_path / "det", fields=4)
    u, v, r, d, hidden = training_rows.label_circles(manifest_rows(frames)[0], (256, 256))
    assert hidden[0] and not hidden[1:].any() and d[1] == pytest.approx(2 * r[1] * 0.06)
    out = tmp_path / "model.pt"
    s = cd.DetectorTrainSettings(steps=3, batch=2, crop_px=32, width=4, threads=1)
    summary = learned_train.train_from_detection(frames, out, s, holdout_share=0.25)
    assert summary["holdout_fields"] == [3] and summary["train_fields"] == 3 and summary["train_frames"] == 6
    assert summary["holdout"]["frames"] == 2 and summary["holdout"]["min_radius_px"] == cd.BAND_LO_PX
    assert "procedural" in summary["trained_on"] and summary["recipe"] == "recipe test"
    assert learned.load_model(str(out))[1]["frames_dir"] == str(frames)


def test_a_streamed_training_reads_each_frame_when_drawn_and_learns_the_same_weights(tmp_path):
    """nav.detector_train.stream=true: no frame is read before training (records hold where each frame and
    label file are), the level samples are those held in memory, in their order, so the same seed draws
    the same crops and learns the same weights, beside a survey held in memory; the hold-out scores alike."""
    survey = fake_survey(tmp_path / "survey")
    det = fake_detection_set(tmp_path / "det", fields=4, label_files=True)
    s = cd.DetectorTrainSettings(steps=4, batch=3, crop_px=32, width=4, threads=1, source_shares=(0.3, 0.7))
    held = learned_train.detection_source(det, 0.25)
    streamed = learned_train.detection_source(det, 0.25, stream=True)
    assert all(im is None and "circles" not in row for im, row in streamed[0] + streamed[1])
    levels = training_rows.StreamedFrames([row for _, row in streamed[0]])
    circles = [training_rows.label_circles(row, im.shape) for im, row in held[0]]
    in_memory = [x for (im, _), (u, v, r, _, h) in zip(held[0], circles) for x in cd.level_samples(im, u, v, r, h)]
    assert len(levels) == len(in_memory) and all(
        np.array_equal(a.image, b.image) and np.array_equal(a.r, b.r) and np.array_equal(a.hidden, b.hidden)
        for a, b in zip(levels, in_memory)
    )
    survey_source = learned_train.survey_source(survey, holdout=1)
    a = learned_train.train_from_sources([survey_source, held], tmp_path / "a.pt", s)
    b = learned_train.train_from_sources(
        [survey_source, streamed], tmp_path / "b.pt", dataclasses.replace(s, stream=True)
    )
    wa, wb = (cd.load_model(tmp_path / f"{n}.pt")[0].state_dict() for n in "ab")
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    assert a["level_samples"] == b["level_samples"] and a["sources"][1]["holdout"] == b["sources"][1]["holdout"]
    with pytest.raises(ValueError, match="stream"):
        cd.DetectorTrainSettings(arch="fcos", stream=True)


def test_loader_workers_build_the_same_batches_and_a_bad_frame_fails_as_itself(tmp_path):
    """nav.detector_train.loader_workers: batches built ahead in a spawned worker from plans drawn in the
    training process are the batches built in it, so the weights are the same; the plans need no frame read
    (a streamed level's shape is known from its row). A frame that cannot be read raises its own error in
    the training process, as it does without workers."""
    det = fake_detection_set(tmp_path / "det", fields=4, label_files=True)
    s = cd.DetectorTrainSettings(steps=3, batch=3, crop_px=32, width=4, threads=1, stream=True)
    streamed = learned_train.detection_source(det, 0.25, stream=True)
    levels = training_rows.StreamedFrames([row for _, row in streamed[0]])
    assert [cd.sample_shape(levels, i) for i in range(len(levels))] == [np.shape(x.image) for x in levels]
    learned_train.train_from_sources([streamed], tmp_path / "a.pt", s)
    learned_train.train_from_sources([streamed], tmp_path / "b.pt", dataclasses.replace(s, loader_workers=1))
    wa, wb = (cd.load_model(tmp_path / f"{n}.pt")[0].state_dict() for n in "ab")
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    for _, row in streamed[0]:
        (det / row["rel_path"]).write_bytes(b"not an EXR")
    errors = []
    for workers in (0, 1):
        with pytest.raises(Exception) as e:
            bad = dataclasses.replace(s, loader_workers=workers)
            learned_train.train_from_sources([streamed], tmp_path / "c.pt", bad)
        errors.append((type(e.value), str(e.value)))
    assert errors[0] == errors[1] and "frame_" in errors[0][1]
    assert not (tmp_path / "c.pt").exists()
    with pytest.raises(ValueError, match="loader_workers"):
        cd.DetectorTrainSettings(loader_workers=-1)


def test_source_shares_set_each_folders_share_of_the_draws():
    """Two sources of 1 and 3 samples at shares 0.5/0.5: the single sample is drawn half the time."""
    p = detector_fit.source_probabilities([0, 1, 1, 1], (0.5, 0.5))
    assert p == pytest.approx([0.5, 1 / 6, 1 / 6, 1 / 6])
    assert detector_fit.source_probabilities([0, 1, 1], ()) is None
    with pytest.raises(DetectorModelError, match="3 entries for 2"):
        detector_fit.source_probabilities([0, 1], (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="source_shares"):
        cd.DetectorTrainSettings(source_shares=(0.0, 0.0))


def test_train_on_a_survey_and_a_detection_set_together_scores_each_hold_out(tmp_path):
    """nav-detector-train with two folders: one model from both, each folder scored on its own hold-out,
    both described in the model's provenance."""
    survey = fake_survey(tmp_path / "survey")
    det = fake_detection_set(tmp_path / "det", fields=4)
    out = tmp_path / "model.pt"
    s = cd.DetectorTrainSettings(steps=3, batch=2, crop_px=32, width=4, threads=1, source_shares=(0.3, 0.7))
    sources = [learned_train.survey_source(survey, holdout=1), learned_train.detection_source(det, 0.25)]
    summary = learned_train.train_from_sources(sources, out, s)
    first, second = summary["sources"]
    assert first["holdout_tracks"] == ["track_002"] and first["train_frames"] == 4
    assert second["holdout_fields"] == [3] and second["train_frames"] == 6
    assert (
        first["holdout"]["frames"] == 2
        and first["holdout"]["min_diameter_km"] == 15.0
        and second["holdout"]["min_radius_px"] == cd.BAND_LO_PX
    )
    assert summary["train_frames"] == first["train_frames"] + second["train_frames"]
    assert "survey" in summary["trained_on"] and "procedural" in summary["trained_on"]
    assert learned.load_model(str(out))[1]["settings"]["source_shares"] == [0.3, 0.7]


def test_nav_detector_train_refuses_a_folder_twice_and_shares_that_do_not_fit(tmp_path):
    """One line naming the input, and no model written."""
    from click.testing import CliRunner

    from crater_synth.cli import main

    det = fake_detection_set(tmp_path / "det", fields=2)
    out = tmp_path / "m.pt"
    runner = CliRunner()
    r = runner.invoke(main, ["nav-detector-train", str(det), "--also", str(det), "--out", str(out)])
    assert r.exit_code == 2 and "given twice" in r.output and len(r.output.strip().splitlines()) == 1
    r = runner.invoke(
        main, ["nav-detector-train", str(det), "--out", str(out), "nav.detector_train.source_shares=[0.5,0.5]"]
    )
    assert r.exit_code == 2 and "one share per training source (1 given)" in r.output
    assert not out.exists()


def test_a_slimmed_detection_row_gives_the_same_circles():
    """Training keeps a detection row's circles only; they are the label dicts' circles."""
    labels = [
        {
            "ellipse": {"cu": 10.0, "cv": 20.0, "a": 7.0},
            "diameter_m": 900.0,
            "lit_rim_fraction": 0.02,
            "occluded": False,
        },
        {
            "ellipse": {"cu": 300.0, "cv": 20.0, "a": 7.0},
            "diameter_m": 900.0,
            "lit_rim_fraction": 0.5,
            "occluded": False,
        },
        {"ellipse": {"cu": -1.0, "cv": 5.0, "a": 9.0}, "diameter_m": 1200.0, "lit_rim_fraction": 0.5, "occluded": True},
        {
            "ellipse": {"cu": 50.0, "cv": 60.0, "a": 9.0},
            "diameter_m": 1200.0,
            "lit_rim_fraction": 0.5,
            "occluded": True,
        },
    ]
    row = {"index": 3, "rel_path": "f.exr", "ground_sample_m": 60.0, "terrain": {"field": 0}, "labels": labels}
    full = training_rows.label_circles(row, (256, 256))
    slim = training_rows.label_circles(training_rows.slim_row(row), (256, 256))
    assert len(full[0]) == 2 and all(np.array_equal(a, b) for a, b in zip(full, slim))
    assert list(full[4]) == [True, True]  # dark rim, occluded rim


def test_train_from_a_sharded_detection_set_holds_out_its_last_fields_across_shards(tmp_path):
    """nav-detector-train DIR on a sharded set (launcher=dask): the shards' frames together, the set's last
    fields held out, whichever shard holds them."""
    from crater_synth.dataset.detection import SHARDS_KIND
    from crater_synth.outfolder import OutFolder

    parent = tmp_path / "sharded"
    parent.mkdir()
    fake_detection_set(parent / "shard_00000", fields=2)
    second = fake_detection_set(parent / "shard_00001", fields=2)
    rows = [json.loads(line) for line in (second / "manifest.jsonl").read_text().splitlines()]
    for row in rows:  # the second shard's fields follow the first's
        row["terrain"]["field"] += 2
    (second / "manifest.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    folder = OutFolder(parent, SHARDS_KIND, subject="recipe test, 4 frames a shard", names=lambda rel: False)
    folder.claim()
    folder.release()
    train, hold, what = learned_train.frames_source(parent)[:3]
    assert what["holdout_fields"] == [3] and what["train_fields"] == 3
    assert len(train) == 6 and len(hold) == 2 and all(r["terrain"]["field"] == 3 for _, r in hold)
    assert all("circles" in r and "labels" not in r for _, r in train)


def test_frames_takes_the_first_training_frames_and_keeps_the_hold_out(tmp_path):
    """nav.detector_train.frames=N (the data curve): the first N training frames by index, the same held-out
    fields as the whole set; more than the set holds is one line naming the folder."""
    frames = fake_detection_set(tmp_path / "det", fields=4)
    train, hold, what = learned_train.frames_source(frames)[:3]
    part, part_hold, part_what = learned_train.frames_source(frames, max_frames=3)[:3]
    assert [r["index"] for _, r in part] == [r["index"] for _, r in train][:3]
    assert [r["index"] for _, r in part_hold] == [r["index"] for _, r in hold]
    assert part_what["holdout_fields"] == what["holdout_fields"] and part_what["train_fields"] == 2
    assert part_what["frames_limit"] == 3 and "frames_limit" not in what
    with pytest.raises(UserError, match=r"det: nav.detector_train.frames=7, but the set has 6 training frames"):
        learned_train.frames_source(frames, max_frames=7)
    with pytest.raises(ValueError, match="frames"):
        cd.DetectorTrainSettings(frames=-1)
    survey = fake_survey(tmp_path / "survey")
    with pytest.raises(UserError, match="survey: nav.detector_train.frames applies to detection sets"):
        learned_train.frames_source(survey, max_frames=3)


def test_max_off_nadir_keeps_the_near_nadir_training_frames_and_the_hold_out(tmp_path):
    """nav.detector_train.max_off_nadir_deg (the oblique-view ablation): only training frames viewed within it,
    counted before ``frames``; the hold-out unchanged; none left is one line naming the folder; a survey
    (nadir) keeps every frame."""
    frames = fake_detection_set(tmp_path / "det", fields=4, frames=2)  # views 0 and 30 degrees off nadir
    train, hold = learned_train.frames_source(frames)[:2]
    near, near_hold, what = learned_train.frames_source(frames, max_off_nadir=10.0)[:3]
    assert len(train) == 6 and [r["index"] for _, r in near] == [0, 2, 4]
    assert all(training_rows.off_nadir_deg(r) == 0.0 for _, r in near) and what["max_off_nadir_deg"] == 10.0
    assert [r["index"] for _, r in near_hold] == [r["index"] for _, r in hold] == [6, 7]
    assert [r["index"] for _, r in learned_train.frames_source(frames, 2, 10.0)[0]] == [0, 2]
    no_train, only_hold, _ = learned_train.detection_set_records(frames, 0.1, training=False)
    assert no_train == [] and [r["index"] for _, r in only_hold] == [6, 7]
    with pytest.raises(UserError, match=r"det: nav.detector_train.frames=4, but the set has 3 training frames "):
        learned_train.frames_source(frames, 4, 10.0)
    strict = fake_detection_set(tmp_path / "oblique", fields=2, frames=1)
    rows = manifest_rows(strict)
    (strict / "manifest.jsonl").write_text(
        "".join(json.dumps(r | {"view": {"off_nadir_deg": 40.0}}) + "\n" for r in rows.values())
    )
    with pytest.raises(UserError, match=r"oblique: training needs frames, but the set has 0 .* within 20 degrees"):
        learned_train.frames_source(strict, max_off_nadir=20.0)
    with pytest.raises(ValueError, match="max_off_nadir_deg"):
        cd.DetectorTrainSettings(max_off_nadir_deg=91.0)
    survey = fake_survey(tmp_path / "survey", tracks=12, frames=1)
    assert (
        len(learned_train.frames_source(survey, max_off_nadir=0.0)[0])
        == 2
        == len(learned_train.survey_source(survey)[0])
    )


def test_code_commit_says_when_the_tree_differs_from_its_commit(monkeypatch, tmp_path):
    """A model's provenance: the commit, ``-dirty`` when a tracked file differs from it, "unknown" outside a
    checkout (never a tag name)."""
    import subprocess

    from crater_synth.navigation.rendered import detector_train as dt

    git = ["git", "-C", str(tmp_path), "-c", "user.email=t@t", "-c", "user.name=t"]
    subprocess.run([*git, "init", "-q"], check=True)
    (tmp_path / "a.py").write_text("x = 1\n")
    subprocess.run([*git, "add", "a.py"], check=True)
    subprocess.run([*git, "commit", "-qm", "a"], check=True)
    subprocess.run([*git, "tag", "v1"], check=True)
    head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    monkeypatch.setattr(dt, "SOURCE_ROOT", tmp_path)
    assert dt.code_commit() == head
    (tmp_path / "a.py").write_text("x = 2\n")
    assert dt.code_commit() == head + "-dirty"
    monkeypatch.setattr(dt, "SOURCE_ROOT", tmp_path / "none")
    assert dt.code_commit() == "unknown"


def test_a_model_names_the_commit_its_training_started_from(monkeypatch, tmp_path):
    """A training runs for up to hours; a commit made meanwhile is not the code that trained the model."""
    from crater_synth.navigation.rendered import detector_train as dt

    tree = {"commit": "started"}
    real = dt.architecture

    def committing_meanwhile(arch):
        train, save, scoring = real(arch)

        def train_and_commit(*args, **kwargs):
            tree["commit"] = "committed during the run"
            return train(*args, **kwargs)

        return train_and_commit, save, scoring

    monkeypatch.setattr(dt, "code_commit", lambda: tree["commit"])
    monkeypatch.setattr(dt, "architecture", committing_meanwhile)
    frames = fake_detection_set(tmp_path / "det", fields=4)
    s = cd.DetectorTrainSettings(steps=2, batch=2, crop_px=32, width=4, threads=1)
    assert dt.train_from_detection(frames, tmp_path / "m.pt", s, holdout_share=0.25)["code_commit"] == "started"
