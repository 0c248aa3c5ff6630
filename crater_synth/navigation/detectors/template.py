"""Second crater detector: normalised cross-correlation with a Hapke-shaded crater template.

A crater seen at low Sun is a pattern, not an edge: a cast shadow on the Sun-facing inner wall, a lit
opposite wall, flat terrain around. The template is that pattern rendered from an analytic crater (a
parabolic bowl of depth ``depth_d`` x D with a raised rim decaying outside, the shape the tests'
synthetic craters and fresh lunar craters share) under the frame's light direction, at the Sun
elevation ``sun_el_deg``, with the project's Hapke model (``crater_core.hapke.shade_np``, the
lunar parameters of the ``hapke`` settings group) and cast shadows. It is matched over scales by normalised
cross-correlation (NCC: invariant to the frame's brightness and contrast, so one threshold serves every
exposure); a local NCC maximum above ``threshold`` is a crater centred on the maximum, of the
template's radius (no centre shift to fit: the template is centred on its crater).

Speed: each scale runs on the frame decimated by a power of two so that the template's radius stays
between 4.5 and 9 px (the anti-aliased decimated frame comes from the spectrum the light estimate already
computed), and the correlation is OpenCV's (:func:`ncc`).

No setting of this module was fitted to real pixels: the template is synthetic; the threshold and the
Sun elevation were chosen on validation windows only (docs/navigation/detectors.md).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np

from crater_core.hapke import shade_np
from crater_core.settings_nav import DetectorSettings
from crater_core.typed_config import need
from crater_synth.config import load_settings
from crater_synth.navigation.detectors.registry import CandidateInput, DetectorEntry
from crater_synth.navigation.detectors.scalespace import PAD_PX, filtered, peaks

TEMPLATE_MIN_R_PX = 4.5  # template radius on its decimated grid is in [4.5, 9) px
TEMPLATE_HALF_WIDTH_R = 1.6  # the template covers +-1.6 r: the rim, its outer flank and some flat ground


@dataclass(frozen=True)
class TemplateSettings(DetectorSettings):
    """The template detector's own settings (configs/nav/detector/template.yaml)."""

    NAME: ClassVar[str] = "template"

    threshold: float = 0.35  # NCC of a template candidate
    sun_el_deg: float = 10.0  # Sun elevation the template is shaded at
    depth_d: float = 0.2  # template bowl depth / diameter

    def _check(self) -> None:
        super()._check()
        need(0.0 < self.sun_el_deg < 90.0, "sun_el_deg", self.sun_el_deg, "must be in (0, 90)")


@functools.lru_cache(maxsize=1)
def hapke_params():
    """The project's lunar Hapke parameters (the composed configuration's ``hapke`` group)."""
    return load_settings().hapke


def crater_heights(rho: np.ndarray, depth_d: float) -> np.ndarray:
    """Heights (units of the radius) of the analytic crater at radial distance ``rho`` (units of the radius):
    a parabolic bowl of depth ``depth_d`` x D inside, a rim of 0.04 D decaying as rho^-3 outside."""
    depth, rim = 2.0 * depth_d, 0.08
    return np.where(rho < 1.0, -depth + (depth + rim) * rho**2, rim * np.clip(rho, 1.0, None) ** -3.0)


@functools.lru_cache(maxsize=256)
def crater_template(theta: float, sun_el_deg: float, r_px: float, depth_d: float) -> np.ndarray:
    """Zero-mean, unit-norm template (odd square) of a crater of radius ``r_px`` lit by light travelling
    along azimuth ``theta`` (radians, from +u towards +v) at Sun elevation ``sun_el_deg``: Hapke I/F,
    zero in cast shadow."""
    n = int(math.ceil(TEMPLATE_HALF_WIDTH_R * r_px))
    vv, uu = np.mgrid[-n : n + 1, -n : n + 1].astype(float)
    # Height in pixels (heights are in units of the radius).
    img = shade_heights(crater_heights(np.hypot(uu, vv) / r_px, depth_d) * r_px, theta, sun_el_deg)
    img -= img.mean()
    norm = np.linalg.norm(img)
    return img / norm if norm > 0 else img


