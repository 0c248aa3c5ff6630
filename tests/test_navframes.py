"""Navigation frames: trajectory pose maths, explicit-pose frame renders and their landmark labels."""

from __future__ import annotations

import dataclasses
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from crater_core import exr, geometry, schema
from crater_core.trajectory import TrajectoryError, footprint_half_width_m, frame_poses

from helpers import render as cr
from helpers.cli import run_cli, run_nav_frames


def _traj(**kw):
    base = dict(
        name="t",
        start=(-85.0, 30.0),
        end=(-85.0, 30.0),
        altitude_km=(100.0, 100.0),
        frames=1,
        off_nadir_deg=0.0,
        off_nadir_azimuth_deg=0.0,
        fov_deg=40.0,
        width_px=96,
        sun="explicit",
        subsolar_lat_deg=0.0,
        subsolar_lon_deg=0.0,
        sun_elevation_deg=10.0,
        sun_azimuth_deg=90.0,
    )
    base.update(kw)
    return SimpleNamespace(**base)


def test_nadir_camera_looks_at_its_ground_point_and_footprint_matches_altitude():
    (p,) = frame_poses(_traj())
    assert p.target_lat == pytest.approx(-85.0, abs=1e-9) and p.target_lon == pytest.approx(30.0, abs=1e-9)
    cam = p.pose_enu(p.target_lat, p.target_lon)
    assert np.allclose(cam.position, [0.0, 0.0, 100e3], atol=1e-6)
    (u, v), depth = geometry.project_points(np.zeros(3), cam, 96)
    assert (u, v) == pytest.approx((48.0, 48.0), abs=1e-9) and depth == pytest.approx(100e3)
    # Flat-ground footprint alt * tan(fov / 2); the sphere falls away under the corners (a little more).
    flat = 100e3 * math.tan(math.radians(20.0))
    assert flat < footprint_half_width_m(p) < 1.01 * flat
    assert p.ground_sample_m() == pytest.approx(100e3 / cam.focal_px(96))
    # Explicit Sun: (elevation, azimuth) above the frame's target.
    assert p.sun_enu(p.target_lat, p.target_lon) == pytest.approx((10.0, 90.0))


def test_track_heading_tilt_and_image_up():
    poses = frame_poses(_traj(start=(-80.0, 0.0), end=(-85.0, 0.0), frames=3, altitude_km=(150.0, 50.0)))
    assert [p.altitude_m for p in poses] == pytest.approx([150e3, 100e3, 50e3])
    assert [p.subcam_lat for p in poses] == pytest.approx([-80.0, -82.5, -85.0])
    assert [p.heading_deg for p in poses] == pytest.approx([180.0] * 3)  # flying south along 0 E
    # Tilted 20 deg to the right of the track (west when flying south): the target moves ~alt tan 20 west.
    (q,) = frame_poses(_traj(off_nadir_deg=20.0, off_nadir_azimuth_deg=90.0, altitude_km=(50.0, 50.0)))
    sub = geometry.latlon_to_mc(q.subcam_lat, q.subcam_lon)
    e, n, _ = geometry.mc_to_enu(geometry.latlon_to_mc(q.target_lat, q.target_lon), q.subcam_lat, q.subcam_lon)
    assert np.hypot(e, n) == pytest.approx(50e3 * math.tan(math.radians(20.0)), rel=0.01)
    assert e > 0 and abs(n) < 1e-6 * 50e3  # flying north (a single point travels north): right is east
    cam = q.pose_enu(q.target_lat, q.target_lon)
    (u, v), _ = geometry.project_points(np.zeros(3), cam, 96)
    assert (u, v) == pytest.approx((48.0, 48.0), abs=1e-6)  # the boresight's ground point is the frame centre
    ahead = geometry.mc_to_enu(geometry.latlon_to_mc(q.target_lat + 0.05, q.target_lon), q.target_lat, q.target_lon)
    (u2, v2), _ = geometry.project_points(ahead, cam, 96)
    assert v2 < 48.0  # image up is the direction of flight (north here)
    assert np.linalg.norm(sub) > 0


def test_project_circle_vertical_normal_is_the_horizontal_circle():
    cam = geometry.look_at_camera(60.0, 30.0, 20e3, 50.0)
    a = geometry.project_horizontal_circle([300.0, -200.0, 50.0], 2e3, cam, 200)
    b = geometry.project_circle([300.0, -200.0, 50.0], [0.0, 0.0, 1.0], 2e3, cam, 200)
    assert a == b
    # A circle facing the camera head-on images as a circle.
    n = -cam.forward
    c = geometry.project_circle(np.zeros(3), n, 2e3, cam, 200)
    assert c.a == pytest.approx(c.b, rel=1e-9)


def test_position_fix_with_known_attitude_is_exact_and_robust():
    from crater_synth.navigation.fix.pose import project_pinhole
    from crater_synth.navigation.fix.solve import FixParams, ransac_position

    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-60e3, 60e3, (12, 2)), rng.uniform(-2e3, 2e3, 12)])
    c = np.array([3e3, -2e3, 120e3])
    r_wc = np.diag([1.0, -1.0, -1.0])  # nadir: camera +z down
    k = np.array([[400.0, 0, 256], [0, 400.0, 256], [0, 0, 1]])
    uv = project_pinhole(pts, r_wc, c, k)
    uv[:3] += 40.0  # three wrong identifications
    ok, reason, c_fix, inl = ransac_position(pts, uv, k, r_wc, FixParams(), inlier_px=2.0)
    assert ok and np.linalg.norm(c_fix - c) < 1e-3 and inl.tolist() == [False] * 3 + [True] * 9, reason
    ok, reason, *_ = ransac_position(pts[:4], uv[:4], k, r_wc, FixParams(), inlier_px=2.0)
    assert not ok and "need 5" in reason


