"""``crater-synth bench --part opencv``: the solvers OpenCV does for the project, against what they replaced.

Each row times the library path and the project's former hand-written one on the same inputs, in the same
run, and states how far their results agree:

- ``pnp_minimal``: one RANSAC hypothesis of :func:`..navigation.fix.solve.ransac_pnp`, 3 correspondences:
  OpenCV's AP3P (:func:`..navigation.fix.p3p.p3p_pose`) against Gauss-Newton from the prior (15
  iterations, :func:`gauss_newton_p3`); ``pnp_ransac``: the whole robust fix with either, 12 landmarks of
  which 4 are wrongly identified (the same draws: the same winner, then the same refinement);
- ``ncc``: the template detector's NCC (:func:`..navigation.detectors.template.ncc`, OpenCV's filter2D and
  box filters) against scipy's FFT convolution and uniform filters (:func:`ncc_scipy`), on a 1024^2 frame;
- ``crop``: a rotated 400 px box resampled to 150^2 (:func:`train.preprocess.resample_box`, OpenCV's bilinear
  warp after the same anti-aliasing Gaussian) against scipy's ``map_coordinates`` (:func:`resample_box_scipy`);
  ``roll``: a 150^2 crop turned and shifted (:func:`train.preprocess.rotate_crop`) against scipy's
  ``affine_transform`` (:func:`rotate_crop_scipy`);
- ``nav_eval_window``: ``nav-eval``'s per-window time with the template detector on every 10th south
  validation window, with the former NCC and with OpenCV's, alternating window by window: the fixes must be
  the same.

The former implementations live here only, as the references of this bench and of
tests/test_opencv_swaps.py.
"""

from __future__ import annotations

import math
import time

import cv2
import numpy as np
from scipy import ndimage

from crater_synth.navigation.detectors import template
from crater_synth.navigation.detectors.template import crater_template, ncc
from crater_synth.navigation.fix import pose as pm
from crater_synth.navigation.fix import solve as nf
from crater_synth.navigation.fix.p3p import p3p_pose
from crater_synth.navigation.map.landmarks import load_default_map
from crater_synth.navigation.settings import compose_nav
from crater_synth.navigation.windows.evaluate import run_frame
from crater_synth.navigation.windows.mosaic import windows
from train.preprocess import box_axes, box_center_side, crop_window, resample_box, rotate_crop, spline_sample

TRIPLES = 200  # minimal solves timed per solver


# --------------------------------------------------------------------------------------------
# The former implementations (references)
# --------------------------------------------------------------------------------------------
def gauss_newton_p3(points, uv, k, r_prior, c_prior):
    """The former minimal solver of :func:`~..navigation.fix.solve.ransac_pnp`: Gauss-Newton from the prior
    pose, 15 iterations, on the 3 correspondences."""
    return pm.refine_pose(points, uv, k, r_prior, c_prior, iterations=15)


