"""The north polar region: the same pipeline as the south, nothing assuming the south pole.

- Products: the embedded north DEM and WAC mosaic are registered and verified like the south ones.
- Physical Sun: the highest Sun stands towards the equator, local south at a north-polar crater.
- Mirror: a synthetic terrain mirrored from the south to the north about the equator (the same raster,
  rows flipped, in the north polar stereographic CRS) renders the mirrored image under the mirrored Sun
  and camera (sun azimuth A -> 180 - A, camera azimuth C -> 180 - C, image flipped left-right).
- Real crops of north craters come from wac_north; a crater in the other hemisphere than its DEM or
  mosaic is one error naming both.
- A north crater renders, trains and evaluates end to end (tiny settings).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from crater_core import geometry as g
from crater_core.exr import read_channel
from crater_core.illumination import LUNAR_OBLIQUITY_DEG, max_sun_elevation_deg
from crater_core.sweep import grid_from_config

from helpers.cli import TINY, run_cli

STEREO = {
    pole: f"+proj=stere +lat_0={lat0} +lat_ts={lat0} +lon_0=0 +k=1 +x_0=0 +y_0=0 +R=1737400 +units=m +no_defs"
    for pole, lat0 in (("south", -90), ("north", 90))
}


# ------------------------------------------------------------------------------ products
@pytest.mark.parametrize("product", ["lola_ldem256_north", "lroc_wac_north"])
def test_north_products_are_registered_and_verified_like_the_south(product):
    from data_manifest.products import embedded_path, get_product, verify_sha256

    p = get_product(product)
    south = get_product(product.replace("north", "south"))
    assert p["source"] == "embedded" and p["package"] == "lunar-toolkit"
    assert "+lat_0=90 " in p["crs"] and p["extent_m"] == south["extent_m"] and p["shape"] == south["shape"]
    path = embedded_path(product)
    assert verify_sha256(path, p["sha256"]) == p["sha256"] and path.stat().st_size == p["size_bytes"]


def test_north_dem_is_the_north_polar_product():
    from crater_synth.terrain.dem import Dem
    from data_manifest.products import embedded_path

    dem = Dem(embedded_path("lola_ldem256_north"), product="lola_ldem256_north")
    assert dem.hemisphere() == "north" and dem.pixel_size_m == 1600.0
    col, row = dem.latlon_to_pixel(90.0, 0.0)
    assert (float(col), float(row)) == pytest.approx((381.0, 381.0))  # the pole in the middle
    col, row = dem.latlon_to_pixel(85.0, 0.0)  # lon 0 runs down the north map
    assert float(col) == pytest.approx(381.0) and float(row) > 381.0


# ------------------------------------------------------------------------------ the physical Sun
@pytest.mark.parametrize("lat", [75.0, 85.0, 88.63])
def test_highest_sun_stands_towards_the_equator_at_both_poles(lat):
    colat = 90.0 - lat
    # North: local south (180 deg) is towards the equator; south: local north (0 deg).
    assert max_sun_elevation_deg(lat, 180.0) == pytest.approx(colat + LUNAR_OBLIQUITY_DEG, abs=1e-9)
    assert max_sun_elevation_deg(-lat, 0.0) == pytest.approx(colat + LUNAR_OBLIQUITY_DEG, abs=1e-9)
    assert max_sun_elevation_deg(lat, 0.0) == pytest.approx(LUNAR_OBLIQUITY_DEG - colat, abs=1e-9)
    az = np.arange(0.0, 360.0, 5.0)
    assert az[np.argmax(max_sun_elevation_deg(lat, az))] == g.noon_azimuth_deg(lat) == 180.0
    # The mirror image about the equator sees the mirrored Sun: the same elevation at 180 - A.
    np.testing.assert_allclose(max_sun_elevation_deg(lat, 180.0 - az), max_sun_elevation_deg(-lat, az), atol=1e-9)


def test_near_noon_sweep_puts_the_suns_where_they_are_highest_at_both_poles():
    from crater_synth.config import compose, resolved

    grid = grid_from_config(resolved(compose(["sweep=demo_physical_noon"]))["sweep"])
    for lat in (-85.0, 85.0):
        params = [grid.params(i, lat) for i in range(len(grid))]
        az = np.array([p.sun_azimuth for p in params])
        off_noon = np.abs((az - g.noon_azimuth_deg(lat) + 180.0) % 360.0 - 180.0)
        assert off_noon.max() == pytest.approx(60.0)  # within 60 deg of noon
        assert all(p.sun_elevation > 0.16 for p in params)  # every sun rises
    south = [grid.params(i, -85.0) for i in range(len(grid))]
    north = [grid.params(i, 85.0) for i in range(len(grid))]
    for s, n in zip(south, north):
        assert n.sun_azimuth == pytest.approx((180.0 - s.sun_azimuth) % 360.0)  # mirrored about the equator
        assert n.sun_elevation == pytest.approx(s.sun_elevation)
        assert n.sun_azimuth_param == s.sun_azimuth == s.sun_azimuth_param  # the grid value, as in the south


# ------------------------------------------------------------------------------ mirrored terrain
PIXEL_M, N_PX = 400.0, 400  # a 160 km square around the crater
CRATER_LAT, CRATER_LON, CRATER_D = -86.0, 30.0, 12_000.0


def south_heights(x, y, x0, y0):
    """A bowl crater with a raised rim, a hill to one side (its shadow breaks the symmetry) and a tilt."""
    r = np.hypot(x - x0, y - y0)
    rad = 0.5 * CRATER_D
    bowl = np.where(r < rad, -2000.0 + 2400.0 * (r / rad) ** 2, 400.0 * np.exp(-(r - rad) / (0.3 * rad)))
    hill = 1500.0 * np.exp(-(((x - x0 - 9000.0) / 4000.0) ** 2 + ((y - y0 - 6000.0) / 3000.0) ** 2))
    return bowl + hill + 0.004 * (x - x0) - 0.002 * (y - y0) + 300.0


def write_dem(path: Path, heights: np.ndarray, left: float, top: float, pole: str) -> Path:
    import rasterio
    from affine import Affine

    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=heights.shape[1],
        height=heights.shape[0],
        count=1,
        dtype="float32",
        crs=STEREO[pole],
        transform=Affine(PIXEL_M, 0.0, left, 0.0, -PIXEL_M, top),
    ) as dst:
        dst.write(heights.astype(np.float32), 1)
    return path


@pytest.fixture(scope="module")
def mirrored_dems(tmp_path_factory):
    """The same terrain at (CRATER_LAT, CRATER_LON) in the south and mirrored at (-CRATER_LAT, CRATER_LON):
    the north raster is the south one with its rows flipped, its extent mirrored in y."""
    d = tmp_path_factory.mktemp("mirror")
    x0, y0 = g.polar_stereo_forward(CRATER_LAT, CRATER_LON, "south")
    left, top = float(x0) - N_PX / 2 * PIXEL_M, float(y0) + N_PX / 2 * PIXEL_M
    c = left + (np.arange(N_PX) + 0.5) * PIXEL_M
    r = top - (np.arange(N_PX) + 0.5) * PIXEL_M
    x, y = np.meshgrid(c, r)
    h = south_heights(x, y, float(x0), float(y0))
    bottom = top - N_PX * PIXEL_M
    return {
        "south": write_dem(d / "south.tif", h, left, top, "south"),
        "north": write_dem(d / "north.tif", h[::-1], left, -bottom, "north"),
    }


def test_mirrored_dem_samples_the_mirrored_terrain(mirrored_dems):
    from crater_synth.terrain.dem import Dem

    south, north = Dem(mirrored_dems["south"]), Dem(mirrored_dems["north"])
    assert (south.hemisphere(), north.hemisphere()) == ("south", "north")
    rng = np.random.default_rng(3)
    e, n = rng.uniform(-40e3, 40e3, (2, 500))
    # Local (e, n) about the crater in the south is (e, -n) about the mirrored crater in the north.
    from crater_synth.terrain.grid import sphere_points

    _, slat, slon = sphere_points(e, n, CRATER_LAT, CRATER_LON)
    _, nlat, nlon = sphere_points(e, -n, -CRATER_LAT, CRATER_LON)
    np.testing.assert_allclose(nlat, -slat, atol=1e-9)
    np.testing.assert_allclose(north.sample(nlat, nlon).heights, south.sample(slat, slon).heights, atol=1e-2)


def _render(tmp_path, dem_path, lat, cam_azimuths, data_dir):
    out = tmp_path / f"ds_{'north' if lat > 0 else 'south'}"
    proc = run_cli(
        "dataset",
        *TINY,
        "crater=custom",
        "crater.custom.name=bowl",
        f"crater.custom.lat={lat}",
        f"crater.custom.lon={CRATER_LON}",
        f"crater.custom.diameter_km={CRATER_D / 1000.0}",
        f"dem.path={dem_path}",
        "dem.stack=[]",
        "terrain.far_radius_km=50",
        # The near mesh splits each quad along one diagonal, which the mirror turns into the other: at
        # TINY's 48 vertices (1.3 km, a tenth of D) that alone changes ~2 % of the lit pixels, so the
        # mesh is denser here (320 m); everything else is TINY.
        "terrain.near_vertices=192",
        "render.roi_min_px=64",
        "sweep.sun_model=physical",
        "sweep.sun_elevation.count=1",
        "sweep.sun_elevation.values=[0.7]",
        "sweep.sun_azimuth.count=1",
        "sweep.sun_azimuth.values=[25]",
        "sweep.cam_elevation.count=1",
        "sweep.cam_elevation.values=[60]",
        "sweep.cam_azimuth.count=2",
        f"sweep.cam_azimuth.values=[{cam_azimuths[0]},{cam_azimuths[1]}]",
        f"data_dir={data_dir}",
        f"out_dir={out}",
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    return sorted(rows, key=lambda r: r["index"]), out


def test_mirrored_terrain_renders_the_mirrored_image(mirrored_dems, tmp_path):
    """The same crater mirrored about the equator, seen by the mirrored camera under the mirrored Sun
    (the physical sweep's sun azimuth 25 deg from noon: 25 in the south, 155 in the north), renders the
    south image flipped left-right."""
    data = tmp_path / "data"
    south, s_dir = _render(tmp_path, mirrored_dems["south"], CRATER_LAT, (30, 90), data)
    north, n_dir = _render(tmp_path, mirrored_dems["north"], -CRATER_LAT, (150, 90), data)
    assert [r["sun_azimuth"] for r in south] == [25.0, 25.0] and [r["sun_azimuth"] for r in north] == [155.0, 155.0]
    assert all(r["sun_azimuth_param"] == 25.0 for r in north) and "sun_azimuth_param" not in south[0]
    for s, n in zip(south, north):
        assert n["sun_elevation"] == pytest.approx(s["sun_elevation"])
        assert (n["width"], n["height"]) == (s["width"], s["height"])
        s_if, n_if = read_channel(s_dir / s["path"]), read_channel(n_dir / n["path"])
        s_lit, n_lit = read_channel(s_dir / s["path"], "lit") > 0.5, read_channel(n_dir / n["path"], "lit") > 0.5
        mirrored_lit, mirrored_if = s_lit[:, ::-1], s_if[:, ::-1]
        assert 0.2 < s_lit.mean() < 0.98  # shadows and light: the comparison means something
        assert (n_lit == mirrored_lit).mean() >= 0.995
        assert abs(float(n_if.mean()) / float(mirrored_if.mean()) - 1.0) <= 0.005
        # Not trivially symmetric: the unflipped south image differs.
        assert (n_lit == s_lit).mean() < 0.99


def test_mirrored_dem_stack_blends_like_the_south(tmp_path):
    """The DEM stack at the north pole: a finer layer over the base blends into the same heights as its
    south mirror image."""
    from crater_synth.terrain.dem import Dem
    from crater_synth.terrain.stack import DemStack

    x0, y0 = g.polar_stereo_forward(CRATER_LAT, CRATER_LON, "south")
    heights = {}
    for pole in ("south", "north"):
        stacks = []
        for name, px, n, bias in (("base", 1600.0, 64, 0.0), ("fine", 200.0, 120, 40.0)):
            left, top = float(x0) - n / 2 * px, float(y0) + n / 2 * px
            c = left + (np.arange(n) + 0.5) * px
            r = top - (np.arange(n) + 0.5) * px
            x, y = np.meshgrid(c, r)
            h = 0.01 * (x - x0) + 0.02 * (y - y0) + bias
            if pole == "north":
                h, top = h[::-1], -(top - n * px)
            path = tmp_path / f"{pole}_{name}.tif"
            import rasterio
            from affine import Affine

            with rasterio.open(
                path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs=STEREO[pole],
                transform=Affine(px, 0.0, left, 0.0, -px, top),
            ) as dst:  # fmt: skip
                dst.write(h.astype(np.float32), 1)
            stacks.append(Dem(path, product=f"{pole}_{name}"))
        stack = DemStack(stacks[0], [(stacks[1], "f" * 64, "fine")], blend_pixels=2.0)
        e = np.linspace(-20e3, 20e3, 81)
        lat = np.full_like(e, CRATER_LAT if pole == "south" else -CRATER_LAT)
        from crater_synth.terrain.grid import sphere_points

        _, plat, plon = sphere_points(e, np.full_like(e, 3000.0 if pole == "south" else -3000.0), lat[0], CRATER_LON)
        heights[pole] = stack.sample(plat, plon)
    np.testing.assert_allclose(heights["north"].heights, heights["south"].heights, atol=1e-2)
    np.testing.assert_allclose(heights["north"].fine_weight, heights["south"].fine_weight, atol=1e-6)
    w = heights["north"].fine_weight  # the line crosses the fine layer: base, blend band, fine
    assert w.min() == 0.0 and w.max() == 1.0 and ((w > 0.0) & (w < 1.0)).any()


# ------------------------------------------------------------------------------ real crops
def test_north_craters_are_cut_from_the_north_mosaic():
    from crater_synth.config import compose, craters, load_settings
    from train.errors import RealSetError
    from train.realset import load_mosaic, plan_embedded_crops

    names = ["peary", "hermite", "de_sitter"]
    realset = load_settings(["realset=wac_north", "realset.per_crater=20"]).realset
    mosaic = load_mosaic(realset)
    assert mosaic.pole == "north" and mosaic.product_id == "lroc_wac_north"
    entries = craters(compose([f"crater=[{','.join(names)}]"]))
    crops = plan_embedded_crops(mosaic.image.shape, mosaic, entries, realset)
    assert len(crops) == 60 and {c.source for c in crops} == {"lroc_wac_north"}
    for c in entries:  # the crater's box is centred where the north projection puts it
        u, v = mosaic.latlon_to_uv(c["lat"], c["lon"])
        lat, lon = mosaic.uv_to_latlon(u, v)
        assert (float(lat), float(lon)) == pytest.approx((c["lat"], c["lon"]), abs=1e-9)
    south = load_mosaic(load_settings([]).realset)
    assert south.pole == "south"
    with pytest.raises(RealSetError, match="crater peary .* lroc_wac_south .* realset=wac_north"):
        plan_embedded_crops(south.image.shape, south, entries[:1], realset)


# ------------------------------------------------------------------------------ end to end
@pytest.mark.integration
def test_a_north_crater_renders_trains_and_evaluates(tmp_path):
    """Two north craters through `dataset`, `train` and `evaluate` with tiny settings: the terrain
    from lola_ldem256_north, the real crops from wac_north."""
    from crater_synth.cli import main

    north = ["crater=[aepinus,bosch]", "dem=lola_ldem256_north", "realset=wac_north"]
    base = [*[o for o in TINY if not o.startswith("crater=")], *north, f"data_dir={tmp_path}/data"]
    base += [f"out_dir={tmp_path}/ds", "sweep.sun_model=physical", "sweep.sun_elevation.values=[1.0]"]
    proc = run_cli("dataset", *base)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [json.loads(line) for line in (tmp_path / "ds" / "manifest.jsonl").read_text().splitlines()]
    assert {r["crater"] for r in rows} == {"aepinus", "bosch"}
    assert all(r["sun_elevation"] > 0.16 for r in rows)  # physical suns around noon, which is south
    train = [
        *base,
        f"train.dataset_dir={tmp_path}/ds",
        f"run_dir={tmp_path}/run",
        f"train.cache_dir={tmp_path}/cache",
        "train.num_threads=1",
        "train.progress=false",
        "realset.per_crater=6",
        "model.input_size=64",
        "train.batch_size=8",
        "train.max_epochs=2",
        "train.hog.max_train_images=50",
    ]
    res = CliRunner().invoke(main, ["train", *train], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(main, ["evaluate", *train], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    for m in ("lunarnet_ex", "lunarsvm_ex", "hog_svm"):
        assert set(metrics[m]["per_crater"]) == {"aepinus", "bosch"}
        assert 0.0 <= metrics[m]["real_accuracy"] <= 1.0
        assert list(metrics[m]["per_source"]) == ["lroc_wac_north"]  # the real crops are the north mosaic's


def test_a_dem_spanning_the_equator_takes_craters_of_both_hemispheres(tmp_path):
    """The hemisphere check refuses only a DEM wholly in the other hemisphere: an equirectangular DEM
    over +-10 deg (any CRS PROJ reads) accepts both, and its coverage decides."""
    import rasterio
    from affine import Affine

    from crater_synth.terrain.dem import Dem, DemCoverageError, check_hemisphere

    px, n = 3000.0, 200
    path = tmp_path / "equator.tif"
    with rasterio.open(
        path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32",
        crs="+proj=eqc +lat_ts=0 +lon_0=0 +R=1737400 +units=m +no_defs",
        transform=Affine(px, 0.0, -n / 2 * px, 0.0, -px, n / 2 * px),
    ) as dst:  # fmt: skip
        dst.write(np.zeros((n, n), np.float32), 1)
    dem = Dem(path, product="equator")
    assert dem.hemisphere() is None
    check_hemisphere(dem, "north_one", 5.0)
    check_hemisphere(dem, "south_one", -5.0)
    assert dem.sample(np.array([5.0, -5.0]), np.array([1.0, 1.0])).heights.tolist() == [0.0, 0.0]
    south = Dem(write_dem(tmp_path / "s.tif", np.zeros((4, 4)), -800.0, 800.0, "south"), product="south_only")
    with pytest.raises(DemCoverageError, match="crater x .* DEM south_only is south-polar: use dem=lola_ldem256_north"):
        check_hemisphere(south, "x", 80.0)