def shade_heights(z: np.ndarray, theta: float, sun_el_deg: float) -> np.ndarray:
    """Nadir image (Hapke I/F, zero in cast shadow) of a height field ``z`` (in pixels) lit by light
    travelling along azimuth ``theta`` (radians, from +u towards +v) at Sun elevation ``sun_el_deg``."""
    gv, gu = np.gradient(z)
    normals = np.stack([-gu, -gv, np.ones_like(z)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    el = math.radians(sun_el_deg)
    su, sv = -math.cos(theta), -math.sin(theta)  # towards the Sun: against the light's travel
    to_sun = np.array([su * math.cos(el), sv * math.cos(el), math.sin(el)])
    view = np.broadcast_to(np.array([0.0, 0.0, 1.0]), normals.shape)
    img = shade_np(normals, to_sun, view, hapke_params())
    img[_cast_shadow(z, su, sv, math.tan(el))] = 0.0
    return img


def _cast_shadow(z: np.ndarray, su: float, sv: float, tan_el: float) -> np.ndarray:
    """Pixels of a height field (pixels) whose ray towards the Sun meets higher terrain (a
    march of one-pixel steps over the template; the template is analytic and a few dozen pixels wide,
    so the renderer's horizon maps would be overkill)."""
    from scipy.ndimage import map_coordinates

    h, w = z.shape
    vv, uu = np.mgrid[0:h, 0:w].astype(float)
    shadow = np.zeros(z.shape, bool)
    # No occluder can shade a point from further than the relief / tan(elevation).
    reach = min(max(h, w), int(math.ceil(float(z.max() - z.min()) / max(tan_el, 1e-6))) + 1)
    for t in range(1, reach + 1):
        pu, pv = uu + t * su, vv + t * sv
        zt = map_coordinates(z, [pv, pu], order=1, mode="nearest")
        shadow |= zt - z > t * tan_el
    return shadow


def template_step(r: float) -> int:
    """Power-of-two grid step that puts the template radius in [4.5, 9) px, at most 16."""
    return int(min(16, 2 ** max(0, math.floor(math.log2(max(r / TEMPLATE_MIN_R_PX, 1.0))))))


def ncc(image: np.ndarray, template: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation of a zero-mean unit-norm odd-square ``template`` at every pixel of
    ``image`` (same shape as ``image``; 0 where the image is flat under the template). The correlation
    reads zeros beyond the image, its mean and energy under the template the image reflected: OpenCV's
    ``filter2D`` (an FFT correlation for a template this size) and box filters, in float64."""
    m = template.shape[0]
    img = np.asarray(image, dtype=np.float64)
    corr = cv2.filter2D(img, -1, np.asarray(template, dtype=np.float64), borderType=cv2.BORDER_CONSTANT)
    mean = cv2.boxFilter(img, -1, (m, m), borderType=cv2.BORDER_REFLECT)
    sq = cv2.boxFilter(img * img, -1, (m, m), borderType=cv2.BORDER_REFLECT)
    energy = np.maximum(m * m * (sq - mean * mean), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(energy > 1e-9 * m * m, corr / np.sqrt(energy), 0.0)
    return out


def template_candidates(frame: CandidateInput, params: TemplateSettings):
    """NCC maxima over scales: (u, v, r, score) in frame pixels (``frame.spectrum``: the padded frame's
    spectrum from :func:`crater_synth.navigation.detectors.scalespace.spectrum`)."""
    spec, shape = frame.spectrum
    frames: dict[int, np.ndarray] = {}
    us, vs, rs, ss = [], [], [], []
    for r in frame.radii:
        step = template_step(r)
        if step not in frames:
            # Anti-aliasing Gaussian of half a decimated pixel before decimation.
            frames[step] = filtered(spec, shape, 0.5 * step if step > 1 else 0.0, step)
        t = crater_template(round(float(frame.light), 4), float(params.sun_el_deg), round(r / step, 3), params.depth_d)
        resp = ncc(frames[step], t)
        i, j, c = peaks(resp, params.threshold)
        us.append(j * step - PAD_PX + 0.5)
        vs.append(i * step - PAD_PX + 0.5)
        rs.append(np.full(c.size, r))
        ss.append(c)
    return tuple(np.concatenate(x) for x in (us, vs, rs, ss))


DETECTOR = DetectorEntry(
    "template",
    TemplateSettings,
    template_candidates,
    "normalised cross-correlation with a Hapke-shaded crater template (crater_synth.navigation.detectors.template)",
)
