"""The procedural crater field (crater_core/procedural.py): deterministic, the production function's
SFD, Pike's morphometry on the generated grid, monotone degradation, exact overprint flags, the
config group and the preview. numpy only, no Blender; each test runs in about a second or less."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import crater_core.procedural as P
from blender_gen.job import load_terrain
from crater_core.geometry import curvature_drop_m
from crater_core.settings_procedural import ProceduralSettings
from crater_synth.config import ConfigError, compose_group
from crater_synth.tools import procedural_preview

SMALL = ProceduralSettings(size_px=256, spacing_m=20.0, surface_age_gyr=3.5, d_min_px=3.0)


def _bilinear(grid: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    r0, c0 = np.floor(rows).astype(int), np.floor(cols).astype(int)
    fr, fc = rows - r0, cols - c0
    g = grid
    return (
        g[r0, c0] * (1 - fr) * (1 - fc)
        + g[r0 + 1, c0] * fr * (1 - fc)
        + g[r0, c0 + 1] * (1 - fr) * fc
        + g[r0 + 1, c0 + 1] * fr * fc
    )


def _radial(terrain: P.ProceduralTerrain, crater: P.Crater, s_max: float = 1.5, n_az: int = 180):
    """Heights on rays from the centre: (s, (n_az, n_s)), s = r / R."""
    radius_px = 0.5 * crater.diameter_m / terrain.spacing_m
    s = np.linspace(0.0, s_max, 601)
    az = np.linspace(0.0, 2 * np.pi, n_az, endpoint=False)[:, None]
    rows = crater.y_m / terrain.spacing_m + s * radius_px * np.sin(az)
    cols = crater.x_m / terrain.spacing_m + s * radius_px * np.cos(az)
    return s, _bilinear(terrain.height, rows, cols)


def _single(diameter_m: float, spacing_m: float, age_myr: float = 0.0, kappa: float = 0.0, size: int = 0):
    size = size or int(2.0 * P.PROFILE_EXTENT_RADII * diameter_m / spacing_m) + 8
    centre = 0.5 * (size - 1) * spacing_m
    table = P.crater_table([diameter_m], [centre], [centre], [age_myr], kappa)
    return P.build(np.zeros((size, size)), spacing_m, table)


def test_deterministic_by_seed():
    a, b = P.generate(SMALL), P.generate(SMALL)
    assert np.array_equal(a.height, b.height) and a.craters == b.craters and len(a.craters) > 100
    c = P.generate(ProceduralSettings(**{**SMALL.as_dict(), "seed": 1}))
    assert not np.array_equal(a.height, c.height)


def test_primaries_follow_the_production_function():
    """Primaries centred on the grid: count within 4 sigma of the production function's expectation,
    diameters' distribution within the KS 1 % critical distance of its truncated CDF, local slope."""
    st = ProceduralSettings(size_px=512, spacing_m=20.0, surface_age_gyr=3.8, d_min_px=3.0)
    prim = P._primaries(st, np.random.default_rng(0))  # what generate() places, before the grid
    side = (st.size_px - 1) * st.spacing_m
    inside = (prim["x"] >= 0) & (prim["x"] <= side) & (prim["y"] >= 0) & (prim["y"] <= side)
    d = prim["diameter"][inside]
    d_min, d_max = st.d_min_px * st.spacing_m, st.d_max_fraction * st.size_px * st.spacing_m
    cum = P.production_cumulative(np.array([d_min, d_max]), st.surface_age_gyr)
    expected = side**2 * (cum[0] - cum[1])
    assert abs(d.size - expected) < 4.0 * math.sqrt(expected) and d.size > 1000
    d.sort()
    model = (cum[0] - P.production_cumulative(d, st.surface_age_gyr)) / (cum[0] - cum[1])
    ks = np.max(np.abs(model - np.arange(1, d.size + 1) / d.size))
    assert ks < 1.63 / math.sqrt(d.size)
    # Cumulative slope over the first decade: the NPF's own, about -3 at 60-600 m.
    grid = np.geomspace(d_min, 10 * d_min, 8)
    counts = np.array([(d >= g).sum() for g in grid])
    slope = np.polyfit(np.log10(grid), np.log10(counts), 1)[0]
    assert abs(slope - float(np.mean(P.production_slope(grid)))) < 0.2
    assert -3.8 < slope < -2.5


