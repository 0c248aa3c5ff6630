"""``crater_core.hapke`` against the published equations, roughness included.

The reference (tests/helpers/hapke_reference.py) is a separate scalar transcription of Hapke 1981/1984/2002,
not the implementation run twice: it takes (i, e, psi) and derives g, selects the roughness case with
an ``if``, and uses ``math`` on floats. The implementation takes (mu0, mu, cos g), derives psi, and
evaluates both branches vectorised. They must agree to 1e-9 relative at every geometry below.

The second test shows the check has teeth: typos planted in the implementation's source -- each one
mirrored in both roughness branches, so reciprocity and "rough is darker than smooth" still hold --
make it fail.
"""

from __future__ import annotations

import inspect
import math
import sys
import types

import numpy as np
import pytest

from crater_core import hapke

from helpers import hapke_reference as ref

PARAMS = [  # (w, xi, b0, h, theta_bar_deg)
    (0.32, -0.25, 1.0, 0.06, 23.657),  # configs/hapke/lunar.yaml
    (0.32, -0.25, 1.0, 0.06, 10.0),
    (0.60, 0.30, 0.5, 0.20, 35.0),  # forward-scattering, wide surge, very rough
    (0.32, -0.25, 1.0, 0.06, 0.0),  # smooth: no roughness correction at all
]
# (i, e, psi) in degrees: both cases (i <= e, e < i), the paper's low Sun (i = 88.4-89.84), near-nadir
# and oblique views, psi from 0 (sun behind the viewer) to 180.
GEOMETRIES = [
    (30.0, 60.0, 40.0),
    (60.0, 30.0, 40.0),
    (45.0, 45.0, 90.0),
    (10.0, 70.0, 150.0),
    (70.0, 10.0, 150.0),
    (88.4, 2.0, 90.0),
    (88.4, 36.0, 0.0),
    (88.4, 36.0, 180.0),
    (89.84, 20.0, 120.0),
    (75.0, 80.0, 10.0),
    (80.0, 75.0, 170.0),
    (20.0, 20.0, 0.5),
    (5.0, 85.0, 60.0),
    (85.0, 5.0, 60.0),
]


def implementation_values(radiance_factor_np, params_cls, p) -> np.ndarray:
    w, xi, b0, h, tb = p
    i, e, psi = (np.radians([g[k] for g in GEOMETRIES]) for k in range(3))
    cos_g = np.cos(i) * np.cos(e) + np.sin(i) * np.sin(e) * np.cos(psi)
    return radiance_factor_np(np.cos(i), np.cos(e), cos_g, params_cls(w=w, xi=xi, b0=b0, h=h, theta_bar_deg=tb))


def reference_values(p) -> np.ndarray:
    return np.array([ref.radiance_factor(i, e, psi, *p) for i, e, psi in GEOMETRIES])


@pytest.mark.parametrize("p", PARAMS, ids=lambda p: f"w{p[0]}-xi{p[1]}-tb{p[4]}")
def test_implementation_matches_the_published_equations(p):
    want = reference_values(p)
    got = implementation_values(hapke.radiance_factor_np, hapke.HapkeParams, p)
    assert np.all(want > 0) and np.all(np.isfinite(want))
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=0)


def test_reference_limits():
    """Sanity of the reference itself: the roughness correction vanishes continuously as theta_bar -> 0,
    in both cases; a grazing Sun goes dark."""
    for i, e, psi in GEOMETRIES:
        smooth = ref.radiance_factor(i, e, psi, *PARAMS[3])
        assert ref.radiance_factor(i, e, psi, *PARAMS[3][:4], 0.01) == pytest.approx(smooth, rel=2e-3)
    tb = math.radians(0.01)
    for case in (ref.roughness_i_le_e, ref.roughness_e_lt_i):
        mu0e, mue, s = case(math.radians(50.0), math.radians(50.0), math.radians(70.0), tb)
        assert (mu0e, mue, s) == pytest.approx((math.cos(math.radians(50.0)),) * 2 + (1.0,), rel=1e-3)
    low = [ref.radiance_factor(x, 10.0, 90.0, *PARAMS[0]) for x in (60.0, 85.0, 89.0, 89.9)]
    assert all(a > b for a, b in zip(low, low[1:])) and low[-1] < 0.02 * low[0]


# Each mutant: (description, [(original, replacement), ...]); the originals must each occur exactly once.
MUTANTS = {
    "sign of the psi/pi term, both denominators": [
        ("2.0 - e1e - psi_pi * e1i", "2.0 - e1e + psi_pi * e1i"),
        ("2.0 - e1i - psi_pi * e1e", "2.0 - e1i + psi_pi * e1e"),
    ],
    "sign of the sin^2(psi/2) term, both cos-psi numerators": [
        ("cos_psi * e2e + sin2_half_psi * e2i", "cos_psi * e2e - sin2_half_psi * e2i"),
        ("cos_psi * e2i + sin2_half_psi * e2e", "cos_psi * e2i - sin2_half_psi * e2e"),
    ],
    "E2 instead of E1 in both eta denominators": [
        ("e2i / (2.0 - e1i))", "e2i / (2.0 - e2i))"),
        ("e2e / (2.0 - e1e))", "e2e / (2.0 - e2e))"),
    ],
    "f(psi) = exp(-tan(psi/2)) (factor 2 lost; shared by both branches)": [
        ("f_psi = ops.exp(-2.0 * ops.tan(", "f_psi = ops.exp(-1.0 * ops.tan("),
    ],
    "chi with tan instead of tan^2": [
        ("chi = 1.0 / math.sqrt(1.0 + math.pi * tan_tb**2)", "chi = 1.0 / math.sqrt(1.0 + math.pi * tan_tb)"),
    ],
}


def _mutant_module(edits):
    src = inspect.getsource(hapke)
    for old, new in edits:
        assert src.count(old) == 1, f"mutation site {old!r} not found once in crater_core/hapke.py: update MUTANTS"
        src = src.replace(old, new)
    name = "crater_core._hapke_mutant"
    mod = types.ModuleType(name)
    sys.modules[name] = mod  # dataclasses look their module up while the class is created
    try:
        exec(compile(src, name, "exec"), mod.__dict__)
    finally:
        del sys.modules[name]
    return mod


@pytest.mark.parametrize("what", list(MUTANTS))
def test_a_broken_roughness_term_fails_the_check(what):
    mutant = _mutant_module(MUTANTS[what])
    p = PARAMS[0]
    got = implementation_values(mutant.radiance_factor_np, mutant.HapkeParams, p)
    rel = np.abs(got / reference_values(p) - 1.0)
    assert rel.max() > 1e-3, f"planted typo ({what}) went unnoticed: max relative error {rel.max():.2e}"