def test_known_attitude_fix_sigma_follows_its_scatter_under_pixel_noise():
    """position_sigma_horizontal_m: the fit's own covariance; with Gaussian pixel noise it is the
    horizontal error's spread (Monte Carlo of the same least-squares solve)."""
    from crater_synth.navigation.fix.pose import position_sigma_horizontal_m, project_pinhole, solve_position

    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-40e3, 40e3, (6, 2)), rng.uniform(-2e3, 2e3, 6)])
    c = np.array([1e3, 2e3, 100e3])
    r_wc = np.diag([1.0, -1.0, -1.0])
    k = np.array([[400.0, 0, 256], [0, 400.0, 256], [0, 0, 1]])
    exact = project_pinhole(pts, r_wc, c, k)
    errors, sigmas = [], []
    for _ in range(300):
        uv = exact + rng.normal(0.0, 0.5, exact.shape)
        c_fix = solve_position(pts, uv, k, r_wc)
        errors.append(np.hypot(*(c_fix - c)[:2]))
        sigmas.append(position_sigma_horizontal_m(pts, uv, k, r_wc, c_fix))
    rms = float(np.sqrt(np.mean(np.square(errors))))
    assert 0.8 < float(np.median(sigmas)) / rms < 1.25, (np.median(sigmas), rms)
    assert position_sigma_horizontal_m(pts, exact, k, r_wc, c) < 1e-3  # exact pixels: no scatter


def test_position_hypotheses_leave_out_degenerate_pairs_and_centres_behind():
    """All pairs are solved at once: a pair whose two pixels coincide (one detection twice) or whose centre
    has a landmark behind the camera gives no hypothesis; every other pair of true correspondences gives
    the true centre, so all its points are inliers."""
    from crater_synth.navigation.fix.pose import project_pinhole
    from crater_synth.navigation.fix.solve import position_hypotheses

    r_wc = np.diag([1.0, -1.0, -1.0])  # nadir
    k = np.array([[400.0, 0, 256], [0, 400.0, 256], [0, 0, 1]])
    c = np.array([1e3, 2e3, 100e3])
    pts = np.array([[-30e3, 20e3, 0.0], [25e3, 15e3, 500.0], [5e3, -30e3, -300.0], [5e3, -30e3, -300.0]])
    uv = project_pinhole(pts, r_wc, c, k)  # the last two: one landmark paired twice
    masks = position_hypotheses(pts, uv, k, r_wc, np.random.default_rng(0), 60, 1.0)
    assert 0 < len(masks) < 60 and masks.all()  # the (2, 3) pairs left out, every other one exact
    behind = 2.0 * c - pts  # on the same lines through the camera, but above it: behind a nadir camera
    assert len(position_hypotheses(behind, uv, k, r_wc, np.random.default_rng(0), 60, 1.0)) == 0


def test_position_fix_refuses_an_ambiguous_set():
    """Two disjoint landmark sets (a pattern and its shifted copy) explain the same detections from two
    camera positions: with the (detection, landmark) ids the known-attitude fix answers "ambiguous";
    the true set alone fixes exactly."""
    from crater_synth.navigation.fix.pose import project_pinhole
    from crater_synth.navigation.fix.solve import FixParams, ransac_position

    r_wc = np.diag([1.0, -1.0, -1.0])  # nadir
    k = np.array([[400.0, 0, 256], [0, 400.0, 256], [0, 0, 1]])
    c = np.array([0.0, 0.0, 100e3])
    a = np.array([[-30e3, 20e3, 0.0], [25e3, 15e3, 500.0], [5e3, -30e3, -300.0], [-10e3, -5e3, 200.0]])
    b = a + np.array([18e3, -7e3, 0.0])  # the same pattern elsewhere: seen from c + shift it looks identical
    uv = project_pinhole(a, r_wc, c, k)
    points = np.vstack([a, b])
    pix = np.vstack([uv, uv])
    pairs = np.array([[i, i] for i in range(4)] + [[i, 4 + i] for i in range(4)])
    params = FixParams(min_inliers=3)
    ok, reason, _, _ = ransac_position(points, pix, k, r_wc, params, 3.0, pairs=pairs)
    assert not ok and reason.startswith("ambiguous"), reason
    # Without the ids no rival is seen: one of the two positions is answered (the test is what refuses).
    ok, _, c_fix, _ = ransac_position(points, pix, k, r_wc, params, 3.0)
    assert ok and min(np.linalg.norm(c_fix - c), np.linalg.norm(c_fix - c - [18e3, -7e3, 0.0])) < 1.0
    ok, reason, c_fix, inl = ransac_position(a, uv, k, r_wc, params, 3.0, pairs=pairs[:4])
    assert ok and np.linalg.norm(c_fix - c) < 1e-3 and inl.all(), reason


def test_map_scales_follow_the_ground_sample_and_the_predicted_landmarks():
    from crater_synth.navigation.detectors.classical import ClassicalSettings
    from crater_synth.navigation.fix.solve import FixParams
    from crater_synth.navigation.rendered.evaluate import map_scales

    fp = FixParams()  # 10 km landmarks, radius ratio 1.3
    d = map_scales(ClassicalSettings(), fp, 338.0, [20.0, 60.0])
    assert d.min_radius_px == pytest.approx(5000.0 / 338.0 / 1.3) and d.max_radius_px == pytest.approx(60.0 * 1.3)
    # Lower down the same landmarks are bigger in pixels; with none predicted the smallest landmark's radius.
    d = map_scales(ClassicalSettings(), fp, 100.0, [])
    assert d.min_radius_px == pytest.approx(50.0 / 1.3) and d.max_radius_px > d.min_radius_px


