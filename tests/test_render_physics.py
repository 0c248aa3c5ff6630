"""Physics tests of the Blender renderer (blender_gen/): tiny renders through the real worker.

Each module fixture runs ``python -m blender_gen.worker`` once on a synthetic terrain written to a
tmp dir, in direct and/or fast mode, and the tests inspect the EXRs:

- flat plane: I/F against the numpy Hapke oracle (per pixel) at several incidence/emission/phase
  angles, including the opposition geometry and grazing sun; depth/normal/lit channels;
- a step (plateau edge) of known height: its shadow ends h / tan(sun elevation) from it (within 2 px);
- a ridge in the far field (curvature included) shadows the crater area at a low sun only;
- fast mode matches direct mode per pixel on a crater-like terrain (tolerances in the test).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from crater_core import exr, geometry

from helpers import render as cr


def _load(out_dir: Path, it: dict) -> dict:
    return exr.read_exr(str(out_dir / it["rel_path"]))[0]


def _run(job_dict, tmp_path, name):
    results, proc = cr.run_worker(job_dict, tmp_path, name)
    assert proc.returncode == 0, f"worker failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
    assert sorted(results) == sorted(it["index"] for it in job_dict["renders"]), proc.stderr[-2000:]
    return results, proc


# ------------------------------------------------------------------------------------------------
# Flat plane
# ------------------------------------------------------------------------------------------------
# (sun elevation, sun azimuth, camera elevation, camera azimuth)
FLAT_ANGLES = [
    (30.0, 0.0, 90.0, 0.0),  # nadir view
    (30.0, 0.0, 60.0, 180.0),  # forward scattering side
    (60.0, 0.0, 60.0, 0.0),  # camera in the sun's direction: phase ~0 (opposition surge)
    (10.0, 90.0, 70.0, 45.0),
    (60.0, 200.0, 54.0, 10.0),  # lowest camera of the sweep
    (1.6, 0.0, 90.0, 0.0),  # the sweep's sun elevations
    (0.5, 45.0, 70.0, 200.0),
]
FLAT_RANGE = 15_000.0


@pytest.fixture(scope="module")
def flat_runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("flat")
    npz = cr.write_npz(tmp / "flat.npz", cr.grid(60_000.0, 33))
    items = [
        cr.item(i, *a, range_m=FLAT_RANGE, frame_width=200, crop=cr.central_crop(200, 80, du=7, dv=-5), name="flat")
        for i, a in enumerate(FLAT_ANGLES)
    ]
    runs = {}
    for mode in ("direct", "fast"):
        job = cr.job(npz, items, tmp / mode, mode=mode, diameter_km=20.0, shadow_map_px=256)
        results, proc = _run(job, tmp, f"flat-{mode}")
        runs[mode] = {"items": items, "out": tmp / mode, "results": results, "stderr": proc.stderr, "job": job}
    return runs


@pytest.mark.parametrize("mode", ["direct", "fast"])
def test_flat_plane_if_matches_hapke_oracle(flat_runs, mode):
    run = flat_runs[mode]
    for it in run["items"]:
        img = _load(run["out"], it)
        expected = cr.flat_expected_if(it)
        got = img["IF"]
        assert got.shape == expected.shape
        rel_mean = got.mean() / expected.mean() - 1.0
        where = f"{mode} {it['sun_elevation']}/{it['cam_elevation']}"
        assert abs(rel_mean) < 0.01, f"{where}: mean I/F off by {rel_mean:.2%}"
        # per pixel: exact formula, only Monte-Carlo noise of the solar disk at grazing sun
        mad = np.abs(got - expected).mean() / expected.mean()
        assert mad < (0.01 if it["sun_elevation"] < 5 else 0.002), f"{mode} {it}: per-pixel MAD {mad:.3%}"
        assert np.isclose(run["results"][it["index"]]["mean_if"], got.mean(), rtol=1e-4)


def test_flat_plane_channels(flat_runs):
    for mode, run in flat_runs.items():
        for it in run["items"]:
            img = _load(run["out"], it)
            np.testing.assert_allclose(img["N.Z"], 1.0, atol=1e-5)
            np.testing.assert_allclose(img["N.X"], 0.0, atol=1e-4)
            np.testing.assert_allclose(img["N.Y"], 0.0, atol=1e-4)
            # flat, unoccluded: the whole disk is visible once the sun clears the horizon by a radius
            lit = img["lit"]
            assert lit.min() >= 0.0 and lit.max() <= 1.0
            assert lit.mean() > (0.97 if it["sun_elevation"] < 1 else 0.995), (mode, it["sun_elevation"], lit.mean())


def _flat_centre_depth(it: dict) -> np.ndarray:
    """The depth of the flat plane z = 0 at each crop pixel's centre ray (distance along the view axis)."""
    pose, d = cr.centre_rays(it)
    return -pose.position[2] / d[..., 2] * (d @ pose.forward)


