"""Identification of detected craters against the landmark map, and the robust position fix.

**Identification with a prior** (:func:`identify`). The prior is a coarse camera state: for a mosaic
window, the map point under the frame centre (error up to ``prior_sigma_km``), the pixel size and the
heading (a lander knows its attitude from its star tracker; its position only coarsely). The landmarks
predicted in the frame by the prior are paired with detections whose centre lies within the prior's
uncertainty (plus a quarter of the radius) and whose radius agrees within ``radius_ratio``: these are
putative correspondences, several per detection.

**Position fix** (:func:`ransac_similarity`). A mosaic window is an orthographic nadir view of the map
plane (module docstring of :mod:`.frames`), so map point = s R(phi) (u, v) + t: a 2-D similarity, the
degenerate (infinite focal length, nadir) case of the pinhole pose. RANSAC draws two correspondences,
solves the similarity, rejects hypotheses whose scale or heading disagree with the prior beyond
``max_scale_error`` / ``max_heading_deg``, and counts the inliers (reprojection within
``inlier_px`` + ``inlier_r`` x r, one landmark per detection). The best set is refitted by least
squares. **No fix** is answered when fewer than ``min_inliers`` (>= 3) landmarks agree, or when a
second, disjoint hypothesis nearly as well supported disagrees (ambiguity), or when the inlier RMS
exceeds ``max_rms_px``: the system says it does not know rather than fix silently wrong.

**Pinhole pose from 3-D landmarks** (:func:`ransac_pnp`): the general case for perspective frames.
Landmarks are 3-D points (centre on the rim plane, Moon-centred, heights from the DEM); minimal sets
of 3 correspondences are solved in closed form (OpenCV's AP3P, :mod:`.p3p`; of its up to four poses, the
one turned least from the prior attitude), scored by reprojection inliers, and the winner is refined on
all inliers (Gauss-Newton from the prior pose). "No fix" with fewer than 4 agreeing landmarks, for a pose
that contradicts its prior (attitude, position), an ambiguous one (the rule above), or an ill-conditioned
one (its 3-sigma horizontal uncertainty reaches the false-fix distance).

Settings were chosen on validation windows only (docs/navigation/fix.md).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from crater_synth.navigation.fix.p3p import p3p_pose, pnp_hypotheses
from crater_synth.navigation.fix.pose import (
    attitude_difference_deg,
    pose_sigma_horizontal_m,
    pose_with_attitude,
    project_pinhole,
    refine_pose,
    solve_position,
)


@dataclass(frozen=True)
class FixParams:
    """Settings of identification and fix (chosen on validation windows; docs/navigation/fix.md)."""

    prior_sigma_km: float = 10.0  # prior position uncertainty the gate allows for
    min_landmark_km: float = 10.0  # smallest landmark predicted in the frame
    radius_ratio: float = 1.3  # putative pair: detection radius / landmark radius within [1/x, x]
    inlier_px: float = 2.0
    inlier_r: float = 0.1
    max_scale_error: float = 0.05
    max_heading_deg: float = 5.0
    min_inliers: int = 5  # >= 3 by the method; 5 chosen on validation windows (no false fix there)
    ambiguity_margin: int = 1  # a disjoint rival with >= best - margin inliers is ambiguous: no fix
    max_rms_px: float = 4.0
    iterations: int = 400
    seed: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class Fix:
    """Result of a fix: ``ok`` False is "no fix" (``reason`` says why)."""

    ok: bool
    reason: str = ""
    x_m: float = math.nan  # map point under the frame centre
    y_m: float = math.nan
    scale_m_per_px: float = math.nan
    heading_deg: float = math.nan
    inliers: list[tuple[int, int]] = field(default_factory=list)  # (detection index, landmark index)
    rms_px: float = math.nan
    # Lost in space: the support of the best verified candidate (its inlier count, or -log10 of its chance),
    # fixed or refused; nan where none verified or for a prior-gated fix.
    support: float = math.nan
    # Lost in space with the frame's own null (null_turns): the best support its turned detections reached; nan where
    # it was not measured.
    null_support: float = math.nan

    def as_dict(self) -> dict:
        d = asdict(self)
        d["inliers"] = [list(p) for p in self.inliers]
        return d


# --------------------------------------------------------------------------------------------
# 2-D similarity (mosaic windows)
# --------------------------------------------------------------------------------------------
def fit_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[complex, complex]:
    """Least-squares similarity dst = a src + b, points as complex numbers (a = s e^{i phi}).
    ``src``, ``dst``: (n, 2), n >= 2."""
    z = src[:, 0] + 1j * src[:, 1]
    w = dst[:, 0] + 1j * dst[:, 1]
    zc, wc = z - z.mean(), w - w.mean()
    spread = np.vdot(zc, zc)
    if not spread.real > 0.0:  # every source point the same (one detection paired twice): no similarity
        return complex(math.nan, math.nan), complex(math.nan, math.nan)
    a = complex(np.vdot(zc, wc) / spread)
    return a, complex(w.mean() - a * z.mean())


def apply_similarity(a: complex, b: complex, pts: np.ndarray) -> np.ndarray:
    w = a * (pts[:, 0] + 1j * pts[:, 1]) + b
    return np.stack([w.real, w.imag], axis=1)


def inliers_of(a, b, det_uv, det_r, lm_xy, pairs, params: FixParams):
    """Greedy one-to-one inlier set of ``pairs`` under dst = a src + b (residual in pixels)."""
    inv = 1.0 / a
    pred = apply_similarity(inv, -b * inv, lm_xy[pairs[:, 1]])  # landmark -> pixel
    res = np.hypot(*(pred - det_uv[pairs[:, 0]]).T)
    ok = res <= params.inlier_px + params.inlier_r * det_r[pairs[:, 0]]
    order = np.argsort(res[ok])
    cand = pairs[ok][order]
    used_d, used_l, out = set(), set(), []
    for d, lm in cand:
        if d not in used_d and lm not in used_l:
            used_d.add(int(d))
            used_l.add(int(lm))
            out.append((int(d), int(lm)))
    return out


def ransac_similarity(
    det_uv, det_r, lm_xy, pairs, prior_a: complex, params: FixParams = FixParams()
) -> tuple[Fix, complex, complex]:
    """Robust similarity pixel -> map from putative ``pairs`` (k, 2) of (detection, landmark) indices.

    ``prior_a``: the prior's complex scale-rotation (map metres per pixel x e^{i heading}). Returns
    (fix without the frame-centre point, a, b); a "no fix" has ``ok`` False.
    """
    det_uv, lm_xy = np.asarray(det_uv, float), np.asarray(lm_xy, float)
    pairs = np.asarray(pairs, int).reshape(-1, 2)
    if pairs.size == 0 or len(np.unique(pairs[:, 0])) < params.min_inliers:
        return Fix(False, f"fewer than {params.min_inliers} detections pair with a predicted landmark"), 0j, 0j
    rng = np.random.default_rng(params.seed)
    hyps: list[list[tuple[int, int]]] = []
    seen: set[frozenset] = set()
    for _ in range(params.iterations):
        i, j = rng.choice(len(pairs), 2, replace=False)
        p, q = pairs[i], pairs[j]
        if p[0] == q[0] or p[1] == q[1]:
            continue
        src = det_uv[[p[0], q[0]]]
        if np.hypot(*(src[0] - src[1])) < 1e-6:
            continue
        a, b = fit_similarity(src, lm_xy[[p[1], q[1]]])
        if abs(abs(a) / abs(prior_a) - 1.0) > params.max_scale_error:
            continue
        if abs(math.degrees(np.angle(a / prior_a))) > params.max_heading_deg:
            continue
        inl = inliers_of(a, b, det_uv, det_r, lm_xy, pairs, params)
        key = frozenset(inl)
        if len(inl) >= 2 and key not in seen:
            seen.add(key)
            hyps.append(inl)
    if not hyps:
        return Fix(False, "no two pairs agree on a scale and heading near the prior"), 0j, 0j
    hyps.sort(key=len, reverse=True)
    best = hyps[0]
    # Refit on the inliers, then recollect them once under the refined transform.
    for _ in range(2):
        idx = np.array(best)
        a, b = fit_similarity(det_uv[idx[:, 0]], lm_xy[idx[:, 1]])
        if not np.isfinite(a):
            return Fix(False, "the agreeing pairs share one detection: no similarity"), a, b
        best = inliers_of(a, b, det_uv, det_r, lm_xy, pairs, params) or best
    if len(best) < params.min_inliers:
        return Fix(False, f"only {len(best)} landmarks agree (need {params.min_inliers})"), a, b
    idx = np.array(best)
    a, b = fit_similarity(det_uv[idx[:, 0]], lm_xy[idx[:, 1]])
    pred = apply_similarity(1.0 / a, -b / a, lm_xy[idx[:, 1]])
    rms = float(np.sqrt(np.mean(np.sum((pred - det_uv[idx[:, 0]]) ** 2, axis=1))))
    best_dets = {d for d, _ in best}
    best_lms = {lm for _, lm in best}
    for rival in hyps[1:]:
        disjoint = not ({d for d, _ in rival} & best_dets) or not ({lm for _, lm in rival} & best_lms)
        if disjoint and len(rival) >= len(best) - params.ambiguity_margin and len(rival) >= params.min_inliers:
            return Fix(False, f"ambiguous: two disjoint landmark sets agree ({len(best)} and {len(rival)})"), a, b
    if rms > params.max_rms_px:
        return Fix(False, f"inlier reprojection RMS {rms:.1f} px > {params.max_rms_px} px"), a, b
    return Fix(True, "", inliers=best, rms_px=rms), a, b


def identify(detections, landmarks, georef_prior, frame_shape, params: FixParams = FixParams()):
    """Putative pairs between ``detections`` and the landmarks predicted in a frame by a prior
    georeference (:class:`.frames.Georef`). Returns (pairs (k, 2), predicted landmark indices)."""
    h, w = frame_shape
    gate_px = params.prior_sigma_km * 1000.0 / georef_prior.pixel_m
    xs = np.array([lm.x_m for lm in landmarks])
    ys = np.array([lm.y_m for lm in landmarks])
    rs = np.array([lm.diameter_km for lm in landmarks]) * 500.0 / georef_prior.pixel_m
    u, v = georef_prior.xy_to_uv(xs, ys)
    big = np.array([lm.diameter_km >= params.min_landmark_km for lm in landmarks], dtype=bool)  # [] is float
    near = big & (u > -gate_px) & (u < w + gate_px) & (v > -gate_px) & (v < h + gate_px)
    cand = np.nonzero(near)[0]
    if not detections or cand.size == 0:
        return np.zeros((0, 2), int), cand
    du = np.array([d.u for d in detections])[:, None] - u[cand][None, :]
    dv = np.array([d.v for d in detections])[:, None] - v[cand][None, :]
    dr = np.array([d.r for d in detections])[:, None] / rs[cand][None, :]
    ok = (
        (np.hypot(du, dv) <= gate_px + 0.25 * rs[cand][None, :])
        & (dr <= params.radius_ratio)
        & (dr >= 1.0 / params.radius_ratio)
    )
    i, j = np.nonzero(ok)
    return np.stack([i, cand[j]], axis=1), cand


def fix_frame(detections, landmarks, georef_prior, frame_shape, params: FixParams = FixParams()) -> Fix:
    """Identify ``detections`` and fix the frame: the map point under the frame centre, or "no fix"."""
    pairs, _ = identify(detections, landmarks, georef_prior, frame_shape, params)
    det_uv = np.array([[d.u, d.v] for d in detections], float).reshape(-1, 2)
    det_r = np.array([d.r for d in detections], float)
    lm_xy = np.array([[lm.x_m, lm.y_m] for lm in landmarks], float)
    prior_a = complex(georef_prior.pixel_m, 0.0) * complex(1.0, 0.0)
    # Pixel (u, v) -> map (x, y) = (left + u p, top - v p): a reflection, so fit in (u, -v) coordinates.
    flip = np.array([1.0, -1.0])
    fix, a, b = ransac_similarity(det_uv * flip, det_r, lm_xy, pairs, prior_a, params)
    if not fix.ok:
        return fix
    h, w = frame_shape
    c = apply_similarity(a, b, np.array([[w / 2.0, -h / 2.0]]))[0]
    fix.x_m, fix.y_m = float(c[0]), float(c[1])
    fix.scale_m_per_px = float(abs(a))
    fix.heading_deg = float(math.degrees(np.angle(a)))
    return fix


# --------------------------------------------------------------------------------------------
# Pinhole pose from 3-D points (perspective frames; the camera maths: :mod:`.pose`)
# --------------------------------------------------------------------------------------------
PNP_MIN_INLIERS = 4  # three points determine a pinhole pose exactly: any three pairs "agree"
FALSE_FIX_KM = 5.0  # a fix further than this from the truth is a false fix (the evaluation's definition)
# A 6-DOF pose whose horizontal 3-sigma uncertainty reaches the false-fix distance is no fix: the pixels
# cannot tell it from a pose that is false (not tuned: the bound is the definition, 3 the usual coverage).
PNP_SIGMAS = 3.0


def ransac_pnp(
    points,
    uv,
    k,
    r_prior,
    c_prior,
    params: FixParams = FixParams(),
    inlier_px: float = 2.0,
    pairs=None,
    minimal=p3p_pose,
    attitude_sigma_rad: float = 0.0,
):
    """Robust pinhole pose from 3-D ``points`` (n, 3) and their pixels ``uv`` (n, 2) with known
    correspondences, some wrong. Returns (ok, reason, r_wc, centre, inlier mask).

    ``attitude_sigma_rad`` > 0: ``r_prior`` is a measured attitude of that 1-sigma (a star tracker), and the
    inliers' pose is its maximum a posteriori estimate (:func:`refine_pose`'s attitude prior, weighted by the
    residuals' own scatter, no less than :data:`PNP_MIN_SIGMA_PX`); the conditioning test counts it too.
    With a few landmarks in a narrow field, a tilt and a shift explain the pixels nearly alike, and the free
    pose can sit kilometres off while its residual scatter, from a handful of degrees of freedom, looks small.

    "No fix" when fewer than ``min_inliers`` (and never fewer than :data:`PNP_MIN_INLIERS`) agree; when the
    pose contradicts the prior it started from: an attitude more than ``max_heading_deg`` from the prior's
    (the attitude a star tracker gives, coarsely) or a position further from the prior's than its
    uncertainty ``prior_sigma_km`` (horizontally: the identification gate assumed no more); given ``pairs``
    (n, 2, the (detection, landmark) ids of the correspondences), when a disjoint hypothesis is nearly as
    well supported (the ambiguity rule of :func:`ransac_position`); and when the pose is ill-conditioned:
    its horizontal uncertainty (:func:`pose_sigma_horizontal_m`) times :data:`PNP_SIGMAS` exceeds
    :data:`FALSE_FIX_KM`. ``minimal``: the minimal solver of each hypothesis (:func:`p3p_pose`'s signature;
    None for a triple with no pose)."""
    points, uv = np.asarray(points, float), np.asarray(uv, float)
    n = len(points)
    need = max(params.min_inliers, PNP_MIN_INLIERS)
    if n < need:
        return False, f"{n} landmarks identified (need {need})", None, None, np.zeros(n, bool)
    rng = np.random.default_rng(params.seed)
    best = np.zeros(n, bool)
    hyps: dict[bytes, np.ndarray] = {}  # distinct inlier sets, for the ambiguity rule
    for inl in pnp_hypotheses(points, uv, k, (r_prior, c_prior), rng, min(params.iterations, 200), inlier_px, minimal):
        if pairs is not None and inl.sum() >= need:
            hyps.setdefault(np.packbits(inl).tobytes(), inl)
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < need:
        return False, f"only {int(best.sum())} landmarks agree on one pose", None, None, best
    r, c = refine_pose(points[best], uv[best], k, r_prior, c_prior)
    err = np.hypot(*(project_pinhole(points, r, c, k) - uv).T)
    best = err <= inlier_px
    if best.sum() < need:
        return False, f"only {int(best.sum())} landmarks agree on one pose", None, None, best
    r, c = refine_pose(points[best], uv[best], k, r, c)
    if attitude_sigma_rad > 0.0:
        r, c = pose_with_attitude(points[best], uv[best], k, r, c, r_prior, attitude_sigma_rad)
    turned = attitude_difference_deg(r, r_prior)
    if turned > params.max_heading_deg:
        return (
            False,
            f"the pose turns {turned:.1f} deg from the prior attitude (> {params.max_heading_deg:g})",
            None,
            None,
            best,
        )
    moved = float(np.hypot(*(np.asarray(c) - np.asarray(c_prior))[:2])) / 1000.0
    if moved > params.prior_sigma_km:
        return False, f"the pose is {moved:.1f} km from the prior (> {params.prior_sigma_km:g} km)", None, None, best
    rival = _rival(pairs, best, hyps, need, params.ambiguity_margin)
    if rival:
        return False, rival, None, None, best
    sigma_km = pose_sigma_horizontal_m(points[best], uv[best], k, r, c, attitude_sigma_rad) / 1000.0
    if PNP_SIGMAS * sigma_km > FALSE_FIX_KM:
        why = f"ill-conditioned pose: {PNP_SIGMAS:g} sigma = {PNP_SIGMAS * sigma_km:.1f} km > {FALSE_FIX_KM:g} km"
        return False, why, None, None, best
    return True, "", r, c, best


# --------------------------------------------------------------------------------------------
# Known attitude: camera position only (perspective frames with a star-tracker attitude)
# --------------------------------------------------------------------------------------------
def _distinct(pairs: np.ndarray, mask: np.ndarray) -> int:
    """Upper bound of the one-to-one pairs in ``pairs[mask]`` (fewest distinct detections or landmarks)."""
    sel = pairs[mask]
    return min(len(np.unique(sel[:, 0])), len(np.unique(sel[:, 1]))) if len(sel) else 0


def _rival(pairs, best: np.ndarray, hyps: dict, need: int, margin: int) -> str:
    """The ambiguity rule: the reason for "no fix" when one of the hypotheses ``hyps`` (inlier masks over
    ``pairs``, the (detection, landmark) ids of the correspondences) shares no detection or no landmark with
    the winner ``best`` and is supported by at least ``need`` and the winner's count less ``margin`` distinct
    landmarks: a rival as well explained as the winner. Empty when there is none (or no ``pairs``)."""
    if pairs is None:
        return ""
    pairs = np.asarray(pairs, int).reshape(-1, 2)
    n_best = _distinct(pairs, best)
    dets, lms = set(pairs[best, 0].tolist()), set(pairs[best, 1].tolist())
    for inl in hyps.values():
        n_rival = _distinct(pairs, inl)
        disjoint = not (set(pairs[inl, 0].tolist()) & dets) or not (set(pairs[inl, 1].tolist()) & lms)
        if disjoint and n_rival >= max(need, n_best - margin):
            return f"ambiguous: two disjoint landmark sets agree ({n_best} and {n_rival})"
    return ""


def position_hypotheses(points, uv, k, r_wc, rng, iterations: int, inlier_px: float) -> np.ndarray:
    """Inlier masks (h, n) of the camera centres solved from ``iterations`` random pairs of
    correspondences (drawn from ``rng`` one pair at a time, in order), all pairs solved at once: a pair
    whose two rays or two points coincide (one detection or one landmark twice: no position) and a centre
    with either landmark behind the camera are left out."""
    n = len(points)
    idx = np.array([rng.choice(n, 2, replace=False) for _ in range(iterations)]).reshape(-1, 2)
    a, b = idx[:, 0], idx[:, 1]
    same = np.all(np.isclose(uv[a], uv[b]), axis=1) | np.all(np.isclose(points[a], points[b]), axis=1)
    a, b = a[~same], b[~same]
    rays = np.linalg.solve(k, np.column_stack([uv, np.ones(n)]).T).T @ r_wc  # world directions
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    proj = np.eye(3)[None, :, :] - rays[:, :, None] * rays[:, None, :]  # (n, 3, 3): I - d d^T
    lhs = proj[a] + proj[b]
    rhs = np.einsum("hij,hj->hi", proj[a], points[a]) + np.einsum("hij,hj->hi", proj[b], points[b])
    centres = np.linalg.solve(lhs, rhs[:, :, None])[:, :, 0]  # (h, 3)
    ahead = ((points[a] - centres) @ r_wc[2] > 0) & ((points[b] - centres) @ r_wc[2] > 0)
    centres = centres[ahead]
    cam = (points[None, :, :] - centres[:, None, :]) @ r_wc.T @ k.T  # (h, n, 3)
    err = np.hypot(*np.moveaxis(cam[..., :2] / cam[..., 2:3] - uv[None], -1, 0))
    return err <= inlier_px


def ransac_position(points, uv, k, r_wc, params: FixParams = FixParams(), inlier_px: float = 2.0, pairs=None):
    """Robust camera centre of known attitude from putative correspondences (some wrong): minimal sets
    of 2, scored by reprojection inliers, refitted on all inliers. Returns (ok, reason, centre, inlier
    mask); the "no fix" rule of :func:`ransac_pnp` (fewer than ``min_inliers`` agreeing) applies.

    ``pairs`` (n, 2): the (detection, landmark) ids of the correspondences; when given, the ambiguity
    rule of :func:`ransac_similarity` applies too: a hypothesis sharing no detection or no landmark with
    the winner, supported by at least ``min_inliers`` and the winner's count less ``ambiguity_margin``
    distinct landmarks, is a rival position as well explained as the winner: "no fix"."""
    points, uv = np.asarray(points, float), np.asarray(uv, float)
    n = len(points)
    if n < params.min_inliers:
        return False, f"{n} landmarks identified (need {params.min_inliers})", None, np.zeros(n, bool)
    rng = np.random.default_rng(params.seed)
    best = np.zeros(n, bool)
    hyps: dict[bytes, np.ndarray] = {}  # distinct inlier sets, for the ambiguity rule
    for inl in position_hypotheses(points, uv, k, r_wc, rng, params.iterations, inlier_px):
        if pairs is not None and inl.sum() >= params.min_inliers:
            hyps.setdefault(np.packbits(inl).tobytes(), inl)
        if inl.sum() > best.sum():
            best = inl
    for _ in range(2):  # refit on the inliers, then re-collect them
        if best.sum() < max(params.min_inliers, 2):
            return False, f"only {int(best.sum())} landmarks agree on one position", None, best
        c = solve_position(points[best], uv[best], k, r_wc)
        best = np.hypot(*(project_pinhole(points, r_wc, c, k) - uv).T) <= inlier_px
    if best.sum() < params.min_inliers:
        return False, f"only {int(best.sum())} landmarks agree on one position", None, best
    rival = _rival(pairs, best, hyps, params.min_inliers, params.ambiguity_margin)
    if rival:
        return False, rival, None, best
    return True, "", solve_position(points[best], uv[best], k, r_wc), best
