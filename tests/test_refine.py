"""Appearance refinement of a known-attitude fix (crater_synth/navigation/fix/refine.py)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, map_coordinates

from crater_core import geometry
from crater_synth.navigation.fix import appearance, refine
from crater_synth.navigation.fix.pose import project_pinhole, solve_position


def _smooth_image(seed: int = 0, size: int = 160) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return gaussian_filter(rng.normal(size=(size, size)), 3.0)


def _window(centre=(80.0, 80.0), n: int = 30, spacing: float = 1.3) -> np.ndarray:
    s = (np.arange(n) - n / 2) * spacing
    gu, gv = np.meshgrid(s + centre[0], s + centre[1])
    return np.stack([gu, gv], axis=-1)


@pytest.mark.parametrize("shift, search", [((2.4, -1.3), 10), ((-7.6, 5.2), 10), ((0.6, -0.4), 3)])
def test_register_recovers_a_subpixel_shift(shift, search):
    """The predicted values sit `shift` px from where the prediction places them: register finds it
    (coarse-to-fine search, parabola peak), in both search modes."""
    image = _smooth_image()
    uv = _window()
    # The image content at uv + shift (pixel i spans [i, i + 1]: array coordinate = u - 0.5).
    pred = map_coordinates(image, [uv[..., 1] + shift[1] - 0.5, uv[..., 0] + shift[0] - 0.5], order=3)
    got, ncc = refine.register(image, uv, pred, search)
    assert got is not None and ncc > 0.98
    np.testing.assert_allclose(got, shift, atol=0.15)


def test_register_refuses_a_peak_beyond_the_search_or_a_window_outside_the_frame():
    image = _smooth_image()
    uv = _window()
    pred = map_coordinates(image, [uv[..., 1] - 0.5, uv[..., 0] + 14.0 - 0.5], order=3)
    got, _ = refine.register(image, uv, pred, 10)  # 14 px away: the best lies on the border
    assert got is None
    got, ncc = refine.register(image, uv + 500.0, pred, 10)  # no sample in the frame
    assert got is None and math.isnan(ncc)
    flat = np.ones_like(pred)
    assert refine.register(image, uv, flat, 10)[0] is None  # nothing to correlate


@pytest.fixture(scope="module")
def scene():
    """A nadir frame synthesised from the real south DEM with the refinement's own physics (DEM, Hapke,
    horizon-map shadows): one window over the whole footprint, projected as the camera sees it and
    interpolated onto the pixel grid (pixel centres at i + 0.5); and the map's landmarks well inside it."""
    from scipy.interpolate import griddata

    from crater_synth.navigation.detectors.template import hapke_params
    from crater_synth.navigation.map.landmarks import load_default_map
    from crater_synth.navigation.rendered.evaluate import cv_camera

    lat0, lon0, altitude, width, fov = -81.5, 68.5, 80e3, 192, 60.0
    dem = refine.lander_dem("south")
    r_wc, k = cv_camera(np.eye(3), width, fov)  # nadir, image up = north
    c_true = np.array([0.0, 0.0, altitude])
    cam_mc = geometry.enu_to_mc(c_true, lat0, lon0)
    to_sun_mc = geometry.enu_basis(lat0, lon0).T @ geometry.direction_from_elevation_azimuth(6.0, 60.0)
    whole = SimpleNamespace(
        id="scene", lat=lat0, lon=lon0, diameter_km=2 * altitude * math.tan(math.radians(fov / 2)) / 1000
    )
    pts_mc, pred = refine.predict_window(
        dem, whole, to_sun_mc, cam_mc, hapke_params(), refine.RefineParams(samples=320)
    )
    uv = project_pinhole(geometry.mc_to_enu(pts_mc.reshape(-1, 3), lat0, lon0), r_wc, c_true, k)
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(width) + 0.5)
    image = griddata(uv, pred.ravel(), (jj, ii), method="linear")
    assert np.isfinite(image).all() and image.std() > 0
    lms = [lm for lm in load_default_map("south")[0] if lm.diameter_km >= 10.0]
    pts = geometry.mc_to_enu(np.array([lm.position_mc() for lm in lms]), lat0, lon0)
    uv_lm = project_pinhole(pts, r_wc, c_true, k)
    margin = np.array([lm.diameter_km * 1000 for lm in lms]) / (2 * altitude / k[0, 0]) + 14
    inside = np.all((uv_lm >= margin[:, None]) & (uv_lm <= width - margin[:, None]), axis=1)
    sel = np.nonzero(inside)[0][:5]
    assert len(sel) >= 3, "the test scene needs three landmarks in view"
    return SimpleNamespace(
        image=image,
        dem=dem,
        r_wc=r_wc,
        k=k,
        c_true=c_true,
        origin=(lat0, lon0),
        to_sun_mc=to_sun_mc,
        landmarks=[lms[i] for i in sel],
        points=pts[sel],
        uv=uv_lm[sel],
        all_landmarks=lms,
        width=width,
        fov=fov,
    )


