"""Lost-in-space identification (no position prior) on synthetic maps and detection lists."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from crater_synth.navigation.detectors.classical import Detection
from crater_synth.navigation.fix.lost_in_space import LostInSpaceParams, build_index, lost_in_space_fix
from crater_synth.navigation.navigate import NavigateRequest, lost_in_space_settings
from crater_synth.navigation.settings import compose_nav

from helpers.lis_maps import PIXEL_M, SHAPE, lis_frame, lis_map


def test_recovers_known_transform_without_prior():
    rng = np.random.default_rng(3)
    lms = lis_map(rng)
    index = build_index(lms)
    for centre, heading in (((120e3, -80e3), 0.0), ((-250e3, 300e3), 37.0), ((10e3, 20e3), -140.0)):
        dets = lis_frame(lms, centre, heading, rng)
        fix = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, index=index)
        assert fix.ok, fix.reason
        assert math.hypot(fix.x_m - centre[0], fix.y_m - centre[1]) < 1000.0
        assert abs((fix.heading_deg - heading + 180.0) % 360.0 - 180.0) < 1.0
        assert abs(fix.scale_m_per_px / PIXEL_M - 1.0) < 0.01


def test_no_map_craters_gives_no_fix():
    rng = np.random.default_rng(4)
    lms = lis_map(rng)
    dets = [Detection(*rng.uniform(0, 512, 2), rng.uniform(12, 60), 0.5) for _ in range(40)]
    fix = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M)
    assert not fix.ok and fix.reason


def test_repeated_pattern_is_ambiguous():
    rng = np.random.default_rng(5)
    motif = lis_map(rng, n=14, half_km=90.0)
    # The same crater pattern twice on the map, 400 km apart: the frame sees one copy, no fix is safe.
    lms = motif + [SimpleNamespace(x_m=m.x_m + 400e3, y_m=m.y_m, diameter_km=m.diameter_km) for m in motif]
    dets = lis_frame(lms, (0.0, 0.0), 20.0, rng, keep=1.0, clutter=5, noise_px=0.5)
    fix = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M)
    assert not fix.ok
    assert "ambiguous" in fix.reason
    # The same frame against a map holding one copy only is fixed (the refusal is the repetition's).
    fix1 = lost_in_space_fix(dets, motif, SHAPE, PIXEL_M)
    assert fix1.ok, fix1.reason
    assert math.hypot(fix1.x_m, fix1.y_m) < 1000.0


def test_params_round_trip():
    assert LostInSpaceParams().as_dict()["n_detections"] == 30


def test_lis_settings_overrides_and_errors():
    import pytest

    from crater_synth.errors import UserError

    p = compose_nav(["nav.lost_in_space.n_detections=40", "nav.lost_in_space.gate_km=6"]).lost_in_space
    assert p.n_detections == 40 and p.gate_km == 6.0
    south_choice = compose_nav(["nav/lost_in_space=south-choice"]).lost_in_space
    assert p.min_inliers == south_choice.min_inliers and south_choice.gate_km == 4.0
    with pytest.raises(UserError, match="nav.lost_in_space.nope"):
        compose_nav(["nav.lost_in_space.nope=1"])
    with pytest.raises(UserError, match="nav/lost_in_space 'missing'"):
        compose_nav(["nav/lost_in_space=missing"])


def _two_tier_frame(lms, centre, rng, n_sure, n_weak, weak_clutter):
    """Detections of a north-up frame: ``n_sure`` true craters at score 1, ``n_weak`` true ones and
    ``weak_clutter`` random circles at score 0.1."""
    true = [d for d in lis_frame(lms, centre, 0.0, rng, keep=1.0, clutter=0, noise_px=0.5)]
    true.sort(key=lambda d: -d.r)
    sure = true[:n_sure]
    weak = [Detection(d.u, d.v, d.r, 0.1) for d in true[n_sure : n_sure + n_weak]]
    clutter = [Detection(*rng.uniform(0, 512, 2), rng.uniform(9, 40), 0.1) for _ in range(weak_clutter)]
    return sure + weak + clutter


def test_weak_detections_confirm_a_vote_they_do_not_cast():
    """Two tiers: the sure detections vote; the weak ones, too many to vote among, confirm the voted
    transform. With too few sure detections the frame is refused before any vote."""
    rng = np.random.default_rng(11)
    lms = lis_map(rng)
    index = build_index(lms)
    dets = _two_tier_frame(lms, (120e3, -80e3), rng, n_sure=4, n_weak=6, weak_clutter=150)
    two = LostInSpaceParams(vote_min_score=0.5, min_inliers=8)
    fix = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, two, index=index)
    assert fix.ok, fix.reason
    assert math.hypot(fix.x_m - 120e3, fix.y_m + 80e3) < 1000.0
    assert len(fix.inliers) >= 8  # more than the 4 sure craters: the weak tier counted
    sure_only = [d for d in dets if d.score >= 0.5]
    alone = lost_in_space_fix(sure_only, lms, SHAPE, PIXEL_M, two, index=index)
    assert not alone.ok  # 4 sure craters cannot reach 8 inliers by themselves
    refused = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, LostInSpaceParams(vote_min_score=2.0), index=index)
    assert not refused.ok and "score >= 2.0" in refused.reason


def test_a_second_detectors_craters_verify_but_never_vote():
    """``voters``: the detections after the first ``voters`` (a verify detector's) confirm a voted transform
    but cast no vote. The first detector's 4 sure craters vote; 5 more true craters found only by the second
    lift the inliers past min_inliers 8. Scored high, the second's craters still never vote: with the first
    detector's list empty of sure craters the frame is refused before any vote."""
    rng = np.random.default_rng(11)
    lms = lis_map(rng)
    index = build_index(lms)
    dets = _two_tier_frame(lms, (120e3, -80e3), rng, n_sure=4, n_weak=5, weak_clutter=40)
    first, second = dets[:4] + dets[9:], [Detection(d.u, d.v, d.r, 1.0) for d in dets[4:9]]
    two = LostInSpaceParams(vote_min_score=0.5, min_inliers=8)
    alone = lost_in_space_fix(first, lms, SHAPE, PIXEL_M, two, index=index)
    assert not alone.ok  # 4 true craters among the first detector's
    both = [*first, *second]
    fix = lost_in_space_fix(both, lms, SHAPE, PIXEL_M, two, index=index, voters=len(first))
    assert fix.ok, fix.reason
    assert math.hypot(fix.x_m - 120e3, fix.y_m + 80e3) < 1000.0
    assert any(i >= len(first) for i, _ in fix.inliers)  # the second detector's craters counted
    none_vote = lost_in_space_fix([*first[4:], *second], lms, SHAPE, PIXEL_M, two, index=index, voters=len(first) - 4)
    assert not none_vote.ok and "score >= 0.5" in none_vote.reason


def test_new_detections_keeps_the_craters_the_first_detector_lacks():
    from crater_synth.navigation.detectors.classical import new_detections, with_new

    known = [Detection(100.0, 100.0, 20.0, 0.9), Detection(300.0, 300.0, 10.0, 0.5)]
    found = [
        Detection(108.0, 96.0, 24.0, 0.6),  # the same crater: centre within 0.6 r, radius within 1.5
        Detection(100.0, 100.0, 40.0, 0.6),  # concentric but twice the size: another crater
        Detection(330.0, 300.0, 10.0, 0.6),  # 30 px off a 10 px crater: another crater
        Detection(400.0, 50.0, 15.0, 0.6),
    ]
    assert new_detections(found, known, 0.6, 1.5) == found[1:]
    assert new_detections(found, [], 0.6, 1.5) == found and new_detections([], known, 0.6, 1.5) == []
    # with_new: no verify detector (an appearance search's lost in space has no suppression settings to read)
    assert with_new(known, [], None) == known
    assert with_new(known, found, SimpleNamespace(nms_centre_r=0.6, nms_radius_ratio=1.5)) == known + found[1:]


def test_verify_detector_names_a_crater_detector():
    from crater_synth.errors import ConfigError
    from crater_synth.navigation.settings import verify_detector_settings

    nav = compose_nav(["nav/lost_in_space=two-tier", "nav.lost_in_space.verify_detector=template"])
    assert nav.lost_in_space.verify_detector == "template"
    assert verify_detector_settings("template").method == "template"
    assert verify_detector_settings("") is None
    for bad, says in (("nope", "not a nav/detector option"), ("appearance", "the appearance method finds no craters")):
        with pytest.raises(ConfigError, match=f"nav.lost_in_space.verify_detector={bad!r}: {says}"):
            compose_nav([f"nav.lost_in_space.verify_detector={bad}"])


def test_verification_tolerance_follows_the_lost_in_space_group():
    """Large craters detected 6-8 px off their map centres: nav.fix's 2 px + 0.1 r refuses them, the
    group's own inlier_r and RMS gate accept them; the prior-gated fix's settings stay as they are."""
    from crater_synth.navigation.fix.solve import FixParams

    rng = np.random.default_rng(12)
    lms = [m for m in lis_map(rng, n=3000) if m.diameter_km >= 20.0]
    index = build_index(lms)
    dets = lis_frame(lms, (60e3, 40e3), 0.0, rng, keep=1.0, clutter=3, noise_px=0.0)
    off = 0.14  # of the radius, each detection in another direction
    shift = [off * d.r * complex(math.cos(k), math.sin(k)) for k, d in enumerate(dets)]
    dets = [Detection(d.u + s.real, d.v + s.imag, d.r, d.score) for d, s in zip(dets, shift)]
    strict = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, LostInSpaceParams(min_inliers=4), index=index)
    loose = LostInSpaceParams(min_inliers=4, inlier_r=0.25, max_rms_px=12.0)
    fix = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, loose, index=index)
    assert fix.ok, fix.reason
    assert math.hypot(fix.x_m - 60e3, fix.y_m - 40e3) < 1000.0
    assert not strict.ok and "RMS" in strict.reason
    v = loose.verify_params(FixParams())
    assert (v.inlier_r, v.max_rms_px, v.min_inliers) == (0.25, 12.0, 4)
    assert LostInSpaceParams().verify_params(FixParams()).inlier_r == FixParams().inlier_r