@pytest.mark.parametrize("theta_deg", [30.0, 200.0])
def test_synthetic_preset_finds_map_sized_craters_among_detail_craters(theta_deg):
    """The nav-frames-eval "synthetic" detector on a Hapke-shaded crater field at a rendered frame's
    scale (338 m/px, Sun 7 degrees): the five map-sized craters (D 11-26 km) among ~50 detail craters of
    D 3.4-6 km are found (centre within 0.25 D, radius within 25 %), with fewer detections than the
    real-window settings (which search every scale) and none far below the map's smallest radius."""
    from crater_synth.navigation.detectors.classical import detect
    from crater_synth.navigation.detectors.template import crater_heights, shade_heights
    from crater_synth.navigation.rendered import evaluate as fe
    from crater_synth.navigation.settings import compose_nav

    gsd, n = 338.0, 384
    big = [(100.0, 110.0, 17.0), (300.0, 90.0, 24.0), (200.0, 250.0, 38.0), (330.0, 320.0, 21.0), (90.0, 330.0, 29.0)]
    rng = np.random.default_rng(3)
    small = [
        (u, v, r)
        for u, v, r in zip(rng.uniform(10, 374, 80), rng.uniform(10, 374, 80), rng.uniform(5.0, 9.0, 80))
        if all(math.hypot(u - bu, v - bv) > 1.6 * br + 2 * r for bu, bv, br in big)
    ]
    assert len(small) > 40
    vv, uu = np.mgrid[0:n, 0:n] + 0.5
    z = sum(crater_heights(np.hypot(uu - cu, vv - cv) / r, 0.2) * r for cu, cv, r in big + small)
    theta = math.radians(theta_deg)
    img = shade_heights(z, theta, 7.0) * 200.0 + 20.0 + np.random.default_rng(0).normal(0.0, 2.0, (n, n))
    labels = [{"ellipse": {"cu": u, "cv": v, "a": r}} for u, v, r in big]
    nav = compose_nav(["nav/preset=synthetic"])
    assert nav.frames.scales_from_map
    dp = fe.map_scales(nav.detector, nav.fix, gsd, [r for *_, r in big])
    dets, _ = detect(img, dp, light_dir=theta)
    assert len(fe.match_pixels(dets, labels)) >= 4
    assert min(d.r for d in dets) >= 0.6 * dp.min_radius_px  # the rim fit may shrink a circle to 0.6 r
    every_scale, _ = detect(img, compose_nav(["nav/preset=real-window"]).detector, light_dir=theta)
    assert len(dets) < len(every_scale)


