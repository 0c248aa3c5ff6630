"""crater_synth.terrain.dem: the embedded LOLA DEM, sampling, nodata policy, bad files, coverage."""

from __future__ import annotations

import numpy as np
import pytest

from crater_core import geometry as g
from crater_synth.terrain.dem import Dem, DemCoverageError, DemNodataError, DemReadError
from data_manifest.products import resolve_product

STEREO_SOUTH = "+proj=stere +lat_0=-90 +lat_ts=-90 +lon_0=0 +k=1 +x_0=0 +y_0=0 +R=1737400 +units=m +no_defs"
CRATERS = {  # IAU values (docs/specification.md): lat, lon, diameter km
    "shackleton": (-89.67, 129.78, 21.0),
    "de_gerlache": (-88.5, -87.1, 32.5),
    "shoemaker": (-88.1, 44.9, 51.0),
}


@pytest.fixture(scope="module")
def lola(tmp_path_factory):
    return Dem(resolve_product("lola_ldem256_south", tmp_path_factory.mktemp("data")), product="lola_ldem256_south")


def write_geotiff(path, data, pixel_m=1600.0, nodata=None, crs=STEREO_SOUTH, scale=None, offset=None, units=None):
    """A small north-up GeoTIFF centred on the south pole."""
    import rasterio
    from affine import Affine

    h, w = data.shape
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=w,
        height=h,
        count=1,
        dtype=data.dtype,
        crs=crs,
        transform=Affine(pixel_m, 0.0, -w / 2 * pixel_m, 0.0, -pixel_m, h / 2 * pixel_m),
        nodata=nodata,
    ) as dst:
        dst.write(data, 1)
        if scale is not None:
            dst.scales = (scale,)
        if offset is not None:
            dst.offsets = (offset,)
        if units is not None:
            dst.units = (units,)
    return path


def plane(n=64, pixel_m=1600.0):
    """Heights (m) of a tilted plane h = 0.02 x - 0.01 y + 100 at pixel centres."""
    c = (np.arange(n) - n / 2 + 0.5) * pixel_m
    x, y = np.meshgrid(c, -c)
    return 0.02 * x - 0.01 * y + 100.0


def ring_latlon(lat, lon, radius_m, n=72):
    """(lat, lon) of points at horizontal ENU radius ``radius_m`` around (lat, lon), projected onto the sphere."""
    az = np.radians(np.arange(n) * 360.0 / n)
    b = g.enu_basis(lat, lon)
    p = g.latlon_to_mc(lat, lon) + radius_m * (np.sin(az)[:, None] * b[0] + np.cos(az)[:, None] * b[1])
    plat, plon, _ = g.mc_to_latlon(p)
    return plat, plon


def test_embedded_dem_metadata(lola):
    assert lola.crs.to_dict()["proj"] == "stere"
    assert lola.crs.to_dict()["lat_0"] == -90
    assert lola.pixel_size_m == 1600.0
    assert (lola.width, lola.height) == (762, 762)
    np.testing.assert_allclose(lola.bounds, (-609600.0, -609600.0, 609600.0, 609600.0))
    assert lola.body_radius_m == g.MOON_RADIUS_M
    info = lola.info()
    assert info["product"] == "lola_ldem256_south" and "stere" in info["crs_proj"]


def test_projection_matches_proj_and_geometry_module(lola):
    from rasterio.warp import transform

    rng = np.random.default_rng(1)
    lat, lon = rng.uniform(-90, -75, 500), rng.uniform(-180, 180, 500)
    assert lola.stereo_pole == "south"  # the numpy projection, checked against PROJ below
    x, y = lola.latlon_to_xy(lat, lon)
    px, py = transform(lola.geographic_crs, lola.crs, lon, lat)
    np.testing.assert_allclose(x, px, atol=1e-6)
    np.testing.assert_allclose(y, py, atol=1e-6)
    xs, ys = g.south_polar_stereo_forward(lat, lon)
    np.testing.assert_allclose(x, xs, atol=1e-6)
    np.testing.assert_allclose(y, ys, atol=1e-6)


@pytest.mark.parametrize(
    "crs, pole",
    [
        (STEREO_SOUTH, "south"),
        (STEREO_SOUTH.replace("-90", "90"), "north"),
        (STEREO_SOUTH.replace("+x_0=0", "+x_0=5000"), None),  # a false easting: PROJ projects
        (STEREO_SOUTH.replace("+lat_ts=-90", "+lat_ts=-80"), None),  # another scale: PROJ projects
        ("+proj=eqc +R=1737400 +units=m +no_defs", None),
    ],
)
def test_projection_in_numpy_only_where_it_is_proj_s(tmp_path, crs, pole):
    from rasterio.warp import transform

    dem = Dem(write_geotiff(tmp_path / "d.tif", plane().astype(np.float32), crs=crs))
    assert dem.stereo_pole == pole
    lat = np.array([-89.0, -88.5, 88.7, 89.2]) if "eqc" not in crs else np.array([0.1, -0.2, 0.3, 0.0])
    lon = np.array([10.0, -120.0, 45.0, 179.0])
    x, y = dem.latlon_to_xy(lat, lon)
    px, py = transform(dem.geographic_crs, dem.crs, lon, lat)
    np.testing.assert_allclose(np.c_[x, y], np.c_[px, py], atol=1e-6)


