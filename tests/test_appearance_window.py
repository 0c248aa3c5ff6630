"""The appearance search on real mosaic windows (crater_synth.navigation.windows.appearance): the Sun
direction, a fix on a real south window, the refusal of a frame that does not match, bad settings."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from crater_core import geometry
from crater_core.settings_nav import AppearanceSettings
from crater_core.typed_config import SettingsError
from crater_synth.errors import UserError
from crater_synth.navigation.detectors.classical import DetectorSettingsError, detect
from crater_synth.navigation.fix.solve import FixParams
from crater_synth.navigation.settings import compose_nav
from crater_synth.navigation.windows.appearance import sun_direction_mc

# The appearance search's settings on map windows (configs/nav/detector/appearance.yaml).
APPEARANCE = compose_nav(["nav/detector=appearance"]).detector

# A south window (development data: the south's settings are chosen on every south window) with 26 map
# landmarks of D >= 15 km in view.
WINDOW_ID = "S0_1600_0384"


@pytest.fixture(scope="module")
def south():
    from crater_synth.navigation.map.landmarks import load_default_map
    from crater_synth.navigation.windows.mosaic import plan_windows, window_frame

    (w,) = [w for w in plan_windows("south") if w[0] == WINDOW_ID]
    return window_frame("south", *w), load_default_map("south")[0]


@pytest.mark.parametrize("lat, lon", [(-85.0, 30.0), (82.0, 250.0)])
def test_sun_direction_is_at_its_local_azimuth_and_elevation(lat, lon):
    east, north, up = geometry.enu_basis(lat, lon)
    s = sun_direction_mc(lat, lon, 0.0, 10.0)
    assert np.isclose(s @ up, math.sin(math.radians(10.0))) and np.isclose(s @ north, math.cos(math.radians(10.0)))
    s = sun_direction_mc(lat, lon, math.pi / 2, 3.0)
    assert np.isclose(s @ east, math.cos(math.radians(3.0))) and abs(s @ north) < 1e-12


def test_appearance_finds_the_map_landmarks_and_fixes_a_real_window(south):
    from crater_synth.navigation.windows.evaluate import run_frame

    frame, landmarks = south
    row = run_frame(frame, landmarks, APPEARANCE, FixParams())
    assert row["fix"], row["reason"]
    assert row["error_km"] < 0.8  # 2 mosaic pixels
    assert row["identified"] >= 5 and row["identified_correct"] >= 0.9 * row["identified"]
    # Nearly every detection is one of the map's landmarks where the mosaic shows it.
    assert row["n_detections"] >= 10 and len(row["matched"]) >= 0.9 * row["n_detections"]


def test_a_real_window_is_also_scored_against_the_crater_catalogue(south):
    """With the catalogue, a window's row lists the catalogued craters in view and which detections match
    them; every map landmark the search found near a catalogued crater counts for both."""
    from crater_synth.navigation.map.check import catalogue_craters
    from crater_synth.navigation.protocol import summarise
    from crater_synth.navigation.windows.evaluate import run_frame

    frame, landmarks = south
    listed = catalogue_craters("south")
    row = run_frame(frame, landmarks, APPEARANCE, FixParams(), listed=listed)
    assert len(row["catalogue_d_km"]) >= 10 and all(d >= 8.0 for d in row["catalogue_d_km"])
    assert set(row["matched_catalogue"]) <= set(range(row["n_detections"]))
    assert 0 < len(row["catalogue_found"]) <= len(row["catalogue_d_km"])
    cat = summarise([row])["against_catalogue"]
    assert cat["precision_15km"] >= summarise([row])["precision_15km"]  # more truth, never less precise


def test_a_window_that_does_not_show_the_map_gives_no_fix(south):
    """The window turned upside down: every landmark is predicted where the image shows something else.
    The search may still find a few look-alikes, but no consistent set: "no fix", never a wrong one."""
    from crater_synth.navigation.windows.evaluate import run_frame

    frame, landmarks = south
    turned = dataclasses.replace(frame, image=np.ascontiguousarray(frame.image[::-1, ::-1]))
    row = run_frame(turned, landmarks, APPEARANCE, FixParams())
    assert not row["fix"]
    assert row["n_detections"] < 0.5 * len(row["truth"])


def test_appearance_settings_and_misuse_are_refused(south):
    from crater_synth.navigation.windows.evaluate import navigate_window

    with pytest.raises(SettingsError, match="sun_el_deg"):
        AppearanceSettings(sun_el_deg=(0.0,))
    with pytest.raises(SettingsError, match="min_ncc"):
        AppearanceSettings(min_ncc=1.5)
    frame, landmarks = south
    with pytest.raises(DetectorSettingsError, match="position prior"):
        detect(frame.image, APPEARANCE, what="window")
    with pytest.raises(UserError, match="light_scope"):
        navigate_window(frame, landmarks, dataclasses.replace(APPEARANCE, light_scope="frame"), FixParams())


@pytest.mark.integration
def test_navigate_a_map_window_with_the_appearance_search(south, tmp_path):
    """`crater-synth navigate WINDOW.png nav/detector=appearance --light-azimuth A`: the window written as a PNG
    with its georeference sidecar, the light's image direction from the local light model."""
    import json

    from click.testing import CliRunner
    from PIL import Image

    from crater_synth.cli import main
    from crater_synth.navigation.windows.light import frame_light

    frame, _ = south
    png = tmp_path / "window.png"
    Image.fromarray(frame.image).save(png)
    (tmp_path / "window.png.geo.json").write_text(json.dumps(frame.georef.as_dict()))
    theta = math.degrees(frame_light(frame, APPEARANCE)["light_dir"])
    r = CliRunner().invoke(main, ["navigate", str(png), "nav/detector=appearance", "--light-azimuth", f"{theta:.2f}"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output.strip().splitlines()[-1])
    assert out["fix"] and out["error_km"] < 0.8 and len(out["landmarks"]) >= 5
    assert (tmp_path / "window.nav.png").is_file() and (tmp_path / "window.nav.json").is_file()
    # No prior: the template's lost-in-space fix (heading known) is the search's prior, as in nav-eval.
    lis = ["--lost-in-space", "--known-heading", "--out", str(tmp_path / "lis.png")]
    r = CliRunner().invoke(
        main, ["navigate", str(png), "nav/detector=appearance", "--light-azimuth", f"{theta:.2f}", *lis]
    )
    assert r.exit_code == 0, r.output
    out = json.loads(r.output.strip().splitlines()[-1])
    assert out["position_prior"] == "none (lost in space)" and out["fix"] and out["error_km"] < 0.8


@pytest.mark.integration
def test_nav_eval_takes_the_prior_offset_and_refuses_a_nonsense_one(tmp_path):
    import json

    from click.testing import CliRunner

    from crater_synth.cli import main

    out = tmp_path / "nav.json"
    args = ["nav-eval", "--pole", "south", "--split", "validation", "--every", "60", "nav/detector=appearance"]
    r = CliRunner().invoke(main, [*args, "--prior-offset-km", "8", "--out", str(out)])
    assert r.exit_code == 0, r.output
    doc = json.loads(out.read_text())
    assert doc["protocol"]["prior_offset_km"] == 8.0 and doc["protocol"]["position_prior"] == "truth + 8 km"
    assert doc["methods"]["appearance"]["splits"]["validation"]["all_windows"]["windows"] == 2
    r = CliRunner().invoke(main, [*args, "--prior-offset-km", "200", "--out", str(tmp_path / "bad.json")])
    assert r.exit_code == 2 and "--prior-offset-km=200" in r.output and len(r.output.strip().splitlines()) == 1
    assert not (tmp_path / "bad.json").exists()


def test_a_prior_beyond_the_search_gives_no_fix(south):
    """The prior offset reaches the search: 60 km off (six times the 10 km the search reaches), no landmark
    is where it is looked for, and the answer is "no fix"."""
    from crater_synth.navigation.windows.evaluate import run_frame

    frame, landmarks = south
    row = run_frame(frame, landmarks, APPEARANCE, FixParams(), prior_offset_km=60.0)
    assert not row["fix"] and len(row["matched"]) <= 2


def test_lost_in_space_then_the_appearance_search(south):
    """No prior: the template's lost-in-space fix (heading known) is the search's prior; the chain's fix
    is the search's (every fix landmark found by its appearance), as accurate as with a prior."""
    import dataclasses as dc

    from crater_synth.navigation.fix.lost_in_space import build_index
    from crater_synth.navigation.windows.evaluate import run_frame

    frame, landmarks = south
    lis_params = dc.replace(compose_nav().lost_in_space, known_heading=True)
    lis = (lis_params, build_index(landmarks, lis_params))
    row = run_frame(frame, landmarks, APPEARANCE, FixParams(), lis=lis)
    assert row["fix"], row["reason"]
    assert row["error_km"] < 0.8 and row["identified"] >= 10 and len(row["matched"]) >= 0.9 * row["n_detections"]


def test_window_patches_lie_on_the_dem_under_the_window_grid(south):
    from crater_synth.navigation.fix.patches import PATCH_SOURCE, PatchParams, window_patches
    from crater_synth.navigation.fix.refine import RefineParams, lander_dem

    frame, _ = south
    dem = lander_dem("south")
    found = window_patches(dem, frame.georef, frame.image.shape, PatchParams(grid=3, half_share=0.1))
    assert len(found) == 9 and len({p.id for p in found}) == 9 and {p.source for p in found} == {PATCH_SOURCE}
    u, v = frame.georef.xy_to_uv(np.array([p.x_m for p in found]), np.array([p.y_m for p in found]))
    cells = (np.arange(3) + 0.5) / 3 * 512
    assert np.allclose(np.unique(np.round(u, 6)), cells) and np.allclose(np.unique(np.round(v, 6)), cells)
    heights = dem.sample(np.array([p.lat for p in found]), np.array([p.lon for p in found])).heights
    assert np.allclose([p.rim_height_m for p in found], heights)
    # Each window is a tenth of the frame's width each way.
    half_km = RefineParams().window_diameters * found[0].diameter_km
    assert half_km == pytest.approx(0.1 * 512 * frame.georef.pixel_m / 1000.0)


def test_terrain_patches_fix_a_real_window_and_refuse_one_that_does_not_match(south):
    """The window navigated with terrain patches alone (no crater): found by their predicted appearance, the
    identifications where the true georeference places the patches' points; turned upside down, no fix."""
    from crater_synth.navigation.fix.patches import PatchParams
    from crater_synth.navigation.protocol import summarise
    from crater_synth.navigation.windows.evaluate import run_frame

    frame, landmarks = south
    row = run_frame(frame, landmarks, APPEARANCE, FixParams(), patches=PatchParams())
    p = row["patches_alone"]
    assert p["n_patches"] == 16 and p["fix"], p["reason"]
    assert p["error_km"] < 0.8 and p["identified"] >= 5 and p["identified_correct"] >= 0.9 * p["identified"]
    assert row["fix_source"] == "craters"  # the craters fix it first; the patches are scored alone beside them
    s = summarise([row])
    assert s["fixed_by_patches"] == 0 and s["patches_alone"]["fix_rate"] == 1.0
    turned = dataclasses.replace(frame, image=np.ascontiguousarray(frame.image[::-1, ::-1]))
    row = run_frame(turned, landmarks, APPEARANCE, FixParams(), patches=PatchParams())
    assert not row["patches_alone"]["fix"] and not row["fix"] and row["fix_source"] is None


def test_a_window_its_craters_do_not_fix_takes_the_patches_fix(south, monkeypatch):
    """Where the craters give no fix (here: no crater in the map), the patches' fix is the window's."""
    from crater_synth.navigation.fix.patches import PatchParams
    from crater_synth.navigation.windows.evaluate import run_frame

    frame, landmarks = south
    row = run_frame(frame, [], APPEARANCE, FixParams(), patches=PatchParams())
    assert row["fix"] and row["fix_source"] == "patches" and row["error_km"] == row["patches_alone"]["error_km"]
    assert row["identified_correct"] == row["patches_alone"]["identified_correct"]


def test_nav_eval_patches_needs_the_appearance_search(tmp_path):
    from click.testing import CliRunner

    from crater_synth.cli import main

    args = ["nav-eval", "--pole", "south", "--split", "validation", "--every", "60", "--patches"]
    for extra in (["nav/detector=template"], ["nav/detector=appearance", "--lost-in-space"]):
        r = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "x.json"), *extra])
        assert r.exit_code == 2 and "--patches needs nav/detector=appearance" in r.output
        assert not (tmp_path / "x.json").exists()


