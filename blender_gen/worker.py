"""Blender render worker: ``python -m blender_gen.worker JOB.json`` or
``blender --background --python blender_gen/worker.py -- JOB.json``.

Renders every item of the job (docs/renderer.md, "Worker contract") and prints, per finished render,
one line ``RESULT {json}`` (index, rel_path, sha256, lit_fraction, mean_if, seconds) on stdout,
flushed. Bad input prints ``ERROR <one line>`` and exits with status 2; anything unexpected prints
``ERROR`` and exits 1. Progress/timing notes go to stderr.

Imports only bpy, numpy, OpenImageIO and the standard library (plus this package).
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
import traceback

if __package__ in (None, ""):  # run as a script (blender --python blender_gen/worker.py)
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from crater_core.blas_threads import one_blas_thread  # noqa: E402 - after the path above

# Before numpy's import, whatever the environment says: the workers are the parallelism, and the rendered
# bytes must not depend on the node's core count (crater_core/blas_threads.py).
one_blas_thread(force=True)

# Python modules the worker needs besides bpy and the standard library. A Blender binary runs its own
# (or the system's) Python, which may lack them: checked first, so that the host gets one ERROR line.
REQUIRED_MODULES = {"numpy": "python3-numpy", "OpenImageIO": "python3-openimageio"}

RENDERER_VERSION = "blender_gen 1"
# Render settings that change how a job runs, not its pixels: kept out of the EXR header so that the
# bytes do not depend on the worker/thread layout (docs/distributed.md, "Determinism").
# Host-side settings that do not change a pixel stay out of the header's render settings: ``blender`` (the
# host's path to a Blender binary) says where the worker ran, and the header records the version that ran
# instead (crater_synth:blender).
EXECUTION_ONLY_KEYS = {"threads", "workers", "max_retries", "horizon_cache_dir", "blender"}
_RESERVED_EXR_KEYS = {
    "compression",
    "DateTime",
    "channels",
    "dataWindow",
    "displayWindow",
    "lineOrder",
    "pixelAspectRatio",
    "PixelAspectRatio",
    "screenWindowCenter",
    "screenWindowWidth",
    "tiles",
    "type",
    "name",
    "version",
    "chunkCount",
    "oiio:subimages",
}


def _args(argv: list[str]) -> list[str]:
    return argv[argv.index("--") + 1 :] if "--" in argv else argv[1:]


def log(msg: str) -> None:
    print(f"[blender_gen.worker] {msg}", file=sys.stderr, flush=True)


_RESULT_FD: int | None = None  # private duplicate of the original stdout (see _protect_stdout)


def _protect_stdout() -> None:
    """Send everything else written to fd 1 (Blender's C-level render log, stray prints) to stderr,
    keeping a private duplicate of stdout for the protocol lines. Blender's buffered C stdio could
    otherwise flush half a log line in front of a RESULT line and the host would miss it."""
    global _RESULT_FD
    if _RESULT_FD is None:
        sys.stdout.flush()
        _RESULT_FD = os.dup(1)
        os.dup2(2, 1)


def emit(prefix: str, payload) -> None:
    """One protocol line (``RESULT {...}`` / ``ERROR ...``), written atomically and unbuffered."""
    text = payload if isinstance(payload, str) else json.dumps(payload, separators=(",", ":"))
    data = f"{prefix} {text}\n".encode()
    if _RESULT_FD is None:
        sys.stdout.write(data.decode())
        sys.stdout.flush()
        return
    while data:
        data = data[os.write(_RESULT_FD, data) :]


# Stopping (SIGTERM/SIGINT from the host or the terminal, or the host gone): the handler only records
# the signal, and the render loop stops at the next safe point -- between renders, never between
# writing an EXR and reporting it (the file would have no manifest row), and never inside bpy: Blender
# turns a SystemExit raised inside an operator (a Cycles render) into a C exit() that skips every
# Python ``finally``, which would leave the scratch file behind.
_STOP = {"signal": None}


def _on_stop_signal(signum, _frame) -> None:
    _STOP["signal"] = signum


def _stop_if_asked() -> None:
    if _STOP["signal"] is not None:
        log(f"stopping on signal {_STOP['signal']}")
        raise SystemExit(128 + _STOP["signal"])


def _watch_parent(interval_s: float = 1.0) -> None:
    """Stop (SIGTERM to self) when the host process is gone, e.g. killed with -9."""
    import threading

    parent = os.getppid()

    def watch():
        while True:
            time.sleep(interval_s)
            if os.getppid() != parent:
                os.kill(os.getpid(), signal.SIGTERM)
                return

    threading.Thread(target=watch, name="watch-host", daemon=True).start()


def header_for(job: dict, cfg: dict, item: dict, mode_used: str, blender_version: str = "") -> dict:
    """Every render parameter, as EXR header attributes (str/int/float)."""
    hdr = {
        "crater_synth:renderer": RENDERER_VERSION,
        "crater_synth:blender": blender_version,
        "crater_synth:mode": mode_used,
        "crater_synth:index": int(item["index"]),
        "crater_synth:indices": json.dumps(item.get("indices", [])),
        "crater_synth:sun_elevation": float(item["sun_elevation"]),
        "crater_synth:sun_azimuth": float(item["sun_azimuth"]),
        "crater_synth:cam_elevation": float(item["cam_elevation"]),
        "crater_synth:cam_azimuth": float(item["cam_azimuth"]),
        "crater_synth:range_m": float(item["range_m"]),
        "crater_synth:fov_deg": float(item["fov_deg"]),
        "crater_synth:frame_width": int(item["frame_width"]),
        "crater_synth:crop": json.dumps([int(c) for c in item["crop"]]),
        "crater_synth:crater": json.dumps(job["crater"], sort_keys=True),
        "crater_synth:terrain_id": str(job.get("terrain_meta", {}).get("terrain_id", "")),
        "crater_synth:hapke": json.dumps(job["hapke"], sort_keys=True),
        "crater_synth:render": json.dumps(
            {k: v for k, v in cfg.items() if k not in EXECUTION_ONLY_KEYS}, sort_keys=True
        ),
        "crater_synth:sun_strength": "pi (white Lambertian at normal incidence renders 1: pixel = I/F)",
        "crater_synth:channels": "IF=radiance factor; depth=m along view axis; N=ENU unit normal; "
        "lit=illuminated fraction of the solar disk",
    }
    for k, v in (item.get("header") or {}).items():  # the host's entries, verbatim (unless reserved by EXR)
        hdr[str(k) if str(k) not in _RESERVED_EXR_KEYS else f"crater_synth:host:{k}"] = v
    return hdr


def missing_modules() -> str | None:
    """One line naming the required modules this Python lacks (None when it has them all)."""
    missing = []
    for name in REQUIRED_MODULES:
        try:
            __import__(name)
        except ImportError:
            missing.append(name)
    if not missing:
        return None
    debs = " ".join(REQUIRED_MODULES[m] for m in missing)
    where = f"{sys.version.split()[0]}, modules from {os.path.dirname(os.__file__)}"
    which = "it" if len(missing) == 1 else "them"
    return (
        f"this Blender's Python ({where}) lacks {', '.join(missing)}: "
        f"install {which} for that Python (Debian: apt-get install {debs})"
    )


def _checked_settings(job: dict, job_path: str) -> tuple[dict, str]:
    """The job's render settings and the running Blender's version; a Blender too old or settings (or
    Hapke parameters) that do not parse are the job's error."""
    from blender_gen import compat
    from blender_gen.job import JobError
    from blender_gen.scene import render_settings
    from crater_core.hapke import HapkeParams

    problem = compat.check_version()
    if problem:
        raise JobError(problem)
    blender_version = compat.version_string()
    try:
        cfg = render_settings(job.get("render"))
        HapkeParams.from_mapping(job["hapke"])
    except (ValueError, KeyError, TypeError) as exc:
        raise JobError(f"job {job_path}: {type(exc).__name__}: {exc}") from None
    return cfg, blender_version


def _fast_renderer(session, job: dict, cfg: dict):
    """The fast-mode renderer with its horizon maps ready, or None in direct mode."""
    from blender_gen import fast
    from blender_gen.job import load_terrain

    if cfg["mode"] != "fast":
        return None
    fast_r = fast.FastRenderer(session, lambda: load_terrain(job["terrain_npz"]))
    cache_dir = fast.horizon_cache_dir(job.get("horizon_cache_dir"), job["terrain_npz"])
    fast_r.prepare_horizons([float(it["sun_azimuth"]) for it in job["renders"]], job["terrain_npz"], cache_dir, log=log)
    return fast_r


def _render_channels(session, fast_r, cfg: dict, item: dict, to_sun) -> tuple[dict, str]:
    """One render's channels and the mode that made them: the fast path, or direct mode when the fast
    path cannot render this view."""
    from blender_gen import direct, fast

    if fast_r is None:
        return direct.render(session, item, to_sun), cfg["mode"]
    try:
        return fast_r.render(item, to_sun), cfg["mode"]
    except fast.FallbackNeeded as exc:
        fast_r.stats["fallbacks"] += 1
        log(f"render {item['index']}: {exc}; rendering it in direct mode")
        return direct.render(session, item, to_sun), "direct"


def _write_render(job: dict, cfg: dict, item: dict, chans: dict, mode_used: str, blender_version: str):
    """Write one render's sealed EXR; its SHA-256 and the file's stats."""
    import numpy as np

    from crater_core import exr

    path = os.path.join(job["out_dir"], item["rel_path"])
    stats = {  # the file's values (lit is stored as half)
        "lit_fraction": round(float(np.mean(exr.as_stored({"lit": chans["lit"]})["lit"])), 6),
        "mean_if": round(float(np.mean(chans["IF"])), 8),
    }
    header = header_for(job, cfg, item, mode_used, blender_version)
    # The stats, and a seal over every attribute (the host's manifest row among them) and the
    # pixels: the row can be rebuilt from the file alone (crater_synth.dataset.recover).
    header["crater_synth:stats"] = json.dumps(stats, sort_keys=True)
    sha = exr.write_exr(path, chans, exr.sealed_header(chans, header))
    return sha, stats


def _render_all(job: dict, session, fast_r, cfg: dict, blender_version: str) -> float:
    """Render and write every item, one RESULT line each, stopping between renders when asked; the
    seconds spent writing EXRs."""
    from blender_gen import render
    from blender_gen.sun import to_sun_vector

    t_write = 0.0
    try:
        for item in job["renders"]:
            _stop_if_asked()
            t1 = time.perf_counter()
            to_sun = to_sun_vector(float(item["sun_elevation"]), float(item["sun_azimuth"]))
            chans, mode_used = _render_channels(session, fast_r, cfg, item, to_sun)
            t2 = time.perf_counter()
            sha, stats = _write_render(job, cfg, item, chans, mode_used, blender_version)
            t_write += time.perf_counter() - t2
            emit(
                "RESULT",
                {
                    "index": int(item["index"]),
                    "rel_path": item["rel_path"],
                    "sha256": sha,
                    **stats,
                    "seconds": round(time.perf_counter() - t1, 4),
                    "mode": mode_used,
                    "blender": blender_version,
                },
            )
            _stop_if_asked()
    finally:
        render.cleanup()
    return t_write


def _report_timing(n: int, cfg: dict, session, fast_r, t0: float, t_job: float, t_write: float) -> None:
    """The job's timing: one readable log line and one ``STATS {json}`` line on stderr."""
    dt = time.perf_counter() - t_job
    extra = ""
    if fast_r is not None:
        extra = ", fast path " + json.dumps({k: round(v, 3) for k, v in fast_r.stats.items()})
    log(
        f"{n} renders in {dt:.2f} s ({n / dt if dt > 0 else 0:.2f}/s); {session.n_cycles_calls} Cycles calls "
        f"({session.cycles_seconds:.2f} s); EXR writing {t_write:.2f} s{extra}"
    )
    stats = {
        "renders": n,
        "seconds": round(dt, 3),
        "setup_s": round(t_job - t0, 3),
        "cycles_calls": session.n_cycles_calls,
        "cycles_s": round(session.cycles_seconds, 3),
        "exr_write_s": round(t_write, 3),
        "mode": cfg["mode"],
    }
    if fast_r is not None:
        stats["fast"] = {k: round(v, 4) for k, v in fast_r.stats.items()}
    print("STATS " + json.dumps(stats), file=sys.stderr, flush=True)


def run(job_path: str) -> int:
    from blender_gen.job import load_job, load_terrain

    job = load_job(job_path)
    terrain = load_terrain(job["terrain_npz"])  # errors before bpy is even imported

    from blender_gen.session import Session

    cfg, blender_version = _checked_settings(job, job_path)
    t0 = time.perf_counter()
    session = Session(job, terrain)
    del terrain
    log(f"scene ready in {time.perf_counter() - t0:.2f} s ({len(job['renders'])} renders, mode {cfg['mode']})")
    fast_r = _fast_renderer(session, job, cfg)
    t_job = time.perf_counter()
    t_write = _render_all(job, session, fast_r, cfg, blender_version)
    _report_timing(len(job["renders"]), cfg, session, fast_r, t0, t_job, t_write)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _args(sys.argv if argv is None else argv)
    _protect_stdout()
    # SIGTERM (host shutting down), SIGINT (Ctrl-C reaches the whole process group) or SIGHUP: unwind
    # normally so the scratch file is removed; the same when the host disappears.
    signal.signal(signal.SIGTERM, _on_stop_signal)
    signal.signal(signal.SIGINT, _on_stop_signal)
    signal.signal(signal.SIGHUP, _on_stop_signal)  # the terminal closed: the same clean stop
    _watch_parent()
    if len(args) != 1:
        emit("ERROR", "usage: python -m blender_gen.worker JOB.json")
        return 2
    problem = missing_modules()
    if problem:
        emit("ERROR", problem)
        return 2
    from blender_gen.job import JobError

    try:
        return run(args[0])
    except BrokenPipeError:  # the host went away: nobody is left to tell
        log("stdout closed by the host; stopping")
        return 1
    except JobError as exc:
        try:
            emit("ERROR", str(exc).replace("\n", " "))
        except OSError:
            pass
        return 2
    except Exception as exc:  # noqa: BLE001 - one clear line for the host, the trace for the log
        traceback.print_exc(file=sys.stderr)
        try:
            emit("ERROR", f"{type(exc).__name__}: {exc}".replace("\n", " "))
        except OSError:
            pass
        return 1


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    # Under `blender --python` sys.exit would leave Blender's own exit code; os._exit skips bpy's
    # (slow) teardown as well.
    os._exit(code)