def test_lis_two_tier_settings_are_checked():
    from crater_synth.errors import UserError

    two = compose_nav(["nav/lost_in_space=two-tier"]).lost_in_space
    assert two.vote_min_score is not None and two.inlier_r is not None
    assert compose_nav([]).lost_in_space.vote_min_score is None  # south-choice: one tier
    one = compose_nav(["nav/lost_in_space=two-tier", "nav.lost_in_space.vote_min_score=null"]).lost_in_space
    assert one.vote_min_score is None and one.inlier_r == two.inlier_r
    for key, bad in (("inlier_r", "-1"), ("max_rms_px", "0"), ("vote_min_score", "nan")):
        with pytest.raises(UserError, match=key):
            compose_nav([f"nav.lost_in_space.{key}={bad}"])


def test_navigate_one_frame_lost_in_space_with_no_georeference(tmp_path):
    """`crater-synth navigate IMAGE --lost-in-space --pixel-m 400`: a south window (development data) with
    no georeference and no prior is placed on the map; --prior with --lost-in-space is refused."""
    import json

    from click.testing import CliRunner

    from crater_synth.cli import main
    from crater_synth.navigation.georef import ground_distance_km, stereo_forward
    from crater_synth.navigation.windows.mosaic import windows
    from crater_synth.navigation.windows.navigate import write_window

    frame = next(f for f in windows("validation", "south") if f.id == "S0_1536_0320")
    img = tmp_path / "w.png"
    write_window(img, frame)
    (tmp_path / "w.png.geo.json").unlink()  # the lander does not know where it is
    runner = CliRunner()
    r = runner.invoke(main, ["navigate", str(img), "--lost-in-space", "--prior", "-80,20", "--pixel-m", "400"])
    assert r.exit_code == 2 and "takes no prior" in r.output
    r = runner.invoke(main, ["navigate", str(img), "--lost-in-space", "--pixel-m", "400", "--pole", "south"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output.strip().splitlines()[-1])
    assert out["fix"] and out["position_prior"] == "none (lost in space)" and "error_km" not in out
    x, y = stereo_forward(out["lat"], out["lon"], "south")
    assert float(ground_distance_km(float(x), float(y), *frame.centre_xy, "south")) < 2.0
    assert (tmp_path / "w.nav.png").is_file()
    # The window is north-up: with the heading known it is placed on the map as well.
    args = ["navigate", str(img), "--lost-in-space", "--known-heading", "--pixel-m", "400", "--pole", "south"]
    r = runner.invoke(main, args)
    assert r.exit_code == 0, r.output
    out = json.loads(r.output.strip().splitlines()[-1])
    x, y = stereo_forward(out["lat"], out["lon"], "south")
    assert out["fix"] and float(ground_distance_km(float(x), float(y), *frame.centre_xy, "south")) < 2.0
    r = runner.invoke(main, ["navigate", str(img), "--known-heading", "--pixel-m", "400"])
    assert r.exit_code == 2 and "--lost-in-space only" in r.output
    # A second detector's craters join the verification (nav.lost_in_space.verify_detector).
    args = ["navigate", str(img), "--lost-in-space", "--pixel-m", "400", "--pole", "south"]
    plain = json.loads(runner.invoke(main, args).output.strip().splitlines()[-1])
    r = runner.invoke(main, [*args, "nav.lost_in_space.verify_detector=classical"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output.strip().splitlines()[-1])
    x, y = stereo_forward(out["lat"], out["lon"], "south")
    assert out["fix"] and float(ground_distance_km(float(x), float(y), *frame.centre_xy, "south")) < 2.0
    assert out["detections"] > plain["detections"] and len(out["landmarks"]) >= len(plain["landmarks"])


def test_nav_frames_lis_without_a_manifest_is_one_error(tmp_path):
    from click.testing import CliRunner

    from crater_synth.cli import main

    res = CliRunner().invoke(main, ["nav-frames-lis", str(tmp_path)])
    assert res.exit_code == 2 and "manifest.jsonl" in res.output and len(res.output.strip().splitlines()) == 1


def test_a_known_heading_keeps_only_the_votes_that_agree_with_it():
    """With the attitude's heading the true solution is still found; told a heading 90 degrees off, the
    vote finds nothing there (the true pairs all point the other way): no fix, never a wrong one."""
    rng = np.random.default_rng(7)
    lms = lis_map(rng)
    index = build_index(lms)
    dets = lis_frame(lms, (-250e3, 300e3), 37.0, rng)
    fix = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, index=index, heading_deg=37.0)
    assert fix.ok and math.hypot(fix.x_m + 250e3, fix.y_m - 300e3) < 1000.0
    off = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, index=index, heading_deg=127.0)
    assert not off.ok or math.hypot(off.x_m + 250e3, off.y_m - 300e3) < 1000.0
    assert not off.ok


