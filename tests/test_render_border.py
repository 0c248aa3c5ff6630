"""Every render's EXR has exactly the planner's crop size and its content sits where the manifest
says (docs/renderer.md).

Blender turns ``render.border_*`` (float32 fractions) back into pixels by truncation, so a border
of exactly ``u0 / W`` came back as ``u0 - 1`` for 20-30 % of the paper sweep's camera poses: the
EXR was a pixel wider or taller than its manifest row and, where the first column or row moved,
shifted by a pixel. Checked here at every camera elevation of ``sweep=paper`` for the three paper
craters, with the frame sizes and crops of the real planner (``crater_synth.dataset.plan_render``)
and the real terrain's rim height: the worker renders a paraboloid bowl whose depth varies in both
image directions, and the sub-pixel offset of the content is fitted from the depth channel against
the analytic depth at every pixel centre (must be < 0.1 px).
"""

from __future__ import annotations

import numpy as np
import pytest

from blender_gen.border import border_fractions, pixels_from_border
from crater_core import exr

from helpers import render as cr

BOWL_RADIUS_M = 60_000.0  # curvature radius of the paraboloid z = (x^2 + y^2) / 2Rc
TERRAIN_HALF_M = 150_000.0


@pytest.fixture(scope="module")
def paper_plans(tmp_path_factory):
    """{crater: [plan of each paper camera elevation]} from the real planner and terrain."""
    from crater_core.sweep import grid_from_config
    from crater_synth.config import compose, craters, resolved
    from crater_synth.dataset import plan_render
    from crater_synth.terrain.patch import build_terrain

    data = tmp_path_factory.mktemp("data")
    cfg = compose(["sweep=paper", f"data_dir={data}"])
    grid = grid_from_config(resolved(cfg)["sweep"])
    roi = int(resolved(cfg)["render"]["roi_min_px"])
    out = {}
    for crater in craters(cfg):
        _, meta = build_terrain(crater, cfg)
        out[crater["name"]] = [
            plan_render(crater, meta, grid, grid.index_of((0, 0, k, 0)), roi) for k in range(len(grid.cam_elevation))
        ]
    return out


def test_border_fractions_select_exactly_the_crop(paper_plans):
    """Pure arithmetic: Blender's truncation of the fractions gives back the crop's pixel edges."""
    for plans in paper_plans.values():
        for plan in plans:
            w = plan["frame_width"]
            u0, v0, u1, v1 = plan["crop"]
            fr = border_fractions(plan["crop"], w)
            assert [pixels_from_border(f, w) for f in fr] == [u0, u1, w - v1, w - v0], (w, plan["crop"])
    # the case of the issue: 113 / 437 truncates to 112, the pixel-centre fraction to 113
    assert pixels_from_border(113 / 437, 437) == 112
    assert pixels_from_border(border_fractions([113, 0, 437, 437], 437)[0], 437) == 113
    assert border_fractions([0, 0, 437, 437], 437) == (0.5 / 437, 1.0, 0.5 / 437, 1.0)


def _bowl_depth(item: dict) -> np.ndarray:
    """Analytic depth (along the view axis) of the paraboloid at every crop pixel centre."""
    pose, d = cr.centre_rays(item)
    o = pose.position
    a = (d[..., 0] ** 2 + d[..., 1] ** 2) / (2 * BOWL_RADIUS_M)
    b = (o[0] * d[..., 0] + o[1] * d[..., 1]) / BOWL_RADIUS_M - d[..., 2]
    c = (o[0] ** 2 + o[1] ** 2) / (2 * BOWL_RADIUS_M) - o[2]
    t = -2 * c / (b + np.sqrt(b * b - 4 * a * c))  # c < 0 (camera above the bowl): the positive root
    return t * (d @ pose.forward)


@pytest.mark.integration
def test_exr_size_and_content_position_at_every_paper_camera_elevation(paper_plans, tmp_path):
    near = cr.grid(TERRAIN_HALF_M, 641, lambda x, y: (x * x + y * y) / (2 * BOWL_RADIUS_M))
    npz = cr.write_npz(tmp_path / "bowl.npz", near)
    items = []
    for name, plans in paper_plans.items():
        for plan in plans:
            p = plan["params"]
            items.append(
                cr.item(
                    len(items),
                    30.0,
                    0.0,
                    p.cam_elevation,
                    37.0 + 11 * len(items),
                    plan["range_m"],
                    plan["frame_width"],
                    list(plan["crop"]),
                    name=name,
                )
            )
    job = cr.job(npz, items, tmp_path / "out", mode="direct", diameter_km=20.0, samples=1)
    results, proc = cr.run_worker(job, tmp_path, "border")
    assert proc.returncode == 0, proc.stderr[-3000:]
    bad = []
    for it in items:
        u0, v0, u1, v1 = it["crop"]
        depth = exr.read_exr(str(tmp_path / "out" / it["rel_path"]))[0]["depth"]
        tag = f"{it['rel_path']}: cam {it['cam_elevation']} frame {it['frame_width']} crop {it['crop']}"
        if depth.shape != (v1 - v0, u1 - u0):
            bad.append(f"{tag}: EXR {depth.shape[1]}x{depth.shape[0]} != crop {u1 - u0}x{v1 - v0}")
            continue
        expected = _bowl_depth(it)
        gv, gu = np.gradient(expected)
        resid = (depth - expected)[2:-2, 2:-2].ravel()
        a = np.stack([gu[2:-2, 2:-2].ravel(), gv[2:-2, 2:-2].ravel()], axis=1)
        (du, dv), *_ = np.linalg.lstsq(a, resid, rcond=None)
        if max(abs(du), abs(dv)) >= 0.1:
            bad.append(f"{tag}: content offset ({du:+.3f}, {dv:+.3f}) px")
    assert not bad, "\n".join(bad)
