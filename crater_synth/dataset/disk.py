"""The dataset directory on disk: writable, room for the renders, one writer at a time, no leftovers.

- :func:`check_sweep_disk`, :func:`check_planned_disk`: before anything is rendered, room for the EXRs of
  the crops the sweep will produce (the directory itself: crater_synth.dataset.marker).
- :class:`DatasetLock`: a second ``crater-synth dataset`` on the same ``out_dir`` (or the same shard
  of it) refuses to start, naming the process that holds it; shards of one sweep
  (``launcher.shard=i/n``) still run side by side. ``flock`` locks: released by the kernel when the
  holder dies, so a killed run never leaves a stale lock.
- :func:`find_orphans`: EXRs without a manifest row and temp files of interrupted writes (``verify``
  names them); :func:`remove_interrupted_writes`: the temp files ``dataset`` removes (those of its
  own planned files only; crater_synth.dataset.marker says what ``dataset`` may delete).
- :func:`prune_jobs`: ``.jobs/`` keeps the files of running writers and the logs of the last runs only.
"""

from __future__ import annotations

import errno
import fcntl
import math
import os
import socket
import time
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from crater_core import schema
from crater_core.files import PathError, disk_full_message, free_bytes, is_disk_full, size_text
from crater_core.settings import RenderSettings
from crater_core.sweep import SweepGrid
from crater_synth.dataset.manifest import writer_tag
from crater_synth.errors import DatasetBusyError, UserError
from crater_synth.outfolder import MARKERS

# The free-disk estimate of one render (before any of the dataset's own files can be measured):
# EXR_HEADER_BYTES + width x height x RAW_BYTES_PER_PX x EXR_COMPRESSION. The raw pixel is the contract's
# channels in their stored types (crater_core.schema.EXR_CHANNEL_TYPES: 2 float32 + 4 half = 16 B).
# Measured (2026-11-29) on fast-mode Shackleton renders, RLE: the tiny smoke sweep (46x46 crops) 0.713 of
# raw (max 0.723) after a 4,311 B header (the render parameters and the sealed manifest row), the smoke
# sweep (212x212) 0.652 (max 0.663), the paper sweep 457,368 B per ~212x212 EXR (0.636,
# docs/renderer.md "EXR size"); float32 render noise does not compress, so 0.75 is the round upper figure.
RAW_BYTES_PER_PX = sum({"float": 4, "half": 2}[schema.EXR_CHANNEL_TYPES[c]] for c in schema.EXR_CHANNELS)
EXR_COMPRESSION = 0.75
EXR_HEADER_BYTES = 4_500
# Rows measured for a resumed dataset's compression (their files' sizes are stat'ed).
MEASURED_ROWS = 50
JOBS_DIR = ".jobs"
LOCK_FILE = ".dataset.lock"
# Written when `crater-synth dataset` claims a directory: this directory is a dataset
# (crater_synth.dataset.marker; every kind's marker: crater_synth.outfolder).
MARKER_NAME = MARKERS["dataset"]
# Logs of finished writers kept in .jobs/ (the newest; job files of finished writers are removed).
KEEP_JOB_LOGS = 32
# Files of writers on other hosts (whose liveness this host cannot check) are pruned after this.
OTHER_HOST_MAX_AGE_S = 7 * 24 * 3600.0
# A temp file this old cannot belong to a write in progress (an EXR or manifest write takes ms).
STALE_TEMP_AGE_S = 3600.0


def exr_bytes(width: int, height: int, compression: float = EXR_COMPRESSION) -> int:
    """Estimated bytes of one dataset EXR of ``width`` x ``height`` px (see :data:`EXR_COMPRESSION`)."""
    return int(EXR_HEADER_BYTES + width * height * RAW_BYTES_PER_PX * compression)


def measured_compression(rows: list[dict], out_dir: Path) -> float:
    """The compression of the dataset's own files (bytes past the header over the raw pixels, the mean of
    up to :data:`MEASURED_ROWS` rows whose file exists), or :data:`EXR_COMPRESSION` when it has none."""
    ratios = []
    for r in rows[:MEASURED_ROWS]:
        try:
            size = (out_dir / r["path"]).stat().st_size
            raw = int(r["width"]) * int(r["height"]) * RAW_BYTES_PER_PX
        except (OSError, KeyError, TypeError, ValueError):
            continue
        if raw > 0:
            ratios.append(max(size - EXR_HEADER_BYTES, 0) / raw)
    return float(np.mean(ratios)) if ratios else EXR_COMPRESSION


def least_crop_side(render: RenderSettings, grid: SweepGrid) -> int:
    """The smallest crop side (px) any render of the sweep can have, from the settings alone: the frame is
    sized so that the smallest sigma box is at least ``roi_min_px`` wide (crater_core.geometry
    .frame_width_for_roi) and the crop is the largest sigma box (crater_synth.dataset.plan)."""
    return int(math.ceil(render.roi_min_px * max(grid.sigmas) / min(grid.sigmas)))


