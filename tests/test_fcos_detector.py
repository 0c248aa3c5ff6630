"""torchvision's FCOS as a crater detector (train.fcos_detector, detectors/fcos.py) and the NMS that lets
torchvision run on the CPU torch (train.tv_ops)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from test_learned_detector import crater_field, fake_detection_set

from crater_synth.errors import UserError
from crater_synth.navigation.detectors import fcos
from crater_synth.navigation.detectors.classical import detect
from crater_synth.navigation.detectors.learned import DetectorModelFileError
from crater_synth.navigation.rendered import detector_train
from crater_synth.navigation.settings import compose_nav
from crater_synth.tools.detector_choice import model_option
from train import crater_detector as cd
from train import fcos_detector as fd
from train.tv_ops import greedy_nms, import_torchvision


def reference_nms(boxes: np.ndarray, scores: np.ndarray, thr: float) -> list[int]:
    """Greedy NMS one box at a time (stable decreasing score, IoU > thr suppresses)."""
    order = sorted(range(len(scores)), key=lambda i: -scores[i])
    keep: list[int] = []
    for i in order:
        ok = True
        for j in keep:
            a, b = boxes[i], boxes[j]
            iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
            ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
            inter = iw * ih
            union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
            if union > 0 and inter / union > thr:
                ok = False
                break
        if ok:
            keep.append(i)
    return keep


def random_boxes(rng, n: int, ties: bool):
    xy = rng.uniform(0, 100, (n, 2))
    wh = rng.uniform(5, 40, (n, 2))
    scores = rng.integers(0, 4, n).astype(np.float64) if ties else rng.uniform(0, 1, n)
    return np.concatenate([xy, xy + wh], 1), scores


@pytest.mark.parametrize("ties", [False, True])
@pytest.mark.parametrize("thr", [0.0, 0.3, 0.7])
def test_nms_equals_a_reference_greedy_nms(ties, thr):
    tv = import_torchvision()
    rng = np.random.default_rng(int(thr * 10) + ties)
    for n in (1, 2, 17, 200):
        boxes, scores = random_boxes(rng, n, ties)
        want = reference_nms(boxes, scores, thr)
        b, s = torch.tensor(boxes, dtype=torch.float32), torch.tensor(scores, dtype=torch.float32)
        assert greedy_nms(b, s, thr).tolist() == want
        assert tv.ops.nms(b, s, thr).tolist() == want  # the registered operator (ours or torchvision's own)


def test_nms_of_no_box_and_batched_nms():
    tv = import_torchvision()
    empty = tv.ops.nms(torch.zeros(0, 4), torch.zeros(0), 0.5)
    assert empty.dtype == torch.int64 and empty.numel() == 0
    rng = np.random.default_rng(3)
    boxes, scores = random_boxes(rng, 300, False)
    classes = rng.integers(0, 3, 300)
    b, s = torch.tensor(boxes, dtype=torch.float32), torch.tensor(scores, dtype=torch.float32)
    got = tv.ops.batched_nms(b, s, torch.tensor(classes), 0.4).tolist()
    want = []
    for c in range(3):
        idx = np.nonzero(classes == c)[0]
        want.extend(idx[reference_nms(boxes[idx], scores[idx], 0.4)].tolist())
    assert got == sorted(want, key=lambda i: -scores[i])


@pytest.mark.parametrize("k", range(4))
@pytest.mark.parametrize("flip", [False, True])
def test_dihedral_circles_follow_the_pixels(k, flip):
    img = torch.zeros(1, 12, 12)
    img[0, 2, 7] = 1.0  # the pixel centred at (u, v) = (7.5, 2.5)
    t = torch.rot90(img, k, dims=(-2, -1))
    t = torch.flip(t, dims=(-2,)) if flip else t
    i, j = (int(x) for x in torch.nonzero(t[0])[0])
    u, v, r = fd.dihedral_circles(np.array([[7.5, 2.5, 3.0]]), 12, k, flip)[0]
    assert (u, v, r) == (j + 0.5, i + 0.5, 3.0)


def test_fcos_trains_saves_loads_and_detects_through_detect(tmp_path):
    """Two training steps on a small detection set (nav-detector-train's path, arch=fcos), its synthetic
    hold-out scored, the model file loaded back, and detect() with nav/detector=fcos."""
    frames = fake_detection_set(tmp_path / "det", fields=3)
    out = tmp_path / "fcos.pt"
    s = cd.DetectorTrainSettings(arch="fcos", steps=2, batch=2, crop_px=64, width=16, threads=1, lr=1e-3)
    summary = detector_train.train_from_sources([detector_train.detection_source(frames, 0.34)], out, s)
    assert summary["holdout"]["frames"] == 2 and summary["settings"]["arch"] == "fcos"
    model, meta = fd.load_model(out)
    assert meta["settings"]["width"] == 16 and fd.weight_count(model) > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["det", "fcos.pt"]
    # Two steps leave the box regression near its zero start (sub-pixel boxes, all below any radius
    # searched): boxes of 1 anchor size each side (r = 8 px at P3 ... 128 px at P7) exercise the plumbing.
    with torch.no_grad():
        model.head.regression_head.bbox_reg.bias.fill_(1.0)
    fd.save_model(out, model, meta)
    nav = compose_nav(["nav/detector=fcos"]).detector
    assert isinstance(nav, fcos.FcosSettings) and not nav.refine
    params = dataclasses.replace(nav, model=str(out), threshold=0.0, min_radius_px=4.5)
    dets, theta = detect(crater_field(5)[0], params)
    assert np.isnan(theta) and dets
    assert all(params.min_radius_px <= d.r <= params.max_radius_px for d in dets)


def test_detect_fcos_reads_boxes_back_as_circles_in_frame_pixels(monkeypatch):
    class Fixed(torch.nn.Module):
        def forward(self, images):
            assert images[0].shape == (1, 32, 32)  # a 64 px frame searched at level 1
            return [{"boxes": torch.tensor([[4.0, 6.0, 12.0, 12.0]]), "scores": torch.tensor([0.9])}]

    u, v, r, s = fd.detect_fcos(Fixed(), np.ones((64, 64)), 0.5, level=1)
    assert (u[0], v[0], r[0], s[0]) == pytest.approx((16.0, 18.0, 7.0, 0.9))


def test_bad_fcos_models_are_one_error_line(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a model")
    params = fcos.FcosSettings(model=str(bad))
    with pytest.raises(DetectorModelFileError, match="bad.pt: cannot be read"):
        detect(crater_field(1)[0], params)
    centernet = tmp_path / "centernet.pt"
    cd.save_model(centernet, cd.CraterNet(4), {})
    with pytest.raises(DetectorModelFileError, match="not a crater-synth-fcos-detector/1 file"):
        fcos.load_fcos_model(str(centernet))
    with pytest.raises(UserError, match="arch=fcos"):
        detect(crater_field(1)[0], fcos.FcosSettings())


def test_arch_setting_cli_guard_and_choice_models(tmp_path):
    from click.testing import CliRunner

    from crater_synth.cli import main

    with pytest.raises(ValueError, match="arch"):
        cd.DetectorTrainSettings(arch="yolo")
    res = CliRunner().invoke(main, ["nav-detector-train", str(tmp_path), "nav.detector_train.arch=fcos"])
    assert res.exit_code != 0 and "needs --out" in res.output
    assert model_option("fcos:/a/m.pt") == ("fcos", "/a/m.pt")
    assert model_option("/a/m.pt") == ("learned-detect", "/a/m.pt")
    assert model_option("committed") == ("learned-detect", "committed")
