"""crater_synth.terrain.stack: multi-resolution DEM stack (blending without seam, user DEMs, terrain, detail)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from crater_core import geometry as g
from crater_synth.cli import main
from crater_synth.config import compose, craters
from crater_synth.terrain.dem import Dem
from crater_synth.terrain.detail import DetailSettings, lowpass, synthesize_detail
from crater_synth.terrain.patch import build_terrain, stack_detail, terrain_id
from crater_synth.terrain.stack import DemStack, StackSample, open_stack

STEREO_SOUTH = "+proj=stere +lat_0=-90 +lat_ts=-90 +lon_0=0 +k=1 +x_0=0 +y_0=0 +R=1737400 +units=m +no_defs"
FAST = ["terrain.near_vertices=128", "terrain.far_spacing_km=10"]
BASE_SLOPE = (0.02, -0.01)  # base plane dh/dx, dh/dy
BIAS_M, EXTRA_TILT = 50.0, 0.005  # the fine layer = base plane + bias + extra tilt along x
FINE_LEFT, FINE_TOP, FINE_PX, FINE_N = -4000.0, 16000.0, 200.0, 100


def write_geotiff(path, heights, pixel_m, left, top, nodata=None):
    """A north-up polar stereographic GeoTIFF with its top-left corner at (left, top) m."""
    import rasterio
    from affine import Affine

    h, w = heights.shape
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=w,
        height=h,
        count=1,
        dtype="float32",
        crs=STEREO_SOUTH,
        transform=Affine(pixel_m, 0.0, left, 0.0, -pixel_m, top),
        nodata=nodata,
    ) as dst:
        dst.write(heights.astype(np.float32), 1)
    return path


def grid_xy(n, pixel_m, left, top):
    c = left + (np.arange(n) + 0.5) * pixel_m
    r = top - (np.arange(n) + 0.5) * pixel_m
    return np.meshgrid(c, r)


def base_plane(x, y):
    return BASE_SLOPE[0] * x + BASE_SLOPE[1] * y + 100.0


def fine_plane(x, y):
    return base_plane(x, y) + BIAS_M + EXTRA_TILT * x


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """Base: a 1600 m plane around the pole; fine: a 200 m plane with a 50 m bias and an extra tilt."""
    d = tmp_path_factory.mktemp("stack")
    n, px = 64, 1600.0
    bx, by = grid_xy(n, px, -n / 2 * px, n / 2 * px)
    base = Dem(write_geotiff(d / "base.tif", base_plane(bx, by), px, -n / 2 * px, n / 2 * px), product="base")
    fx, fy = grid_xy(FINE_N, FINE_PX, FINE_LEFT, FINE_TOP)
    fine = Dem(write_geotiff(d / "fine.tif", fine_plane(fx, fy), FINE_PX, FINE_LEFT, FINE_TOP), product="fine")
    return DemStack(base, [(fine, "f" * 64, "fine.tif")], blend_pixels=2.0), d


def sample_xy(stack, x, y, spacing_m=None):
    lat, lon = g.south_polar_stereo_inverse(x, y)
    return stack.sample(lat, lon, spacing_m=spacing_m)


def test_band_is_two_coarse_pixels(synthetic):
    stack, _ = synthetic
    info = stack.stack_info()[0]
    assert info["blend_band_m"] == 3200.0 and info["blends_into"] == "base"


def test_biased_tilted_layer_blends_without_step_or_kink(synthetic):
    """Across the fine layer's west edge (pixel-centre hull at x = -3900 m): base heights outside,
    fine heights inside the band, and neither a step nor a gradient kink in between."""
    stack, _ = synthetic
    ds = 10.0
    x = np.arange(-9000.0, 6000.0, ds)
    y = np.full_like(x, 6000.0)
    s = sample_xy(stack, x, y)
    h, w = s.heights, s.fine_weight
    edge = FINE_LEFT + 0.5 * FINE_PX
    # Full weight beyond band + dead zone (sigma / 2) + one distance-field cell (band / 8).
    outside, deep = x < edge, x > edge + 3200.0 + 400.0 + 400.0
    np.testing.assert_allclose(h[outside], base_plane(x, y)[outside], atol=1e-3)
    np.testing.assert_allclose(h[deep], fine_plane(x, y)[deep], atol=1e-3)
    assert np.all(w[outside] == 0.0) and np.all(w[deep] == 1.0) and np.all(np.diff(w) >= -1e-12)
    # Steps: |dh/dx| <= base slope + extra tilt + |fine - base| * max w' (pi / 2 band): under 1 m per 10 m.
    # (A hard switch would jump by ~30 m here.)
    bound = ds * (abs(BASE_SLOPE[0]) + EXTRA_TILT + (BIAS_M + EXTRA_TILT * 6000.0) * np.pi / (2 * 3200.0))
    assert np.abs(np.diff(h)).max() <= bound < 1.0
    # Gradient continuity: a kink (e.g. a linear ramp) would show one second difference of
    # ~|fine - base| * ds / band ~ 0.1 m; the C1 weight keeps them below 5 mm.
    assert np.abs(np.diff(h, 2)).max() < 0.005


@pytest.mark.parametrize("blend_pixels", [1.0, 2.0, 3.0, 3.5])
def test_weight_is_zero_at_every_edge(synthetic, blend_pixels):
    """Whatever the distance-cell size (band / 8, whole cells of a 100-pixel layer), the weight is 0
    on all four edges of the layer's pixel-centre hull and 1 in its middle."""
    stack, _ = synthetic
    s2 = DemStack(stack.base, [(stack.layers[0].dem, "f" * 64, "fine.tif")], blend_pixels=blend_pixels)
    lo, hi = FINE_LEFT + 0.5 * FINE_PX, FINE_LEFT + (FINE_N - 0.5) * FINE_PX
    top, bottom = FINE_TOP - 0.5 * FINE_PX, FINE_TOP - (FINE_N - 0.5) * FINE_PX
    mid_x, mid_y = 0.5 * (lo + hi), 0.5 * (top + bottom)
    x = np.array([lo, hi, mid_x, mid_x, mid_x])
    y = np.array([mid_y, mid_y, top, bottom, mid_y])
    w = sample_xy(s2, x, y).fine_weight
    assert list(w[:4]) == [0.0] * 4 and w[4] == 1.0


