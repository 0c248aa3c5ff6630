"""Lost-in-space places from the terrain (crater_synth/navigation/fix/terrain_places.py): the horizon march, the
template's turn to the map, the correlation's peaks, and the settings that switch it on."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from crater_core import geometry
from crater_synth.navigation.fix import terrain_places as tp
from crater_synth.navigation.fix.lost_in_space import Candidate, LostInSpaceParams, confirm_places, hypotheses
from crater_synth.navigation.settings import compose_nav


def test_the_horizon_towards_the_sun_is_the_steepest_rise_less_the_moons_curvature():
    pixel = 800.0
    z = np.zeros((60, 80), dtype=np.float32)
    z[:, 50] = 2000.0  # a wall 2 km high, north-south, at column 50
    slopes = tp.horizon_slopes(z, pixel, 0.0)  # looking towards +x (east on the map)
    t = 20 * pixel  # column 30 lies 20 pixels west of the wall
    assert slopes[30, 30] == pytest.approx(2000.0 / t - t / (2.0 * geometry.MOON_RADIUS_M), rel=0.02)
    assert slopes[30, 60] < 0.0  # east of the wall: nothing rises towards +x
    # towards +y (north, up the image) the wall is never ahead: the horizon is the sphere's fall
    assert tp.horizon_slopes(z, pixel, 90.0)[30, 30] < 0.0
    # towards -x the wall shades column 60 and not column 30
    west = tp.horizon_slopes(z, pixel, 180.0)
    assert west[30, 60] > 0.1 and west[30, 30] < 0.0


def _field(shape=(400, 400), seed=3) -> np.ndarray:
    """A smooth random 'shaded map' with features of every size."""
    rng = np.random.default_rng(seed)
    out = np.zeros(shape, dtype=np.float32)
    for sigma in (2.0, 6.0, 15.0):
        out += cv2.GaussianBlur(rng.normal(size=shape).astype(np.float32), (0, 0), sigma) * sigma
    return out


def _view_of(field: np.ndarray, pixel: float, x0: float, y1: float, place: complex, heading_deg: float, size=90):
    """A nadir view of ``field`` (a map of ``pixel`` m, left edge x0, top y1) centred on map point ``place``,
    its +u axis along map direction ``heading_deg``: what a lander's turned ground view is."""
    c = (size / 2.0, size / 2.0)
    u, v = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    east, north = (u - c[0]) * pixel, -(v - c[1]) * pixel
    a = math.radians(heading_deg)
    x = place.real + east * math.cos(a) - north * math.sin(a)
    y = place.imag + east * math.sin(a) + north * math.cos(a)
    mx = ((x - x0) / pixel - 0.5).astype(np.float32)
    my = ((y1 - y) / pixel - 0.5).astype(np.float32)
    return cv2.remap(field, mx, my, cv2.INTER_LINEAR), c


@pytest.mark.parametrize("heading_deg", [0.0, 37.0, -120.0])
def test_a_turned_view_is_placed_where_it_was_cut_from(heading_deg):
    pixel, x0, y1 = 800.0, -160000.0, 160000.0
    field = _field()
    shaded = tp.ShadedMap(field, pixel, x0, y1)
    place = complex(23400.0, -51700.0)
    view, centre = _view_of(field, pixel, x0, y1, place, heading_deg)
    # the view at 400 m (twice the map's resolution) with a footprint that is not the whole square
    view = cv2.resize(view, None, fx=2.0, fy=2.0, interpolation=cv2.INTER_LINEAR)
    valid = np.ones(view.shape, dtype=bool)
    valid[:40, :] = False
    found = tp.terrain_places(view, valid, pixel / 2.0, (centre[0] * 2, centre[1] * 2), heading_deg, shaded, 3, 16.0)
    assert len(found) == 3 and found[0][1] > 0.9 > found[1][1]
    assert abs(found[0][0] - place) < pixel
    assert all(abs(a[0] - b[0]) > 16000.0 for a in found for b in found if a is not b)


def test_a_view_larger_than_the_map_or_with_no_footprint_offers_no_place():
    shaded = tp.ShadedMap(_field((50, 50)), 800.0, 0.0, 0.0)
    big = np.ones((200, 200), dtype=np.float32)
    assert tp.terrain_places(big, np.ones_like(big, bool), 800.0, (100, 100), 0.0, shaded, 3, 16.0) == []
    small = np.ones((20, 20), dtype=np.float32)
    assert tp.terrain_places(small, np.zeros_like(small, bool), 800.0, (10, 10), 0.0, shaded, 3, 16.0) == []


