"""Evaluation on real crops: test-time averaging over the unknown camera roll (``train.tta_rotations``)."""

import numpy as np
import pytest
import torch

from crater_core.settings import replace
from crater_synth.config import ConfigError, compose, load_settings, resolved
from train.evaluate import roll_averaged_predictions
from train.models import LunarNetEx, hog_features, make_linear_svm
from train.preprocess import PreprocessConfig, apply_support
from train.trainer import fc1_activations, predict_logits

torch.set_num_threads(1)
SIZE = 48
SETTINGS = load_settings([])
HOG = replace(SETTINGS.train.hog, pixels_per_cell=8, cells_per_block=2, orientations=9, max_iter=2000)


@pytest.fixture(scope="module")
def models():
    """A small random LunarNet_ex and two linear SVMs fitted on random disc crops (3 classes)."""
    torch.manual_seed(0)
    net = LunarNetEx(replace(SETTINGS.model, input_size=SIZE)).eval()
    rng = np.random.default_rng(0)
    disc = PreprocessConfig(support="disc", size=SIZE)
    x = apply_support(rng.random((60, SIZE, SIZE), dtype=np.float32), disc)
    y = np.arange(60) % 3
    svm = make_linear_svm(replace(SETTINGS.train.svm, max_iter=2000), 0).fit(fc1_activations(net, x), y)
    hog = make_linear_svm(HOG, 1).fit(hog_features(x, HOG), y)
    images = apply_support(rng.random((12, SIZE, SIZE), dtype=np.float32), disc)
    return net, svm, hog, images


def _softmax(logits):
    p = np.exp(logits - logits.max(axis=1, keepdims=True))
    return p / p.sum(axis=1, keepdims=True)


def test_one_roll_is_each_models_plain_prediction(models):
    net, svm, hog, images = models
    pred = roll_averaged_predictions(net, svm, hog, HOG, images, 1, 8, torch.device("cpu"))
    np.testing.assert_array_equal(pred["lunarnet_ex"], predict_logits(net, images).argmax(1))
    np.testing.assert_array_equal(pred["lunarsvm_ex"], svm.predict(fc1_activations(net, images)))
    np.testing.assert_array_equal(pred["hog_svm"], hog.predict(hog_features(images, HOG)))


def test_four_rolls_average_the_scores_over_right_angle_turns(models):
    """With 4 rolls the scores are averaged over the crop and its turns by 90, 180 and 270 degrees
    (exact rotations of the pixel grid): the prediction is the arg-max of those averaged scores, the
    same set of scores whichever of the four turns comes in (up to the order of a floating sum)."""
    net, svm, hog, images = models
    turns = [np.rot90(images, k, axes=(1, 2)).copy() for k in range(4)]
    net_p = np.mean([_softmax(predict_logits(net, t).astype(np.float64)) for t in turns], axis=0)
    svm_s = np.mean([svm.decision_function(fc1_activations(net, t)) for t in turns], axis=0)
    hog_s = np.mean([hog.decision_function(hog_features(t, HOG)) for t in turns], axis=0)
    pred = roll_averaged_predictions(net, svm, hog, HOG, images, 4, 8, torch.device("cpu"))
    np.testing.assert_array_equal(pred["lunarnet_ex"], net_p.argmax(1))
    np.testing.assert_array_equal(pred["lunarsvm_ex"], svm.classes_[svm_s.argmax(1)])
    np.testing.assert_array_equal(pred["hog_svm"], hog.classes_[hog_s.argmax(1)])


def test_roll_averaging_needs_disc_support():
    with pytest.raises(ConfigError, match="tta_rotations"):
        compose(["train.tta_rotations=8"])  # square support (the default)
    with pytest.raises(ConfigError, match="tta_rotations"):
        compose(["train=sim2real", "train.tta_rotations=0"])
    assert resolved(compose(["train=sim2real", "train.tta_rotations=8"]))["train"]["tta_rotations"] == 8
