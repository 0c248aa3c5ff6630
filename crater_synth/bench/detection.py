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
"""

from __future__ import annotations

import time
from pathlib import Path

from crater_synth.bench.renderer import stage_summary, worker_stats
from crater_synth.config import load_settings
from crater_synth.dataset.detection import detection_overrides
from crater_synth.dataset.detection_run import render_detection_frames

FIELD_PX_512 = 1400  # check_field_fits: a 512 px frame at the grid's spacing, 45 deg off nadir
PER_FRAME = ("detection.views_per_field=1", "detection.suns_per_view=1", "detection.azimuths_per_field=0")


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
    return " ".join(parts)
