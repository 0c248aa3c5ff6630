"""Crater detectors of crater_synth.navigation: light direction, suppression, the template method, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crater_core.typed_config import SettingsError
from crater_synth.errors import ConfigError
from crater_synth.navigation.detectors.classical import (
    ClassicalSettings,
    azimuth_grads,
    detect,
    light_axis,
    spectrum,
    suppress,
)
from crater_synth.navigation.detectors.template import (
    TemplateSettings,
    crater_heights,
    crater_template,
    ncc,
    shade_heights,
)
from crater_synth.navigation.georef import FrameError

CRATERS = [(80.0, 90.0, 14.0), (250.0, 80.0, 22.0), (150.0, 200.0, 30.0), (300.0, 290.0, 18.0), (90.0, 300.0, 25.0)]


def crater_field(theta_deg: float, n: int = 384, sun_el_deg: float = 15.0, craters=CRATERS, noise: float = 0.0):
    """Hapke-shaded, cast-shadowed nadir image of bowl craters (heights in px) under a known light."""
    vv, uu = np.mgrid[0:n, 0:n] + 0.5
    z = np.zeros((n, n))
    for cu, cv, r in craters:
        z += crater_heights(np.hypot(uu - cu, vv - cv) / r, 0.2) * r
    img = shade_heights(z, math.radians(theta_deg), sun_el_deg) * 200.0 + 20.0
    if noise:
        img = img + np.random.default_rng(0).normal(0.0, noise, img.shape)
    return img


def _near(dets, cu, cv, r, within=0.5):
    return [d for d in dets if math.hypot(d.u - cu, d.v - cv) < within * r]


@pytest.mark.parametrize("theta_deg", [0.0, 70.0, 135.0, 250.0])
def test_structure_tensor_recovers_the_light_axis(theta_deg):
    img = crater_field(theta_deg)
    a = (img - img.mean()) / img.std()
    spec, shape = spectrum(a)
    axis = math.degrees(light_axis(azimuth_grads(spec, shape, ClassicalSettings())))
    err = (axis - theta_deg + 90.0) % 180.0 - 90.0  # an axis: modulo 180 degrees
    assert abs(err) < 8.0


@pytest.mark.parametrize("theta_deg", [20.0, 200.0])
def test_light_direction_sign_on_synthetic_bowls(theta_deg):
    # On clean synthetic bowls the strongest rise runs with the light (shadow -> lit far wall); the real
    # mosaic's validation windows need the opposite convention (nav.detector.tail_points_to_sun, docs).
    _, theta = detect(crater_field(theta_deg), ClassicalSettings(light_method="tensor", tail_points_to_sun=False))
    err = (math.degrees(theta) - theta_deg + 180.0) % 360.0 - 180.0
    assert abs(err) < 8.0
    _, flipped = detect(crater_field(theta_deg), ClassicalSettings(light_method="tensor", tail_points_to_sun=True))
    assert abs((math.degrees(flipped) - theta_deg) % 360.0 - 180.0) < 8.0


def test_concentric_suppression_keeps_one_per_crater():
    # Three concentric detections of one crater and one of a neighbour: one each survives.
    u = np.array([100.0, 101.0, 99.0, 160.0])
    v = np.array([100.0, 100.5, 99.0, 100.0])
    r = np.array([20.0, 11.0, 35.0, 15.0])
    score = np.array([1.0, 2.0, 0.5, 1.5])
    keep = suppress(u, v, r, score, 0.5, math.inf)
    assert sorted(keep.tolist()) == [1, 3]  # the best-ranked of the concentric group, and the neighbour
    # Without the concentric rule (radius ratio 1.5) the nested members of different size all survive.
    assert len(suppress(u, v, r, score, 0.6, 1.5)) == 4


@pytest.mark.parametrize("method", ["classical", "template"])
def test_detectors_leave_one_detection_per_synthetic_crater(method):
    theta = 30.0
    img = crater_field(theta, noise=2.0)
    settings = {"classical": ClassicalSettings, "template": TemplateSettings}[method](concentric_r=0.5)
    dets, _ = detect(img, settings, light_dir=math.radians(theta))
    counts = [len(_near(dets, cu, cv, r)) for cu, cv, r in CRATERS]
    assert max(counts) <= 1, (method, counts)  # never two detections of one crater
    assert sum(counts) >= 4, (method, counts)  # and the craters are found


def test_template_method_finds_synthetic_craters():
    theta = 200.0
    img = crater_field(theta, noise=2.0)
    dets, _ = detect(img, TemplateSettings(), light_dir=math.radians(theta))
    found = 0
    for cu, cv, r in CRATERS:
        # The evaluation's match rule: centre within 0.25 D, diameter within 25 %.
        found += any(math.hypot(d.u - cu, d.v - cv) <= 0.5 * r and abs(d.r / r - 1.0) <= 0.25 for d in dets)
    assert found >= 4
    # A flat frame with noise only yields (almost) nothing.
    noise = np.random.default_rng(1).normal(100.0, 5.0, (384, 384))
    none, _ = detect(noise, TemplateSettings(), light_dir=math.radians(theta))
    assert len(none) <= 2


def test_ncc_is_one_on_the_template_itself_and_contrast_invariant():
    t = crater_template(0.3, 10.0, 8.0, 0.2)
    assert abs(float(t.mean())) < 1e-9 and np.linalg.norm(t) == pytest.approx(1.0)
    img = np.zeros((80, 80))
    m = t.shape[0]
    img[20 : 20 + m, 30 : 30 + m] = t
    c = ncc(img, t)
    i, j = np.unravel_index(np.argmax(c), c.shape)
    assert (i, j) == (20 + m // 2, 30 + m // 2)
    assert c[i, j] == pytest.approx(1.0, abs=1e-6)
    assert ncc(3.0 * img + 7.0, t)[i, j] == pytest.approx(1.0, abs=1e-6)


def test_bad_detector_input_gives_one_clear_error():
    with pytest.raises(SettingsError, match="method='cnn': must be 'classical'"):
        ClassicalSettings(method="cnn")
    with pytest.raises(SettingsError, match="light_scope"):
        ClassicalSettings(light_scope="sky")
    with pytest.raises(SettingsError, match="sun_el_deg"):
        TemplateSettings(sun_el_deg=0.0)
    with pytest.raises(FrameError, match="empty"):
        detect(np.full((128, 128), 50.0), TemplateSettings(), what="frame x")


def test_setting_overrides_are_checked():
    from crater_synth.navigation.settings import compose_nav

    d = compose_nav(["nav/detector=template", "nav.detector.threshold=0.5"]).detector
    assert isinstance(d, TemplateSettings) and d.method == "template" and d.threshold == 0.5
    d = compose_nav(["nav/detector=template"]).detector
    assert d.method == "template"
    with pytest.raises(ConfigError):  # a detector is chosen as nav/detector=NAME, not by its method key
        compose_nav(["nav.detector.method=template"])
    with pytest.raises(ConfigError, match="nav.detector.light_scope='moon'"):
        compose_nav(["nav.detector.light_scope=moon"])
    with pytest.raises(ConfigError, match="unknown nav/detector 'cnn'"):
        compose_nav(["nav/detector=cnn"])
