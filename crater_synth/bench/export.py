"""``crater-synth bench --part export``: export time and peak RSS, extrapolated to the paper sweep.

The dataset is GENERATED, not rendered: ``n`` EXRs with the channels, types, tiling and compression
of a real render (crater_core.exr.write_exr) at the paper crater's ROI size (212 x 212 px), filled
with seeded noise so that the RLE compression gains nothing (~ the 480 kB of a real render; the
worst case for I/O), and schema-valid manifest rows. Each export runs in its own process, which
reports its own peak RSS. Export time is linear in the number of samples (each is read, checked,
encoded and appended once), so the 67,500-render time is ``seconds * 67500 / n``; peak RSS does not
grow with ``n`` (one Parquet row group or one sample in memory), which the run shows twice: the
largest RSS seen in the second half of each export against the first half, and a quarter-size export.
The baseline in the same run is a plain tar of the same EXRs and manifest (``baseline_tar``).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from crater_core.exr import sealed_header, write_exr
from crater_core.render_labels import header_for_row
from crater_core.schema import SCHEMA_VERSION, render_rel_path, write_manifest

PAPER_RENDERS = 67_500
ROI_PX = 212


def make_dataset(out: Path, n: int, seed: int = 0) -> Path:
    """``n`` synthetic renders (EXR + manifest row) in ``out``; returns ``out``."""
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    s = ROI_PX
    for i in range(n):
        se, sa, ce, ca = 0.1 + (i % 15) * 0.1, float(i // 15 % 150) * 2.4, 45.0 + i // 2250 % 30, float(i % 7)
        rel = render_rel_path("bench", se, sa, ce, ca)
        n_ = rng.normal(size=(3, s, s)).astype(np.float32)
        n_ /= np.linalg.norm(n_, axis=0)
        chans = {
            "IF": rng.random((s, s), dtype=np.float32) * 0.05,
            "depth": 30000.0 + rng.random((s, s), dtype=np.float32) * 5000.0,
            "N.X": n_[0],
            "N.Y": n_[1],
            "N.Z": n_[2],
            "lit": rng.random((s, s), dtype=np.float32),
        }
        half = s / 2 / 1.4
        row = {
            "schema_version": SCHEMA_VERSION,
            "crater": "bench",
            "index": i,
            "indices": [i % 15, i // 15 % 150, i // 2250 % 30, i % 7],
            "sun_elevation": se,
            "sun_azimuth": sa,
            "cam_elevation": ce,
            "cam_azimuth": ca,
            "range_m": 31500.0,
            "fov_deg": 90.0,
            "frame_width": 2 * s,
            "width": s,
            "height": s,
            "crop_origin": [s // 2, s // 2],
            "center_px": [s / 2, s / 2],
            "rim_ellipse": {"cu": s / 2, "cv": s / 2, "a": half, "b": half * 0.9, "angle_rad": 0.3},
            "sigma_boxes": {
                str(k): [s / 2 - k * half, s / 2 - k * half, s / 2 + k * half, s / 2 + k * half]
                for k in (1.0, 1.2, 1.4)
            },
            "lit_fraction": float(chans["lit"].mean()),
            "mean_if": float(chans["IF"].mean()),
            "path": rel,
            "sha256": "",
            "seed": i,
            "code_version": "bench",
            "renderer": "fast",
            "terrain_id": "bench",
            "render_digest": "bench",
        }
        # Labels in the header and a seal, as the renderer writes them: export checks both.
        row["sha256"] = write_exr(out / rel, chans, sealed_header(chans, header_for_row(row)))
        rows.append(row)
    write_manifest(out / "manifest.jsonl", rows)
    return out


_CHILD = """
import json, resource, sys, time
import pyarrow.parquet  # imported before the clock starts: the time is the export's, linear in the samples
from crater_synth.dataset.export import export_dataset
ds, out, fmt, chans = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4].split(",")
trace = []  # (samples done, current RSS in MiB, as ru_maxrss / 1024) at each progress report
def tick(done, total):
    trace.append((done, int(open("/proc/self/statm").read().split()[1]) * resource.getpagesize() / 2**20))
t0 = time.perf_counter()
idx = export_dataset(ds, out, fmt, channels=chans, overwrite=True, progress=tick)
half = idx["rows"] / 2
print(json.dumps({"seconds": time.perf_counter() - t0, "rows": idx["rows"],
                  "bytes": sum(s["bytes"] for s in idx["shards"]),
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "rss_first_half_mb": max([r for d, r in trace if d <= half] or [0]),
                  "rss_second_half_mb": max([r for d, r in trace if d > half] or [0])}))
