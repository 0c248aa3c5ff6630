"""``crater-synth bench --part navframes``: navigation-frame renders per second.

Renders ``frames`` frames of a trajectory (default ``descent_ridge``, its first frames; every override
applies, e.g. ``render.mode=direct trajectory.width_px=1024``) into a scratch directory and reports:
end-to-end frames/s (terrain patches, worker start-up, rendering, labels), the rendering-only rate
(the workers' per-frame seconds, summed over workers' wall time), and the fast path's breakdown
(horizon maps, G-buffers, shading) from the workers' STATS lines. The horizon maps are computed afresh
(a scratch cache per run); terrain patches come from ``data_dir``'s cache when there (``patch_s`` says).
The same frames are rendered twice in one call, with the same settings: ``shared`` (consecutive frames
on one terrain patch: one worker start-up, scene, BVH and horizon map per patch and worker) and
``per_frame`` (each frame its own patch, worker and horizon map), with the ratio of their rates.
"dispatch" is the wall time of the workers (start-up, horizon maps, rendering; patches and labels not in
it).

``navigate``: the shared run's frames then go through ``nav-frames-eval``'s per-frame pipeline with the
default ``appearance`` preset (the landmarks searched for by their predicted appearance) and with the
``synthetic`` preset (the classical detector) as the baseline, on the same frames in the same call:
seconds per frame (search or detection, identification, fix, refinement and check; the DEM and map loads
are outside it), frames/s and fixes of each, and the ratio of their median times; and the appearance
preset with terrain patches and sequential priors (``appearance_patches_sequential``, and with two terrain
workers: how many frames the patches fixed and what the fallback costs on them).
"""

from __future__ import annotations

import time
from pathlib import Path

from crater_synth.bench.renderer import worker_stats
from crater_synth.config import load_settings
from crater_synth.navigation.fix.patches import PatchParams
from crater_synth.navigation.fix.sequence import SequenceParams
from crater_synth.navigation.rendered.evaluate import DirOptions, evaluate_dir, frame_run
from crater_synth.navigation.rendered.frames import frame_overrides, render_frames
from crater_synth.navigation.settings import compose_nav


def _run(settings, out: Path, n: int, share: bool) -> dict:

    t0 = time.perf_counter()
    summary = render_frames(settings, out, list(range(n)), share_patches=share)
    wall = time.perf_counter() - t0
    stats = worker_stats(out)
    fast = {}
    for s in stats:
        for k, v in (s.get("fast") or {}).items():
            fast[k] = round(fast.get(k, 0.0) + v, 3)
    return {
        "patches": summary["patches"],
        "modes_used": summary["modes_used"],
        "wall_s": round(wall, 2),
        "frames_per_s": round(n / wall, 3),
        "patch_s": summary["patch_seconds"],
        "dispatch_s": summary["render_seconds"],
        "dispatch_frames_per_s": round(n / summary["render_seconds"], 3),
        "render_s_per_frame": round(summary["worker_render_seconds"] / n, 3),
        # the workers' per-frame seconds, as many running at once as there are patches (one worker each), at most
        # render.workers: the steady rate once scene, BVH and horizon maps are built
        "render_frames_per_s": round(
            min(settings.render.workers, summary["patches"]) * n / summary["worker_render_seconds"], 3
        ),
        "worker_setup_s": round(sum(s.get("setup_s", 0.0) for s in stats), 2),
        "fast_breakdown_s": fast,
    }


def _untimed(value):
    """A result row without its timings (``seconds`` at any depth): what two runs must agree on."""
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items() if k != "seconds"}
    if isinstance(value, list):
        return [_untimed(v) for v in value]
    return value


def _navigate(frames_dir: Path) -> dict:

    out: dict = {}
    results: dict = {}
    for name in (
        "appearance",
        "synthetic",
        "appearance_2_workers",
        "appearance_patches_sequential",
        "appearance_patches_sequential_2_workers",
    ):
        nav = compose_nav([f"nav/preset={name.split('_')[0]}"])
        workers = 2 if name.endswith("_2_workers") else 1  # the new landmark windows in two processes
        # A frame its craters do not fix navigated with terrain patches, priors carried along the trajectory.
        extra = dict(patches=PatchParams(), sequence=SequenceParams()) if "_patches_sequential" in name else {}
        _, rows = evaluate_dir(
            frames_dir, frame_run(nav, method="position"), DirOptions(terrain_workers=workers, **extra)
        )
        secs = sorted(r["seconds"] for r in rows)
        out[name] = {
            "fixes": sum(bool(r["fix"]) for r in rows),
            "patch_fixes": sum(r.get("fix_source") == "patches" for r in rows),
            "median_s_per_frame": secs[len(secs) // 2],
            "max_s_per_frame": secs[-1],
            "frames_per_s": round(len(secs) / max(sum(secs), 1e-9), 3),
        }
        results[name] = [_untimed(r) for r in rows]
    out["appearance_2_workers"]["same_results"] = results["appearance_2_workers"] == results["appearance"]
    out["appearance_patches_sequential_2_workers"]["same_results"] = (
        results["appearance_patches_sequential_2_workers"] == results["appearance_patches_sequential"]
    )
    out["median_time_ratio_appearance_to_synthetic"] = round(
        out["appearance"]["median_s_per_frame"] / max(out["synthetic"]["median_s_per_frame"], 1e-3), 2
    )
    return out


def bench_navframes(overrides, work: Path, frames: int = 4) -> dict:
    """Render the first ``frames`` frames of the trajectory (``trajectory=descent_ridge`` unless an
    override names another) twice, with the same settings: frames sharing terrain patches (the default
    path) and every frame on its own patch (the per-frame path); times both and gives their ratio."""

    overrides = frame_overrides(overrides)  # the frames' own defaults, as nav-frames renders them
    if not any(o.startswith("trajectory=") for o in overrides):
        overrides.insert(0, "trajectory=descent_ridge")
    runs = {}
    settings = None
    for name, share in (("shared", True), ("per_frame", False)):
        ov = list(overrides)
        if not any(o.startswith("render.horizon_cache_dir=") for o in overrides):
            # a fresh horizon cache per run: every patch pays its horizon map, as a new one does
            ov.append(f"render.horizon_cache_dir={work / ('horizon_' + name)}")
        settings = load_settings(ov)
        n = min(frames, settings.trajectory.frames)
        runs[name] = _run(settings, work / f"navframes_{name}", n, share)
    assert settings is not None
    a, b = runs["shared"], runs["per_frame"]
    return {
        "trajectory": settings.trajectory.name,
        "frames": n,
        "width_px": settings.trajectory.width_px,
        "mode": settings.render.mode,
        "samples": settings.render.samples,
        "gbuffer_samples": settings.render.gbuffer_samples or settings.render.samples,
        "workers": settings.render.workers,
        **runs,
        "speedup_end_to_end": round(a["frames_per_s"] / b["frames_per_s"], 2),
        "speedup_dispatch": round(a["dispatch_frames_per_s"] / b["dispatch_frames_per_s"], 2),
        "speedup_render": round(a["render_frames_per_s"] / b["render_frames_per_s"], 2),
        "navigate": _navigate(work / "navframes_shared"),
    }