def test_refiner_recovers_the_camera_from_scattered_detections(scene):
    """Landmark observations scattered by ~3 px spoil the plain fix by kilometres; registering the
    landmarks' predicted windows brings it back to the image's precision."""
    rng = np.random.default_rng(3)
    observed = scene.uv + rng.normal(scale=3.0, size=scene.uv.shape)
    c_fix = solve_position(scene.points, observed, scene.k, scene.r_wc)
    plain = np.linalg.norm(c_fix - scene.c_true)
    refiner = refine.Refiner(scene.dem)
    c_new, info = refiner.refine(
        scene.image, scene.landmarks, observed, scene.points, c_fix, scene.r_wc, scene.k, scene.origin, scene.to_sun_mc
    )
    assert plain > 1000.0  # the scatter costs kilometres
    records = info["landmarks"]
    assert all(r["used"] and r["ncc"] > 0.9 for r in records), records
    assert np.linalg.norm(c_new - scene.c_true) < 150.0 < plain / 5


def test_register_wide_recovers_a_shift_far_beyond_the_fine_search():
    image = _smooth_image(size=240)
    uv = _window(centre=(120.0, 120.0), n=40)
    shift = (23.4, -17.2)
    pred = map_coordinates(image, [uv[..., 1] + shift[1] - 0.5, uv[..., 0] + shift[0] - 0.5], order=3)
    cache = {1: image}

    def blurred(step):
        return cache.setdefault(step, gaussian_filter(image, step / 2.0))

    got, ncc = appearance.register_wide(image, uv, pred, 30, 8, blurred)
    assert got is not None and ncc > 0.98
    np.testing.assert_allclose(got, shift, atol=0.15)
    assert appearance.register_wide(image, uv, pred, 12, 8, blurred)[0] is None  # beyond the search: refused
    # Thinned coarse grids (every k-th sample where the step spans k samples) find the same peak: the last
    # stage correlates every sample.
    thin, thin_ncc = appearance.register_wide(image, uv, pred, 30, 8, blurred, thin=True)
    np.testing.assert_allclose(thin, got, atol=1e-9)
    assert thin_ncc == ncc


def test_appearance_search_finds_the_landmarks_from_a_prior_kilometres_off(scene):
    """From a prior 5 km off, each landmark is found where its rim ellipse lies in the frame (within a
    pixel), so the fix from these detections alone lands within the image's precision; on a frame of
    noise nothing is found."""
    from crater_core.settings_nav import AppearanceSettings
    from crater_synth.navigation.fix.solve import FixParams

    c_prior = scene.c_true + np.array([3000.0, -4000.0, 0.0])
    refiner = refine.Refiner(scene.dem)
    search_km = FixParams().prior_sigma_km
    args = (
        scene.landmarks,
        scene.points,
        refiner,
        c_prior,
        scene.r_wc,
        scene.k,
        scene.origin,
        scene.to_sun_mc,
        search_km,
    )
    dets, windows = appearance.appearance_detections(scene.image, *args)
    assert len(dets) == len(scene.landmarks) and set(windows) == {lm.id for lm in scene.landmarks}
    pose = geometry.CameraPose(
        position=scene.c_true, rotation=np.stack([scene.r_wc[0], -scene.r_wc[1], -scene.r_wc[2]], 1), fov_deg=scene.fov
    )
    for d, p, lm in zip(dets, scene.points, scene.landmarks):
        normal = (p + [0.0, 0.0, geometry.MOON_RADIUS_M]) / np.linalg.norm(p + [0.0, 0.0, geometry.MOON_RADIUS_M])
        rim = geometry.project_circle(p, normal, lm.diameter_km * 500.0, pose, scene.width)
        assert math.hypot(d.u - rim.cu, d.v - rim.cv) < 1.0 and d.score >= AppearanceSettings().min_ncc
    noise = np.random.default_rng(0).uniform(size=scene.image.shape) * scene.image.max()
    assert appearance.appearance_detections(noise, *args)[0] == []


def test_a_fix_its_landmarks_contradict_is_refused(scene):
    """A fix 12 km off whose landmark pixels agree with it (as a wrong set of three detections can): no
    landmark registers near where it predicts them, so the appearance check refuses it; the true fix
    passes; the check can be switched off."""
    refiner = refine.Refiner(scene.dem)
    wrong = scene.c_true + np.array([12e3, 0.0, 0.0])
    uv_wrong = project_pinhole(scene.points, scene.r_wc, wrong, scene.k)
    args = (scene.r_wc, scene.k, scene.origin, scene.to_sun_mc)
    _, info = refiner.refine(scene.image, scene.landmarks, uv_wrong, scene.points, wrong, *args)
    ok, reason = refiner.verified(info)
    assert not ok and reason.startswith("appearance check: 0 of")
    _, info = refiner.refine(scene.image, scene.landmarks, scene.uv, scene.points, scene.c_true, *args)
    assert refiner.verified(info) == (True, "")
    lax = refine.Refiner(scene.dem, refine.RefineParams(verify=False))
    assert lax.verified({"landmarks": [{"used": False}]}) == (True, "")


