"""Lost in space confirmed by appearance: the places searched, and how their answers make a fix or none."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from crater_synth.navigation.fix.lost_in_space import Candidate, LostInSpaceParams, hypotheses
from crater_synth.navigation.fix.solve import Fix, FixParams
from crater_synth.navigation.georef import local_north_image_angle
from crater_synth.navigation.settings import compose_nav
from crater_synth.navigation.windows import appearance

CONFIRM = LostInSpaceParams(known_heading=True, confirm="appearance", confirm_hypotheses=2)


def _cand(support: float, x_km: float, inliers: int, rms: float | None = 1.0) -> Candidate:
    fix = None if rms is None else Fix(True, rms_px=rms)
    return Candidate(support, fix, 400.0 + 0j, 0j, complex(x_km * 1000.0, 200.0e3), inliers)


def test_places_are_the_best_supported_candidates_one_per_place():
    cands = [_cand(5.0, 0.0, 5), _cand(9.0, 100.0, 6), _cand(8.0, 103.0, 6), _cand(7.0, 300.0, 2), _cand(6.0, 50.0, 4)]
    places = hypotheses(cands, CONFIRM)
    # 103 km is 100 km's place (3 km apart, rival_km 5); 300 km agrees with too few landmarks; at most two places
    assert [p.centre.real / 1000.0 for p in places] == [100.0, 50.0]
    assert hypotheses(cands, LostInSpaceParams(known_heading=True, confirm="appearance", confirm_min_inliers=7)) == []


def test_confirm_settings_are_checked():
    with pytest.raises(ValueError, match="known_heading"):
        LostInSpaceParams(confirm="appearance")
    with pytest.raises(ValueError, match="confirm must be one of"):
        LostInSpaceParams(known_heading=True, confirm="dem")
    with pytest.raises(ValueError, match="confirm_reach_km"):
        LostInSpaceParams(known_heading=True, confirm="appearance", confirm_reach_km=0.0)
    lis = compose_nav(["nav/lost_in_space=confirmed"]).lost_in_space
    assert (lis.confirm, lis.known_heading, lis.confirm_hypotheses) == ("appearance", True, 3)


def _search(monkeypatch, confirms: dict[float, tuple[float, int]]):
    """The appearance search faked: a place (by its x in km) in ``confirms`` is fixed at (x km, inliers); the
    local azimuth each place is searched under is recorded."""
    seen = []
    monkeypatch.setattr(appearance, "lander_refiner", lambda pole: None)

    def detections(image, prior, landmarks, alpha, dparams, fparams, refiner):
        x_km = round((prior.left_m + 256 * prior.pixel_m) / 1000.0)
        seen.append((x_km, alpha, fparams.prior_sigma_km))
        return [x_km], None

    def fix(dets, landmarks, prior, shape, fparams):
        if dets[0] not in confirms:
            return Fix(False, "only 2 landmarks agree")
        x_km, n = confirms[dets[0]]
        return Fix(True, x_m=x_km * 1000.0, y_m=200.0e3, inliers=[(0, 0)] * n)

    monkeypatch.setattr(appearance, "window_detections", detections)
    monkeypatch.setattr(appearance, "fix_frame", fix)
    return seen


def _confirm(cands, light=1.0):
    image = np.zeros((512, 512))
    return appearance.confirmed_fix(image, "south", 400.0, cands, [], light, CONFIRM, None, FixParams())


def test_the_first_confirmed_place_is_the_fix_under_the_lights_azimuth_there(monkeypatch):
    seen = _search(monkeypatch, {50: (50.4, 12)})
    cands = [_cand(9.0, 100.0, 6), _cand(6.0, 50.0, 4), _cand(3.0, 70.0, 3)]
    dets, fix = _confirm(cands, light=1.0)
    assert fix.ok and fix.x_m == 50.4e3 and dets == [50] and fix.support == 6.0
    # both places searched within the confirmation's reach, each under its own local azimuth
    assert [s[0] for s in seen] == [100, 50] and {s[2] for s in seen} == {CONFIRM.confirm_reach_km}
    for x_km, alpha, _ in seen:
        north = float(local_north_image_angle(x_km * 1000.0, 200.0e3, "south"))
        assert alpha == pytest.approx(1.0 - north)


def test_two_confirmed_places_apart_are_ambiguous_and_near_ones_are_one(monkeypatch):
    _search(monkeypatch, {100: (100.2, 9), 50: (50.0, 7)})
    _, fix = _confirm([_cand(9.0, 100.0, 6), _cand(6.0, 50.0, 4)])
    assert not fix.ok and fix.reason.startswith("ambiguous: appearance confirms places 50 km apart")
    # two candidates 6 km apart (two places) whose searches both land on one spot: one place, fixed
    _search(monkeypatch, {100: (103.0, 9), 106: (103.2, 7)})
    _, fix = _confirm([_cand(9.0, 100.0, 6), _cand(6.0, 106.0, 4)])
    assert fix.ok and fix.x_m == 103.0e3


def test_no_confirmed_place_is_no_fix_that_says_a_place_was_searched(monkeypatch):
    _search(monkeypatch, {})
    _, fix = _confirm([_cand(9.0, 100.0, 6)])
    assert not fix.ok and fix.reason.startswith("no place confirmed by appearance (1 searched") and fix.support == 9.0
    _, fix = _confirm([_cand(9.0, 100.0, 2)])
    assert not fix.ok and "no candidate with 3 landmarks" in fix.reason and math.isnan(fix.support)


@pytest.mark.integration
def test_a_real_window_is_confirmed_where_it_lies_and_its_mirror_image_nowhere():
    """A south validation window lost in space with the template's craters, confirmed by appearance: fixed within
    a kilometre by the search's detections; the same window mirrored (image and craters) is not fixed."""
    from dataclasses import replace

    from crater_synth.navigation.detectors.classical import detect
    from crater_synth.navigation.fix.lost_in_space import build_index
    from crater_synth.navigation.windows.evaluate import nav_eval_map, window_lost_in_space
    from crater_synth.navigation.windows.light import frame_light
    from crater_synth.navigation.windows.mosaic import windows
    from crater_synth.tools.lis_choice import null_image, null_window

    frame = next(f for f in windows("validation", "south") if f.id == "S0_1536_0320")
    landmarks, _ = nav_eval_map("south", None)
    nav = compose_nav(["nav/detector=template", "nav/lost_in_space=confirmed", "nav.lost_in_space.vote_min_score=null"])
    lis = (nav.lost_in_space, build_index(landmarks, nav.lost_in_space))
    dets, _ = detect(frame.image, nav.detector, **frame_light(frame, nav.detector))
    found, fix = window_lost_in_space(frame, dets, landmarks, lis, nav.fix, len(dets))
    assert fix.ok and math.hypot(fix.x_m - frame.centre_xy[0], fix.y_m - frame.centre_xy[1]) < 1000.0
    assert found is not dets and all(d.score >= 0.5 for d in found)  # the search's NCC peaks
    moved = null_window(dets, frame.image.shape, "mirror", "left-right")
    mirror = replace(frame, image=null_image(frame.image, "mirror", "left-right"))
    kept, refused = window_lost_in_space(mirror, moved, landmarks, lis, nav.fix, len(moved))
    assert not refused.ok and kept == moved


