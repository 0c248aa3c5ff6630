"""The five-parameter simplified Hapke model: the one source of truth for the reflectance formula.

The formula is written once, against a tiny "ops" backend, so that the same code
- evaluates with numpy (the test oracle and the fast renderer's per-pixel shading), and
- builds a Cycles shader-node graph (``blender_gen.material``) whose math nodes are the same formula.

Model (Hapke 1981, JGR 86:3039; roughness correction Hapke 1984, Icarus 59:41; see docs/hapke.md):

    r(i, e, g) = w/(4 pi) * mu0e/(mu0e + mue) * [(1 + B(g)) p(g) + H(mu0e) H(mue) - 1] * S(i, e, g, theta_bar)

    B(g) = B0 / (1 + tan(g/2)/h)                     shadow-hiding opposition surge
    p(g) = (1 - xi^2) / (1 + 2 xi cos g + xi^2)^1.5   single-lobe Henyey-Greenstein, xi < 0 backscatters
    H(x) = (1 + 2x) / (1 + 2 sqrt(1 - w) x)           Hapke 1981 approximation of Chandrasekhar's H

The radiance factor is I/F = pi * r. Cycles renders a Lambertian BSDF of albedo c under a sun lamp
of strength S as c * S * mu0 / pi (measured, docs/renderer.md), so with S = pi
(``blender_gen.sun.SUN_STRENGTH``) it returns c * mu0, and weighting a Diffuse BSDF by
``pi * r / mu0`` makes Cycles output I/F while supplying the cast shadows itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

_EPS = 1e-6


@dataclass(frozen=True)
class HapkeParams:
    """Five-parameter simplified Hapke model (angles in degrees)."""

    w: float  # single-scattering albedo
    xi: float  # Henyey-Greenstein asymmetry (xi < 0: backscattering)
    b0: float  # opposition surge amplitude B0
    h: float  # opposition surge angular width h
    theta_bar_deg: float  # macroscopic roughness (mean slope angle)

    def __post_init__(self):
        checks = {
            "w": 0.0 < self.w < 1.0,
            "xi": -1.0 < self.xi < 1.0,
            "b0": 0.0 <= self.b0 <= 5.0,
            "h": self.h > 0.0,
            "theta_bar_deg": 0.0 <= self.theta_bar_deg < 60.0,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(
                "Hapke parameter(s) out of physical range: " + ", ".join(f"{k}={getattr(self, k)}" for k in bad)
            )

    @classmethod
    def from_mapping(cls, m) -> "HapkeParams":
        return cls(
            w=float(m["w"]),
            xi=float(m["xi"]),
            b0=float(m["b0"]),
            h=float(m["h"]),
            theta_bar_deg=float(m["theta_bar_deg"]),
        )


class NumpyOps:
    """numpy backend for :func:`radiance_factor`."""

    sqrt = staticmethod(np.sqrt)
    exp = staticmethod(np.exp)
    cos = staticmethod(np.cos)
    sin = staticmethod(np.sin)
    tan = staticmethod(np.tan)
    arccos = staticmethod(np.arccos)
    maximum = staticmethod(np.maximum)
    minimum = staticmethod(np.minimum)

    @staticmethod
    def power(x, p):
        return np.power(x, p)

    @staticmethod
    def less_equal(a, b):
        return (np.asarray(a) <= np.asarray(b)).astype(np.float64)

    @staticmethod
    def select(cond01, a, b):
        return np.where(np.asarray(cond01) > 0.5, a, b)


def _clip(ops, x, lo, hi):
    return ops.minimum(ops.maximum(x, lo), hi)


def radiance_factor(mu0, mu, cos_g, params: HapkeParams, ops=NumpyOps):
    """I/F (= pi * r) for incidence cosine ``mu0``, emission cosine ``mu`` and phase-angle cosine.

    Inputs are arrays (numpy backend) or node sockets (shader backend). Points with mu0 <= 0 or
    mu <= 0 get 0 in the numpy backend (Cycles never shades them).
    """
    w, xi, b0, h = params.w, params.xi, params.b0, params.h
    tb = math.radians(params.theta_bar_deg)
    tan_tb = max(math.tan(tb), _EPS)
    chi = 1.0 / math.sqrt(1.0 + math.pi * tan_tb**2)
    gamma = math.sqrt(1.0 - w)

    mu0c = _clip(ops, mu0, _EPS, 1.0)
    muc = _clip(ops, mu, _EPS, 1.0)
    cosg = _clip(ops, cos_g, -1.0, 1.0)
    sin_i = ops.sqrt(ops.maximum(1.0 - mu0c * mu0c, 0.0))
    sin_e = ops.sqrt(ops.maximum(1.0 - muc * muc, 0.0))
    tan_i = ops.maximum(sin_i / mu0c, _EPS)
    tan_e = ops.maximum(sin_e / muc, _EPS)

    # Azimuth psi between the incidence and emission planes.
    cos_psi = _clip(ops, (cosg - mu0c * muc) / ops.maximum(sin_i * sin_e, _EPS), -1.0, 1.0)
    psi = ops.arccos(cos_psi)
    sin2_half_psi = 0.5 * (1.0 - cos_psi)
    f_psi = ops.exp(-2.0 * ops.tan(ops.minimum(0.5 * psi, 1.5707)))

    def e1(tan_x):
        return ops.exp(-2.0 / (math.pi * tan_tb * tan_x))

    def e2(tan_x):
        return ops.exp(-1.0 / (math.pi * tan_tb**2 * tan_x * tan_x))

    e1i, e2i, e1e, e2e = e1(tan_i), e2(tan_i), e1(tan_e), e2(tan_e)
    eta0 = chi * (mu0c + sin_i * tan_tb * e2i / (2.0 - e1i))
    eta = chi * (muc + sin_e * tan_tb * e2e / (2.0 - e1e))
    psi_pi = psi / math.pi

    # Hapke (1984) eqs. 46-51: effective cosines for i <= e and for e < i.
    den_a = 2.0 - e1e - psi_pi * e1i
    mu0e_a = chi * (mu0c + sin_i * tan_tb * (cos_psi * e2e + sin2_half_psi * e2i) / den_a)
    mue_a = chi * (muc + sin_e * tan_tb * (e2e - sin2_half_psi * e2i) / den_a)
    s_a = (mue_a / eta) * (mu0c / eta0) * chi / (1.0 - f_psi + f_psi * chi * (mu0c / eta0))

    den_b = 2.0 - e1i - psi_pi * e1e
    mu0e_b = chi * (mu0c + sin_i * tan_tb * (e2i - sin2_half_psi * e2e) / den_b)
    mue_b = chi * (muc + sin_e * tan_tb * (cos_psi * e2i + sin2_half_psi * e2e) / den_b)
    s_b = (mue_b / eta) * (mu0c / eta0) * chi / (1.0 - f_psi + f_psi * chi * (muc / eta))

    i_le_e = ops.less_equal(sin_i * muc, sin_e * mu0c)  # tan i <= tan e  <=>  i <= e
    mu0e = ops.select(i_le_e, mu0e_a, mu0e_b)
    mue = ops.select(i_le_e, mue_a, mue_b)
    shadowing = ops.select(i_le_e, s_a, s_b)

    half_g = 0.5 * ops.arccos(cosg)
    opposition = b0 / (1.0 + ops.tan(ops.minimum(half_g, 1.5707)) / h)
    phase = (1.0 - xi * xi) / ops.power(1.0 + 2.0 * xi * cosg + xi * xi, 1.5)
    h_mu0 = (1.0 + 2.0 * mu0e) / (1.0 + 2.0 * gamma * mu0e)
    h_mu = (1.0 + 2.0 * mue) / (1.0 + 2.0 * gamma * mue)

    r = (w / (4.0 * math.pi)) * mu0e / (mu0e + mue) * ((1.0 + opposition) * phase + h_mu0 * h_mu - 1.0) * shadowing
    return math.pi * r


def radiance_factor_np(mu0, mu, cos_g, params: HapkeParams) -> np.ndarray:
    """numpy I/F with zero where the surface is unlit or seen from behind."""
    mu0 = np.asarray(mu0, dtype=np.float64)
    mu = np.asarray(mu, dtype=np.float64)
    out = radiance_factor(mu0, mu, np.asarray(cos_g, dtype=np.float64), params, NumpyOps)
    return np.where((mu0 > 0.0) & (mu > 0.0), out, 0.0)


def shade_np(normals: np.ndarray, to_sun: np.ndarray, to_viewer: np.ndarray, params: HapkeParams) -> np.ndarray:
    """I/F for unit normals (..., 3), a unit sun direction (3,) and unit view directions (..., 3)."""
    mu0 = normals @ to_sun
    mu = np.einsum("...k,...k->...", normals, to_viewer)
    cos_g = to_viewer @ to_sun
    return radiance_factor_np(mu0, mu, cos_g, params)
