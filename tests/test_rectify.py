"""crater_synth.navigation.rendered.rectify: detection on an oblique frame's ground plane."""

from __future__ import annotations

import numpy as np
import pytest

from crater_core import geometry
from crater_synth.navigation.detectors.classical import Detection
from crater_synth.navigation.detectors.learned import LearnedSettings
from crater_synth.navigation.rendered import rectify as rc

WIDTH = 128
RANGE_M = 50_000.0


def oblique_row(off_nadir: float, azimuth: float = 30.0) -> dict:
    target = np.array([2_000.0, -1_000.0, 300.0])
    cam = geometry.look_at_camera(90.0 - off_nadir, azimuth, RANGE_M, 30.0, target=target)
    return {
        "rel_path": "f.exr",
        "camera_enu": {
            "position_m": cam.position.tolist(),
            "rotation": cam.rotation.tolist(),
            "fov_deg": 30.0,
            "width_px": WIDTH,
        },
        "view": {"off_nadir_deg": off_nadir, "range_m": RANGE_M},
    }


def test_the_plane_passes_under_the_boresight_level_with_the_moon():
    row = oblique_row(40.0)
    point, normal = rc.ground_plane(row, rc.frame_pose(row))
    assert point == pytest.approx([2_000.0, -1_000.0, 300.0], abs=1e-6)
    up = point + np.array([0.0, 0.0, geometry.MOON_RADIUS_M])
    assert normal == pytest.approx(up / np.linalg.norm(up)) and normal[2] > 0.999


def test_a_frame_pixel_lands_on_its_ground_point_in_the_plane_image(monkeypatch):
    """The plane image is the frame resampled: a bright pixel at the image of a ground point appears at that
    point's plane pixel; the plane image is larger than the frame for an oblique view (foreshortening undone)."""
    row = oblique_row(40.0)
    rect = rc.rectification(row, (WIDTH, WIDTH))
    e1, e2 = geometry.plane_basis(rect["normal"])
    ground = rect["point"] + 4_000.0 * e1 - 3_000.0 * e2
    (u, v), _ = geometry.project_points(ground, rect["pose"], WIDTH)
    frame = np.zeros((WIDTH, WIDTH), np.float32)
    frame[int(v) - 1 : int(v) + 2, int(u) - 1 : int(u) + 2] = 1.0
    seen = {}
    monkeypatch.setattr(rc, "detect", lambda image, *a, **k: (seen.setdefault("plane", image), ([], 0.0))[1])
    assert rc.rectified_detect(frame, row, LearnedSettings()) == []
    plane = seen["plane"]
    assert plane.shape == (rect["size"][1], rect["size"][0]) and plane.size > 1.5 * frame.size
    j, i = np.linalg.solve(rect["to_plane"], [4_000.0, -3_000.0, 1.0])[:2]
    bright = np.argwhere(plane > 0.5)
    assert len(bright) and np.abs(bright.mean(0) - [i, j]).max() < 2.0


def test_a_circle_found_on_the_plane_comes_back_as_its_rim_ellipse(monkeypatch):
    """A crater found on the plane is returned as the exact image of its rim circle: centre and semi-major
    axis of geometry.project_circles; one found on the fill outside the footprint is dropped."""
    row = oblique_row(35.0, azimuth=200.0)
    rect = rc.rectification(row, (WIDTH, WIDTH))
    r_m = 1_500.0
    x, y = 2_500.0, 1_000.0
    j, i = np.linalg.solve(rect["to_plane"], [x, y, 1.0])[:2]
    near_corner = Detection(1.0, rect["size"][1] - 1.0, 3.0, 0.8)  # the near side is narrower: fill there
    found = [Detection(j, i, r_m / rect["gsd_m"], 0.9), near_corner]
    monkeypatch.setattr(rc, "detect", lambda *a, **k: (found, 0.0))
    (det,) = rc.rectified_detect(np.random.default_rng(0).random((WIDTH, WIDTH)), row, LearnedSettings())
    e1, e2 = geometry.plane_basis(rect["normal"])
    centre = rect["point"] + x * e1 + y * e2
    cu, cv, a, b, _ = geometry.project_circles(centre[None], rect["normal"][None], np.array([r_m]), rect["pose"], WIDTH)
    assert (det.u, det.v, det.r, det.score) == pytest.approx((cu[0], cv[0], a[0], 0.9), abs=1e-6)
    assert b[0] < 0.9 * a[0]  # foreshortened in the frame


def test_a_frame_near_nadir_is_its_own_plane_image():
    """The plane's axes are the camera's: a frame seen 0.5 degrees off nadir maps onto its plane image
    nearly pixel for pixel (scale and offset within a pixel across the frame)."""
    row = oblique_row(0.5, azimuth=123.0)
    rect = rc.rectification(row, (WIDTH, WIDTH))
    grid = np.array([[0.0, 0.0, 1.0], [WIDTH, 0.0, 1.0], [0.0, WIDTH, 1.0], [WIDTH, WIDTH, 1.0]])
    frame = grid @ (rect["to_frame"] @ rect["to_plane"]).T
    assert np.abs(frame[:, :2] / frame[:, 2:] - grid[:, :2]).max() < 1.5


def test_a_nadir_frame_is_detected_as_it_is(monkeypatch):
    calls = []
    monkeypatch.setattr(
        rc, "detect", lambda image, *a, **k: (calls.append(image.shape), ([Detection(1, 2, 3, 4)], 0.0))[1]
    )
    assert rc.rectified_detect(np.zeros((WIDTH, WIDTH)), oblique_row(0.0), LearnedSettings()) == [Detection(1, 2, 3, 4)]
    assert calls == [(WIDTH, WIDTH)]
