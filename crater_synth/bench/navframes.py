"""``crater-synth bench --part navframes``: navigation-frame renders per second.

Renders ``frames`` frames of a trajectory (default ``descent_ridge``, its first frames; every override
applies, e.g. ``render.mode=direct trajectory.width_px=1024``) into a scratch directory and reports:
end-to-end frames/s (terrain patches, worker start-up, rendering, labels), the rendering-only rate
(the workers' per-frame seconds, summed over workers' wall time), and the fast path's breakdown
(horizon maps, G-buffers, shading) from the workers' STATS lines. The horizon maps are computed afresh
(a scratch cache); terrain patches come from ``data_dir``'s cache when there (``patch_s`` says). Each
frame has its own terrain patch, so the fast path's sharing of horizon maps and G-buffers between renders (the sweep's
factorisation) does not apply: a frame pays one horizon map and one G-buffer.
"""

from __future__ import annotations

import json
import time
from pathlib import Path


def _worker_stats(out_dir: Path) -> list[dict]:
    stats = []
    for log in sorted((out_dir / ".jobs").glob("*.log")):
        for line in log.read_text(encoding="utf-8", errors="replace").splitlines():
            if line.startswith("STATS "):
                stats.append(json.loads(line[6:]))
    return stats


def bench_navframes(overrides, work: Path, frames: int = 4) -> dict:
    """Render the first ``frames`` frames of the trajectory (``trajectory=descent_ridge`` unless an
    override names another) and time them."""
    from crater_synth.config import load_settings
    from crater_synth.navigation.render_frames import render_frames

    overrides = list(overrides)
    if not any(o.startswith("trajectory=") for o in overrides):
        overrides.insert(0, "trajectory=descent_ridge")
    if not any(o.startswith("render.horizon_cache_dir=") for o in overrides):
        # a fresh horizon cache: every frame pays its horizon map, as a new frame does
        overrides.append(f"render.horizon_cache_dir={work / 'horizon'}")
    settings = load_settings(overrides)
    n = min(frames, settings.trajectory.frames)
    out = work / "navframes"
    t0 = time.perf_counter()
    summary = render_frames(settings, out, list(range(n)))
    wall = time.perf_counter() - t0
    stats = _worker_stats(out)
    fast = {}
    for s in stats:
        for k, v in (s.get("fast") or {}).items():
            fast[k] = round(fast.get(k, 0.0) + v, 3)
    return {
        "trajectory": settings.trajectory.name,
        "frames": n,
        "width_px": settings.trajectory.width_px,
        "mode": settings.render.mode,
        "modes_used": summary["modes_used"],
        "samples": settings.render.samples,
        "workers": settings.render.workers,
        "wall_s": round(wall, 2),
        "frames_per_s": round(n / wall, 3),
        "patch_s": summary["patch_seconds"],
        "dispatch_s": summary["render_seconds"],
        "render_s_per_frame": round(summary["worker_render_seconds"] / n, 3),
        "render_frames_per_s": round(settings.render.workers * n / summary["worker_render_seconds"], 3),
        "worker_setup_s": round(sum(s.get("setup_s", 0.0) for s in stats), 2),
        "fast_breakdown_s": fast,
    }