def test_secondaries_are_steeper_shallow_and_near_their_parent():
    """300 copies of one 60 km primary on an 819 km grid: the secondaries' diameters follow the steep
    truncated power law, they lie 2-10 primary radii out, and they are shallow (d/D = 0.1)."""
    st = ProceduralSettings(size_px=4096, spacing_m=200.0, d_min_px=3.0, secondary_fraction=10.0)
    centre, parent_d = 0.5 * 4095 * 200.0, 60000.0
    prim = {"diameter": np.full(300, parent_d), "x": np.full(300, centre), "y": np.full(300, centre)}
    prim["age_myr"] = np.full(300, 100.0)
    sec = P._secondaries(prim, st, np.random.default_rng(0))
    d, d_min, top = np.sort(sec["diameter"]), 600.0, P.LARGEST_SECONDARY_FRACTION * parent_d
    assert abs(d.size - 3000) < 4 * math.sqrt(3000) and d.min() >= d_min and d.max() <= top
    b = P.SECONDARY_SFD_SLOPE
    model = (d_min**-b - d**-b) / (d_min**-b - top**-b)
    assert np.max(np.abs(model - np.arange(1, d.size + 1) / d.size)) < 1.63 / math.sqrt(d.size)
    r = np.hypot(sec["x"] - centre, sec["y"] - centre) / (0.5 * parent_d)
    lo, hi = P.SECONDARY_RANGE_RADII
    assert np.percentile(r, 1) > 0.75 * lo and np.percentile(r, 99) < 1.3 * hi
    assert np.all(sec["age_myr"] == 100.0) and np.all(sec["parent"] >= 0)
    shape = P.morphometry(np.array([500.0, 500.0]), np.array([False, True]))
    assert shape["depth"][1] == pytest.approx(0.1 * 500.0) and shape["depth"][0] > 1.9 * shape["depth"][1]


@pytest.mark.parametrize("diameter_m, spacing_m", [(3000.0, 50.0), (300.0, 5.0)])
def test_fresh_simple_crater_rim_at_half_diameter_and_pike_depth(diameter_m, spacing_m):
    t = _single(diameter_m, spacing_m)
    (c,) = t.craters
    assert c.morph_class == "simple" and c.degradation == 0.0 and c.visible_rim_fraction == 1.0
    pike = 0.196 * (diameter_m / 1000.0) ** 1.010 * 1000.0
    assert c.depth_m == pytest.approx(pike) and c.fresh_depth_m == pytest.approx(pike)
    assert c.rim_height_m == pytest.approx(0.036 * (diameter_m / 1000.0) ** 1.014 * 1000.0)
    s, h = _radial(t, c)
    rim_s = s[np.argmax(h, axis=1)]
    assert abs(rim_s.mean() - 1.0) * 0.5 * diameter_m < 0.75 * spacing_m  # crest at D/2, under a pixel
    assert np.all(np.abs(rim_s - 1.0) * 0.5 * diameter_m <= 1.0 * spacing_m)
    measured = t.height.max() - t.height.min()
    assert measured == pytest.approx(pike, rel=0.02)


def test_fresh_complex_crater_floor_peak_terraces_and_pike_depth():
    d_km = 40.0
    t = _single(d_km * 1000.0, 200.0)
    (c,) = t.craters
    assert c.morph_class == "complex" and c.terraces == 2
    assert c.depth_m == pytest.approx(1.044 * d_km**0.301 * 1000.0)
    assert c.rim_height_m == pytest.approx(0.236 * d_km**0.399 * 1000.0)
    assert c.floor_diameter_m == pytest.approx(0.187 * d_km**1.249 * 1000.0)
    assert c.peak_height_m == pytest.approx(0.0006 * d_km**1.969 * 1000.0)
    s, h = _radial(t, c)
    rim_s = s[np.argmax(h, axis=1)]
    assert abs(rim_s.mean() - 1.0) * 0.5 * c.diameter_m < 0.75 * 200.0  # the cusp sampled on pixel nodes
    floor_level = c.rim_height_m - c.depth_m
    flat = (s > P.PEAK_BASE_FRACTION + 0.02) & (s < 0.5 * c.floor_diameter_m / c.diameter_m - 0.02)
    assert np.allclose(h[:, flat], floor_level, atol=1.0)  # a flat floor
    assert h[:, 0].mean() - floor_level == pytest.approx(c.peak_height_m, rel=0.02)  # the peak
    wall = h[:, (s > 0.5 * c.floor_diameter_m / c.diameter_m) & (s < 1.0)].mean(axis=0)
    steps = np.diff(wall)
    assert np.all(steps >= -1e-6) and steps.max() > 4.0 * np.median(steps)  # terraces: benches and scarps
    assert t.height.max() - floor_level == pytest.approx(c.depth_m, rel=0.01)


