"""LunarNet_ex: the paper's layer order, shapes, parameter count / FLOPs as documented."""

import pytest
import torch
from torch import nn

from crater_core.settings import ConvSettings, SettingsError, replace
from crater_synth.config import load_settings
from train.models import PAPER_LAYER_ORDER, LunarNetEx, multiply_adds, parameter_count

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def mcfg():
    return load_settings([]).model


def test_layer_order_is_the_papers(mcfg):
    model = LunarNetEx(mcfg)
    names = [n for n, _ in model.layers.named_children()]
    assert tuple(names) == PAPER_LAYER_ORDER
    kinds = [type(m) for _, m in model.layers.named_children()]
    assert kinds == [nn.Conv2d, nn.ReLU, nn.MaxPool2d, nn.Conv2d, nn.ReLU, nn.Flatten, nn.Linear, nn.ReLU, nn.Linear]
    assert model.layers.conv1.stride == (1, 1)
    # No pooling after CONV2: exactly one pooling layer, before conv2.
    pools = [n for n, m in model.layers.named_children() if isinstance(m, (nn.MaxPool2d, nn.AvgPool2d))]
    assert pools == ["pool"] and names.index("pool") < names.index("conv2")
    # The softmax is not a module (it is in the loss / predict_proba): forward returns logits.
    assert not any(isinstance(m, nn.Softmax) for m in model.modules())


def test_output_shape_and_softmax(mcfg):
    model = LunarNetEx(mcfg).eval()
    x = torch.rand(2, 1, 150, 150)
    assert model(x).shape == (2, 3)
    p = model.predict_proba(x)
    assert torch.allclose(p.sum(1), torch.ones(2), atol=1e-5)
    assert model.fc1_features(x).shape == (2, mcfg.fc1)


def test_parameter_count_and_macs_match_docs(mcfg):
    model = LunarNetEx(mcfg)
    assert parameter_count(model) == 1_062_723  # docs/classifiers.md
    assert multiply_adds(mcfg)["total"] == 20_582_784


def test_bad_model_config_is_refused_by_the_settings(mcfg):
    with pytest.raises(SettingsError, match="conv1.stride=2: must be 1"):
        replace(mcfg, conv1=ConvSettings(channels=8, kernel=5, stride=2))
    with pytest.raises(SettingsError, match="input_size=12: too small"):
        replace(mcfg, input_size=12)
