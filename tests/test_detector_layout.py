"""How the learned detector's network runs, not what it learns: the channels-last layout and the bfloat16
forward pass of its training (``nav.detector_train.channels_last``, ``nav.detector_train.precision``;
train/detector_fit.py ``fit``, ``autocast_forward``), and the layout its model files keep
(train/model_files.py)."""

from __future__ import annotations

import hashlib
import io

import numpy as np
import pytest
import torch
from test_learned_detector import crater_field, fake_detection_set

from crater_core.typed_config import SettingsError
from crater_synth.navigation.rendered import detector_train
from train import crater_detector as cd
from train import crater_detector_inference as infer
from train import detector_fit
from train import fcos_detector as fd
from train.model_files import write_model_file


def samples(n_fields: int = 3):
    """Level samples of small shaded bowl fields (the learning test's, smaller)."""
    out = []
    for seed in range(n_fields):
        img, u, v, r = crater_field(seed, size=64, n=3)
        out.extend(cd.level_samples(img, u, v, r))
    return out


def short(**kw) -> cd.DetectorTrainSettings:
    return cd.DetectorTrainSettings(steps=3, batch=2, crop_px=32, width=4, threads=1, **kw)


def test_either_layout_trains_alike_and_hands_back_the_standard_layout():
    data = samples()
    nchw = cd.train_detector(data, short(channels_last=False))
    nhwc = cd.train_detector(data, short(channels_last=True))
    assert nhwc["history"][-1]["loss"] == pytest.approx(nchw["history"][-1]["loss"], rel=1e-3)
    for k, v in nhwc["model"].state_dict().items():
        assert v.stride() == v.clone(memory_format=torch.contiguous_format).stride(), k
    # Adam's first steps move each weight by ~lr whatever its gradient's size, so a gradient rounded to the
    # other side of 0 moves a weight the other way: compare what the networks compute, not the weights.
    x = torch.randn(2, 1, 48, 48)
    assert torch.allclose(nchw["model"](x), nhwc["model"](x), atol=1e-2)


def test_a_bfloat16_forward_pass_trains_float32_weights_near_the_float32_run():
    data = samples()
    fp32 = cd.train_detector(data, short())
    bf16 = cd.train_detector(data, short(precision="bf16"))
    assert all(v.dtype in (torch.float32, torch.int64) for v in bf16["model"].state_dict().values())
    assert np.isfinite([h["loss"] for h in bf16["history"]]).all()
    first = [h["loss"] for h in (fp32["history"][-1], bf16["history"][-1])]
    assert first[1] == pytest.approx(first[0], rel=0.05)  # bfloat16 keeps ~3 significant digits


def test_autocast_forward_hands_back_float32_tensors_and_loss_dicts():
    model = cd.CraterNet(4)
    x = torch.randn(1, 1, 32, 32)
    assert detector_fit.autocast_forward(model, "fp32", "cpu") is model
    forward = detector_fit.autocast_forward(model, "bf16", "cpu")
    out = forward(x)
    assert out.dtype == torch.float32 and out.shape == (1, 4, 32, 32)
    assert torch.allclose(out, model(x), atol=0.1)
    losses = detector_fit.autocast_forward(
        lambda t: {"a": t.sum(), "b": (t @ t.transpose(-1, -2)).mean()}, "bf16", "cpu"
    )(x)
    assert {k: v.dtype for k, v in losses.items()} == {"a": torch.float32, "b": torch.float32}


def test_a_model_file_holds_the_standard_layout_whatever_layout_the_model_runs_in(tmp_path):
    model = cd.CraterNet(4)
    buf = io.BytesIO()
    torch.save(model.state_dict(), buf)  # how a standard-layout model was always saved: its bytes unchanged
    cd.save_model(tmp_path / "a.pt", model, {})
    cd.save_model(tmp_path / "b.pt", model.to(memory_format=torch.channels_last), {})  # .to: in place
    write_model_file(tmp_path / "c.pt", "x/1", model.state_dict(), {})  # any detector's file, the same rule
    digest = [torch.load(tmp_path / n, weights_only=True)["weights_sha256"] for n in ("a.pt", "b.pt", "c.pt")]
    assert digest == [hashlib.sha256(buf.getvalue()).hexdigest()] * 3


def test_a_loaded_model_runs_channels_last_and_detects_as_the_standard_layout_does(tmp_path):
    path = tmp_path / "m.pt"
    cd.save_model(path, cd.CraterNet(8), {})
    loaded, _ = cd.load_model(path)
    conv = loaded.enc0[0][0].weight
    assert conv.is_contiguous(memory_format=torch.channels_last)
    standard = cd.CraterNet(8)
    standard.load_state_dict(loaded.state_dict())
    standard.eval()
    a = np.random.default_rng(0).random((96, 96)).astype(np.float32)
    np.testing.assert_allclose(infer.level_output(loaded, a, 2), infer.level_output(standard, a, 2), atol=1e-5)


def test_an_unknown_precision_is_one_error_naming_the_setting():
    with pytest.raises(SettingsError, match="precision"):
        cd.DetectorTrainSettings(precision="fp16")


def test_fcos_trains_in_the_standard_layout_and_under_bfloat16(tmp_path, monkeypatch):
    """FCOS keeps the standard layout whatever ``channels_last`` says (its training step ran slower channels
    last), and trains under the bfloat16 forward pass as torchvision's references do under autocast."""
    frames = fake_detection_set(tmp_path / "det", fields=3)
    s = cd.DetectorTrainSettings(arch="fcos", steps=2, batch=2, crop_px=64, width=16, threads=1, precision="bf16")
    layouts = []

    def fit(build, *args, channels_last=False):
        layouts.append(channels_last)
        return detector_fit.fit(build, *args, channels_last=channels_last)

    monkeypatch.setattr(fd, "fit", fit)
    summary = detector_train.train_from_sources([detector_train.detection_source(frames, 0.34)], tmp_path / "m.pt", s)
    assert layouts == [False] and s.channels_last
    assert summary["settings"]["precision"] == "bf16"
    model, meta = fd.load_model(tmp_path / "m.pt")
    assert np.isfinite([h["loss"] for h in meta["history"]]).all()
    assert all(v.dtype in (torch.float32, torch.int64) for v in model.state_dict().values())
