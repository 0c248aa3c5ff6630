"""An independent, scalar transcription of the published Hapke equations: the reference that
``crater_core.hapke`` is checked against (tests/test_hapke_reference.py).

Written from the papers, not from ``crater_core/hapke.py``: plain ``math`` on floats, one function per
equation, the geometry given as (i, e, psi) -- the phase angle is *derived* here (the implementation
goes the other way, from cos g to psi), and the two roughness cases are written out separately.

Sources (equation numbers as printed in the papers; the 1984 numbering is the one the photometry
literature cites for the roughness correction -- the project had no offline copy of the papers, see
docs/hapke.md):
- Hapke, B. (1981) Bidirectional reflectance spectroscopy 1. Theory. JGR 86(B4):3039-3054:
  the bidirectional reflectance of a smooth particulate surface with the shadow-hiding opposition
  surge, and the closed-form approximation of Chandrasekhar's H function.
- Hapke, B. (1984) Bidirectional reflectance spectroscopy 3. Correction for macroscopic roughness.
  Icarus 59:41-59: chi(theta_bar), E1, E2, eta, the effective cosines and the shadowing function S
  for i <= e and for e < i (eqs. 46-51), f(psi).
- Hapke, B. (2002) Bidirectional reflectance spectroscopy 5. Icarus 157:523-534: the combination
  r = K w/(4 pi) mu0e/(mu0e + mue) [p (1 + B_SH) + H(mu0e) H(mue) - 1] S used with roughness (here
  K = 1, no porosity term, no coherent backscatter, the 1981 H function: the five-parameter
  "simplified" model of docs/specification.md).
- Single-lobe Henyey-Greenstein phase function p(g) = (1 - xi^2)/(1 + 2 xi cos g + xi^2)^(3/2)
  (xi < 0: backscattering), as in the lunar fits of Sato et al. 2014 (JGR Planets 119:1775).
"""

from __future__ import annotations

import math


# ---- Hapke 1981 --------------------------------------------------------------------------------
def h_function(x: float, w: float) -> float:
    """Chandrasekhar's H function, Hapke's 1981 approximation: H(x) = (1 + 2x) / (1 + 2 gamma x),
    gamma = sqrt(1 - w)."""
    gamma = math.sqrt(1.0 - w)
    return (1.0 + 2.0 * x) / (1.0 + 2.0 * gamma * x)


def opposition_surge(g: float, b0: float, h: float) -> float:
    """Shadow-hiding opposition surge B(g) = B0 / (1 + tan(g/2) / h)."""
    return b0 / (1.0 + math.tan(g / 2.0) / h)


def henyey_greenstein(g: float, xi: float) -> float:
    """Single-lobe Henyey-Greenstein phase function."""
    return (1.0 - xi * xi) / (1.0 + 2.0 * xi * math.cos(g) + xi * xi) ** 1.5


# ---- Hapke 1984: macroscopic roughness ------------------------------------------------------------
def chi(theta_bar: float) -> float:
    """chi(theta_bar) = 1 / sqrt(1 + pi tan^2 theta_bar)."""
    return 1.0 / math.sqrt(1.0 + math.pi * math.tan(theta_bar) ** 2)


def e1(x: float, theta_bar: float) -> float:
    """E1(x) = exp(-(2/pi) cot(theta_bar) cot(x))."""
    return math.exp(-2.0 / math.pi / math.tan(theta_bar) / math.tan(x))


def e2(x: float, theta_bar: float) -> float:
    """E2(x) = exp(-(1/pi) cot^2(theta_bar) cot^2(x))."""
    return math.exp(-1.0 / math.pi / math.tan(theta_bar) ** 2 / math.tan(x) ** 2)


def eta(x: float, theta_bar: float) -> float:
    """eta(x) = chi [cos x + sin x tan(theta_bar) E2(x) / (2 - E1(x))]: the effective cosine at psi = 0
    of a single direction (mu0e(0) for x = i, mue(0) for x = e)."""
    return chi(theta_bar) * (
        math.cos(x) + math.sin(x) * math.tan(theta_bar) * e2(x, theta_bar) / (2.0 - e1(x, theta_bar))
    )


def f_psi(psi: float) -> float:
    """f(psi) = exp(-2 tan(psi/2)); 0 at psi = pi."""
    return 0.0 if psi >= math.pi else math.exp(-2.0 * math.tan(psi / 2.0))


def roughness_i_le_e(i: float, e: float, psi: float, tb: float) -> tuple[float, float, float]:
    """Case i <= e: (mu0e, mue, S)."""
    c, t = chi(tb), math.tan(tb)
    s2 = math.sin(psi / 2.0) ** 2
    den = 2.0 - e1(e, tb) - (psi / math.pi) * e1(i, tb)
    mu0e = c * (math.cos(i) + math.sin(i) * t * (math.cos(psi) * e2(e, tb) + s2 * e2(i, tb)) / den)
    mue = c * (math.cos(e) + math.sin(e) * t * (e2(e, tb) - s2 * e2(i, tb)) / den)
    f = f_psi(psi)
    s = (mue / eta(e, tb)) * (math.cos(i) / eta(i, tb)) * c / (1.0 - f + f * c * (math.cos(i) / eta(i, tb)))
    return mu0e, mue, s


def roughness_e_lt_i(i: float, e: float, psi: float, tb: float) -> tuple[float, float, float]:
    """Case e < i: (mu0e, mue, S)."""
    c, t = chi(tb), math.tan(tb)
    s2 = math.sin(psi / 2.0) ** 2
    den = 2.0 - e1(i, tb) - (psi / math.pi) * e1(e, tb)
    mu0e = c * (math.cos(i) + math.sin(i) * t * (e2(i, tb) - s2 * e2(e, tb)) / den)
    mue = c * (math.cos(e) + math.sin(e) * t * (math.cos(psi) * e2(i, tb) + s2 * e2(e, tb)) / den)
    f = f_psi(psi)
    s = (mue / eta(e, tb)) * (math.cos(i) / eta(i, tb)) * c / (1.0 - f + f * c * (math.cos(e) / eta(e, tb)))
    return mu0e, mue, s


# ---- geometry and the whole model ----------------------------------------------------------------
def phase_angle(i: float, e: float, psi: float) -> float:
    """Spherical law of cosines: cos g = cos i cos e + sin i sin e cos psi."""
    return math.acos(math.cos(i) * math.cos(e) + math.sin(i) * math.sin(e) * math.cos(psi))


def radiance_factor(
    i_deg: float, e_deg: float, psi_deg: float, w: float, xi: float, b0: float, h: float, theta_bar_deg: float
) -> float:
    """I/F = pi r of the five-parameter model at incidence i, emission e and azimuth psi (degrees)."""
    i, e, psi = math.radians(i_deg), math.radians(e_deg), math.radians(psi_deg)
    g = phase_angle(i, e, psi)
    if theta_bar_deg == 0.0:
        mu0e, mue, s = math.cos(i), math.cos(e), 1.0
    elif i <= e:
        mu0e, mue, s = roughness_i_le_e(i, e, psi, math.radians(theta_bar_deg))
    else:
        mu0e, mue, s = roughness_e_lt_i(i, e, psi, math.radians(theta_bar_deg))
    r = (
        w
        / (4.0 * math.pi)
        * mu0e
        / (mu0e + mue)
        * (
            (1.0 + opposition_surge(g, b0, h)) * henyey_greenstein(g, xi)
            + h_function(mu0e, w) * h_function(mue, w)
            - 1.0
        )
        * s
    )
    return math.pi * r
