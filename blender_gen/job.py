"""Worker job file and terrain npz: loading and validation (clear one-line errors)."""

from __future__ import annotations

import json
import os
import zipfile

import numpy as np


class JobError(Exception):
    """Bad job file or terrain input; the worker prints ``ERROR <message>`` and exits non-zero."""


RENDER_KEYS = (
    "index",
    "sun_elevation",
    "sun_azimuth",
    "cam_elevation",
    "cam_azimuth",
    "range_m",
    "fov_deg",
    "frame_width",
    "crop",
    "rel_path",
)


def load_job(path: str) -> dict:
    try:
        with open(path, encoding="utf-8") as fh:
            job = json.load(fh)
    except FileNotFoundError:
        raise JobError(f"job file {path} does not exist") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise JobError(f"job file {path} is unreadable: {exc}") from None
    for key in ("terrain_npz", "crater", "hapke", "out_dir", "renders"):
        if key not in job:
            raise JobError(f"job file {path}: missing key {key!r}")
    if "diameter_km" not in job["crater"]:
        raise JobError(f"job file {path}: crater has no diameter_km")
    for i, r in enumerate(job["renders"]):
        missing = [k for k in RENDER_KEYS if k not in r]
        if missing:
            raise JobError(f"job file {path}: renders[{i}] lacks {missing}")
        try:
            u0, v0, u1, v1 = (int(c) for c in r["crop"])
            width = int(r["frame_width"])
        except (TypeError, ValueError):
            raise JobError(
                f"job file {path}: renders[{i}] needs crop [u0, v0, u1, v1] and frame_width "
                f"as integers, got {r['crop']!r}, {r['frame_width']!r}"
            ) from None
        if not (0 <= u0 < u1 <= width and 0 <= v0 < v1 <= width):
            raise JobError(
                f"job file {path}: renders[{i}] (index {r['index']}): crop {r['crop']} is not a "
                f"non-empty box inside the {width}-px frame"
            )
        if r.get("camera") is not None:
            _check_camera(r["camera"], f"job file {path}: renders[{i}] (index {r['index']})")
    job.setdefault("terrain_meta", {})
    job.setdefault("render", {})
    return job


def _check_camera(cam, where: str) -> None:
    """An explicit camera pose: ``position`` (3 finite m) and ``rotation`` (3 x 3, orthonormal columns)."""
    try:
        pos = np.asarray(cam["position"], dtype=np.float64)
        rot = np.asarray(cam["rotation"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise JobError(f"{where}: camera needs position [x, y, z] and rotation [[...] x 3]") from None
    if pos.shape != (3,) or rot.shape != (3, 3) or not (np.all(np.isfinite(pos)) and np.all(np.isfinite(rot))):
        raise JobError(f"{where}: camera position must be 3 finite numbers and rotation a finite 3 x 3 matrix")
    if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-6):
        raise JobError(f"{where}: camera rotation is not orthonormal")


def _grid(arr, name: str, path: str) -> np.ndarray:
    a = np.asarray(arr)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 2 or a.shape[1] < 2:
        raise JobError(f"terrain {path}: {name} has shape {a.shape}, expected (rows>=2, cols>=2, 3)")
    if not np.issubdtype(a.dtype, np.floating):
        raise JobError(f"terrain {path}: {name} has dtype {a.dtype}, expected float")
    if not np.isfinite(a).all():
        raise JobError(f"terrain {path}: {name} has non-finite values")
    return a.astype(np.float32, copy=False)


def load_terrain(path: str) -> dict:
    """{near_xyz, far_xyz (or None), far_keep_quads (or None)} from the terrain npz."""
    if not os.path.isfile(path):
        raise JobError(f"terrain npz {path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as z:
            names = set(z.files)
            if "near_xyz" not in names:
                raise JobError(f"terrain npz {path} has no near_xyz array (has {sorted(names)})")
            data = {k: z[k] for k in ("near_xyz", "far_xyz", "far_keep_quads") if k in names}
    except JobError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise JobError(f"terrain npz {path} is unreadable or corrupt: {type(exc).__name__}: {exc}") from None
    out = {"near_xyz": _grid(data["near_xyz"], "near_xyz", path), "far_xyz": None, "far_keep_quads": None}
    far = data.get("far_xyz")
    if far is not None and far.size:
        far = _grid(far, "far_xyz", path)
        keep = data.get("far_keep_quads")
        if keep is not None and keep.size:
            keep = np.asarray(keep).astype(bool)
            if keep.shape != (far.shape[0] - 1, far.shape[1] - 1):
                raise JobError(
                    f"terrain {path}: far_keep_quads has shape {keep.shape}, expected "
                    f"{(far.shape[0] - 1, far.shape[1] - 1)}"
                )
        else:
            keep = None
        out["far_xyz"], out["far_keep_quads"] = far, keep
    return out