def test_refiner_keeps_each_landmark_terrain_for_its_sun_and_a_refusal_too(scene):
    """A trajectory's frames share one Sun: the second prediction of a landmark reuses its DEM window and
    horizon (identical to predicting afresh), a new Sun vector computes anew, and a window that leaves the
    DEM is refused again without reading the DEM again."""
    from crater_synth.terrain.dem import DemError

    refiner = refine.Refiner(scene.dem)
    reads = []
    sample = scene.dem.sample
    refiner.dem = SimpleNamespace(sample=lambda *a, **kw: reads.append(1) or sample(*a, **kw))
    lm = scene.landmarks[0]
    cam = geometry.enu_to_mc(scene.c_true, *scene.origin)
    first = refiner.predict(lm, scene.to_sun_mc, cam)
    n = len(reads)
    again = refiner.predict(lm, scene.to_sun_mc, cam)
    assert len(reads) == n and refiner.terrain(lm, scene.to_sun_mc) is refiner.terrain(lm, scene.to_sun_mc)
    fresh = refine.predict_window(scene.dem, lm, scene.to_sun_mc, cam, refiner.hapke, refiner.params)
    for a, b in zip(again, fresh):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(first[1], fresh[1])
    other_sun = geometry.enu_basis(*scene.origin).T @ geometry.direction_from_elevation_azimuth(6.0, 90.0)
    refiner.predict(lm, other_sun, cam)
    assert len(reads) > n
    outside = SimpleNamespace(id="far", lat=-60.0, lon=0.0, diameter_km=20.0)
    with pytest.raises(DemError):
        refiner.terrain(outside, scene.to_sun_mc)
    n = len(reads)
    with pytest.raises(DemError):
        refiner.terrain(outside, scene.to_sun_mc)
    assert len(reads) == n
    refiner.clear_terrains()
    refiner.predict(lm, scene.to_sun_mc, cam)
    assert len(reads) > n


def test_terrains_prepared_in_worker_processes_are_the_same_to_the_bit(scene):
    """A refiner with workers computes a frame's new landmark windows in other processes: the same terrains
    (and the same refusal of a window that leaves the DEM) as computed in place."""
    from crater_synth.terrain.dem import DemError

    outside = SimpleNamespace(id="far", lat=-60.0, lon=0.0, diameter_km=20.0)
    jobs = [(lm, scene.to_sun_mc) for lm in scene.landmarks[:3]] + [(outside, scene.to_sun_mc)]
    pooled = refine.Refiner(scene.dem, workers=2)
    try:
        pooled.prepare(jobs)
        assert len(pooled._pending) == len(jobs)
        here = refine.Refiner(scene.dem)
        for lm, sun in jobs[:3]:
            a, b = pooled.terrain(lm, sun), here.terrain(lm, sun)
            for field in ("origin_mc", "frame", "near", "slope"):
                np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        with pytest.raises(DemError):
            pooled.terrain(outside, scene.to_sun_mc)
        pooled.prepare(jobs)  # all kept: nothing submitted again
        assert not pooled._pending
    finally:
        pooled.close()
    with pytest.raises(ValueError, match="workers"):
        refine.Refiner(scene.dem, workers=0)


def test_pose_refinement_recovers_attitude_and_centre(scene):
    """A 6-DOF fix off by 0.5 degree and a kilometre, its landmarks seen with a 1.5 px scatter: registering the
    windows and solving attitude and centre together (``pose=True``) brings both back; the record gives the
    rotation."""
    from crater_synth.navigation.fix.pose import attitude_difference_deg, rodrigues

    rng = np.random.default_rng(5)
    observed = scene.uv + rng.normal(scale=1.5, size=scene.uv.shape)
    r_fix = rodrigues(np.radians([0.4, -0.3, 0.0])) @ scene.r_wc
    c_fix = scene.c_true + np.array([600.0, -800.0, 0.0])
    before = np.linalg.norm(c_fix - scene.c_true), attitude_difference_deg(r_fix, scene.r_wc)
    refiner = refine.Refiner(scene.dem)
    args = (scene.image, scene.landmarks, observed, scene.points, c_fix, r_fix, scene.k, scene.origin)
    c_new, info = refiner.refine(*args, scene.to_sun_mc, pose=True)
    r_new = np.array(info["rotation"])
    after = np.linalg.norm(c_new - scene.c_true), attitude_difference_deg(r_new, scene.r_wc)
    assert all(r["used"] for r in info["landmarks"]), info["landmarks"]
    assert after[0] < before[0] / 3 and after[1] < before[1] / 3, (before, after)
    # With a believed attitude of a tight sigma the solve stays at it: the prior weighs against the pixels.
    held = np.array(refiner.refine(*args, scene.to_sun_mc, pose=True, attitude_prior=(r_fix, 1e-6))[1]["rotation"])
    assert attitude_difference_deg(held, r_fix) < 0.01 < attitude_difference_deg(r_new, r_fix)
    # Without pose=True the attitude is held and no rotation is recorded.
    assert "rotation" not in refiner.refine(*args, scene.to_sun_mc)[1]
