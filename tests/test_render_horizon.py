"""Horizon-map shadows (crater_core.horizon), checked independently of their implementation.

- The solar-disc factor against direct numerical integration over the disc.
- The ``lit`` channel of fast-mode renders of the bowl crater at sun elevations 0.16, 0.64 and 1.6 deg
  against brute-force ray marching over the terrain mesh (bilinear cells, near field then far field,
  scipy's map_coordinates; nothing shared with the implementation): every pixel the march calls
  clearly lit (horizon below the disc's lower limb) or clearly shadowed (horizon above its upper
  limb) must be so in the render, away from class boundaries and the self-shadow terminator. Like
  the renderer (and Cycles' smooth-shaded mesh), terrain closer than
  ``horizon.MIN_OCCLUDER_DISTANCE_SPACINGS`` near-grid spacings is left to the shading normal.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import map_coordinates, spline_filter

from crater_core import exr, geometry, horizon

from helpers import render as cr

SUN_R = math.radians(geometry.SUN_ANGULAR_DIAMETER_DEG / 2)


def test_disc_factor_matches_numerical_integration():
    rng = np.random.default_rng(1)
    n = 400_000  # uniform points on the unit disc
    rad, ang = np.sqrt(rng.random(n)), 2 * np.pi * rng.random(n)
    dy = rad * np.sin(ang) * SUN_R  # offset in elevation (the azimuth offset does not matter)
    for theta_deg, h_deg, tilt in [
        (0.16, 0.0, 0.0),
        (0.3, 0.25, 0.0),
        (0.64, 0.5, 0.3),
        (1.6, 1.7, -0.2),
        (0.2, -0.5, 0.0),
        (0.4, 0.9, 0.0),
    ]:
        theta, h = math.radians(theta_deg), math.radians(h_deg)
        # a surface tilted away from the sun by `tilt` deg: N.l = sin(elevation of l - tilt)
        n_dot_l = np.sin(theta + dy - math.radians(tilt))
        visible = (theta + dy) > h
        mu0 = math.sin(theta - math.radians(tilt))
        expected = np.mean(np.maximum(n_dot_l, 0) * visible) / mu0
        got = float(
            horizon.disc_lit_factor(
                theta, np.float32(h), np.float32(mu0), np.float32(math.cos(theta - math.radians(tilt)))
            )
        )
        assert got == pytest.approx(expected, abs=0.01 + 0.01 * expected), (theta_deg, h_deg, tilt, got, expected)
        frac = float(horizon.disc_fraction_above(theta, np.float32(h)))
        assert frac == pytest.approx(np.mean(visible), abs=0.003)


def test_mean_disc_factor_equals_the_full_formula_everywhere():
    """The penumbra-band shortcut gives the formula's value for every pixel: in the band, at its
    edges (a sub-pixel horizon exactly a solar radius from the Sun) and outside it."""
    rng = np.random.default_rng(2)
    n = 20_000
    theta = np.float32(math.radians(0.64))
    h = (theta + rng.normal(0.0, 3 * SUN_R, (4, n))).astype(np.float32)
    h[:, :50] = theta - np.float32(SUN_R)  # exactly at the lower limb: whole disc visible
    h[:, 50:100] = theta + np.float32(SUN_R)  # exactly at the upper limb: none of it
    h[:2, 100:150] = theta - np.float32(SUN_R)  # mixed sub-pixels
    mu0 = rng.uniform(0.01, 0.3, n).astype(np.float32)
    slope = rng.normal(0.0, 0.5, n).astype(np.float32)
    full = sum(horizon.disc_lit_factor(theta, hk, mu0, slope) for hk in h) / np.float32(4)
    got = horizon.mean_disc_lit_factor(theta, h, mu0, slope)
    assert got.dtype == np.float32 and got.shape == (n,)
    np.testing.assert_allclose(got, full, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(got[:50], 1.0)
    np.testing.assert_allclose(got[50:100], 0.0, atol=1e-7)


def _plain_row_scan(z_occ, z_eye, spacing, k_min):
    """The row scan of the module doc, written plainly: the whole array at once, every eye."""
    rows, n = z_occ.shape
    occ = np.where(np.isnan(z_occ), np.float32(-1e30), z_occ).astype(np.float32)
    eye = np.where(np.isnan(z_eye), np.float32(1e30), z_eye).astype(np.float32)
    best = np.full((rows, n), horizon.NO_OCCLUDER_SLOPE, dtype=np.float32)
    best_t = np.full((rows, n), horizon.NO_OCCLUDER_DISTANCE_M, dtype=np.float32)
    pooled, width, k = occ, 1, k_min
    while k < n:
        while k >= horizon.WINDOW_RATIO * 2 * width and 2 * width < n:
            nxt = pooled.copy()
            nxt[:, :-width] = np.maximum(pooled[:, :-width], pooled[:, width:])
            pooled, width = nxt, 2 * width
        dist = (k + 0.5 * (width - 1)) * spacing
        cand = (pooled[:, k:] - eye[:, :-k]) * np.float32(1.0 / dist)
        better = cand > best[:, :-k]
        best[:, :-k] = np.where(better, cand, best[:, :-k])
        best_t[:, :-k] = np.where(better, np.float32(dist), best_t[:, :-k])
        k += width
    return best, best_t


def test_blocked_row_scan_and_cropped_grid_change_nothing(monkeypatch):
    """The speed-ups of the horizon maps are exact: row blocks and the eyes-only-where-needed scan
    equal the plain scan bit for bit, and maps from the cropped rotated grid equal the full grid's."""
    rng = np.random.default_rng(5)
    z = (rng.normal(0.0, 30.0, (300, 700)).cumsum(axis=1)).astype(np.float32)
    z[:, :15] = np.nan  # no terrain there: never an occluder
    best, dist = horizon._row_horizon_slopes(z, z, 250.0, k_min=2, n_eye=420)
    ref_best, ref_dist = _plain_row_scan(z, z, 250.0, k_min=2)
    np.testing.assert_array_equal(best, ref_best[:, :420])
    np.testing.assert_array_equal(dist, ref_dist[:, :420])

    near = cr.grid(NEAR_HALF, 128, cr.crater_z(CRATER_D), curvature=True)
    far = cr.grid(FAR_HALF, FAR_N, _far_z, curvature=True)
    terrain = horizon.Terrain(near, far, cr.keep_outside(far, NEAR_HALF))
    halves = [0.9 * CRATER_D, 1.8 * CRATER_D]
    cropped = {az: horizon.horizon_maps(terrain, az, halves, 96) for az in (0.0, 37.0, 250.0)}
    monkeypatch.setattr(horizon._RotatedGrid, "crop", lambda self, half_extent: self.na)
    for az, maps in cropped.items():
        np.testing.assert_array_equal(maps, horizon.horizon_maps(terrain, az, halves, 96), err_msg=f"azimuth {az}")