def test_a_heading_tolerance_holds_the_fix_to_the_attitudes_heading():
    """A frame 5 degrees from the heading the attitude gives: within a vote cell (10 degrees) it is fixed as
    before; held to 2 degrees of the attitude it is not (a chance transform is turned like it), and a frame
    at the attitude's heading is still fixed at its place."""
    rng = np.random.default_rng(7)
    lms = lis_map(rng)
    index = build_index(lms)
    dets = lis_frame(lms, (-250e3, 300e3), 42.0, rng)
    loose = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, index=index, heading_deg=37.0)
    assert loose.ok and abs(loose.heading_deg - 42.0) < 1.0
    held = LostInSpaceParams(heading_tol_deg=2.0)
    assert not lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, held, index=index, heading_deg=37.0).ok
    fix = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, held, index=index, heading_deg=42.0)
    assert fix.ok and math.hypot(fix.x_m + 250e3, fix.y_m - 300e3) < 1000.0
    assert abs(fix.heading_deg - 42.0) < 1.0
    # heading-free, the tolerance changes nothing
    free = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, held, index=index)
    assert free.ok and free.heading_deg == pytest.approx(
        lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, index=index).heading_deg
    )
    with pytest.raises(ValueError, match="heading_tol_deg"):
        LostInSpaceParams(heading_tol_deg=12.0)


