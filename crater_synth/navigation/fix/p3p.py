"""Minimal-set pose hypotheses of the pinhole-pose RANSAC (:func:`.solve.ransac_pnp`): OpenCV's AP3P on
3 correspondences, the solution nearest the prior attitude, and the reprojection inliers of many such poses
at once."""

from __future__ import annotations

import math

import cv2
import numpy as np


def p3p_pose(points, uv, k, r_prior, c_prior):
    """(r_wc, centre) of the camera that sees the 3 ``points`` (3, 3) at pixels ``uv`` (3, 2) with intrinsics
    ``k`` (the convention of :func:`.solve.project_pinhole`): of OpenCV's AP3P poses (up to four, each exact), the
    one whose attitude is nearest ``r_prior``, the pose Gauss-Newton from the prior converges to. The points
    are taken relative to ``c_prior`` (tens of km, not the Moon's radius: the solver's numbers stay small). None when
    the three admit no pose (collinear, or a point repeated)."""
    origin = np.asarray(c_prior, dtype=np.float64)
    obj = np.ascontiguousarray(points - origin, dtype=np.float64)
    img = np.ascontiguousarray(uv, dtype=np.float64)
    try:
        n, rvecs, tvecs = cv2.solveP3P(obj, img, np.asarray(k, dtype=np.float64), None, flags=cv2.SOLVEPNP_AP3P)
    except cv2.error:  # a degenerate triple (e.g. one point twice)
        return None
    prior = np.asarray(r_prior, dtype=np.float64).ravel()
    best, closest, pick = None, -math.inf, 0
    for i in range(n):  # at most four poses: a loop is cheaper than stacking them
        r = cv2.Rodrigues(rvecs[i])[0]
        closeness = r.ravel() @ prior  # trace(r r_prior^T): the largest is the least turn from the prior
        if closeness > closest:  # False for NaN: a non-finite pose never wins
            best, closest, pick = r, closeness, i
    return None if best is None else (best, origin - best.T @ tvecs[pick].ravel())


def pnp_hypotheses(points, uv, k, prior, rng, iterations: int, inlier_px: float, minimal=p3p_pose) -> np.ndarray:
    """Inlier masks (h, n) of the poses ``minimal`` solves from ``iterations`` random triples of
    correspondences (drawn from ``rng`` one triple at a time, in order), from the prior pose ``prior``
    (r_wc, centre); a triple with no pose is left out. The reprojections of every pose are computed at once."""
    triples = [rng.choice(len(points), 3, replace=False) for _ in range(iterations)]
    poses = [p for p in (minimal(points[i], uv[i], k, *prior) for i in triples) if p is not None]
    if not poses:
        return np.zeros((0, len(points)), bool)
    rots = np.stack([r for r, _ in poses])  # (h, 3, 3)
    centres = np.stack([c for _, c in poses])  # (h, 3)
    cam = np.einsum("hij,hnj->hni", rots, points[None, :, :] - centres[:, None, :]) @ np.asarray(k).T
    with np.errstate(divide="ignore", invalid="ignore"):  # a point in the camera's plane: no pixel, no inlier
        err = np.hypot(*np.moveaxis(cam[..., :2] / cam[..., 2:3] - uv[None], -1, 0))
    return err <= inlier_px