"""


# The baseline a careful user would run instead of an export: one tar of the dataset's EXRs and manifest
# (``tar cf``; what WebDataset-style loaders read as is). It copies bytes only (no decoding, no checksum,
# no label columns), so it bounds what streaming the same files can cost on this disk.
_TAR_CHILD = """
import json, resource, sys, tarfile, time
from pathlib import Path
ds, out = Path(sys.argv[1]), Path(sys.argv[2])
out.mkdir(parents=True, exist_ok=True)
t0 = time.perf_counter()
with tarfile.open(out / "dataset.tar", "w") as tar:
    tar.add(ds / "manifest.jsonl", arcname="manifest.jsonl")
    files = sorted(ds.rglob("*.exr"))
    for p in files:
        tar.add(p, arcname=str(p.relative_to(ds)))
print(json.dumps({"seconds": time.perf_counter() - t0, "rows": len(files),
                  "bytes": (out / "dataset.tar").stat().st_size,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def _run(ds: Path, out: Path, fmt: str, channels: str) -> dict:
    return _child(_CHILD, str(ds), str(out), fmt, channels)


def _child(script: str, *args: str) -> dict:
    """Run ``script`` in a fresh interpreter (its own peak RSS) and return the JSON of its last line."""
    proc = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"export benchmark child failed: {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def bench_export(work: Path, n: int = 1000) -> dict:
    """Export a generated ``n``-render dataset as Parquet and as WebDataset (IF only, the default) and
    as Parquet with every channel; the same for ``n // 4`` renders (Parquet, IF) to show that peak RSS
    does not grow with the dataset. Returns the measurements and the paper-sweep extrapolation."""
    t0 = time.perf_counter()
    ds = make_dataset(work / "dataset", n)
    small = make_dataset(work / "dataset_quarter", max(n // 4, 1), seed=1)
    gen_s = time.perf_counter() - t0
    exr_bytes = sum(p.stat().st_size for p in (work / "dataset").rglob("*.exr"))
    runs = {
        "parquet_IF": _run(ds, work / "pq", "parquet", "IF"),
        "webdataset_IF": _run(ds, work / "wds", "webdataset", "IF"),
        "parquet_all": _run(ds, work / "pq_all", "parquet", "IF,depth,N.X,N.Y,N.Z,lit"),
        "parquet_IF_quarter": _run(small, work / "pq_q", "parquet", "IF"),
        "baseline_tar": _child(_TAR_CHILD, str(ds), str(work / "tar")),
    }
    out: dict = {"renders": n, "generate_seconds": round(gen_s, 2), "exr_mb_per_render": exr_bytes / n / 1e6}
    for name, r in runs.items():
        rows = r["rows"]
        out[name] = {
            "seconds": round(r["seconds"], 2),
            "renders_per_s": round(rows / r["seconds"], 1),
            "peak_rss_mb": round(r["peak_rss_mb"], 1),
            # the exports' RSS per half of their samples (the tar baseline reports none)
            "rss_first_half_mb": round(r["rss_first_half_mb"], 1) if "rss_first_half_mb" in r else None,
            "rss_second_half_mb": round(r["rss_second_half_mb"], 1) if "rss_second_half_mb" in r else None,
            "mb_per_render": round(r["bytes"] / rows / 1e6, 4),
        }
        if not name.endswith("quarter"):
            out[name]["paper_sweep_minutes"] = round(r["seconds"] * PAPER_RENDERS / rows / 60, 1)
            out[name]["paper_sweep_gb"] = round(r["bytes"] / rows * PAPER_RENDERS / 1e9, 1)
    base = out["baseline_tar"]["seconds"]
    for name in ("parquet_IF", "webdataset_IF", "parquet_all"):
        out[name]["seconds_vs_tar"] = round(out[name]["seconds"] / base, 2) if base > 0 else None
    return out


def summary_line(r: dict) -> str:
    """``export_renders_per_s=... export_peak_rss_mb=... paper_sweep_minutes=...`` (Parquet, IF)."""
    p = r["parquet_IF"]
    peak = max(v["peak_rss_mb"] for v in r.values() if isinstance(v, dict))
    return (
        f"export_parquet_renders_per_s={p['renders_per_s']} export_webdataset_renders_per_s="
        f"{r['webdataset_IF']['renders_per_s']} export_peak_rss_mb={peak} "
        f"paper_sweep_parquet_minutes={p['paper_sweep_minutes']} "
        f"tar_baseline_renders_per_s={r['baseline_tar']['renders_per_s']} parquet_vs_tar={p['seconds_vs_tar']}"
    )