SIGNIFICANCE = LostInSpaceParams(candidate_score="significance", n_verify=64)


def test_chance_log10_is_the_poisson_tail_where_one_minus_the_cdf_rounds_to_zero():
    from scipy.stats import poisson

    from crater_synth.navigation.fix.lost_in_space import chance_log10

    for k, lam in ((1, 0.3), (6, 0.25), (6, 4.0), (12, 9.0), (3, 30.0)):
        assert chance_log10(k, lam) == pytest.approx(poisson.logsf(k - 1, lam) / math.log(10), abs=1e-9)
    assert chance_log10(40, 0.2) == pytest.approx(poisson.logsf(39, 0.2) / math.log(10), rel=1e-9)
    assert 1.0 - poisson.cdf(39, 0.2) == 0.0  # the naive tail is lost to rounding
    assert chance_log10(0, 0.5) == 0.0 and chance_log10(3, 0.0) == -math.inf


def test_chance_inliers_counts_compatible_detections_over_the_tolerance_discs():
    """One landmark in the frame (radius 25 px), one outside: of four detections, the two within the radius
    ratio of the one inside count, over its tolerance disc (2 px + 0.2 r) and the frame's area."""
    from crater_synth.navigation.fix.lost_in_space import chance_inliers
    from crater_synth.navigation.fix.solve import FixParams

    lms = [
        SimpleNamespace(x_m=100e3, y_m=-100e3, diameter_km=20.0),  # pixel (250, 250) under (a, b) below
        SimpleNamespace(x_m=900e3, y_m=-100e3, diameter_km=20.0),  # far outside the frame
    ]
    index = build_index(lms)
    a, b = complex(PIXEL_M), complex(0.0, 0.0)
    params = LostInSpaceParams(inlier_r=0.2)
    vparams = params.verify_params(FixParams())
    det_r = np.array([25.0, 30.0, 10.0, 60.0])
    expected = chance_inliers(det_r, index, a, b, SHAPE, PIXEL_M, params, vparams)
    disc = math.pi * (2.0 + 0.2 * 25.0) ** 2
    assert expected == pytest.approx(1.0 - math.exp(-2 * disc / (512 * 512)))


