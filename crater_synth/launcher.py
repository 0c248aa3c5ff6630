"""Distributed sweep on Dask (``launcher=dask``): deterministic shards, one task per shard.

Each task runs :func:`crater_synth.dataset.build_dataset` for ``launcher.shard=i/n`` inside a Dask
worker process; that in turn runs one Blender worker subprocess (bpy imported once per process).
Shards write their own manifest parts and merge them under a lock; the launcher merges whatever
parts remain (e.g. of a task whose worker was killed) at the end. A task whose worker dies is
rescheduled by Dask (``launcher.retries``) and resumes: renders whose row and file hash exist are
skipped. The dataset directory must be on a filesystem all workers share.

Every check that needs no rendering runs once on the host before any cluster starts
(:func:`preflight`), and a bad-input error inside a task is returned, not raised, so Dask does not
retry it: a bad configuration ends with one ``error:`` line. Scaling model and multi-node recipe:
docs/distributed.md; :func:`bench_distributed` measures it.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from crater_core import schema
from crater_core.errors import ContractError
from crater_core.sweep import grid_from_config
from crater_synth.config import ConfigError, resolved
from crater_synth.errors import UserError


def _render_shard(cfg_yaml: str, shard_index: int, shard_count: int) -> dict:
    """Task body: render one shard (runs in a Dask worker process).

    Bad input (a :class:`UserError` or :class:`ContractError` other than a render failure) is
    returned as ``{"error": message}``: retrying it on another worker cannot help. A
    :class:`~crater_synth.dataset.RenderError` (a Blender worker kept dying) is raised, so Dask
    retries the task elsewhere."""
    from crater_synth.dataset import RenderError, build_dataset

    cfg = OmegaConf.create(cfg_yaml)
    OmegaConf.update(cfg, "launcher.shard", f"{shard_index}/{shard_count}")
    OmegaConf.update(cfg, "render.workers", 1)
    try:
        return build_dataset(cfg, progress=False)
    except RenderError:
        raise
    except (UserError, ContractError) as exc:
        return {"error": str(exc)}


def shard_count(cfg_r: dict) -> int:
    launcher = cfg_r["launcher"]
    n = launcher.get("shards") or 4 * int(launcher.get("n_workers", 2))
    if int(n) < 1:
        raise ConfigError(f"launcher.shards={n}: must be >= 1")
    return int(n)


def _absolute_cfg(cfg: DictConfig) -> tuple[dict, DictConfig]:
    """(resolved dict, plain config) with out_dir and data_dir made absolute, so every task on every
    node sees identical paths and values."""
    cfg_r = resolved(cfg)
    plain = OmegaConf.create(cfg_r)
    OmegaConf.update(plain, "out_dir", str(Path(cfg_r["out_dir"]).resolve()))
    OmegaConf.update(plain, "data_dir", str(Path(cfg_r["data_dir"]).resolve()))
    return resolved(plain), plain


def preflight(cfg: DictConfig) -> dict:
    """Every check :func:`build_dataset` makes before rendering, run once on the host before a cluster
    starts: render and Hapke values, sweep grid, craters (and their DEM coverage: the terrain patches
    are built here, so tasks reuse them instead of racing to build them), output directory, free disk.
    Returns ``{"renders_total", "craters", "shards"}``."""
    from crater_synth.config import craters as selected_craters
    from crater_synth.dataset import (
        check_free_disk,
        check_output_dir,
        hapke_params,
        measured_bytes_per_render,
        plan_render,
        validate_render_config,
    )
    from crater_synth.terrain import build_terrain

    cfg_r, plain = _absolute_cfg(cfg)
    validate_render_config(cfg_r["render"])
    hapke_params(cfg_r)
    grid = grid_from_config(cfg_r["sweep"])
    n_shards = shard_count(cfg_r)
    if not cfg_r["launcher"].get("address") and int(cfg_r["launcher"].get("n_workers", 2)) < 1:
        raise ConfigError(f"launcher.n_workers={cfg_r['launcher'].get('n_workers')}: must be >= 1")
    craters = selected_craters(plain)
    out_dir = Path(cfg_r["out_dir"])
    check_output_dir(out_dir)
    existing = schema.dataset_rows(out_dir)
    check_free_disk(out_dir, max(0, len(grid) * len(craters) - len(existing)),
                    measured_bytes_per_render(existing, out_dir))
    n_sun = grid.shape[0] * grid.shape[1]
    for crater in craters:
        _, meta = build_terrain(crater, plain)
        for index in range(n_sun and len(grid) // n_sun):  # every camera pose once: its ROI fits the frame
            plan_render(crater, meta, grid, index, int(cfg_r["render"]["roi_min_px"]))
    return {"renders_total": len(grid) * len(craters), "craters": [c["name"] for c in craters],
            "shards": n_shards}


def run_dask(cfg: DictConfig, progress: bool = True) -> dict:
    """Render the configured sweep on a Dask cluster (local on 127.0.0.1 unless ``launcher.address``)."""
    from distributed import Client, LocalCluster, as_completed
    from distributed.scheduler import KilledWorker

    from crater_synth.dataset import RenderError

    plan = preflight(cfg)  # bad values fail here, before any cluster starts
    cfg_r, plain = _absolute_cfg(cfg)
    launcher = cfg_r["launcher"]
    out_dir = Path(cfg_r["out_dir"])
    n_shards = plan["shards"]
    cfg_yaml = OmegaConf.to_yaml(plain)

    cluster = None
    t0 = time.perf_counter()
    try:
        if launcher.get("address"):
            client = Client(launcher["address"], timeout="30s")
        else:
            cluster = LocalCluster(n_workers=int(launcher.get("n_workers", 2)), threads_per_worker=1,
                                   processes=True, host="127.0.0.1", dashboard_address=None, silence_logs=40)
            client = Client(cluster)
    except OSError as exc:
        raise UserError(f"cannot reach Dask scheduler {launcher.get('address')}: {exc}") from None

    t_cluster = time.perf_counter() - t0
    try:
        workers = len(client.scheduler_info().get("workers", {}))
        if launcher.get("address") and not launcher.get("shards"):
            n_shards = 4 * max(1, workers)  # a remote cluster: n_workers describes the local one only
        futures = [client.submit(_render_shard, cfg_yaml, i, n_shards, key=f"render-shard-{i}-of-{n_shards}",
                                 retries=int(launcher.get("retries", 3)), pure=False)
                   for i in range(n_shards)]
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=n_shards, unit="shard", desc=f"dask sweep ({workers} workers)")
        rendered = skipped = 0
        try:
            for fut in as_completed(futures):
                try:
                    summary = fut.result()
                except KilledWorker as exc:
                    raise RenderError(f"Dask task {fut.key} killed its worker process repeatedly "
                                      f"(distributed.scheduler.allowed-failures): {exc}") from None
                if "error" in summary:
                    raise UserError(summary["error"])
                rendered += summary["rendered"]
                skipped += summary["skipped_existing"]
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(renders=rendered, per_s=f"{rendered / (time.perf_counter() - t0):.2f}")
        finally:
            if bar is not None:
                bar.close()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    n_rows = schema.merge_parts(out_dir)
    elapsed = time.perf_counter() - t0
    return {"dataset": str(out_dir), "launcher": "dask", "workers": workers, "shards": n_shards,
            "rendered": rendered, "skipped_existing": skipped, "manifest_rows": n_rows,
            "seconds": round(elapsed, 2), "cluster_start_s": round(t_cluster, 2),
            "renders_per_s": round(rendered / elapsed, 3) if rendered else None}


# ------------------------------------------------------------------------------------------------
# Benchmark: Dask path vs single process on the same sweep
# ------------------------------------------------------------------------------------------------
_WORKER_DONE = re.compile(r"\] (\d+) renders in ([0-9.]+) s .*?; (\d+) Cycles calls \(([0-9.]+) s\)")
_SCENE_READY = re.compile(r"scene ready in ([0-9.]+) s")


def _worker_logs(out_dir: Path) -> dict:
    """Totals over a dataset's Blender worker logs: processes, scene-build and render seconds."""
    stats = {"processes": 0, "scene_s": 0.0, "renders": 0, "render_s": 0.0, "cycles_calls": 0, "cycles_s": 0.0}
    for log in sorted((out_dir / ".jobs").glob("*.log")):
        text = log.read_text(errors="replace")
        for m in _SCENE_READY.finditer(text):
            stats["processes"] += 1
            stats["scene_s"] += float(m.group(1))
        for m in _WORKER_DONE.finditer(text):
            stats["renders"] += int(m.group(1))
            stats["render_s"] += float(m.group(2))
            stats["cycles_calls"] += int(m.group(3))
            stats["cycles_s"] += float(m.group(4))
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in stats.items()}


