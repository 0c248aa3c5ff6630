"""Oblique rendered frames on the ground: detections cut with the Moon's sphere (``rectify``) and the frame
resampled onto the ground (``ground_view``), with their way back into the frame's pixels (``to_frame``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crater_core.geometry import MOON_RADIUS_M
from crater_synth.navigation.detectors.classical import Detection
from crater_synth.navigation.fix.pose import project_pinhole
from crater_synth.navigation.rendered.evaluate import cv_camera
from crater_synth.navigation.rendered.ground_view import (
    MAX_SIDE_PX,
    camera_from_centre,
    ground_coords,
    ground_view,
    inside_footprint,
    sphere_points,
    to_frame,
)
from crater_synth.navigation.rendered.lost_in_space import LIS_PIXEL_M, camera_height_m, rectify

# The frame's ENU: the boresight's ground point at the origin, up its local vertical.
CENTRE = np.array([0.0, 0.0, -MOON_RADIUS_M])
RANGE_M = 220e3
WIDTH = 1024


def _oblique(view_deg: float = 52.0, fov_deg: float = 40.0, width: int = WIDTH, heading_deg: float = 0.0):
    """(frame row, camera position, world -> camera rotation, K) of a camera ``RANGE_M`` from the boresight's
    ground point, the boresight ``view_deg`` from the vertical there (~45 degrees off nadir from 150 km),
    looking ``heading_deg`` east of north."""
    view, head = math.radians(view_deg), math.radians(heading_deg)
    cam = RANGE_M * np.array([-math.sin(view) * math.sin(head), -math.sin(view) * math.cos(head), math.cos(view)])
    fwd = -cam / RANGE_M
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    rotation = np.column_stack([right, -down, -fwd])  # Blender columns: right, up, back
    row = {"camera_enu": {"rotation": rotation.tolist()}, "pose": {"width_px": width, "fov_deg": fov_deg}}
    r_wc, k = cv_camera(rotation, width, fov_deg)
    return row, cam, r_wc, k


def _visible_ground(cam, r_wc, k, n: int, seed: int = 3):
    """Up to ``n`` points of the sphere that the camera sees, and their pixels."""
    dirs = np.random.default_rng(seed).normal(size=(4000, 3)) * [0.08, 0.08, 0.0] + [0.0, 0.0, 1.0]
    pts = CENTRE + MOON_RADIUS_M * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    vis = (pts - cam) @ r_wc[2] > 0
    uv = project_pinhole(pts, r_wc, cam, k)
    vis &= (uv >= 0).all(axis=1) & (uv < WIDTH).all(axis=1)
    vis &= np.sum((pts - cam) * (pts - CENTRE), axis=1) < 0  # on the near side of the limb
    return pts[vis][:n], uv[vis][:n]


def test_rectify_places_an_oblique_frames_craters_at_their_distances_on_the_sphere():
    """A camera looking ~45 degrees off nadir from 150 km sees ground up to ~300 km away, where the Moon's
    curvature drops it ~25 km below a flat plane: cut with the sphere, the rectified detections keep the
    craters' distances along the ground (azimuthal equidistant about the point under the camera)."""
    row, cam, r_wc, k = _oblique()
    pts, uv = _visible_ground(cam, r_wc, k, 60)
    dets = [Detection(u, v, 5.0, 1.0) for u, v in uv]
    flat, _, kept = rectify(dets, row, RANGE_M)
    assert kept == list(range(len(dets))) and len(dets) == 60
    assert camera_height_m(row, RANGE_M) == pytest.approx(np.linalg.norm(cam - CENTRE) - MOON_RADIUS_M, abs=1.0)
    xy = np.array([[d.u, -d.v] for d in flat]) * LIS_PIXEL_M
    unit = (pts - CENTRE) / MOON_RADIUS_M
    i, j = np.triu_indices(len(pts), 1)
    truth = MOON_RADIUS_M * np.arccos(np.clip(np.sum(unit[i] * unit[j], axis=1), -1.0, 1.0))
    ratio = np.hypot(*(xy[i] - xy[j]).T) / truth
    assert truth.max() > 100e3 and np.median(np.abs(ratio - 1.0)) < 0.005 and np.max(np.abs(ratio - 1.0)) < 0.03


def test_ground_points_inverts_ground_coords():
    _, cam, _, _ = _oblique()
    q = cam - CENTRE
    east, north = np.meshgrid(np.linspace(-300e3, 300e3, 7), np.linspace(-250e3, 250e3, 5))
    pts = sphere_points(east, north, q)
    assert np.allclose(np.linalg.norm(pts, axis=-1), MOON_RADIUS_M)
    e, n = ground_coords(pts.reshape(-1, 3), q)
    assert np.allclose(e, east.ravel(), atol=0.01) and np.allclose(n, north.ravel(), atol=0.01)


