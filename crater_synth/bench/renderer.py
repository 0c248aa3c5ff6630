"""``crater-synth bench --part renderer``: the renderer's throughput and accuracy, measured end to end.

Every part renders through the real pipeline (``crater_synth.dataset.build_dataset``: the project's
sweep grid, planner, Hapke and render config, worker processes, manifest) into its own directory,
with its own cold horizon-map cache, so each rate includes everything a user would wait for except
building the terrain patches (cached data, built before the clock starts):

- (a) ``paper_crater``: one whole paper crater, Shackleton, 150 suns x 150 cameras = 22,500 renders;
- (b) ``demo``: ``sweep=demo`` (3 craters x 288);
- (c) ``grid``: 60 sun directions x 24 camera poses per crater (3 x 1,440), a grid with many suns and
  few cameras;
- (d) ``direct_roi``: direct mode (one Cycles render per image, ROI crop) on a sample of (a)'s items;
  the same items of (a) are compared with it per pixel (fast-vs-direct accuracy on real terrain);
- (e) ``naive``: direct mode rendering the whole 90 deg frame (crop afterwards), 6 items;
- peak RSS of the host process and of the largest worker process;
- the EXR storage choices (compression x channel types, through OpenImageIO) and the project's own
  encoder (crater_core.exr.encoder) on 40 of (a)'s renders: bytes and encode ms.

The last two lines are exactly
``paper_crater_renders_per_s=A demo_renders_per_s=B grid_renders_per_s=C direct_roi_renders_per_s=D`` and
``renders_per_s=X naive_renders_per_s=Y ratio=Z`` (X = A, the production rate on a paper crater).

Also holds the synthetic bowl crater the renderer tests use as a DEM stand-in (:func:`bowl_crater_z`).
"""

from __future__ import annotations

import json
import os
import re
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from crater_core import exr, schema
from crater_synth.config import compose, craters
from crater_synth.dataset import build_dataset
from crater_synth.terrain.patch import build_terrain

PAPER_CRATER = ["crater=shackleton", "sweep=paper", "render.mode=fast"]
DEMO = ["sweep=demo", "render.mode=fast"]
GRID = [
    "sweep=demo",
    "sweep.name=mid",
    "sweep.sun_elevation.count=10",
    "sweep.cam_elevation.count=4",
    "render.mode=fast",
]
# A sample of (a)'s items: 2 sun elevations x 1 azimuth x 3 camera elevations x 2 azimuths = 12.
SAMPLE = [
    "crater=shackleton",
    "sweep=paper",
    "sweep.sun_elevation.values=[0.48,1.28]",
    "sweep.sun_azimuth.values=[48.0]",
    "sweep.cam_elevation.values=[90.0,70.0,54.0]",
    "sweep.cam_azimuth.values=[0.0,120.0]",
]
DIRECT_ROI = SAMPLE + ["render.mode=direct"]
# Naive baseline: whole 90 deg frame, direct mode, one render call per image.
NAIVE = [
    "crater=shackleton",
    "sweep=paper",
    "render.mode=direct",
    "render.crop_to_roi=false",
    "sweep.sun_elevation.values=[1.6]",
    "sweep.sun_azimuth.values=[0.0]",
    "sweep.cam_elevation.values=[90.0,70.0,54.0]",
    "sweep.cam_azimuth.values=[0.0,120.0]",
]
PARTS = {"paper_crater": PAPER_CRATER, "demo": DEMO, "grid": GRID, "direct_roi": DIRECT_ROI, "naive": NAIVE}
_STATS = re.compile(r"^STATS (\{.*\})$", re.M)


def bowl_crater_z(diameter_m: float):
    """Height function z(x, y) of a bowl crater (depth 0.2 D, raised rim 0.04 D; Pike 1977 fresh simple
    crater proportions) with gentle undulations: a stand-in for a DEM in the renderer tests."""
    radius = diameter_m / 2.0

    def z(x, y):
        r = np.hypot(x, y) / radius
        bowl = np.where(
            r < 1.0, 0.2 * diameter_m * (r**2 - 1.0) + 0.04 * diameter_m, 0.04 * diameter_m * np.exp(-3.0 * (r - 1.0))
        )
        return bowl + 0.003 * diameter_m * np.sin(x / (0.033 * diameter_m)) * np.cos(y / (0.043 * diameter_m))

    return z


