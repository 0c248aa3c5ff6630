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
from crater_synth.config import as_settings
from crater_synth.dataset.disk import (
    DatasetLock,
    check_planned_disk,
    check_sweep_disk,
    prune_jobs,
    remove_interrupted_writes,
    unplanned_files,
)
from crater_synth.dataset.dispatch import run_workers
from crater_synth.dataset.identity import render_identity
from crater_synth.dataset.manifest import manifest_row, part_file, planned_row, stale_parts
from crater_synth.dataset.marker import DatasetClaim
from crater_synth.dataset.plan import CraterJob, plan_render, render_seed, worker_item
from crater_synth.dataset.recover import prove
from crater_synth.errors import DatasetBusyError, RenderError, UserError
from crater_synth.terrain.patch import build_terrain


def _warn(message: str) -> None:
    print(f"warning: {message}", file=sys.stderr, flush=True)


def build_dataset(
    settings: Settings | Mapping, progress: bool = True, lock: bool = True, warn: Callable[[str], None] | None = _warn
) -> dict:
    """Render the configured sweep (or ``launcher.shard``) into ``out_dir``, resuming: a planned render
    whose file is proved (crater_synth.dataset.recover: its header holds the row planned now, and its
    bytes hash to the row's sha256 or its pixels give the header's seal) is kept, with its row rebuilt
    from the file if the manifest lost it; every other planned render is rendered (again).

    ``settings``: :class:`Settings` (a raw configuration is converted once, here). ``lock=False`` is for
    a launcher that already holds the dataset lock (the Dask tasks). ``warn`` receives the warnings of
    a legal but suspicious run (a Sun below the horizon; renders that came out all black; files left
    alone). A directory that is neither empty nor a dataset is refused (crater_synth.dataset.marker);
    a run refused before rendering leaves nothing behind. Returns a summary dict (counts, timings,
    dataset path)."""

    s = as_settings(settings)
    if warn is not None:
        for w in s.warnings():
            warn(w)
    grid = s.sweep.grid
    shard = s.launcher.shard_slice
    indices = grid.shard(*shard) if shard else range(len(grid))
    ensure_writable_dir(s.data_dir, "data_dir")  # the terrain patches go there
    out_dir = Path(s.out_dir).resolve()
    claim = DatasetClaim(out_dir)
    claim.create()
    dataset_lock = DatasetLock(out_dir, shard if lock else None)
    state = {"dispatched": False}
    if lock:
        try:
            dataset_lock.acquire()
        except DatasetBusyError:
            raise  # another writer's directory now: nothing of it is ours to remove
        except BaseException:
            claim.discard()
            raise
    try:
        claim.mark()
        return _build_locked(s, grid, indices, shard, out_dir, progress, warn, lock and dataset_lock.exclusive, state)
    except BaseException as exc:
        if not state["dispatched"]:  # refused (or stopped) before rendering: no litter
            claim.discard()
        if isinstance(exc, OSError) and is_disk_full(exc):
            raise RenderError(os_error_text(exc)) from None
        raise
    finally:
        dataset_lock.release()


def _existing_rows(out_dir: Path) -> dict:
    """The dataset's readable manifest rows by key, after merging the part files of a killed run and
    clearing the leftovers of killed workers."""
    stale = stale_parts(out_dir)
    if stale:  # rows of a killed run on this host: merge them, or they would never reach the manifest
        schema.merge_parts(out_dir, parts=stale)
    # A row whose path leaves the dataset is never followed (and is dropped from the manifest below).
    # dataset_rows drops every unreadable row, one whose path leaves the dataset included (schema.validate_row)
    existing = {schema.row_key(r): r for r in schema.dataset_rows(out_dir)}
    prune_jobs(out_dir)
    remove_stale_scratch()  # Cycles scratch files of workers killed with -9 (their host never cleaned up)
    return existing


def _plan_sweep(s: Settings, grid, indices) -> tuple[list[CraterJob], list[tuple[CraterJob, tuple, dict]], dict]:
    """Every crater's terrain and planned renders: (jobs, (job, key, plan) per render, key by file name).
    Two renders that would share a file are refused."""

    jobs: list[CraterJob] = []
    planned: list[tuple[CraterJob, tuple, dict]] = []
    names: dict[str, tuple] = {}
    for crater in s.craters:
        npz, meta = build_terrain(crater, s)
        job = CraterJob(crater=crater, npz=Path(npz), meta=meta)
        digest = render_identity(s, crater, meta["terrain_id"])
        for index in indices:
            if not grid.renders(grid.params(index, crater.lat)):
                continue  # physical sweep: the Sun never stands that high in that direction here
            plan = plan_render(crater, meta, grid, index, s.render.roi_min_px, s.render.crop_to_roi)
            p = plan["params"]
            key = schema.params_key(crater.name, p.sun_elevation, p.sun_azimuth, p.cam_elevation, p.cam_azimuth)
            if plan["rel_path"] in names:  # physical sun elevations (per crater) that round together
                values = ",".join(f"{v:g}" for v in grid.sun_elevation)
                raise UserError(
                    f"sweep.sun_elevation.values=[{values}]: two renders of {crater.name} would share the "
                    f"file {plan['rel_path']} (angles are named to 0.001 deg): space the values further apart"
                )
            names[plan["rel_path"]] = key
            plan["seed"] = render_seed(s.seed, key)
            plan["digest"] = digest
            plan["row"] = planned_row(crater.name, meta["terrain_id"], plan, grid.fov_deg, s.render.mode)
            planned.append((job, key, plan))
        jobs.append(job)
    return jobs, planned, names


