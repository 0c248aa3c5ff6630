"""``crater-synth bench --part detection-frames``: detection frames rendered per second (issue target: >= 10 frames/s at
256² on 2 cores).

At 256² and at 512², in one call and with the same settings (every override applies), it renders:

- ``grouped``: the default recipe (configs/detection/default.yaml: 64 frames a field, 4 Suns a camera, 4
  Sun azimuths a field), ``frames`` frames;
- ``per_frame``: the ungrouped path (:data:`PER_FRAME`: each frame its own field, worker start-up, scene,
  horizon map and G-buffer), ``per_frame_frames`` frames;

and reports end-to-end frames/s of each (field generation and patches, worker start-up, rendering,
labels: the command's own ``seconds``), their ratio, and the workers' breakdown from their STATS lines
(set-up, horizon maps, G-buffers, shading, EXR writing). A 512² frame 45° off nadir needs a larger field
than the default one (``procedural.size_px`` :data:`FIELD_PX_512`).

``manifest``: the manifest's cost at the last chunk of a :data:`MANIFEST_SET_FRAMES`-frame run, with the
256² grouped run's own rows (their real size) repeated: rewriting every row so far, as each chunk once
did, against appending the chunk's rows, as it does now; and both totals over the run (a rewrite costs
its bytes, so the rewrites' total is the last one's times half the chunks).
"""

from __future__ import annotations

import time
from pathlib import Path

from crater_core import schema
from crater_synth.bench.renderer import stage_summary, worker_stats
from crater_synth.config import load_settings
from crater_synth.dataset.detection import detection_overrides, manifest_rows
from crater_synth.dataset.detection_run import append_rows, render_detection_frames

FIELD_PX_512 = 1400  # check_field_fits: a 512 px frame at the grid's spacing, 45 deg off nadir
PER_FRAME = ("detection.views_per_field=1", "detection.suns_per_view=1", "detection.azimuths_per_field=0")
MANIFEST_SET_FRAMES = 4096  # a set's size for the manifest figure (its rewrite is held in memory whole)
MANIFEST_CHUNK_FRAMES = 256  # frames a chunk: 2 fields of 64 on each of 2 workers


def bench_manifest(rows: list[dict], work: Path, frames: int = MANIFEST_SET_FRAMES) -> dict:
    """The manifest's cost per chunk and per run, rewritten after every chunk against appended (module
    docstring), at the size of ``rows``."""
    chunk = MANIFEST_CHUNK_FRAMES
    many = [rows[i % len(rows)] | {"index": i} for i in range(frames)]
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    schema.atomic_write_text(work / "rewritten.jsonl", "".join(schema.dumps_row(r) + "\n" for r in many))
    rewrite = time.perf_counter() - t0
    t0 = time.perf_counter()
    append_rows(work, many[-chunk:])
    append = time.perf_counter() - t0
    chunks = frames // chunk
    return {
        "frames": frames,
        "chunk_frames": chunk,
        "kb_per_row": round((work / "rewritten.jsonl").stat().st_size / frames / 1024, 1),
        "last_chunk_rewrite_s": round(rewrite, 3),
        "last_chunk_append_s": round(append, 4),
        "ratio": round(rewrite / append, 1),
        "run_rewrites_s": round(rewrite * (chunks + 1) / 2, 2),
        "run_appends_and_compaction_s": round(append * chunks + rewrite, 2),
    }


def _run(overrides: list[str], out: Path, frames: int) -> dict:
    settings = load_settings(detection_overrides(overrides))
    t0 = time.perf_counter()
    summary = render_detection_frames(settings, out, frames)
    wall = time.perf_counter() - t0
    return {
        "frames": summary["rendered"],
        "fields": summary["fields"],
        "wall_s": round(wall, 2),
        "frames_per_s": round(summary["rendered"] / wall, 3),
        "labels_per_frame": round(summary["labels"] / max(1, summary["frames"]), 1),
        "workers": stage_summary(worker_stats(out)),
    }


def bench_detection(overrides, work: Path, frames: int = 256, per_frame_frames: int = 8) -> dict:
    """Grouped and per-frame detection frames/s at 256² and 512² (module docstring)."""
    out: dict = {}
    for width, extra in ((256, []), (512, [f"procedural.size_px={FIELD_PX_512}"])):
        ov = [f"detection.width_px={width}", *extra, *overrides]
        grouped = _run(ov, work / f"grouped_{width}", frames)
        single = _run([*ov, *PER_FRAME], work / f"per_frame_{width}", per_frame_frames)
        out[f"{width}px"] = {
            "grouped": grouped,
            "per_frame": single,
            "ratio": round(grouped["frames_per_s"] / single["frames_per_s"], 2),
        }
    out["manifest"] = bench_manifest(list(manifest_rows(work / "grouped_256").values()), work / "manifest")
    return out


def summary_line(r: dict) -> str:
    """``detection_256_fps=A per_frame_256_fps=B ratio_256=C detection_512_fps=D ...``."""
    parts = []
    for width in (256, 512):
        row = r[f"{width}px"]
        parts += [
            f"detection_{width}_fps={row['grouped']['frames_per_s']}",
            f"per_frame_{width}_fps={row['per_frame']['frames_per_s']}",
            f"ratio_{width}={row['ratio']}",
        ]
    m = r["manifest"]
    parts += [f"manifest_rewrite_s={m['last_chunk_rewrite_s']}", f"manifest_append_s={m['last_chunk_append_s']}"]
    return " ".join(parts)
