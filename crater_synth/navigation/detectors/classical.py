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

A second method (:mod:`crater_synth.navigation.detectors.template`: Hapke-shaded template, normalised
cross-correlation) shares the light estimate, the rim fit and the suppression; ``DetectorParams.method``
picks it. Every setting (``PRESETS``) was chosen on validation windows only (docs/navigation/detectors.md).
The filtering is done in the Fourier domain (:mod:`.scalespace`): one forward FFT, one inverse FFT per
scale.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import asdict, dataclass

import numpy as np

from crater_synth.errors import UserError
from crater_synth.navigation.detectors.scalespace import PAD_PX, decimation, filtered, peaks, spectrum
from crater_synth.navigation.detectors.template import template_candidates
from crater_synth.navigation.georef import check_frame

__all__ = ["PAD_PX", "decimation", "filtered", "peaks", "spectrum"]  # re-exported for callers and tests


@dataclass(frozen=True)
class DetectorParams:
    """Settings of :func:`detect` (values chosen on validation windows; docs/navigation/detectors.md)."""

    min_radius_px: float = 9.0  # D = 7.2 km at 400 m/px: the 10 km landmarks less the 25 % tolerance
    max_radius_px: float = 160.0
    scale_ratio: float = 1.2
    sigma_per_radius: float = 0.45
    centre_shift: float = 0.2  # fraction of r, along the light direction
    threshold: float = 0.5
    n_azimuths: int = 24
    # The strongest derivative tail points towards the Sun (True: the rise from a rim's cast shadow to
    # the lit terrain beyond) or along the light (False: the rise across a crater from shadow to limb).
    tail_points_to_sun: bool = True
    light_method: str = "tail"  # "tail" (tail alone; chosen on validation) or "tensor" (tensor axis + tail sign)
    # Real mosaic windows (crater_synth.navigation.windows.light.frame_light): "frame" estimates the light per
    # window; "quadrant" uses one estimate pooled over the validation windows of the window's mosaic
    # quadrant (assumes one light direction per quadrant, which the test sectors refuted:
    # docs/history.md); "local": the light at one fixed *local* azimuth (clockwise from local
    # north), so it turns with the window's longitude in the map image; that azimuth is pooled from the
    # image statistics of the windows of one mosaic quadrant ("quadrant"), 45-degree sector ("sector") or
    # the whole mosaic ("pole") of the same pole, no truth used. light_seed_deg > 0: the frame's own
    # estimate, searched only within +-this many degrees of the pooled local direction. light_tries_deg:
    # the detector and the fix run once per offset added to the light direction, and the fix with most
    # inliers is kept (a lander without the Sun). detect() itself always takes light_dir (or light_prior)
    # or estimates the light on its frame.
    light_scope: str = "frame"
    light_pool: str = "quadrant"
    light_seed_deg: float = 0.0
    light_tries_deg: tuple = (0.0,)
    azimuth_sigmas_px: tuple = (8.0, 12.0, 20.0)
    azimuth_tail: float = 0.002  # top share of pixels whose mean response scores an azimuth
    nms_centre_r: float = 0.6  # two detections closer than this x the larger r, of similar size: one crater
    nms_radius_ratio: float = 1.5
    # Concentric detections (centres closer than this x the larger r, any size ratio): one crater. 0 = off
    # (the evaluated default); a validation-only experiment, docs/navigation/detectors.md.
    concentric_r: float = 0.0
    concentric_rank: str = "rim"  # keep the concentric detection with the best rim fit ("rim") or filter score
    method: str = "filter"  # "filter" (classical), "template" (Hapke template NCC, .template) or "learned" (.learned)
    # "appearance": no detector, the map's landmarks searched for by their predicted appearance under the
    # prior (.appearance_window; needs the map and the prior, so nav-eval and navigate run it, not detect()).
    template_threshold: float = 0.35  # NCC of a template candidate
    template_sun_el_deg: float = 10.0  # Sun elevation the template is shaded at
    template_depth_d: float = 0.2  # template bowl depth / diameter
    learned_threshold: float = 0.3  # heat-map peak of a learned-detector candidate
    learned_model: str = ""  # model file of the learned detector ("": the committed south model)
    border_r: float = 0.5  # the crater centre lies at least this x r inside the frame
    refine: bool = True  # fit the rim to the shadow and limb edges (:func:`refine_rims`)
    rim_min_inliers: float = 0.5  # share of the edge points on the fitted rim circle, else the detection is dropped
    max_candidates: int = 400  # strongest filter maxima refined per frame
    appearance_sun_el_deg: tuple = (8.0,)  # Sun elevations tried per window (the best-correlating kept)
    appearance_min_ncc: float = 0.7  # a weaker correlation peak is no detection
    appearance_coarse_steps: int = 8  # the search's first grid, steps each way
    appearance_margin_px: int = 3  # added to the prior's uncertainty
    appearance_thin: bool = False  # coarse search grids correlate fewer samples (.appearance.register_wide)

    def __post_init__(self):
        choices = {
            "method": ("filter", "template", "learned", "appearance"),
            "light_method": ("tensor", "tail"),
            "light_scope": ("frame", "quadrant", "local"),
            "light_pool": ("quadrant", "sector", "pole"),
            "concentric_rank": ("rim", "score"),
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise DetectorSettingsError(f"detect.{name}={getattr(self, name)!r}: expected one of {allowed}")
        if not 0 < self.min_radius_px < self.max_radius_px or self.scale_ratio <= 1.0:
            raise DetectorSettingsError(
                f"detect radii: need 0 < min_radius_px ({self.min_radius_px}) < max_radius_px "
                f"({self.max_radius_px}) and scale_ratio ({self.scale_ratio}) > 1"
            )
        if not 0.0 <= self.light_seed_deg <= 180.0 or not self.light_tries_deg:
            raise DetectorSettingsError(
                f"detect.light_seed_deg={self.light_seed_deg} must be in [0, 180] and detect.light_tries_deg="
                f"{self.light_tries_deg} must name at least one offset"
            )
        if not self.appearance_sun_el_deg or not all(0.0 < e < 90.0 for e in self.appearance_sun_el_deg):
            raise DetectorSettingsError(
                f"detect.appearance_sun_el_deg={self.appearance_sun_el_deg}: expected elevations in (0, 90)"
            )
        search = (self.appearance_coarse_steps, self.appearance_margin_px)
        if not -1.0 <= self.appearance_min_ncc <= 1.0 or search[0] < 1 or search[1] < 0:
            raise DetectorSettingsError(
                f"detect.appearance_min_ncc={self.appearance_min_ncc} must be in [-1, 1], appearance_coarse_steps="
                f"{self.appearance_coarse_steps} >= 1 and appearance_margin_px={self.appearance_margin_px} >= 0"
            )
        if not 0.0 < self.template_sun_el_deg < 90.0:
            raise DetectorSettingsError(f"detect.template_sun_el_deg={self.template_sun_el_deg}: expected in (0, 90)")

    def as_dict(self) -> dict:
        return asdict(self)


class DetectorSettingsError(UserError):
    """A detector setting out of its allowed values."""


# The two detection methods compared in ``nav-eval``, each with the settings chosen for it on validation
# windows only (docs/navigation/protocol.md). Third round: the light model (local azimuth pooled per
# mosaic quadrant from image statistics; the classical detector's own estimate within +-30 degrees of it)
# chosen on the whole south mosaic (its old test sectors are development data since the south test was
# run), frozen before the north test windows were run.
PRESETS = {
    "classical": DetectorParams(
        light_method="tail", light_scope="local", light_pool="quadrant", light_seed_deg=30.0, threshold=0.4
    ),
    "template": DetectorParams(
        method="template",
        light_method="tail",
        light_scope="local",
        light_pool="quadrant",
        template_threshold=0.35,
        template_sun_el_deg=10.0,
        concentric_r=0.5,
        concentric_rank="score",
    ),
    # The network of .learned (the committed model), trained on rendered frames only; it needs no light
    # direction (no Sun knowledge, no pooling over a quadrant). Fourth round, chosen on the south windows
    # (development data) and frozen before the north windows were run: the model and the heat threshold
    # by the navigation rule (no false fix, most fixes, lowest median error; docs/navigation/protocol.md),
    # no rim fit (it added a false fix); "learned-detect" is the same model at the threshold with the best
    # detection F1 (D >= 15 km), the detection operating point.
    "learned": DetectorParams(
        method="learned",
        light_scope="frame",
        refine=False,
        learned_threshold=0.07,
        concentric_r=0.5,
        concentric_rank="score",
    ),
}
PRESETS["learned-detect"] = dataclasses.replace(PRESETS["learned"], learned_threshold=0.3)
# No detector: the map's landmarks searched for by their predicted appearance (.appearance_window) under
# the frozen light model's azimuth. Fifth round, chosen on the south windows (development data) and
# frozen before the north windows were run: one Sun elevation, NCC threshold and thinned coarse grids by
# the declared rule (docs/navigation/protocol.md).
PRESETS["appearance"] = DetectorParams(
    method="appearance",
    light_scope="local",
    light_pool="quadrant",
    appearance_sun_el_deg=(8.0,),
    appearance_min_ncc=0.5,
    appearance_thin=True,
)
# The second round's presets (light pooled per quadrant over the south validation sectors), with which
# the south test split was run once: kept to reproduce that historic result (`nav-eval --set
# detect.light_scope=quadrant --set detect.light_seed_deg=0`).
PRESETS_SECOND_ROUND = {
    "classical": DetectorParams(light_method="tail", light_scope="quadrant", threshold=0.4),
    "template": dataclasses.replace(PRESETS["template"], light_scope="quadrant"),
}


def preset(name: str, overrides: dict | None = None) -> DetectorParams:
    """The detector settings of method ``name`` (a key of :data:`PRESETS`) with ``overrides`` applied."""
    import dataclasses

    if name not in PRESETS:
        raise DetectorSettingsError(f"detection method {name!r}: expected one of {sorted(PRESETS)}")
    return dataclasses.replace(PRESETS[name], **(overrides or {}))


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


def azimuth_grads(spec, shape, params: DetectorParams):
    """Gaussian-derivative images (d/du, d/dv) at the ``azimuth_sigmas_px`` scales."""
    grads = []
    for s in params.azimuth_sigmas_px:
        step = decimation(s)
        grads.append((_derivative(spec, shape, s, 1.0, 0.0, step), _derivative(spec, shape, s, 0.0, 1.0, step)))
    return grads


def _tail_scores(grads, candidates, params: DetectorParams) -> np.ndarray:
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


def _candidates(grads, params: DetectorParams) -> np.ndarray:
    if params.light_method == "tensor":
        axis = light_axis(grads)
        return np.array([axis, axis + math.pi])
    if params.light_method == "tail":
        return np.arange(params.n_azimuths) * 2.0 * np.pi / params.n_azimuths
    raise ValueError(f"light_method {params.light_method!r}: expected 'tensor' or 'tail'")


def _light_from(candidates, scores, params: DetectorParams) -> float:
    # The strongest rise is at the Sun-side rim: from the shadow cast by the rim crest up to the lit
    # terrain beyond it, i.e. towards the Sun (validation windows: the opposite sign halves the fix rate).
    best = float(candidates[int(np.argmax(scores))])
    return (best + (math.pi if params.tail_points_to_sun else 0.0)) % (2.0 * math.pi)


def _angle_diff(a, b):
    """a - b wrapped to [-pi, pi)."""
    return (np.asarray(a) - b + math.pi) % (2.0 * math.pi) - math.pi


def light_azimuth(spec, shape, params: DetectorParams, prior: tuple[float, float] | None = None) -> float:
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


def pooled_light_azimuth(images, params: DetectorParams, rotations=None, n_azimuths: int | None = None) -> float:
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
        raise DetectorSettingsError("a light pooled in a rotating frame needs detect.light_method='tail'")
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


def scale_radii(params: DetectorParams, shape) -> np.ndarray:
    """Crater radii (px) searched: ``min_radius_px`` up by ``scale_ratio``, at most half the frame."""
    n_scales = int(math.floor(math.log(params.max_radius_px / params.min_radius_px) / math.log(params.scale_ratio))) + 1
    radii = params.min_radius_px * params.scale_ratio ** np.arange(n_scales)
    return radii[radii <= 0.5 * min(shape)]


def _filter_candidates(spec, shape, radii, theta: float, params: DetectorParams):
    """Maxima of the shadow-to-limb derivative filter over scales: (u, v, r, score) in frame pixels."""
    du, dv = math.cos(theta), math.sin(theta)
    us, vs, rs, ss = [], [], [], []
    for r in radii:
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


def detect(
    image: np.ndarray,
    params: DetectorParams = DetectorParams(),
    light_dir: float | None = None,
    what: str = "frame",
    light_prior: tuple[float, float] | None = None,
):
    """Craters in ``image`` (2-D): (list of :class:`Detection`, light azimuth used in radians).

    The light direction: ``light_dir`` when given, else estimated on the frame (within ``light_prior``
    = (direction, half-width) radians when given, :func:`light_azimuth`).

    ``params.method`` "filter": the classical shadow/limb derivative filter (module docstring);
    "template": normalised cross-correlation with a Hapke-shaded crater template at the frame's light
    direction (:mod:`crater_synth.navigation.detectors.template`). Both share the light estimate, the rim fit and
    the suppression of overlapping and concentric detections."""
    if params.method == "appearance":  # refused before any work on the frame
        raise DetectorSettingsError(
            f"{what}: detect.method='appearance' searches for map landmarks under a position prior; "
            "run it through nav-eval or navigate, not as a detector"
        )
    a = check_frame(image, what)
    a = (a - a.mean()) / a.std()
    h, w = a.shape
    radii = scale_radii(params, a.shape)
    # The Fourier spectrum serves the two filter methods and the light estimate; the network needs neither.
    spec, shape = (None, None) if params.method == "learned" else spectrum(a)
    if light_dir is not None:
        theta = float(light_dir)
    elif params.method == "learned" and not params.refine:
        theta = math.nan  # the network needs no light direction, and without the rim fit nothing uses it
    else:
        if spec is None:
            spec, shape = spectrum(a)
        theta = light_azimuth(spec, shape, params, light_prior)
    if params.method == "filter":
        u, v, r, score = _filter_candidates(spec, shape, radii, theta, params)
    elif params.method == "template":
        u, v, r, score = template_candidates(spec, shape, radii, theta, params)
    elif params.method == "learned":
        from crater_synth.navigation.detectors.learned import learned_candidates

        u, v, r, score = learned_candidates(a, params)
    else:
        raise ValueError(f"detector method {params.method!r}: expected 'filter', 'template' or 'learned'")
    b = params.border_r * r
    inside = (u >= b) & (u <= w - b) & (v >= b) & (v <= h - b)
    u, v, r, score = u[inside], v[inside], r[inside], score[inside]
    quality = np.ones_like(score)
    if params.refine:
        top = np.argsort(-score)[: params.max_candidates]
        u, v, r, score = u[top], v[top], r[top], score[top]
        u, v, r, ok, quality = refine_rims(a, u, v, r, theta, params.rim_min_inliers)
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


def refine_rims(a: np.ndarray, u, v, r, theta: float, min_inliers: float):
    """Rim circles fitted to the shadow and lit-limb edges around each filter maximum.

    Along a ray from the centre towards the Sun, the rim is where the shadow ends and the lit outer
    flank begins (the strongest outward *rise* of intensity); along a ray away from the Sun it is where
    the bright limb ends (the strongest outward *fall*). Rays across the light carry no such edge and are
    skipped. A robust circle through these edge points (``crater_synth.terrain.catalogue.robust_circle``, the
    same fit the DEM rims use) gives the centre and radius. Returns (u, v, r, ok, quality): ``ok`` False
    where fewer than ``min_inliers`` of the edge points lie on one circle or the circle is implausible;
    ``quality`` the share of edge points on the circle.
    """
    from scipy.ndimage import gaussian_filter, map_coordinates

    from crater_synth.terrain.catalogue import robust_circle

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
        centre, rad, inl, _ = robust_circle(ex[i], ey[i], 0.05 * r[i])
        quality[i] = inl.mean()
        if inl.mean() >= min_inliers and 0.6 * r[i] <= rad <= 1.5 * r[i] and np.hypot(*centre) <= 0.5 * r[i]:
            out_u[i], out_v[i], out_r[i] = u[i] + centre[0], v[i] + centre[1], rad
            ok[i] = True
    return out_u, out_v, out_r, ok, quality
