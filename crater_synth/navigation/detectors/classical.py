"""Classical crater detector: shadow / lit-limb pairs as a scale-space matched filter.

At low Sun a crater is a dark shadow on the Sun-facing inner wall followed, along the light's
travel direction d, by the bright limb of the opposite wall. The intensity therefore *rises* along d
across the crater, at the crater's own scale; a hill does the opposite (bright slope, then its shadow).
The detector is the scale-normalised first derivative of the Gaussian-smoothed image along d,

    R_sigma(u, v) = sigma * d . grad (G_sigma * I)(u, v),

a smooth shadow-minus-limb filter. Craters are local maxima of R over (u, v, sigma) above
``threshold``; a maximum at scale sigma stands for a crater of radius sigma / ``sigma_per_radius``
whose centre lies ``centre_shift`` x r from the maximum along d (the shadow is wider than the lit limb
at low Sun, so the maximum is offset). The image is normalised to zero mean and unit standard
deviation first, so the threshold does not depend on exposure.

d is not given by a mosaic window: it is estimated per frame (:func:`light_azimuth`: the azimuth whose
derivative at the mid scales has the strongest positive tail, or the axis of the frame's gradient
structure tensor with the tail picking the sign), or pooled over frames known to share one Sun
(:func:`pooled_light_azimuth`). A caller that knows the Sun (a lander knows its attitude and the
ephemeris) passes it instead.

The other detectors (:mod:`.template`: Hapke-shaded template, normalised cross-correlation; :mod:`.learned`:
a network) share :func:`detect`: the light estimate, the rim fit and the suppression; ``params.method``
picks one from the registry (:mod:`.registry`). The settings of each (configs/nav/detector/) were chosen
on validation windows only (docs/navigation/overview.md).
The filtering is done in the Fourier domain (:mod:`.scalespace`): one forward FFT, one inverse FFT per
scale.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np

from crater_core.settings_nav import DetectorSettings, LightSettings
from crater_synth.errors import UserError
from crater_synth.navigation.detectors.registry import CandidateInput, DetectorEntry, detector
from crater_synth.navigation.detectors.scalespace import PAD_PX, decimation, filtered, peaks, spectrum
from crater_synth.navigation.georef import check_frame
from crater_synth.terrain.catalogue import robust_circle

__all__ = ["PAD_PX", "decimation", "filtered", "peaks", "spectrum"]  # re-exported for callers and tests


@dataclass(frozen=True)
class ClassicalSettings(DetectorSettings):
    """The classical detector's own settings (module docstring; values chosen on validation windows,
    docs/navigation/overview.md; configs/nav/detector/classical.yaml)."""

    NAME: ClassVar[str] = "classical"

    sigma_per_radius: float = 0.45
    centre_shift: float = 0.2  # fraction of r, along the light direction
    threshold: float = 0.5


class DetectorSettingsError(UserError):
    """A detector cannot run on this input with these settings."""


@dataclass(frozen=True)
class Detection:
    """One detected crater in frame pixels (u right, v down, origin top-left corner)."""

    u: float
    v: float
    r: float  # rim radius, px
    score: float

    def as_dict(self) -> dict:
        return {k: round(float(v), 3) for k, v in asdict(self).items()}


def _derivative(spec, shape, sigma: float, du: float, dv: float, step: int = 1) -> np.ndarray:
    """sigma x d . grad (G_sigma * I) for unit d = (du, dv) on the padded grid decimated by ``step``."""
    return filtered(spec, shape, sigma, step, du, dv)


def light_axis(grads) -> float:
    """Axis of the light (radians modulo pi) from the frame's gradient structure tensor.

    Shading at low Sun responds to the terrain slope along the Sun's azimuth only, so for terrain
    without a preferred direction the image gradient energy is largest along the light's axis
    (|grad I|^2 spectrum ~ cos^2 of the angle to the light): the principal axis of the tensor
    sum(grad I grad I^T) over the whole frame, pooled over the scales, is the light's axis. A whole-frame
    statistic, so one crater field's geometry cannot pull it the way the strongest few responses can.
    """
    juu = jvv = juv = 0.0
    for gu, gv in grads:
        # Each scale normalised by its total energy, so no scale dominates the pooled estimate.
        e = float(np.mean(gu * gu + gv * gv)) or 1.0
        juu += float(np.mean(gu * gu)) / e
        jvv += float(np.mean(gv * gv)) / e
        juv += float(np.mean(gu * gv)) / e
    return 0.5 * math.atan2(2.0 * juv, juu - jvv)


def azimuth_grads(spec, shape, params: LightSettings):
    """Gaussian-derivative images (d/du, d/dv) at the ``azimuth_sigmas_px`` scales."""
    grads = []
    for s in params.azimuth_sigmas_px:
        step = decimation(s)
        grads.append((_derivative(spec, shape, s, 1.0, 0.0, step), _derivative(spec, shape, s, 0.0, 1.0, step)))
    return grads


def _tail_scores(grads, candidates, params: LightSettings) -> np.ndarray:
    """Per candidate direction: summed over scales, the mean of the top ``azimuth_tail`` share of the
    directional derivative."""
    out = np.zeros(len(candidates))
    for n, theta in enumerate(candidates):
        c, s = math.cos(theta), math.sin(theta)
        for gu, gv in grads:
            r = (c * gu + s * gv).ravel()
            k = max(1, int(params.azimuth_tail * r.size))
            out[n] += float(np.partition(r, r.size - k)[-k:].mean())
    return out


def _candidates(grads, params: LightSettings) -> np.ndarray:
    if params.light_method == "tensor":
        axis = light_axis(grads)
        return np.array([axis, axis + math.pi])
    if params.light_method == "tail":
        return np.arange(params.n_azimuths) * 2.0 * np.pi / params.n_azimuths
    raise ValueError(f"light_method {params.light_method!r}: expected 'tensor' or 'tail'")


def _light_from(candidates, scores, params: LightSettings) -> float:
    # The strongest rise is at the Sun-side rim: from the shadow cast by the rim crest up to the lit
    # terrain beyond it, i.e. towards the Sun (validation windows: the opposite sign halves the fix rate).
    best = float(candidates[int(np.argmax(scores))])
    return (best + (math.pi if params.tail_points_to_sun else 0.0)) % (2.0 * math.pi)


def light_azimuth(spec, shape, params: LightSettings, prior: tuple[float, float] | None = None) -> float:
    """Estimated light travel direction (radians, from +u towards +v) of a frame (module docstring).

    ``params.light_method`` "tensor": the axis from :func:`light_axis`, its sign (of the two opposite
    directions) by the derivative tail; "tail": the tail over ``n_azimuths`` directions alone.
    ``prior`` (direction, half-width), radians: the estimate is searched only among light directions
    within the half-width of the prior direction (the tail scored on a 5-degree grid there)."""
    grads = azimuth_grads(spec, shape, params)
    if prior is None:
        cand = _candidates(grads, params)
        return _light_from(cand, _tail_scores(grads, cand, params), params)
    centre, half = prior
    n = max(1, int(round(half / math.radians(5.0))))
    light = centre + np.linspace(-half, half, 2 * n + 1)
    # The tail scores the direction its rise points to; with tail_points_to_sun the light is reversed.
    cand = light + (math.pi if params.tail_points_to_sun else 0.0)
    return float(light[int(np.argmax(_tail_scores(grads, cand, params)))] % (2.0 * math.pi))


def pooled_light_azimuth(images, params: LightSettings, rotations=None, n_azimuths: int | None = None) -> float:
    """One light direction for frames known to share one Sun (e.g. the windows of one mosaic quadrant,
    imaged under one illumination): the structure tensor and the tail scores pooled over the frames.

    ``rotations`` (radians, one per image): the frames share the light in a frame rotated by that angle
    from each image's own (e.g. local north's image angle: one *local* azimuth for all); the candidate
    directions are scored in each image turned by its rotation and the result is in the common frame (tail
    method only, on ``n_azimuths`` directions, default ``params.n_azimuths``)."""
    grads_all = []
    for img in images:
        a = check_frame(img, "frame")
        spec, shape = spectrum((a - a.mean()) / a.std())
        grads_all.append(azimuth_grads(spec, shape, params))
    if rotations is None:
        cand = _candidates([g for grads in grads_all for g in grads], params)
        scores = sum(_tail_scores(grads, cand, params) for grads in grads_all)
        return _light_from(cand, scores, params)
    if params.light_method != "tail":
        raise DetectorSettingsError("a light pooled in a rotating frame needs nav.detector.light_method='tail'")
    n = n_azimuths or params.n_azimuths
    cand = np.arange(n) * 2.0 * np.pi / n
    scores = sum(_tail_scores(grads, cand + rot, params) for grads, rot in zip(grads_all, rotations, strict=True))
    return _light_from(cand, scores, params)


def suppress(u, v, r, score, centre_r: float, radius_ratio: float) -> np.ndarray:
    """Indices kept by greedy non-maximum suppression (best score first): a detection is dropped when a
    kept one lies within ``centre_r`` x the larger radius and their radii differ by less than
    ``radius_ratio``."""
    n = len(u)
    if n == 0:
        return np.zeros(0, int)
    order = np.argsort(-score)
    u, v, r = u[order], v[order], r[order]
    big = np.maximum(r[:, None], r[None, :])
    conflict = (np.hypot(u[:, None] - u[None, :], v[:, None] - v[None, :]) < centre_r * big) & (
        big / np.minimum(r[:, None], r[None, :]) < radius_ratio
    )
    dropped = np.zeros(n, bool)
    keep = []
    for i in range(n):
        if not dropped[i]:
            keep.append(i)
            dropped |= conflict[i]
    return order[np.array(keep)]


def new_detections(found, known, centre_r: float, radius_ratio: float) -> list:
    """The detections of ``found`` that no detection of ``known`` overlaps, as :func:`suppress` counts overlap
    (centres within ``centre_r`` x the larger radius, radii within ``radius_ratio``): another detector's craters
    that these detections do not already hold."""
    if not found or not known:
        return list(found)
    a = np.array([[d.u, d.v, d.r] for d in found], float)
    b = np.array([[d.u, d.v, d.r] for d in known], float)
    big = np.maximum(a[:, None, 2], b[None, :, 2])
    near = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1]) < centre_r * big
    alike = big / np.minimum(a[:, None, 2], b[None, :, 2]) < radius_ratio
    return [d for d, hit in zip(found, (near & alike).any(axis=1)) if not hit]


def with_new(known, found, params) -> list:
    """``known`` followed by the detections of ``found`` it lacks (:func:`new_detections` with the suppression
    settings of ``params``, the detector that found them; None: ``found`` is empty)."""
    if not found:
        return list(known)
    return [*known, *new_detections(found, known, params.nms_centre_r, params.nms_radius_ratio)]


def scale_radii(params: DetectorSettings, shape) -> np.ndarray:
    """Crater radii (px) searched: ``min_radius_px`` up by ``scale_ratio``, at most half the frame."""
    n_scales = int(math.floor(math.log(params.max_radius_px / params.min_radius_px) / math.log(params.scale_ratio))) + 1
    radii = params.min_radius_px * params.scale_ratio ** np.arange(n_scales)
    return radii[radii <= 0.5 * min(shape)]


def filter_candidates(frame: CandidateInput, params: ClassicalSettings):
    """Maxima of the shadow-to-limb derivative filter over scales: (u, v, r, score) in frame pixels."""
    spec, shape = frame.spectrum
    du, dv = math.cos(frame.light), math.sin(frame.light)
    us, vs, rs, ss = [], [], [], []
    for r in frame.radii:
        sigma = params.sigma_per_radius * r
        step = decimation(sigma)
        resp = _derivative(spec, shape, sigma, du, dv, step)
        i, j, c = peaks(resp, params.threshold)
        # Decimated grid sample k sits at padded pixel k * step (pixel corner convention: + 0.5).
        us.append(j * step - PAD_PX + 0.5)
        vs.append(i * step - PAD_PX + 0.5)
        rs.append(np.full(c.size, r))
        ss.append(c)
    u, v, r, score = (np.concatenate(x) for x in (us, vs, rs, ss))
    return u - params.centre_shift * r * du, v - params.centre_shift * r * dv, r, score


DETECTOR = DetectorEntry(
    "classical",
    ClassicalSettings,
    filter_candidates,
    "shadow/lit-limb scale-space matched filter (crater_synth.navigation.detectors.classical)",
)


def detect(
    image: np.ndarray,
    params: DetectorSettings = ClassicalSettings(),
    light_dir: float | None = None,
    what: str = "frame",
    light_prior: tuple[float, float] | None = None,
):
    """Craters in ``image`` (2-D): (list of :class:`Detection`, light azimuth used in radians).

    The light direction: ``light_dir`` when given, else estimated on the frame (within ``light_prior``
    = (direction, half-width) radians when given, :func:`light_azimuth`).

    ``params.method`` names the detector (:mod:`.registry`) whose candidates function finds candidate
    craters; every detector shares the light estimate, the border rule, the rim fit and the suppression
    of overlapping and concentric detections."""
    entry = detector(params.method)
    if entry.candidates is None:  # refused before any work on the frame
        raise DetectorSettingsError(
            f"{what}: nav.detector.method={params.method!r} searches for map landmarks under a position prior; "
            "run it through nav-eval or navigate, not as a detector"
        )
    a = check_frame(image, what)
    a = (a - a.mean()) / a.std()
    h, w = a.shape
    radii = scale_radii(params, a.shape)
    # The Fourier spectrum serves the filter methods and the light estimate; a network needs neither.
    spec, shape = spectrum(a) if entry.spectrum else (None, None)
    if light_dir is not None:
        theta = float(light_dir)
    elif not entry.spectrum and not params.refine:
        theta = math.nan  # the detector needs no light direction, and without the rim fit nothing uses it
    else:
        if spec is None:
            spec, shape = spectrum(a)
        theta = light_azimuth(spec, shape, params, light_prior)
    frame = CandidateInput(a, None if spec is None else (spec, shape), radii, theta)
    u, v, r, score = entry.candidates(frame, params)
    b = params.border_r * r
    inside = (u >= b) & (u <= w - b) & (v >= b) & (v <= h - b)
    u, v, r, score = u[inside], v[inside], r[inside], score[inside]
    quality = np.ones_like(score)
    if params.refine:
        top = np.argsort(-score)[: params.max_candidates]
        u, v, r, score = u[top], v[top], r[top], score[top]
        u, v, r, ok, quality = refine_rims(a, u, v, r, theta, params.rim_min_inliers, params.rim_ransac)
        u, v, r, score, quality = u[ok], v[ok], r[ok], score[ok], quality[ok]
    keep = suppress(u, v, r, score, params.nms_centre_r, params.nms_radius_ratio)
    if params.concentric_r > 0:
        u, v, r, score, quality = u[keep], v[keep], r[keep], score[keep], quality[keep]
        # Among concentric detections (one crater seen at several scales) keep the best rim fit: the
        # share of edge points on the circle, the filter score breaking ties.
        rank = score if params.concentric_rank == "score" else quality + 1e-3 * score / (1.0 + np.abs(score).max())
        keep = suppress(u, v, r, rank, params.concentric_r, math.inf)
    return [Detection(float(u[k]), float(v[k]), float(r[k]), float(score[k])) for k in keep], theta


RIM_AZIMUTHS = 36
RIM_RADII = np.linspace(0.5, 1.6, 45)  # radial search window, fractions of the filter's radius
RIM_MIN_SUNWARD = 0.4  # |cos(azimuth - light)| below this: the rim runs along the light, no edge to see


def refine_rims(a: np.ndarray, u, v, r, theta: float, min_inliers: float, ransac: bool = False):
    """Rim circles fitted to the shadow and lit-limb edges around each filter maximum.

    Along a ray from the centre towards the Sun, the rim is where the shadow ends and the lit outer
    flank begins (the strongest outward *rise* of intensity); along a ray away from the Sun it is where
    the bright limb ends (the strongest outward *fall*). Rays across the light carry no such edge and are
    skipped. A robust circle through these edge points (``crater_synth.terrain.catalogue.robust_circle``, the
    same fit the DEM rims use; with ``ransac`` from a RANSAC start too) gives the centre and radius.
    Returns (u, v, r, ok, quality): ``ok`` False where fewer than ``min_inliers`` of the edge points lie
    on one circle or the circle is implausible; ``quality`` the share of edge points on the circle.
    """
    from scipy.ndimage import gaussian_filter, map_coordinates

    n = len(u)
    if n == 0:
        return u, v, r, np.zeros(0, bool), np.zeros(0)
    sm = gaussian_filter(a, 1.0)
    alpha = np.arange(RIM_AZIMUTHS) * 2.0 * np.pi / RIM_AZIMUTHS
    c = np.cos(alpha - theta)  # > 0: ray along the light's travel (away from the Sun)
    use = np.abs(c) >= RIM_MIN_SUNWARD
    alpha, c = alpha[use], c[use]
    rho = r[:, None, None] * RIM_RADII[None, None, :]
    pu = u[:, None, None] + rho * np.cos(alpha)[None, :, None]
    pv = v[:, None, None] + rho * np.sin(alpha)[None, :, None]
    prof = map_coordinates(sm, [pv.ravel() - 0.5, pu.ravel() - 0.5], order=1, mode="nearest").reshape(pu.shape)
    slope = np.diff(prof, axis=2) * -np.sign(c)[None, :, None]  # towards the Sun: rise; away: fall
    k = slope.argmax(axis=2)
    mid = 0.5 * (RIM_RADII[k] + RIM_RADII[k + 1]) * r[:, None]
    ex = mid * np.cos(alpha)[None, :]
    ey = mid * np.sin(alpha)[None, :]
    out_u, out_v, out_r = u.copy(), v.copy(), r.copy()
    ok = np.zeros(n, bool)
    quality = np.zeros(n)
    for i in range(n):
        centre, rad, inl, _ = robust_circle(ex[i], ey[i], 0.05 * r[i], ransac=ransac)
        quality[i] = inl.mean()
        if inl.mean() >= min_inliers and 0.6 * r[i] <= rad <= 1.5 * r[i] and np.hypot(*centre) <= 0.5 * r[i]:
            out_u[i], out_v[i], out_r[i] = u[i] + centre[0], v[i] + centre[1], rad
            ok[i] = True
    return out_u, out_v, out_r, ok, quality