def crops_bytes(crops: Iterable[Sequence[int]], compression: float) -> int:
    """Estimated bytes of the EXRs of these crops (``[u0, v0, u1, v1]``, as plans carry them)."""
    return sum(exr_bytes(c[2] - c[0], c[3] - c[1], compression) for c in crops)


def check_free_disk(out_dir: Path, n_renders: int, need_bytes: int) -> None:
    """Refuse, in one line before anything is rendered, ``n_renders`` renders whose EXRs are estimated at
    ``need_bytes`` (+10 %) when the file system of ``out_dir`` has less free space."""
    need = int(need_bytes * 1.1)
    free = free_bytes(out_dir)
    if need > free:
        each = size_text(need_bytes // max(n_renders, 1))
        raise UserError(
            f"not enough free disk in {out_dir}: {n_renders} renders need ~{size_text(need)} "
            f"(~{each} each, +10 %), {size_text(free)} free"
        )


def check_sweep_disk(out_dir: Path, n_renders: int, render: RenderSettings, grid: SweepGrid, rows: list[dict]) -> None:
    """The early check, from the settings alone (before terrain and planning): ``n_renders`` EXRs of at
    least the least crop side, at the compression of the dataset's ``rows`` (or the measured default)."""
    side = least_crop_side(render, grid)
    check_free_disk(out_dir, n_renders, n_renders * exr_bytes(side, side, measured_compression(rows, out_dir)))


def check_planned_disk(out_dir: Path, crops: Sequence[Sequence[int]], rows: list[dict]) -> None:
    """The check of the planned renders still to do: their crops' EXRs, at the compression of ``rows``."""
    check_free_disk(out_dir, len(crops), crops_bytes(crops, measured_compression(rows, out_dir)))


# ------------------------------------------------------------------------------------------------
# One writer per dataset (or per shard)
# ------------------------------------------------------------------------------------------------
class DatasetLock:
    """Exclusive lock of a whole dataset directory, or (``shard=(i, n)``) a shared lock of the directory
    plus an exclusive lock of that shard: shards of one sweep run side by side, while a second writer
    of the same shard, or of the whole sweep, refuses with :class:`DatasetBusyError`."""

    def __init__(self, out_dir: Path, shard: tuple[int, int] | None = None):
        self.out_dir = Path(out_dir)
        self.shard = shard
        self._files: list = []

    @property
    def exclusive(self) -> bool:
        """True when no other writer can touch the directory (the whole sweep is locked)."""
        return self.shard is None

    def _take(self, name: str, mode: int, what: str) -> None:
        path = self.out_dir / name
        fh = open(path, "a+")
        try:
            fcntl.flock(fh, mode | fcntl.LOCK_NB)
        except OSError as exc:
            fh.close()
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            self.release()
            raise DatasetBusyError(
                f"{what} {self.out_dir} is being written by another crater-synth process "
                f"({holder(path)}): wait for it to finish, or give another out_dir"
            ) from None
        self._files.append(fh)
        if mode == fcntl.LOCK_EX:  # say who holds it, for the message a second writer prints
            try:
                fh.seek(0)
                fh.truncate()
                fh.write(f"pid {os.getpid()} on {socket.gethostname()}, since {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
                fh.flush()
            except OSError as exc:
                self.release()
                if is_disk_full(exc):  # e.g. a full disk at start-up: name the file
                    raise PathError(disk_full_message(path, exc)) from None
                raise

    def acquire(self) -> "DatasetLock":
        if self.shard is None:
            self._take(LOCK_FILE, fcntl.LOCK_EX, "dataset")
        else:
            i, n = self.shard
            self._take(LOCK_FILE, fcntl.LOCK_SH, "dataset")
            self._take(f".dataset-shard{i}of{n}.lock", fcntl.LOCK_EX, f"shard {i}/{n} of dataset")
        return self

    def release(self) -> None:
        for fh in reversed(self._files):
            try:
                if self.exclusive or fh is not self._files[0]:
                    fh.seek(0)
                    fh.truncate()  # no holder any more (a stale line would mislead the next message)
                fcntl.flock(fh, fcntl.LOCK_UN)
            except OSError:
                pass
            finally:
                try:
                    fh.close()
                except OSError:
                    pass  # a holder line that never reached a full disk
        self._files = []

    def __enter__(self) -> "DatasetLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def holder(lock_path: Path) -> str:
    """Who holds a lock, from the line its exclusive holder wrote (``pid N on HOST, since ...``)."""
    try:
        text = lock_path.read_text().strip()
    except OSError:
        text = ""
    parts = text.split()
    if len(parts) >= 4 and parts[0] == "pid" and parts[1].isdigit() and parts[3].rstrip(",") == socket.gethostname():
        try:
            os.kill(int(parts[1]), 0)
        except ProcessLookupError:
            text = ""  # written by a holder that has died since: the lock is held by someone else now
        except OSError:
            pass
    if text:
        return text
    return "shards of a sweep, launcher.shard=i/n" if lock_path.name == LOCK_FILE else "another process"


# ------------------------------------------------------------------------------------------------
# Orphans: files no manifest row points to
# ------------------------------------------------------------------------------------------------
def _is_temp(p: Path) -> bool:
    """Temp files of interrupted atomic writes (``.<name>.<random>.tmp[.exr]``)."""
    return p.name.startswith(".") and (p.name.endswith(".tmp") or p.name.endswith(".tmp.exr"))


def find_orphans(out_dir: Path, rows: list[dict]) -> list[Path]:
    """EXRs in ``<out_dir>/<crater>/`` that no row names, and temp files of interrupted writes in
    ``out_dir`` and its sub-directories (``.jobs/`` has its own pruning), sorted."""
    out_dir = Path(out_dir)
    named = {r["path"] for r in rows}
    found = []
    if not out_dir.is_dir():
        return found
    for sub in [out_dir, *sorted(p for p in out_dir.iterdir() if p.is_dir() and p.name != JOBS_DIR)]:
        for f in sub.iterdir():
            if not f.is_file():
                continue
            if _is_temp(f):
                found.append(f)
            elif (
                sub != out_dir
                and f.suffix == ".exr"
                and not f.name.startswith(".")
                and str(f.relative_to(out_dir)) not in named
            ):
                found.append(f)
    return sorted(found)


def temp_target(p: Path) -> str | None:
    """The file name an interrupted atomic write ``.<name>.<random>.tmp[.exr]`` was writing, or None."""
    if not _is_temp(p):
        return None
    stem = p.name[1 : p.name.rindex(".tmp")]
    return stem.rsplit(".", 1)[0] if "." in stem else None


def remove_interrupted_writes(out_dir: Path, planned: set[str], exclusive: bool) -> list[Path]:
    """Remove the temp files of interrupted writes of ``manifest.jsonl``, the dataset marker or a
    planned render (``planned``: relative paths), and nothing else. Holding the whole dataset
    (``exclusive``) every such temp file goes; a shard shares the directory with writers whose writes
    are in progress, so it removes only old ones."""
    now = time.time()
    ours = {schema.MANIFEST_NAME, MARKER_NAME} | set(planned)
    removed = []
    for f in find_orphans(out_dir, []):
        target = temp_target(f)
        if target is None or str(f.parent.joinpath(target).relative_to(out_dir)) not in ours:
            continue
        try:
            if not exclusive and now - f.stat().st_mtime <= STALE_TEMP_AGE_S:
                continue
            f.unlink()
            removed.append(f)
        except FileNotFoundError:
            pass
    return removed


def unplanned_files(out_dir: Path, rows: list[dict], planned: set[str]) -> list[Path]:
    """Files in the renders' directories that no row and no planned render names (left alone)."""
    return [
        f for f in find_orphans(out_dir, rows) if temp_target(f) is None and str(f.relative_to(out_dir)) not in planned
    ]


# ------------------------------------------------------------------------------------------------
# .jobs/: worker job files and logs
# ------------------------------------------------------------------------------------------------
def _writer_state(stem: str, host: str) -> str:
    """``running``, ``dead`` or ``other-host`` for a job file stem ``<crater>-<host>-<pid>-<n>``."""
    parts = stem.rsplit("-", 3)
    if len(parts) < 4 or not parts[2].isdigit():
        return "other-host"
    if parts[1] != host:
        return "other-host"
    pid = int(parts[2])
    if pid == os.getpid():
        return "running"
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return "dead"
    except OSError:
        pass
    return "running"


def prune_jobs(out_dir: Path, keep_logs: int = KEEP_JOB_LOGS) -> int:
    """Bound ``.jobs/``: remove the job files of writers that have ended, and all but the newest
    ``keep_logs`` of their logs (files of other hosts: after a week). Returns the files removed."""
    jobs = Path(out_dir) / JOBS_DIR
    if not jobs.is_dir():
        return 0
    host = writer_tag().rsplit("-", 1)[0]
    now = time.time()
    removable_logs, removed = [], 0
    for f in jobs.iterdir():
        if not f.is_file():
            continue
        try:
            mtime = f.stat().st_mtime
        except FileNotFoundError:
            continue
        state = _writer_state(f.stem, host)
        if state == "running":
            continue
        if state == "other-host" and now - mtime < OTHER_HOST_MAX_AGE_S:
            continue
        if f.suffix == ".log" and state == "dead":
            removable_logs.append((mtime, f))
            continue
        f.unlink(missing_ok=True)
        removed += 1
    removable_logs.sort(reverse=True)
    for _, f in removable_logs[keep_logs:]:
        f.unlink(missing_ok=True)
        removed += 1
    return removed
