"""crater_synth.detail: seeded, switchable sub-DEM roughness and craters, only below DEM resolution."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crater_synth.detail import (
    EQ_COEF, PIKE_DEPTH_COEF, DetailConfigError, DetailSettings, crater_population, crater_profile, lowpass,
    stamp_craters, synthesize_detail,
)

SHAPE, SPACING, PIXEL = (128, 128), 200.0, 1600.0


def make(**kw):
    return synthesize_detail(SHAPE, SPACING, PIXEL, DetailSettings(**kw), key="shackleton")


def test_deterministic_for_a_seed():
    a, sa = make(seed=7)
    b, sb = make(seed=7)
    np.testing.assert_array_equal(a, b)
    assert sa["n_craters"] == sb["n_craters"] > 0
    c, _ = make(seed=8)
    assert np.abs(a - c).max() > 1.0
    d, _ = synthesize_detail(SHAPE, SPACING, PIXEL, DetailSettings(seed=7), key="shoemaker")
    assert np.abs(a - d).max() > 1.0


def test_disabled_is_zero():
    f, stats = make(enabled=False)
    assert not f.any() and stats["enabled"] is False and stats["n_craters"] == 0


def test_no_detail_when_grid_is_not_finer_than_dem():
    f, stats = synthesize_detail(SHAPE, 1600.0, 1600.0, DetailSettings(), key="x")
    assert not f.any() and stats["active"] is False


def test_only_below_dem_resolution():
    from scipy.ndimage import gaussian_filter

    f, _ = make(seed=3)
    assert f.std() > 1.0
    # Ideal low-pass at the DEM Nyquist (wavelengths >= 2 p): nothing left.
    assert np.abs(lowpass(f, SPACING, PIXEL)).max() < 1e-9 * f.std()
    # A Gaussian blur of one DEM pixel (response 0.7 % at the DEM Nyquist) leaves almost nothing.
    assert gaussian_filter(f, PIXEL / SPACING, mode="wrap").std() < 0.02 * f.std()


def test_roughness_rms_slope_matches_setting():
    f, stats = make(seed=1, crater_density_scale=0.0, rms_slope_deg=4.0)
    assert stats["n_craters"] == 0
    gx = (np.roll(f, -1, axis=1) - f) / SPACING
    gy = (np.roll(f, -1, axis=0) - f) / SPACING
    assert math.degrees(math.atan(np.sqrt(np.mean(gx**2 + gy**2)))) == pytest.approx(4.0, rel=1e-6)


def test_crater_counts_follow_equilibrium_sfd():
    rng = np.random.default_rng(0)
    area, d_min, d_max = 1e10, 400.0, 3200.0  # 10,000 km^2
    pop = crater_population(area, d_min, d_max, 1.0, 0.05, rng)
    expected = area * EQ_COEF * (d_min**-2 - d_max**-2)
    assert abs(len(pop["diameter"]) - expected) < 5 * math.sqrt(expected)
    assert pop["diameter"].min() >= d_min and pop["diameter"].max() <= d_max
    # Cumulative slope -2: N(>=2 d_min) / N(>=d_min) ~ (1/4 - 1/64) / (1 - 1/64).
    frac = np.mean(pop["diameter"] >= 2 * d_min)
    assert frac == pytest.approx((0.25 - 1 / 64) / (1 - 1 / 64), abs=0.03)
    ratio = pop["depth"] / pop["diameter"]
    assert ratio.max() <= PIKE_DEPTH_COEF * 1.01 * (3.2**0.01) and ratio.min() >= 0.05 * 0.99


def test_fresh_crater_shape():
    d, depth, rim = 2000.0, 0.196 * 2000.0, 72.0
    s = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    z = crater_profile(s, depth, rim)
    assert z[0] == pytest.approx(rim - depth) and z[1] == pytest.approx(rim)
    assert 0.0 < z[2] < rim and z[3] == pytest.approx(0.0) and z[4] == 0.0
    field = stamp_craters((101, 101), 50.0, np.array([[50.0, 50.0]]), np.array([d]), np.array([depth]),
                          np.array([rim]))
    assert field.max() - field.min() == pytest.approx(depth, rel=0.02)  # rim crest to floor


@pytest.mark.parametrize("key, value", [("hurst", 1.5), ("rms_slope_deg", -1.0), ("min_depth_diameter", 0.5),
                                        ("min_crater_diameter_m", 0.0)])
def test_bad_settings_name_the_key(key, value):
    with pytest.raises(DetailConfigError, match=f"terrain.detail.{key}"):
        DetailSettings.from_config({key: value})
    with pytest.raises(DetailConfigError, match=r"terrain\.detail\.hurts: unknown key"):
        DetailSettings.from_config({"hurts": 0.5})
