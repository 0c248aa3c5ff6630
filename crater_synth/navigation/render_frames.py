"""Navigation frames: whole camera frames along a trajectory, rendered by the dataset's renderer, with
their truth labels (``crater-synth nav-frames trajectory=NAME``; docs/navigation.md, "Rendered frames").

Per frame (poses: :mod:`crater_core.trajectory`):

1. **Terrain**: the dataset's patch builder (:func:`crater_synth.terrain.patch.build_terrain`) around the
   frame's target (the boresight's ground point), its near field sized to the frame's footprint
   (:data:`PATCH_MARGIN` x the half-width of the square holding the four corner rays' ground
   points) rather than to a crater's diameter; the far field reaches at least two far cells beyond.
   Each frame has its own patch (cached by its content key like every patch).
2. **Render**: one worker item with an explicit camera (position and rotation in the patch's ENU
   frame), no crop, the Sun's (elevation, azimuth) in the same frame; direct or fast mode as
   ``render.mode`` says. In fast mode the job's "crater" diameter sets the horizon map to cover the
   near field (:data:`FAST_MAP_MARGIN`).
3. **Labels**: every landmark of the map whose 3-D rim-centre point projects inside the frame, with
   its projected rim ellipse (the rim circle in the landmark's own local horizontal plane: the Moon's
   curvature tilts it against the frame's) and its lit-rim fraction (mean of the ``lit`` channel at
   90 points of the ellipse inside the frame).

Output: ``<out>/frame_NNNN.exr`` (the dataset's channels: IF, depth, N.*, lit) and
``<out>/manifest.jsonl`` (JSON Lines, one row per frame, ``schema_version``, no timestamps, written
atomically once every frame is rendered).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from types import SimpleNamespace

import click
import numpy as np

from crater_core import geometry, schema
from crater_core.settings import CraterSettings, replace
from crater_core.trajectory import FramePose, TrajectoryError, footprint_half_width_m, frame_poses
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.errors import ConfigError, UserError

PATCH_MARGIN = 1.1  # near-field half-width / footprint half-width: terrain relief and rounding stay inside
FAST_MAP_MARGIN = 1.02  # fast path: horizon map half-width / near-field half-width
RIM_POINTS = 90  # points on a projected rim where the lit channel is sampled
MIN_RIM_INSIDE = 0.5  # lit-rim fraction only when at least this share of the rim lies in the frame
FRAME_LABEL_VERSION = 1


def frame_rel_path(index: int) -> str:
    return f"frame_{index:04d}.exr"


def patch_entry(traj_name: str, pose: FramePose, near_radius_factor: float) -> dict:
    """The patch builder's crater entry for a frame: centred on the target, its diameter chosen so that
    the near field (``near_radius_factor`` x D) holds the footprint with :data:`PATCH_MARGIN`."""
    hw = footprint_half_width_m(pose) * PATCH_MARGIN
    return {
        "name": f"nav-{traj_name}-{pose.index:04d}",
        "lat": pose.target_lat,
        "lon": pose.target_lon,
        "diameter_km": hw / near_radius_factor / 1000.0,
        "source": "navigation frame footprint",
    }


def frame_settings(settings, half_width_m: float):
    """``settings`` with a far field reaching at least two far cells beyond the frame's near field."""
    t = settings.terrain
    if t.far_radius_km <= 0.0:
        return settings
    need = half_width_m / 1000.0 + 2.0 * t.far_spacing_km
    return (
        replace(settings, **{"terrain.far_radius_km": max(t.far_radius_km, need)})
        if need > t.far_radius_km
        else settings
    )


def worker_item(pose: FramePose, lat0: float, lon0: float, seed: int, header: dict) -> dict:
    """One worker ``renders`` entry with an explicit camera (docs/renderer.md, "Worker contract")."""
    cam = pose.pose_enu(lat0, lon0)
    sun_el, sun_az = pose.sun_enu(lat0, lon0)
    rng = float(np.linalg.norm(cam.position))
    w = int(pose.width_px)
    return {
        "index": pose.index,
        "indices": [pose.index],
        "sun_elevation": sun_el,
        "sun_azimuth": sun_az,
        # informative only (the explicit camera wins): the camera seen from the patch origin
        "cam_elevation": math.degrees(math.asin(max(-1.0, min(1.0, cam.position[2] / rng)))),
        "cam_azimuth": math.degrees(math.atan2(cam.position[0], cam.position[1])) % 360.0,
        "range_m": rng,
        "fov_deg": pose.fov_deg,
        "frame_width": w,
        "crop": [0, 0, w, w],
        "camera": {
            "position": [float(v) for v in cam.position],
            "rotation": [[float(v) for v in r] for r in cam.rotation],
        },
        "rel_path": frame_rel_path(pose.index),
        "seed": seed,
        "header": header,
    }


