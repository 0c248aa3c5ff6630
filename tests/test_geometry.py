"""crater_core.geometry: projections against PROJ, curvature, local frames, cameras, rim ellipses."""

from __future__ import annotations

import numpy as np
import pytest

from crater_core import geometry as g

STEREO_SOUTH = "+proj=stere +lat_0=-90 +lat_ts=-90 +lon_0=0 +k=1 +x_0=0 +y_0=0 +R=1737400 +units=m +no_defs"
MOON_LONLAT = "+proj=longlat +R=1737400 +no_defs"


def test_south_polar_stereographic_matches_proj():
    from rasterio.crs import CRS
    from rasterio.warp import transform

    rng = np.random.default_rng(0)
    lat = rng.uniform(-90.0, -60.0, 2000)
    lon = rng.uniform(-180.0, 180.0, 2000)
    xp, yp = transform(CRS.from_proj4(MOON_LONLAT), CRS.from_proj4(STEREO_SOUTH), lon, lat)
    x, y = g.south_polar_stereo_forward(lat, lon)
    np.testing.assert_allclose(x, xp, atol=1e-6)
    np.testing.assert_allclose(y, yp, atol=1e-6)
    lat2, lon2 = g.south_polar_stereo_inverse(x, y)
    np.testing.assert_allclose(lat2, lat, atol=1e-9)
    np.testing.assert_allclose(lon2, lon, atol=1e-9)


STEREO_NORTH = "+proj=stere +lat_0=90 +lat_ts=90 +lon_0=0 +k=1 +x_0=0 +y_0=0 +R=1737400 +units=m +no_defs"


@pytest.mark.parametrize(
    "pole, crs, lat_range", [("south", STEREO_SOUTH, (-90.0, -60.0)), ("north", STEREO_NORTH, (60.0, 90.0))]
)
def test_polar_stereographic_round_trips_and_matches_proj_at_both_poles(pole, crs, lat_range):
    from rasterio.crs import CRS
    from rasterio.warp import transform

    rng = np.random.default_rng(1)
    lat = rng.uniform(*lat_range, 2000)
    lon = rng.uniform(-180.0, 180.0, 2000)
    xp, yp = transform(CRS.from_proj4(MOON_LONLAT), CRS.from_proj4(crs), lon, lat)
    x, y = g.polar_stereo_forward(lat, lon, pole)
    np.testing.assert_allclose(x, xp, atol=1e-6)
    np.testing.assert_allclose(y, yp, atol=1e-6)
    lat2, lon2 = g.polar_stereo_inverse(x, y, pole)
    np.testing.assert_allclose(lat2, lat, atol=1e-9)
    np.testing.assert_allclose(lon2, lon, atol=1e-9)
    # The inverse first: projected points back to the same projected points.
    xy = rng.uniform(-600e3, 600e3, (2, 500))
    np.testing.assert_allclose(g.polar_stereo_forward(*g.polar_stereo_inverse(*xy, pole), pole), xy, atol=1e-6)


def test_north_projection_is_the_south_one_mirrored():
    """(lat, lon) in the north lands where (-lat, lon) lands in the south, y mirrored: lon 0 points down
    the north map and up the south one, lon 90 E to the right on both."""
    lat, lon = np.array([80.0, 85.0, 89.0]), np.array([0.0, 90.0, -135.0])
    xn, yn = g.polar_stereo_forward(lat, lon, "north")
    xs, ys = g.polar_stereo_forward(-lat, lon, "south")
    np.testing.assert_allclose(xn, xs, atol=1e-9)
    np.testing.assert_allclose(yn, -ys, atol=1e-9)
    assert yn[0] < 0 < xn[1]
    with pytest.raises(ValueError, match="pole"):
        g.polar_stereo_forward(80.0, 0.0, "east")


def test_local_north_points_at_the_north_pole_and_away_from_the_south_pole():
    for lat, towards in ((85.0, 1.0), (-85.0, -1.0)):
        north = g.enu_basis(lat, 40.0)[1]
        pole = np.array([0.0, 0.0, towards])
        # The pole lies ahead along local north in the north, behind it in the south.
        assert np.sign(north @ (pole - g.latlon_to_mc(lat, 40.0) / g.MOON_RADIUS_M)) == towards
    assert g.hemisphere(85.0) == "north" and g.hemisphere(-85.0) == "south"
    assert g.noon_azimuth_deg(85.0) == 180.0 and g.noon_azimuth_deg(-85.0) == 0.0


def test_curvature_drop_at_100_km():
    d, r = 100e3, g.MOON_RADIUS_M
    approx = d**2 / (2.0 * r)
    assert abs(g.curvature_drop_m(d) - approx) / approx < 0.01
    assert 2.8e3 < approx < 2.95e3
    # The same drop seen in the ENU frame: a sphere point at arc length d from the origin.
    lat0, lon0 = -89.67, 129.78
    north = g.enu_basis(lat0, lon0)[1]
    up = g.enu_basis(lat0, lon0)[2]
    theta = d / r
    p = r * (np.cos(theta) * up + np.sin(theta) * north)
    enu = g.mc_to_enu(p, lat0, lon0)
    assert abs(-enu[2] - approx) / approx < 0.01