def test_flat_plane_depth_and_crop_alignment(flat_runs):
    """Depth is the distance along the view axis, and the crop box is exactly the requested pixels:
    Cycles' depth (one sample per pixel, jittered inside it) agrees with the analytic depth at the
    pixel centres with a mean offset well under one pixel's depth gradient."""
    run = flat_runs["direct"]
    for it in run["items"]:
        depth = _load(run["out"], it)["depth"]
        expected = _flat_centre_depth(it)
        u0, v0, u1, v1 = it["crop"]
        assert depth.shape == expected.shape == (v1 - v0, u1 - u0)
        grad = np.hypot(*np.gradient(expected)).mean()
        resid = depth - expected
        if grad < 1e-3:  # nadir view: depth == range everywhere
            np.testing.assert_allclose(depth, it["range_m"], rtol=1e-5)
        else:
            assert abs(resid.mean()) < 0.25 * grad, (it, resid.mean(), grad)
            assert np.abs(resid).max() < 1.0 * grad + 1e-3 * it["range_m"]


def test_one_sample_gbuffer_is_the_pixel_centre_whatever_the_seed(tmp_path):
    """Fast mode with ``gbuffer_samples=1`` (the navigation frames' default): Cycles' single ray goes
    through each pixel's centre, not a jittered point, so the G-buffer is sharp and the same for every seed.
    On an oblique view of a plane, depth equals the centre ray's to a tiny fraction of a pixel's depth step."""
    npz = cr.write_npz(tmp_path / "flat.npz", cr.grid(60_000.0, 33))
    items = [
        cr.item(i, 30.0, 0.0, cam_el, cam_az, range_m=FLAT_RANGE, frame_width=120, name="flat")
        for i, (cam_el, cam_az) in enumerate([(60.0, 180.0), (54.0, 10.0)])
    ]
    images = []
    for seed in (0, 12345):
        job = cr.job(npz, items, tmp_path / f"s{seed}", mode="fast", diameter_km=20.0, shadow_map_px=128)
        job["render"].update(gbuffer_samples=1, seed=seed)
        for it in job["renders"]:
            it["seed"] = seed
        _run(job, tmp_path, f"centre-{seed}")
        images.append([_load(tmp_path / f"s{seed}", it) for it in items])
    for it, a, b in zip(items, *images):
        for c in ("IF", "depth", "N.Z", "lit"):
            np.testing.assert_array_equal(a[c], b[c])
        expected = _flat_centre_depth(it)
        step = np.hypot(*np.gradient(expected)).mean()  # depth change per pixel
        assert step > 1.0
        assert np.abs(a["depth"] - expected).max() < 0.01 * step, (it["cam_elevation"], step)


# ------------------------------------------------------------------------------------------------
# Step (mesa) shadow
# ------------------------------------------------------------------------------------------------
MESA_H, MESA_HALF = 1500.0, 3000.0
# (sun elevation, sun azimuth, a point on the mesa's top edge that casts the measured shadow)
MESA_SUNS = [
    (20.0, 90.0, (-MESA_HALF, 0.0)),  # sun in the east: shadow west of the west edge
    (12.0, 0.0, (0.0, -MESA_HALF)),  # sun in the north: shadow south of the south edge
    (30.0, 225.0, (0.0, MESA_HALF)),
]  # oblique: the north edge's shadow, towards north-east