def test_navigate_a_map_window_with_terrain_patches(south, tmp_path):
    """`navigate WINDOW.png nav/detector=appearance`: with a map of two craters the craters cannot fix the window
    (`--no-patches`); its terrain patches do (drawn as cyan squares), and the JSON says so."""
    import json

    from click.testing import CliRunner
    from PIL import Image

    from crater_synth.cli import main
    from crater_synth.navigation.map.landmarks import load_default_map, to_geojson
    from crater_synth.navigation.windows.light import frame_light

    frame, _ = south
    png = tmp_path / "window.png"
    Image.fromarray(frame.image).save(png)
    (tmp_path / "window.png.geo.json").write_text(json.dumps(frame.georef.as_dict()))
    landmarks, prov = load_default_map("south")
    u, v = frame.georef.xy_to_uv(np.array([lm.x_m for lm in landmarks]), np.array([lm.y_m for lm in landmarks]))
    inside = [lm for lm, a, b in zip(landmarks, u, v) if 0 <= a < 512 and 0 <= b < 512]
    (tmp_path / "two.geojson").write_text(to_geojson(inside[:2], prov))
    theta = math.degrees(frame_light(frame, APPEARANCE)["light_dir"])
    args = ["navigate", str(png), "nav/detector=appearance", "--light-azimuth", f"{theta:.2f}"]
    args += ["--map", str(tmp_path / "two.geojson")]
    r = CliRunner().invoke(main, [*args, "--no-patches"])
    assert r.exit_code == 0, r.output
    assert not json.loads(r.output.strip().splitlines()[-1])["fix"]
    r = CliRunner().invoke(main, args)  # patches by default with the appearance search
    assert r.exit_code == 0, r.output
    out = json.loads(r.output.strip().splitlines()[-1])
    assert out["fix"] and out["fix_source"] == "patches" and out["error_km"] < 0.8
    assert all(name.startswith("patch:") for name in out["landmarks"]) and len(out["landmarks"]) >= 5
    assert (tmp_path / "window.nav.png").stat().st_size > 10_000
    r = CliRunner().invoke(main, ["navigate", str(png), "--patches", "nav/detector=template"])
    assert r.exit_code == 2 and "--patches needs the appearance search" in r.output