def ncc_scipy(image: np.ndarray, template: np.ndarray) -> np.ndarray:
    """The former :func:`~..navigation.detectors.template.ncc`: scipy's overlap-add FFT correlation (zeros
    beyond the image) over reflected-border uniform filters of the image and its square."""
    from scipy.signal import oaconvolve

    m = template.shape[0]
    corr = oaconvolve(image, template[::-1, ::-1], mode="same")
    mean = ndimage.uniform_filter(image, m, mode="reflect")
    sq = ndimage.uniform_filter(image * image, m, mode="reflect")
    energy = np.maximum(m * m * (sq - mean * mean), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(energy > 1e-9 * m * m, corr / np.sqrt(energy), 0.0)


def resample_box_scipy(image, box, size: int, rotation_deg: float = 0.0, antialias: bool = True) -> np.ndarray:
    """The former bilinear :func:`train.preprocess.resample_box` (scipy's Gaussian and ``map_coordinates``)."""
    cu, cv, w, h = box_center_side(box)
    return resample_affine_scipy(image, (cu, cv), box_axes(w, h, rotation_deg), size, antialias)


def resample_affine_scipy(image, center, axes, size: int, antialias: bool = True, order: int = 1) -> np.ndarray:
    """The former :func:`train.preprocess.resample_affine`: the same window, blurred by scipy's Gaussian and
    sampled by scipy's ``map_coordinates`` (order 1 as every order)."""

    def scipy_blur(win, sigma_u, sigma_v):
        return ndimage.gaussian_filter(win, sigma=(sigma_v, sigma_u), mode="nearest", truncate=4.0)

    win, to_window = crop_window(image, center, axes, size, antialias, blur=scipy_blur)
    return spline_sample(win, to_window, size, order)


def rotate_crop_scipy(y: np.ndarray, angle_deg: float, shift_px=(0.0, 0.0)) -> np.ndarray:
    """The former :func:`train.preprocess.rotate_crop` of one (H, W) crop: scipy's ``affine_transform``."""
    y = np.asarray(y, dtype=np.float32)
    a = math.radians(float(angle_deg))
    m = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
    c = (np.array(y.shape, dtype=np.float64) - 1.0) / 2.0
    offset = c - m @ (c + np.array([shift_px[1], shift_px[0]], dtype=np.float64))
    return ndimage.affine_transform(y, m, offset=offset, order=1, mode="constant", cval=0.0).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------------
def pnp_problem(seed: int = 3, n: int = 12, wrong: int = 4):
    """(points, uv, k, r_true, c_true, r_prior, c_prior): ``n`` landmarks over 80 km seen from 90 km,
    ``wrong`` of them moved by tens of pixels (wrong identifications), the prior 4 km and 0.5 deg off."""
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-40e3, 40e3, (n, 2)), rng.uniform(-2e3, 2e3, n)])
    k = np.array([[800.0, 0, 512], [0, 800.0, 512], [0, 0, 1]])
    r_true = pm.rodrigues(np.array([math.pi - 0.05, 0.03, 0.02]))
    c_true = np.array([1500.0, -800.0, 90e3])
    uv = pm.project_pinhole(pts, r_true, c_true, k) + rng.normal(0.0, 0.3, (n, 2))
    uv[:wrong] += rng.uniform(30.0, 80.0, (wrong, 2)) * rng.choice([-1.0, 1.0], (wrong, 2))
    r_prior = pm.rodrigues(np.radians([0.5, 0.0, 0.0])) @ r_true
    return pts, uv, k, r_true, c_true, r_prior, c_true + np.array([3000.0, -2500.0, 1000.0])


def smooth_image(shape, seed: int = 0, sigma: float = 3.0) -> np.ndarray:
    """A float32 image of smooth random relief (values ~0.5 +- 0.1), the kind the crops and frames hold."""
    rng = np.random.default_rng(seed)
    return ndimage.gaussian_filter(rng.uniform(0.0, 1.0, shape), sigma).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Rows
# --------------------------------------------------------------------------------------------
def _seconds(fn, repeat: int) -> float:
    """Best-of-3 mean seconds per call of ``fn`` over ``repeat`` calls (the fastest, least disturbed run)."""
    fn()
    best = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(repeat):
            fn()
        best = min(best, (time.perf_counter() - t0) / repeat)
    return best


def _row(before_s: float, after_s: float, **agreement) -> dict:
    return {
        "before_ms": round(before_s * 1e3, 4),
        "after_ms": round(after_s * 1e3, 4),
        "ratio": round(before_s / after_s, 1),
        **agreement,
    }


def bench_pnp() -> dict:
    """The minimal solve and the whole robust fix, before and after, on :func:`pnp_problem`."""
    pts, uv, k, _, c_true, r_prior, c_prior = pnp_problem()
    rng = np.random.default_rng(0)
    triples = [rng.choice(len(pts) - 4, 3, replace=False) + 4 for _ in range(TRIPLES)]  # correct pairs only
    gaps, err, none = [], {"before": [], "after": []}, 0
    for i in triples:
        c_a = gauss_newton_p3(pts[i], uv[i], k, r_prior, c_prior)[1]
        pose = p3p_pose(pts[i], uv[i], k, r_prior, c_prior)
        if pose is None:  # the pixels' noise leaves the triple no exact pose (Gauss-Newton returns its last step)
            none += 1
            continue
        gaps.append(float(np.linalg.norm(c_a - pose[1])))
        err["before"].append(float(np.linalg.norm(c_a - c_true)))
        err["after"].append(float(np.linalg.norm(pose[1] - c_true)))

    def solve_all(minimal):
        return lambda: [minimal(pts[i], uv[i], k, r_prior, c_prior) for i in triples]

    minimal = _row(
        _seconds(solve_all(gauss_newton_p3), 1) / TRIPLES,
        _seconds(solve_all(p3p_pose), 1) / TRIPLES,
        same_pose_within_1mm=f"{sum(g < 1e-3 for g in gaps)}/{TRIPLES}",
        triples_without_pose=none,
        median_centre_error_m={key: round(float(np.median(v)), 2) for key, v in err.items()},
    )
    old = nf.ransac_pnp(pts, uv, k, r_prior, c_prior, minimal=gauss_newton_p3)
    new = nf.ransac_pnp(pts, uv, k, r_prior, c_prior)
    ransac = _row(
        _seconds(lambda: nf.ransac_pnp(pts, uv, k, r_prior, c_prior, minimal=gauss_newton_p3), 1),
        _seconds(lambda: nf.ransac_pnp(pts, uv, k, r_prior, c_prior), 3),
        same_inliers=bool(np.array_equal(old[4], new[4])),
        fixed=bool(old[0] and new[0]),
        centre_gap_m=round(float(np.linalg.norm(old[3] - new[3])), 9) if old[0] and new[0] else None,
        centre_error_m=round(float(np.linalg.norm(new[3] - c_true)), 2) if new[0] else None,
    )
    return {"pnp_minimal": minimal, "pnp_ransac": ransac}