def test_bad_trajectories_give_one_clear_error():
    with pytest.raises(TrajectoryError, match="beyond the horizon"):
        frame_poses(_traj(fov_deg=120.0, off_nadir_deg=50.0, altitude_km=(300.0, 300.0)))
    with pytest.raises(TrajectoryError, match="antipodal"):
        frame_poses(_traj(start=(-10.0, 0.0), end=(10.0, 180.0), frames=2))
    proc = run_cli("nav-frames", "trajectory=descent_ridge", "trajectory.fov_deg=0", timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "trajectory.fov_deg" in lines[0], proc.stderr
    proc = run_cli("nav-frames", timeout=120)
    assert proc.returncode == 2 and "trajectory=NAME" in proc.stderr.strip().splitlines()[-1], proc.stderr


def test_frame_outside_the_dem_is_one_error_and_no_output(tmp_path):
    out = tmp_path / "frames"
    proc = run_cli(
        "nav-frames",
        "trajectory=descent_ridge",
        "trajectory.start=[-40,0]",
        "trajectory.end=[-41,0]",
        f"data_dir={tmp_path / 'data'}",
        "--out",
        out,
        timeout=120,
    )
    assert proc.returncode == 2
    (line,) = proc.stderr.strip().splitlines()
    assert "trajectory=descent_ridge frames 0-" in line and "outside DEM" in line  # the first shared patch
    assert not out.exists()


def _landmark(lat, lon, height, d_km):
    from crater_synth.navigation.map.landmarks import Landmark

    return Landmark(
        id="syn-1",
        name="synthetic",
        lat=float(lat),
        lon=float(lon),
        x_m=0.0,
        y_m=0.0,
        diameter_km=d_km,
        depth_m=0.2 * d_km * 1e3,
        rim_height_m=float(height),
        spill_depth_m=0.0,
        rim_inlier_share=1.0,
        source="test",
    )


def test_frame_render_labels_a_known_synthetic_crater(tmp_path):
    """An explicit-pose frame of a bowl crater placed off-centre: its label sits where the depth and lit
    channels show the crater, and the labelled lit-rim fraction is what the lit channel says."""
    from crater_synth.navigation.rendered.frames import worker_item
    from crater_synth.navigation.rendered.labels import landmarks_in_view

    (p,) = frame_poses(
        _traj(altitude_km=(30.0, 30.0), off_nadir_deg=10.0, off_nadir_azimuth_deg=45.0, sun_elevation_deg=25.0)
    )
    lat0, lon0 = p.target_lat, p.target_lon
    d_m, x0, y0 = 8000.0, 4000.0, -3000.0
    bowl = cr.crater_z(d_m)
    half = 1.2 * footprint_half_width_m(p)
    near = cr.grid(half, 161, lambda x, y: bowl(x - x0, y - y0), curvature=True)
    npz = cr.write_npz(tmp_path / "t.npz", near)
    item = worker_item(p, lat0, lon0, seed=3, header={"test": "navframe"})
    job = cr.job(npz, [item], tmp_path / "out", mode="direct", diameter_km=d_m / 1e3, samples=1)
    results, proc = cr.run_worker(job, tmp_path, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    ch, _ = exr.read_exr(tmp_path / "out" / item["rel_path"])
    assert ch["IF"].shape == (96, 96)
    rim_mc = geometry.enu_to_mc(np.array([x0, y0, 0.04 * d_m]), lat0, lon0)
    lat, lon, h = geometry.mc_to_latlon(rim_mc)
    labels = landmarks_in_view(p, [_landmark(lat, lon, h, d_m / 1e3)], lat0, lon0, ch["lit"], ch["depth"])
    assert len(labels) == 1
    # the label is the manifest schema's, field for field (what `crater-synth export` writes as columns)
    assert list(labels[0]) == [name for name, _ in schema.NAVFRAME_LANDMARK_FIELDS]
    assert tuple(labels[0]["ellipse"]) == schema.NAVFRAME_ELLIPSE_FIELDS
    assert labels[0]["occluded_rim_fraction"] == 0.0  # nothing stands between the camera and the rim
    e = labels[0]["ellipse"]
    assert (e["cu"], e["cv"]) != pytest.approx((48.0, 48.0), abs=5.0)  # off-centre, truly
    # The depth channel, back-projected to the ground: its lowest point (the crater floor) lies inside the
    # labelled rim, near its centre.
    uu, vv = np.meshgrid(np.arange(96) + 0.5, np.arange(96) + 0.5)
    ground = geometry.back_project_pixels(np.stack([uu, vv], -1), ch["depth"], p.pose_enu(lat0, lon0), 96)
    height = ground[..., 2] + geometry.curvature_drop_m(np.hypot(ground[..., 0], ground[..., 1]))
    iv, iu = np.unravel_index(np.argmin(height), height.shape)
    assert math.hypot(iu + 0.5 - e["cu"], iv + 0.5 - e["cv"]) < 0.25 * e["a"]
    # Sun 25 deg up in the east: the inner wall facing away from it (the east half of the bowl) is in shadow,
    # the ground outside the rim is lit.
    ell = geometry.Ellipse(e["cu"], e["cv"], e["a"], e["b"], e["angle_rad"])
    inside = np.hypot(uu - ell.cu, vv - ell.cv) < 0.8 * ell.b
    east = geometry.project_points(np.array([x0 + 1000.0, y0, 0.0]), p.pose_enu(lat0, lon0), 96)[0][0] > ell.cu
    east_half = inside & ((uu > ell.cu) == east)
    west_half = inside & ((uu > ell.cu) != east)
    assert ch["lit"][east_half].mean() < 0.5 < ch["lit"][west_half].mean()
    outside = np.hypot(uu - ell.cu, vv - ell.cv) > 1.5 * ell.a
    assert ch["lit"][outside].mean() > 0.9
    frac = labels[0]["lit_rim_fraction"]
    assert 0.0 < frac < 1.0  # the rim crest is partly in its own shadow near the terminator side
    pts = ell.points(90)
    assert frac == pytest.approx(float(np.mean(ch["lit"][pts[:, 1].astype(int), pts[:, 0].astype(int)])), abs=1e-4)


def test_nav_frames_command_end_to_end(tmp_path):
    """`crater-synth nav-frames` on a real-DEM trajectory frame at tiny settings: EXR + manifest + labels."""
    out = tmp_path / "frames"
    proc = run_nav_frames(tmp_path / "data", out, "0")
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["frames"] == 1 and summary["modes_used"] == ["fast"] and summary["sun_below_horizon"] == []
    assert "below the horizon" not in proc.stderr
    (row,) = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    assert row["schema_version"] == 1 and row["index"] == 0 and row["pose"]["altitude_m"] == pytest.approx(150e3)
    ch, header = exr.read_exr(out / row["rel_path"])
    assert ch["IF"].shape == (64, 64) and np.isfinite(ch["IF"]).all()
    assert header["trajectory"] == "descent_ridge" and json.loads(header["pose_mc"])["index"] == 0
    assert len(row["landmarks"]) > 5
    for lb in row["landmarks"]:
        assert 0 <= lb["centre_px"][0] < 64 and 0 <= lb["centre_px"][1] < 64
        assert lb["lit_rim_fraction"] is None or 0.0 <= lb["lit_rim_fraction"] <= 1.0
    # Identification and fix from the labels' own ellipses (perfect detections): the chain labels ->
    # prior -> identification -> known-attitude fix -> ellipse-centre correction is exact; 6-DOF PnP
    # is close (its tilt/shift ambiguity at nadir makes it looser).
    from crater_synth.navigation.detectors.classical import Detection
    from crater_synth.navigation.fix.solve import FixParams
    from crater_synth.navigation.map.landmarks import load_default_map
    from crater_synth.navigation.rendered import evaluate as frames_eval

    lms = load_default_map("south")[0]
    dets = frames_eval.perfect_detections(row)  # what nav-frames-eval's perfect-detection check uses
    assert [(d.u, d.v, d.r) for d in dets] == [
        (lb["ellipse"]["cu"], lb["ellipse"]["cv"], lb["ellipse"]["a"]) for lb in row["landmarks"]
    ]
    run = frames_eval.FrameRun()  # the classical detector's and the fix's defaults, the known attitude
    r = frames_eval.evaluate_frame(row, ch["IF"], lms, run, detections=dets)
    assert r["fix"] and r["error_km"] < 0.01 and r["identified_correct"] == r["identified"] >= 5, r
    assert len(r["matched"]) == len(r["truth"])  # every label matched by its own ellipse
    assert r["n_detections"] == r["landmarks_in_view"] == len(row["landmarks"])
    # An attitude error of 0.1 deg moves the known-attitude fix by about altitude x angle (150 km: 0.26 km).
    tilted_run = dataclasses.replace(run, attitude_error_deg=0.1)
    tilted = frames_eval.evaluate_frame(row, ch["IF"], lms, tilted_run, detections=dets)
    assert tilted["fix"] and 0.1 < tilted["error_km"] < 0.5, tilted
    # A frame all in shadow (a descent's last frame over a dark floor) is an answer of "no fix", not an error.
    r = frames_eval.evaluate_frame(row, np.zeros_like(ch["IF"]), lms, run)
    assert not r["fix"] and "empty" in r["reason"] and r["n_detections"] == 0
    # Shift every detection by 20 px: no consistent landmark set near the prior -> no fix, never a wrong one.
    far = [Detection(d.u + 20.0, d.v, d.r, 1.0) for d in dets]
    r = frames_eval.evaluate_frame(row, ch["IF"], lms, run, detections=far)
    assert not r["fix"] or r["error_km"] < 5.0, r
    # Two rims mostly hidden behind nearer relief: no longer truth (no miss), their detections not false.
    from crater_synth.navigation.protocol import summarise
    from crater_synth.navigation.rendered.labels import HIDDEN_RIM_MAX

    hid = json.loads(json.dumps(row))
    big = [lb for lb in hid["landmarks"] if lb["diameter_km"] >= FixParams().min_landmark_km]
    for lb in big[:2]:
        lb["occluded_rim_fraction"] = HIDDEN_RIM_MAX + 0.1
    big[2]["occluded_rim_fraction"] = HIDDEN_RIM_MAX  # at the bound: still in sight
    r = frames_eval.evaluate_frame(hid, ch["IF"], lms, run, detections=dets)
    assert len(r["truth"]) == len(big) - 2 and len(r["matched_any"]) == len(big)
    assert summarise([r])["recall_15km"] in (1.0, None)  # the hidden ones are no misses
    # nav-frames-eval's JSON (what `crater-synth report` reads): detector and perfect-detection fix per frame.
    from click.testing import CliRunner

    from crater_synth.cli import main
    from crater_synth.report.inputs import load_nav_frames

    res = CliRunner().invoke(main, ["nav-frames-eval", str(out), "--json", str(tmp_path / "nav" / "frames_eval.json")])
    assert res.exit_code == 0, res.output
    doc = load_nav_frames(tmp_path / "nav" / "frames_eval.json")
    (f,) = doc["frames"]
    assert doc["trajectory"] == "descent_ridge" and f["index"] == 0 and f["altitude_km"] == pytest.approx(150.0)
    assert f["landmarks_in_view"] == len(row["landmarks"]) and f["perfect"]["n_detections"] == len(row["landmarks"])
    assert f["perfect"]["fix"] and f["perfect"]["error_km"] < 0.01 and doc["summary"]["perfect"]["all"]["fix_rate"] == 1
    # The default preset is the one chosen on rendered frames; its settings are recorded with the result.
    assert doc["preset"] == "appearance" and doc["min_inliers"] == 3 and doc["inlier_px"] == 5.0
    assert f["enough_landmarks"] and doc["summary"]["not_enough_landmarks"] == 0
    # --results records the summary under "synthetic", keyed by trajectory, method and preset.
    results = ["--results", str(tmp_path / "navigation.json")]
    res = CliRunner().invoke(main, ["nav-frames-eval", str(out), *results, "nav/preset=appearance"])
    assert res.exit_code == 0, res.output
    # Terrain patches are the appearance preset's default fallback, and the key says so.
    rec = json.loads((tmp_path / "navigation.json").read_text())["synthetic"]
    rec = rec["descent_ridge/position/appearance/patches"]
    assert rec["protocol"]["preset_settings"]["refine"] and rec["all"]["windows"] == 1
    # The recorded command renders these frames again: they named their samples, so no G-buffer setting.
    assert rec["render"]["gbuffer_samples"] is None and "render.samples=1 " in rec["command"]
    assert "gbuffer" not in rec["command"]
    # --sensor puts a camera (noise, PSF, 8 bits) on each frame first; recorded, and keyed apart.
    res = CliRunner().invoke(
        main,
        ["nav-frames-eval", str(out), "--sensor", "nav_camera", "--json", str(tmp_path / "s.json"), *results],
    )
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "s.json").read_text())["summary"]["sensor"] == "nav_camera"
    assert (
        "descent_ridge/position/appearance/sensor=nav_camera/patches"
        in json.loads((tmp_path / "navigation.json").read_text())["synthetic"]
    )
    res = CliRunner().invoke(
        main, ["nav-frames-eval", str(out), "--sensor", "nope", "--json", str(tmp_path / "t.json")]
    )
    assert res.exit_code != 0 and "unknown sensor 'nope'" in res.output and not (tmp_path / "t.json").exists()
    for args, message in (
        (["--prior-offset-km", "200"], "expected 0 to 100 km"),
        (["--attitude-error-deg", "20"], "expected 0 to 10 degrees"),
        (["--attitude-error-deg", "0.1", *results], "standard prior and attitude only"),
    ):
        res = CliRunner().invoke(main, ["nav-frames-eval", str(out), "--json", str(tmp_path / "t.json"), *args])
        assert res.exit_code != 0 and message in res.output and not (tmp_path / "t.json").exists()
    res = CliRunner().invoke(
        main, ["nav-frames-eval", str(out), "--prior-offset-km", "12", "--json", str(tmp_path / "p.json")]
    )
    assert res.exit_code == 0 and json.loads((tmp_path / "p.json").read_text())["summary"]["prior_offset_km"] == 12.0
    # Lost in space (no prior): the labels' own ellipses, rectified onto the ground with the attitude and the
    # centre's depth as the altimeter range, are found by the map-wide pair vote within a kilometre; the
    # detector on this toy 64 px frame may find nothing, but never a wrong position.
    from crater_synth.navigation.rendered.lost_in_space import evaluate_lis_dir
    from crater_synth.navigation.settings import compose_nav

    lis = evaluate_lis_dir(out, compose_nav(["nav/preset=synthetic"]))
    (lr,) = lis["rows"]
    assert lr["perfect"]["fix"] and lr["perfect"]["error_km"] < 1.5, lr["perfect"]
    assert lr["perfect"]["identified_correct"] == lr["perfect"]["identified"] >= 6
    assert not lr["fix"] or lr["error_km"] < 5.0
    # The vote's fix seeds the 6-DOF pinhole fix (the attitude taken as a measurement); the perfect detections
    # are the vote's landmarks themselves, every one found.
    assert lr["perfect"]["found_lis"][0] == lr["perfect"]["found_lis"][1] >= 6
    six = lr["perfect"]["six_dof"]
    assert six["fix"] and six["error_km"] < 5.0 and six["attitude_error_deg"] < 0.5, six
    assert lis["perfect_six_dof_summary"]["fixes"] == 1 and lis["perfect_six_dof_summary"]["false_fixes"] == 0
    assert set(lis["detector_recall"]) == {"rim_span_10px", "lis_landmarks"}
    # The heading the attitude gives is the one the vote finds (only votes near it are kept).
    known = compose_nav(["nav/preset=synthetic", "nav.lost_in_space.known_heading=true"])
    (lh,) = evaluate_lis_dir(out, known)["rows"]
    assert lh["perfect"]["fix"] and lh["perfect"]["error_km"] == pytest.approx(lr["perfect"]["error_km"], abs=0.05)
    # `crater-synth navigate` on the rendered frame: nav-frames-eval's pipeline for one frame, and its PNG.
    exr_path, png = out / row["rel_path"], tmp_path / "nav.png"
    res = CliRunner().invoke(main, ["navigate", str(exr_path), "--out", str(png)])
    assert res.exit_code == 0, res.output
    nav = json.loads(res.output.strip().splitlines()[-1])
    assert nav["preset"] == "appearance" and nav["landmarks_in_view"] == len(row["landmarks"]) and png.is_file()
    assert nav["fix"] == f["fix"] and nav.get("error_km") == (round(f["error_km"], 3) if f["fix"] else None)
    listed = json.loads((tmp_path / "nav.json").read_text())["detections"]
    assert len(listed) == nav["detections"] and all("truth_landmark" in d and "landmark" in d for d in listed)
    assert sum(d["truth_landmark"] is not None for d in listed) == f["matched"]  # the JSON counts them
    for args, message in (
        (["--prior", "-89,0"], "--prior apply to map windows only"),
        (["nav/preset=template"], "unknown nav/preset 'template'"),
    ):
        res = CliRunner().invoke(main, ["navigate", str(exr_path), "--out", str(tmp_path / "x.png"), *args])
        assert res.exit_code != 0 and message in res.output and not (tmp_path / "x.png").exists()
    # The labels record the landmark map they name landmarks from; a row labelled with another map (a rebuilt
    # map numbers its landmarks anew) is refused by the readers of truth until it is relabelled.
    from crater_synth.navigation.map.landmarks import default_map_identity

    manifest = out / "manifest.jsonl"
    assert row["landmark_map"] == default_map_identity("south") and row["label_version"] == 3
    res = CliRunner().invoke(main, ["nav-frames-relabel", str(out)])
    done = json.loads(res.output.strip().splitlines()[-1])
    assert res.exit_code == 0 and done["labels_changed"] == done["map_record_changed"] == 0, res.output
    assert [json.loads(line) for line in manifest.read_text().splitlines()] == [row]  # the render's own labels
    stale = dict(row, landmark_map=dict(row["landmark_map"], sha256="0" * 64, landmarks=830))
    manifest.write_text(json.dumps(stale) + "\n")
    for cmd in (
        ["nav-frames-eval", str(out), "--json", str(tmp_path / "t.json")],
        ["navigate", str(exr_path), "--out", str(tmp_path / "x.png")],
    ):
        res = CliRunner().invoke(main, cmd)
        assert res.exit_code != 0 and "relabel the frames" in res.output and "(830 landmarks)" in res.output
    res = CliRunner().invoke(main, ["nav-frames-relabel", str(out)])
    done = json.loads(res.output.strip().splitlines()[-1])
    assert res.exit_code == 0 and (done["labels_changed"], done["map_record_changed"]) == (0, 1), res.output
    assert [json.loads(line) for line in manifest.read_text().splitlines()] == [row]
    stray = tmp_path / "frames" / "stray.exr"
    stray.write_bytes(exr_path.read_bytes())
    res = CliRunner().invoke(main, ["navigate", str(stray), "--out", str(tmp_path / "x.png")])
    assert res.exit_code != 0 and "not a frame of" in res.output and not (tmp_path / "x.png").exists()
    exr_path.write_bytes(exr_path.read_bytes()[:-100])  # truncated: its sha256 no longer matches the manifest
    res = CliRunner().invoke(main, ["navigate", str(exr_path), "--out", str(tmp_path / "x.png")])
    assert res.exit_code != 0 and "sha256 mismatch" in res.output and not (tmp_path / "x.png").exists()
    before = manifest.read_bytes()
    res = CliRunner().invoke(main, ["nav-frames-relabel", str(out)])
    assert res.exit_code != 0 and "nothing relabelled" in res.output and manifest.read_bytes() == before


