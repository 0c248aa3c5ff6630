"""Dispatch: Blender worker processes, their protocol lines, retries, and a clean stop.

The host never imports bpy: each worker is a separate process (``python -m blender_gen.worker JOB``,
or ``blender --background --python blender_gen/worker.py -- JOB`` with ``render.blender``) that
imports bpy once and renders a contiguous, camera-major block of renders, printing one ``RESULT`` line
per finished render (docs/renderer.md, "Worker contract"). A worker that dies is restarted on
its unfinished renders (``render.max_retries``). When the host stops early (an error, SIGTERM,
Ctrl-C), every worker gets SIGTERM, the host keeps reading their RESULT lines until they exit (a
render written is a render recorded), kills what is left after a grace period, and removes the
scratch files of the workers it started.
"""

from __future__ import annotations

import json
import os
import re
import selectors
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from blender_gen import compat
from crater_core import schema
from crater_core.files import remove_stale_scratch
from crater_core.settings import HapkeParams, RenderSettings
from crater_synth.dataset.disk import JOBS_DIR
from crater_synth.dataset.manifest import writer_tag
from crater_synth.dataset.plan import CraterJob, camera_major, hapke_dict
from crater_synth.errors import STOP_SIGNALS, RenderError
from crater_synth.paths import BLENDER_WORKER, SOURCE_ROOT

# Seconds a worker gets to finish its current render and exit after SIGTERM before SIGKILL.
STOP_GRACE_S = 10.0
_DISK_FULL_MARKERS = ("ENOSPC", "EDQUOT", "No space left on device", "Disk quota exceeded", "disk full")


# Seconds `blender --version` may take (a cold start of a Blender binary from a slow disk).
BLENDER_VERSION_TIMEOUT_S = 120.0


def worker_command(job_file: Path, blender: str | None = None) -> list[str]:
    """The worker process for ``job_file``: the bpy module of this Python, or the Blender binary
    ``blender`` running the worker script (``--factory-startup``: no user preferences or add-ons)."""
    if blender is None:
        return [sys.executable, "-m", "blender_gen.worker", str(job_file)]
    script = BLENDER_WORKER
    return [blender, "--background", "--factory-startup", "--python", str(script), "--", str(job_file)]


