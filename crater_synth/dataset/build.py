"""``build_dataset``: render the configured sweep (or one shard of it) into ``out_dir``, resuming."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Callable, Mapping

from crater_core import schema
from crater_core.files import ensure_writable_dir, is_disk_full, os_error_text, remove_stale_scratch
from crater_core.progress import Progress
from crater_core.settings import Settings
from crater_synth.dataset.disk import (
    DatasetLock,
    check_free_disk,
    check_output_dir,
    measured_bytes_per_render,
    prune_jobs,
    remove_orphans,
)
from crater_synth.dataset.dispatch import run_workers
from crater_synth.dataset.manifest import is_done, manifest_row, part_file, stale_parts
from crater_synth.dataset.plan import CraterJob, plan_render, render_digest, render_seed, worker_item
from crater_synth.errors import RenderError


def _warn(message: str) -> None:
    print(f"warning: {message}", file=sys.stderr, flush=True)


def build_dataset(
    settings: Settings | Mapping, progress: bool = True, lock: bool = True, warn: Callable[[str], None] | None = _warn
) -> dict:
    """Render the configured sweep (or ``launcher.shard``) into ``out_dir``, resuming: renders whose row
    has the current digest and whose file hashes right are skipped.

    ``settings``: :class:`Settings` (a raw configuration is converted once, here). ``lock=False`` is for
    a launcher that already holds the dataset lock (the Dask tasks). ``warn`` receives the warnings of
    a legal but suspicious run (a Sun below the horizon; renders that came out all black).
    Returns a summary dict (counts, timings, dataset path)."""
    from crater_synth.config import as_settings

    s = as_settings(settings)
    if warn is not None:
        for w in s.warnings():
            warn(w)
    grid = s.sweep.grid
    shard = s.launcher.shard_slice
    indices = grid.shard(*shard) if shard else range(len(grid))
    ensure_writable_dir(s.data_dir, "data_dir")  # the terrain patches go there
    out_dir = Path(s.out_dir).resolve()
    check_output_dir(out_dir)
    dataset_lock = DatasetLock(out_dir, shard if lock else None)
    if lock:
        dataset_lock.acquire()
    try:
        return _build_locked(
            s, grid, indices, shard, out_dir, progress, warn, exclusive=lock and dataset_lock.exclusive
        )
    except OSError as exc:
        if is_disk_full(exc):
            raise RenderError(os_error_text(exc)) from None
        raise
    finally:
        dataset_lock.release()


def _build_locked(s: Settings, grid, indices, shard, out_dir: Path, progress: bool, warn, exclusive: bool) -> dict:
    from crater_synth.terrain.patch import build_terrain

    stale = stale_parts(out_dir)
    if stale:  # rows of a killed run on this host: merge them, or they would never reach the manifest
        schema.merge_parts(out_dir, parts=stale)
    existing = {schema.row_key(r): r for r in schema.dataset_rows(out_dir)}
    removed = remove_orphans(out_dir, list(existing.values()), exclusive)
    if removed and warn is not None:
        warn(f"removed {len(removed)} orphan file(s) of an interrupted run from {out_dir} (no manifest row)")
    prune_jobs(out_dir)
    remove_stale_scratch()  # Cycles scratch files of workers killed with -9 (their host never cleaned up)
    craters = s.craters
    # Early, cheap disk check (before terrain and per-render planning, which a huge sweep makes slow):
    # at least this many renders are left even if every existing row belongs to this run.
    check_free_disk(
        out_dir,
        max(0, len(indices) * len(craters) - len(existing)),
        measured_bytes_per_render(list(existing.values()), out_dir),
    )
    jobs, skipped, total = [], 0, 0
    for crater in craters:
        npz, meta = build_terrain(crater, s)
        job = CraterJob(crater=crater, npz=Path(npz), meta=meta)
        digest = render_digest(s.render, s.hapke, meta["terrain_id"])
        for index in indices:
            if not grid.renders(grid.params(index, crater.lat)):
                continue  # physical sweep: the Sun never stands that high in that direction here
            plan = plan_render(crater, meta, grid, index, s.render.roi_min_px, s.render.crop_to_roi)
            p = plan["params"]
            key = schema.params_key(crater.name, p.sun_elevation, p.sun_azimuth, p.cam_elevation, p.cam_azimuth)
            plan["seed"] = render_seed(s.seed, key)
            plan["digest"] = digest
            total += 1
            if is_done(existing.get(key), out_dir, digest):
                skipped += 1
            else:
                plan["item"] = worker_item(crater, meta, plan, s.render, s.hapke, grid.fov_deg)
                job.plans.append(plan)
        jobs.append(job)

    todo = sum(len(j.plans) for j in jobs)
    check_free_disk(out_dir, todo, measured_bytes_per_render(list(existing.values()), out_dir))
    part = part_file(out_dir, shard)
    bar = Progress(todo, f"rendering ({s.render.mode})", "render", mode="auto" if progress and todo else "off")
    dark = []
    rows = schema.RowAppender(part)  # each row written at once, fsynced per 256 rows / 2 s
    t0 = time.perf_counter()

    def on_result(job: CraterJob, plan: dict, result: dict):
        row = manifest_row(job, plan, result, grid.fov_deg, s.render.mode)
        rows.add(row)
        if row["lit_fraction"] <= 0.0:
            dark.append(row["path"])
        bar.update(1)

    try:
        run_workers(jobs, s.render, s.hapke, out_dir, on_result)
        rows.close()
    except BaseException:
        try:  # stopped early: the rows rendered so far reach the manifest now
            rows.close()
            if part.exists():
                schema.merge_parts(out_dir, parts=[part])
        except OSError:
            pass  # e.g. the disk is full: the part file stays and the next run merges it
        raise
    finally:
        bar.close()
    elapsed = time.perf_counter() - t0
    n_rows = schema.merge_parts(out_dir, parts=[part])
    if dark and warn is not None:
        warn(
            f"{len(dark)} of {todo} new renders are entirely in shadow (lit_fraction 0, all black), e.g. "
            f"{out_dir / dark[0]}: check sweep.sun_elevation and the crater's latitude"
        )
    return {
        "dataset": str(out_dir),
        "renders_total": total,
        "rendered": todo,
        "skipped_existing": skipped,
        "manifest_rows": n_rows,
        "seconds": round(elapsed, 2),
        "renders_per_s": round(todo / elapsed, 3) if todo and elapsed > 0 else None,
        "craters": [c.name for c in craters],
        "mode": s.render.mode,
    }