def test_significance_recovers_transforms_refuses_clutter_and_repetition():
    rng = np.random.default_rng(3)
    lms = lis_map(rng)
    index = build_index(lms, SIGNIFICANCE)
    for centre, heading in (((120e3, -80e3), 0.0), ((-250e3, 300e3), 37.0)):
        fix = lost_in_space_fix(lis_frame(lms, centre, heading, rng), lms, SHAPE, PIXEL_M, SIGNIFICANCE, index=index)
        assert fix.ok, fix.reason
        assert math.hypot(fix.x_m - centre[0], fix.y_m - centre[1]) < 1000.0
    clutter = [Detection(*rng.uniform(0, 512, 2), rng.uniform(12, 60), 0.5) for _ in range(40)]
    assert not lost_in_space_fix(clutter, lms, SHAPE, PIXEL_M, SIGNIFICANCE, index=index).ok
    motif = lis_map(rng, n=14, half_km=90.0)
    twice = motif + [SimpleNamespace(x_m=m.x_m + 400e3, y_m=m.y_m, diameter_km=m.diameter_km) for m in motif]
    dets = lis_frame(twice, (0.0, 0.0), 20.0, rng, keep=1.0, clutter=5, noise_px=0.5)
    fix = lost_in_space_fix(dets, twice, SHAPE, PIXEL_M, SIGNIFICANCE)
    assert not fix.ok and "ambiguous" in fix.reason
    strict = replace(SIGNIFICANCE, max_log10_nfa=-80.0)
    fix = lost_in_space_fix(dets, motif, SHAPE, PIXEL_M, strict)
    assert not fix.ok and "not significant" in fix.reason


def test_significance_weighs_a_rival_by_its_chance_not_its_count():
    """A true candidate of 7 large craters (few detections of their size: little chance) against a far rival
    of 5 small ones (many detections of their size): the inlier count calls them ambiguous (5 >= 7 - 2), their
    chance tells them apart."""
    from crater_synth.navigation.fix.lost_in_space import Candidate, chance_log10, unambiguous_candidate
    from crater_synth.navigation.fix.solve import Fix

    true = Fix(True, inliers=[(i, i) for i in range(7)], rms_px=1.0)
    rival = Fix(False, "only 5 landmarks agree (need 6)")
    counts = [Candidate(7.0, true, 1j, 0j, 0j, 7), Candidate(5.0, rival, 1j, 0j, 300e3 + 0j, 5)]
    best, no_fix = unambiguous_candidate(counts, LostInSpaceParams())
    assert best is None and "ambiguous" in no_fix.reason
    chance = [
        Candidate(-chance_log10(7, 0.05), true, 1j, 0j, 0j, 7),
        Candidate(-chance_log10(5, 2.0), rival, 1j, 0j, 300e3 + 0j, 5),
    ]
    best, no_fix = unambiguous_candidate(chance, SIGNIFICANCE)
    assert no_fix is None and best.fix is true