def test_transitional_craters_bridge_simple_and_complex():
    d = np.array([14.9, 15.0, 17.0, 19.99, 20.0]) * 1000.0
    shape = P.morphometry(d)
    assert [P.CLASSES[k] for k in shape["cls"]] == ["simple", "transitional", "transitional", "transitional", "complex"]
    assert shape["depth"][1] == pytest.approx(shape["depth"][0], rel=0.01)
    assert shape["depth"][3] == pytest.approx(shape["depth"][4], rel=0.01)
    assert shape["floor_diameter"][1] == 0.0 and 0.0 < shape["floor_diameter"][2] < shape["floor_diameter"][4]


@pytest.mark.parametrize("diameter_m, spacing_m", [(1000.0, 20.0), (30000.0, 300.0)])
def test_degradation_lowers_depth_monotonically(diameter_m, spacing_m):
    ages = np.array([0.0, 100.0, 500.0, 1000.0, 2000.0, 3500.0])
    kappa = 5.5 * (diameter_m / 1000.0) ** 2 * 4.0  # the same ladder for both sizes, fresh to d/D ~ 0.06
    table = P.crater_table(np.full(ages.size, diameter_m), np.zeros(ages.size), np.zeros(ages.size), ages, kappa)
    order = np.argsort(table["age_myr"])  # youngest first
    depth, state = table["depth"][order], table["degradation"][order]
    assert np.all(np.diff(depth) < 0) and np.all(np.diff(state) > 0) and state[0] == 0.0
    assert np.all(np.diff(table["rim_height"][order]) < 0)
    measured = [_single(diameter_m, spacing_m, a, kappa).height.ptp() for a in ages[[0, 2, 5]]]
    assert measured[0] > measured[1] > measured[2]


def test_a_ghost_reaches_degradation_one():
    table = P.crater_table([200.0], [0.0], [0.0], [3500.0], 5.5)
    assert table["degradation"][0] == 1.0 and table["depth"][0] < P.GHOST_DEPTH_RATIO * table["fresh_depth"][0]


def test_overprinting_flags_erased_and_partly_covered_craters():
    sp, size = 20.0, 400
    mid = 0.5 * (size - 1) * sp
    # 0: old 1 km crater inside a younger 5 km one; 1: old 1 km crater on the 5 km rim; 2: young, alone.
    table = P.crater_table(
        [1000.0, 1000.0, 5000.0, 800.0],
        [mid, mid + 2500.0, mid, mid - 3000.0],
        [mid, mid, mid, mid + 2800.0],
        [3000.0, 2900.0, 1000.0, 10.0],
        0.0,
    )
    t = P.build(np.zeros((size, size)), sp, table)
    inside, on_rim, big, alone = t.craters
    assert inside.diameter_m == 1000.0 and on_rim.x_m == mid + 2500.0 and big.diameter_m == 5000.0
    assert inside.visible_rim_fraction == 0.0
    # A circle of radius r centred on one of radius R: 1 - arccos(r / 2R) / pi of its rim stays outside.
    assert on_rim.visible_rim_fraction == pytest.approx(1.0 - math.acos(500.0 / 5000.0) / math.pi, abs=0.05)
    assert big.visible_rim_fraction == 1.0 and alone.visible_rim_fraction == 1.0
    assert [c.order for c in t.detectable(min_visible_rim=0.6)] == [big.order, alone.order]
    assert inside.order not in [c.order for c in t.detectable()]
    # The new crater excavates: the old one's bowl is gone from the grid, the new floor is level.
    r = (np.arange(size) - 0.5 * (size - 1)) * sp
    rr = np.hypot(*np.meshgrid(r, r))
    floor = t.height[rr < 0.2 * 2500.0]
    assert floor.ptp() < 0.05 * big.depth_m


def test_labels_of_a_generated_field_match_its_grid():
    """Every fresh, fully visible crater of a dense field away from the edges: the grid's rim crest at D/2."""
    t = P.generate(
        ProceduralSettings(
            size_px=256,
            spacing_m=20.0,
            surface_age_gyr=1.0,
            d_min_px=10.0,
            density_scale=5.0,
            diffusivity_m2_per_myr=0.0,
        )
    )
    side = 255 * 20.0
    offsets = []
    for c in t.craters:
        margin = 1.6 * 0.5 * c.diameter_m
        if c.degradation > 0.05 or c.visible_rim_fraction < 1.0 or not margin < c.x_m < side - margin:
            continue
        if not margin < c.y_m < side - margin:
            continue
        s, h = _radial(t, c)
        offsets.append(abs(np.median(s[np.argmax(h, axis=1)]) - 1.0) * 0.5 * c.diameter_m / t.spacing_m)
    assert len(offsets) >= 10 and max(offsets) < 0.75  # px: on rough ground, among neighbours' ejecta