def _worker_start_seconds(plain: DictConfig, work: Path) -> float:
    """Wall time of a Blender worker process with an empty job: interpreter + bpy import + scene build
    (the fixed cost every shard pays once), median of 3."""
    from crater_synth.config import craters as selected_craters
    from crater_synth.dataset import worker_command
    from crater_synth.terrain import build_terrain

    cfg_r = resolved(plain)
    crater = selected_craters(plain)[0]
    npz, meta = build_terrain(crater, plain)
    job = work / "empty-job.json"
    job.write_text(json.dumps({"terrain_npz": str(npz), "terrain_meta": meta, "crater": crater,
                               "hapke": cfg_r["hapke"], "render": cfg_r["render"], "out_dir": str(work),
                               "renders": []}))
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        subprocess.run(worker_command(job), check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    return sorted(times)[1]


def bench_distributed(cfg: DictConfig, work_dir: str | Path | None = None) -> dict:
    """Renders/s of the Dask path (local cluster of ``launcher.n_workers`` worker processes,
    ``launcher.shards`` shards) vs the single-process path (``build_dataset``, one Blender worker) for the
    same sweep, each into a fresh directory under ``work_dir`` (default: a new temp dir). Terrain is
    built before timing. Also measures the inputs of the scaling model in docs/distributed.md: the
    fixed cost of a Blender worker process (bpy import + scene build), the steady per-render time, the
    Dask cluster start, and checks that both paths wrote byte-identical manifests."""
    from crater_synth.dataset import build_dataset

    work = Path(work_dir) if work_dir else Path(tempfile.mkdtemp(prefix="crater-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    base = OmegaConf.create(resolved(cfg))
    OmegaConf.update(base, "launcher.shard", None)
    runs = {}
    for name in ("single", "dask"):
        OmegaConf.update(base, "out_dir", str(work / name))
        runs[name] = OmegaConf.create(resolved(base))
    plan = preflight(runs["single"])  # builds the terrain, outside the timings

    t0 = time.perf_counter()
    build_dataset(runs["single"], progress=False)
    t_single = time.perf_counter() - t0
    t0 = time.perf_counter()
    dask = run_dask(runs["dask"], progress=False)
    t_dask = time.perf_counter() - t0

    n = plan["renders_total"]
    worker_start = _worker_start_seconds(runs["single"], work)
    logs_single, logs_dask = _worker_logs(work / "single"), _worker_logs(work / "dask")
    per_render = logs_single["render_s"] / max(1, logs_single["renders"])
    w, s = dask["workers"], dask["shards"]
    nonempty = min(s, n)
    # Scaling model (docs/distributed.md): cluster start + the busiest worker's shard start-ups + its
    # renders. The single-process render time used every core of this machine; the local cluster's
    # workers share those cores, so each renders w times slower (a worker per node would not).
    same_node = 1 if resolved(cfg)["launcher"].get("address") else w
    model_dask = dask["cluster_start_s"] + math.ceil(nonempty / w) * worker_start + n * per_render * same_node / w
    # What a shard really cost beyond its renders, from the Dask run itself (start-up under contention,
    # scheduling, terrain load, manifest merge): per worker, (wall - cluster start) = its shards' overhead
    # + its renders.
    observed = ((t_dask - dask["cluster_start_s"]) * w - logs_dask["render_s"]) / max(1, nonempty)
    same = (work / "single" / schema.MANIFEST_NAME).read_bytes() == (work / "dask" / schema.MANIFEST_NAME).read_bytes()
    return {
        "renders": n, "work_dir": str(work),
        "single": {"seconds": round(t_single, 2), "renders_per_s": round(n / t_single, 3),
                   "worker_logs": logs_single},
        "dask": {"workers": w, "shards": s, "seconds": round(t_dask, 2), "renders_per_s": round(n / t_dask, 3),
                 "cluster_start_s": dask["cluster_start_s"], "worker_logs": logs_dask},
        "speedup_dask_over_single": round(t_single / t_dask, 3),
        "model": {"worker_start_s": round(worker_start, 3), "per_render_s": round(per_render, 4),
                  "renders_per_s_per_worker_steady": round(1.0 / per_render, 2) if per_render > 0 else None,
                  "predicted_dask_s": round(model_dask, 2), "shard_overhead_observed_s": round(observed, 3)},
        "identical_manifests": same,
    }


if __name__ == "__main__":  # python -m crater_synth.launcher [OVERRIDES]...  (prints the benchmark JSON)
    from crater_synth.config import compose

    print(json.dumps(bench_distributed(compose(sys.argv[1:] or ["sweep=smoke", "crater=shackleton"])), indent=1))
