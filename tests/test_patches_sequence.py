"""Terrain patches (navigation/patches.py) and sequential priors (navigation/sequence.py)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from crater_core import exr, geometry
from crater_synth.navigation.fix.patches import PATCH_SOURCE, PatchParams, ground_points, patch_landmarks
from crater_synth.navigation.fix.sequence import SequenceParams, frame_point_mc, last_fix, propagated_prior
from crater_synth.navigation.fix.solve import FixParams
from crater_synth.navigation.rendered import evaluate as frames_eval


def _row(index: int, lat0: float, lon0: float, position_enu) -> dict:
    return {
        "trajectory": "t",
        "index": index,
        "frame_origin": {"lat": lat0, "lon": lon0},
        "camera_enu": {"position_m": list(map(float, position_enu))},
    }


def test_prior_is_the_last_fix_carried_by_the_motion_and_its_bound_grows_with_the_distance():
    first = _row(0, -85.0, 10.0, [0.0, 0.0, 100e3])
    fix_enu = np.array([120.0, -80.0, 100e3 + 30.0])  # the fix's own error: 0.15 km
    last = last_fix(first, {"position_enu_m": fix_enu.tolist()})
    # The next frame 40 km along, in another frame's ENU (each frame has its own origin).
    second = _row(1, -85.3, 12.0, [500.0, 300.0, 90e3])
    exact = SequenceParams(drift_share=0.0)
    prior, sigma = propagated_prior(second, last, exact, seed=0, default_sigma_km=10.0)
    truth_mc = frame_point_mc(second, second["camera_enu"]["position_m"])
    error_mc = frame_point_mc(first, fix_enu) - frame_point_mc(first, first["camera_enu"]["position_m"])
    # No drift: the prior is the true camera plus the last fix's error, exactly.
    assert np.allclose(frame_point_mc(second, prior) - truth_mc, error_mc, atol=1e-6)
    assert sigma == exact.min_sigma_km
    # With drift: the prior moves by drift_share x distance travelled, horizontally; the bound is 3 x that.
    travelled = float(np.linalg.norm(truth_mc - last["true_mc"]))
    params = SequenceParams(drift_share=0.05)
    prior_d, sigma_d = propagated_prior(second, last, params, seed=0, default_sigma_km=100.0)
    drift = prior_d - prior
    assert abs(drift[2]) < 1e-6 and math.hypot(*drift[:2]) == pytest.approx(0.05 * travelled, rel=1e-9)
    assert sigma_d == pytest.approx(3 * 0.05 * travelled / 1000.0)
    assert propagated_prior(second, last, params, seed=1, default_sigma_km=100.0)[0] != pytest.approx(prior_d)
    # A bound no tighter than the lone frame's prior: the frame is navigated alone.
    assert propagated_prior(second, last, params, seed=0, default_sigma_km=sigma_d) is None


@pytest.mark.parametrize(
    "kw", [dict(drift_share=-0.1), dict(sigma_factor=0.5), dict(min_sigma_km=0.0), dict(drift_share=1.0)]
)
def test_bad_sequence_settings_are_refused(kw):
    with pytest.raises(ValueError, match="sequence"):
        SequenceParams(**kw)


@pytest.mark.parametrize("kw", [dict(grid=0), dict(grid=40), dict(half_share=0.0), dict(half_share=0.9)])
def test_bad_patch_settings_are_refused(kw):
    with pytest.raises(ValueError, match="patch"):
        PatchParams(**kw)


def test_patches_lie_on_the_dem_under_the_frame_grid():
    from crater_synth.navigation.fix.refine import lander_dem

    dem = lander_dem("south")
    lat0, lon0 = -85.0, 30.0
    c = np.array([0.0, 0.0, 100e3])
    nadir = np.array([[0.0, 0.0, -1.0]])
    lat, lon, h = ground_points(dem, c, nadir, (lat0, lon0))
    assert lat[0] == pytest.approx(lat0, abs=1e-9) and lon[0] == pytest.approx(lon0, abs=1e-9)
    assert h[0] == pytest.approx(float(dem.sample(np.array([lat0]), np.array([lon0])).heights[0]), abs=1e-6)
    # A ray that misses the Moon gives no point.
    up = ground_points(dem, c, np.array([[0.0, 0.0, 1.0]]), (lat0, lon0))
    assert np.isnan(up[0]).all()
    # A nadir 60-degree frame: grid x grid patches, unique ids, windows a tenth of the footprint each way.
    r_wc, k = frames_eval.cv_camera(np.eye(3), 512, 60.0)  # Blender camera: right east, up north, looking down
    params = PatchParams(grid=3, half_share=0.1)
    lms = patch_landmarks(dem, c, r_wc, k, 512, (lat0, lon0), "south", params)
    assert len(lms) == 9 and len({lm.id for lm in lms}) == 9 and {lm.source for lm in lms} == {PATCH_SOURCE}
    pts = geometry.mc_to_enu(np.array([lm.position_mc() for lm in lms]), lat0, lon0)
    from crater_synth.navigation.fix.pose import project_pinhole

    uv = project_pinhole(pts, r_wc, c, k)  # each point is seen at its cell's centre
    centres = (np.arange(3) + 0.5) / 3 * 512
    assert np.allclose(np.sort(uv[:, 0]), np.repeat(centres, 3), atol=1e-3)
    footprint = 512 / k[0, 0] * np.median((pts - c) @ r_wc[2])
    assert lms[0].diameter_km == pytest.approx(0.1 * footprint / 0.75 / 1000.0, rel=1e-9)


@pytest.mark.integration
def test_patches_fix_descent_frames_with_too_few_craters(tmp_path):
    """Two descent frames (67 and 55 km up: two map craters >= 10 km in view, no fix from craters) at 256 px:
    terrain patches (the appearance preset's default) fix both, every patch identification correct;
    --sequential carries frame 7's fix into frame 8's prior."""
    from click.testing import CliRunner

    from crater_synth.cli import main

    from helpers.cli import run_nav_frames

    out = tmp_path / "frames"
    proc = run_nav_frames(tmp_path / "data", out, "7,8", "trajectory.width_px=256")
    assert proc.returncode == 0, proc.stderr[-2000:]

    def run(*args):
        res = CliRunner().invoke(main, ["nav-frames-eval", str(out), "--json", str(tmp_path / "e.json"), *args])
        assert res.exit_code == 0, res.output
        return json.loads((tmp_path / "e.json").read_text())

    plain = run("--no-patches")
    assert [f["fix"] for f in plain["frames"]] == [False, False] and plain["summary"]["patches"] is None
    default = run()
    assert default["summary"]["patches"] == {"grid": 4, "half_share": 0.1}
    assert [f["fix_source"] for f in default["frames"]] == ["patches", "patches"]
    doc = run("--sequential")
    assert doc["summary"]["patches"] == {"grid": 4, "half_share": 0.1} and doc["summary"]["sequence"]["drift_share"]
    for f in doc["frames"]:
        assert f["fix"] and f["fix_source"] == "patches" and f["error_km"] < 1.0, f
        assert f["patches"]["identified"] >= 3 and f["patches"]["identified_correct"] == f["patches"]["identified"]
        assert 0.0 < f["sigma_horizontal_km"] < 1.0  # the fix's own 1-sigma, recorded with it
        position = f["fix_position"]  # the fixed camera: lat, lon, altitude above the sphere
        assert abs(position["altitude_m"] / 1e3 - f["altitude_km"]) < 5.0 and -90 < position["lat"] < -80
    assert doc["frames"][0]["prior_sigma_km"] == FixParams().prior_sigma_km
    assert doc["frames"][1]["prior_sigma_km"] < FixParams().prior_sigma_km  # carried from frame 7's fix
    # Two terrain workers prepare the windows: the same frames, to the bit.
    assert run("--patches", "--sequential", "--terrain-workers", "2")["frames"] == doc["frames"]
    # A lander DEM with a 10 m error: recorded, and no false fix from it.
    noisy = run("--patches", "--dem-error-m", "10")
    assert noisy["summary"]["dem_error"] == {"rms_m": 10.0, "wavelength_km": 5.0}
    assert all(not f["fix"] or f["error_km"] < 5.0 for f in noisy["frames"])
    # --results keys the record by the options and states them in its protocol.
    run("--sequential", "--results", str(tmp_path / "navigation.json"))
    rec = json.loads((tmp_path / "navigation.json").read_text())["synthetic"]
    (key,) = rec
    assert key == "descent_ridge/position/appearance/patches/sequential", key
    assert rec[key]["protocol"]["patches"]["grid"] == 4 and rec[key]["protocol"]["sequence"]["min_sigma_km"] == 1.0
    assert [f["fix_source"] for f in rec[key]["frames"]] == ["patches", "patches"]
    # `navigate FRAME`: the same fix for one frame (patches by default), the patches drawn.
    frame7 = out / "frame_0007.exr"
    res = CliRunner().invoke(main, ["navigate", str(frame7), "--out", str(tmp_path / "n.png")])
    assert res.exit_code == 0, res.output
    nav = json.loads(res.output.strip().splitlines()[-1])
    assert (
        nav["fix"]
        and nav["fix_source"] == "patches"
        and nav["error_km"] == pytest.approx(doc["frames"][0]["error_km"], abs=5e-4)
    )
    assert (tmp_path / "n.png").stat().st_size > 1000
    res = CliRunner().invoke(main, ["navigate", str(frame7), "--no-patches", "--out", str(tmp_path / "m.png")])
    assert res.exit_code == 0 and not json.loads(res.output.strip().splitlines()[-1])["fix"]
    # --six-dof: the attitude fixed too (from the patches here), and how far it is from the truth.
    res = CliRunner().invoke(main, ["navigate", str(frame7), "--six-dof", "--out", str(tmp_path / "s.png")])
    assert res.exit_code == 0, res.output
    six = json.loads(res.output.strip().splitlines()[-1])
    assert six["fix_method"].startswith("6-DOF")
    assert six["fix"] and six["error_km"] < 2.0 and 0.0 < six["attitude_error_deg"] < 2.0, six
    res = CliRunner().invoke(main, ["navigate", str(frame7), "--patches", "nav/preset=synthetic"])
    assert res.exit_code != 0 and "--patches needs the appearance search" in res.output
    # A frame all in shadow: the patches find nothing, an answer of "no fix".
    from crater_synth.navigation.fix.refine import Refiner, lander_dem
    from crater_synth.navigation.map.landmarks import load_default_map
    from crater_synth.navigation.rendered.labels import labelled_rows

    row = labelled_rows(out)[0]
    image = exr.read_channel(out / row["rel_path"], "IF")
    lms = load_default_map("south")[0]
    from crater_synth.navigation.settings import compose_nav

    run = frames_eval.frame_run(compose_nav(["nav/preset=appearance"]))
    refiner = Refiner(lander_dem("south"))
    dark = np.zeros_like(image)
    r = frames_eval.evaluate_frame(row, dark, lms, run, refiner=refiner)
    r = frames_eval.with_patch_fallback(r, row, dark, lms, refiner, PatchParams(), run)
    assert not r["fix"] and r["fix_source"] is None and r["patches"]["searched"] == 16


def test_patch_and_sequence_options_are_refused_where_they_do_not_apply(tmp_path):
    from click.testing import CliRunner

    from crater_synth.cli import main

    out = tmp_path / "none"
    out.mkdir()
    for args, message in (
        (["--patches", "nav/preset=synthetic"], "--patches needs the appearance search"),
        (["--refine-pose"], "--refine-pose refines a 6-DOF fix"),  # the default method: known attitude
        (["--refine-pose", "nav.frames.solver=pnp", "nav/preset=real-window"], "--refine-pose refines a 6-DOF fix"),
        (["--attitude-sigma-deg", "0.2"], "--attitude-sigma-deg 0.2: 0 to 10 degrees, with a refined 6-DOF fix"),
        (["nav.frames.solver=pnp", "--attitude-sigma-deg", "20"], "--attitude-sigma-deg 20"),
    ):
        res = CliRunner().invoke(main, ["nav-frames-eval", str(out), "--json", str(tmp_path / "t.json"), *args])
        assert res.exit_code != 0 and message in res.output and not (tmp_path / "t.json").exists()


def test_navigate_refuses_patches_where_they_do_not_apply(tmp_path):
    from click.testing import CliRunner

    from crater_synth.cli import main

    window = tmp_path / "window.png"
    window.write_bytes(b"")
    res = CliRunner().invoke(main, ["navigate", str(window), "--patches"])  # the default detector: template
    assert res.exit_code != 0 and "--patches needs the appearance search" in res.output
    res = CliRunner().invoke(main, ["navigate", str(window), "--six-dof"])
    assert res.exit_code != 0 and "--six-dof applies to rendered frames" in res.output


def test_patches_at_the_dem_edge_are_those_on_the_dem():
    """A frame reaching past the DEM: patches only where the DEM has data, no error."""
    from crater_synth.navigation.fix.refine import lander_dem

    r_wc, k = frames_eval.cv_camera(np.eye(3), 512, 60.0)
    lms = patch_landmarks(lander_dem("south"), np.array([0.0, 0.0, 150e3]), r_wc, k, 512, (-71.0, 0.0), "south")
    assert 0 < len(lms) < 16 and all(-74.0 < lm.lat < -68.0 for lm in lms)


def test_perturbed_dem_adds_a_seeded_field_of_the_asked_rms():
    import pickle

    from crater_synth.navigation.fix.refine import lander_dem
    from crater_synth.navigation.map.dem_error import DemErrorParams, PerturbedDem

    dem = lander_dem("south")
    noisy = PerturbedDem(dem, DemErrorParams(30.0, 5.0), "south", seed=0)
    rng = np.random.default_rng(0)
    lat, lon = rng.uniform(-89.0, -80.0, 4000), rng.uniform(-180.0, 180.0, 4000)
    err = noisy.error_m(lat, lon)
    assert 20.0 < float(np.sqrt(np.mean(err**2))) < 40.0  # a random field: its RMS near the asked one
    got = noisy.sample(lat[:50], lon[:50]).heights - dem.sample(lat[:50], lon[:50]).heights
    assert np.allclose(got, err[:50])
    assert noisy.pixel_size_m == dem.pixel_size_m  # everything else is the DEM's
    again = pickle.loads(pickle.dumps(noisy))  # what a terrain worker receives
    assert np.allclose(again.error_m(lat[:5], lon[:5]), err[:5])
    other = PerturbedDem(dem, DemErrorParams(30.0, 5.0), "south", seed=1)
    assert not np.allclose(other.error_m(lat[:5], lon[:5]), err[:5])
    with pytest.raises(ValueError, match="DEM error"):
        DemErrorParams(-1.0)


def test_dem_error_option_is_refused_where_it_does_not_apply(tmp_path):
    from click.testing import CliRunner

    from crater_synth.cli import main

    out = tmp_path / "none"
    out.mkdir()
    for args, message in (
        (["--dem-error-m", "30", "--results", str(tmp_path / "r.json")], "drop --dem-error-m"),
        (["--dem-error-m", "30", "--dem-error-km", "0.1"], "expected 0.5 to 500 km"),
        (["--dem-error-m", "30", "nav/preset=real-window"], "does not use the lander's DEM"),
    ):
        res = CliRunner().invoke(main, ["nav-frames-eval", str(out), "--json", str(tmp_path / "t.json"), *args])
        assert res.exit_code != 0 and message in res.output and not (tmp_path / "t.json").exists(), res.output


def test_error_arrow_is_magnified_by_a_stated_step():
    """navigate's error arrow on a rendered frame: truth -> fix, at least MIN_ARROW_PX long, its
    magnification a 1-2-5 step written beside it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from crater_synth.navigation.rendered.navigate import MIN_ARROW_PX, error_arrow

    row = {
        "frame_origin": {"lat": -85.0, "lon": 0.0},
        "pose": {"width_px": 512, "fov_deg": 60.0, "target_lat": -85.0, "target_lon": 0.0},
        "camera_enu": {"rotation": np.eye(3).tolist(), "position_m": [0.0, 0.0, 100e3]},
    }
    fig, ax = plt.subplots()
    caption = error_arrow(ax, {"position_enu_m": [30.0, 0.0, 100e3]}, row)  # 30 m east at 100 km: 0.13 px
    tip = np.array(ax.texts[-1].get_position())
    assert np.hypot(*(tip - 256.0)) >= MIN_ARROW_PX and caption.endswith("x500"), caption
    assert "x500" in ax.texts[-1].get_text()
    plt.close(fig)