def _sort_proved(s: Settings, grid, out_dir: Path, planned, existing: dict) -> tuple[int, list[dict]]:
    """Give every planned render whose file is not proved a worker item (it is rendered); count those
    proved with their manifest row intact, and return the rows rebuilt from the other proved files."""
    skipped, recovered = 0, []
    for job, key, plan in planned:
        row = existing.get(key)
        try:  # a link out of the dataset is never taken as a done render (schema.row_file refuses it)
            f = schema.row_file(out_dir, {"path": plan["rel_path"]})
            proved = prove(f, plan["row"], row) if f.is_file() else None
        except schema.ManifestError:
            proved = None
        if proved is None:
            plan["item"] = worker_item(job.crater, job.meta, plan, s.render, s.hapke, grid.fov_deg)
            job.plans.append(plan)
        elif row is not None and schema.dumps_row(row) == schema.dumps_row(proved):
            skipped += 1
        else:
            recovered.append(proved)
    return skipped, recovered


def _prune_manifest(out_dir: Path, existing: dict, planned, names: dict, recovered: list, exclusive: bool) -> None:
    """With the dataset to itself, keep in the manifest only rows proved now and those of renders outside
    this sweep (another shard, a larger grid) that name no planned file."""
    planned_keys = {key for _, key, _ in planned}
    kept = {k for k, r in existing.items() if k not in planned_keys and r["path"] not in names}
    kept |= {key for _, key, plan in planned if "item" not in plan and existing.get(key) is not None}
    kept -= {schema.row_key(r) for r in recovered}
    if exclusive and (out_dir / schema.MANIFEST_NAME).exists():
        # A wrong, stale or edited row is gone before rendering starts, even if this run is stopped.
        schema.merge_parts(out_dir, parts=[], keep=kept)


def _render_jobs(
    s: Settings, jobs, todo: int, out_dir: Path, shard, recovered: list, progress: bool, warn, state: dict
):
    """Record the recovered rows, render every job's plans and merge the rows into the manifest (the rows
    rendered so far as well when stopped): (manifest rows, renders done, paths of all-black renders,
    seconds)."""
    part = part_file(out_dir, shard)
    bar = Progress(todo, f"rendering ({s.render.mode})", "render", mode="auto" if progress and todo else "off")
    dark = []
    rows = schema.RowAppender(part)  # each row written at once, fsynced per 256 rows / 2 s
    for row in recovered:  # proved from their files: recorded, not rendered
        rows.add(row)
    if recovered and warn is not None:
        warn(
            f"recovered {len(recovered)} manifest row(s) of {out_dir} from their EXR files (header and "
            "pixel seal): not rendered again"
        )
    t0 = time.perf_counter()

    def on_result(job: CraterJob, plan: dict, result: dict):
        row = manifest_row(plan, result)
        rows.add(row)
        if row["lit_fraction"] <= 0.0:
            dark.append(row["path"])
        bar.update(1)

    state["dispatched"] = True
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
    return schema.merge_parts(out_dir, parts=[part]), dark, elapsed


def _build_locked(
    s: Settings, grid, indices, shard, out_dir: Path, progress: bool, warn, exclusive: bool, state: dict
) -> dict:
    existing = _existing_rows(out_dir)
    craters = s.craters
    # Early, cheap disk check (before terrain and per-render planning, which a huge sweep makes slow):
    # at least this many renders are left even if every existing row belongs to this run.
    n_left = max(0, len(indices) * len(craters) - len(existing))
    check_sweep_disk(out_dir, n_left, s.render, grid, list(existing.values()))
    jobs, planned, names = _plan_sweep(s, grid, indices)
    removed = remove_interrupted_writes(out_dir, set(names), exclusive)
    if removed and warn is not None:
        warn(f"removed {len(removed)} temp file(s) of interrupted writes from {out_dir}, e.g. {removed[0]}")
    skipped, recovered = _sort_proved(s, grid, out_dir, planned, existing)
    _prune_manifest(out_dir, existing, planned, names, recovered, exclusive)
    left = unplanned_files(out_dir, list(existing.values()), set(names))
    if left and warn is not None:
        warn(
            f"left {len(left)} file(s) alone that no manifest row and no planned render names, e.g. {left[0]} "
            "(crater-synth deletes only files it planned)"
        )
    todo = sum(len(j.plans) for j in jobs)
    check_planned_disk(out_dir, [p["crop"] for j in jobs for p in j.plans], list(existing.values()))
    n_rows, dark, elapsed = _render_jobs(s, jobs, todo, out_dir, shard, recovered, progress, warn, state)
    if dark and warn is not None:
        warn(
            f"{len(dark)} of {todo} new renders are entirely in shadow (lit_fraction 0, all black), e.g. "
            f"{out_dir / dark[0]}: check sweep.sun_elevation and the crater's latitude"
        )
    return {
        "dataset": str(out_dir),
        "renders_total": len(planned),
        "rendered": todo,
        "skipped_existing": skipped,
        "recovered": len(recovered),
        "manifest_rows": n_rows,
        "seconds": round(elapsed, 2),
        "renders_per_s": round(todo / elapsed, 3) if todo and elapsed > 0 else None,
        "craters": [c.name for c in craters],
        "mode": s.render.mode,
    }