def worker_stats(dataset_dir: Path) -> list[dict]:
    """The STATS line each Blender worker wrote at the end of its log."""
    out = []
    for log in sorted((dataset_dir / ".jobs").glob("*.log")):
        out += [json.loads(m.group(1)) for m in _STATS.finditer(log.read_text(errors="replace"))]
    return out


def stage_summary(stats: list[dict]) -> dict:
    """Per-stage worker time (s, summed over workers) and per-render ms: where the time went."""
    n = sum(s["renders"] for s in stats) or 1
    fast = [s["fast"] for s in stats if "fast" in s]
    out = {
        "workers": len(stats),
        "setup_s": round(sum(s["setup_s"] for s in stats), 2),
        "exr_write_ms_per_render": round(1e3 * sum(s["exr_write_s"] for s in stats) / n, 2),
    }
    if fast:
        out.update(
            {
                "horizon_maps": sum(f["horizon_maps"] for f in fast),
                "horizon_s": round(sum(f["horizon_s"] for f in fast), 2),
                "gbuffers": sum(f["gbuffers"] for f in fast),
                "gbuffer_s": round(sum(f["gbuffer_s"] for f in fast), 2),
                "shade_ms_per_render": round(1e3 * sum(f["shade_s"] for f in fast) / n, 2),
                "fallbacks": sum(f["fallbacks"] for f in fast),
            }
        )
    else:
        out["cycles_s_per_render"] = round(sum(s["cycles_s"] for s in stats) / n, 3)
    return out


def timed_dataset(overrides: list[str], out_dir: Path) -> dict:
    """Render ``overrides`` into ``out_dir`` (terrain built first, untimed) with a cold horizon cache."""
    cfg = compose(overrides + [f"out_dir={out_dir}", f"render.horizon_cache_dir={out_dir / 'horizon-cache'}"])
    for crater in craters(cfg):
        build_terrain(crater, cfg)
    t0 = time.perf_counter()
    summary = build_dataset(cfg, progress=False)
    seconds = time.perf_counter() - t0
    return {
        "renders": summary["rendered"],
        "seconds": round(seconds, 2),
        "renders_per_s": round(summary["rendered"] / seconds, 3) if seconds > 0 else None,
        "stages": stage_summary(worker_stats(out_dir)),
    }


def compare(reference_dir: Path, test_dir: Path) -> dict:
    """Per-pixel agreement of ``test_dir``'s EXRs with ``reference_dir``'s (same manifest paths)."""
    rows = []
    for ref in schema.dataset_rows(reference_dir):
        path = test_dir / ref["path"]
        if not path.is_file():
            continue
        a, _ = exr.read_exr(reference_dir / ref["path"])
        b, _ = exr.read_exr(path)
        d_if, f_if = a["IF"], b["IF"]
        lit_px = d_if[a["lit"] > 0.5]
        med = float(np.median(lit_px)) if lit_px.size else float(d_if.mean())
        diff = np.abs(d_if - f_if)
        rows.append(
            {
                "path": ref["path"],
                "rel_mean": round(float(f_if.mean() / max(d_if.mean(), 1e-12) - 1.0), 5),
                "mad_over_median": round(float(diff.mean() / med), 5),
                "frac_gt_10pct": round(float((diff > 0.1 * med).mean()), 5),
                "lit_mad": round(float(np.abs(a["lit"] - b["lit"]).mean()), 5),
            }
        )
    if not rows:
        return {"renders": 0}
    agg = {
        k: round(float(np.mean([abs(r[k]) for r in rows])), 5)
        for k in ("rel_mean", "mad_over_median", "frac_gt_10pct", "lit_mad")
    }
    agg["max_abs_rel_mean"] = round(float(max(abs(r["rel_mean"]) for r in rows)), 5)
    agg["max_mad_over_median"] = round(float(max(r["mad_over_median"] for r in rows)), 5)
    return {"renders": len(rows), "mean_over_renders": agg, "per_render": rows}


# EXR storage choices compared on real renders: (compression, stored channel types); "contract" is
# crater_core.schema.EXR_CHANNEL_TYPES (half normals and lit), "float32" is every channel float32.
EXR_CHOICES = [
    ("zip", "float32"),
    ("rle", "float32"),
    ("none", "float32"),
    ("zip", "contract"),
    ("rle", "contract"),
    ("pxr24", "float32"),
]