def test_corner_of_layer_has_continuous_gradients(synthetic):
    """Near a corner the distance to the edge has a kink along the diagonal; the smoothed distance
    field keeps the blended surface's gradient continuous there too."""
    stack, _ = synthetic
    ds = 20.0
    c = np.arange(-6000.0, 2000.0, ds)
    x, y = np.meshgrid(c, c + FINE_TOP - FINE_N * FINE_PX + 4000.0)  # around the south-west corner
    h = sample_xy(stack, x, y).heights
    # Smooth curvature of w there: |fine - base| (~30 m) x |w''| (~1e-6 /m^2) x ds^2 ~ 0.01 m. An
    # unsmoothed distance field would turn grad w by 90 degrees across the diagonal: a kink of
    # ~|fine - base| x sqrt(2) pi / (2 band) x ds ~ 0.4 m.
    for axis in (0, 1):
        assert np.abs(np.diff(h, 2, axis=axis)).max() < 0.05


def test_nodata_hole_falls_back_to_base(tmp_path, synthetic):
    stack, _ = synthetic
    fx, fy = grid_xy(FINE_N, FINE_PX, FINE_LEFT, FINE_TOP)
    heights = fine_plane(fx, fy)
    heights[40:60, 40:60] = -32768.0
    holed = Dem(write_geotiff(tmp_path / "holed.tif", heights, FINE_PX, FINE_LEFT, FINE_TOP, nodata=-32768.0))
    hs = DemStack(stack.base, [(holed, "e" * 64, "holed.tif")], blend_pixels=2.0)
    centre = (FINE_LEFT + 50 * FINE_PX, FINE_TOP - 50 * FINE_PX)
    s = sample_xy(hs, np.array([centre[0]]), np.array([centre[1]]))
    assert s.fine_weight[0] == 0.0 and s.heights[0] == pytest.approx(base_plane(*centre), abs=1e-3)
    x = np.arange(centre[0] - 8000.0, centre[0], 10.0)  # from good data into the hole
    h = sample_xy(hs, x, np.full_like(x, centre[1])).heights
    assert np.abs(np.diff(h, 2)).max() < 0.01


