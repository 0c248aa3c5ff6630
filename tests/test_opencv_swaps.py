"""OpenCV's solvers agree with the hand-written code they replaced (kept as references in
crater_synth/bench/opencv.py), on the same inputs, within the stated tolerances:

- PnP: each AP3P hypothesis is the pose Gauss-Newton from the prior reaches (within 1 mm, where both reach
  one), and the robust fix picks the same inliers and the same pose (the refinement is the project's);
- NCC: to 1e-9 everywhere, borders included (the same zero-padded correlation, reflected mean and energy);
- crops: bilinear warps within OpenCV's coordinate rounding (1/32 px: at most 1/64 px times the sum of the
  input's largest steps along each axis); nearest and cubic-spline crops unchanged; the anti-aliasing Gaussian
  to float32 noise; the crop cache key names the resampler.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from crater_synth.bench.opencv import (
    gauss_newton_p3,
    ncc_scipy,
    pnp_problem,
    resample_affine_scipy,
    resample_box_scipy,
    rotate_crop_scipy,
    smooth_image,
)
from crater_synth.navigation.detectors.template import crater_template, ncc
from crater_synth.navigation.fix import pose as pm
from crater_synth.navigation.fix import solve as nf
from crater_synth.navigation.fix.p3p import p3p_pose
from train.preprocess import PreprocessConfig, box_axes, resample_affine, resample_box, rotate_crop


def rounding_bound(y: np.ndarray) -> float:
    """The largest change 1/64 px of coordinate rounding makes to a bilinear sample of ``y`` (+ float32 noise)."""
    y = np.asarray(y, dtype=np.float64)
    steps = np.abs(np.diff(y, axis=-1)).max() + np.abs(np.diff(y, axis=-2)).max()
    return steps / 64.0 + 1e-6


def test_ap3p_hypotheses_are_the_gauss_newton_poses():
    pts, uv, k, _, _, r_prior, c_prior = pnp_problem(seed=11, wrong=0)
    rng = np.random.default_rng(1)
    agree = 0
    for _ in range(60):
        i = rng.choice(len(pts), 3, replace=False)
        new, old = p3p_pose(pts[i], uv[i], k, r_prior, c_prior), gauss_newton_p3(pts[i], uv[i], k, r_prior, c_prior)
        if new is None:  # the pixels' noise leaves no exact pose: Gauss-Newton's last step is no pose either
            assert np.abs(pm.project_pinhole(pts[i], *old, k) - uv[i]).max() > 1e-3
            continue
        assert np.abs(pm.project_pinhole(pts[i], *new, k) - uv[i]).max() < 1e-6  # exact
        agree += np.linalg.norm(new[1] - old[1]) < 1e-3 and pm.attitude_difference_deg(new[0], old[0]) < 1e-4
    assert agree >= 50  # 53 of 59: on the rest Gauss-Newton ends on another of the triple's poses, or diverges


def test_ap3p_refuses_a_degenerate_triple():
    pts, uv, k, _, _, r_prior, c_prior = pnp_problem()
    same = [0, 0, 1]
    assert p3p_pose(pts[same], uv[same], k, r_prior, c_prior) is None


@pytest.mark.parametrize("seed", [3, 4, 5, 6])
def test_ransac_pnp_fixes_alike_with_either_minimal_solver(seed):
    """12 landmarks, 4 wrongly identified: the same inliers, the same pose to 1 mm and 1e-4 deg (the
    angle's own acos rounding is ~2e-6 deg)."""
    pts, uv, k, _, c_true, r_prior, c_prior = pnp_problem(seed=seed)
    pairs = np.column_stack([np.arange(len(pts)), np.arange(len(pts))])
    for params in (nf.FixParams(), dataclasses.replace(nf.FixParams(), min_inliers=4, iterations=60)):
        old = nf.ransac_pnp(pts, uv, k, r_prior, c_prior, params, pairs=pairs, minimal=gauss_newton_p3)
        new = nf.ransac_pnp(pts, uv, k, r_prior, c_prior, params, pairs=pairs)
        assert old[0] == new[0] and old[1] == new[1] and np.array_equal(old[4], new[4])
        if new[0]:
            assert not new[4][:4].any() and np.linalg.norm(new[3] - old[3]) < 1e-3
            assert pm.attitude_difference_deg(new[2], old[2]) < 1e-4
            assert np.linalg.norm(new[3] - c_true) < 500.0


@pytest.mark.parametrize("radius", [4.5, 6.0, 8.9])
def test_ncc_matches_the_scipy_version_everywhere(radius):
    image = smooth_image((300, 260), seed=2, sigma=2.0).astype(np.float64) + 3.0  # a mean well above the scatter
    image[:40, :50] = 3.0  # a flat patch: 0 there in both
    t = crater_template(0.7, 10.0, radius, 0.2)
    new, old = ncc(image, t), ncc_scipy(image, t)
    assert new.shape == image.shape
    np.testing.assert_allclose(new, old, rtol=0, atol=1e-9)
    assert np.all(new[:5, :5] == 0.0)


@pytest.mark.parametrize("side, rotation", [(80.0, 10.0), (150.0, 0.0), (150.0, 30.0), (400.0, 30.0), (1200.0, 75.0)])
def test_bilinear_crops_match_the_scipy_version_within_the_rounding(side, rotation):
    image = smooth_image((1024, 1024))
    box = (300.3, 310.7, 300.3 + side, 310.7 + side)
    new, old = resample_box(image, box, 150, rotation), resample_box_scipy(image, box, 150, rotation)
    assert new.dtype == np.float32 and new.shape == (150, 150)
    assert np.abs(new - old).max() <= rounding_bound(image)


def test_crops_at_the_image_edge_and_other_orders():
    image = smooth_image((400, 400), seed=1)
    edge = (-5.0, -5.0, 200.0, 200.0)  # leaves the image: edge values outside
    assert np.abs(resample_box(image, edge, 150, 20.0) - resample_box_scipy(image, edge, 150, 20.0)).max() <= (
        rounding_bound(image)
    )
    axes = box_axes(300.0, 300.0, 40.0)
    for order in (0, 3):  # scipy's, as before; the anti-aliasing Gaussian differs by float32 noise only
        new = resample_affine(image, (200.0, 190.0), axes, 150, True, order)
        np.testing.assert_allclose(new, resample_affine_scipy(image, (200.0, 190.0), axes, 150, True, order), atol=1e-6)


@pytest.mark.parametrize(
    "angle, shift", [(0.0, (0.0, 0.0)), (33.0, (3.0, -2.0)), (90.0, (0.0, 0.0)), (217.5, (-4.5, 1.25))]
)
def test_rolls_match_the_scipy_version_within_the_rounding(angle, shift):
    crop = resample_box(smooth_image((400, 400), seed=4), (100.0, 110.0, 250.0, 260.0), 150)
    new, old = rotate_crop(crop, angle, shift), rotate_crop_scipy(crop, angle, shift)
    assert np.abs(new - old).max() <= rounding_bound(crop)
    stack = np.stack([crop, 2.0 * crop])  # a stack is turned crop by crop, alike
    np.testing.assert_array_equal(rotate_crop(stack, angle, shift)[1], rotate_crop(2.0 * crop, angle, shift))
    if angle == 0.0 and shift == (0.0, 0.0):
        np.testing.assert_array_equal(new, crop)  # no turn: the crop itself, to the bit
    if math.isclose(angle % 90.0, 0.0) and shift == (0.0, 0.0):
        np.testing.assert_allclose(new, np.rot90(crop, round(angle / 90.0)), atol=1e-6)


def test_the_crop_cache_key_names_the_resampler():
    assert PreprocessConfig().geometry_key()["resampler"] == "cv2.warpAffine"
    assert PreprocessConfig(interp_order=3).geometry_key()["resampler"] == "scipy.ndimage"
