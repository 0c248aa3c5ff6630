"""Helpers for the renderer tests (tests/test_render_*.py): synthetic terrain npz files, worker jobs,
running ``python -m blender_gen.worker`` in a subprocess, and the flat-plane oracle.

The test modules import it as ``from helpers import render as cr``.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from crater_core import geometry, hapke

REPO = Path(__file__).resolve().parents[2]
# Fast-vs-direct I/F tolerances, per render (docs/renderer.md, "Accuracy of fast vs direct"); the two
# Blender backends are held to the same ones (tests/test_blender_binary.py).
FAST_MEAN_TOL = 0.015  # |mean(fast) / mean(direct) - 1|
FAST_MAD_TOL = 0.03  # mean |fast - direct| / median(direct I/F of lit pixels)
FAST_OUTLIER_TOL = 0.05  # fraction of pixels with |fast - direct| > 10 % of that median (shadow edges)
LIT_MAD_TOL = 0.02  # mean |lit_fast - lit_direct|
R_MOON = geometry.MOON_RADIUS_M
HAPKE = {"w": 0.32, "xi": -0.25, "b0": 1.0, "h": 0.06, "theta_bar_deg": 23.657}


def grid(half_m: float, n: int, zfun=None, curvature: bool = False) -> np.ndarray:
    """(n, n, 3) ENU grid over [-half, half]^2, rows north -> south, z = zfun(x, y) (+ curvature)."""
    xs = np.linspace(-half_m, half_m, n)
    x, y = np.meshgrid(xs, xs[::-1])
    z = np.zeros_like(x) if zfun is None else zfun(x, y)
    if curvature:
        z = z - geometry.curvature_drop_m(np.hypot(x, y))
    return np.stack([x, y, z], axis=-1).astype(np.float32)


def write_npz(path: Path, near: np.ndarray, far: np.ndarray | None = None, keep: np.ndarray | None = None) -> str:
    arrays = {"near_xyz": near}
    if far is not None:
        arrays["far_xyz"] = far
        arrays["far_keep_quads"] = keep if keep is not None else np.ones((far.shape[0] - 1, far.shape[1] - 1), bool)
    np.savez(path, **arrays)
    return str(path)


def keep_outside(far: np.ndarray, half_m: float) -> np.ndarray:
    """far_keep_quads dropping far quads whose centre lies inside the near square."""
    cx = 0.25 * (far[:-1, :-1, 0] + far[1:, 1:, 0] + far[:-1, 1:, 0] + far[1:, :-1, 0])
    cy = 0.25 * (far[:-1, :-1, 1] + far[1:, 1:, 1] + far[:-1, 1:, 1] + far[1:, :-1, 1])
    return ~((np.abs(cx) < half_m) & (np.abs(cy) < half_m))


def central_crop(frame_width: int, size: int, du: int = 0, dv: int = 0) -> list[int]:
    u0 = (frame_width - size) // 2 + du
    v0 = (frame_width - size) // 2 + dv
    return [u0, v0, u0 + size, v0 + size]


def item(
    index: int,
    sun_el: float,
    sun_az: float,
    cam_el: float,
    cam_az: float,
    range_m: float,
    frame_width: int = 200,
    crop: list[int] | None = None,
    name: str = "t",
) -> dict:
    return {
        "index": index,
        "indices": [0, 0, 0, 0],
        "sun_elevation": float(sun_el),
        "sun_azimuth": float(sun_az),
        "cam_elevation": float(cam_el),
        "cam_azimuth": float(cam_az),
        "range_m": float(range_m),
        "fov_deg": 90.0,
        "frame_width": frame_width,
        "crop": crop or central_crop(frame_width, 80),
        "rel_path": f"{name}/{index:06d}.exr",
        "header": {"crater": name, "terrain_id": f"{name}-test", "seed": 7, "crop": json.dumps(crop)},
    }


def job(npz: str, items: list[dict], out_dir: Path, mode: str = "direct", diameter_km: float = 10.0, **render) -> dict:
    r = {
        "mode": mode,
        "samples": 16,
        "max_bounces": 0,
        "denoise": False,
        "threads": 1,
        "shadow_map_px": 512,
        "shadow_map_extent_factor": 2.1,
    }
    r.update(render)
    return {
        "terrain_npz": npz,
        "terrain_meta": {"terrain_id": "test", "rim_z_m": 0.0},
        "crater": {"name": "test", "lat": -89.9, "lon": 0.0, "diameter_km": diameter_km},
        "hapke": dict(HAPKE),
        "render": r,
        "out_dir": str(out_dir),
        "renders": items,
    }


def run_worker(
    job_dict: dict, tmp_path: Path, name: str = "job", argv: list[str] | None = None, timeout: float = 600.0
):
    """Run the worker on ``job_dict``; returns (results {index: dict}, completed process)."""
    job_file = tmp_path / f"{name}.json"
    job_file.write_text(json.dumps(job_dict))
    cmd = argv or [sys.executable, "-m", "blender_gen.worker"]
    proc = subprocess.run(
        cmd + [str(job_file)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=os.environ | {"PYTHONUNBUFFERED": "1"},
    )
    results = {}
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            r = json.loads(line[len("RESULT ") :])
            results[r["index"]] = r
    return results, proc


def flat_expected_if(it: dict, params: dict = HAPKE, z0: float = 0.0) -> np.ndarray:
    """Per-pixel I/F of the plane z = z0 seen through each crop pixel's centre ray (numpy oracle)."""
    pose, d = centre_rays(it)
    t = (z0 - pose.position[2]) / d[..., 2]
    p = pose.position + t[..., None] * d
    view = pose.position - p
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    to_sun = geometry.direction_from_elevation_azimuth(it["sun_elevation"], it["sun_azimuth"])
    normals = np.broadcast_to(np.array([0.0, 0.0, 1.0]), view.shape)
    return hapke.shade_np(normals, to_sun, view, hapke.HapkeParams.from_mapping(params))