def test_config_group_holds_the_schema_defaults_and_names_bad_keys():
    assert compose_group("procedural", ProceduralSettings) == ProceduralSettings()
    assert compose_group("procedural", ProceduralSettings, ["procedural.seed=4"]).seed == 4
    with pytest.raises(ConfigError, match=r"procedural.hurst=1.5: must lie in \(0, 1\)"):
        compose_group("procedural", ProceduralSettings, ["procedural.hurst=1.5"])
    with pytest.raises(ConfigError, match="procedural.d_max_fraction"):
        compose_group("procedural", ProceduralSettings, ["procedural.size_px=64", "procedural.d_max_fraction=0.01"])


def test_too_many_craters_is_one_line_naming_the_settings():
    with pytest.raises(ValueError, match="raise d_min_px"):
        P.generate(ProceduralSettings(size_px=8192, spacing_m=1.0, d_min_px=2.0, density_scale=100.0))


def test_preview_writes_a_hillshade_and_the_crater_list(tmp_path):
    rc = procedural_preview.main(["--out", str(tmp_path), "procedural.size_px=128", "procedural.spacing_m=20"])
    assert rc == 0
    doc = json.loads((tmp_path / "craters.json").read_text())
    assert doc["summary"]["craters"] == len(doc["craters"]) > 0 and doc["settings"]["size_px"] == 128
    assert (tmp_path / "hillshade.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "overlay.png").stat().st_size > 0
    assert procedural_preview.main(["--out", str(tmp_path), "procedural.hurst=2"]) == 2


def test_patch_is_the_workers_terrain_format_curved_with_the_moon(tmp_path):
    """--patch-at writes what blender_gen/job.py loads; the centre vertex is the grid's height, a corner
    lies its curvature drop below the tangent plane, rows run north and columns east."""
    argv = ["--out", str(tmp_path), "--patch-at", "-89.0", "0.0", "procedural.size_px=128", "procedural.spacing_m=200"]
    assert procedural_preview.main(argv) == 0
    terrain = load_terrain(str(tmp_path / "terrain.npz"))
    xyz, far = terrain["near_xyz"], terrain["far_xyz"]
    assert xyz.shape == (128, 128, 3) and far is None
    with np.load(tmp_path / "terrain.npz") as z:
        height = z["near_height"]
    half = 0.5 * 127 * 200.0
    assert xyz[0, 0, 0] == pytest.approx(-half, rel=1e-3) and xyz[0, 0, 1] == pytest.approx(-half, rel=1e-3)
    assert xyz[-1, -1, 0] > 0 and xyz[-1, -1, 1] > 0
    drop = curvature_drop_m(math.hypot(half, half))
    assert xyz[0, 0, 2] == pytest.approx(height[0, 0] - drop, abs=0.05 * drop)
    mid = xyz[63:65, 63:65, 2].mean() - height[63:65, 63:65].mean()
    assert abs(mid) < 1.0


def test_degradation_agrees_with_the_sub_dem_details_independent_solution():
    """The same radial diffusion, solved separately by crater_synth/terrain/detail.py (scipy's tridiagonal
    eigen-solver, its own grid): a 1 km crater's profiles agree to 0.1 % of the fresh depth."""
    from crater_synth.terrain import detail

    s = P._diffusion().s
    for tau in (1e-3, 0.02, 0.1):
        table = P.crater_table([1000.0], [0.0], [0.0], [tau * 1e6 / 5.5], 5.5)
        mine = table["profile"][0] / table["fresh_depth"][0]
        theirs = detail.degraded_profile(s, np.full(s.shape, tau))
        assert np.abs(mine - theirs)[s < P.TAPER_START_RADII].max() < 1e-3


def test_profiles_and_their_labels_do_not_depend_on_the_chunk_size(monkeypatch):
    """Profiles are computed PROFILE_CHUNK rows at a time (memory); any chunk gives the same bits."""
    rng = np.random.default_rng(4)
    d = np.concatenate([rng.uniform(150.0, 3000.0, 40), [17000.0, 30000.0]])  # simple, transitional, complex
    args = (d, rng.uniform(0, 9e3, d.size), rng.uniform(0, 9e3, d.size), rng.uniform(0, 3900.0, d.size), 5.5)
    whole = P.crater_table(*args)
    monkeypatch.setattr(P, "PROFILE_CHUNK", 7)
    chunked = P.crater_table(*args)
    for key, value in whole.items():
        assert np.array_equal(value, chunked[key]), key


def test_detectable_craters_are_computed_once_and_not_shared_out():
    t = P.generate(SMALL)
    first = t.detectable()
    first.clear()
    assert t.detectable() and t.detectable() == t.detectable() and t.detectable(0.9) != t.detectable()