def lit_rim_fraction(lit: np.ndarray, ellipse: geometry.Ellipse) -> float | None:
    """Mean of the ``lit`` channel (illuminated fraction of the solar disc) at :data:`RIM_POINTS` points
    of the projected rim inside the frame; None when less than :data:`MIN_RIM_INSIDE` of it is inside."""
    h, w = lit.shape
    pts = ellipse.points(RIM_POINTS)
    inside = (pts[:, 0] >= 0) & (pts[:, 0] < w) & (pts[:, 1] >= 0) & (pts[:, 1] < h)
    if inside.mean() < MIN_RIM_INSIDE:
        return None
    u = np.floor(pts[inside, 0]).astype(int)
    v = np.floor(pts[inside, 1]).astype(int)
    return float(np.mean(lit[v, u]))


def landmarks_in_view(
    pose: FramePose, landmarks, lat0: float, lon0: float, lit: np.ndarray | None = None
) -> list[dict]:
    """Labels of every landmark whose rim-centre point projects inside the frame (in front of the camera)."""
    if not landmarks:
        return []
    cam = pose.pose_enu(lat0, lon0)
    w = int(pose.width_px)
    pts_mc = np.array([lm.position_mc() for lm in landmarks])
    pts = geometry.mc_to_enu(pts_mc, lat0, lon0)
    uv, depth = geometry.project_points(pts, cam, w)
    inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < w)
    basis = geometry.enu_basis(lat0, lon0)
    out = []
    for k in np.nonzero(inside)[0]:
        lm = landmarks[k]
        normal = basis @ (pts_mc[k] / np.linalg.norm(pts_mc[k]))  # the landmark's local up, in the frame's ENU
        ell = geometry.project_circle(pts[k], normal, lm.diameter_km * 500.0, cam, w)
        row = {
            "id": lm.id,
            "name": lm.name,
            "diameter_km": lm.diameter_km,
            "lat": lm.lat,
            "lon": lm.lon,
            "centre_px": [round(float(uv[k, 0]), 3), round(float(uv[k, 1]), 3)],
            "depth_m": round(float(depth[k]), 1),
            "ellipse": {key: round(float(v), 4) for key, v in ell.as_dict().items()},
            "rim_inside": bool(
                ell.cu - ell.a >= 0 and ell.cv - ell.a >= 0 and ell.cu + ell.a <= w and ell.cv + ell.a <= w
            ),
        }
        if lit is not None:
            frac = lit_rim_fraction(lit, ell)
            row["lit_rim_fraction"] = None if frac is None else round(frac, 4)
        out.append(row)
    return out


def _pole(lat: float) -> str:
    return "south" if lat < 0 else "north"