def test_the_suns_map_direction_points_to_the_longitude_it_shines_from():
    # south pole: a Sun over longitude 90 E lies along the map's direction to the point (lat, 90 E)
    to_sun = geometry.latlon_to_mc(0.0, 90.0)
    to_sun = to_sun / np.linalg.norm(to_sun)
    x, y = geometry.polar_stereo_forward(-80.0, 90.0, "south")
    assert tp.sun_map_angle_deg(to_sun, "south") == pytest.approx(math.degrees(math.atan2(y, x)), abs=0.01)
    with pytest.raises(ValueError, match="zenith"):
        tp.sun_map_angle_deg(np.array([0.0, 0.0, -1.0]), "south")


def test_terrain_places_need_a_confirmation_and_may_stand_alone():
    confirmed = compose_nav(["nav/lost_in_space=confirmed"]).lost_in_space
    with pytest.raises(ValueError, match="terrain_places needs confirm"):
        dataclasses.replace(compose_nav().lost_in_space, terrain_places=1)
    with pytest.raises(ValueError, match="one >= 1"):
        dataclasses.replace(confirmed, confirm_hypotheses=0)
    with pytest.raises(ValueError, match="terrain_pixel_m"):
        dataclasses.replace(confirmed, terrain_places=1, terrain_pixel_m=0.0)
    alone = dataclasses.replace(confirmed, terrain_places=1, confirm_hypotheses=0)
    cand = Candidate(10.0, None, 1.0 + 0j, 0j, 0j, 6)
    assert hypotheses([cand], alone) == [] and hypotheses([cand], confirmed) == [cand]
    assert compose_nav(["nav/lost_in_space=terrain-frames"]).lost_in_space.terrain_places >= 1
    assert isinstance(alone, LostInSpaceParams)


def test_a_terrain_place_below_the_correlation_floor_is_not_searched():
    windows = compose_nav(["nav/lost_in_space=terrain-windows"]).lost_in_space
    assert windows.terrain_places == 1 and windows.confirm_hypotheses == 0 and 0.43 < windows.terrain_min_ncc < 0.81
    terrain = [(1e5 + 0j, 0.9), (3e5 + 0j, 0.5)]
    assert [p[1] for p in confirm_places(terrain, [], windows)] == [1e5 + 0j]
    assert confirm_places([(3e5 + 0j, 0.5)], [], windows) == []
    assert "no terrain place correlating >= 0.62" in windows.no_place_reason()
    unfloored = dataclasses.replace(windows, terrain_min_ncc=-1.0)  # the default: every place searched
    assert len(confirm_places(terrain, [], unfloored)) == 2
    with pytest.raises(ValueError, match="terrain_min_ncc"):
        dataclasses.replace(windows, terrain_min_ncc=1.0)


@pytest.mark.integration
def test_a_real_south_validation_window_is_placed_by_the_terrain_where_it_lies():
    """A WAC mosaic window (south validation, 400 m/px) against the south DEM shaded as the mosaic shows it: the
    best place lies under the window's centre, and its mirror image correlates nowhere as well."""
    from crater_synth.navigation.georef import ground_distance_km
    from crater_synth.navigation.windows.appearance import window_terrain_places
    from crater_synth.navigation.windows.evaluate import appearance_settings
    from crater_synth.navigation.windows.light import frame_light
    from crater_synth.navigation.windows.mosaic import windows

    frame = next(f for f in windows("validation", "south") if f.id == "S4_0896_2304")
    app = appearance_settings()
    lis = dataclasses.replace(compose_nav(["nav/lost_in_space=confirmed"]).lost_in_space, terrain_places=3)
    light = frame_light(frame, app)["light_dir"]
    places = window_terrain_places(frame.image, "south", frame.georef.pixel_m, light, lis, app)
    h, w = frame.image.shape
    x, y = frame.georef.uv_to_xy(w / 2.0, h / 2.0)
    best, ncc = places[0]
    assert float(ground_distance_km(best.real, best.imag, float(x), float(y), "south")) < 2.0
    assert ncc > 0.6 > places[1][1]
    mirrored = window_terrain_places(frame.image[:, ::-1], "south", frame.georef.pixel_m, light, lis, app)
    assert mirrored[0][1] < 0.6
