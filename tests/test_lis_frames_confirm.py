"""Lost in space on rendered frames confirmed by appearance (``nav.lost_in_space.confirm=appearance`` in
``nav-frames-lis``): the places the vote offers become priors of the appearance search's 6-DOF fix."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from crater_core import exr, geometry
from crater_core.settings import TrajectorySettings
from crater_core.trajectory import frame_poses
from crater_synth.errors import UserError
from crater_synth.navigation.fix.lost_in_space import Candidate
from crater_synth.navigation.fix.refine import Refiner, lander_dem
from crater_synth.navigation.map.landmarks import load_default_map
from crater_synth.navigation.rendered import lost_in_space as lis_frames
from crater_synth.navigation.settings import compose_nav

from helpers.cli import run_cli


def _row(off_nadir_deg: float = 38.0) -> tuple[dict, float]:
    """(a frame row as `nav-frames` writes its pose fields, the boresight's range) of an oblique camera 140 km
    above (-85, 30)."""
    traj = TrajectorySettings(
        name="t", start=(-85.0, 30.0), end=(-85.0, 30.0), altitude_km=(140.0, 140.0), frames=1,
        off_nadir_deg=off_nadir_deg, off_nadir_azimuth_deg=90.0, fov_deg=30.0, width_px=64, sun="explicit",
        subsolar_lat_deg=0.0, subsolar_lon_deg=0.0, sun_elevation_deg=15.0, sun_azimuth_deg=60.0,
    )  # fmt: skip
    (pose,) = frame_poses(traj)
    cam = pose.pose_enu(pose.target_lat, pose.target_lon)
    row = {
        "index": 0,
        "rel_path": "frame_0000.exr",
        "frame_origin": {"lat": pose.target_lat, "lon": pose.target_lon},
        "pose": pose.as_dict(),
        "camera_enu": {"position_m": [float(v) for v in cam.position], "rotation": cam.rotation.tolist()},
    }
    target = geometry.latlon_to_mc(pose.target_lat, pose.target_lon)
    return row, float(np.linalg.norm(target - pose.position_mc))


def test_a_frames_true_place_is_the_prior_of_its_true_camera():
    """The camera over the map point under the true camera, at the height the range and attitude give, is the
    true camera: what the vote's place becomes for the search."""
    row, rng = _row()
    prior = lis_frames.place_prior(row, lis_frames.true_place(row), rng)
    assert np.allclose(prior, row["camera_enu"]["position_m"], atol=1.0)
    moved = lis_frames.place_prior(row, lis_frames.true_place(row) + 3000.0, rng)  # 3 km east on the map
    # 3 km along the ground, the same height (the camera's, 140 km up, about 8 % further than on the ground)
    centre = np.array([0.0, 0.0, -geometry.MOON_RADIUS_M])
    assert np.linalg.norm(moved - centre) == pytest.approx(np.linalg.norm(prior - centre), abs=1.0)
    assert 3000.0 < np.linalg.norm(moved - prior) < 3300.0


def _cand(row: dict, east_km: float, inliers: int = 5, support: float = 10.0) -> Candidate:
    """A vote's candidate ``east_km`` east of the frame's true place on the map."""
    place = lis_frames.true_place(row) + east_km * 1000.0
    return Candidate(support, None, 1.0 + 0j, 0j, place, inliers)


def _searched(monkeypatch, fixes: dict[float, float | None]):
    """search_frame_place replaced: a place x km east of the truth fixes the camera ``fixes[x]`` km east of the
    truth (None: no fix); returns the places searched (km)."""
    seen = []

    def fake(row, image, centre, range_m, landmarks, run, refiner):
        x_km = round((centre - lis_frames.true_place(row)).real / 1000.0, 3)
        seen.append(x_km)
        at = fixes[x_km]
        if at is None:
            return {"fix": False, "reason": "no putative landmark pairs"}
        truth = np.array(row["camera_enu"]["position_m"])
        at_m = (truth + [at * 1000.0, 0, 0]).tolist()
        return {"fix": True, "reason": "", "error_km": abs(at), "position_enu_m": at_m, "identified": 6,
                "attitude_error_deg": 0.02, "fix_source": "craters"}  # fmt: skip

    monkeypatch.setattr(lis_frames, "search_frame_place", fake)
    return seen


def _confirm(row, rng, cands, **changes):
    lis = dataclasses.replace(compose_nav(["nav/lost_in_space=confirmed"]).lost_in_space, **changes)
    return lis_frames.confirmed_six_dof(row, None, cands, rng, [], lis, refiner=object())


def test_the_first_confirmed_place_is_the_fix_and_every_place_is_reported(monkeypatch):
    row, rng = _row()
    seen = _searched(monkeypatch, {400.0: None, 1.0: 0.3})
    out = _confirm(row, rng, [_cand(row, 400.0, support=20.0), _cand(row, 1.0, support=12.0)])
    assert seen == [400.0, 1.0]  # best supported first
    assert out["fix"] and out["error_km"] == pytest.approx(0.3) and out["fix_source"] == "craters"
    assert [p["place_km"] for p in out["places"]] == pytest.approx([400.0, 1.0], rel=0.01)
    assert [p["fix"] for p in out["places"]] == [False, True]


def test_two_places_confirmed_apart_make_the_frame_ambiguous_and_near_ones_agree(monkeypatch):
    row, rng = _row()
    _searched(monkeypatch, {0.0: 0.2, 300.0: 300.0, 10.0: 0.4})
    out = _confirm(row, rng, [_cand(row, 0.0, support=20.0), _cand(row, 300.0, support=12.0)])
    assert not out["fix"] and out["reason"].startswith("ambiguous")
    # a second place 10 km off that the search brings back to the truth is the same place
    out = _confirm(row, rng, [_cand(row, 0.0, support=20.0), _cand(row, 10.0, support=12.0)])
    assert out["fix"] and out["error_km"] == pytest.approx(0.2)


def test_places_with_too_few_landmarks_are_not_searched_and_the_dem_is_needed(monkeypatch):
    row, rng = _row()
    seen = _searched(monkeypatch, {})
    out = _confirm(row, rng, [_cand(row, 0.0, inliers=2)])
    assert not out["fix"] and out["places"] == [] and seen == []
    lis = compose_nav(["nav/lost_in_space=confirmed"]).lost_in_space
    with pytest.raises(UserError, match="DEM"):
        lis_frames.confirmed_six_dof(row, None, [_cand(row, 0.0)], rng, [], lis, refiner=None)


def test_the_confirmation_searches_with_the_appearance_preset_at_its_reach():
    lis = dataclasses.replace(compose_nav(["nav/lost_in_space=confirmed"]).lost_in_space, confirm_min_landmarks=7)
    run = lis_frames.confirm_run(lis)
    assert run.appearance is not None and run.method == "pnp" and run.refine_pnp
    assert run.fparams.prior_sigma_km == lis.confirm_reach_km and run.fparams.min_inliers == 7
    assert run.pnp_attitude_sigma_deg == lis_frames.LIS_ATTITUDE_SIGMA_DEG


def test_places_elsewhere_count_only_confirmations_away_from_the_truth(monkeypatch):
    row, rng = _row()
    lms = [
        dataclasses.make_dataclass("L", ["x_m", "y_m", "diameter_km"])(x * 1000.0, 0.0, 20.0)
        for x in range(-900, 900, 50)
    ]
    calls = iter([{"fix": True, "error_km": 600.0, "identified": 5}, {"fix": True, "error_km": 0.4, "identified": 9},
                  {"fix": False, "reason": "x"}])  # fmt: skip
    monkeypatch.setattr(lis_frames, "search_frame_place", lambda *a: next(calls))
    lis = compose_nav(["nav/lost_in_space=confirmed"]).lost_in_space
    chance = lis_frames.places_null(row, None, rng, lms, lis, object(), 3)
    assert chance == [{"frame": 0, "landmarks": 5, "error_km": 600.0}]
    summary = lis_frames.confirmation_summary(
        [{"six_dof": {"places": [{"place_km": 0.5, "fix": True, "error_km": 0.3},
                                 {"place_km": 80.0, "fix": True, "error_km": 80.0},
                                 {"place_km": 9.0, "fix": True, "error_km": 0.5}]}}, {"six_dof": {"fix": False}}],
        3, chance,
    )  # fmt: skip
    assert summary["places_searched"] == 3 and summary["wrong_places_searched"] == 2
    assert summary["wrong_places_confirmed"] == 1 and summary["elsewhere"]["places"] == 6


def test_places_elsewhere_need_a_confirmation(tmp_path):
    with pytest.raises(UserError, match="--places"):
        lis_frames.evaluate_lis_dir(tmp_path, compose_nav(["nav/preset=synthetic"]), places=2)


@pytest.mark.integration
def test_a_rendered_oblique_frame_is_confirmed_at_its_place_and_nowhere_else(tmp_path):
    """One frame of the oblique development arc (38 degrees off nadir, the Sun 15 degrees up), rendered: from a
    place 3 km off its true one the appearance search fixes its 6-DOF pose within a kilometre; a place 500 km away
    confirms nothing, and neither do places elsewhere. The terrain offers its true place."""
    out = tmp_path / "frames"
    sun = ["trajectory.sun=explicit", "trajectory.sun_elevation_deg=15", "trajectory.sun_azimuth_deg=60"]
    args = ["nav-frames", "trajectory=oblique_arc_south_c", *sun, f"data_dir={tmp_path / 'data'}", "render.workers=1"]
    proc = run_cli(*args, "--out", out, "--frames", "7", timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (row,) = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    ch = exr.read_channels(out / row["rel_path"], ("IF", "depth"))
    rng = lis_frames.boresight_range_m(ch["depth"])
    lms = load_default_map("south")[0]
    lis = compose_nav(["nav/lost_in_space=confirmed-frames"]).lost_in_space
    refiner = Refiner(lander_dem("south"))
    cands = [_cand(row, 3.0, support=20.0), _cand(row, 500.0, support=10.0)]
    r = lis_frames.confirmed_six_dof(row, ch["IF"], cands, rng, lms, lis, refiner)
    assert r["fix"] and r["error_km"] < 1.0 and r["attitude_error_deg"] < 0.3, r
    assert [p["fix"] for p in r["places"]] == [True, False]
    assert lis_frames.places_null(row, ch["IF"], rng, lms, lis, refiner, 2) == []
    # The terrain's best place (the frame's ground view against the DEM shaded under its Sun) is its own, and
    # the confirmation fixes the frame from it with no vote at all.
    terrain = compose_nav(["nav/lost_in_space=terrain-frames", "nav.lost_in_space.confirm_hypotheses=0"]).lost_in_space
    ((place, ncc),) = lis_frames.frame_terrain_places(row, ch["IF"], rng, terrain)
    assert abs(place - lis_frames.true_place(row)) < 3000.0 and ncc > 0.5
    r = lis_frames.confirmed_six_dof(row, ch["IF"], [], rng, lms, terrain, refiner)
    assert r["fix"] and r["error_km"] < 1.0 and [p["source"] for p in r["places"]] == ["terrain"], r
    # A frame all in shadow is an answer of "no fix", not the end of the folder's run.
    nav = compose_nav(["nav/preset=synthetic", "nav/lost_in_space=terrain-frames"])
    index = lis_frames.build_index(lms, nav.lost_in_space)
    dark = lis_frames.lis_frame(row, np.zeros_like(ch["IF"]), ch["depth"], lms, nav, index, refiner=refiner)
    assert not dark["fix"] and not dark["six_dof"]["fix"] and dark["detections"] == 0, dark
    assert "no terrain place" in dark["six_dof"]["reason"], dark