def test_significance_settings_are_checked():
    from crater_synth.errors import UserError

    sig = compose_nav(["nav/lost_in_space=significance"]).lost_in_space
    two = compose_nav(["nav/lost_in_space=two-tier"]).lost_in_space
    assert sig.candidate_score == "significance" and sig.n_verify == 128
    assert (sig.vote_min_score, sig.inlier_r, sig.max_rms_px) == (two.vote_min_score, two.inlier_r, two.max_rms_px)
    assert compose_nav([]).lost_in_space.candidate_score == "inliers"
    for key, bad in (("candidate_score", "votes"), ("ambiguity_log10", "-1"), ("max_log10_nfa", "nan")):
        with pytest.raises(UserError, match=key):
            compose_nav([f"nav.lost_in_space.{key}={bad}"])


def test_nav_eval_window_with_a_verify_detector_keeps_the_fix_and_indexes_both():
    """``navigate_window`` lost in space with a second detector: its new craters follow the first detector's in
    the detections returned, the fix still places the window, and every inlier indexes that list."""
    from dataclasses import replace as dc_replace

    from crater_synth.navigation.windows.evaluate import nav_eval_map, navigate_window
    from crater_synth.navigation.windows.mosaic import windows

    frame = next(f for f in windows("validation", "south") if f.id == "S0_1536_0320")
    landmarks, _ = nav_eval_map("south", None)
    nav = compose_nav(["nav/detector=template"])
    base = nav.lost_in_space
    plain = navigate_window(frame, landmarks, nav.detector, nav.fix, lis=(base, build_index(landmarks, base)))
    lis = dc_replace(base, verify_detector="classical")
    dets, _, fix, _ = navigate_window(frame, landmarks, nav.detector, nav.fix, lis=(lis, build_index(landmarks, lis)))
    assert len(dets) > len(plain[0]) and dets[: len(plain[0])] == plain[0]
    assert fix.ok and math.hypot(fix.x_m - frame.centre_xy[0], fix.y_m - frame.centre_xy[1]) < 2000.0
    assert all(0 <= i < len(dets) for i, _ in fix.inliers)


def test_navigate_keeps_a_known_heading_its_settings_give():
    """`navigate` once replaced nav.lost_in_space.known_heading by its --known-heading flag: a settings
    group that says the attitude gives the heading was run heading-free."""
    plain = NavigateRequest(Path("w.png"), Path("out"), lost_in_space=True)
    flag = NavigateRequest(Path("w.png"), Path("out"), lost_in_space=True, known_heading=True)
    assert not lost_in_space_settings(plain, compose_nav()).known_heading
    assert lost_in_space_settings(flag, compose_nav()).known_heading
    assert lost_in_space_settings(plain, compose_nav(["nav.lost_in_space.known_heading=true"])).known_heading


def test_a_fix_and_a_refusal_carry_the_best_candidates_support():
    """The support of the best verified candidate: a fix's inlier count (inlier scoring); a refused
    repeated pattern's too (its rival was as well supported); nan where no candidate verified."""
    rng = np.random.default_rng(5)
    motif = lis_map(rng, n=14, half_km=90.0)
    lms = motif + [SimpleNamespace(x_m=m.x_m + 400e3, y_m=m.y_m, diameter_km=m.diameter_km) for m in motif]
    dets = lis_frame(lms, (0.0, 0.0), 20.0, rng, keep=1.0, clutter=5, noise_px=0.5)
    fix = lost_in_space_fix(dets, motif, SHAPE, PIXEL_M)
    assert fix.ok and fix.support == len(fix.inliers)
    refused = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M)
    assert not refused.ok and refused.support >= 6
    nothing = [Detection(*rng.uniform(0, 512, 2), rng.uniform(12, 60), 0.5) for _ in range(40)]
    none = lost_in_space_fix(nothing, motif, SHAPE, PIXEL_M)
    assert not none.ok and math.isnan(none.support)
