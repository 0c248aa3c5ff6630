"""The learned detector trained and run sun-aligned (train/light_turn.py, nav.detector_train.sun_aligned): the
frame turned so its light travels along +u, the labels with it, no quarter-turn augmentation, and the
detections turned back into the frame's pixels."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from test_learned_detector import crater_field, fake_detection_set

from crater_synth.errors import UserError
from crater_synth.navigation.detectors import learned
from crater_synth.navigation.detectors.classical import detect
from crater_synth.navigation.rendered import detector_train as learned_train
from crater_synth.navigation.rendered import training_rows
from crater_synth.navigation.rendered.sunlight import light_direction, rendered_light, row_to_sun
from train import crater_detector as cd
from train import crater_detector_inference as infer
from train.light_turn import turn_to_light, turned_shape

# A nadir camera of a detection row: image right = east, image up = north, looking down.
NADIR = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


@pytest.mark.parametrize("light", [0.0, 0.7, -2.5, math.pi / 2, 3.0])
def test_a_turned_frame_keeps_its_points_and_its_light_travels_along_u(light):
    h, w = 48, 64
    dot = np.zeros((h, w), np.float32)
    dot[10, 30] = 1.0  # the pixel centred at (30.5, 10.5)
    turned = turn_to_light(dot, light)
    assert turned.image.shape == turned_shape((h, w), light)
    i, j = np.unravel_index(np.nanargmax(turned.image), turned.image.shape)
    pu, pv = turned.points(30.5, 10.5)
    assert abs(pu - (j + 0.5)) <= 0.5 and abs(pv - (i + 0.5)) <= 0.5
    assert np.allclose(turned.back(pu, pv), (30.5, 10.5))
    inside = np.isfinite(turned.image).sum()
    assert 0.95 * h * w < inside <= h * w  # the frame, less its edge pixels where the turn mixes in the outside
    uu, vv = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    ramp = turn_to_light((math.cos(light) * uu + math.sin(light) * vv).astype(np.float32), light).image
    gv, gu = np.gradient(ramp)
    assert math.atan2(np.nanmean(gv), np.nanmean(gu)) == pytest.approx(0.0, abs=1e-3)
    with pytest.raises(ValueError, match="finite"):
        turn_to_light(dot, math.nan)


def test_pixels_outside_the_turned_frame_carry_no_loss_and_no_brightness():
    image = np.ones((40, 40), np.float32)
    image[:, :10] = np.nan
    sample = cd.LevelSample(image, np.array([25.0]), np.array([20.0]), np.array([8.0]), np.zeros(1, bool))
    assert cd.brightness_top(image) == 1.0
    t = cd.crop_stack(sample, 1.0, 0, 0, 48, 48)
    valid, img = t[cd._VALID], t[cd._IMG]
    assert not valid[:, :10].any() and valid[:40, 10:40].all() and not valid[40:].any()
    assert np.isfinite(img).all() and (img[:, :10] == 0).all()


def test_a_sun_aligned_plan_never_turns_a_crop_but_mirrors_along_the_light():
    samples = [cd.LevelSample(np.zeros((64, 64), np.float32), *(np.zeros(0),) * 3, np.zeros(0, bool))]
    s = cd.DetectorTrainSettings(batch=200, crop_px=32, sun_aligned=True)
    plan = cd.plan_batch(samples, s, np.random.default_rng(0))
    assert {p[3] for p in plan} == {0} and {p[4] for p in plan} == {False, True}
    free = cd.plan_batch(samples, dataclasses.replace(s, sun_aligned=False), np.random.default_rng(0))
    assert {p[3] for p in free} == {0, 1, 2, 3}
    with pytest.raises(ValueError, match="sun_aligned"):
        cd.DetectorTrainSettings(arch="fcos", sun_aligned=True)


def _sunlit_rows(folder, azimuth_deg: float = 90.0):
    """Give a fake detection set's rows a nadir camera and a Sun (``sun_enu``), as detection-frames writes."""
    path = folder / "manifest.jsonl"
    rows = [json.loads(line) for line in path.read_text().splitlines()]
    for row in rows:
        row["camera_enu"] = {"rotation": NADIR, "width_px": 128, "fov_deg": 10.0, "position_m": [0.0, 0.0, 1e5]}
        row["sun_enu"] = {"elevation_deg": 10.0, "azimuth_deg": azimuth_deg}
    path.write_text("".join(json.dumps(row) + "\n" for row in rows))
    return rows


def test_a_training_frame_and_its_rims_turn_together_and_a_frame_without_a_sun_is_named(tmp_path):
    folder = fake_detection_set(tmp_path / "det", fields=2, frames=1, label_files=True)
    rows = _sunlit_rows(folder, azimuth_deg=90.0)  # Sun in the east: light travels west, to -u
    assert rendered_light(rows[0]) == pytest.approx(math.pi)
    assert rendered_light(rows[0]) == pytest.approx(light_direction(np.array(NADIR), row_to_sun(rows[0])))
    image, u, v, r = crater_field(2000)
    circles = (u, v, r, 2 * r * 0.06, np.zeros(len(u), bool))
    plain = training_rows.training_levels(image, rows[0], circles)[0]
    turned = training_rows.training_levels(image, rows[0], circles, sun_aligned=True)[0]
    # a half turn: every rim centre and pixel goes to the point opposite the centre
    assert np.allclose(turned.u, 128.0 - plain.u) and np.allclose(turned.v, 128.0 - plain.v)
    assert np.allclose(turned.image[1:-1, 1:-1], image[::-1, ::-1][1:-1, 1:-1], atol=1e-5)
    streamed = learned_train.detection_source(folder, 0.5, stream=True)[0]
    levels = training_rows.StreamedFrames([row for _, row in streamed], sun_aligned=True)
    assert [cd.sample_shape(levels, i) for i in range(len(levels))] == [np.shape(x.image) for x in levels]
    bare = {k: v for k, v in rows[0].items() if k != "sun_enu"}
    with pytest.raises(UserError, match="frame_000000.exr.*sun_aligned"):
        training_rows.training_levels(image, bare, circles, sun_aligned=True)