@pytest.mark.parametrize("lat, lon", [(-89.67, 129.78), (-88.5, -87.1), (-88.1, 44.9), (0.0, 0.0), (45.0, 200.0)])
def test_enu_basis_orthonormal_right_handed(lat, lon):
    b = g.enu_basis(lat, lon)
    np.testing.assert_allclose(b @ b.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.cross(b[0], b[1]), b[2], atol=1e-12)
    np.testing.assert_allclose(b[2], g.latlon_to_mc(lat, lon) / g.MOON_RADIUS_M, atol=1e-12)


@pytest.mark.parametrize("lat, lon", [(-89.67, 129.78), (-88.5, -87.1), (-88.1, 44.9)])
def test_north_points_away_from_south_pole(lat, lon):
    east, north, _ = g.enu_basis(lat, lon)
    pole = np.array([0.0, 0.0, -g.MOON_RADIUS_M])
    here = g.latlon_to_mc(lat, lon)
    step = 1000.0
    assert np.linalg.norm(here + step * north - pole) > np.linalg.norm(here - pole) + 0.99 * step
    # East is the direction of increasing longitude.
    lat1, lon1, _ = g.mc_to_latlon(here + step * east)
    assert (lon1 - lon + 540.0) % 360.0 - 180.0 > 0.0
    lat2, _, _ = g.mc_to_latlon(here + step * north)
    assert lat2 > lat


@pytest.mark.parametrize("elev, az", [(90.0, 0.0), (70.0, 40.0), (54.0, 215.0)])
def test_projected_circle_is_the_returned_ellipse(elev, az):
    width, radius = 1024, 10.5e3
    pose = g.look_at_camera(elev, az, 1.5 * 21e3, 90.0)
    centre = np.array([0.0, 0.0, 250.0])
    t = np.linspace(0.0, 2.0 * np.pi, 400, endpoint=False)
    circle = centre + radius * np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=-1)
    uv, depth = g.project_points(circle, pose, width)
    assert (depth > 0).all()
    ell = g.project_horizontal_circle(centre, radius, pose, width)
    ca, sa = np.cos(ell.angle), np.sin(ell.angle)
    du, dv = uv[:, 0] - ell.cu, uv[:, 1] - ell.cv
    q = ((ca * du + sa * dv) / ell.a) ** 2 + ((-sa * du + ca * dv) / ell.b) ** 2
    np.testing.assert_allclose(q, 1.0, atol=1e-6)
    assert ell.a >= ell.b > 0


@pytest.mark.parametrize("elev, az", [(90.0, 180.0), (86.0, 60.0), (54.0, 215.0)])
def test_back_projection_inverts_projection(elev, az):
    pose = g.look_at_camera(elev, az, 1.5 * 40e3, 90.0)
    rng = np.random.default_rng(1)
    pts = np.stack([rng.uniform(-20e3, 20e3, 500), rng.uniform(-20e3, 20e3, 500), rng.uniform(-3e3, 2e3, 500)], axis=-1)
    uv, depth = g.project_points(pts, pose, 600)
    np.testing.assert_allclose(g.back_project_pixels(uv, depth, pose, 600), pts, atol=1e-6)


def test_nadir_camera_at_azimuth_180_puts_north_up_and_east_right():
    pose = g.look_at_camera(90.0, 180.0, 30e3, 90.0)
    (u_n, v_n), _ = g.project_points(np.array([0.0, 1e3, 0.0]), pose, 400)
    (u_e, v_e), _ = g.project_points(np.array([1e3, 0.0, 0.0]), pose, 400)
    assert v_n < 200.0 and abs(u_n - 200.0) < 1e-6  # north is up
    assert u_e > 200.0 and abs(v_e - 200.0) < 1e-6  # east is right


@pytest.mark.parametrize("elev, az", [(90.0, 0.0), (62.0, 120.0), (54.0, 330.0)])
def test_camera_looks_at_target(elev, az):
    target = np.array([100.0, -50.0, 30.0])
    pose = g.look_at_camera(elev, az, 30e3, 90.0, target=target)
    want = (target - pose.position) / np.linalg.norm(target - pose.position)
    np.testing.assert_allclose(pose.forward, want, atol=1e-12)
    np.testing.assert_allclose(pose.rotation.T @ pose.rotation, np.eye(3), atol=1e-12)
    uv, depth = g.project_points(target, pose, 640)
    np.testing.assert_allclose(uv, [320.0, 320.0], atol=1e-9)
    assert depth == pytest.approx(30e3)
    # Camera elevation above the local horizon as configured.
    v = pose.position - target
    assert np.degrees(np.arcsin(v[2] / np.linalg.norm(v))) == pytest.approx(elev)