def _encode_cost(encode, images: list[dict[str, np.ndarray]], scratch_dir: str, repeats: int) -> tuple[int, float]:
    """(mean bytes, best-of-``repeats`` mean seconds) of ``encode(path, arrays)`` over ``images``."""
    best, size = float("inf"), 0
    for _ in range(repeats):
        size, t0 = 0, time.perf_counter()
        for i, arrays in enumerate(images):
            path = os.path.join(scratch_dir, f"crater-synth-codec-{os.getpid()}-{i}.exr")
            encode(path, arrays)
            size += os.path.getsize(path)
            os.unlink(path)
        best = min(best, (time.perf_counter() - t0) / len(images))
    return round(size / len(images)), best


def exr_codecs(dataset_dir: Path, n: int = 40, repeats: int = 3) -> list[dict]:
    """Mean bytes and CPU ms to encode one EXR, for each of :data:`EXR_CHOICES` (through OpenImageIO)
    and for the project's own encoder (:func:`crater_core.exr.encoder`), on ``n`` renders of
    ``dataset_dir`` (spread over its manifest); the encoding alone (to /dev/shm or a temp dir), best of
    ``repeats`` passes, so the figures compare codecs, not disks."""
    rows = schema.load_manifest(dataset_dir)
    rows = rows[:: max(1, len(rows) // n)][:n]
    images = [exr.read_exr(dataset_dir / r["path"])[0] for r in rows]
    contract = [{c: img[c].astype(exr.stored_dtype(c)) for c in schema.EXR_CHANNELS} for img in images]
    float32 = [{c: img[c].astype(np.float32) for c in schema.EXR_CHANNELS} for img in images]
    scratch_dir = "/dev/shm" if os.path.isdir("/dev/shm") else tempfile.gettempdir()
    project = exr.encoder()
    out = []
    for compression, types in EXR_CHOICES:

        def encode(path, arrays, compression=compression):
            exr._encode_oiio(path, arrays, {}, exr.TILE, compression)

        size, seconds = _encode_cost(encode, contract if types == "contract" else float32, scratch_dir, repeats)
        current = compression == exr.COMPRESSION and types == "contract" and project is exr._encode_oiio
        out.append(
            {
                "compression": compression,
                "channel_types": types,
                "library": "OpenImageIO",
                "current": current,
                "mean_bytes": size,
                "encode_ms": round(1e3 * seconds, 2),
            }
        )
    size, seconds = _encode_cost(
        lambda path, arrays: project(path, arrays, {}, exr.TILE), contract, scratch_dir, repeats
    )
    out.append(
        {
            "compression": exr.COMPRESSION,
            "channel_types": "contract",
            "library": "OpenEXR" if project is exr._encode_openexr else "OpenImageIO",
            "current": True,
            "mean_bytes": size,
            "encode_ms": round(1e3 * seconds, 2),
        }
    )
    return out


def bench_renderer(overrides: list[str], work: Path, parts=tuple(PARTS)) -> dict:
    """Run the parts, in order, each into ``work/<part>``; returns the report."""
    report: dict = {}
    for name in parts:
        report[name] = timed_dataset(PARTS[name] + list(overrides), work / name)
        if name == "paper_crater":  # measured right away, while nothing else runs
            report["exr_codecs"] = exr_codecs(work / name)
    if "direct_roi" in report and "paper_crater" in report:
        report["fast_vs_direct"] = compare(work / "direct_roi", work / "paper_crater")
    # ru_maxrss is in KiB on Linux; RUSAGE_CHILDREN reports the largest terminated child (a worker).
    report["peak_rss_mb"] = {
        "host": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "worker": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, 1),
    }
    return report


def summary_lines(report: dict) -> list[str]:
    def rate(part):
        return report.get(part, {}).get("renders_per_s")

    a, naive = rate("paper_crater"), rate("naive")
    ratio = round(a / naive, 2) if a and naive else None
    return [
        f"paper_crater_renders_per_s={a} demo_renders_per_s={rate('demo')} grid_renders_per_s={rate('grid')} "
        f"direct_roi_renders_per_s={rate('direct_roi')}",
        f"renders_per_s={a} naive_renders_per_s={naive} ratio={ratio}",
    ]