def test_dem_handle_kept_open_and_reopened_after_pickling(lola):
    import pickle

    lat, lon = np.array([-88.0, -87.5]), np.array([20.0, 100.0])
    before = lola.sample(lat, lon).heights
    handle = lola._dataset()
    assert lola._dataset() is handle  # one open handle per process
    copy = pickle.loads(pickle.dumps(lola))  # as a worker receives it
    assert copy._open is None
    np.testing.assert_array_equal(copy.sample(lat, lon).heights, before)


@pytest.mark.parametrize("name", sorted(CRATERS))
def test_craters_inside_and_floor_below_rim(lola, name):
    lat, lon, d_km = CRATERS[name]
    col, row = lola.latlon_to_pixel(lat, lon)
    assert lola.inside(col, row)
    r = 500.0 * d_km
    floor = [lola.sample(*ring_latlon(lat, lon, f * r)).heights for f in (0.0, 0.1, 0.2, 0.3)]
    rims = np.stack([lola.sample(*ring_latlon(lat, lon, f * r)).heights for f in np.linspace(0.9, 1.1, 5)])
    floor_h, rim_h = float(np.min(floor)), float(rims.max(axis=0).mean())
    # Real LOLA data: every crater is over a kilometre deep even at 1600 m/px (Shackleton ~4 km).
    assert rim_h - floor_h > 1500.0, (name, rim_h, floor_h)


def test_bicubic_beats_nearest_on_smooth_surface(tmp_path):
    n, p = 64, 1600.0
    c = (np.arange(n) - n / 2 + 0.5) * p
    x, y = np.meshgrid(c, -c)
    truth = lambda xx, yy: 500.0 * np.sin(xx / 9000.0) * np.cos(yy / 7000.0)  # noqa: E731
    dem = Dem(write_geotiff(tmp_path / "smooth.tif", truth(x, y).astype(np.float32)))
    rng = np.random.default_rng(2)
    xq, yq = rng.uniform(-20 * p, 20 * p, 300), rng.uniform(-20 * p, 20 * p, 300)
    lat, lon = g.south_polar_stereo_inverse(xq, yq)
    got = dem.sample(lat, lon).heights
    err = np.abs(got - truth(xq, yq))
    col, row = dem.xy_to_pixel(xq, yq)
    nearest = truth(c[np.floor(col).astype(int)], -c[np.floor(row).astype(int)])
    assert err.max() < 2.0  # cubic spline on a 500 m, ~50 km wavelength field
    assert err.mean() < 0.1 * np.abs(nearest - truth(xq, yq)).mean()


def test_scale_offset_radius_and_km_units(tmp_path):
    h = plane()
    lat, lon = g.south_polar_stereo_inverse(np.array([3000.0, -8000.0]), np.array([-5000.0, 12000.0]))
    want = 0.02 * np.array([3000.0, -8000.0]) - 0.01 * np.array([-5000.0, 12000.0]) + 100.0
    # PDS-style: DN * 0.5 + 1737400 = planetary radius (m).
    dn = np.round(h / 0.5).astype(np.int16)
    radius_dem = Dem(write_geotiff(tmp_path / "radius.tif", dn, nodata=-32768, scale=0.5, offset=1737400.0))
    assert radius_dem.stores_radius
    np.testing.assert_allclose(radius_dem.sample(lat, lon).heights, want, atol=0.5)
    km_dem = Dem(write_geotiff(tmp_path / "km.tif", (h / 1000.0).astype(np.float32), units="km"))
    np.testing.assert_allclose(km_dem.sample(lat, lon).heights, want, atol=0.05)