def test_pds3_layer_like_ldem_875s_20m(tmp_path, synthetic):
    """A LOLA-style PDS3 product (detached label, int16 DN x 0.5 m + radius), pole-centred at 20 m, as
    a stack layer: used inside, the base outside, the 20 m layer blending over 2 base pixels."""
    from test_dem import write_pds3

    stack, _ = synthetic
    n, px = 600, 20.0  # 12 km around the pole

    def layer_plane(x, y):
        return base_plane(x, y) - 30.0

    c = (np.arange(n) - n / 2 + 0.5) * px
    xx, yy = np.meshgrid(c, -c)
    layer = Dem(write_pds3(tmp_path, layer_plane(xx, yy), px))
    s20 = DemStack(stack.base, [(layer, "d" * 64, "ldem_test.lbl")], blend_pixels=2.0)
    assert s20.stack_info()[0]["blend_band_m"] == 3200.0
    x = np.array([0.0, 500.0, -9000.0])
    y = np.array([0.0, -300.0, 0.0])
    s = sample_xy(s20, x, y)
    np.testing.assert_allclose(s.heights[:2], layer_plane(x, y)[:2], atol=0.5)  # DN quantum 0.5 m
    assert s.heights[2] == pytest.approx(base_plane(x[2], y[2]), abs=1e-3) and list(s.fine_weight) == [1, 1, 0]


def test_weights_and_effective_pixel(synthetic):
    stack, _ = synthetic
    s = sample_xy(stack, np.array([-20000.0, 6000.0]), np.array([6000.0, 6000.0]), spacing_m=400.0)
    assert isinstance(s, StackSample) and s.layer_names == ["base", "fine"]
    np.testing.assert_allclose(s.layer_weights[0] + s.layer_weights[1], 1.0)
    assert list(s.fine_weight) == [0.0, 1.0]
    # 200 m layer on a 400 m grid: box-averaged by 2 -> 400 m effective; base 1600 m.
    assert s.layer_pixel_m == [1600.0, 400.0]
    np.testing.assert_allclose(s.effective_pixel_m, [1600.0, 400.0])


def test_stack_detail_scaled_by_layer_weight():
    """No synthetic detail on top of data as fine as the grid; the base's detail where only the base
    covers; a layer coarser than the grid gets detail only below its own resolution."""
    n, spacing = 128, 100.0
    settings = DetailSettings(seed=3)
    ramp = np.clip((np.arange(n) - 40) / 40.0, 0.0, 1.0)
    w = np.broadcast_to(0.5 - 0.5 * np.cos(np.pi * ramp), (n, n))
    base_detail, _ = synthesize_detail((n, n), spacing, 1600.0, settings, key="k")
    assert np.abs(base_detail).max() > 1.0
    s = StackSample(
        heights=np.zeros((n, n)),
        nodata_fraction=0.0,
        filled_pixels=0,
        filled_holes=0,
        decimation=1,
        layer_names=["base", "fine"],
        layer_weights=[1.0 - w, w],
        layer_pixel_m=[1600.0, 100.0],
    )
    field, stats = stack_detail((n, n), spacing, s, settings, key="k")
    np.testing.assert_allclose(field, (1.0 - w) * base_detail, atol=1e-9)
    assert np.all(field[:, w[0] == 1.0] == 0.0) and stats["stack"]["base_weight_mean"] < 0.6
    s.layer_pixel_m = [1600.0, 400.0]
    field, _ = stack_detail((n, n), spacing, s, settings, key="k")
    covered = field[:, w[0] == 1.0]
    assert np.abs(covered).max() > 0.1
    layer_detail, _ = synthesize_detail((n, n), spacing, 400.0, settings, key="k")
    assert np.abs(lowpass(layer_detail, spacing, 400.0)).max() < 1e-6  # nothing the 400 m layer resolves