def test_nav_frames_warns_of_a_night_frame(tmp_path):
    """A trajectory whose Sun is on the far side of the pole renders dark frames: rendered as asked, listed
    in the summary and named in a warning line."""
    proc = run_nav_frames(tmp_path / "data", tmp_path / "night", "0", "trajectory.subsolar_lon_deg=120")
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["sun_below_horizon"] == [0] and "Sun is below the horizon at the target of frames [0]" in proc.stderr


def test_worker_rejects_a_bad_explicit_camera(tmp_path):
    (p,) = frame_poses(_traj())
    from crater_synth.navigation.rendered.frames import worker_item

    item = worker_item(p, p.target_lat, p.target_lon, seed=1, header={})
    item["camera"]["rotation"][0][0] += 0.5  # not a rotation
    npz = cr.write_npz(tmp_path / "t.npz", cr.grid(50e3, 16))
    results, proc = cr.run_worker(cr.job(npz, [item], tmp_path / "out"), tmp_path, timeout=120)
    assert proc.returncode == 2 and not results
    (line,) = proc.stdout.strip().splitlines()
    assert line.startswith("ERROR ") and "camera rotation is not orthonormal" in line
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.exr"))


def test_every_preset_serves_the_6dof_fix_with_at_least_four_landmarks():
    """The presets of 3 agreeing landmarks take 4 for the 6-DOF fix (three points fix a pinhole pose
    exactly, so any three pairs would agree)."""
    from crater_synth.navigation.fix import pose as pm
    from crater_synth.navigation.fix import solve as nf
    from crater_synth.navigation.settings import compose_nav, preset_options

    assert preset_options() == ["appearance", "learned", "real-window", "synthetic"]
    for name in preset_options():
        fparams = compose_nav([f"nav/preset={name}"]).fix
        assert fparams.min_inliers in (3, 5)
    pts = np.column_stack([np.linspace(-9e3, 9e3, 3), np.zeros(3), np.zeros(3)])
    k = np.array([[500.0, 0, 256], [0, 500.0, 256], [0, 0, 1]])
    r0 = pm.rodrigues(np.array([np.pi, 0.0, 0.0]))
    uv = pm.project_pinhole(pts, r0, np.array([0.0, 0.0, 60e3]), k)
    ok, reason, *_ = nf.ransac_pnp(
        pts, uv, k, r0, np.array([0.0, 0.0, 60e3]), dataclasses.replace(fparams, min_inliers=3)
    )
    assert not ok and "need 4" in reason