def test_window_patches_off_the_dem_are_left_out(south):
    """A window reaching past the DEM keeps the patches on it; one wholly off it has none, and its patch
    navigation is an answer of "no fix", not an error."""
    from crater_synth.navigation.fix.patches import PatchParams, window_patches
    from crater_synth.navigation.fix.refine import Refiner, lander_dem
    from crater_synth.navigation.georef import Georef
    from crater_synth.navigation.windows.appearance import window_patch_fix

    frame, _ = south
    dem = lander_dem("south")
    shape, pixel = frame.image.shape, frame.georef.pixel_m
    half_extent = 0.5 * dem.width * dem.pixel_size_m  # the polar stereographic DEM is a square about the pole
    # The window's left half on the DEM, its right half past the edge: the patches of the left half only.
    across = Georef("south", half_extent - 0.5 * shape[1] * pixel, 0.5 * shape[0] * pixel, pixel)
    assert 4 <= len(window_patches(dem, across, shape, PatchParams())) < 16
    far = Georef("south", 5.0e6, 5.0e6, pixel)  # thousands of km from the pole
    assert window_patches(dem, far, shape, PatchParams()) == []
    found, dets, fix = window_patch_fix(frame.image, far, 0.0, APPEARANCE, FixParams(), Refiner(dem), PatchParams())
    assert found == [] and dets == [] and not fix.ok and fix.reason == "no patch on the DEM"