def test_terrain_id_unchanged_without_layers():
    crater = {"name": "x", "lat": -89.0, "lon": 0.0, "diameter_km": 10.0}
    s = {
        "near_radius_factor": 2.5,
        "near_vertices": 64,
        "far_radius_km": 0.0,
        "far_spacing_km": 2.0,
        "max_nodata_fraction": 0.02,
        "detail": DetailSettings(),
    }
    empty = terrain_id("a" * 64, "a" * 64, crater, s, {"layers": [], "blend_pixels": 2.0})
    assert empty == terrain_id("a" * 64, "a" * 64, crater, s)
    assert empty != terrain_id("a" * 64, "a" * 64, crater, s, {"layers": [{"sha256": "b" * 64, "band_m": 3.2e3}]})


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("data")


@pytest.fixture(scope="module")
def user_dem(tmp_path_factory):
    """A user GeoTIFF: LDEM_256 resampled to 200 m over 40 km around Shackleton, raised by 100 m."""
    from data_manifest.products import resolve_product

    d = tmp_path_factory.mktemp("user")
    base = Dem(resolve_product("lola_ldem256_south", d), product="lola_ldem256_south")
    cx, cy = g.south_polar_stereo_forward(-89.67, 129.78)
    left, top = round(cx) - 20000.0, round(cy) + 20000.0
    x, y = grid_xy(200, 200.0, left, top)
    lat, lon = g.south_polar_stereo_inverse(x, y)
    heights = base.sample(lat, lon).heights + 100.0
    return write_geotiff(d / "user_dem.tif", heights, 200.0, left, top)


def _terrain(data_dir, *args):
    cfg = compose([f"data_dir={data_dir}", "crater=shackleton", *FAST, *args])
    return build_terrain(craters(cfg)[0], cfg)