def test_frames_are_grouped_onto_patches_no_coarser_than_their_own():
    """Consecutive frames share a patch that holds every footprint, at a vertex spacing no coarser than each
    frame's own patch, with at most SHARE_MAX_VERTEX_FACTOR x the vertices; per-frame: each its own patch."""
    from crater_core.trajectory import frame_corners_mc
    from crater_synth.config import load_settings
    from crater_synth.navigation.rendered.frames import (
        PATCH_MARGIN,
        SHARE_MAX_VERTEX_FACTOR,
        group_frames,
        own_half_width_m,
    )

    for name in ("descent_ridge", "polar_orbit_arc"):
        poses = frame_poses(load_settings([f"trajectory={name}"]).trajectory)
        groups = group_frames(poses, 512)
        assert [p.index for g in groups for p in g.poses] == list(range(len(poses)))
        assert len(groups) < len(poses)
        for g in groups:
            assert g.near_vertices <= SHARE_MAX_VERTEX_FACTOR * 512
            spacing = 2.0 * g.half_width_m / (g.near_vertices - 1)
            for p in g.poses:
                assert spacing <= 2.0 * own_half_width_m(p) / 511 * (1 + 1e-9)
                enu = geometry.mc_to_enu(frame_corners_mc(p), g.lat, g.lon)
                assert np.abs(enu[:, :2]).max() * PATCH_MARGIN <= g.half_width_m * (1 + 1e-9)
        own = group_frames(poses, 512, share=False)
        assert [len(g.poses) for g in own] == [1] * len(poses)
        for g, p in zip(own, poses):
            assert (g.lat, g.lon, g.near_vertices) == (p.target_lat, p.target_lon, 512)
            assert g.half_width_m == own_half_width_m(p)