@pytest.mark.parametrize("heading_deg", [0.0, 35.0, -120.0])
def test_ground_view_samples_each_ground_point_at_its_pixel_and_to_frame_carries_it_back(heading_deg):
    """The frame holds its own u coordinate (linear, so bilinear sampling is exact to OpenCV's 1/32 px
    grid): every ground-view pixel inside the footprint holds the u of the pixel its ground point projects
    to. A ground-view detection carried back lands on that pixel, its radius the ground radius over the
    ground sample there; for a camera looking north and for cameras turned from it."""
    row, cam, r_wc, k = _oblique(heading_deg=heading_deg)
    image = np.tile(np.arange(WIDTH, dtype=np.float32) + 0.5, (WIDTH, 1))
    view = ground_view(image, row, RANGE_M)
    _, _, q = camera_from_centre(row, RANGE_M)
    assert np.allclose(q, cam - CENTRE)
    # its side capped by a coarser ground sample than the boresight's; looking north, a footprint far longer
    # than wide (the tilt) on the east-north grid
    assert max(view.image.shape) <= MAX_SIDE_PX + 1 and view.pixel_m > RANGE_M / k[0, 0]
    assert 0.3 < view.valid.mean() < 0.9
    assert heading_deg or view.image.shape[0] > 1.3 * view.image.shape[1]
    row30, _, _, k30 = _oblique(view_deg=30.0, fov_deg=20.0)
    assert ground_view(image, row30, RANGE_M).pixel_m == pytest.approx(RANGE_M / k30[0, 0])  # uncapped
    ii, jj = np.nonzero(view.valid)
    pick = np.random.default_rng(0).choice(len(ii), 200, replace=False)
    i, j = ii[pick], jj[pick]
    gp = sphere_points(view.origin_m[0] + (j + 0.5) * view.pixel_m, view.origin_m[1] - (i + 0.5) * view.pixel_m, q)
    uv = project_pinhole(gp + CENTRE, r_wc, cam, k)
    assert np.allclose(view.image[i, j], uv[:, 0], atol=0.05)  # OpenCV interpolates in 1/32 px steps
    dets = [Detection(float(jj[p] + 0.5), float(ii[p] + 0.5), 4.0, 1.0) for p in pick[:20]]
    back = to_frame(dets, view, row, RANGE_M)
    got = np.array([[d.u, d.v] for d in back])
    assert np.allclose(got, uv[:20], atol=1e-3)
    depth = (gp[:20] + CENTRE - cam) @ r_wc[2]
    assert np.allclose([d.r for d in back], 4.0 * view.pixel_m * k[0, 0] / depth, rtol=1e-6)


def test_inside_footprint_drops_rims_the_footprints_edge_cuts():
    row, _, _, _ = _oblique()
    view = ground_view(np.ones((WIDTH, WIDTH), np.float32), row, RANGE_M)
    h, w = view.valid.shape
    ii, jj = np.nonzero(view.valid)
    centre = Detection(float(np.median(jj)) + 0.5, float(np.median(ii)) + 0.5, 8.0, 1.0)
    assert view.valid[int(centre.v), int(centre.u)]
    edge_j = int(np.nonzero(view.valid[int(centre.v)])[0][0])  # the footprint's first pixel on that row
    cut = Detection(edge_j + 2.5, centre.v, 8.0, 1.0)
    assert inside_footprint([centre, cut], view) == [centre]
    assert inside_footprint([], view) == []


def test_detect_on_ground_reads_a_detection_frames_row_and_returns_frame_pixels(monkeypatch):
    """A detection frame's row carries its optics in ``camera_enu``: the ground view of it is the one a
    navigation frame's row (optics in ``pose``) gives. The detector runs on the ground view; its rims
    within the footprint by the detector's border margin come back in the frame's pixels, the rest not."""
    from crater_synth.navigation.detectors.learned import LearnedSettings
    from crater_synth.navigation.rendered import ground_view as gv

    row, _, _, _ = _oblique(view_deg=38.0, fov_deg=30.0, width=256)
    # the Sun 10 degrees up in the east: its light travels west, -u in the ground view (east along +u)
    sun = {"elevation_deg": 10.0, "azimuth_deg": 90.0}
    set_row = {"camera_enu": dict(row["camera_enu"], width_px=256, fov_deg=30.0), "sun_enu": sun}
    image = np.random.default_rng(1).random((256, 256)).astype(np.float32)
    view = ground_view(image, set_row, RANGE_M)
    assert np.array_equal(view.image, ground_view(image, row, RANGE_M).image)
    ii, jj = np.nonzero(view.valid)
    inside = Detection(float(np.median(jj)) + 0.5, float(np.median(ii)) + 0.5, 6.0, 0.9)
    outside = Detection(0.5, 0.5, 6.0, 0.8)
    seen, lights = [], []

    def fake_detect(img, *a, **k):
        seen.append(img.shape)
        lights.append(k["light_dir"])
        return [inside, outside], 0.0

    monkeypatch.setattr(gv, "detect", fake_detect)
    params = LearnedSettings()
    got = gv.detect_on_ground(image, set_row, RANGE_M, params)
    assert seen == [view.image.shape] and got == to_frame([inside], view, set_row, RANGE_M)
    assert math.cos(lights[0]) == pytest.approx(-1.0, abs=1e-3)  # travel west; the ground's east is near ENU east
    assert 0 <= got[0].u < 256 and 0 <= got[0].v < 256
