"""Appearance refinement of a known-attitude fix (crater_synth/navigation/refine.py)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, map_coordinates

from crater_core import geometry
from crater_synth.navigation import refine
from crater_synth.navigation.fix import project_pinhole, solve_position


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


def test_refiner_recovers_the_camera_from_scattered_detections():
    """A nadir frame synthesised from the real DEM with the refinement's own physics (DEM, Hapke,
    horizon-map shadows), projected as a camera sees it; landmark observations scattered by ~3 px
    spoil the plain fix by kilometres; registering the landmarks' predicted windows brings it back to
    the image's precision."""
    from scipy.interpolate import griddata

    from crater_synth.navigation.frames_eval import cv_camera
    from crater_synth.navigation.landmarks import load_default_map
    from crater_synth.navigation.template import hapke_params

    lat0, lon0, altitude, width, fov = -81.5, 68.5, 80e3, 192, 60.0
    dem = refine.lander_dem("south")
    r_wc, k = cv_camera(np.eye(3), width, fov)  # nadir, image up = north
    c_true = np.array([0.0, 0.0, altitude])
    cam_mc = geometry.enu_to_mc(c_true, lat0, lon0)
    to_sun_mc = geometry.enu_basis(lat0, lon0).T @ geometry.direction_from_elevation_azimuth(6.0, 60.0)
    # The "frame": one window over the whole footprint, splatted onto the pixel grid.
    scene = SimpleNamespace(
        id="scene", lat=lat0, lon=lon0, diameter_km=2 * altitude * math.tan(math.radians(fov / 2)) / 1000
    )
    pts_mc, pred = refine.predict_window(
        dem, scene, to_sun_mc, cam_mc, hapke_params(), refine.RefineParams(samples=320)
    )
    uv = project_pinhole(geometry.mc_to_enu(pts_mc.reshape(-1, 3), lat0, lon0), r_wc, c_true, k)
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(width) + 0.5)
    image = griddata(uv, pred.ravel(), (jj, ii), method="linear")
    assert np.isfinite(image).all() and image.std() > 0
    # The map's landmarks well inside the frame.
    lms = [lm for lm in load_default_map("south")[0] if lm.diameter_km >= 10.0]
    pts = geometry.mc_to_enu(np.array([lm.position_mc() for lm in lms]), lat0, lon0)
    uv_lm = project_pinhole(pts, r_wc, c_true, k)
    margin = np.array([lm.diameter_km * 1000 for lm in lms]) / (2 * altitude / k[0, 0]) + 14
    inside = np.all((uv_lm >= margin[:, None]) & (uv_lm <= width - margin[:, None]), axis=1)
    sel = np.nonzero(inside)[0][:5]
    assert len(sel) >= 3, "the test scene needs three landmarks in view"
    rng = np.random.default_rng(3)
    observed = uv_lm[sel] + rng.normal(scale=3.0, size=(len(sel), 2))
    c_fix = solve_position(pts[sel], observed, k, r_wc)
    plain = np.linalg.norm(c_fix - c_true)
    refiner = refine.Refiner(dem)
    c_new, info = refiner.refine(
        image, [lms[i] for i in sel], observed, pts[sel], c_fix, r_wc, k, (lat0, lon0), to_sun_mc
    )
    assert plain > 1000.0  # the scatter costs kilometres
    records = info["landmarks"]
    assert all(r["used"] and r["ncc"] > 0.9 for r in records), records
    assert np.linalg.norm(c_new - c_true) < 150.0 < plain / 5
