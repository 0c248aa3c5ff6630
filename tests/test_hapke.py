"""The numpy Hapke oracle: limits, symmetries and a hand-computed value."""

import math

import numpy as np
import pytest

from crater_core.hapke import HapkeParams, radiance_factor_np


def hand_hapke_smooth(mu0, mu, g, w, xi, b0, h):
    """Hapke 1981 without roughness, written out independently."""
    gamma = math.sqrt(1 - w)
    H = lambda x: (1 + 2 * x) / (1 + 2 * gamma * x)  # noqa: E731
    B = b0 / (1 + math.tan(g / 2) / h)
    P = (1 - xi**2) / (1 + 2 * xi * math.cos(g) + xi**2) ** 1.5
    return math.pi * w / (4 * math.pi) * mu0 / (mu0 + mu) * ((1 + B) * P + H(mu0) * H(mu) - 1)


@pytest.mark.parametrize("i, e, g", [(30, 0, 30), (60, 20, 50), (80, 40, 100), (10, 70, 75)])
def test_zero_roughness_matches_hand_formula(i, e, g):
    p = HapkeParams(w=0.32, xi=-0.25, b0=1.0, h=0.06, theta_bar_deg=0.0)
    got = radiance_factor_np(math.cos(math.radians(i)), math.cos(math.radians(e)), math.cos(math.radians(g)), p)
    want = hand_hapke_smooth(
        math.cos(math.radians(i)), math.cos(math.radians(e)), math.radians(g), 0.32, -0.25, 1.0, 0.06
    )
    assert float(got) == pytest.approx(want, rel=1e-4)


def test_reciprocity_with_roughness():
    """r(i, e, g) = r(e, i, g) * (same) -- I/F/mu0 is reciprocal for a symmetric phase function."""
    p = HapkeParams(w=0.32, xi=-0.25, b0=1.0, h=0.06, theta_bar_deg=23.657)
    rng = np.random.default_rng(0)
    i, e = np.radians(rng.uniform(5, 85, 50)), np.radians(rng.uniform(5, 85, 50))
    psi = rng.uniform(0, np.pi, 50)
    cos_g = np.cos(i) * np.cos(e) + np.sin(i) * np.sin(e) * np.cos(psi)
    brdf_ie = radiance_factor_np(np.cos(i), np.cos(e), cos_g, p) / np.cos(i)
    brdf_ei = radiance_factor_np(np.cos(e), np.cos(i), cos_g, p) / np.cos(e)
    np.testing.assert_allclose(brdf_ie, brdf_ei, rtol=2e-3)


def test_grazing_sun_goes_dark_and_unlit_is_zero():
    p = HapkeParams(w=0.32, xi=-0.25, b0=1.0, h=0.06, theta_bar_deg=23.657)
    mu0 = np.cos(np.radians([60.0, 85.0, 89.0, 89.9]))
    vals = radiance_factor_np(mu0, 1.0, mu0, p)
    assert np.all(np.diff(vals) < 0) and vals[-1] < 0.01 * vals[0]
    assert radiance_factor_np(-0.1, 1.0, 0.0, p) == 0.0


def test_roughness_darkens_low_sun():
    smooth = HapkeParams(w=0.32, xi=-0.25, b0=1.0, h=0.06, theta_bar_deg=0.0)
    rough = HapkeParams(w=0.32, xi=-0.25, b0=1.0, h=0.06, theta_bar_deg=23.657)
    mu0 = math.cos(math.radians(88.4))  # the Sun 1.6 deg above a flat horizon
    assert radiance_factor_np(mu0, 1.0, mu0, rough) < radiance_factor_np(mu0, 1.0, mu0, smooth)


@pytest.mark.parametrize("bad", [dict(w=1.2), dict(xi=-1.5), dict(h=0.0), dict(theta_bar_deg=75.0)])
def test_out_of_range_parameters_are_refused(bad):
    args = dict(w=0.32, xi=-0.25, b0=1.0, h=0.06, theta_bar_deg=20.0) | bad
    with pytest.raises(ValueError, match=list(bad)[0]):
        HapkeParams(**args)