def blender_binary(path: str) -> tuple[str, str]:
    """(absolute path, version) of the Blender binary ``render.blender=path`` (a path, or a name on
    PATH), checked to run and to be a supported version; otherwise one :class:`RenderError` line
    naming the setting, the version found and the versions supported."""
    what = f"render.blender={path}"
    exe = shutil.which(path)
    if exe is None:
        found = "not executable" if os.path.exists(path) else "no such file (nor a command on PATH)"
        raise RenderError(f"{what}: {found}; {compat.supported_text()}")
    exe = os.path.abspath(exe)
    try:
        proc = subprocess.run(
            [exe, "--factory-startup", "--version"],
            capture_output=True,
            text=True,
            timeout=BLENDER_VERSION_TIMEOUT_S,
            stdin=subprocess.DEVNULL,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise RenderError(f"{what}: cannot run `{exe} --version` ({exc}); {compat.supported_text()}") from None
    lines = (proc.stdout + "\n" + proc.stderr).splitlines()
    head = next((ln.strip() for ln in lines if re.match(r"\s*Blender\s+\d", ln)), "")
    version = compat.parse_version(head) if head else None
    if proc.returncode != 0 and version is None:
        tail = " ".join(lines[-3:]).strip() or f"exit status {proc.returncode}"
        raise RenderError(f"{what}: `{exe} --version` failed: {tail}; {compat.supported_text()}")
    problem = compat.version_problem(version, what)
    if problem:
        raise RenderError(problem)
    return exe, ".".join(str(v) for v in version)  # type: ignore[union-attr]


# What one more work unit costs, in renders' worth of time: a worker start-up (python and bpy import
# ~1.4 s, scene and mesh build ~1.2 s) at ~27 renders/s per worker. The horizon maps are not in it:
# they are per crater, and the units of a crater share them through the on-disk cache (units running
# at the same time split the azimuths between them). Measured with `crater-synth bench --part renderer`
# (worker logs; docs/renderer.md, "Order of work").
WORKER_STARTUP_RENDERS = 75
MAX_BLOCKS_PER_WORKER = 4


def split_contiguous(items: list, n: int) -> list[list]:
    n = max(1, min(n, len(items)))
    return [items[i * len(items) // n : (i + 1) * len(items) // n] for i in range(n)]


def makespan(unit_sizes: list[int], n_workers: int, startup: int = WORKER_STARTUP_RENDERS) -> int:
    """Finish time (in renders) of ``unit_sizes`` taken in order by ``n_workers`` slots, each unit
    paying a worker start-up: the host's own schedule, simulated."""
    slots = [0] * max(1, n_workers)
    for size in unit_sizes:
        i = slots.index(min(slots))
        slots[i] += size + startup
    return max(slots)


def _units_of(sizes: list[int], blocks: list[int]) -> list[int]:
    return [len(part) for n, b in zip(sizes, blocks) if n for part in split_contiguous(range(n), b)]


def blocks_per_crater(
    sizes: list[int], n_workers: int, startup: int = WORKER_STARTUP_RENDERS, refine: bool = False
) -> list[int]:
    """How many contiguous blocks each crater's renders are split into (one worker per block).

    Proportional to the crater's share of the work, scaled by the smallest factor m (1..
    :data:`MAX_BLOCKS_PER_WORKER`) whose simulated finish time is best: with 3 craters and 2 workers,
    m = 1 gives 3 units and a last one rendered alone (a third of the work at half the throughput),
    m = 3 gives 6 equal units; tiny sweeps keep one unit per crater, since each unit costs a worker
    start-up (``startup``, in renders' worth of time).

    ``refine``: :func:`_refined_blocks`, for jobs of a few dozen renders whose start-up is a sizeable
    share (navigation frames on shared patches: 3 patches of ~20 frames on 2 workers finish ~20 % sooner
    with one of them split in two than with the proportional 6 units; :func:`run_workers` then takes the
    units largest first)."""
    if refine:
        return _refined_blocks(sizes, n_workers, startup)
    total = max(1, sum(sizes))
    best: tuple[int, list[int]] | None = None
    for m in range(1, MAX_BLOCKS_PER_WORKER + 1):
        blocks = [min(n, max(1, round(m * n_workers * n / total))) if n else 0 for n in sizes]
        span = makespan(_units_of(sizes, blocks), n_workers, startup)
        if best is None or span < best[0]:
            best = (span, blocks)
    assert best is not None
    return best[1]


def _refined_blocks(sizes: list[int], n_workers: int, startup: int) -> list[int]:
    """From one block per job, one more block at a time to the job whose split shortens the simulated
    finish time (units largest first) most, while that gains at least half a start-up (the start-up is
    an estimate: a split that gains less may well lose)."""

    def span_of(blocks: list[int]) -> int:
        return makespan(sorted(_units_of(sizes, blocks), reverse=True), n_workers, startup)

    blocks = [1 if n else 0 for n in sizes]
    span = span_of(blocks)
    while True:
        trials = [
            (span_of(blocks[:j] + [b + 1] + blocks[j + 1 :]), j) for j, (n, b) in enumerate(zip(sizes, blocks)) if b < n
        ]
        if not trials or min(trials)[0] > span - startup / 2:
            return blocks
        span, j = min(trials)
        blocks[j] += 1


def _worker_error(crater: str, message: str) -> RenderError:
    if any(m in message for m in _DISK_FULL_MARKERS):
        text = message.split("ExrError: ", 1)[-1]
        return RenderError(
            f"{text} (while rendering {crater})"
            if text.startswith("disk full")
            else f"disk full (ENOSPC) while rendering {crater}: {text}"
        )
    return RenderError(f"worker for {crater}: {message}")


class _Worker:
    """One running worker process and what the host knows about it."""

    def __init__(self, proc: subprocess.Popen, job: CraterJob, block: list[dict], unit_id: int, log, job_file: Path):
        self.proc, self.job, self.id, self.log, self.job_file = proc, job, unit_id, log, job_file
        self.block = {p["params"].index: p for p in block}
        self.error: str | None = None
        self.buf = b""

    def feed(self, chunk: bytes, on_result) -> None:
        self.buf += chunk
        *lines, self.buf = self.buf.split(b"\n")
        for raw in lines:
            line = raw.decode("utf-8", "replace")
            if line.startswith("RESULT "):
                result = json.loads(line[7:])
                plan = self.block.pop(int(result["index"]), None)
                if plan is not None:
                    on_result(self.job, plan, result)
            elif line.startswith("ERROR "):
                self.error = line[6:]


def _work_units(jobs: list[CraterJob], n_workers: int, startup_renders: int | None):
    """Work units: contiguous blocks of one crater's plans, camera-major (all suns of a camera pose
    together): each worker renders each of its G-buffers once and reads the shared horizon maps of
    every sun azimuth (docs/renderer.md, "Order of work"); as many blocks per crater as balance the
    workers (blocks_per_crater)."""
    units: list[tuple[CraterJob, list[dict]]] = []
    sizes = [len(j.plans) for j in jobs]
    if startup_renders is None:
        shares = blocks_per_crater(sizes, n_workers)
    else:
        shares = blocks_per_crater(sizes, n_workers, startup_renders, refine=True)
    for job, share in zip(jobs, shares):
        if job.plans:
            ordered = sorted(job.plans, key=camera_major)
            units += [(job, block) for block in split_contiguous(ordered, share)]
    if startup_renders is not None:
        units.sort(key=lambda unit: len(unit[1]), reverse=True)  # stable: equal units keep their order
    return units


def _launch_worker(
    job: CraterJob,
    block: list[dict],
    unit_id: int,
    jobs_dir: Path,
    blender,
    render_cfg: dict,
    render: RenderSettings,
    hapke: HapkeParams,
    out_dir: Path,
) -> _Worker:
    """Write the job file of one work unit and start its worker process (its stderr to the job's log)."""
    job_file = jobs_dir / f"{job.crater.name}-{writer_tag()}-{unit_id}.json"
    spec = {
        "terrain_npz": str(job.npz),
        "terrain_meta": job.meta,
        "crater": job.crater.as_dict(),
        "hapke": hapke_dict(hapke),
        "render": render_cfg | job.render_overrides,
        "out_dir": str(out_dir),
        "horizon_cache_dir": render.horizon_cache_dir,
        "renders": [p["item"] for p in block],
    }
    schema.atomic_write_text(job_file, json.dumps(spec))
    log = open(job_file.with_suffix(".log"), "ab")
    proc = subprocess.Popen(
        worker_command(job_file, blender),
        stdout=subprocess.PIPE,
        stderr=log,
        cwd=SOURCE_ROOT,
        env=os.environ | {"PYTHONUNBUFFERED": "1"},
    )
    return _Worker(proc, job, block, unit_id, log, job_file)


def run_workers(
    jobs: list[CraterJob],
    render: RenderSettings,
    hapke: HapkeParams,
    out_dir: Path,
    on_result,
    startup_renders: int | None = None,
) -> None:
    """Render every plan of ``jobs`` (each plan carries its worker ``item``) with ``render.workers``
    processes; ``on_result(job, plan, result)`` is called for each finished render. ``startup_renders``:
    a worker start-up in renders' worth for jobs unlike the sweep's craters (navigation frames on shared
    patches, whose scene, BVH and horizon map outweigh a few frames): the blocks are then refined by
    :func:`blocks_per_crater` and the units taken largest first."""
    n_workers = render.workers
    blender = blender_binary(render.blender)[0] if render.blender is not None else None
    jobs_dir = out_dir / JOBS_DIR
    jobs_dir.mkdir(parents=True, exist_ok=True)
    render_cfg = render.as_dict()
    units = _work_units(jobs, n_workers, startup_renders)
    # the cores split between the workers that can run at once (fewer units than workers: more threads each)
    concurrent = max(1, min(n_workers, len(units)))
    if concurrent > 1 and render.threads == 0:
        render_cfg["threads"] = max(1, (os.cpu_count() or 1) // concurrent)
    pending = list(units)
    attempts: dict[int, int] = {}
    running: dict[subprocess.Popen, _Worker] = {}
    started: set[int] = set()
    sel = selectors.DefaultSelector()
    uid = 0

    def start(job: CraterJob, block: list[dict], unit_id: int) -> None:
        w = _launch_worker(job, block, unit_id, jobs_dir, blender, render_cfg, render, hapke, out_dir)
        started.add(w.proc.pid)
        running[w.proc] = w
        sel.register(w.proc.stdout, selectors.EVENT_READ, w.proc)

    def finish(w: _Worker) -> int:
        sel.unregister(w.proc.stdout)
        rc = w.proc.wait()
        w.log.close()
        del running[w.proc]
        if rc == 0 and not w.block:
            w.job_file.unlink(missing_ok=True)  # done: the log says what happened; the job is not needed
        return rc

    try:
        while pending or running:
            while pending and len(running) < n_workers:
                job, block = pending.pop(0)
                uid += 1
                attempts[uid] = attempts.get(uid, 0)
                start(job, block, uid)
            for key, _ in sel.select(timeout=1.0):
                w = running[key.data]
                with _HeldSignals():  # a RESULT line read is a row written, or the EXR is an orphan
                    chunk = os.read(w.proc.stdout.fileno(), 65536)
                    if chunk:
                        w.feed(chunk, on_result)
                if chunk:
                    continue
                rc = finish(w)
                if w.error:
                    raise _worker_error(w.job.crater.name, w.error)
                left = sorted(w.block.values(), key=camera_major)
                if left:
                    tries = attempts.get(w.id, 0) + 1
                    if tries > render.max_retries:
                        raise RenderError(
                            f"worker for {w.job.crater.name} failed {tries} times (exit {rc}); see {jobs_dir}/*.log"
                        )
                    uid += 1
                    attempts[uid] = tries
                    start(w.job, left, uid)
    finally:
        _stop(running, sel, on_result)
        sel.close()
        remove_stale_scratch(started)


def _stop(running: dict, sel: selectors.BaseSelector, on_result) -> None:
    """Stop the workers still running: SIGTERM, record the RESULT lines they still print, SIGKILL
    after :data:`STOP_GRACE_S`. Further SIGINT/SIGTERM/SIGHUP to the host wait until this is done."""
    if not running:
        return
    restore = _defer_signals()
    try:
        for w in running.values():
            _signal(w.proc, signal.SIGTERM)
        deadline = time.monotonic() + STOP_GRACE_S
        while running and time.monotonic() < deadline:
            for key, _ in sel.select(timeout=0.2):
                w = running[key.data]
                chunk = os.read(w.proc.stdout.fileno(), 65536)
                if chunk:
                    try:
                        w.feed(chunk, on_result)
                    except Exception:  # noqa: BLE001 - stopping anyway; the row is merged next run or lost
                        pass
                    continue
                sel.unregister(w.proc.stdout)
                w.proc.wait()
                w.log.close()
                del running[w.proc]
        for w in list(running.values()):
            _signal(w.proc, signal.SIGKILL)
            w.proc.wait()
            w.log.close()
            running.pop(w.proc, None)
    finally:
        restore()


def _signal(proc: subprocess.Popen, signum: int) -> None:
    try:
        proc.send_signal(signum)
    except ProcessLookupError:
        pass


class _HeldSignals:
    """Hold SIGINT/SIGTERM/SIGHUP for a moment (main thread only) and deliver the one that came on exit.

    The CLI turns those signals into an exception raised wherever the main thread is. Raised between
    reading a worker's RESULT line and appending its manifest row, it would leave an EXR on disk that no
    row names; held, it is raised after the row. The Python handler is swapped rather than the signal
    masked: a signal masked in the main thread can land in another thread, whose C handler still has
    the main thread run the Python handler at its next bytecode, inside the section."""

    def __enter__(self):
        self.got: list[int] = []
        self.old = {}
        if threading.current_thread() is threading.main_thread():
            self.old = {s: signal.signal(s, self._record) for s in STOP_SIGNALS}
        return self

    def _record(self, signum, _frame) -> None:
        self.got.append(signum)

    def __exit__(self, *exc):
        for s, h in self.old.items():
            signal.signal(s, h)
        for signum in dict.fromkeys(self.got):
            signal.raise_signal(signum)  # now under the restored handler


def _defer_signals():
    """Ignore SIGINT/SIGTERM/SIGHUP while the workers are being stopped (main thread only); returns the
    function restoring the previous handlers."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    old = {s: signal.signal(s, signal.SIG_IGN) for s in STOP_SIGNALS}

    def restore():
        for s, h in old.items():
            signal.signal(s, h)

    return restore