@pytest.mark.integration
def test_navigate_confirms_a_window_lost_in_space_under_the_light_it_is_given(tmp_path):
    """`crater-synth navigate W.png --lost-in-space --pixel-m 400 --pole south --light-azimuth A
    nav/lost_in_space=confirmed`: a south validation window with no georeference is placed by the search's
    landmarks, as with `nav/lost_in_space=terrain-windows` (the terrain's place searched instead of the vote's);
    without the light the command ends with one error line."""
    import json

    from click.testing import CliRunner

    from crater_synth.cli import main
    from crater_synth.navigation.georef import ground_distance_km, stereo_forward
    from crater_synth.navigation.windows.evaluate import appearance_settings
    from crater_synth.navigation.windows.light import frame_light
    from crater_synth.navigation.windows.mosaic import windows
    from crater_synth.navigation.windows.navigate import write_window

    frame = next(f for f in windows("validation", "south") if f.id == "S0_1536_0320")
    img = tmp_path / "w.png"
    write_window(img, frame)
    (tmp_path / "w.png.geo.json").unlink()
    args = ["navigate", str(img), "--lost-in-space", "--pixel-m", "400", "--pole", "south"]
    args += ["nav/lost_in_space=confirmed", "nav.lost_in_space.vote_min_score=null"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2 and "nav.lost_in_space.confirm=appearance" in r.output and "--light-azimuth" in r.output
    light = math.degrees(frame_light(frame, appearance_settings())["light_dir"])
    for preset in ([], ["nav/lost_in_space=terrain-windows"]):  # the vote's places; the terrain's place instead
        r = CliRunner().invoke(main, [*args, *preset, "--light-azimuth", f"{light:.1f}"])
        assert r.exit_code == 0, r.output
        out = json.loads(r.output.strip().splitlines()[-1])
        x, y = stereo_forward(out["lat"], out["lon"], "south")
        assert out["fix"] and float(ground_distance_km(float(x), float(y), *frame.centre_xy, "south")) < 1.0


def test_the_search_needs_the_confirmations_landmarks(monkeypatch):
    """``confirm_min_landmarks`` raises the search's fix minimum above ``nav.fix``'s, never below it."""
    from dataclasses import replace

    needs = []
    monkeypatch.setattr(appearance, "lander_refiner", lambda pole: None)
    monkeypatch.setattr(appearance, "window_detections", lambda *a: ([], None))
    monkeypatch.setattr(appearance, "fix_frame", lambda d, lm, prior, shape, fparams: needs.append(fparams.min_inliers))
    image = np.zeros((512, 512))
    for gate in (3, 7):
        lis = replace(CONFIRM, confirm_min_landmarks=gate)
        appearance.search_place(image, "south", 400.0, 100.0e3 + 200.0e3j, [], 1.0, lis, None, FixParams())
    assert needs == [FixParams().min_inliers, 7]
    with pytest.raises(ValueError, match="confirm_min_landmarks"):
        replace(CONFIRM, confirm_min_landmarks=0)


def test_navigate_refuses_a_confirmation_of_the_appearance_searchs_own_lost_in_space(tmp_path):
    """`nav/detector=appearance` lost in space already searches from the template's vote: a confirmation of a crater
    detector's places on top of it would be silently ignored, so the pair is one error line."""
    from click.testing import CliRunner

    from crater_synth.cli import main

    img = tmp_path / "w.png"
    cv2.imwrite(str(img), np.full((64, 64), 100, np.uint8))
    args = ["navigate", str(img), "--lost-in-space", "--pixel-m", "400", "--pole", "south", "--light-azimuth", "30"]
    r = CliRunner().invoke(main, [*args, "nav/detector=appearance", "nav/lost_in_space=confirmed"])
    assert r.exit_code == 2 and "give one of them" in r.output and not (tmp_path / "w_navigate.png").exists()


def test_a_window_is_correlated_with_the_terrain_once_whatever_its_light_tries(monkeypatch):
    from types import SimpleNamespace

    from crater_synth.navigation.windows import evaluate

    nav = compose_nav(["nav/detector=learned-detect", "nav/lost_in_space=terrain-windows"])
    dparams = dataclasses.replace(nav.detector, light_tries_deg=[0.0, 90.0, 180.0])
    frame = SimpleNamespace(id="w", image=np.zeros((64, 64)), georef=SimpleNamespace(pole="south", pixel_m=400.0))
    correlated, given = [], []
    monkeypatch.setattr(evaluate, "prior_georef", lambda *a: None)
    monkeypatch.setattr(evaluate, "frame_light", lambda *a: {"light_dir": 0.5})
    monkeypatch.setattr(evaluate, "detect", lambda image, params, **kw: ([], kw.get("light_dir", 0.5)))
    monkeypatch.setattr(evaluate, "lost_in_space_search", lambda *a: (Fix(False, "no vote"), []))
    monkeypatch.setattr(evaluate, "window_terrain_places", lambda *a: correlated.append(a) or [(1.0e5 + 2.0e5j, 0.9)])
    monkeypatch.setattr(evaluate, "confirmed_fix", lambda *a: given.append(a[-1]) or ([], Fix(False, "not confirmed")))
    evaluate.navigate_window(frame, [], dparams, nav.fix, lis=(nav.lost_in_space, None))
    assert len(correlated) == 1 and given == [[(1.0e5 + 2.0e5j, 0.9)]] * 3


def test_terrain_places_given_to_the_confirmation_are_not_found_again(monkeypatch):
    _search(monkeypatch, {120: (120.3, 9)})

    def correlate(*args):
        raise AssertionError("the terrain was correlated again")

    monkeypatch.setattr(appearance, "window_terrain_places", correlate)
    lis = LostInSpaceParams(known_heading=True, confirm="appearance", confirm_hypotheses=0, terrain_places=1)
    image = np.zeros((512, 512))
    terrain = [(120.0e3 + 200.0e3j, 0.9)]
    _, fix = appearance.confirmed_fix(image, "south", 400.0, [], [], 1.0, lis, None, FixParams(), None, terrain)
    assert fix.ok and fix.x_m == 120.3e3