def _nav_frames(tmp_path, out, *extra):
    return run_nav_frames(
        tmp_path / "data", out, "0,1,2", "terrain.near_vertices=128", "render.samples=4", *extra, timeout=300
    )


@pytest.mark.integration
def test_shared_patch_frames_match_per_frame_patches(tmp_path):
    """Three frames on one shared patch against the same frames each on its own patch (same poses, same Sun,
    no sub-DEM detail, so both grids sample the same DEM surface): identical labels, a complete manifest and
    no scratch files left, and the same image: mean I/F within the fast-vs-direct tolerance of
    docs/renderer.md (1.5 %); per pixel the two grids sample the DEM at different points, which at this toy
    size (64 px, 128 vertices, Sun ~7 deg) moves the MAD to 2.5-3.3 % of the lit median, 5-6 % of the
    pixels past 10 % and the lit MAD to 0.013-0.021 (direct mode gives the same, so it is the grid; fast vs
    direct on one grid at this size: 5 %, 14 %, 0.03), hence 4 %, 8 % and 0.03 here."""
    from crater_core.schema import sha256_file

    runs = {}
    for name, extra in (("shared", ()), ("own", ("--per-frame-patches",))):
        out = tmp_path / name
        proc = _nav_frames(tmp_path, out, *extra)
        assert proc.returncode == 0, proc.stderr[-2000:]
        summary = json.loads(proc.stdout.strip().splitlines()[-1])
        rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
        assert [r["index"] for r in rows] == [0, 1, 2] and summary["frames"] == 3
        for r in rows:  # complete: every row's file is there, with the sha256 the row says
            assert sha256_file(out / r["rel_path"]) == r["sha256"]
        assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
            "frame_0000.exr",
            "frame_0001.exr",
            "frame_0002.exr",
            "manifest.jsonl",
        ]
        runs[name] = (summary, rows, out)
    (s_sh, rows_sh, out_sh), (s_own, rows_own, out_own) = runs["shared"], runs["own"]
    assert s_sh["patches"] == 1 and s_own["patches"] == 3
    assert len({r["terrain_id"] for r in rows_sh}) == 1 and len({r["terrain_id"] for r in rows_own}) == 3
    assert rows_sh[0]["patch"]["frames"] == [0, 1, 2] and rows_sh[0]["patch"]["near_vertices"] > 128
    for a, b in zip(rows_sh, rows_own):
        assert a["pose"] == b["pose"] and a["camera_enu"] == b["camera_enu"] and a["sun_enu"] == b["sun_enu"]
        assert [lb["id"] for lb in a["landmarks"]] == [lb["id"] for lb in b["landmarks"]] and a["landmarks"]
        for la, lb in zip(a["landmarks"], b["landmarks"]):
            for k in ("cu", "cv", "a", "b"):
                assert abs(la["ellipse"][k] - lb["ellipse"][k]) < 0.1
        ca, _ = exr.read_exr(out_sh / a["rel_path"])
        cb, _ = exr.read_exr(out_own / b["rel_path"])
        lit_med = float(np.median(cb["IF"][cb["lit"] > 0.5]))
        diff = np.abs(ca["IF"] - cb["IF"])
        assert abs(ca["IF"].mean() / cb["IF"].mean() - 1.0) < 0.015
        assert diff.mean() / lit_med < 0.04
        assert np.mean(diff > 0.1 * lit_med) < 0.08
        assert np.abs(ca["lit"] - cb["lit"]).mean() < 0.03


def test_frame_commands_default_to_a_one_sample_gbuffer_unless_told_the_samples():
    """Navigation frames render fast mode's G-buffer at one (centre) sample by default; a command that sets
    render.samples or render.gbuffer_samples keeps exactly what it says (the documented frame sets)."""
    from crater_synth.config import load_settings
    from crater_synth.navigation.rendered.frames import frame_overrides

    default = load_settings(frame_overrides(["trajectory=descent_ridge"])).render
    assert (default.gbuffer_samples, default.samples) == (1, 16)  # direct renders and fallbacks keep 16
    told = load_settings(frame_overrides(["trajectory=descent_ridge", "render.samples=4"])).render
    assert (told.gbuffer_samples, told.samples) == (0, 4)  # 0: the G-buffer takes render.samples
    own = load_settings(frame_overrides(["render.gbuffer_samples=8"])).render
    assert own.gbuffer_samples == 8
    assert frame_overrides(("+render.samples=2",)) == ["+render.samples=2"]
    # A preset that sets render.samples decides as those overrides would: the navigation demo's preset
    # renders what its spelled-out overrides render.
    preset = load_settings(frame_overrides(["experiment=navigation_demo"])).as_dict()
    spelled = ["trajectory=polar_orbit_arc", "trajectory.frames=6", "render.samples=1"]
    assert preset == load_settings(frame_overrides(spelled)).as_dict()
    assert frame_overrides(["experiment=demo"])[0] == "render.gbuffer_samples=1"  # sets no render samples