CRATER_D = 10_000.0
NEAR_HALF, NEAR_N = 2.5 * CRATER_D, 256
FAR_HALF, FAR_N = 60_000.0, 61
SUNS = [(0.16, 135.0), (0.64, 300.0), (1.6, 45.0)]
CAMS = [(90.0, 0.0), (62.0, 200.0)]


def _far_z(x, y):
    return 600.0 * np.sin(x / 9000.0) * np.cos(y / 13000.0)


@pytest.fixture(scope="module")
def bowl(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("horizon")
    near = cr.grid(NEAR_HALF, NEAR_N, cr.crater_z(CRATER_D), curvature=True)
    far = cr.grid(FAR_HALF, FAR_N, _far_z, curvature=True)
    npz = cr.write_npz(tmp / "bowl.npz", near, far, cr.keep_outside(far, NEAR_HALF))
    items = cr.crater_items(CRATER_D, SUNS, CAMS, roi_min_px=100)
    job = cr.job(
        npz,
        items,
        tmp / "fast",
        mode="fast",
        diameter_km=CRATER_D / 1000.0,
        samples=8,
        shadow_map_px=384,
        shadow_map_levels=2,
        shadow_map_extent_factor=1.8,
    )
    results, proc = cr.run_worker(job, tmp, "bowl")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert '"fallbacks": 0' in proc.stderr
    return {"items": items, "out": tmp / "fast", "near": near, "far": far}


def _mesh_height(near_coeffs, far, x, y):
    """Height of the vertex grids (rows north -> south; near field: interpolating cubic spline, far
    field: bilinear), near field first, then far field."""

    def index(half, n):
        return [(half - y) / (2 * half) * (n - 1), (x + half) / (2 * half) * (n - 1)]

    z = map_coordinates(far[..., 2].astype(np.float64), index(FAR_HALF, FAR_N), order=1, mode="nearest")
    inside = (np.abs(x) <= NEAR_HALF) & (np.abs(y) <= NEAR_HALF)
    z[inside] = map_coordinates(near_coeffs, index(NEAR_HALF, NEAR_N), order=3, mode="nearest", prefilter=False)[inside]
    z[(np.abs(x) > FAR_HALF) | (np.abs(y) > FAR_HALF)] = -np.inf
    return z


def _marched_horizon(near, far, px, py, azimuth_deg):
    """Horizon elevation (rad) by marching from each point towards the sun azimuth."""
    dx, dy = math.sin(math.radians(azimuth_deg)), math.cos(math.radians(azimuth_deg))
    coeffs = spline_filter(near[..., 2].astype(np.float64), order=3, mode="nearest")
    z0 = _mesh_height(coeffs, far, px, py)
    spacing = 2 * NEAR_HALF / (NEAR_N - 1)
    t_min = max(horizon.MIN_OCCLUDER_DISTANCE_SPACINGS, 0.25) * spacing
    steps = np.concatenate(
        [np.arange(t_min, 3 * NEAR_HALF, spacing / 3), np.arange(3 * NEAR_HALF, 3 * FAR_HALF, 250.0)]
    )
    best = np.full(px.shape, -np.inf)
    for t in steps:
        best = np.maximum(best, (_mesh_height(coeffs, far, px + t * dx, py + t * dy) - z0) / t)
    return np.arctan(best)


@pytest.mark.integration
def test_lit_mask_matches_brute_force_ray_marching(bowl):
    for it in bowl["items"]:
        img = exr.read_exr(str(bowl["out"] / it["rel_path"]))[0]
        pose, ray = cr.centre_rays(it)
        p = pose.position + img["depth"][..., None] * ray  # ray . forward == 1
        theta = math.radians(it["sun_elevation"])
        h = _marched_horizon(bowl["near"], bowl["far"], p[..., 0], p[..., 1], it["sun_azimuth"])
        to_sun = geometry.direction_from_elevation_azimuth(it["sun_elevation"], it["sun_azimuth"])
        mu0 = np.stack([img["N.X"], img["N.Y"], img["N.Z"]], -1) @ to_sun
        margin = math.radians(0.03)
        cls = np.where(h < theta - SUN_R - margin, 1, np.where(h > theta + SUN_R + margin, 0, -1))
        # away from class boundaries (a pixel's mean surface point is not its centre ray's) and from
        # the self-shadow terminator
        pad = np.pad(cls, 1, mode="edge")
        same = np.ones(cls.shape, bool)
        for di in (0, 1, 2):
            for dj in (0, 1, 2):
                same &= pad[di : di + cls.shape[0], dj : dj + cls.shape[1]] == cls
        check = same & (cls >= 0) & (mu0 > 0.03)
        lit = img["lit"]
        tag = f"sun {it['sun_elevation']}/{it['sun_azimuth']} cam {it['cam_elevation']}/{it['cam_azimuth']}"
        n_lit, n_dark = int((check & (cls == 1)).sum()), int((check & (cls == 0)).sum())
        assert n_lit > 500, (tag, n_lit)
        if it["sun_elevation"] < 1.0:
            assert n_dark > 500, (tag, n_dark)  # the low suns shadow part of the bowl
        wrong = (check & (cls == 1) & (lit < 0.9)) | (check & (cls == 0) & (lit > 0.1))
        assert wrong.sum() <= 0.005 * check.sum(), (tag, int(wrong.sum()), int(check.sum()))