def test_a_sun_aligned_training_writes_a_model_the_detector_turns_each_frame_for(tmp_path):
    folder = fake_detection_set(tmp_path / "det", fields=3, frames=2, label_files=True)
    _sunlit_rows(folder)
    out = tmp_path / "aligned.pt"
    s = cd.DetectorTrainSettings(steps=3, batch=2, crop_px=32, width=4, threads=1, sun_aligned=True, stream=True)
    summary = learned_train.train_from_detection(folder, out, s, holdout_share=0.34)
    model, meta = learned.load_model(str(out))
    assert learned.sun_aligned(meta) and summary["settings"]["sun_aligned"] and summary["holdout"]["frames"] == 2
    image = crater_field(7)[0]
    params = learned.LearnedSettings(model=str(out), threshold=0.0, refine=False, min_radius_px=4.5)
    with pytest.raises(UserError, match="aligned.pt is sun-aligned.*light"):
        detect(image, params)
    plain = tmp_path / "plain.pt"
    cd.save_model(plain, model, {"settings": {"sun_aligned": False}})
    with pytest.raises(learned.DetectorModelFileError, match="every model is sun-aligned"):
        detect(image, dataclasses.replace(params, ensemble=(str(plain),)), light_dir=0.0)
    dets, _ = detect(image, params, light_dir=1.0)
    assert dets and all(0 <= d.u < 128 and 0 <= d.v < 128 for d in dets)


def test_the_detector_finds_a_peak_where_the_turned_frame_had_it(monkeypatch, tmp_path):
    """The network's peak at a point of the turned frame comes back at that point of the frame."""
    path = tmp_path / "m.pt"
    cd.save_model(path, cd.CraterNet(4), {"settings": {"sun_aligned": True}})
    image = np.random.default_rng(0).random((100, 140)).astype(np.float32)
    light = 2.2
    turned = turn_to_light(image, light)
    tu, tv = turned.points(np.array([50.0]), np.array([40.0]))
    seen = {}

    def fake_pyramid(models, img, threshold, first, tta, half, sun_aligned=False):
        seen.update(shape=img.shape, finite=bool(np.isfinite(img).all()), sun_aligned=sun_aligned)
        return tu, tv, np.array([9.0]), np.array([0.9]), np.array([0.0])

    monkeypatch.setattr(infer, "detect_pyramid", fake_pyramid)
    params = learned.LearnedSettings(model=str(path), refine=False, border_r=0.0)
    dets, _ = detect(image, params, light_dir=light)
    assert seen == {"shape": turned.image.shape, "finite": True, "sun_aligned": True}
    assert len(dets) == 1 and (dets[0].u, dets[0].v) == pytest.approx((50.0, 40.0)) and dets[0].r == 9.0


def test_a_sun_aligned_model_is_seen_as_it_is_and_mirrored_along_the_light_only():
    class Counting(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.inputs = []

        def forward(self, x):
            self.inputs.append(x.clone())
            return torch.zeros(1, 4, *x.shape[-2:])

    model = Counting()
    a = np.random.default_rng(1).random((16, 24)).astype(np.float32)
    infer.level_output(model, a, tta=8, sun_aligned=True)
    assert len(model.inputs) == 2 and torch.equal(model.inputs[1], model.inputs[0].flip(2))
    model.inputs.clear()
    infer.level_output(model, a, tta=8)
    assert len(model.inputs) == 8


def test_detect_asks_for_the_light_of_a_sun_aligned_model_and_uses_it(tmp_path):
    """``crater-synth detect`` with a sun-aligned model: refused up front without ``--light-azimuth`` (one
    line naming the model), run with it; a model trained without the turn still refuses the option."""
    import cv2
    from click.testing import CliRunner

    from crater_synth.cli import main

    aligned, plain = tmp_path / "aligned.pt", tmp_path / "plain.pt"
    cd.save_model(aligned, cd.CraterNet(4), {"settings": {"sun_aligned": True}})
    cd.save_model(plain, cd.CraterNet(4), {"settings": {"sun_aligned": False}})
    img = tmp_path / "field.png"
    assert cv2.imwrite(str(img), (crater_field(3)[0] / crater_field(3)[0].max() * 255).astype(np.uint8))
    runner = CliRunner()
    r = runner.invoke(main, ["detect", str(img), "--detector", "learned", f"nav.detector.model={aligned}"])
    assert r.exit_code != 0 and "aligned.pt is sun-aligned: give the light with --light-azimuth" in r.output
    args = ["detect", str(img), "--detector", "learned", "--light-azimuth", "35", "nav.detector.threshold=0.0"]
    r = runner.invoke(main, [*args, f"nav.detector.model={aligned}"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(main, [*args, f"nav.detector.model={plain}"])
    assert r.exit_code != 0 and "uses no light direction" in r.output