def test_user_geotiff_plugs_into_the_stack(data_dir, user_dem):
    _, plain = _terrain(data_dir, "dem.stack=[]", "terrain.detail.enabled=false")
    path, meta = _terrain(data_dir, f"dem.stack=[{user_dem}]", "terrain.detail.enabled=false")
    layer = meta["dem"]["stack"][0]
    assert layer["product"] == "user_dem.tif" and layer["pixel_size_m"] == 200.0
    assert layer["crater_weight_mean"] == pytest.approx(1.0)
    assert meta["terrain_id"] != plain["terrain_id"]
    h = np.load(path)["near_height"].astype(np.float64)
    h0 = np.load(plain["patch"])["near_height"].astype(np.float64)
    n = h.shape[0]
    centre = slice(n // 2 - 8, n // 2 + 8)  # +-6.6 km around the crater centre: inside the layer's core
    assert np.median(h[centre, centre] - h0[centre, centre]) == pytest.approx(100.0, abs=5.0)
    assert np.abs(h[:8, :8] - h0[:8, :8]).max() < 1e-3  # near-field corner, outside the user DEM


def test_detail_not_added_on_fine_data(data_dir):
    """Default stack (200 m Shackleton crop): inside the crater the fine layer is as fine as the grid,
    so the detail is zero there; outside the crop the 1600 m DEM's detail is unchanged."""
    _, on = _terrain(data_dir)
    _, off = _terrain(data_dir, "terrain.detail.enabled=false")
    _, base_on = _terrain(data_dir, "dem.stack=[]")
    _, base_off = _terrain(data_dir, "dem.stack=[]", "terrain.detail.enabled=false")
    h_on, h_off = (np.load(m["patch"])["near_height"].astype(np.float64) for m in (on, off))
    b_on, b_off = (np.load(m["patch"])["near_height"].astype(np.float64) for m in (base_on, base_off))
    n = h_on.shape[0]
    centre = slice(n // 2 - 8, n // 2 + 8)
    assert np.abs((h_on - h_off)[centre, centre]).max() < 1e-3
    assert np.abs((b_on - b_off)[centre, centre]).std() > 1.0  # the 1600 m DEM alone gets detail there
    corner = (slice(0, 10), slice(n - 10, n))  # north-east corner, far from the crop
    np.testing.assert_allclose((h_on - h_off)[corner], (b_on - b_off)[corner], atol=1e-3)
    assert on["detail"]["stack"]["base_weight_mean"] < 0.95


@pytest.mark.parametrize(
    "args, needle",
    [
        (["dem.stack=[no_such_dem]"], "neither a registered DEM product"),
        (["dem.stack=[lroc_wac_south]"], "not a DEM"),
        (["dem.stack=shackleton_lola_200m"], "must be a list"),
        (["dem.stack=[shackleton_lola_200m,shackleton_lola_40m]"], "finest DEM first"),
        (["dem.blend_pixels=0"], "dem.blend_pixels"),
    ],
)
def test_bad_stack_config_is_one_error_line(data_dir, args, needle):
    res = CliRunner().invoke(main, ["terrain", "crater=shackleton", f"data_dir={data_dir}", *FAST, *args])
    assert res.exit_code == 2, res.output
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and needle in err[0], err


def test_corrupt_user_dem_is_one_error_line(data_dir, tmp_path):
    bad = tmp_path / "broken.tif"
    bad.write_bytes(b"II*\x00garbage")
    res = CliRunner().invoke(
        main, ["terrain", "crater=shackleton", f"data_dir={data_dir}", *FAST, f"dem.stack=[{bad}]"]
    )
    assert res.exit_code == 2 and str(bad) in res.stderr and len(res.stderr.strip().splitlines()) == 1


def test_default_stack_in_terrain_summary(data_dir):
    res = CliRunner().invoke(main, ["terrain", "crater=shackleton", f"data_dir={data_dir}", *FAST])
    assert res.exit_code == 0, res.output
    row = json.loads(res.stdout)
    assert row["dem_stack"] == ["shackleton_lola_200m"] and row["fine_weight_crater"] > 0.95
    assert 3500.0 < row["rim_to_floor_depth_m"] < 4600.0


def test_open_stack_skips_the_base_itself(synthetic):
    from data_manifest.products import cached_sha256

    stack, _ = synthetic
    assert open_stack(stack.base, cached_sha256(stack.base.path), [str(stack.base.path)], ".").layers == []


def test_seam_report_on_shackleton(tmp_path, capsys):
    """``python -m crater_synth.tools.demstack_seams``: in the blend band of the real 200 m layer the surface
    is no steeper than the terrain on either side and stays between the two DEMs."""
    from crater_synth.tools.demstack_seams import main as report

    assert report(["crater=shackleton", "terrain.near_vertices=256", "--png", str(tmp_path / "seam")]) == 0
    m = json.loads(capsys.readouterr().out)
    assert m["band"]["vertices"] > 100 and m["rim_circle_fine_weight_min"] > 0.99
    assert m["band"]["step_max_m"] <= max(m["base"]["step_max_m"], m["fine"]["step_max_m"])
    assert m["band"]["second_diff_max_m"] <= max(m["base"]["second_diff_max_m"], m["fine"]["second_diff_max_m"])
    assert m["band_envelope_excursion_m"] < 1e-3
    assert all((tmp_path / f"seam_shackleton_{k}.png").stat().st_size > 10_000 for k in ("hillshade", "profile"))