@pytest.fixture(scope="module")
def mesa_runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mesa")

    def mesa(x, y):  # a 6 km square plateau, 1500 m high; its cliffs span one 100 m grid cell
        return np.where((np.abs(x) <= MESA_HALF + 1) & (np.abs(y) <= MESA_HALF + 1), MESA_H, 0.0)

    npz = cr.write_npz(tmp / "mesa.npz", cr.grid(16_000.0, 321, mesa))  # 100 m grid, edges on vertices
    items = [
        cr.item(i, se, sa, 90.0, 0.0, range_m=20_000.0, frame_width=400, crop=cr.central_crop(400, 240), name="mesa")
        for i, (se, sa, _) in enumerate(MESA_SUNS)
    ]
    runs = {}
    for mode in ("direct", "fast"):
        # horizon maps +-6.3 km and +-12.6 km (covering the crop), 33 / 66 m texels (camera pixels: 100 m)
        job = cr.job(npz, items, tmp / mode, mode=mode, diameter_km=6.0, shadow_map_px=384, shadow_map_levels=2)
        _run(job, tmp, f"mesa-{mode}")
        runs[mode] = {"items": items, "out": tmp / mode}
    return runs


@pytest.mark.integration
@pytest.mark.parametrize("mode", ["direct", "fast"])
def test_step_shadow_length(mesa_runs, mode):
    """The shadow of the plateau's edge ends h / tan(sun elevation) from it (within 2 px; measured
    at the lit = 0.5 crossing along the anti-sun direction)."""
    run = mesa_runs[mode]
    for it, (_, _, edge) in zip(run["items"], MESA_SUNS):
        lit = _load(run["out"], it)["lit"]
        pose = geometry.look_at_camera(it["cam_elevation"], it["cam_azimuth"], it["range_m"], it["fov_deg"])
        u0, v0 = it["crop"][:2]
        away = -geometry.direction_from_elevation_azimuth(0.0, it["sun_azimuth"])  # anti-sun, horizontal
        dist = np.arange(600.0, 12_000.0, 5.0)  # from beyond the cliff (seen in perspective)
        pts = np.array([edge[0], edge[1], 0.0])[None, :] + dist[:, None] * away[None, :]
        uv, _ = geometry.project_points(pts, pose, it["frame_width"])
        cols = np.floor(uv[:, 0] - u0).astype(int)
        rows = np.floor(uv[:, 1] - v0).astype(int)
        ok = (cols >= 0) & (cols < lit.shape[1]) & (rows >= 0) & (rows < lit.shape[0])
        profile = lit[rows[ok], cols[ok]]
        dist = dist[ok]
        assert profile[0] < 0.05, f"{mode}: no shadow just behind the step"
        first_lit = np.nonzero(profile >= 0.5)[0]
        assert first_lit.size, f"{mode}: the shadow never ends"
        end_measured = dist[first_lit[0]]
        end_expected = MESA_H / math.tan(math.radians(it["sun_elevation"]))
        px_per_m = pose.focal_px(it["frame_width"]) / it["range_m"]  # nadir view of z = 0
        err_px = abs(end_measured - end_expected) * px_per_m
        assert err_px <= 2.0, (
            f"{mode} sun {it['sun_elevation']}/{it['sun_azimuth']}: shadow ends at "
            f"{end_measured:.0f} m, expected {end_expected:.0f} m ({err_px:.1f} px)"
        )
        assert profile[first_lit[0] + 40 :].min() > 0.95  # lit beyond it
        assert profile[: max(first_lit[0] - 40, 1)].max() < 0.05  # in shadow before it


# ------------------------------------------------------------------------------------------------
# Far-field ridge (curvature included)
# ------------------------------------------------------------------------------------------------
RIDGE_Y, RIDGE_H, NEAR_HALF = 60_000.0, 2000.0, 20_000.0
# Seen from the crater area (|y| < 8 km) the ridge top (2000 m high, 60 km north, dropped 1036 m by
# the Moon's curvature) stands 0.80-1.08 deg above the horizontal: it shadows a 0.32 deg sun
# (upper limb 0.59 deg) from the north, not a 1.6 deg one (lower limb 1.33 deg), nor any sun from
# the south. Without the curvature drop it would rise 1.9-2.2 deg and shadow the 1.6 deg sun too.
RIDGE_SUNS = [(0.32, 0.0, "shadow"), (1.6, 0.0, "lit"), (0.32, 180.0, "lit")]


