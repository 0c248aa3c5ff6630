"""Navigation frames: whole camera frames along a trajectory, rendered by the dataset's renderer, with
their truth labels (``crater-synth nav-frames trajectory=NAME``; docs/navigation/rendered.md).

Per frame (poses: :mod:`crater_core.trajectory`):

1. **Terrain**: the dataset's patch builder (:func:`crater_synth.terrain.patch.build_terrain`). A frame's
   own patch is centred on its target (the boresight's ground point), its near field sized to the
   frame's footprint (:data:`PATCH_MARGIN` x the half-width of the square holding the four corner rays'
   ground points) rather than to a crater's diameter. By default consecutive frames share one patch
   (:func:`group_frames`): it holds all their footprints at a vertex spacing no coarser than any of their
   own patches', with up to :data:`SHARE_MAX_VERTEX_FACTOR` x ``terrain.near_vertices`` per side. The far
   field reaches at least two far cells beyond the near field. Patches are cached by their content key
   like every patch.
2. **Render**: one worker item per frame with an explicit camera (position and rotation in the patch's
   ENU frame), no crop, the Sun's (elevation, azimuth) in the same frame (parallel rays: one Sun
   direction, one horizon map, for every frame of a patch); one worker job per patch, so a worker
   imports bpy, builds the scene and Cycles' BVH once for all its frames. Direct or fast mode as
   ``render.mode`` says. In fast mode the job's "crater" diameter sets the horizon map to cover the
   near field (:data:`FAST_MAP_MARGIN`), its texels scaled with the vertices.
3. **Labels** (:mod:`.labels`): every landmark of the map whose 3-D rim-centre point projects
   inside the frame, with its projected rim ellipse and its lit and occluded rim fractions.

Output: ``<out>/frame_NNNN.exr`` (the dataset's channels: IF, depth, N.*, lit) and
``<out>/manifest.jsonl`` (JSON Lines, one row per frame, ``schema_version``, no timestamps, written
atomically once every frame is rendered; rows of frames rendered by earlier runs are merged in). The
folder is the trajectory's alone (:mod:`.frame_folder`).

Length: one stage, a trajectory from its poses to labelled EXRs (patch grouping, the frames' render
defaults, worker items, the reuse of finished frames, the labels as frames arrive, the command); the
labels' geometry is in :mod:`.labels`, the workers' dispatch in the dataset's.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import click
import numpy as np
import yaml

from blender_gen.fast import ensure_horizons, horizon_cache_dir
from crater_core import exr, geometry, schema
from crater_core.files import ensure_writable_dir
from crater_core.progress import Progress
from crater_core.schema import content_key
from crater_core.settings import CraterSettings, replace
from crater_core.trajectory import FramePose, TrajectoryError, footprint_half_width_m, frame_corners_mc, frame_poses
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import load_settings
from crater_synth.dataset.dispatch import run_workers
from crater_synth.dataset.identity import render_identity
from crater_synth.dataset.plan import CraterJob, camera_worker_item, code_version, hapke_dict, render_seed
from crater_synth.dataset.recover import STATS_HEADER
from crater_synth.errors import ConfigError, UserError
from crater_synth.navigation.georef import pole_of
from crater_synth.navigation.map.landmarks import default_map_identity, load_default_map
from crater_synth.navigation.rendered.frame_folder import (
    adopt_unlisted,
    claim_frames_folder,
    manifest_rows,
    merged_rows,
)
from crater_synth.navigation.rendered.labels import FRAME_LABEL_VERSION, landmarks_in_view
from crater_synth.paths import CONFIG_DIR
from crater_synth.terrain.patch import build_terrain

PATCH_MARGIN = 1.1  # near-field half-width / footprint half-width: terrain relief and rounding stay inside
FAST_MAP_MARGIN = 1.02  # fast path: horizon map half-width / near-field half-width
# Frames sharing a patch: its near field at most this many times the configured vertices per side (4 x the
# vertices: one BVH and one horizon map for several frames instead of one per frame).
SHARE_MAX_VERTEX_FACTOR = 2.0
# A worker's start-up in frames' worth, for splitting shared patches between workers
# (crater_synth.dataset.dispatch.blocks_per_crater): python and bpy import ~0.6 s, the scene of a
# ~1000^2-vertex patch ~1.4 s, the first frame's Cycles sync and BVH ~1.5 s (the horizon map, ~2.7 s, is
# made once per patch), against ~0.33 s per further frame on one thread at 1 sample, ~0.85 s at 4
# (worker logs of `crater-synth nav-frames trajectory=polar_orbit_arc`, unloaded 2-core machine).
FRAME_STARTUP_RENDERS = 10
# Fast mode's G-buffer for navigation frames, unless the command sets render.samples or
# render.gbuffer_samples: one ray per pixel, which Cycles sends through the pixel's centre whatever the seed
# (a sharp, noise-free G-buffer). Against direct-mode references at 64 samples it is closer than 4 jittered
# samples and within the renderer's fast-vs-direct tolerances, at ~1.6 times the frame rate of 4 samples end
# to end (docs/navigation/rendered.md). Shadow edges are anti-aliased by the fast path's sub-pixel
# horizon either way; direct renders (render.mode=direct, fast-path fallbacks) keep render.samples.
FRAME_GBUFFER_SAMPLES = 1


def frame_overrides(overrides) -> list[str]:
    """The overrides a navigation-frame command composes: ``render.gbuffer_samples=1``
    (:data:`FRAME_GBUFFER_SAMPLES`) ahead of the user's own, unless those set ``render.samples`` or
    ``render.gbuffer_samples``, themselves or through the ``experiment=`` preset they name (then they alone
    decide, as in every documented frame command)."""
    overrides = list(overrides)
    keys = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    for o in overrides:
        key, _, name = o.lstrip("+").partition("=")
        if key == "experiment":
            keys |= experiment_render_keys(name)
    if keys & {"render.samples", "render.gbuffer_samples"}:
        return overrides
    return [f"render.gbuffer_samples={FRAME_GBUFFER_SAMPLES}"] + overrides


def experiment_render_keys(name: str) -> set[str]:
    """The ``render.<key>`` settings an experiment preset (``configs/experiment/<name>.yaml``) sets; none for
    an unknown name (the composition then refuses it in one line)."""
    path = CONFIG_DIR / "experiment" / f"{name}.yaml"
    data = yaml.safe_load(path.read_text(encoding="utf-8")) if path.is_file() else None
    render = (data or {}).get("render") or {}
    return {f"render.{k}" for k in render}


def frame_rel_path(index: int) -> str:
    return f"frame_{index:04d}.exr"


@dataclass(frozen=True)
class PatchGroup:
    """Consecutive frames rendered on one terrain patch: its centre, near-field half-width and vertices."""

    poses: tuple
    lat: float
    lon: float
    half_width_m: float
    near_vertices: int

    def entry(self, traj_name: str, near_radius_factor: float) -> dict:
        """The patch builder's crater entry: centred on the patch, its diameter chosen so that the near field
        (``near_radius_factor`` x D) is the patch's half-width."""
        first, last = self.poses[0].index, self.poses[-1].index
        name = f"nav-{traj_name}-{first:04d}" if first == last else f"nav-{traj_name}-{first:04d}-{last:04d}"
        return {
            "name": name,
            "lat": self.lat,
            "lon": self.lon,
            "diameter_km": self.half_width_m / near_radius_factor / 1000.0,
            "source": "navigation frame footprint" if first == last else "navigation frames' joint footprint",
        }


