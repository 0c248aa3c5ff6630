"""Render a sweep into a dataset directory: plan, resume, dispatch Blender workers, record the manifest.

Layout of a dataset directory::

    manifest.jsonl            merged, sorted rows (crater_core/schema.py)
    manifest.parts/*.jsonl    rows appended while rendering (merged at the end)
    <crater>/<params>.exr     one tiled EXR per render
    .jobs/                    worker job files and logs

The host never imports bpy: each worker is a separate process (``python -m blender_gen.worker``)
that imports bpy once and renders a contiguous, camera-major block of renders.

Length: planning, resume, worker dispatch and manifest recording share one render-key/fingerprint
model and one set of on-disk conventions (partial rows, job files, the lock); split apart they would
have to pass that state around. The click command at the end is a thin wrapper.
"""

from __future__ import annotations

import json
import math
import os
import re
import selectors
import shutil
import socket
import subprocess
import sys
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from crater_core import geometry, schema
from crater_core.hapke import HapkeParams
from crater_core.horizon import HORIZON_VERSION
from crater_core.sweep import SweepGrid, grid_from_config
from crater_synth import __version__
from crater_synth.config import ConfigError, resolved
from crater_synth.config import craters as selected_craters
from crater_synth.errors import UserError

REPO_ROOT = Path(__file__).resolve().parent.parent
# Bytes per render used for the free-disk check before any measured value exists
# (210x210 px x 6 float32 channels, zip-compressed: measured ~0.6-0.9 MB; rounded up).
DEFAULT_BYTES_PER_RENDER = 1_000_000


class RenderError(UserError):
    """A worker reported bad input or kept failing."""


# ------------------------------------------------------------------------------------------------
# Validation (before any rendering starts)
# ------------------------------------------------------------------------------------------------
def validate_render_config(render: dict) -> None:
    if render.get("mode") not in ("fast", "direct"):
        raise ConfigError(f"render.mode={render.get('mode')!r}: must be 'fast' or 'direct'")

    def number(key, default, cast=int):
        try:
            return cast(render.get(key, default))
        except (TypeError, ValueError):
            raise ConfigError(f"render.{key}={render.get(key)!r}: must be a number") from None

    if number("samples", 0) < 1:
        raise ConfigError(f"render.samples={render.get('samples')}: must be >= 1")
    if number("max_bounces", 0) < 0:
        raise ConfigError(f"render.max_bounces={render.get('max_bounces')}: must be >= 0")
    if number("roi_min_px", 0) < 8:
        raise ConfigError(f"render.roi_min_px={render.get('roi_min_px')}: must be >= 8")
    if number("workers", 1) < 1:
        raise ConfigError(f"render.workers={render.get('workers')}: must be >= 1")
    if number("threads", 0) < 0:
        raise ConfigError(f"render.threads={render.get('threads')}: must be >= 0 (0 = all cores)")
    if number("shadow_map_px", 1) < 1:
        raise ConfigError(f"render.shadow_map_px={render.get('shadow_map_px')}: must be >= 1")
    if not number("shadow_map_extent_factor", 1.0, float) > 0:
        raise ConfigError(f"render.shadow_map_extent_factor={render.get('shadow_map_extent_factor')}: must be > 0")