@pytest.fixture(scope="module")
def ridge_runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ridge")
    near = cr.grid(NEAR_HALF, 65, curvature=True)
    far = cr.grid(90_000.0, 181, lambda x, y: RIDGE_H * np.exp(-(((y - RIDGE_Y) / 4000.0) ** 2)), curvature=True)
    npz = cr.write_npz(tmp / "ridge.npz", near, far, cr.keep_outside(far, NEAR_HALF))
    items = [
        cr.item(i, se, sa, 90.0, 0.0, range_m=15_000.0, frame_width=200, crop=cr.central_crop(200, 100), name="ridge")
        for i, (se, sa, _) in enumerate(RIDGE_SUNS)
    ]
    runs = {}
    for mode in ("direct", "fast"):
        job = cr.job(npz, items, tmp / mode, mode=mode, diameter_km=10.0, shadow_map_px=256)
        results, _ = _run(job, tmp, f"ridge-{mode}")
        runs[mode] = {"items": items, "out": tmp / mode, "results": results}
    return runs


@pytest.mark.parametrize("mode", ["direct", "fast"])
def test_far_ridge_shadows_only_low_sun(ridge_runs, mode):
    run = ridge_runs[mode]
    for it, (_, _, expect) in zip(run["items"], RIDGE_SUNS):
        lit = _load(run["out"], it)["lit"]
        if expect == "shadow":
            assert lit.mean() < 0.02, f"{mode} sun {it['sun_elevation']}/{it['sun_azimuth']}: lit {lit.mean():.3f}"
            assert run["results"][it["index"]]["mean_if"] < 1e-5
        else:
            assert lit.mean() > 0.98, f"{mode} sun {it['sun_elevation']}/{it['sun_azimuth']}: lit {lit.mean():.3f}"
            assert run["results"][it["index"]]["mean_if"] > 1e-4


# ------------------------------------------------------------------------------------------------
# Fast mode == direct mode
# ------------------------------------------------------------------------------------------------
CRATER_D = 10_000.0
CRATER_SUNS = [(1.6, 135.0), (0.48, 300.0), (10.0, 45.0)]
CRATER_CAMS = [(90.0, 0.0), (62.0, 200.0)]
# Tolerances, per render (measured values on this scene are ~3-5x smaller, docs/renderer.md):
FAST_MEAN_TOL, FAST_MAD_TOL, FAST_OUTLIER_TOL, LIT_MAD_TOL = (
    cr.FAST_MEAN_TOL,
    cr.FAST_MAD_TOL,
    cr.FAST_OUTLIER_TOL,
    cr.LIT_MAD_TOL,
)


@pytest.fixture(scope="module")
def crater_runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("crater")
    near = cr.grid(2.5 * CRATER_D, 256, cr.crater_z(CRATER_D), curvature=True)
    far = cr.grid(60_000.0, 61, lambda x, y: 600.0 * np.sin(x / 9000.0) * np.cos(y / 13000.0), curvature=True)
    npz = cr.write_npz(tmp / "crater.npz", near, far, cr.keep_outside(far, 2.5 * CRATER_D))
    items = cr.crater_items(CRATER_D, CRATER_SUNS, CRATER_CAMS, roi_min_px=100)
    runs = {}
    for mode in ("direct", "fast"):
        job = cr.job(
            npz,
            items,
            tmp / mode,
            mode=mode,
            diameter_km=CRATER_D / 1000.0,
            samples=16,
            shadow_map_px=384,
            shadow_map_levels=2,
            shadow_map_extent_factor=1.8,
        )
        # horizon-map texels 47 m (|x|, |y| < 9 km) and 94 m (out to 18 km); camera pixels ~100 m
        results, proc = _run(job, tmp, f"crater-{mode}")
        runs[mode] = {"items": items, "out": tmp / mode, "results": results, "stderr": proc.stderr}
    return runs


