"""``crater-synth bench`` / ``make bench``: the performance goals, measured (never asserted in tests).

Parts (``--part``, default all, in this order):
- ``distributed``: renders/s of the Dask path vs one process (crater_synth.launcher.bench_distributed);
- ``train``: LunarNet_ex training images/s and time to the validation target on the demo sweep
  (crater_synth.bench_train.run_train_bench; skipped with a note if that dataset is not rendered yet);
- ``renderer``: the project's renderer on the paper geometry at ROI resolution (fast mode, real
  Shackleton terrain, 10 sun directions x the 150 paper camera poses = 1,500 renders, sun-major, on
  ``render.workers`` processes) against the naive baseline (direct mode, one Cycles render per image of
  the whole 90 deg frame, cropped afterwards), in the same run. Also prints the throughput the measured
  stage times imply for a whole 22,500-render crater (lit maps shared by 150 cameras).

The last line is exactly ``renders_per_s=X naive_renders_per_s=Y ratio=Z``.
"""

from __future__ import annotations

import json
import re
import shutil
import tempfile
import time
from pathlib import Path

import click

from crater_synth.cli_common import OVERRIDES, user_errors

# Paper geometry: all 10 sun elevations at one azimuth, all 150 camera poses (one shard's worth of work).
RENDERER_OVERRIDES = ["crater=shackleton", "sweep=paper", "sweep.sun_azimuth.values=[0.0]", "render.mode=fast"]
# Naive baseline: the same geometry, whole 90 deg frame, direct mode, one render call per image.
NAIVE_OVERRIDES = ["crater=shackleton", "sweep=paper", "render.mode=direct", "render.crop_to_roi=false",
                   "sweep.sun_elevation.values=[1.6]", "sweep.sun_azimuth.values=[0.0]",
                   "sweep.cam_elevation.values=[90.0,70.0,54.0]", "sweep.cam_azimuth.values=[0.0,120.0]"]
_STATS = re.compile(r"^STATS (\{.*\})$", re.M)


def worker_stats(dataset_dir: Path) -> list[dict]:
    """The STATS line each Blender worker wrote at the end of its log."""
    out = []
    for log in sorted((dataset_dir / ".jobs").glob("*.log")):
        out += [json.loads(m.group(1)) for m in _STATS.finditer(log.read_text(errors="replace"))]
    return out


def implied_full_crater_rate(stats: list[dict], workers: int, n_suns: int = 150, n_cams: int = 150) -> float | None:
    """Renders/s for one whole paper crater from measured per-stage times: each of ``workers``
    processes renders n_suns/workers lit maps, all n_cams G-buffers and its share of the images."""
    fast = [s["fast"] for s in stats if "fast" in s]
    if not fast:
        return None
    lit = sum(f["lit_maps"] for f in fast)
    gbuf = sum(f["gbuffers"] for f in fast)
    renders = sum(s["renders"] for s in stats)
    if not (lit and gbuf and renders):
        return None
    t_lit = sum(f["lit_map_s"] for f in fast) / lit
    t_gbuf = sum(f["gbuffer_s"] for f in fast) / gbuf
    t_setup = sum(s["setup_s"] for s in stats) / len(stats)
    t_image = (sum(s["seconds"] - s["setup_s"] for s in stats) - sum(f["lit_map_s"] + f["gbuffer_s"] for f in fast)) / renders
    per_worker = t_setup + (n_suns / workers) * t_lit + n_cams * t_gbuf + (n_suns * n_cams / workers) * t_image
    return n_suns * n_cams / per_worker


def _timed_dataset(overrides: list[str], out_dir: Path) -> tuple[dict, float]:
    from crater_synth.config import compose
    from crater_synth.dataset import build_dataset
    from crater_synth.terrain import build_terrain
    from crater_synth.config import craters

    cfg = compose(overrides + [f"out_dir={out_dir}"])
    for crater in craters(cfg):  # terrain is cached data, not rendering: build it outside the timing
        build_terrain(crater, cfg)
    t0 = time.perf_counter()
    summary = build_dataset(cfg, progress=False)
    return summary, time.perf_counter() - t0


def bench_renderer(overrides: list[str], work: Path) -> dict:
    from crater_synth.config import compose, resolved

    workers = int(resolved(compose(overrides))["render"]["workers"])
    fast, t_fast = _timed_dataset(RENDERER_OVERRIDES + overrides, work / "fast")
    naive, t_naive = _timed_dataset(NAIVE_OVERRIDES + overrides, work / "naive")
    stats = worker_stats(work / "fast")
    rate = fast["rendered"] / t_fast
    naive_rate = naive["rendered"] / t_naive
    return {"renders": fast["rendered"], "seconds": round(t_fast, 2), "renders_per_s": round(rate, 3),
            "naive_renders": naive["rendered"], "naive_seconds": round(t_naive, 2),
            "naive_renders_per_s": round(naive_rate, 3), "ratio": round(rate / naive_rate, 2),
            "workers": workers, "implied_full_crater_renders_per_s":
                None if (r := implied_full_crater_rate(stats, workers)) is None else round(r, 2),
            "fast_stage_stats": [s.get("fast") for s in stats]}


@click.command("bench")
@click.option("--part", type=click.Choice(["all", "renderer", "train", "distributed"]), default="all",
              show_default=True)
@click.option("--keep", type=click.Path(file_okay=False), default=None,
              help="Keep the benchmark datasets in this directory (default: a temp dir, removed).")
@OVERRIDES
@user_errors
def bench_command(part, keep, overrides):
    """Measure the performance goals: renderer vs naive baseline, training, distributed sweep.

    Overrides apply to every part, e.g. ``crater-synth bench render.workers=2``. The last line is
    ``renders_per_s=X naive_renders_per_s=Y ratio=Z``.
    """
    from crater_synth.config import compose, resolved

    overrides = list(overrides)
    work = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="crater-synth-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        if part in ("all", "distributed"):
            from crater_synth.launcher import bench_distributed

            cfg = compose(["sweep=smoke", "crater=shackleton", "launcher=dask", *overrides])
            click.echo("distributed " + json.dumps(bench_distributed(cfg, work / "distributed")))
        if part in ("all", "train"):
            cfg = resolved(compose(["sweep=demo", "train.progress=false", *overrides]))
            dataset = Path(cfg["train"]["dataset_dir"]) / "manifest.jsonl"
            if dataset.is_file():
                from crater_synth.bench_train import run_train_bench

                click.echo("train " + json.dumps(run_train_bench(cfg)))
            else:
                click.echo(f"train skipped: no rendered dataset at {dataset.parent} (make demo, or "
                           f"make dataset OVERRIDES=sweep=demo, renders it)")
        if part in ("all", "renderer"):
            r = bench_renderer(overrides, work / "renderer")
            click.echo("renderer " + json.dumps(r))
            click.echo(f"renders_per_s={r['renders_per_s']} naive_renders_per_s={r['naive_renders_per_s']} "
                       f"ratio={r['ratio']}")
    finally:
        if not keep:
            shutil.rmtree(work, ignore_errors=True)
