"""Lost in space with the frame's own null: its detections turned by quarter turns, searched at the attitude's
heading, measure what chance reaches on this frame's craters (``nav.lost_in_space.null_turns``)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from crater_synth.errors import UserError
from crater_synth.navigation.detectors.classical import Detection
from crater_synth.navigation.fix.lost_in_space import (
    build_index,
    lost_in_space_fix,
    moved_detections,
    quarter_turn,
)
from crater_synth.navigation.settings import compose_nav

from helpers.lis_maps import PIXEL_M, SHAPE, lis_frame, lis_map

OWN_NULL = compose_nav(
    ["nav/lost_in_space=attitude", "nav.lost_in_space.max_log10_nfa=-2.0", "nav.lost_in_space.null_turns=3"]
).lost_in_space


def test_quarter_turns_move_a_frame_onto_itself():
    uv = np.array([[0.0, 0.0], [100.0, 30.0], [256.0, 256.0], [511.0, 7.0]])
    r = np.array([10.0, 20.0, 30.0, 40.0])
    once, r1, kept = moved_detections(uv, r, quarter_turn(SHAPE, 1), SHAPE)
    # u right, v down: a quarter turn takes the top-left corner to the top-right one; the centre stays.
    np.testing.assert_allclose(once[0], [512.0, 0.0])
    np.testing.assert_allclose(once[2], [256.0, 256.0])
    np.testing.assert_allclose(r1, r)
    assert not kept[0] and kept[1:].all()  # the corner lands on the frame's far edge, outside [0, 512)
    back = uv
    for _ in range(4):
        back, _, _ = moved_detections(back, r, quarter_turn(SHAPE, 1), SHAPE)
    np.testing.assert_allclose(back, uv, atol=1e-9)
    np.testing.assert_allclose(moved_detections(uv, r, quarter_turn(SHAPE, 2), SHAPE)[0][1], [412.0, 482.0])


def test_a_turned_wide_frame_keeps_only_what_stays_inside():
    shape = (200, 400)  # h, w
    uv = np.array([[10.0, 100.0], [200.0, 100.0], [390.0, 150.0]])
    turned, _, kept = moved_detections(uv, np.ones(3), quarter_turn(shape, 1), shape)
    np.testing.assert_allclose(turned[1], [200.0, 100.0])  # the centre
    assert kept.tolist() == [False, True, False]  # 190 px from the centre along u: beyond the 100 px half-height


def test_moved_detections_scale_radii_with_the_map():
    m = np.array([[1.3, 0.0, -10.0], [0.0, 1.3, 5.0]])
    uv, r, kept = moved_detections([[100.0, 100.0]], [10.0], m, SHAPE)
    np.testing.assert_allclose(uv, [[120.0, 135.0]])
    np.testing.assert_allclose(r, [13.0])
    assert kept.all()


def test_a_true_fix_stands_far_above_its_own_turned_craters():
    rng = np.random.default_rng(7)
    lms = lis_map(rng)
    index = build_index(lms, OWN_NULL)
    dets = lis_frame(lms, (-250e3, 300e3), 0.0, rng)
    fix = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, OWN_NULL, index=index, heading_deg=0.0)
    assert fix.ok, fix.reason
    assert math.hypot(fix.x_m + 250e3, fix.y_m - 300e3) < 1000.0
    assert math.isfinite(fix.null_support) and fix.support > fix.null_support + OWN_NULL.null_margin_log10
    # Without the null the same fix, unmeasured.
    plain = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, replace(OWN_NULL, null_turns=0), index=index, heading_deg=0.0)
    assert plain.ok and (plain.x_m, plain.y_m) == (fix.x_m, fix.y_m) and math.isnan(plain.null_support)


def test_a_fix_within_its_own_null_is_refused_and_says_why():
    rng = np.random.default_rng(7)
    lms = lis_map(rng)
    dets = lis_frame(lms, (-250e3, 300e3), 0.0, rng)
    demanding = replace(OWN_NULL, null_margin_log10=1000.0)
    fix = lost_in_space_fix(dets, lms, SHAPE, PIXEL_M, demanding, heading_deg=0.0)
    assert not fix.ok and "own turned craters" in fix.reason
    assert math.isfinite(fix.support) and math.isfinite(fix.null_support)


def test_clutter_is_not_searched_turned():
    """No candidate passes the gates: the null is not measured (it costs a search a turn)."""
    rng = np.random.default_rng(4)
    lms = lis_map(rng)
    clutter = [Detection(*rng.uniform(0, 512, 2), rng.uniform(12, 60), 0.5) for _ in range(40)]
    fix = lost_in_space_fix(clutter, lms, SHAPE, PIXEL_M, OWN_NULL, heading_deg=0.0)
    assert not fix.ok and math.isnan(fix.null_support)


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        (["nav.lost_in_space.null_turns=4"], "null_turns"),
        (["nav/lost_in_space=significance", "nav.lost_in_space.null_turns=3"], "known_heading"),
        (
            ["nav/lost_in_space=two-tier", "nav.lost_in_space.known_heading=true", "nav.lost_in_space.null_turns=1"],
            "significance",
        ),
        (["nav/lost_in_space=attitude", "nav.lost_in_space.null_margin_log10=-1"], "null_margin_log10"),
    ],
)
def test_own_null_settings_are_checked(overrides, key):
    with pytest.raises(UserError, match=key):
        compose_nav(overrides)