@pytest.mark.integration
def test_nav_eval_patches_in_full_joins_the_pole_entry_as_its_own_method(tmp_path, monkeypatch):
    """`nav-eval --pole north --patches --out FILE nav/detector=appearance` over the pole's splits adds the method
    'appearance+patches' to the pole's entry of the results file; the craters-only 'appearance' entry and
    every other method stay as they were. (The windows are cut to two to keep the test short.)"""
    import json
    import shutil

    from click.testing import CliRunner

    from crater_synth.cli import main
    from crater_synth.navigation.windows import evaluate
    from crater_synth.paths import SOURCE_ROOT

    results = tmp_path / "navigation.json"
    shutil.copyfile(SOURCE_ROOT / "docs" / "results" / "navigation.json", results)  # the committed record
    every_window = evaluate.windows  # nav-eval's own binding of mosaic.windows
    monkeypatch.setattr(evaluate, "windows", lambda split=None, pole="south": every_window(split, pole)[100:102])
    before = json.loads(results.read_text())["regions"]["north"]["methods"]
    r = CliRunner().invoke(
        main, ["nav-eval", "--pole", "north", "--patches", "--out", str(results), "nav/detector=appearance"]
    )
    assert r.exit_code == 0, r.output
    after = json.loads(results.read_text())["regions"]["north"]["methods"]
    others = [k for k in before if k != evaluate.PATCHES_METHOD]
    assert others and set(after) == {*others, evaluate.PATCHES_METHOD}
    assert all(after[k] == before[k] for k in others)
    test = after[evaluate.PATCHES_METHOD]["splits"]["test"]
    assert test["all_windows"]["windows"] == 2 and test["all_windows"]["patches_alone"]["patches_per_window"] == 16
    assert "terrain patches" in after[evaluate.PATCHES_METHOD]["detector"]["method"]
