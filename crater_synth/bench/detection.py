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
did, against appending the chunk's rows one frame at a time with one fsync, as it does now; and both
totals over the run (a rewrite costs its bytes, so the rewrites' total is the last one's times half the
chunks).

``labels``: the 256² grouped run's labels as each frame's label file (columns, crater_core.detection_labels)
against the same labels inline in its row as JSON, as rows once held them: bytes a frame (row and file
against the inline row), the time to read a frame's labels (the label file's columns against parsing the
inline row) and to read them as a training does (its rim circles, :func:`slim_row`: from the columns against
from the parsed row's label dicts).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from crater_core import schema
from crater_core.detection_labels import label_path, read_label_columns, with_labels
from crater_synth.bench.renderer import stage_summary, worker_stats
from crater_synth.config import load_settings
from crater_synth.dataset.detection import detection_overrides, scan_manifest
from crater_synth.dataset.detection_run import append_rows, render_detection_frames
from crater_synth.navigation.rendered.training_rows import slim_row

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
    for row in many[-chunk:]:  # as a run appends: each frame's row as it is labelled, one fsync a chunk
        append_rows(work, [row], sync=False)
    with open(work / schema.MANIFEST_NAME, "ab") as fh:
        os.fsync(fh.fileno())
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


def bench_labels(folder: Path) -> dict:
    """Label storage of the set in ``folder``: label files against the same labels inline (module docstring)."""
    rows = [v[2] for v in scan_manifest(folder)[0].values()]
    inline = [schema.dumps_row(with_labels(folder, r)).encode("utf-8") for r in rows]
    file_bytes = sum(len(schema.dumps_row(r)) + 1 + label_path(folder, r).stat().st_size for r in rows)
    inline_bytes = sum(len(line) + 1 for line in inline)
    timings = {
        "read_file": lambda: [read_label_columns(folder, r) for r in rows],
        "read_inline": lambda: [json.loads(line) for line in inline],
        "training_file": lambda: [slim_row(r, folder) for r in rows],
        "training_inline": lambda: [slim_row(json.loads(line)) for line in inline],
    }
    ms = {}
    for name, fn in timings.items():
        t0 = time.perf_counter()
        fn()
        ms[name] = 1000 * (time.perf_counter() - t0) / max(1, len(rows))
    n = max(1, len(rows))
    return {
        "frames": len(rows),
        "kb_per_frame_file": round(file_bytes / n / 1024, 1),
        "kb_per_frame_inline": round(inline_bytes / n / 1024, 1),
        "size_ratio": round(inline_bytes / max(1, file_bytes), 2),
        **{f"{k}_ms_per_frame": round(v, 3) for k, v in ms.items()},
        "read_ratio": round(ms["read_inline"] / ms["read_file"], 2) if ms["read_file"] > 0 else None,
        "training_ratio": round(ms["training_inline"] / ms["training_file"], 2) if ms["training_file"] > 0 else None,
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
    rows = [v[2] for v in scan_manifest(work / "grouped_256")[0].values()]
    out["manifest"] = bench_manifest(rows, work / "manifest")
    out["labels"] = bench_labels(work / "grouped_256")
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
    lb = r["labels"]
    parts += [f"labels_size_ratio={lb['size_ratio']}", f"labels_training_read_ratio={lb['training_ratio']}"]
    return " ".join(parts)
