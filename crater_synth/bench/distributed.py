"""``crater-synth bench --part distributed``: the Dask path against one process on the same sweep.

Measures the inputs of the scaling model in docs/distributed.md (a Blender worker's fixed start cost,
the steady per-render time, the Dask cluster start) and checks that both paths write byte-identical
manifests.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Mapping

from crater_core import schema
from crater_core.settings import Settings, replace
from crater_synth.config import as_settings
from crater_synth.dataset import build_dataset, worker_command
from crater_synth.dataset.dask_launcher import preflight, run_dask
from crater_synth.dataset.plan import hapke_dict
from crater_synth.terrain.patch import build_terrain

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


def _worker_start_seconds(s: Settings, work: Path) -> float:
    """Wall time of a Blender worker process with an empty job: interpreter + bpy import + scene build
    (the fixed cost every shard pays once), median of 3."""
    crater = s.craters[0]
    npz, meta = build_terrain(crater, s)
    job = work / "empty-job.json"
    schema.atomic_write_text(
        job,
        json.dumps(
            {
                "terrain_npz": str(npz),
                "terrain_meta": meta,
                "crater": crater.as_dict(),
                "hapke": hapke_dict(s.hapke),
                "render": s.render.as_dict(),
                "out_dir": str(work),
                "renders": [],
            }
        ),
    )
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        subprocess.run(worker_command(job, s.render.blender), check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    return sorted(times)[1]


def bench_distributed(settings: Settings | Mapping, work_dir: str | Path | None = None) -> dict:
    """Renders/s of the Dask path (local cluster of ``launcher.n_workers`` worker processes,
    ``launcher.shards`` shards) vs the single-process path (``build_dataset``, one Blender worker) for the
    same sweep, each into a fresh directory under ``work_dir`` (default: a new temp dir). Terrain is
    built before timing. Also measures the inputs of the scaling model in docs/distributed.md: the
    fixed cost of a Blender worker process (bpy import + scene build), the steady per-render time, the
    Dask cluster start, and checks that both paths wrote byte-identical manifests."""
    s = as_settings(settings)
    work = Path(work_dir) if work_dir else Path(tempfile.mkdtemp(prefix="crater-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    runs = {name: replace(s, out_dir=str(work / name), **{"launcher.shard": None}) for name in ("single", "dask")}
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
    same_node = 1 if s.launcher.address else w
    model_dask = dask["cluster_start_s"] + math.ceil(nonempty / w) * worker_start + n * per_render * same_node / w
    # What a shard really cost beyond its renders, from the Dask run itself (start-up under contention,
    # scheduling, terrain load, manifest merge): per worker, (wall - cluster start) = its shards' overhead
    # + its renders.
    observed = ((t_dask - dask["cluster_start_s"]) * w - logs_dask["render_s"]) / max(1, nonempty)
    same = (work / "single" / schema.MANIFEST_NAME).read_bytes() == (work / "dask" / schema.MANIFEST_NAME).read_bytes()
    return {
        "renders": n,
        "work_dir": str(work),
        "single": {"seconds": round(t_single, 2), "renders_per_s": round(n / t_single, 3), "worker_logs": logs_single},
        "dask": {
            "workers": w,
            "shards": s,
            "seconds": round(t_dask, 2),
            "renders_per_s": round(n / t_dask, 3),
            "cluster_start_s": dask["cluster_start_s"],
            "worker_logs": logs_dask,
        },
        "speedup_dask_over_single": round(t_single / t_dask, 3),
        "model": {
            "worker_start_s": round(worker_start, 3),
            "per_render_s": round(per_render, 4),
            "renders_per_s_per_worker_steady": round(1.0 / per_render, 2) if per_render > 0 else None,
            "predicted_dask_s": round(model_dask, 2),
            "shard_overhead_observed_s": round(observed, 3),
        },
        "identical_manifests": same,
    }