@pytest.mark.integration
def test_fast_matches_direct(crater_runs):
    assert 'fallbacks": 0' in crater_runs["fast"]["stderr"]
    for it in crater_runs["direct"]["items"]:
        a = _load(crater_runs["direct"]["out"], it)
        b = _load(crater_runs["fast"]["out"], it)
        d_if, f_if = a["IF"], b["IF"]
        lit_px = d_if[a["lit"] > 0.5]
        assert lit_px.size > 0.05 * d_if.size
        med = float(np.median(lit_px))
        diff = np.abs(d_if - f_if)
        tag = f"sun {it['sun_elevation']}/{it['sun_azimuth']} cam {it['cam_elevation']}/{it['cam_azimuth']}"
        assert abs(f_if.mean() / d_if.mean() - 1.0) < FAST_MEAN_TOL, (tag, f_if.mean(), d_if.mean())
        assert diff.mean() / med < FAST_MAD_TOL, (tag, diff.mean() / med)
        assert (diff > 0.1 * med).mean() < FAST_OUTLIER_TOL, (tag, (diff > 0.1 * med).mean())
        assert np.abs(a["lit"] - b["lit"]).mean() < LIT_MAD_TOL, tag
        # geometry channels come from the same Cycles scene
        np.testing.assert_allclose(b["depth"], a["depth"], rtol=2e-3)
        assert np.mean(np.abs(a["N.Z"] - b["N.Z"])) < 2e-3


@pytest.mark.integration
def test_crater_renders_have_shadows_and_light(crater_runs):
    for it in crater_runs["direct"]["items"]:
        lit = _load(crater_runs["direct"]["out"], it)["lit"]
        if it["sun_elevation"] < 2:  # low sun: the crater floor is in shadow, the sunward rim lit
            assert 0.05 < lit.mean() < 0.9, (it["sun_elevation"], lit.mean())


@pytest.mark.slow
def test_bench_fast_vs_direct_real_terrain(tmp_path):
    """The production-size comparison: the real Shackleton terrain, planner and config, 12 paper-grid
    items (crater_synth.bench.renderer.SAMPLE) in fast and direct mode, compared per pixel."""
    from crater_synth.bench import renderer as render_bench

    data = [f"data_dir={tmp_path / 'data'}"]
    render_bench.timed_dataset(render_bench.SAMPLE + ["render.mode=fast"] + data, tmp_path / "fast")
    render_bench.timed_dataset(render_bench.DIRECT_ROI + data, tmp_path / "direct")
    report = render_bench.compare(tmp_path / "direct", tmp_path / "fast")
    assert report["renders"] == 12
    for r in report["per_render"]:
        assert abs(r["rel_mean"]) < FAST_MEAN_TOL, r
        assert r["mad_over_median"] < FAST_MAD_TOL, r
        assert r["frac_gt_10pct"] < FAST_OUTLIER_TOL, r
        assert r["lit_mad"] < LIT_MAD_TOL, r
    assert render_bench.worker_stats(tmp_path / "fast")[0]["fast"]["fallbacks"] == 0


def test_lit_map_levels_lookup():
    """Nested map levels: each point reads the finest level whose square holds its bilinear stencil,
    and the lookup reproduces a linear function of (x, y) exactly on every level."""
    from blender_gen import fast

    geo = fast.MapGeometry(half_width_m=1000.0, px=8, levels=3)  # half-widths 250, 500, 1000 m
    assert geo.halves == [250.0, 500.0, 1000.0]
    levels = []
    for half in geo.halves:  # a linear "lit" field sampled at each level's texel centres
        d = 2 * half / geo.px
        c = -half + (np.arange(geo.px) + 0.5) * d
        x, y = np.meshgrid(c, c[::-1])
        levels.append(0.3 + 1e-4 * x - 2e-4 * y)  # a linear field sampled at the texel centres
    hm = fast.HorizonMap(np.concatenate([lv.ravel() for lv in levels]).astype(np.float32), geo)
    pts = np.array([[0.0, 0.0], [150.0, -180.0], [400.0, 300.0], [-800.0, 800.0], [1200.0, 0.0]])
    x, y = pts[:, 0][None, :], pts[:, 1][None, :]
    i00, fx, fy, n_out = geo.locate(x, y, np.ones_like(x, dtype=bool))
    assert n_out == 1  # (1200, 0) is beyond the outer map
    level = i00[0] // (geo.px * geo.px)
    assert list(level[:4]) == [0, 0, 1, 2]
    g = object.__new__(fast.GBuffer)
    g.i00, g.fx, g.fy, g.px = i00.astype(np.int32), fx, fy, geo.px
    got = g.lookup(hm)[0, :4]
    np.testing.assert_allclose(got, 0.3 + 1e-4 * pts[:4, 0] - 2e-4 * pts[:4, 1], atol=1e-6)
