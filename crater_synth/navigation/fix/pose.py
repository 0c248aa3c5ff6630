"""Pinhole camera maths of the perspective fixes (:mod:`.solve`): projection, rotations, the Gauss-Newton
pose and its uncertainty, the maximum a posteriori pose given a measured attitude, and the known-attitude
camera centre. numpy only; conventions of :func:`project_pinhole` (world -> camera rotation, camera +z
forward, +x right, +y down)."""

from __future__ import annotations

import math

import numpy as np


def rodrigues(w: np.ndarray) -> np.ndarray:
    """The rotation matrix of the rotation vector ``w`` (axis times angle, radians)."""
    t = float(np.linalg.norm(w))
    if t < 1e-12:
        return np.eye(3)
    k = w / t
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(t) * kx + (1 - math.cos(t)) * kx @ kx


def project_pinhole(points: np.ndarray, r_wc: np.ndarray, c: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Pixels (u right, v down) of world points for a camera at ``c`` whose world->camera rotation is
    ``r_wc`` (camera +z forward, +x right, +y down: the computer-vision convention) and intrinsics ``k``."""
    pc = (np.asarray(points, float) - c) @ r_wc.T
    uvw = pc @ k.T
    return uvw[:, :2] / uvw[:, 2:3]


def _pose_jacobian(points, uv, k, r, c, scale: float):
    """(residuals (2n,), their Jacobian (2n, 6)) of the reprojection of ``points`` at pose (r, c) against
    ``uv``, by forward differences in (rotation increment, camera centre / ``scale``)."""
    res = (project_pinhole(points, r, c, k) - uv).ravel()
    jac = np.empty((res.size, 6))
    eps = 1e-6
    for q in range(6):
        dw = np.zeros(3)
        dc = np.zeros(3)
        if q < 3:
            dw[q] = eps
        else:
            dc[q - 3] = eps * scale
        rp = rodrigues(dw) @ r
        jac[:, q] = ((project_pinhole(points, rp, c + dc, k) - uv).ravel() - res) / eps
    return res, jac


def pose_sigma_horizontal_m(points, uv, k, r, c, attitude_sigma_rad: float = 0.0) -> float:
    """1-sigma horizontal (first two axes) uncertainty (m) of the camera centre of pose (r, c) fitted to
    >= 4 ``points`` at pixels ``uv``: the least-squares covariance sigma^2 (J^T J)^-1, sigma the residuals'
    own scatter with the fit's 6 unknowns taken off (sum of squares / (2n - 6)). Large where a tilt and a
    shift of the camera explain the pixels nearly alike (a few landmarks, seen near nadir, or a narrow
    field). ``attitude_sigma_rad`` > 0: the attitude also measured to that 1-sigma (a star tracker), its
    information added to the pixels'."""
    return _sigma_horizontal_m(points, uv, k, r, c, attitude_held=False, attitude_sigma_rad=attitude_sigma_rad)


def position_sigma_horizontal_m(points, uv, k, r, c) -> float:
    """1-sigma horizontal (first two axes) uncertainty (m) of the known-attitude camera centre ``c`` fitted
    to >= 3 ``points`` at pixels ``uv``: :func:`pose_sigma_horizontal_m`'s covariance with the attitude
    held (the centre's 3 unknowns taken off the residuals' degrees of freedom). It measures how well the
    landmarks agree with each other, not an error they share (a DEM or attitude bias moves them alike)."""
    return _sigma_horizontal_m(points, uv, k, r, c, attitude_held=True)


def _sigma_horizontal_m(points, uv, k, r, c, attitude_held: bool, attitude_sigma_rad: float = 0.0) -> float:
    """The least-squares 1-sigma horizontal uncertainty (m) of the camera centre, sigma^2 (J^T J)^-1 with sigma
    from the residuals less the unknowns (6, or the centre's 3 with the attitude held); with a measured
    attitude (``attitude_sigma_rad`` > 0), (J^T J / sigma^2 + diag(1 / attitude_sigma^2, 0))^-1."""
    points, uv = np.asarray(points, float), np.asarray(uv, float)
    scale = max(float(np.linalg.norm(points - c, axis=1).mean()), 1.0)
    res, jac = _pose_jacobian(points, uv, k, r, c, scale)
    if attitude_held:
        jac = jac[:, 3:]
    unknowns = jac.shape[1]
    sigma2 = float(res @ res) / max(res.size - unknowns, 1)
    if attitude_sigma_rad > 0.0 and not attitude_held:
        prior = np.diag([attitude_sigma_rad**-2] * 3 + [0.0] * 3)
        cov = np.linalg.pinv(jac.T @ jac / max(sigma2, 1e-300) + prior)
    else:
        cov = np.linalg.pinv(jac.T @ jac) * sigma2
    x = unknowns - 3  # the centre's first axis among the unknowns
    return float(math.sqrt(max(cov[x, x] + cov[x + 1, x + 1], 0.0))) * scale


def rotation_vector(r: np.ndarray) -> np.ndarray:
    """The rotation vector (axis times angle, radians) of the rotation matrix ``r`` (:func:`rodrigues`' inverse,
    for angles below pi)."""
    r = np.asarray(r, float)
    vee = 0.5 * np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    s = float(np.linalg.norm(vee))
    angle = math.atan2(s, 0.5 * (float(np.trace(r)) - 1.0))
    return vee * (angle / s) if s > 1e-12 else vee


def refine_pose(points, uv, k, r0, c0, iterations: int = 20, attitude_prior=None):
    """Gauss-Newton on (rotation increment, camera centre) minimising reprojection error from (r0, c0).
    ``attitude_prior`` (r_prior, weight px per radian): the rotation's angle from ``r_prior`` counts in the
    least squares as that many pixels of residual per radian (a pose with a Gaussian attitude prior)."""
    r, c = np.array(r0, float), np.array(c0, float)
    scale = max(float(np.linalg.norm(np.asarray(points) - c, axis=1).mean()), 1.0)
    for _ in range(iterations):
        res, jac = _pose_jacobian(points, uv, k, r, c, scale)
        if attitude_prior is not None:  # d rotvec(exp(dw) r r_prior^T) / d dw is ~ the identity for small angles
            r_prior, weight = attitude_prior
            res = np.concatenate([res, weight * rotation_vector(r @ np.asarray(r_prior, float).T)])
            jac = np.vstack([jac, np.hstack([weight * np.eye(3), np.zeros((3, 3))])])
        step, *_ = np.linalg.lstsq(jac, -res, rcond=None)
        r = rodrigues(step[:3]) @ r
        c = c + step[3:] * scale
        if np.linalg.norm(step) < 1e-10:
            break
    return r, c


# The pixels' scatter a measured attitude is weighed against is estimated from a 6-DOF fit's residuals; with
# 4-5 landmarks a near-exact fit would make it ~0 and the attitude weightless: a tenth of a pixel is the floor
# (a stated assumption, not tuned).
PNP_MIN_SIGMA_PX = 0.1


def pose_with_attitude(points, uv, k, r, c, r_measured, attitude_sigma_rad: float):
    """The pose (r, c), fitted to ``points`` at ``uv``, fitted again as the maximum a posteriori pose given
    a measured attitude ``r_measured`` of 1-sigma ``attitude_sigma_rad``: :func:`refine_pose`'s attitude
    prior, weighted against the pixels' own scatter in the first fit (no less than :data:`PNP_MIN_SIGMA_PX`)."""
    res = (project_pinhole(points, r, c, k) - uv).ravel()
    sigma_px = max(math.sqrt(float(res @ res) / max(res.size - 6, 1)), PNP_MIN_SIGMA_PX)
    return refine_pose(points, uv, k, r, c, attitude_prior=(r_measured, sigma_px / attitude_sigma_rad))


def attitude_difference_deg(r_a: np.ndarray, r_b: np.ndarray) -> float:
    """Angle (deg) of the rotation taking the world->camera rotation ``r_a`` to ``r_b``."""
    cos = (float(np.trace(np.asarray(r_a) @ np.asarray(r_b).T)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def solve_position(points, uv, k, r_wc) -> np.ndarray:
    """Camera centre (least squares, linear) from >= 2 landmark ``points`` (n, 3) seen at pixels ``uv``
    (n, 2) by a camera of known world->camera rotation ``r_wc`` (convention of :func:`project_pinhole`)
    and intrinsics ``k``: each pixel's ray through the centre must pass through its point, so
    sum_i (I - d_i d_i^T)(c - P_i) = 0 with d_i the ray's world direction."""
    points, uv = np.asarray(points, float), np.asarray(uv, float)
    rays = np.linalg.solve(k, np.column_stack([uv, np.ones(len(uv))]).T).T @ r_wc  # world directions
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    proj = np.eye(3)[None, :, :] - rays[:, :, None] * rays[:, None, :]
    return np.linalg.solve(proj.sum(axis=0), np.einsum("nij,nj->i", proj, points))
