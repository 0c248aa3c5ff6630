"""Distributed sweep on Dask (``launcher=dask``): deterministic shards, one task per shard.

Each task runs :func:`crater_synth.dataset.build_dataset` for ``launcher.shard=i/n`` inside a Dask
worker process; that in turn runs one Blender worker subprocess (bpy imported once per process).
Shards write their own manifest parts and merge them under a lock; the launcher merges whatever
parts remain (e.g. of a task whose worker was killed) at the end. A task whose worker dies is
rescheduled by Dask (``launcher.retries``) and resumes: renders whose row and file hash exist are
skipped. The dataset directory must be on a filesystem all workers share.
"""

from __future__ import annotations

import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from crater_synth.config import ConfigError, resolved
from crater_synth.errors import UserError
from data_manifest import schema
from data_manifest.sweep import grid_from_config


def _render_shard(cfg_yaml: str, shard_index: int, shard_count: int) -> dict:
    """Task body: render one shard (runs in a Dask worker process)."""
    from crater_synth.dataset import build_dataset

    cfg = OmegaConf.create(cfg_yaml)
    OmegaConf.update(cfg, "launcher.shard", f"{shard_index}/{shard_count}")
    OmegaConf.update(cfg, "render.workers", 1)
    return build_dataset(cfg, progress=False)


def shard_count(cfg_r: dict) -> int:
    launcher = cfg_r["launcher"]
    n = launcher.get("shards") or 4 * int(launcher.get("n_workers", 2))
    if int(n) < 1:
        raise ConfigError(f"launcher.shards={n}: must be >= 1")
    return int(n)


def run_dask(cfg: DictConfig, progress: bool = True) -> dict:
    """Render the configured sweep on a Dask cluster (local on 127.0.0.1 unless ``launcher.address``)."""
    from distributed import Client, LocalCluster, as_completed

    from crater_synth.dataset import check_output_dir

    cfg_r = resolved(cfg)
    grid_from_config(cfg_r["sweep"])  # bad sweep values fail here, before any cluster starts
    launcher = cfg_r["launcher"]
    out_dir = Path(cfg_r["out_dir"]).resolve()
    check_output_dir(out_dir)
    n_shards = shard_count(cfg_r)
    # Resolve once on the host so every task sees identical absolute paths and values.
    plain = OmegaConf.create(cfg_r)
    OmegaConf.update(plain, "out_dir", str(out_dir))
    OmegaConf.update(plain, "data_dir", str(Path(cfg_r["data_dir"]).resolve()))
    cfg_yaml = OmegaConf.to_yaml(plain)

    cluster = None
    t0 = time.perf_counter()
    try:
        if launcher.get("address"):
            client = Client(launcher["address"], timeout="30s")
        else:
            n_workers = int(launcher.get("n_workers", 2))
            if n_workers < 1:
                raise ConfigError(f"launcher.n_workers={n_workers}: must be >= 1")
            cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                   host="127.0.0.1", dashboard_address=None, silence_logs=40)
            client = Client(cluster)
    except OSError as exc:
        raise UserError(f"cannot reach Dask scheduler {launcher.get('address')}: {exc}") from None

    try:
        workers = len(client.scheduler_info().get("workers", {}))
        futures = [client.submit(_render_shard, cfg_yaml, i, n_shards, key=f"render-shard-{i}-of-{n_shards}",
                                 retries=int(launcher.get("retries", 3)), pure=False)
                   for i in range(n_shards)]
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=n_shards, unit="shard", desc=f"dask sweep ({workers} workers)")
        rendered = skipped = 0
        for fut in as_completed(futures):
            summary = fut.result()
            rendered += summary["rendered"]
            skipped += summary["skipped_existing"]
            if bar is not None:
                bar.update(1)
                bar.set_postfix(renders=rendered, per_s=f"{rendered / (time.perf_counter() - t0):.2f}")
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
            "seconds": round(elapsed, 2), "renders_per_s": round(rendered / elapsed, 3) if rendered else None}
