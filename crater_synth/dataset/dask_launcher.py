"""``launcher=dask``: the sweep rendered on a Dask cluster: deterministic shards, one task per shard, all
under the one dataset lock the host holds (:mod:`crater_synth.dataset.launcher` imports this module only
for ``launcher=dask``: Dask is the ``dask`` extra, docs/install.md).

Each Dask task runs :func:`crater_synth.dataset.build_dataset` for ``launcher.shard=i/n`` inside a Dask
worker process; that in turn runs one Blender worker subprocess (bpy imported once per process).
Shards write their own manifest parts and merge them under a lock; the launcher merges whatever
parts remain (e.g. of a task whose worker was killed) at the end. A task whose worker dies is
rescheduled by Dask (``launcher.retries``) and resumes: renders whose row and file hash exist are
skipped. The dataset directory must be on a filesystem all workers share.

Every check that needs no rendering runs once on the host before any cluster starts
(:func:`preflight`), and a bad-input error inside a task is returned, not raised, so Dask does not
retry it: a bad configuration ends with one ``error:`` line. Scaling model and multi-node recipe:
docs/distributed.md; :func:`crater_synth.bench.distributed.bench_distributed` measures it.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Mapping

from distributed import Client, LocalCluster, as_completed
from distributed.scheduler import KilledWorker

from crater_core import schema
from crater_core.errors import ContractError
from crater_core.files import ensure_writable_dir
from crater_core.progress import Progress
from crater_core.settings import Settings, replace
from crater_synth.config import as_settings
from crater_synth.dataset import build_dataset, plan_render
from crater_synth.dataset.disk import DatasetLock, check_sweep_disk
from crater_synth.dataset.marker import DatasetClaim
from crater_synth.errors import RenderError, UserError
from crater_synth.terrain.patch import build_terrain


def _render_shard(settings: Settings, shard_index: int, shard_count: int) -> dict:
    """Task body: render one shard (runs in a Dask worker process; the host holds the dataset lock).

    Bad input (a :class:`UserError` or :class:`ContractError` other than a render failure) is
    returned as ``{"error": message}``: retrying it on another worker cannot help. A
    :class:`~crater_synth.errors.RenderError` (a Blender worker kept dying) is raised, so Dask
    retries the task elsewhere."""
    s = replace(settings, **{"launcher.shard": f"{shard_index}/{shard_count}", "render.workers": 1})
    try:
        return build_dataset(s, progress=False, lock=False, warn=None)
    except RenderError:
        raise
    except (UserError, ContractError) as exc:
        return {"error": str(exc)}


def shard_count(s: Settings) -> int:
    return s.launcher.shards or 4 * s.launcher.n_workers


def _absolute(s: Settings) -> Settings:
    """The settings with out_dir and data_dir made absolute, so every task on every node sees identical
    paths."""
    return replace(s, out_dir=str(Path(s.out_dir).resolve()), data_dir=str(Path(s.data_dir).resolve()))


def preflight(settings: Settings | Mapping, claim: DatasetClaim | None = None) -> dict:
    """Every check :func:`build_dataset` makes before rendering, run once on the host before a cluster
    starts: output directory, free disk, craters and their DEM coverage (the terrain patches are built
    here, so tasks reuse them instead of racing to build them), every camera pose's ROI.
    ``claim`` (:class:`~crater_synth.dataset.marker.DatasetClaim`) remembers what creating the output
    directory created. Returns ``{"renders_total", "craters", "shards"}``."""
    s = _absolute(as_settings(settings))
    grid = s.sweep.grid
    ensure_writable_dir(s.data_dir, "data_dir")
    out_dir = Path(s.out_dir)
    (claim or DatasetClaim(out_dir)).create()  # refuses a directory that is neither empty nor a dataset
    existing = schema.dataset_rows(out_dir)
    check_sweep_disk(out_dir, max(0, len(grid) * len(s.craters) - len(existing)), s.render, grid, existing)
    n_sun = grid.shape[0] * grid.shape[1]
    for crater in s.craters:
        _, meta = build_terrain(crater, s)
        for index in range(n_sun and len(grid) // n_sun):  # every camera pose once: its ROI fits the frame
            plan_render(crater, meta, grid, index, s.render.roi_min_px)
    return {
        "renders_total": len(grid) * len(s.craters),
        "craters": [c.name for c in s.craters],
        "shards": shard_count(s),
    }


def run_dask(settings: Settings | Mapping, progress: bool = True) -> dict:
    """Render the configured sweep on a Dask cluster (local on 127.0.0.1 unless ``launcher.address``)."""
    s = _absolute(as_settings(settings))
    claim = DatasetClaim(Path(s.out_dir))
    try:
        plan = preflight(s, claim)  # bad values fail here, before any cluster starts
    except BaseException:
        claim.discard()  # refused: no litter
        raise
    with DatasetLock(Path(s.out_dir)):  # the tasks' shards write under this one lock
        claim.mark()
        return _run_dask_locked(s, plan, progress)


def completed_summaries(futures):
    """Each task's summary as it completes. A task returns bad input as ``{"error": ...}`` (so Dask does not
    retry it): that is one error line; a task that killed its worker process repeatedly is one too."""
    for fut in as_completed(futures):
        try:
            summary = fut.result()
        except KilledWorker as exc:
            raise RenderError(
                f"Dask task {fut.key} killed its worker process repeatedly "
                f"(distributed.scheduler.allowed-failures): {exc}"
            ) from None
        if "error" in summary:
            raise UserError(summary["error"])
        yield summary


def open_client(launcher) -> tuple[Client, LocalCluster | None]:
    """(client, its local cluster or None): a client of ``launcher.address``'s scheduler, or of a local
    cluster of ``launcher.n_workers`` single-threaded worker processes on 127.0.0.1. The caller closes both."""
    cluster = None
    try:
        if launcher.address:
            return Client(launcher.address, timeout="30s"), None
        cluster = LocalCluster(
            n_workers=launcher.n_workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            silence_logs=40,
        )
        return Client(cluster), cluster
    except OSError as exc:
        if cluster is not None:
            cluster.close()
        raise UserError(f"cannot reach Dask scheduler launcher.address={launcher.address}: {exc}") from None


def _run_dask_locked(s: Settings, plan: dict, progress: bool) -> dict:
    launcher = s.launcher
    out_dir = Path(s.out_dir)
    n_shards = plan["shards"]
    t0 = time.perf_counter()
    client, cluster = open_client(launcher)
    t_cluster = time.perf_counter() - t0
    try:
        workers = len(client.scheduler_info().get("workers", {}))
        if launcher.address and not launcher.shards:
            n_shards = 4 * max(1, workers)  # a remote cluster: n_workers describes the local one only
        futures = [
            client.submit(
                _render_shard,
                s,
                i,
                n_shards,
                key=f"render-shard-{i}-of-{n_shards}",
                retries=launcher.retries,
                pure=False,
            )
            for i in range(n_shards)
        ]
        rendered = skipped = 0
        with Progress(n_shards, f"dask sweep ({workers} workers)", "shard", "auto" if progress else "off") as bar:
            for summary in completed_summaries(futures):
                rendered += summary["rendered"]
                skipped += summary["skipped_existing"]
                bar.update(1, renders=rendered)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    n_rows = schema.merge_parts(out_dir)
    elapsed = time.perf_counter() - t0
    return {
        "dataset": str(out_dir),
        "launcher": "dask",
        "workers": workers,
        "shards": n_shards,
        "rendered": rendered,
        "skipped_existing": skipped,
        "manifest_rows": n_rows,
        "seconds": round(elapsed, 2),
        "cluster_start_s": round(t_cluster, 2),
        "renders_per_s": round(rendered / elapsed, 3) if rendered else None,
    }
