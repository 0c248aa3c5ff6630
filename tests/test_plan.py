"""Host-side render planning: camera, frame size, rim ellipse, sigma boxes and crop."""

import numpy as np
import pytest

from crater_core import geometry
from crater_core.sweep import grid_from_config
from crater_synth.config import compose, resolved
from crater_synth.dataset import plan_render

CRATER = {"name": "shackleton", "lat": -89.67, "lon": 129.78, "diameter_km": 21.0}


@pytest.fixture(scope="module")
def grid():
    return grid_from_config(resolved(compose(["sweep=paper"]))["sweep"])


@pytest.mark.parametrize("index", [0, 7, 149, 1234, 22_499])
def test_sigma_boxes_nest_are_centred_and_smallest_is_150px(grid, index):
    plan = plan_render(CRATER, {"rim_z_m": 0.0}, grid, index, 150)
    boxes = [plan["sigma_boxes"][f"{s:.1f}"] for s in sorted(grid.sigmas)]
    cu, cv = plan["center_px"]
    for (a0, b0, a1, b1), (c0, d0, c1, d1) in zip(boxes, boxes[1:]):
        assert c0 <= a0 and d0 <= b0 and a1 <= c1 and b1 <= d1  # nested
    for u0, v0, u1, v1 in boxes:
        assert (u0 + u1) / 2 == pytest.approx(cu) and (v0 + v1) / 2 == pytest.approx(cv)
        assert u1 - u0 == pytest.approx(v1 - v0)
    side_min = boxes[0][2] - boxes[0][0]
    assert 150 - 1e-6 <= side_min < 152
    u0, v0, u1, v1 = boxes[-1]
    width, height = plan["crop"][2] - plan["crop"][0], plan["crop"][3] - plan["crop"][1]
    assert u0 >= 0 and v0 >= 0 and u1 <= width and v1 <= height  # the render covers the biggest box


def test_box_side_is_sigma_times_major_axis(grid):
    plan = plan_render(CRATER, {"rim_z_m": 0.0}, grid, grid.index_of((0, 0, 9, 3)), 150)  # oblique 54 deg
    e = plan["rim_ellipse"]
    u0, _, u1, _ = plan["sigma_boxes"]["1.2"]
    assert u1 - u0 == pytest.approx(1.2 * 2 * e["a"])
    assert e["b"] < 0.9 * e["a"]  # an oblique view flattens the rim


def test_rim_ellipse_matches_projected_rim_points(grid):
    p = grid.params(grid.index_of((0, 0, 6, 5)))
    plan = plan_render(CRATER, {"rim_z_m": 350.0}, grid, p.index, 150)
    pose = geometry.look_at_camera(p.cam_elevation, p.cam_azimuth, plan["range_m"], grid.fov_deg)
    t = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    rim = np.stack([10_500 * np.cos(t), 10_500 * np.sin(t), np.full_like(t, 350.0)], axis=-1)
    uv, _ = geometry.project_points(rim, pose, plan["frame_width"])
    uv -= plan["crop"][:2]
    e = plan["rim_ellipse"]
    ca, sa = np.cos(e["angle_rad"]), np.sin(e["angle_rad"])
    d = uv - [e["cu"], e["cv"]]
    x, y = d @ [ca, sa], d @ [-sa, ca]
    np.testing.assert_allclose((x / e["a"]) ** 2 + (y / e["b"]) ** 2, 1.0, atol=1e-9)