def bench_ncc() -> dict:
    """NCC of a 6 px-radius crater template over a 1024^2 frame, before and after."""
    image = smooth_image((1024, 1024), sigma=2.0).astype(np.float64)
    t = crater_template(0.3, 10.0, 6.0, 0.2)
    diff = float(np.abs(ncc(image, t) - ncc_scipy(image, t)).max())
    return {
        "ncc": _row(_seconds(lambda: ncc_scipy(image, t), 3), _seconds(lambda: ncc(image, t), 3), max_abs_diff=diff)
    }


def bench_crops() -> dict:
    """A rotated 400 px box resampled to 150^2, and a 150^2 crop rolled and shifted, before and after."""
    image = smooth_image((1024, 1024))
    box, angle = (300.3, 310.7, 700.3, 710.7), 30.0
    a, b = resample_box(image, box, 150, angle), resample_box_scipy(image, box, 150, angle)
    crop = resample_box(image, (300.0, 310.0, 450.0, 460.0), 150)
    c, d = rotate_crop(crop, 33.0, (3.0, -2.0)), rotate_crop_scipy(crop, 33.0, (3.0, -2.0))
    return {
        "crop": _row(
            _seconds(lambda: resample_box_scipy(image, box, 150, angle), 50),
            _seconds(lambda: resample_box(image, box, 150, angle), 50),
            max_abs_diff=float(np.abs(a - b).max()),
            value_range=float(np.ptp(b)),
        ),
        "roll": _row(
            _seconds(lambda: rotate_crop_scipy(crop, 33.0, (3.0, -2.0)), 50),
            _seconds(lambda: rotate_crop(crop, 33.0, (3.0, -2.0)), 50),
            max_abs_diff=float(np.abs(c - d).max()),
            value_range=float(np.ptp(d)),
        ),
    }


def bench_nav_windows(every: int = 10) -> dict:
    """``nav-eval``'s template method on every ``every``-th south validation window, once with the former NCC
    and once with OpenCV's per window (alternating, so the machine's load falls on both alike)."""
    nav = compose_nav([], defaults=["nav/detector=template"])
    landmarks, _ = load_default_map("south")
    seconds, rows = {"before": 0.0, "after": 0.0}, {"before": [], "after": []}
    frames = windows("validation", "south")[::every]
    for frame in frames:
        run_frame(frame, landmarks, nav.detector, nav.fix)  # untimed: the mosaic, map and the frame's light cached
        for key, fn in (("before", ncc_scipy), ("after", ncc)):
            template.ncc = fn  # the detector looks its NCC up in its module at each call
            try:
                t0 = time.perf_counter()
                rows[key].append(run_frame(frame, landmarks, nav.detector, nav.fix))
                seconds[key] += time.perf_counter() - t0
            finally:
                template.ncc = ncc

    def outcome(row):  # the error to 1 mm: the two NCCs differ by float rounding (1e-12), not by a pixel
        return (row["fix"], row["reason"], row["n_detections"], round(row.get("error_km") or 0.0, 6))

    same = [outcome(a) == outcome(b) for a, b in zip(rows["before"], rows["after"])]
    return {
        "nav_eval_window": {
            **_row(seconds["before"] / len(frames), seconds["after"] / len(frames)),
            "windows": len(frames),
            "same_fixes": f"{sum(same)}/{len(frames)}",
            "fixes": sum(r["fix"] for r in rows["after"]),
        }
    }


def bench_opencv() -> dict:
    """Every row, with OpenCV's thread count (its filters may run on several)."""
    return {
        "opencv": cv2.__version__,
        "cv2_threads": cv2.getNumThreads(),
        **bench_pnp(),
        **bench_ncc(),
        **bench_crops(),
        **bench_nav_windows(),
    }