def test_truncated_dem_is_one_clear_error(tmp_path, lola):
    data = lola.path.read_bytes()
    bad = tmp_path / "truncated.tif"
    bad.write_bytes(data[: len(data) // 3])
    lat, lon, d_km = CRATERS["shackleton"]
    with pytest.raises(DemReadError, match="truncated.tif") as info:
        Dem(bad).sample(*ring_latlon(lat, lon, 500.0 * d_km))
    assert "\n" not in str(info.value)


def test_garbage_and_missing_files(tmp_path):
    junk = tmp_path / "junk.tif"
    junk.write_bytes(b"not a raster" * 50)
    with pytest.raises(DemReadError, match="junk.tif"):
        Dem(junk)
    with pytest.raises(DemReadError, match="does not exist"):
        Dem(tmp_path / "nope.tif")


def test_non_lunar_or_geographic_crs_refused(tmp_path):
    with pytest.raises(DemReadError, match="geographic CRS"):
        Dem(write_geotiff(tmp_path / "geo.tif", plane().astype(np.float32), crs="+proj=longlat +R=1737400 +no_defs"))
    with pytest.raises(DemReadError, match="not lunar"):
        Dem(write_geotiff(tmp_path / "earth.tif", plane().astype(np.float32), crs="EPSG:3031"))


def test_point_outside_dem(lola):
    with pytest.raises(DemCoverageError, match="outside DEM lola_ldem256_south"):
        lola.sample(np.array([-70.0, -89.0]), np.array([0.0, 0.0]), what="test patch")


def test_mostly_nodata_patch_refused(tmp_path):
    h = plane().astype(np.float32)
    h[:, : int(0.6 * h.shape[1])] = -9999.0
    dem = Dem(write_geotiff(tmp_path / "holey.tif", h, nodata=-9999.0))
    xq, yq = np.meshgrid(np.linspace(-40e3, 40e3, 30), np.linspace(-40e3, 40e3, 30))
    lat, lon = g.south_polar_stereo_inverse(xq, yq)
    with pytest.raises(DemNodataError, match="max_nodata_fraction=0.02"):
        dem.sample(lat, lon, max_nodata_fraction=0.02, what="near field of crater test")


def test_small_holes_filled_and_counted(tmp_path):
    h = plane().astype(np.float32)
    truth = h.copy()
    for r, c in [(20, 20), (30, 40), (44, 25)]:  # three 2x2 holes
        h[r : r + 2, c : c + 2] = -32768
    dem = Dem(write_geotiff(tmp_path / "holes.tif", h, nodata=-32768))
    n = h.shape[0]
    centres = (np.arange(n) - n / 2 + 0.5) * 1600.0
    xq, yq = np.meshgrid(centres[8:-8], -centres[8:-8])  # every interior pixel centre
    lat, lon = g.south_polar_stereo_inverse(xq, yq)
    res = dem.sample(lat, lon, max_nodata_fraction=0.02)
    assert res.filled_holes == 3
    assert res.filled_pixels == 12
    assert 0 < res.nodata_fraction < 0.02
    assert np.isfinite(res.heights).all()
    # Exact away from the holes; inside them the inverse-distance fill of this 32 m/px plane stays
    # within about one pixel's worth of relief.
    err = np.abs(res.heights - truth[8:-8, 8:-8])
    assert np.median(err) < 1e-6
    assert err.max() < 40.0


def write_pds3(dirpath, heights_m, pixel_m=20.0):
    """A tiny LOLA-style PDS3 product: detached label + LSB int16 image, DN * 0.5 + 1737400 = radius."""
    n = heights_m.shape[0]
    np.round(heights_m / 0.5).astype("<i2").tofile(dirpath / "ldem_test.img")
    label = f"""PDS_VERSION_ID = "PDS3"
RECORD_TYPE = FIXED_LENGTH
RECORD_BYTES = {2 * n}
FILE_RECORDS = {n}
^IMAGE = "ldem_test.img"
PRODUCT_ID = "LDEM_TEST"
TARGET_NAME = MOON
OBJECT = IMAGE
  LINES = {n}
  LINE_SAMPLES = {n}
  SAMPLE_TYPE = LSB_INTEGER
  SAMPLE_BITS = 16
  UNIT = METER
  SCALING_FACTOR = 0.5
  OFFSET = 1737400.
  MISSING_CONSTANT = -32768
END_OBJECT = IMAGE
OBJECT = IMAGE_MAP_PROJECTION
  MAP_PROJECTION_TYPE = "POLAR STEREOGRAPHIC"
  A_AXIS_RADIUS = 1737.4 <KM>
  B_AXIS_RADIUS = 1737.4 <KM>
  C_AXIS_RADIUS = 1737.4 <KM>
  POSITIVE_LONGITUDE_DIRECTION = "EAST"
  CENTER_LATITUDE = -90. <DEG>
  CENTER_LONGITUDE = 0. <DEG>
  LINE_FIRST_PIXEL = 1
  LINE_LAST_PIXEL = {n}
  SAMPLE_FIRST_PIXEL = 1
  SAMPLE_LAST_PIXEL = {n}
  MAP_PROJECTION_ROTATION = 0.0
  MAP_SCALE = {pixel_m} <METERS/PIXEL>
  LINE_PROJECTION_OFFSET = {n / 2 - 0.5}
  SAMPLE_PROJECTION_OFFSET = {n / 2 - 0.5}
END_OBJECT = IMAGE_MAP_PROJECTION
END
"""
    (dirpath / "ldem_test.lbl").write_text(label.replace("\n", "\r\n"))
    return dirpath / "ldem_test.lbl"


def test_pds3_img_lbl_product(tmp_path):
    n, p = 32, 20.0
    h = plane(n, p)
    dem = Dem(write_pds3(tmp_path, h, p))
    assert dem.driver == "PDS" and dem.pixel_size_m == p and dem.stores_radius
    xq, yq = np.array([0.0, -155.0, 201.0]), np.array([0.0, 97.0, -233.0])
    lat, lon = g.south_polar_stereo_inverse(xq, yq)
    np.testing.assert_allclose(dem.sample(lat, lon).heights, 0.02 * xq - 0.01 * yq + 100.0, atol=0.5)