def crater_z(diameter_m: float):
    """Bowl crater (depth 0.2 D, raised rim 0.04 D) with gentle undulations: a stand-in for a DEM."""
    from crater_synth.bench.renderer import bowl_crater_z

    return bowl_crater_z(diameter_m)


def crater_items(
    diameter_m: float, suns, cams, roi_min_px: int = 100, sigma_max: float = 1.4, name: str = "crater"
) -> list[dict]:
    """Render items laid out like the host's plan (ROI-sized crop around the projected rim)."""
    out = []
    rim = np.array([0.0, 0.0, 0.04 * diameter_m])
    for sun_el, sun_az in suns:
        for cam_el, cam_az in cams:
            pose = geometry.look_at_camera(cam_el, cam_az, 1.5 * diameter_m, 90.0)
            width = geometry.frame_width_for_roi(pose, rim, diameter_m / 2, roi_min_px, 1.0)
            ell = geometry.project_horizontal_circle(rim, diameter_m / 2, pose, width)
            (cu, cv), _ = geometry.project_points(rim, pose, width)
            b = geometry.roi_box((cu, cv), 2 * ell.a, sigma_max)
            crop = [int(math.floor(b[0])), int(math.floor(b[1])), int(math.ceil(b[2])), int(math.ceil(b[3]))]
            out.append(item(len(out), sun_el, sun_az, cam_el, cam_az, 1.5 * diameter_m, width, crop, name))
    return out


def centre_rays(it: dict):
    """The look-at camera of a sweep item and the direction (world, unnormalised, view axis -1) of the
    ray through the centre of each pixel of its crop: (pose, (rows, cols, 3))."""
    pose = geometry.look_at_camera(it["cam_elevation"], it["cam_azimuth"], it["range_m"], it["fov_deg"])
    w = it["frame_width"]
    f = pose.focal_px(w)
    u0, v0, u1, v1 = it["crop"]
    uu, vv = np.meshgrid(np.arange(u0, u1) + 0.5, np.arange(v0, v1) + 0.5)
    return pose, np.stack([(uu - w / 2) / f, -(vv - w / 2) / f, -np.ones_like(uu)], -1) @ pose.rotation.T