def hapke_params(cfg_resolved: dict) -> HapkeParams:
    try:
        return HapkeParams.from_mapping(cfg_resolved["hapke"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"hapke: {exc}") from None


def check_output_dir(out_dir: Path) -> None:
    """The dataset directory must be creatable and writable."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / f".write-probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise UserError(f"output directory {out_dir} is not writable: {exc.strerror or exc}") from None


def measured_bytes_per_render(rows: list[dict], out_dir: Path) -> int:
    sizes = [(out_dir / r["path"]).stat().st_size for r in rows[:50] if (out_dir / r["path"]).exists()]
    return int(np.mean(sizes)) if sizes else DEFAULT_BYTES_PER_RENDER


def _size(n: float) -> str:
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.2f} {unit}"
    return f"{int(n)} B"


def check_free_disk(out_dir: Path, n_renders: int, bytes_per_render: int) -> None:
    need = int(n_renders * bytes_per_render * 1.1)
    free = shutil.disk_usage(out_dir).free
    if need > free:
        raise UserError(f"not enough free disk in {out_dir}: {n_renders} renders need ~{_size(need)} "
                        f"({_size(bytes_per_render)} each, +10 %), {_size(free)} free")


def writer_tag() -> str:
    """``<host>-<pid>`` of this process: names its job and manifest part files, so concurrent shards
    (several processes, or several nodes on a shared filesystem) never write the same file."""
    host = re.sub(r"[^A-Za-z0-9.]+", "_", socket.gethostname()) or "host"
    return f"{host}-{os.getpid()}"


def stale_parts(out_dir: Path) -> list[Path]:
    """Manifest part files of writers on this host that are no longer running (e.g. a sweep killed
    with -9), which are safe to merge. Part names end in ``-<host>-<pid>``; parts of other hosts are
    merged by their host's next run or by the Dask launcher's final merge."""
    host = writer_tag().rsplit("-", 1)[0]
    out = []
    for part in sorted((out_dir / schema.PARTS_DIR).glob("*.jsonl")):
        head, _, pid = part.stem.rpartition("-")
        if not pid.isdigit() or int(pid) == os.getpid() or not head.endswith("-" + host):
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            out.append(part)
        except OSError:
            pass  # alive (another user's process)
    return out


def parse_shard(shard) -> tuple[int, int] | None:
    if shard in (None, "", "null"):
        return None
    try:
        i, n = (int(x) for x in str(shard).split("/"))
    except ValueError:
        raise ConfigError(f"launcher.shard={shard!r}: expected 'i/n', e.g. 0/4") from None
    if n < 1 or not 0 <= i < n:
        raise ConfigError(f"launcher.shard={shard!r}: need 0 <= i < n")
    return i, n


# ------------------------------------------------------------------------------------------------
# Planning: geometry of every render, computed analytically on the host
# ------------------------------------------------------------------------------------------------
def code_version() -> str:
    return f"crater-synth {__version__}"


def render_digest(render: dict, hapke: dict, terrain_id: str) -> str:
    """Fingerprint of everything besides the angles that changes the pixels of a render."""
    keys = ("mode", "samples", "max_bounces", "denoise", "shadow_map_px", "shadow_map_levels",
            "shadow_map_extent_factor", "shadow_map_samples", "gbuffer_samples", "roi_min_px", "crop_to_roi")
    payload = {"render": {k: render.get(k) for k in keys}, "hapke": hapke, "terrain": terrain_id}
    if render.get("mode") == "fast":  # fast-mode shadows come from horizon maps (crater_core.horizon)
        payload["horizon_version"] = HORIZON_VERSION
    payload = json.dumps(payload, sort_keys=True)
    return f"{zlib.crc32(payload.encode()):08x}"


def render_seed(base_seed: int, key: tuple) -> int:
    return zlib.crc32(f"{base_seed}:{key}".encode()) & 0x7FFFFFFF


def plan_render(crater: dict, meta: dict, grid: SweepGrid, index: int, roi_min_px: int,
                crop_to_roi: bool = True) -> dict:
    """Camera, frame size, rim ellipse, sigma boxes and crop of one render (full-frame -> crop px).

    With ``crop_to_roi`` (the default) only the largest sigma box is rendered; otherwise the whole
    90 deg frame (the naive baseline of ``crater-synth bench``)."""
    p = grid.params(index, crater["lat"])
    diameter_m = crater["diameter_km"] * 1000.0
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
        raise UserError(f"ROI box of sigma={max(grid.sigmas)} leaves the {grid.fov_deg} deg frame for "
                        f"{crater['name']} at camera elevation {p.cam_elevation}: lower sigma or raise range_factor")
    if not crop_to_roi:
        crop = [0, 0, width, width]
    u0, v0 = crop[0], crop[1]
    return {
        "params": p,
        "range_m": range_m,
        "frame_width": width,
        "crop": crop,
        "center_px": [float(cu - u0), float(cv - v0)],
        "rim_ellipse": ellipse.as_dict() | {"cu": ellipse.cu - u0, "cv": ellipse.cv - v0},
        "sigma_boxes": {k: [b[0] - u0, b[1] - v0, b[2] - u0, b[3] - v0] for k, b in boxes.items()},
    }


@dataclass
class CraterJob:
    """Everything needed to render (part of) one crater's sweep."""

    crater: dict
    npz: Path
    meta: dict
    plans: list[dict] = field(default_factory=list)


def _row(job: CraterJob, plan: dict, result: dict, cfg_r: dict, digest: str) -> dict:
    p = plan["params"]
    return {
        "schema_version": schema.SCHEMA_VERSION,
        "crater": job.crater["name"],
        "index": p.index,
        "indices": list(p.indices),
        "sun_elevation": p.sun_elevation, "sun_azimuth": p.sun_azimuth,
        "cam_elevation": p.cam_elevation, "cam_azimuth": p.cam_azimuth,
        **({"sun_elevation_param": p.sun_elevation_param} if p.sun_elevation_param != p.sun_elevation else {}),
        "range_m": plan["range_m"], "fov_deg": float(cfg_r["sweep"]["fov_deg"]),
        "width": plan["crop"][2] - plan["crop"][0], "height": plan["crop"][3] - plan["crop"][1],
        "frame_width": plan["frame_width"], "crop_origin": plan["crop"][:2],
        "center_px": plan["center_px"], "rim_ellipse": plan["rim_ellipse"], "sigma_boxes": plan["sigma_boxes"],
        "lit_fraction": float(result["lit_fraction"]), "mean_if": float(result["mean_if"]),
        "path": result["rel_path"], "sha256": result["sha256"], "seed": plan["seed"],
        "code_version": code_version(), "renderer": cfg_r["render"]["mode"],
        "terrain_id": job.meta["terrain_id"], "render_digest": digest,
    }


def _is_done(row: dict | None, out_dir: Path, digest: str) -> bool:
    if row is None or row.get("render_digest") != digest:
        return False
    f = out_dir / row["path"]
    return f.is_file() and schema.sha256_file(f) == row["sha256"]


# ------------------------------------------------------------------------------------------------
# Worker dispatch
# ------------------------------------------------------------------------------------------------
def _worker_render_item(job: CraterJob, plan: dict, cfg_r: dict) -> dict:
    p = plan["params"]
    rel = schema.render_rel_path(job.crater["name"], p.sun_elevation, p.sun_azimuth, p.cam_elevation, p.cam_azimuth)
    header = {"crater": job.crater["name"], "terrain_id": job.meta["terrain_id"], "code_version": code_version(),
              "renderer": cfg_r["render"]["mode"], "samples": int(cfg_r["render"]["samples"]),
              "range_m": plan["range_m"], "fov_deg": float(cfg_r["sweep"]["fov_deg"]),
              "frame_width": plan["frame_width"], "crop": json.dumps(plan["crop"]),
              "sigma_boxes": json.dumps(plan["sigma_boxes"]), "rim_ellipse": json.dumps(plan["rim_ellipse"]),
              "hapke": json.dumps(cfg_r["hapke"], sort_keys=True), "seed": plan["seed"]}
    return {"index": p.index, "indices": list(p.indices), "sun_elevation": p.sun_elevation,
            "sun_azimuth": p.sun_azimuth, "cam_elevation": p.cam_elevation, "cam_azimuth": p.cam_azimuth,
            "range_m": plan["range_m"], "fov_deg": float(cfg_r["sweep"]["fov_deg"]),
            "frame_width": plan["frame_width"], "crop": plan["crop"], "rel_path": rel, "seed": plan["seed"],
            "header": header}


def worker_command(job_file: Path) -> list[str]:
    return [sys.executable, "-m", "blender_gen.worker", str(job_file)]


def camera_major(plan: dict) -> tuple[int, int, int, int]:
    """Sort key of a plan: camera pose first, then the sun (the sweep index is sun-major)."""
    i = plan["params"].indices
    return i[2], i[3], i[0], i[1]


def _split_contiguous(items: list, n: int) -> list[list]:
    n = max(1, min(n, len(items)))
    return [items[i * len(items) // n:(i + 1) * len(items) // n] for i in range(n)]


def run_workers(jobs: list[CraterJob], cfg_r: dict, out_dir: Path, on_result, max_retries: int = 2) -> None:
    """Render every plan of ``jobs`` with ``render.workers`` processes; ``on_result(job, plan, result)``
    is called for each finished render. A worker that dies is restarted on its unfinished renders."""
    n_workers = int(cfg_r["render"].get("workers", 1))
    jobs_dir = out_dir / ".jobs"
    jobs_dir.mkdir(parents=True, exist_ok=True)
    render_cfg = dict(cfg_r["render"])
    if n_workers > 1 and int(render_cfg.get("threads", 0)) == 0:
        render_cfg["threads"] = max(1, (os.cpu_count() or 1) // n_workers)

    # Work units: contiguous blocks of one crater's plans, one block per worker slot, camera-major
    # (all suns of a camera pose together): each worker renders each of its G-buffers once and reads
    # the shared horizon maps of every sun azimuth (docs/renderer.md, "Order of work").
    units: list[tuple[CraterJob, list[dict]]] = []
    for job in jobs:
        if job.plans:
            share = max(1, round(n_workers * len(job.plans) / max(1, sum(len(j.plans) for j in jobs))))
            ordered = sorted(job.plans, key=camera_major)
            units += [(job, block) for block in _split_contiguous(ordered, share)]
    pending = list(units)
    attempts: dict[int, int] = {}
    running: dict = {}
    sel = selectors.DefaultSelector()
    uid = 0

    def start(job: CraterJob, block: list[dict], unit_id: int):
        job_file = jobs_dir / f"{job.crater['name']}-{writer_tag()}-{unit_id}.json"
        spec = {"terrain_npz": str(job.npz), "terrain_meta": job.meta, "crater": job.crater,
                "hapke": cfg_r["hapke"], "render": render_cfg, "out_dir": str(out_dir),
                "horizon_cache_dir": render_cfg.get("horizon_cache_dir"),
                "renders": [_worker_render_item(job, p, cfg_r) for p in block]}
        schema.atomic_write_text(job_file, json.dumps(spec))
        log = open(job_file.with_suffix(".log"), "ab")
        proc = subprocess.Popen(worker_command(job_file), stdout=subprocess.PIPE, stderr=log, cwd=REPO_ROOT,
                                env=os.environ | {"PYTHONUNBUFFERED": "1"})
        state = {"job": job, "block": {p["params"].index: p for p in block}, "id": unit_id, "log": log,
                 "error": None, "buf": b""}
        running[proc] = state
        sel.register(proc.stdout, selectors.EVENT_READ, proc)

    try:
        while pending or running:
            while pending and len(running) < n_workers:
                job, block = pending.pop(0)
                uid += 1
                attempts[uid] = attempts.get(uid, 0)
                start(job, block, uid)
            for key, _ in sel.select(timeout=1.0):
                proc = key.data
                state = running[proc]
                chunk = os.read(proc.stdout.fileno(), 65536)
                if chunk:
                    state["buf"] += chunk
                    *lines, state["buf"] = state["buf"].split(b"\n")
                    for raw in lines:
                        line = raw.decode("utf-8", "replace")
                        if line.startswith("RESULT "):
                            result = json.loads(line[7:])
                            plan = state["block"].pop(int(result["index"]), None)
                            if plan is not None:
                                on_result(state["job"], plan, result)
                        elif line.startswith("ERROR "):
                            state["error"] = line[6:]
                    continue
                sel.unregister(proc.stdout)
                rc = proc.wait()
                state["log"].close()
                del running[proc]
                if state["error"]:
                    raise RenderError(f"worker for {state['job'].crater['name']}: {state['error']}")
                left = list(state["block"].values())
                if left:
                    tries = attempts.get(state["id"], 0) + 1
                    if tries > max_retries:
                        raise RenderError(f"worker for {state['job'].crater['name']} failed {tries} times "
                                          f"(exit {rc}); see {jobs_dir}/*.log")
                    uid += 1
                    attempts[uid] = tries
                    left.sort(key=camera_major)
                    start(state["job"], left, uid)
    finally:
        for proc, state in list(running.items()):
            proc.kill()
            proc.wait()
            state["log"].close()
        sel.close()


class _RowBuffer:
    """Manifest rows appended to a part file in batches: one write + fsync per ``max_rows`` rows or
    ``max_age_s`` seconds instead of one per row (at 50+ renders/s the per-row fsync dominated the
    host's time). A crash loses at most the unflushed rows, whose EXRs are re-rendered on resume."""

    def __init__(self, part_file: Path, max_rows: int = 256, max_age_s: float = 2.0):
        self.part_file, self.max_rows, self.max_age_s = part_file, max_rows, max_age_s
        self.lines: list[str] = []
        self.t_first = 0.0

    def add(self, row: dict) -> None:
        if not self.lines:
            self.t_first = time.monotonic()
        self.lines.append(schema.dumps_row(schema.validate_row(row)) + "\n")
        if len(self.lines) >= self.max_rows or time.monotonic() - self.t_first >= self.max_age_s:
            self.flush()

    def flush(self) -> None:
        if not self.lines:
            return
        self.part_file.parent.mkdir(parents=True, exist_ok=True)
        with open(self.part_file, "a", encoding="utf-8") as fh:
            fh.write("".join(self.lines))
            fh.flush()
            os.fsync(fh.fileno())
        self.lines = []


# ------------------------------------------------------------------------------------------------
# The dataset command's body
# ------------------------------------------------------------------------------------------------
def build_dataset(cfg, progress: bool = True) -> dict:
    """Render the configured sweep (or one shard of it) into ``cfg.out_dir``, resuming.

    Returns a summary dict (counts, timings, dataset path).
    """
    from crater_synth.terrain import build_terrain

    cfg_r = resolved(cfg)
    render = cfg_r["render"]
    validate_render_config(render)
    hapke_params(cfg_r)
    grid = grid_from_config(cfg_r["sweep"])
    shard = parse_shard(cfg_r["launcher"].get("shard"))
    indices = grid.shard(*shard) if shard else range(len(grid))
    out_dir = Path(cfg_r["out_dir"]).resolve()
    check_output_dir(out_dir)
    craters = selected_craters(cfg)
    stale = stale_parts(out_dir)
    if stale:  # rows of a killed run on this host: merge them, or they would never reach the manifest
        schema.merge_parts(out_dir, parts=stale)

    existing = {schema.row_key(r): r for r in schema.dataset_rows(out_dir)}
    # Early, cheap disk check (before terrain and per-render planning, which a huge sweep makes slow):
    # at least this many renders are left even if every existing row belongs to this run.
    check_free_disk(out_dir, max(0, len(indices) * len(craters) - len(existing)),
                    measured_bytes_per_render(list(existing.values()), out_dir))
    jobs, skipped, total = [], 0, 0
    for crater in craters:
        npz, meta = build_terrain(crater, cfg)
        job = CraterJob(crater=crater, npz=Path(npz), meta=meta)
        digest = render_digest(render, cfg_r["hapke"], meta["terrain_id"])
        for index in indices:
            if not grid.renders(grid.params(index, crater["lat"])):
                continue  # physical sweep: the Sun never stands that high in that direction here
            plan = plan_render(crater, meta, grid, index, int(render["roi_min_px"]),
                               bool(render.get("crop_to_roi", True)))
            p = plan["params"]
            key = schema.params_key(crater["name"], p.sun_elevation, p.sun_azimuth, p.cam_elevation, p.cam_azimuth)
            plan["seed"] = render_seed(int(cfg_r["seed"]), key)
            plan["digest"] = digest
            total += 1
            if _is_done(existing.get(key), out_dir, digest):
                skipped += 1
            else:
                job.plans.append(plan)
        jobs.append(job)

    todo = sum(len(j.plans) for j in jobs)
    check_free_disk(out_dir, todo, measured_bytes_per_render(list(existing.values()), out_dir))
    part_name = f"shard{shard[0]}of{shard[1]}" if shard else "all"
    part_file = out_dir / schema.PARTS_DIR / f"{part_name}-{writer_tag()}.jsonl"

    bar = None
    if progress and todo:
        from tqdm import tqdm

        bar = tqdm(total=todo, unit="render", desc=f"rendering ({render['mode']})", dynamic_ncols=True,
                   file=sys.stderr)
    t0 = time.perf_counter()

    rows = _RowBuffer(part_file)

    def on_result(job: CraterJob, plan: dict, result: dict):
        rows.add(_row(job, plan, result, cfg_r, plan["digest"]))
        if bar is not None:
            bar.update(1)

    try:
        run_workers(jobs, cfg_r, out_dir, on_result, max_retries=int(render.get("max_retries", 2)))
    finally:
        rows.flush()
        if bar is not None:
            bar.close()
    elapsed = time.perf_counter() - t0
    n_rows = schema.merge_parts(out_dir, parts=[part_file])
    return {"dataset": str(out_dir), "renders_total": total, "rendered": todo, "skipped_existing": skipped,
            "manifest_rows": n_rows, "seconds": round(elapsed, 2),
            "renders_per_s": round(todo / elapsed, 3) if todo and elapsed > 0 else None,
            "craters": [c["name"] for c in craters], "mode": render["mode"]}


# ------------------------------------------------------------------------------------------------
# CLI
# ------------------------------------------------------------------------------------------------
import click  # noqa: E402

from crater_synth.cli_common import OVERRIDES, user_errors  # noqa: E402


@click.command("dataset")
@OVERRIDES
@user_errors
def dataset_command(overrides):
    """Render the sweep into out_dir (resumable; `launcher.shard=i/n` renders one slice).

    Examples: `crater-synth dataset sweep=smoke crater=shoemaker render.samples=2`,
    `crater-synth dataset sweep=paper render.workers=2 out_dir=/big/disk/paper`,
    `crater-synth dataset sweep=paper launcher=dask launcher.address=tcp://head:8786`.
    """
    from crater_synth.config import compose

    cfg = compose(overrides)
    if cfg.launcher.name == "dask":
        from crater_synth.launcher import run_dask

        summary = run_dask(cfg)
    else:
        summary = build_dataset(cfg)
    click.echo(json.dumps(summary))