def test_recorded_frame_settings_name_the_gbuffer_samples_the_frames_were_rendered_with(tmp_path):
    """A frame rendered with the one-sample G-buffer default records it, so the command recorded with its
    results (render.samples and render.gbuffer_samples) renders the same frames again."""
    from crater_synth.navigation.rendered import record as frames_record

    chans = {c: np.zeros((4, 4), np.float32) for c in schema.EXR_CHANNELS}
    header = {"crater_synth:mode": "fast", "samples": 16, "crater_synth:render": json.dumps({"gbuffer_samples": 1})}
    exr.write_exr(tmp_path / "frame_0000.exr", chans, header)
    row = {"rel_path": "frame_0000.exr", "pose": {"width_px": 4, "fov_deg": 60.0}}
    (tmp_path / schema.MANIFEST_NAME).write_text(json.dumps(row) + "\n")
    info = frames_record._render_info(tmp_path)
    assert info == {"mode": "fast", "samples": 16, "gbuffer_samples": 1, "width_px": 4, "fov_deg": 60.0}


@pytest.mark.integration
def test_bench_navframes_runs_both_paths_on_the_same_frames(tmp_path):
    """`crater-synth bench --part navframes` renders the same frames shared and per-frame in one call (no
    timing is asserted: benchmarks are not timed tests)."""
    from crater_synth.bench.navframes import bench_navframes

    r = bench_navframes(
        [
            "trajectory.width_px=48",
            f"data_dir={tmp_path / 'data'}",
            "terrain.near_vertices=64",
            "terrain.far_spacing_km=8",
            "terrain.detail.enabled=false",
            "render.samples=1",
            "render.shadow_map_px=48",
            "render.workers=1",
        ],
        tmp_path / "work",
        frames=2,
    )
    assert r["trajectory"] == "descent_ridge" and r["frames"] == 2
    assert r["shared"]["patches"] == 1 and r["per_frame"]["patches"] == 2
    for k in ("shared", "per_frame"):
        assert r[k]["modes_used"] == ["fast"] and r[k]["frames_per_s"] > 0 and r[k]["render_frames_per_s"] > 0
    assert r["speedup_end_to_end"] == pytest.approx(r["shared"]["frames_per_s"] / r["per_frame"]["frames_per_s"], 0.02)
    a = [json.loads(x) for x in (tmp_path / "work" / "navframes_shared" / "manifest.jsonl").read_text().splitlines()]
    b = [json.loads(x) for x in (tmp_path / "work" / "navframes_per_frame" / "manifest.jsonl").read_text().splitlines()]
    assert [r["pose"] for r in a] == [r["pose"] for r in b] and len(a) == 2
    nav = r["navigate"]  # the same frames through nav-frames-eval's pipeline, appearance and classical
    for k in ("appearance", "synthetic"):
        assert 0 <= nav[k]["fixes"] <= 2 and 0 < nav[k]["median_s_per_frame"] <= nav[k]["max_s_per_frame"]


def test_occluded_rim_fraction_counts_the_rim_points_behind_nearer_relief():
    """A rim 100 km away along the view axis, a depth map showing terrain at the rim's own depth except
    over the left third of the frame, where relief 20 km nearer stands in front: that third of the rim is
    hidden; within the margin (a rim crest higher than the map's mean) nothing is."""
    from crater_synth.navigation.rendered.labels import OCCLUSION_MARGIN_M, occluded_rim_fraction

    theta = np.arange(360) * np.pi / 180.0
    rim_uv = np.stack([50.0 + 30.0 * np.cos(theta), 50.0 + 30.0 * np.sin(theta)], 1)
    rim_depth = np.full(360, 100e3)
    depth = np.full((100, 100), 100e3)
    assert occluded_rim_fraction(depth, rim_uv, rim_depth, 10e3) == 0.0
    depth[:, :30] = 80e3
    expected = float(np.mean(rim_uv[:, 0] < 30.0))
    assert occluded_rim_fraction(depth, rim_uv, rim_depth, 10e3) == pytest.approx(expected)
    depth[:, :30] = 100e3 - OCCLUSION_MARGIN_M  # within the margin: a higher crest, not an occluder
    assert occluded_rim_fraction(depth, rim_uv, rim_depth, 10e3) == 0.0
    assert occluded_rim_fraction(depth, rim_uv + 80.0, rim_depth, 10e3) is None  # most of the rim outside


@pytest.mark.integration
def test_nav_frames_rerun_keeps_intact_frames_and_renders_changed_ones(tmp_path):
    """A re-run keeps a frame whose EXR is intact and was rendered with the same settings (an interrupted
    trajectory resumes); a changed setting that alters pixels, or a damaged file, renders it again."""
    out, data = tmp_path / "frames", tmp_path / "data"
    first = run_nav_frames(data, out, "0,1")
    assert first.returncode == 0, first.stderr[-2000:]
    f0, f1 = out / "frame_0000.exr", out / "frame_0001.exr"

    def rows():  # the manifest less the seconds each frame took in this run (0 for a frame kept)
        return [
            {k: v for k, v in json.loads(x).items() if k != "render_seconds"} for x in (out / "manifest.jsonl").open()
        ]

    manifest = rows()
    stamp = f0.stat().st_mtime_ns
    again = run_nav_frames(data, out, "0,1")
    assert again.returncode == 0, again.stderr[-2000:]
    assert json.loads(again.stdout.strip().splitlines()[-1])["reused"] == 2
    assert f0.stat().st_mtime_ns == stamp and rows() == manifest
    # A damaged frame (one byte of its pixels) is rendered again; the intact one is kept.
    raw = bytearray(f1.read_bytes())
    raw[-200] ^= 0xFF
    f1.write_bytes(bytes(raw))
    fixed = run_nav_frames(data, out, "0,1")
    assert fixed.returncode == 0 and json.loads(fixed.stdout.strip().splitlines()[-1])["reused"] == 1
    assert rows() == manifest  # the same render, sha256 and labels again
    # With no manifest recording their sha256, intact frames prove themselves by their seal.
    (out / "manifest.jsonl").unlink()
    sealed = run_nav_frames(data, out, "0,1")
    assert sealed.returncode == 0 and json.loads(sealed.stdout.strip().splitlines()[-1])["reused"] == 2
    assert rows() == manifest
    # A setting that changes pixels (the horizon map's texels): nothing is kept.
    changed = run_nav_frames(data, out, "0,1", "render.shadow_map_px=40")
    assert changed.returncode == 0 and json.loads(changed.stdout.strip().splitlines()[-1])["reused"] == 0