def render_frames(settings, out_dir: Path, only: list[int] | None = None, progress: bool = False) -> dict:
    """Render the trajectory's frames (all, or the indices ``only``) into ``out_dir`` with labels;
    returns a summary. Raises :class:`UserError` on bad input before anything is rendered."""
    from crater_core.files import ensure_writable_dir
    from crater_synth.dataset.dispatch import run_workers
    from crater_synth.dataset.plan import CraterJob, code_version, hapke_dict, render_seed
    from crater_synth.navigation.landmarks import load_default_map
    from crater_synth.terrain.patch import build_terrain

    traj = settings.trajectory
    if traj is None:
        raise ConfigError("no trajectory selected: add trajectory=NAME (configs/trajectory/)")
    try:
        poses = frame_poses(traj)
    except TrajectoryError as exc:
        raise ConfigError(f"trajectory={traj.name}: {exc}") from None
    if only:
        bad = [i for i in only if not 0 <= i < len(poses)]
        if bad:
            raise UserError(f"--frames {bad}: trajectory {traj.name} has frames 0..{len(poses) - 1}")
        poses = [poses[i] for i in sorted(set(only))]
    out_dir = Path(out_dir)
    ensure_writable_dir(settings.data_dir, "data_dir")
    render = settings.render
    maps: dict[str, list] = {}
    t0 = time.perf_counter()
    jobs, frames = [], {}
    for pose in poses:
        entry = patch_entry(traj.name, pose, settings.terrain.near_radius_factor)
        hw = entry["diameter_km"] * 1000.0 * settings.terrain.near_radius_factor
        try:
            npz, meta = build_terrain(entry, frame_settings(settings, hw))
        except UserError as exc:
            raise UserError(
                f"trajectory={traj.name} frame {pose.index} (target lat {pose.target_lat:.2f}, "
                f"lon {pose.target_lon:.2f}): {exc}"
            ) from None
        if progress:
            click.echo(
                f"frame {pose.index}: patch +-{hw / 1e3:.1f} km ({'cached' if meta.get('cached') else 'built'})",
                err=True,
            )
        seed = render_seed(settings.seed, ("navframe", traj.name, pose.index))
        header = {
            "trajectory": traj.name,
            "frame": pose.index,
            "terrain_id": meta["terrain_id"],
            "code_version": code_version(),
            "renderer": render.mode,
            "samples": int(render.samples),
            "pose_mc": json.dumps(pose.as_dict(), sort_keys=True),
            "hapke": json.dumps(hapke_dict(settings.hapke), sort_keys=True),
            "seed": seed,
        }
        item = worker_item(pose, pose.target_lat, pose.target_lon, seed, header)
        # The job's crater diameter sets only the fast path's horizon-map extent (blender_gen/fast.py).
        map_d_km = hw * FAST_MAP_MARGIN / render.shadow_map_extent_factor / 1000.0
        crater = CraterSettings(name=entry["name"], lat=entry["lat"], lon=entry["lon"], diameter_km=map_d_km)
        plan = {"params": SimpleNamespace(index=pose.index, indices=(0, 0, 0, pose.index)), "item": item}
        jobs.append(CraterJob(crater=crater, npz=npz, meta=meta, plans=[plan]))
        frames[pose.index] = {"pose": pose, "meta": meta, "item": item, "half_width_m": hw}
    t_patch = time.perf_counter() - t0
    ensure_writable_dir(out_dir, "--out")  # only once every frame has its terrain: no empty output on bad input
    results: dict[int, dict] = {}

    def on_result(_job, plan, result):
        results[int(result["index"])] = result
        if progress:
            click.echo(f"frame {result['index']}: rendered in {result['seconds']:.2f} s ({result['mode']})", err=True)

    t1 = time.perf_counter()
    run_workers(jobs, render, settings.hapke, out_dir, on_result)
    t_render = time.perf_counter() - t1
    from crater_core import exr

    rows = []
    for idx, fr in sorted(frames.items()):
        res = results.get(idx)
        if res is None:
            raise UserError(f"frame {idx} of trajectory {traj.name} was not rendered (see {out_dir}/.jobs/*.log)")
        pose = fr["pose"]
        pole = _pole(pose.target_lat)
        if pole not in maps:
            maps[pole] = load_default_map(pole)[0]
        lit = exr.read_channel(out_dir / res["rel_path"], "lit")
        cam = pose.pose_enu(pose.target_lat, pose.target_lon)
        sun_el, sun_az = pose.sun_enu(pose.target_lat, pose.target_lon)
        rows.append(
            {
                "schema_version": schema.SCHEMA_VERSION,
                "label_version": FRAME_LABEL_VERSION,
                "trajectory": traj.name,
                "index": idx,
                "rel_path": res["rel_path"],
                "sha256": res["sha256"],
                "mode": res["mode"],
                "render_seconds": res["seconds"],
                "terrain_id": fr["meta"]["terrain_id"],
                "frame_origin": {
                    "lat": pose.target_lat,
                    "lon": pose.target_lon,
                    "frame": "ENU on the 1737.4 km sphere",
                },
                "pose": pose.as_dict(),
                "camera_enu": {"position_m": [float(v) for v in cam.position], "rotation": cam.rotation.tolist()},
                "sun_enu": {"elevation_deg": sun_el, "azimuth_deg": sun_az},
                "ground_sample_m": pose.ground_sample_m(),
                "footprint_half_width_m": footprint_half_width_m(pose),
                "lit_fraction": res["lit_fraction"],
                "mean_if": res["mean_if"],
                "landmarks": landmarks_in_view(pose, maps[pole], pose.target_lat, pose.target_lon, lit),
            }
        )
    text = "".join(schema.dumps_row(r) + "\n" for r in rows)
    schema.atomic_write_text(out_dir / schema.MANIFEST_NAME, text)
    return {
        "trajectory": traj.name,
        "frames": len(rows),
        "out_dir": str(out_dir),
        "mode": render.mode,
        "modes_used": sorted({r["mode"] for r in rows}),
        "width_px": int(traj.width_px),
        "patch_seconds": round(t_patch, 2),
        "render_seconds": round(t_render, 2),
        "worker_render_seconds": round(sum(r["render_seconds"] for r in rows), 2),
        "landmarks_in_view": [len(r["landmarks"]) for r in rows],
    }


@click.command("nav-frames")
@OVERRIDES
@click.option(
    "--out", type=click.Path(path_type=Path), default=None, help="Output directory [data_dir/navframes/NAME]."
)
@click.option("--frames", "only", default="", help="Comma-separated frame indices to render (default: all).")
@user_errors
def nav_frames_command(overrides, out, only):
    """Render a trajectory's navigation frames (EXR + labelled manifest).

    Example: `crater-synth nav-frames trajectory=descent_ridge render.mode=direct`
    """
    from crater_synth.config import load_settings

    settings = load_settings(overrides)
    if settings.trajectory is None:
        raise ConfigError("no trajectory selected: add trajectory=NAME (configs/trajectory/)")
    try:
        idx = [int(s) for s in only.split(",") if s.strip()] if only else None
    except ValueError:
        raise UserError(f"--frames {only!r}: must be comma-separated integers") from None
    out = out or Path(str(settings.data_dir)) / "navframes" / settings.trajectory.name
    summary = render_frames(settings, out, idx, progress=True)
    click.echo(json.dumps(summary))
