"""crater_synth.terrain.patch: the patch contract consumed by the Blender worker, caching, and the CLI."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from click.testing import CliRunner

from crater_core import geometry as g
from crater_synth.cli import main
from crater_synth.config import compose, craters
from crater_synth.terrain.patch import build_terrain

FAST = ["terrain.near_vertices=128", "terrain.far_spacing_km=10"]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("data")


@pytest.fixture(scope="module")
def shackleton(data_dir):
    cfg = compose([f"data_dir={data_dir}", "crater=shackleton", *FAST])
    crater = craters(cfg)[0]
    path, meta = build_terrain(crater, cfg)
    return crater, cfg, path, meta, dict(np.load(path))


def test_patch_arrays_contract(shackleton):
    _, _, path, meta, z = shackleton
    assert path.name == f"shackleton-{meta['terrain_id']}.npz" and path.with_suffix(".json").is_file()
    assert set(z) == {"near_xyz", "far_xyz", "far_keep_quads", "near_height"}
    assert z["near_xyz"].shape == (128, 128, 3) and z["near_xyz"].dtype == np.float32
    assert z["near_height"].shape == (128, 128) and z["near_height"].dtype == np.float32
    my, mx, three = z["far_xyz"].shape
    assert three == 3 and z["far_xyz"].dtype == np.float32 and my == mx == 61  # +-300 km at 10 km
    assert z["far_keep_quads"].shape == (my - 1, mx - 1) and z["far_keep_quads"].dtype == bool
    assert meta["vertex_count"] == 128 * 128 + my * mx
    # Rows go north, columns go east.
    near = z["near_xyz"]
    assert (np.diff(near[:, :, 1], axis=0) > 0).all() and (np.diff(near[:, :, 0], axis=1) > 0).all()


def test_vertices_sit_at_sphere_radius_plus_height(shackleton):
    crater, _, _, meta, z = shackleton
    mc = g.enu_to_mc(z["near_xyz"].astype(np.float64), crater["lat"], crater["lon"])
    h = np.linalg.norm(mc, axis=-1) - g.MOON_RADIUS_M
    np.testing.assert_allclose(h, z["near_height"], atol=0.1)  # float32 ENU coordinates
    # Each vertex is on the ray from the Moon's centre through the tangent-plane point (e, n, 0):
    # ENU (x, y) = (R + h) (e, n) / sqrt(R^2 + e^2 + n^2).
    hw = meta["near"]["half_width_m"]
    e = np.linspace(-hw, hw, 128)
    ee, nn = np.meshgrid(e, e)
    scale = (g.MOON_RADIUS_M + h) / np.sqrt(g.MOON_RADIUS_M**2 + ee**2 + nn**2)
    np.testing.assert_allclose(z["near_xyz"][..., 0], ee * scale, atol=0.05)
    np.testing.assert_allclose(z["near_xyz"][..., 1], nn * scale, atol=0.05)


def test_curvature_in_far_field(shackleton):
    _, _, _, meta, z = shackleton
    far = z["far_xyz"].astype(np.float64)
    d = np.hypot(far[..., 0], far[..., 1])
    edge = d > 250e3
    # 250-300 km away the ground is 18-26 km below the tangent plane; relief is only ~ +-5 km.
    assert far[..., 2][edge].mean() < -15e3
    resid = far[..., 2] + g.curvature_drop_m(d)
    assert np.abs(resid).max() < 10e3
    assert meta["far"]["half_width_m"] == 300e3 and meta["far"]["spacing_m"] == 10e3


def test_far_quads_overlap_near_field_without_gaps(shackleton):
    _, _, _, meta, z = shackleton
    keep = z["far_keep_quads"]
    hw, fs = meta["near"]["half_width_m"], meta["far"]["spacing_m"]
    coords = np.arange(-(keep.shape[0] // 2), keep.shape[0] // 2 + 1) * fs
    lo, hi = coords[:-1], coords[1:]
    dropped = ~keep
    assert dropped.any() and keep[0, 0] and keep[-1, -1]
    # Every dropped quad lies inside the near field; every quad not fully inside it is kept.
    inside_near = np.maximum(np.abs(lo), np.abs(hi)) <= hw
    assert (inside_near[:, None] & inside_near[None, :])[dropped].all()
    assert keep[~(inside_near[:, None] & inside_near[None, :])].all()


def test_metadata_fields(shackleton):
    _, _, path, meta, _ = shackleton
    on_disk = json.loads(path.with_suffix(".json").read_text())
    for key in (
        "terrain_id",
        "crater",
        "dem",
        "near",
        "far",
        "rim_z_m",
        "floor_z_m",
        "rim_to_floor_depth_m",
        "vertex_count",
        "nodata_fraction",
        "filled_holes",
        "detail",
    ):
        assert key in on_disk, key
    assert re.fullmatch(r"[0-9a-f]{16}", on_disk["terrain_id"])
    dem = on_disk["dem"]
    assert dem["product"] == "lola_ldem256_south" and dem["pixel_size_m"] == 1600.0
    assert dem["sha256"].startswith("12c33e28") and "stere" in dem["crs_proj"]
    col, row = dem["crater_center_px"]
    assert 375 < col < 395 and 375 < row < 395  # ~10 km from the pole, 1600 m/px, pole at 381
    # Shackleton is ~4.2 km deep (Zuber et al. 2012); 1600 m/px smooths the floor a little.
    assert 3000.0 < on_disk["rim_to_floor_depth_m"] < 5000.0
    assert on_disk["floor_z_m"] < on_disk["rim_z_m"]
    assert on_disk["detail"]["active"] and on_disk["detail"]["n_craters"] > 0
    assert on_disk["near"]["shape"] == [128, 128] and on_disk["nodata_fraction"] == 0.0


def test_cache_and_terrain_id(shackleton, data_dir):
    crater, cfg, path, meta, _ = shackleton
    path2, meta2 = build_terrain(crater, cfg)
    assert path2 == path and meta2["cached"] and meta2["terrain_id"] == meta["terrain_id"]
    cfg3 = compose([f"data_dir={data_dir}", "crater=shackleton", *FAST, "seed=99"])
    path3, meta3 = build_terrain(crater, cfg3)
    assert meta3["terrain_id"] != meta["terrain_id"] and not meta3["cached"]
    # The 1600 m DEM alone (no stack layer): the detail is wholly below its resolution.
    on = compose([f"data_dir={data_dir}", "crater=shackleton", *FAST, "dem.stack=[]"])
    off = compose([f"data_dir={data_dir}", "crater=shackleton", *FAST, "dem.stack=[]", "terrain.detail.enabled=false"])
    _, meta_on = build_terrain(crater, on)
    _, meta_off = build_terrain(crater, off)
    assert meta_on["terrain_id"] != meta["terrain_id"]  # the stack is part of the key
    h_off = np.load(meta_off["patch"])["near_height"].astype(np.float64)
    h_on = np.load(meta_on["patch"])["near_height"].astype(np.float64)
    assert np.abs(h_on - h_off).max() > 1.0  # the detail is there ...
    from crater_synth.terrain.detail import lowpass

    diff = h_on - h_off  # ... and only below the DEM's resolution (float32 storage aside)
    assert np.abs(lowpass(diff, meta["near"]["spacing_m"], 1600.0)).max() < 0.01 * diff.std() + 0.01
    assert not list((data_dir / "terrain").glob(".*.tmp"))


def test_cli_prints_one_json_line(data_dir):
    res = CliRunner().invoke(main, ["terrain", "crater=shackleton", f"data_dir={data_dir}", *FAST])
    assert res.exit_code == 0, res.output
    lines = res.stdout.strip().splitlines()
    assert len(lines) == 1
    row = json.loads(lines[0])
    for key in (
        "crater",
        "dem_product",
        "dem_pixel_m",
        "crater_center_px",
        "rim_to_floor_depth_m",
        "near_extent_km",
        "far_extent_km",
        "vertex_count",
        "nodata_fraction",
        "patch",
    ):
        assert key in row, key
    assert row["crater"] == "shackleton" and 3000 < row["rim_to_floor_depth_m"] < 5000
    assert row["near_extent_km"] == pytest.approx(105.0) and row["far_extent_km"] == pytest.approx(600.0)


@pytest.mark.parametrize(
    "args, needle",
    [
        (["terrain.near_vertices=1"], "terrain.near_vertices=1"),
        (["terrain.near_radius_factor=0.2"], "terrain.near_radius_factor"),
        (["terrain.far_spacing_km=0"], "terrain.far_spacing_km"),
        (["dem.max_nodata_fraction=2"], "dem.max_nodata_fraction"),
        (["terrain.detail.hurst=1.5"], "terrain.detail.hurst"),
        (["crater=custom", "crater.custom.lon=10", "crater.custom.diameter_km=20"], "crater.custom.lat"),
        (
            ["crater=custom", "crater.custom.lat=-60", "crater.custom.lon=0", "crater.custom.diameter_km=20"],
            "outside DEM",
        ),
        (["dem.path=/nonexistent/dem.tif"], "/nonexistent/dem.tif"),
    ],
)
def test_cli_bad_input_is_one_error_line(data_dir, args, needle):
    res = CliRunner().invoke(main, ["terrain", "crater=shackleton", f"data_dir={data_dir}", *FAST, *args])
    assert res.exit_code == 2, res.output
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and needle in err[0], err
    assert res.stdout == ""


def test_far_radius_zero_disables_far_field(data_dir):
    cfg = compose([f"data_dir={data_dir}", "crater=shoemaker", "terrain.near_vertices=32", "terrain.far_radius_km=0"])
    path, meta = build_terrain(craters(cfg)[0], cfg)
    z = np.load(path)
    assert z["far_xyz"].shape == (0, 0, 3) and z["far_keep_quads"].shape == (0, 0)
    assert meta["far"]["half_width_m"] == 0.0