def own_half_width_m(pose: FramePose) -> float:
    """Near-field half-width of the frame's own patch (per-frame rendering): footprint x :data:`PATCH_MARGIN`."""
    return footprint_half_width_m(pose) * PATCH_MARGIN


def joint_patch(poses, near_vertices: int) -> PatchGroup:
    """The patch that holds every footprint of ``poses`` with :data:`PATCH_MARGIN`, at a vertex spacing no
    coarser than any of the frames' own patches (``near_vertices`` over :func:`own_half_width_m`): centred
    on the middle of the footprints' corners (in the middle frame's ENU plane), its vertex count raised to
    keep the spacing. A single frame's patch is its own (centred on its target, ``near_vertices``)."""
    poses = tuple(poses)
    if len(poses) == 1:
        p = poses[0]
        return PatchGroup(poses, p.target_lat, p.target_lon, own_half_width_m(p), int(near_vertices))
    mid = poses[len(poses) // 2]
    corners = np.concatenate([frame_corners_mc(p) for p in poses])
    enu = geometry.mc_to_enu(corners, mid.target_lat, mid.target_lon)[:, :2]
    ce, cn = (enu.max(axis=0) + enu.min(axis=0)) / 2.0
    lat, lon, _ = geometry.mc_to_latlon(geometry.enu_to_mc(np.array([ce, cn, 0.0]), mid.target_lat, mid.target_lon))
    lat, lon = float(lat), float(lon)
    hw = float(np.max(np.abs(geometry.mc_to_enu(corners, lat, lon)[:, :2]))) * PATCH_MARGIN
    finest = min(own_half_width_m(p) for p in poses)  # the smallest own patch has the finest spacing
    n = int(math.ceil((near_vertices - 1) * hw / finest - 1e-9)) + 1
    return PatchGroup(poses, lat, lon, hw, n)


def group_frames(poses, near_vertices: int, share: bool = True) -> list[PatchGroup]:
    """Consecutive frames grouped onto shared terrain patches (:func:`joint_patch`): a frame joins the
    current group while the joint patch needs at most :data:`SHARE_MAX_VERTEX_FACTOR` x ``near_vertices``
    per side. ``share=False``: every frame on its own patch (the per-frame path)."""
    if not share:
        return [joint_patch([p], near_vertices) for p in poses]
    groups: list[PatchGroup] = []
    cur: list = []
    for p in poses:
        trial = joint_patch(cur + [p], near_vertices)
        if cur and trial.near_vertices > SHARE_MAX_VERTEX_FACTOR * near_vertices:
            groups.append(joint_patch(cur, near_vertices))
            cur = [p]
        else:
            cur.append(p)
    if cur:
        groups.append(joint_patch(cur, near_vertices))
    return groups


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
    rng = float(np.linalg.norm(cam.position))
    # The camera seen from the patch origin (informative only: the explicit camera wins).
    view_el = math.degrees(math.asin(max(-1.0, min(1.0, cam.position[2] / rng))))
    view_az = math.degrees(math.atan2(cam.position[0], cam.position[1])) % 360.0
    return camera_worker_item(
        index=pose.index,
        camera=cam,
        sun=pose.sun_enu(lat0, lon0),
        view=(view_el, view_az),
        range_m=rng,
        fov_deg=pose.fov_deg,
        width_px=int(pose.width_px),
        rel_path=frame_rel_path(pose.index),
        seed=seed,
        header=header,
    )


def _compute_horizons(specs: list[tuple]) -> None:
    """(Child process) the horizon maps of ``specs`` (:func:`blender_gen.fast.ensure_horizons` arguments)
    into the shared cache. A failure is left to the workers, which compute what is missing themselves."""
    # Ctrl-C reaches the process group, and the host terminates this process once the workers are done: end
    # quietly (the handlers inherited from the host would raise its Interrupted here).
    for stop in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(stop, signal.SIG_DFL)
    for spec in specs:
        try:
            ensure_horizons(*spec)
        except Exception:  # noqa: BLE001 - only a head start: the worker computes the map itself
            pass


def _horizons_ahead(jobs, render):
    """Fast mode with fewer patches than ``render.workers``: a core would idle while each worker imports
    bpy and builds its scene (single-threaded, seconds), so a host-side process computes the patches'
    horizon maps meanwhile (the workers then read them from the cache, or wait on its lock). Returns the
    process, or None."""
    if render.mode != "fast" or not jobs or len(jobs) >= render.workers:  # no jobs: every frame was reused
        return None

    base = render.as_dict()
    specs = [
        (
            str(job.npz),
            base | job.render_overrides,
            job.crater.diameter_km * 1000.0,
            sorted({float(p["item"]["sun_azimuth"]) for p in job.plans}),
            horizon_cache_dir(render.horizon_cache_dir, str(job.npz)),
        )
        for job in jobs
    ]
    proc = multiprocessing.get_context("fork").Process(target=_compute_horizons, args=(specs,), daemon=True)
    proc.start()
    return proc


def frame_row(trajectory: str, fr: dict, res: dict, out_dir: Path, landmark_map, map_identity: dict) -> dict:
    """The manifest row of one rendered frame: the worker's ``res``, the pose and patch of ``fr``, and the
    labels of the landmarks in view (their lit and occluded rim fractions read from the frame's EXR), with
    the identity of the map ``landmark_map`` they come from (:func:`.landmarks.map_identity`)."""
    pose = fr["pose"]
    channels = exr.read_channels(out_dir / res["rel_path"], ("lit", "depth"))
    lit, depth = channels["lit"], channels["depth"]
    cam = pose.pose_enu(pose.target_lat, pose.target_lon)
    sun_el, sun_az = pose.sun_enu(pose.target_lat, pose.target_lon)
    return {
        "schema_version": schema.SCHEMA_VERSION,
        "label_version": FRAME_LABEL_VERSION,
        "trajectory": trajectory,
        "index": int(res["index"]),
        "rel_path": res["rel_path"],
        "sha256": res["sha256"],
        "mode": res["mode"],
        "render_seconds": res["seconds"],
        "terrain_id": fr["meta"]["terrain_id"],
        "patch": {
            "lat": fr["group"].lat,
            "lon": fr["group"].lon,
            "half_width_m": fr["group"].half_width_m,
            "near_vertices": fr["group"].near_vertices,
            "frames": [p.index for p in fr["group"].poses],
            "camera_enu_m": fr["item"]["camera"]["position"],
            "sun_enu": {"elevation_deg": fr["item"]["sun_elevation"], "azimuth_deg": fr["item"]["sun_azimuth"]},
        },
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
        "landmarks": landmarks_in_view(pose, landmark_map, pose.target_lat, pose.target_lon, lit, depth),
        "landmark_map": map_identity,
    }


def reusable_frame(out_dir: Path, index: int, header: dict, recorded_sha256: str | None) -> dict | None:
    """The worker result of frame ``index`` already in ``out_dir``, when it was rendered with the planned
    ``header`` (pose: camera, field of view, size and Sun; patch, seed, code version and the digest of
    every setting that can change a pixel) and its bytes are proved as the sweep proves a kept render
    (:mod:`crater_synth.dataset.recover`): by ``recorded_sha256``, the sha256 the previous manifest
    recorded for it, or else by its seal (pixels and attributes as written, decoded and encoded again).
    Else None: it is rendered again, the file replaced atomically. What a re-run keeps."""
    path = out_dir / frame_rel_path(index)
    planned = exr.as_read(header)
    try:
        attrs = exr.read_header(path)
        if any(attrs.get(k) != v for k, v in planned.items()):
            return None
        sha = schema.sha256_file(path)
        if sha != recorded_sha256:  # no row records these bytes: the file must prove itself
            attrs = exr.check_seal(path) or {}
            if any(attrs.get(k) != v for k, v in planned.items()):
                return None
        stats = json.loads(attrs[STATS_HEADER])
        return {
            "index": index,
            "rel_path": frame_rel_path(index),
            "sha256": sha,
            "lit_fraction": stats["lit_fraction"],
            "mean_if": stats["mean_if"],
            "seconds": 0.0,
            "mode": attrs["crater_synth:mode"],
            "reused": True,
        }
    except (exr.ExrError, OSError, KeyError, TypeError, ValueError):
        return None  # missing, unreadable, or not a frame of this project


def _selected_poses(traj, only: list[int] | None) -> list:
    """The trajectory's frame poses, all or those of the indices ``only``; bad input is one error."""
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
    return poses


def _group_patch(settings, traj_name: str, group, n_near: int, bar: Progress):
    """Build (or reuse) the terrain patch a group of frames shares: (its catalogue entry, its settings,
    npz path, metadata), said on ``bar``. A patch that cannot be built is an error naming the frames."""
    entry = group.entry(traj_name, settings.terrain.near_radius_factor)
    hw = group.half_width_m
    gsettings = frame_settings(settings, hw)
    if group.near_vertices != n_near:
        gsettings = replace(gsettings, **{"terrain.near_vertices": group.near_vertices})
    first = group.poses[0]
    try:
        npz, meta = build_terrain(entry, gsettings)
    except UserError as exc:
        which = f"frame {first.index}" if len(group.poses) == 1 else f"frames {first.index}-{group.poses[-1].index}"
        raise UserError(
            f"trajectory={traj_name} {which} (target lat {first.target_lat:.2f}, lon {first.target_lon:.2f}): {exc}"
        ) from None
    bar.write(
        f"frames {[p.index for p in group.poses]}: patch +-{hw / 1e3:.1f} km, {group.near_vertices}^2 "
        f"vertices ({'cached' if meta.get('cached') else 'built'})"
    )
    return entry, gsettings, npz, meta


def _patch_render_job(render, group, entry: dict, gsettings, meta: dict, n_near: int):
    """What the workers are told about a group's patch: (the job's crater, its render overrides, the
    render digest of every setting that can change a pixel)."""
    # The fast path's horizon map: as many texels as keep its texel no coarser than a frame's own patch's.
    scale = group.near_vertices / n_near
    overrides = {}
    if scale > 1.0:
        overrides["shadow_map_px"] = int(math.ceil(render.shadow_map_px * scale / 8.0)) * 8
    # The job's crater diameter sets only the fast path's horizon-map extent (blender_gen/fast.py).
    map_d_km = group.half_width_m * FAST_MAP_MARGIN / render.shadow_map_extent_factor / 1000.0
    crater = CraterSettings(name=entry["name"], lat=entry["lat"], lon=entry["lon"], diameter_km=map_d_km)
    # Every setting that can change a pixel (crater_synth.dataset.identity), the patch and the map overrides.
    digest = content_key([render_identity(gsettings, crater, meta["terrain_id"]), overrides])
    return crater, overrides, digest


def _frame_header(settings, traj_name: str, pose, meta: dict, group, digest: str, seed: int) -> dict:
    """The host's EXR header entries of one frame: what it is and everything that made it."""
    return {
        "trajectory": traj_name,
        "frame": pose.index,
        "terrain_id": meta["terrain_id"],
        "code_version": code_version(),
        "renderer": settings.render.mode,
        "samples": int(settings.render.samples),
        "pose_mc": json.dumps(pose.as_dict(), sort_keys=True),
        "hapke": json.dumps(hapke_dict(settings.hapke), sort_keys=True),
        "seed": seed,
        "patch_origin": json.dumps([group.lat, group.lon]),
        "render_digest": digest,
    }


def _plan_frames(settings, traj_name: str, groups: list, out_dir: Path, progress: bool):
    """Each group's patch and each frame's worker item: (worker jobs of the frames to render, frame
    index -> its pose, patch metadata, item and group; frame index -> the RESULT of a frame kept as it is
    on disk, same settings and seal intact)."""
    n_near = int(settings.terrain.near_vertices)
    recorded = {r.get("rel_path"): r.get("sha256") for r in schema.iter_rows(out_dir / schema.MANIFEST_NAME)}
    jobs, frames, reused = [], {}, {}
    bar = Progress(len(groups), "nav-frames terrain", "patch", "auto" if progress else "off")
    for group in groups:
        entry, gsettings, npz, meta = _group_patch(settings, traj_name, group, n_near, bar)
        bar.update()
        crater, overrides, digest = _patch_render_job(settings.render, group, entry, gsettings, meta, n_near)
        plans = []
        for pose in group.poses:
            seed = render_seed(settings.seed, ("navframe", traj_name, pose.index))
            header = _frame_header(settings, traj_name, pose, meta, group, digest, seed)
            item = worker_item(pose, group.lat, group.lon, seed, header)
            frames[pose.index] = {"pose": pose, "meta": meta, "item": item, "group": group}
            kept = reusable_frame(out_dir, pose.index, header, recorded.get(frame_rel_path(pose.index)))
            if kept is not None:
                reused[pose.index] = kept
            else:
                plans.append({"params": SimpleNamespace(index=pose.index, indices=(0, 0, 0, pose.index)), "item": item})
        if plans:
            jobs.append(CraterJob(crater=crater, npz=npz, meta=meta, plans=plans, render_overrides=overrides))
    bar.close()
    return jobs, frames, reused


def _render_frame_jobs(jobs: list, settings, out_dir: Path, on_result) -> None:
    """Run the workers over ``jobs`` while the horizon maps are computed ahead. A shared patch's frames
    stay with one worker (its scene and BVH built once) unless splitting them between two finishes
    sooner; the horizon map is computed once either way (the on-disk cache)."""
    render = settings.render
    ahead = _horizons_ahead(jobs, render)
    try:
        if jobs:
            run_workers(jobs, render, settings.hapke, out_dir, on_result, startup_renders=FRAME_STARTUP_RENDERS)
    finally:
        if ahead is not None and ahead.is_alive():  # the workers are done: the maps are no longer needed
            ahead.terminate()
            ahead.join()


def render_frames(
    settings, out_dir: Path, only: list[int] | None = None, progress: bool = False, share_patches: bool = True
) -> dict:
    """Render the trajectory's frames (all, or the indices ``only``) into ``out_dir`` with labels;
    returns a summary. ``share_patches``: consecutive frames share a terrain patch (:func:`group_frames`);
    False renders each frame on its own patch. Raises :class:`UserError` on bad input before anything is
    rendered, and on a folder the run may not write into (:mod:`.frame_folder`); a run refused before
    rendering leaves nothing behind."""
    traj = settings.trajectory
    poses = _selected_poses(traj, only)
    out_dir = Path(out_dir)
    ensure_writable_dir(settings.data_dir, "data_dir")
    folder = claim_frames_folder(out_dir, traj.name)
    dispatched = False
    try:
        t0 = time.perf_counter()
        groups = group_frames(poses, int(settings.terrain.near_vertices), share=share_patches)
        jobs, frames, reused = _plan_frames(settings, traj.name, groups, out_dir, progress)
        recorded = {r.get("rel_path"): r.get("sha256") for r in manifest_rows(out_dir) or []}
        adopt_unlisted(folder, {frame_rel_path(i) for i in reused}, recorded)
        folder.record([frame_rel_path(i) for i in frames] + [schema.MANIFEST_NAME])
        t_patch = time.perf_counter() - t0
        dispatched = True
        rows, t_render = _render_and_label(settings, traj.name, jobs, frames, reused, out_dir, progress)
        ordered = merged_rows(out_dir, rows, set(reused))
        text = "".join(schema.dumps_row(r) + "\n" for r in ordered)
        manifest = out_dir / schema.MANIFEST_NAME
        if not manifest.is_file() or manifest.read_text(encoding="utf-8", errors="replace") != text:
            schema.atomic_write_text(manifest, text)
        folder.seal([frame_rel_path(i) for i in frames] + [schema.MANIFEST_NAME])
    except BaseException:
        if not dispatched:  # refused (or stopped) before rendering: no litter
            folder.discard()
        raise
    finally:
        folder.release()
    mine = [rows[i] for i in sorted(rows)]
    return {
        "trajectory": traj.name,
        "frames": len(mine),
        "out_dir": str(out_dir),
        "mode": settings.render.mode,
        "modes_used": sorted({r["mode"] for r in mine}),
        "width_px": int(traj.width_px),
        "patch_seconds": round(t_patch, 2),
        "render_seconds": round(t_render, 2),
        "worker_render_seconds": round(sum(rows[i]["render_seconds"] for i in rows if i not in reused), 2),
        "landmarks_in_view": [len(r["landmarks"]) for r in mine],
        "sun_below_horizon": [r["index"] for r in mine if r["sun_enu"]["elevation_deg"] < 0.0],
        "patches": len(groups),
        "reused": len(reused),
        "manifest_frames": len(ordered),
    }


def _render_and_label(settings, traj_name: str, jobs, frames: dict, reused: dict, out_dir: Path, progress: bool):
    """Render ``jobs`` and label every frame (kept or rendered) as it arrives: (frame index -> manifest row,
    seconds)."""
    maps: dict[str, tuple] = {}
    rows: dict[int, dict] = {}
    bar = Progress(len(frames), "nav-frames", "frame", "auto" if progress else "off")

    def on_result(_job, plan, result):
        # labelled as each frame arrives: the host's work overlaps the workers'
        idx = int(result["index"])
        pole = pole_of(frames[idx]["pose"].target_lat)
        if pole not in maps:
            maps[pole] = (load_default_map(pole)[0], default_map_identity(pole))
        rows[idx] = frame_row(traj_name, frames[idx], result, out_dir, *maps[pole])
        bar.update(kept=len(reused), mode=result["mode"])

    for result in reused.values():
        on_result(None, None, result)
    t1 = time.perf_counter()
    _render_frame_jobs(jobs, settings, out_dir, on_result)
    bar.close()
    missing = sorted(set(frames) - set(rows))
    if missing:
        raise UserError(f"frames {missing} of trajectory {traj_name} were not rendered (see {out_dir}/.jobs/*.log)")
    return rows, time.perf_counter() - t1


@click.command("nav-frames")
@OVERRIDES
@click.option(
    "--out", type=click.Path(path_type=Path), default=None, help="Output directory [data_dir/navframes/NAME]."
)
@click.option("--frames", "only", default=None, help="Comma-separated frame indices to render (default: all).")
@click.option(
    "--per-frame-patches",
    is_flag=True,
    help="Render every frame on its own terrain patch (the slower per-frame path; default: frames share patches).",
)
@user_errors
def nav_frames_command(overrides, out, only, per_frame_patches):
    """Render a trajectory's navigation frames (EXR + labelled manifest).

    Fast mode's G-buffer takes one sample per pixel (its centre) unless render.samples or
    render.gbuffer_samples is given. Example: `crater-synth nav-frames trajectory=descent_ridge
    render.mode=direct`
    """
    settings = load_settings(frame_overrides(overrides))
    if settings.trajectory is None:
        raise ConfigError("no trajectory selected: add trajectory=NAME (configs/trajectory/)")
    try:
        idx = None if only is None else [int(s) for s in only.split(",") if s.strip()]
    except ValueError:
        raise UserError(f"--frames {only!r}: must be comma-separated integers") from None
    if idx is not None and not idx:  # an empty list from a script's variable: not "all frames"
        raise UserError(f"--frames {only!r}: names no frame (leave the option out for every frame)")
    out = out or Path(str(settings.data_dir)) / "navframes" / settings.trajectory.name
    summary = render_frames(settings, out, idx, progress=True, share_patches=not per_frame_patches)
    if summary["sun_below_horizon"]:  # rendered as asked, but a night frame shows nothing to navigate by
        click.echo(
            f"warning: the Sun is below the horizon at the target of frames {summary['sun_below_horizon']}: "
            "they are dark (the trajectory's subsolar longitude is on the far side of the pole?)",
            err=True,
        )
    click.echo(json.dumps(summary))
