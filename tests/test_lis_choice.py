"""The lost-in-space choice tool: its variants and its rule (the windows themselves run in nav-eval's tests)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from crater_synth.errors import UserError
from crater_synth.navigation.detectors.classical import Detection
from crater_synth.navigation.fix import lost_in_space
from crater_synth.navigation.settings import compose_nav
from crater_synth.navigation.windows import evaluate
from crater_synth.tools import lis_choice


def test_a_variant_is_a_minimum_score_and_lost_in_space_overrides():
    assert lis_choice.parse_variant("", 0.05) == (0.05, [])
    text = "min_score=0.1 nav/lost_in_space=two-tier nav.lost_in_space.min_inliers=7"
    lis = ["nav/lost_in_space=two-tier", "nav.lost_in_space.min_inliers=7"]
    assert lis_choice.parse_variant(text, 0.05) == (0.1, lis)
    with pytest.raises(UserError, match="below the detector's threshold"):
        lis_choice.parse_variant("min_score=0.01", 0.05)
    with pytest.raises(UserError, match="nav.detector.threshold=0.3"):
        lis_choice.parse_variant("nav.detector.threshold=0.3", 0.05)  # the detector is --detector's alone
    with pytest.raises(UserError, match="min_score must be a number"):
        lis_choice.parse_variant("min_score=high", 0.05)


def _run(variant, fixed, false, median=0.3, windows=100):
    head = {"fix_rate": fixed / windows, "median_error_km": median, "windows": windows}
    return {"variant": variant, "headline": head, "all_windows": {"false_fixes": false}}


def test_the_rule_refuses_any_false_fix_then_takes_the_most_fixes():
    runs = [_run("a", 90, 1), _run("b", 71, 0, 0.4), _run("c", 70, 0, 0.3), _run("d", 60, 0, 0.1)]
    assert lis_choice.choose(runs)["variant"] == "c"  # one window fewer than b: tied, and closer
    runs = [_run("b", 72, 0, 0.4), _run("c", 70, 0, 0.3)]
    assert lis_choice.choose(runs)["variant"] == "b"  # two windows more: not a tie
    assert lis_choice.choose([_run("a", 0.9, 2)])["variant"] is None


def test_a_bad_variant_is_one_error_before_any_window_is_read(capsys):
    with pytest.raises(SystemExit, match="nav.lost_in_space.nope"):
        lis_choice.main(["--detector", "nav/detector=learned-detect", "--variant", "nav.lost_in_space.nope=1"])
    with pytest.raises(SystemExit, match="neither min_score"):
        lis_choice.main(["--detector", "nav/detector=learned-detect", "--variant", "gate=3"])


@pytest.mark.parametrize(("known", "heading"), [(False, None), (True, 0.0)])
def test_a_variant_with_the_heading_known_gives_the_fix_nav_evals_heading(monkeypatch, known, heading):
    seen = []
    monkeypatch.setattr(lis_choice, "build_index", lambda landmarks, lis: None)

    def search(dets, landmarks, shape, pixel_m, params, fparams, index, heading_deg, voters):
        seen.append(heading_deg)
        # "fixes" the left-right mirror only, at the map's origin: 5 km from the window's place
        ok = bool(dets) and dets[0].u > 256 > dets[0].v
        return SimpleNamespace(ok=ok, x_m=0.0, y_m=0.0, inliers=[(0, 0)] * 6, support=6.0 if ok else math.nan), []

    monkeypatch.setattr(evaluate, "lost_in_space_search", search)
    monkeypatch.setattr(lis_choice, "score_window", lambda *a: {})
    monkeypatch.setattr(lis_choice, "summarise_windows", lambda rows: {"headline": {}, "all_windows": {}})
    nav = compose_nav(["nav/detector=learned-detect"])
    lis = compose_nav([f"nav.lost_in_space.known_heading={str(known).lower()}"]).lost_in_space
    georef = SimpleNamespace(pixel_m=400.0, pole="south")
    frame = SimpleNamespace(georef=georef, image=SimpleNamespace(shape=(512, 512)), centre_xy=(3.0e3, 4.0e3))
    frame.id = "w7"
    dets = [Detection(10.0, 100.0, 7.0, 0.6)]
    run = lis_choice.run_variant("", 0.1, lis, [frame], [(dets, 0.0)], nav, [], None, nulls=("mirror", "scale"))
    # the window, its four mirror images and two scalings, each with the heading (the tool once ran them
    # heading-free)
    assert seen == [heading] * 7
    fixed = [{"window": "w7", "null": "mirror left-right", "landmarks": 6, "km": 5.0}]
    assert run["null"] == {
        "families": ["mirror", "scale"],
        "windows": 6,
        "fixes": 1,
        "fixed": fixed,
        "supports_verified": [6.0],
    }
    assert run["fixed_supports"] == []


def test_a_mirrored_window_keeps_each_craters_size_and_score_and_flips_its_place():
    d = [Detection(10.0, 100.0, 7.0, 0.6)]
    assert lis_choice.null_window(d, (512, 512), "mirror", "left-right") == [Detection(502.0, 100.0, 7.0, 0.6)]
    assert lis_choice.null_window(d, (512, 512), "mirror", "top-bottom") == [Detection(10.0, 412.0, 7.0, 0.6)]
    assert lis_choice.null_window(d, (512, 512), "mirror", "diagonal") == [Detection(100.0, 10.0, 7.0, 0.6)]
    assert lis_choice.null_window(d, (512, 512), "mirror", "anti-diagonal") == [Detection(412.0, 502.0, 7.0, 0.6)]
    with pytest.raises(UserError, match="square"):
        lis_choice.null_window(d, (512, 256), "mirror", "left-right")


def test_a_scaled_window_moves_and_grows_its_craters_about_the_centre_and_drops_those_it_pushes_out():
    d = [Detection(156.0, 256.0, 10.0, 0.6), Detection(10.0, 10.0, 5.0, 0.2)]
    big = lis_choice.null_window(d, (512, 512), "scale", "x1.30")
    assert big == [Detection(pytest.approx(126.0), 256.0, pytest.approx(13.0), 0.6)]  # the corner one left
    small = lis_choice.null_window(d, (512, 512), "scale", "x0.77")
    assert len(small) == 2 and small[0].u == pytest.approx(256 - 100 / 1.3) and small[1].r == pytest.approx(5 / 1.3)


def test_a_variant_that_fixes_a_mirrored_window_is_not_safe():
    runs = [_run("a", 90, 0), _run("b", 70, 0)]
    runs[0]["null"] = {"families": ["mirror"], "windows": 300, "fixes": 1}
    runs[1]["null"] = {"families": ["mirror"], "windows": 300, "fixes": 0}
    assert lis_choice.choose(runs)["variant"] == "b"


@pytest.mark.parametrize(("family", "how"), [(f, h) for f in lis_choice.NULLS for h in lis_choice.NULLS[f]])
def test_a_moved_image_carries_its_craters_where_the_moved_detections_lie(family, how):
    # a bright disc centred at pixel-corner coordinates (100.5, 60.5), radius 6 px
    v, u = np.mgrid[0:256, 0:256] + 0.5
    image = (np.hypot(u - 100.5, v - 60.5) <= 6.0).astype(np.float32) * 200.0
    moved = lis_choice.null_image(image, family, how)
    (d,) = lis_choice.null_window([Detection(100.5, 60.5, 6.0, 0.9)], image.shape, family, how)
    vv, uu = np.nonzero(moved > 100.0)
    assert abs((uu + 0.5).mean() - d.u) < 0.3 and abs((vv + 0.5).mean() - d.v) < 0.3
    # the disc's area grows with the move's scale, as the detection's radius does
    assert (moved > 100.0).sum() == pytest.approx(math.pi * d.r**2, rel=0.15)


def test_places_elsewhere_lie_on_landmarks_far_from_the_window_and_repeat():
    lms = [
        SimpleNamespace(x_m=1000.0 * k, y_m=0.0, diameter_km=12.0 if k // 50 % 2 else 8.0) for k in range(0, 2000, 50)
    ]
    places = lost_in_space.places_elsewhere("S0_0000_0000", (0.0, 0.0), lms, 5, 10.0)
    assert len(places) == 5 and places == lost_in_space.places_elsewhere("S0_0000_0000", (0.0, 0.0), lms, 5, 10.0)
    jitter = lost_in_space.PLACE_JITTER_KM * 1000.0
    for p in places:
        assert abs(p) >= (lost_in_space.PLACE_MIN_KM - lost_in_space.PLACE_JITTER_KM * 1.5) * 1000.0
        # each near one of the landmarks >= 10 km (odd multiples of 50 km here)
        assert min(abs(p - complex(lm.x_m, lm.y_m)) for lm in lms if lm.diameter_km >= 10.0) <= jitter * 1.5


def test_a_place_elsewhere_confirmed_by_chance_makes_a_variant_unsafe():
    safe, chance = _run("a", 90, 0), _run("b", 95, 0)
    chance["elsewhere"] = {"places": 10, "confirmed": [{"window": "w", "landmarks": 5, "km": 800.0}]}
    assert lis_choice.choose([safe, chance])["variant"] == "a"
    voted = _run("c", 95, 0)
    voted["elsewhere"] = {"vote": {"places": 3, "confirmed": [{"window": "w", "landmarks": 6, "km": 500.0}]}}
    assert lis_choice.choose([safe, voted])["variant"] == "a"


def test_vote_places_elsewhere_are_every_place_the_vote_offers_away_from_the_window(monkeypatch):
    from crater_synth.navigation.fix.lost_in_space import Candidate

    def cand(support, x_km, inliers):
        return Candidate(support, None, 400.0 + 0j, 0j, complex(x_km * 1000.0, -900.0e3), inliers)

    # the window's own place (0 km), a place 2 km from it, and four places elsewhere, one with too few landmarks
    cands = [cand(9.0, 0.0, 8), cand(8.0, 2.0, 5), cand(7.0, 300.0, 4), cand(6.0, 500.0, 3), cand(5.0, 700.0, 2)]
    cands += [cand(4.0, 900.0, 3)]
    monkeypatch.setattr(lis_choice, "lost_in_space_search", lambda *a: (None, cands))
    lis = compose_nav(["nav/lost_in_space=confirmed"]).lost_in_space  # at most 3 places when confirming a fix
    georef = SimpleNamespace(pixel_m=400.0, pole="south")
    frame = SimpleNamespace(georef=georef, image=SimpleNamespace(shape=(512, 512)), centre_xy=(0.0, -900.0e3))
    places = lis_choice.vote_places_elsewhere(frame, [], [], lis, None, compose_nav([]), 0)
    assert [round(p.real / 1000.0) for p in places] == [300, 500, 900]


def test_a_place_elsewhere_counts_only_when_its_confirmation_lands_away_from_the_window(monkeypatch):
    # a place 7 km off whose search reaches the true place (0.4 km): a correct fix; one confirmed 600 km away: chance
    fixes = {7: (0.4e3, 12), 600: (600.0e3, 5), 900: None}

    def search(image, pole, pixel_m, place, *a):
        got = fixes[round(place.real / 1000.0)]
        if got is None:
            return [], SimpleNamespace(ok=False)
        return [], SimpleNamespace(ok=True, x_m=got[0], y_m=-900.0e3, inliers=[(0, 0)] * got[1])

    monkeypatch.setattr(lis_choice, "search_place", search)
    monkeypatch.setattr(lis_choice, "frame_light", lambda frame, dparams: {"light_dir": 0.0})
    georef = SimpleNamespace(pixel_m=400.0, pole="south")
    frame = SimpleNamespace(id="w", georef=georef, image=None, centre_xy=(0.0, -900.0e3))
    places = [complex(k * 1000.0, -900.0e3) for k in (7, 600, 900)]
    found = lis_choice.search_elsewhere(frame, [], None, compose_nav([]), places)
    assert [f["landmarks"] for f in found] == [5] and found[0]["km"] > 500.0  # ground km (the map scale)
