"""A training run's files in ``run_dir``: published together or not at all, and checked to be of one run.

``crater-synth train`` writes a run -- ``config.yaml``, the models of :mod:`train.registry`,
``train_summary.json``, then ``metrics.json``, ``realset.jsonl`` and the confusion PNGs -- into a hidden
staging directory inside ``run_dir`` (:class:`StagedRun`, ``.train-<host>-<pid>-<random>.tmp``) and
moves them into ``run_dir`` only once every one is written (one rename each, the summary last;
``evaluate`` stages its outputs the same way). An interrupted run -- Ctrl-C, an error, a kill --
leaves the previous run in ``run_dir`` as it was; the next run removes the staging directory of a
killed one. A refused run that had to create ``run_dir`` removes it again.

Each model file and the summary carry the run's id (``run_id``), the summary also the sha256 of each
model, and ``metrics.json`` the id of the run it evaluated. :func:`check_one_run` refuses a
``run_dir`` whose files are not all of one run (a crash between two renames, a model copied in by
hand), so ``evaluate`` never combines the LunarNet_ex of one run with the SVMs of another.

``evaluate`` keeps what it replaces (``StagedRun(..., keep_previous=True)``): the ``metrics.json``,
``realset.jsonl`` and confusion PNGs already in ``run_dir`` move to ``run_dir/previous/<UTC time>/``
(the time the old files were written; hard links where the file system allows, so the
files appear there whole, under one folder rename, before the new ones replace them).
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import tempfile
import uuid
from datetime import datetime, timezone
from pathlib import Path
from typing import Mapping

from crater_core.files import check_dir_path, ensure_writable_dir
from crater_core.schema import sha256_file
from train.errors import ModelError
from train.registry import ARTEFACTS, MODELS

STAGE_PREFIX, STAGE_SUFFIX = ".train-", ".tmp"
SUMMARY_FILE = "train_summary.json"  # the run's record: published last
CONFIG_FILE = "config.yaml"  # the settings the run trained with
METRICS_FILE, REALSET_FILE = "metrics.json", "realset.jsonl"  # written by the evaluation


def confusion_file(model: str) -> str:
    """The confusion-matrix PNG of ``model`` (a :data:`train.registry.MODELS` key)."""
    return f"confusion_{model}.png"


# The files an evaluation writes into run_dir, and those a training run writes (its evaluation's too).
EVALUATE_FILES = (METRICS_FILE, REALSET_FILE, *(confusion_file(m) for m in MODELS))
TRAIN_FILES = (CONFIG_FILE, *ARTEFACTS, SUMMARY_FILE, *EVALUATE_FILES)
PREVIOUS_DIR = "previous"  # where keep_previous puts the files a re-evaluation replaces


def new_run_id() -> str:
    """A fresh, unique id for one training run."""
    return uuid.uuid4().hex


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9.]+", "_", socket.gethostname()) or "host"


def _dead(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:
        pass  # alive (another user's process)
    return False


def remove_stale_stages(run_dir: Path) -> list[Path]:
    """Staging directories of runs on this host whose process has died (a kill -9): removed."""
    removed = []
    for stage in Path(run_dir).glob(f"{STAGE_PREFIX}*{STAGE_SUFFIX}"):
        fields = stage.name[len(STAGE_PREFIX) : -len(STAGE_SUFFIX)].rsplit("-", 2)
        if len(fields) == 3 and fields[0] == _host() and fields[1].isdigit() and _dead(int(fields[1])):
            shutil.rmtree(stage, ignore_errors=True)
            removed.append(stage)
    return removed


def publish(stage: Path, run_dir: Path) -> list[str]:
    """Move every file of ``stage`` into ``run_dir``. When the stage holds a run's summary, the old one
    goes first and the new one comes last: between the two, ``run_dir`` holds no summary, and a crash
    there leaves files that :func:`check_one_run` refuses rather than files that look whole."""
    names = sorted(f.name for f in stage.iterdir() if f.is_file())
    if SUMMARY_FILE in names:
        names.remove(SUMMARY_FILE)
        names.append(SUMMARY_FILE)
        (run_dir / SUMMARY_FILE).unlink(missing_ok=True)
    for name in names:
        os.replace(stage / name, run_dir / name)
    fd = os.open(run_dir, os.O_RDONLY)
    try:
        os.fsync(fd)  # the renames are durable before the command says it wrote the run
    finally:
        os.close(fd)
    return names


def keep_previous(stage: Path, run_dir: Path) -> Path | None:
    """Put the files of ``run_dir`` that ``stage`` is about to replace into ``run_dir/previous/<stamp>/``
    and return that folder (None when nothing would be replaced). ``<stamp>`` is the UTC time the
    newest of them was written (``20250131T120000Z``; ``-2``, ``-3``... when taken). The folder is
    filled under a hidden name and renamed once, so it is either whole or absent; the originals stay
    in place (hard links, else copies) until :func:`publish` replaces them."""
    old = [run_dir / f.name for f in sorted(stage.iterdir()) if f.is_file() and (run_dir / f.name).is_file()]
    if not old:
        return None
    previous = run_dir / PREVIOUS_DIR
    previous.mkdir(exist_ok=True)
    written = max(p.stat().st_mtime for p in old)
    stamp = datetime.fromtimestamp(written, timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    tmp = Path(tempfile.mkdtemp(prefix=".keep-", suffix=STAGE_SUFFIX, dir=previous))
    try:
        for p in old:
            try:
                os.link(p, tmp / p.name)
            except OSError:  # a file system without hard links
                shutil.copy2(p, tmp / p.name)
        n = 1
        while True:
            target = previous / (stamp if n == 1 else f"{stamp}-{n}")
            try:
                os.rename(tmp, target)  # fails on an existing non-empty folder: never merges two
                return target
            except OSError:
                if not target.exists():
                    raise
                n += 1
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


class StagedRun:
    """``with StagedRun(run_dir) as stage:`` write a run's files into ``stage``; they are published into
    ``run_dir`` when the block ends normally, dropped when it raises (``run_dir`` and the parents this
    created are removed again if they are still empty). ``key`` names ``run_dir`` in errors. With
    ``keep_previous`` the files publishing replaces are first kept (:func:`keep_previous`); ``kept``
    is then their folder (None when there were none)."""

    def __init__(self, run_dir: str | os.PathLike, key: str = "run_dir", keep_previous: bool = False):
        self.run_dir, self.key = Path(run_dir), key
        self.keep_previous = keep_previous
        self.kept: Path | None = None
        self.created: list[Path] = []
        self.stage: Path | None = None

    def __enter__(self) -> Path:
        check_dir_path(self.run_dir, self.key)
        p = self.run_dir
        while not p.exists() and p != p.parent:
            self.created.append(p)
            p = p.parent
        try:
            ensure_writable_dir(self.run_dir, self.key)
            remove_stale_stages(self.run_dir)
            prefix = f"{STAGE_PREFIX}{_host()}-{os.getpid()}-"
            self.stage = Path(tempfile.mkdtemp(prefix=prefix, suffix=STAGE_SUFFIX, dir=self.run_dir))
        except BaseException:
            self._remove_created()
            raise
        return self.stage

    def __exit__(self, exc_type, exc, tb) -> None:
        ok = False
        try:
            if exc_type is None:
                if self.keep_previous:
                    self.kept = keep_previous(self.stage, self.run_dir)
                publish(self.stage, self.run_dir)
                ok = True
        finally:
            shutil.rmtree(self.stage, ignore_errors=True)
            if not ok:
                self._remove_created()

    def _remove_created(self) -> None:
        for p in self.created:  # deepest first; stops at the first that is not empty
            try:
                p.rmdir()
            except OSError:
                break


def check_one_run(run_dir: Path, run_ids: Mapping[str, str | None], summary: Mapping | None) -> str | None:
    """Refuse (:class:`ModelError`, one line) the files of ``run_dir`` unless they are of one training
    run: ``run_ids`` maps each model file to the ``run_id`` it carries (None: saved before run ids
    existed), ``summary`` is ``train_summary.json`` (None when absent), whose recorded sha256 of each
    model must also match. A run directory written before run ids existed (no id anywhere) is accepted
    as it is. Returns the run id (or None)."""
    recorded = dict(run_ids)
    if summary is not None:
        recorded[SUMMARY_FILE] = summary.get("run_id")
    by_run: dict[str | None, list[str]] = {}
    for name, rid in recorded.items():
        by_run.setdefault(rid, []).append(name)
    if len(by_run) > 1:
        parts = "; ".join(
            f"{', '.join(names)} of {f'run {rid[:12]}' if rid else 'a run from before run ids'}"
            for rid, names in by_run.items()
        )
        n = "two" if len(by_run) == 2 else str(len(by_run))
        raise ModelError(
            f"{run_dir} mixes the files of {n} training runs ({parts}): an interrupted or partly copied run; "
            f"train again into it, or give the run_dir of one whole run"
        )
    for name, sha in ((summary or {}).get("artefacts") or {}).items():
        f = Path(run_dir) / name
        if f.is_file() and sha256_file(f) != sha:
            raise ModelError(
                f"{f} is not the file its training run wrote (its sha256 differs from the one in {SUMMARY_FILE}): "
                "changed or replaced since; train again"
            )
    return next(iter(by_run)) if by_run else None
