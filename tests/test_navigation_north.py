"""North-pole navigation: north mosaic windows, the north landmark map, and the local-frame light model
(a light at one local azimuth turns with longitude in the map image, with opposite senses at the poles)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from crater_core.geometry import polar_stereo_forward, polar_stereo_inverse
from crater_synth.navigation.detectors.classical import ClassicalSettings, light_azimuth, pooled_light_azimuth, spectrum
from crater_synth.navigation.detectors.template import crater_heights, shade_heights
from crater_synth.navigation.georef import local_north_image_angle
from crater_synth.navigation.windows.mosaic import WINDOW_PX, load_mosaic_image, plan_windows, sector_of

ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]


def _wrap_deg(a):
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


# --------------------------------------------------------------------------------------------
# Windows
# --------------------------------------------------------------------------------------------
def test_north_windows_are_test_only_inside_the_mosaic_and_off_seams():
    img, extent, pixel, product = load_mosaic_image("north")
    assert product == "lroc_wac_north"
    plan = plan_windows("north")
    assert len(plan) > 200
    assert {split for _, split, *_ in plan} == {"test"}  # the north is the held-out pole
    assert {sector for _, _, sector, *_ in plan} == set(range(8))
    n = img.shape[0]
    for wid, _, sector, u0, v0 in plan:
        assert wid.startswith(f"N{sector}_")
        assert 0 <= u0 and u0 + WINDOW_PX <= n and 0 <= v0 and v0 + WINDOW_PX <= n
        uu, vv = np.meshgrid(np.arange(u0, u0 + WINDOW_PX + 1, 16.0), np.arange(v0, v0 + WINDOW_PX + 1, 16.0))
        x, y = uu * pixel - extent, extent - vv * pixel
        # Every sample of the footprint is in the window's sector: no quadrant seam (0/90/180/270 E) inside,
        # longitudes from the core's north projection (lon 0 on -y, 90 E on +x).
        lat, lon = polar_stereo_inverse(x, y, "north")
        assert (np.floor((lon % 360.0) / 45.0).astype(int) == sector).all()
        assert (sector_of(x, y, "north") == sector).all()
        assert (lat > 0).all() and np.hypot(x, y).min() > 200e3  # off the polar cap
    # The same geometry as the south (the north plane is the south's mirrored in y): as many windows.
    assert len(plan_windows("south")) == len(plan)


def test_sector_of_follows_the_core_projection_at_both_poles():
    lons = np.array([5.0, 50.0, 100.0, 150.0, 190.0, 240.0, 290.0, 350.0])
    for pole, lat in (("south", -80.0), ("north", 80.0)):
        x, y = polar_stereo_forward(lat, lons, pole)
        assert list(sector_of(x, y, pole)) == list(range(8))


# --------------------------------------------------------------------------------------------
# North landmark map
# --------------------------------------------------------------------------------------------
def test_north_map_loads_and_named_landmarks_project_into_north_windows_at_the_right_place():
    from crater_synth.navigation.map.landmarks import load_default_map
    from crater_synth.navigation.protocol import truth_in_frame
    from crater_synth.navigation.windows.mosaic import window_frame

    landmarks, prov = load_default_map("north")
    assert prov["pole"] == "north" and prov["dem_product"] == "lola_ldem256_north"
    assert len(landmarks) > 500 and all(lm.lat > 0 for lm in landmarks)
    plan = plan_windows("north")
    checked = 0
    for lm in landmarks:
        if not lm.name:
            continue
        # The catalogue's own IAU position of the named crater (configs/crater/<name>.yaml).
        cfg = yaml.safe_load((ROOT / "configs" / "crater" / f"{lm.name}.yaml").read_text())
        # Round trip through the core's north polar stereographic.
        x, y = polar_stereo_forward(lm.lat, lm.lon, "north")
        assert math.hypot(x - lm.x_m, y - lm.y_m) < 1.0
        lat, lon = polar_stereo_inverse(lm.x_m, lm.y_m, "north")
        assert abs(lat - lm.lat) < 1e-5  # the file keeps 5 decimals (and x, y to 0.1 m)
        assert np.allclose(polar_stereo_forward(lat, lon, "north"), (lm.x_m, lm.y_m), atol=1e-3)
        cx, cy = polar_stereo_forward(cfg["lat"], cfg["lon"], "north")
        assert math.hypot(cx - lm.x_m, cy - lm.y_m) < 0.15 * lm.diameter_km * 1000.0, lm.name
        # The window(s) holding it see it at the pixel whose map point is the landmark.
        for w in plan:
            frame = window_frame("north", *w)
            if not truth_in_frame([lm], frame.georef, frame.image.shape):
                continue
            u, v = frame.georef.xy_to_uv(lm.x_m, lm.y_m)
            assert 0 <= u < WINDOW_PX and 0 <= v < WINDOW_PX
            plat, plon = polar_stereo_inverse(*frame.georef.uv_to_xy(u, v), "north")
            assert abs(plat - cfg["lat"]) < 0.1 * lm.diameter_km / 30.3 and plat > 70.0
            checked += 1
            break
    assert checked >= 5  # named north craters that lie in some test window


# --------------------------------------------------------------------------------------------
# Local-frame light model
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("pole, lat", [("south", -80.0), ("north", 80.0)])
def test_local_north_image_angle_matches_the_projection(pole, lat):
    """Local north (increasing latitude) and east (increasing longitude) measured by finite differences
    through the core's projection; image (du, dv) = (dx, -dy)."""
    for lon in (0.0, 37.0, 123.0, 250.0, 330.0):
        x, y = polar_stereo_forward(lat, lon, pole)
        xn, yn = polar_stereo_forward(lat + 1e-3, lon, pole)
        xe, ye = polar_stereo_forward(lat, lon + 1e-3, pole)
        north = math.degrees(math.atan2(-(yn - y), xn - x))
        east = math.degrees(math.atan2(-(ye - y), xe - x))
        got = math.degrees(float(local_north_image_angle(x, y, pole)))
        assert abs(_wrap_deg(got - north)) < 1e-3
        assert abs(_wrap_deg(east - north - 90.0)) < 1e-2  # east clockwise of north at both poles


