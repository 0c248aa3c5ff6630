"""Planning: the geometry of every render, computed analytically on the host before any rendering.

For each render of the sweep: camera pose, frame size, projected rim ellipse, sigma boxes and the crop
actually rendered (full-frame pixels -> crop pixels), its seed, and the fingerprint of everything that
changes its pixels or labels (:mod:`crater_synth.dataset.identity`), so a resumed run knows which
files are still valid.
"""

from __future__ import annotations

import json
import math
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from crater_core import geometry, schema
from crater_core.hapke import HapkeParams
from crater_core.settings import CraterSettings, RenderSettings
from crater_core.sweep import SweepGrid
from crater_synth import __version__
from crater_synth.errors import UserError


def code_version() -> str:
    return f"crater-synth {__version__}"


def hapke_dict(hapke: HapkeParams) -> dict:
    """The five Hapke parameters as the plain dict the worker job and the EXR header carry."""
    return {"w": hapke.w, "xi": hapke.xi, "b0": hapke.b0, "h": hapke.h, "theta_bar_deg": hapke.theta_bar_deg}


def render_seed(base_seed: int, key: tuple) -> int:
    return zlib.crc32(f"{base_seed}:{key}".encode()) & 0x7FFFFFFF


def _crater(crater: CraterSettings | Mapping) -> CraterSettings:
    return crater if isinstance(crater, CraterSettings) else CraterSettings.from_config(crater, "crater")


def plan_render(
    crater: CraterSettings | Mapping, meta: dict, grid: SweepGrid, index: int, roi_min_px: int, crop_to_roi: bool = True
) -> dict:
    """Camera, frame size, rim ellipse, sigma boxes and crop of one render (full-frame -> crop px).

    With ``crop_to_roi`` (the default) only the largest sigma box is rendered; otherwise the whole
    90 deg frame (the naive baseline of ``crater-synth bench``)."""
    crater = _crater(crater)
    p = grid.params(index, crater.lat)
    diameter_m = crater.diameter_km * 1000.0
    range_m = grid.range_factor * diameter_m
    pose = geometry.look_at_camera(p.cam_elevation, p.cam_azimuth, range_m, grid.fov_deg)
    rim_center = np.array([0.0, 0.0, float(meta.get("rim_z_m", 0.0))])
    width = geometry.frame_width_for_roi(pose, rim_center, diameter_m / 2.0, roi_min_px, min(grid.sigmas))
    ellipse = geometry.project_horizontal_circle(rim_center, diameter_m / 2.0, pose, width)
    (cu, cv), _ = geometry.project_points(rim_center, pose, width)
    boxes = {f"{s:.1f}": geometry.roi_box((cu, cv), 2.0 * ellipse.a, s) for s in grid.sigmas}
    big = boxes[f"{max(grid.sigmas):.1f}"]
    crop = [int(math.floor(big[0])), int(math.floor(big[1])), int(math.ceil(big[2])), int(math.ceil(big[3]))]
    if crop[0] < 0 or crop[1] < 0 or crop[2] > width or crop[3] > width:
        raise UserError(
            f"ROI box of sigma={max(grid.sigmas)} leaves the {grid.fov_deg} deg frame for "
            f"{crater.name} at camera elevation {p.cam_elevation}: lower sigma or raise range_factor"
        )
    if not crop_to_roi:
        crop = [0, 0, width, width]
    u0, v0 = crop[0], crop[1]
    return {
        "params": p,
        "rel_path": schema.render_rel_path(crater.name, p.sun_elevation, p.sun_azimuth, p.cam_elevation, p.cam_azimuth),
        "range_m": range_m,
        "frame_width": width,
        "crop": crop,
        "center_px": [float(cu - u0), float(cv - v0)],
        "rim_ellipse": ellipse.as_dict() | {"cu": ellipse.cu - u0, "cv": ellipse.cv - v0},
        "sigma_boxes": {k: [b[0] - u0, b[1] - v0, b[2] - u0, b[3] - v0] for k, b in boxes.items()},
    }


@dataclass
class CraterJob:
    """Everything needed to render (part of) one crater's sweep: its terrain patch and the plans of the
    renders still to do (each with its ``seed``, ``digest`` and worker ``item``)."""

    crater: CraterSettings
    npz: Path
    meta: dict
    plans: list[dict] = field(default_factory=list)
    # render settings of this job only, over the run's (navigation frames: a shared patch's larger horizon map)
    render_overrides: dict = field(default_factory=dict)


def camera_major(plan: dict) -> tuple[int, int, int, int]:
    """Sort key of a plan: camera pose first, then the sun (the sweep index is sun-major)."""
    i = plan["params"].indices
    return i[2], i[3], i[0], i[1]


def worker_item(
    crater: CraterSettings, meta: dict, plan: dict, render: RenderSettings, hapke: HapkeParams, fov_deg: float
) -> dict:
    """One entry of a worker job's ``renders`` list (docs/renderer.md, "Worker contract")."""
    p = plan["params"]
    rel = plan["rel_path"]
    header = {
        "crater": crater.name,
        "terrain_id": meta["terrain_id"],
        "code_version": code_version(),
        "renderer": render.mode,
        "samples": int(render.samples),
        "range_m": plan["range_m"],
        "fov_deg": float(fov_deg),
        "frame_width": plan["frame_width"],
        "crop": json.dumps(plan["crop"]),
        "sigma_boxes": json.dumps(plan["sigma_boxes"]),
        "rim_ellipse": json.dumps(plan["rim_ellipse"]),
        "hapke": json.dumps(hapke_dict(hapke), sort_keys=True),
        "seed": plan["seed"],
        # The manifest row this render is made for (less the worker's stats and the file's sha256),
        # sealed with the pixels by the worker: crater_synth.dataset.recover rebuilds the row from it.
        "manifest_row": schema.dumps_row(plan["row"]),
    }
    return {
        "index": p.index,
        "indices": list(p.indices),
        "sun_elevation": p.sun_elevation,
        "sun_azimuth": p.sun_azimuth,
        "cam_elevation": p.cam_elevation,
        "cam_azimuth": p.cam_azimuth,
        "range_m": plan["range_m"],
        "fov_deg": float(fov_deg),
        "frame_width": plan["frame_width"],
        "crop": plan["crop"],
        "rel_path": rel,
        "seed": plan["seed"],
        "header": header,
    }


def camera_worker_item(
    *,
    index: int,
    camera,
    sun: tuple,
    view: tuple,
    range_m: float,
    fov_deg: float,
    width_px: int,
    rel_path: str,
    seed: int,
    header: dict,
) -> dict:
    """A worker ``renders`` entry with an explicit camera (nav-frames, detection frames; docs/renderer.md,
    "Worker contract"): the whole square frame, ``camera`` (position, rotation) in the patch's ENU frame,
    ``sun`` (elevation, azimuth) deg. ``view`` (elevation, azimuth) deg is informative only: the explicit
    camera wins."""
    return {
        "index": index,
        "indices": [index],
        "sun_elevation": sun[0],
        "sun_azimuth": sun[1],
        "cam_elevation": view[0],
        "cam_azimuth": view[1],
        "range_m": range_m,
        "fov_deg": fov_deg,
        "frame_width": width_px,
        "crop": [0, 0, width_px, width_px],
        "camera": {
            "position": [float(v) for v in camera.position],
            "rotation": [[float(v) for v in r] for r in camera.rotation],
        },
        "rel_path": rel_path,
        "seed": seed,
        "header": header,
    }