def test_local_light_turns_with_longitude_in_opposite_senses_at_the_poles():
    # A light at one local azimuth: its image angle turns by +dlon (south) and -dlon (north).
    lon = np.arange(0.0, 360.0, 30.0)
    for pole, lat, sense in (("south", -80.0, 1.0), ("north", 80.0, -1.0)):
        x, y = polar_stereo_forward(lat, lon, pole)
        theta = np.degrees(local_north_image_angle(x, y, pole)) + 40.0
        assert np.allclose(_wrap_deg(np.diff(theta) - sense * 30.0), 0.0, atol=1e-9)


CRATERS = [(80.0, 90.0, 14.0), (250.0, 80.0, 22.0), (150.0, 200.0, 30.0), (300.0, 290.0, 18.0), (90.0, 300.0, 25.0)]


def crater_field(theta_deg: float, n: int = 384):
    vv, uu = np.mgrid[0:n, 0:n] + 0.5
    z = np.zeros((n, n))
    for cu, cv, r in CRATERS:
        z += crater_heights(np.hypot(uu - cu, vv - cv) / r, 0.2) * r
    return shade_heights(z, math.radians(theta_deg), 15.0) * 200.0 + 20.0


def test_pooled_local_azimuth_is_recovered_from_frames_at_different_longitudes():
    """Frames of windows at different longitudes of one pole, each lit at one local azimuth: pooled in the
    local frame, the common azimuth comes back, and each frame's light is local north + that azimuth."""
    params = ClassicalSettings(light_method="tail", tail_points_to_sun=False)  # synthetic-bowl convention
    alpha = 70.0
    for pole, lat in (("south", -80.0), ("north", 80.0)):
        lons = [10.0, 100.0, 215.0]
        rots = [float(local_north_image_angle(*polar_stereo_forward(lat, lo, pole), pole)) for lo in lons]
        images = [crater_field(math.degrees(r) + alpha) for r in rots]
        got = math.degrees(pooled_light_azimuth(images, params, rotations=rots, n_azimuths=72))
        assert abs(_wrap_deg(got - alpha)) <= 10.0, (pole, got)
    # The seeded per-frame estimate stays inside its prior window even when the frame says otherwise.
    img = crater_field(20.0)
    a = (img - img.mean()) / img.std()
    spec, shape = spectrum(a)
    free = math.degrees(light_azimuth(spec, shape, params))
    near = math.degrees(light_azimuth(spec, shape, params, prior=(math.radians(30.0), math.radians(30.0))))
    far = math.degrees(light_azimuth(spec, shape, params, prior=(math.radians(200.0), math.radians(30.0))))
    assert abs(_wrap_deg(free - 20.0)) < 10.0 and abs(_wrap_deg(near - 20.0)) < 10.0
    assert abs(_wrap_deg(far - 200.0)) <= 30.0 + 1e-6


def test_north_validation_split_and_quadrant_light_are_refused():
    from click.testing import CliRunner

    from crater_synth.cli import main

    res = CliRunner().invoke(main, ["nav-eval", "--pole", "north", "--split", "validation"])
    assert res.exit_code != 0 and "test only" in res.output


def test_results_merge_keeps_the_other_region(tmp_path):
    import json

    from crater_synth.navigation.windows.evaluate import merge_results

    path = tmp_path / "navigation.json"
    path.write_text(json.dumps({"methods": {"classical": 1}, "splits": 2, "synthetic": {"a": 1}}))
    merged = merge_results(path, "north", {"methods": {"template": 3}})
    assert merged["methods"] == {"classical": 1} and merged["synthetic"] == {"a": 1}
    assert merged["regions"]["north"] == {"methods": {"template": 3}}
    path.write_text(json.dumps(merged))
    again = merge_results(path, "south", {"methods": {"classical": 5}, "splits": 6})
    assert again["methods"] == {"classical": 5} and again["regions"]["north"] == {"methods": {"template": 3}}
    assert again["synthetic"] == {"a": 1}
    assert again["history"] == [{"methods": {"classical": 1}, "splits": 2}]  # the replaced south result is kept
