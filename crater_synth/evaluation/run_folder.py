"""The ``run_dir`` of ``train``, ``evaluate`` and ``loop``: a folder several commands share, each keeping
only its own files (crater_synth/outfolder.py; docs/architecture.md, "Output folders").

A run_dir is shared by design: ``experiments`` writes its CSV and figure there, the navigation demo
``RUN_DIR/navigation/``, ``report`` ``RUN_DIR/report/``, ``evaluate`` ``previous/``. So a run writer
claims no kind for the folder. It holds the folder's lock while it runs (one writer of a run_dir at a
time, the second refused naming the holder), and its marker (``.crater-synth-run``, shared by the three
commands) lists the files they wrote with their size and mtime. A writer checks only the files of its own
names (:data:`train.runs.TRAIN_FILES`, :data:`train.runs.EVALUATE_FILES`, the loop's :data:`LOOP_FILES`
and ``rounds/<round>/``'s files): one it cannot prove it wrote refuses the run, in one line naming it, and
nothing is written. Every other file and subfolder is another writer's and left alone.

A file of a run's name proves itself by its content where the marker does not list it (a run_dir
written before markers) or it changed since (a run killed between two renames): :func:`proved`.
"""

from __future__ import annotations

import json
import os
import pickle
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Callable

import yaml

from crater_core.schema import sha256_file
from crater_synth.outfolder import OutFolder, matplotlib_png
from train.registry import MODELS, SPECS
from train.runs import (
    CONFIG_FILE,
    METRICS_FILE,
    REALSET_FILE,
    SUMMARY_FILE,
    TRAIN_FILES,
)

KIND = "run"
HISTORY_FILE, HISTORY_PLOT = "loop_history.json", "loop_history.png"  # the closed loop's record and plot
ROUNDS_DIR = "rounds"  # the loop's rounds, each a run_dir of its own: rounds/round<k>-sun<n>/
IDENTITY_FILE = "round_identity.json"  # in a round's directory: its identity and the settings hashed into it


def round_dir(run_dir: Path, k: int, sun_count: int) -> Path:
    """The folder of the loop's round ``k`` (``sun_count`` sun elevations): a run_dir of its own."""
    return Path(run_dir) / ROUNDS_DIR / f"round{k}-sun{sun_count}"


LOOP_FILES = (HISTORY_FILE, HISTORY_PLOT, *TRAIN_FILES)  # the last round's run is copied to run_dir
ROUND_FILES = frozenset((*TRAIN_FILES, IDENTITY_FILE))
_ROUND = re.compile(rf"{ROUNDS_DIR}/round\d+-sun\d+/([^/]+)")
NET_FILE = SPECS["lunarnet_ex"].artefact  # the one model a proof may load (weights only)


# -- proof by content ------------------------------------------------------------------------------
def _json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return None


def _summary(folder: Path) -> dict | None:
    doc = _json(folder / SUMMARY_FILE)
    ok = isinstance(doc, dict) and isinstance(doc.get("class_names"), list) and "train_images" in doc
    return doc if ok else None


def _model(path: Path) -> bool:
    """A model whose sha256 its run's summary records; a LunarNet_ex checkpoint also by its fields (loaded
    ``weights_only``: never code from the file)."""
    recorded = ((_summary(path.parent) or {}).get("artefacts") or {}).get(path.name)
    if isinstance(recorded, str) and sha256_file(path) == recorded:
        return True
    if path.name != NET_FILE:
        return False
    import torch

    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, OSError, EOFError, ValueError, pickle.UnpicklingError):
        return False
    return isinstance(ck, dict) and {"state_dict", "class_names", "model"} <= set(ck)


def _metrics(path: Path) -> bool:
    doc = _json(path)
    return isinstance(doc, dict) and any(isinstance(doc.get(m), dict) and "real_accuracy" in doc[m] for m in MODELS)


def _realset(path: Path) -> bool:
    try:
        rows = [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return bool(rows) and all(isinstance(r, dict) and any(k.startswith("pred_") for k in r) for r in rows)


def _config(path: Path) -> bool:
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False
    return isinstance(doc, dict) and all(isinstance(doc.get(k), dict) for k in ("train", "sweep", "model"))


def _history(path: Path) -> bool:
    doc = _json(path)
    return isinstance(doc, dict) and isinstance(doc.get("schedule"), list) and isinstance(doc.get("rounds"), list)


def _identity(path: Path) -> bool:
    doc = _json(path)
    return isinstance(doc, dict) and isinstance(doc.get("identity"), str) and isinstance(doc.get("settings"), dict)


_PROOFS: dict[str, Callable[[Path], bool]] = {
    SUMMARY_FILE: lambda p: _summary(p.parent) is not None,
    CONFIG_FILE: _config,
    METRICS_FILE: _metrics,
    REALSET_FILE: _realset,
    HISTORY_FILE: _history,
    IDENTITY_FILE: _identity,
}


def proved(path: Path) -> bool:
    """``path``, a file of a run's name, is what a run writes there: its content says so (a summary, the
    settings, metrics, realset rows, a loop history or round identity of this project's layout; a model
    its summary records; a matplotlib PNG)."""
    path = Path(path)
    if path.name in _PROOFS:
        return _PROOFS[path.name](path)
    if path.suffix == ".png":
        return matplotlib_png(path)
    return _model(path)


# -- the hold --------------------------------------------------------------------------------------
def _names(top: tuple[str, ...], rounds: bool) -> Callable[[str], bool]:
    top_set = frozenset(top)

    def mine(rel: str) -> bool:
        if rel in top_set:
            return True
        m = _ROUND.fullmatch(rel) if rounds else None
        return m is not None and m.group(1) in ROUND_FILES

    return mine


def _present(f: OutFolder, mine: Callable[[str], bool]) -> dict[str, tuple[int, int]]:
    """The writer's files now (relative path -> size, mtime)."""
    found: dict[str, tuple[int, int]] = {}
    if not f.path.is_dir():
        return found
    for root, dirs, files in os.walk(f.path):
        rel_root = Path(root).relative_to(f.path).as_posix()
        if rel_root != "." and not (rel_root + "/").startswith(ROUNDS_DIR + "/"):
            dirs[:] = []  # only the top and rounds/ hold a run's names
            continue
        for name in files:
            rel = name if rel_root == "." else f"{rel_root}/{name}"
            if mine(rel):
                st = os.stat(os.path.join(root, name))
                found[rel] = (st.st_size, st.st_mtime_ns)
    return found


def _refuse_unproved(f: OutFolder) -> list[str]:
    """The writer's unlisted (or changed) files, each proved by its content; the first that is not is the
    refusal. Returns them, to be adopted."""
    unlisted = f.unlisted()
    bad = [rel for rel in unlisted if not proved(f.path / rel)]
    if bad:
        f.refuse(bad)
    return unlisted


def _settle(f: OutFolder, mine: Callable[[str], bool]) -> None:
    """List the writer's files as they are now (written by it, or proved at the start); forget the gone."""
    f.seal(sorted({n for n in f.files if mine(n)} | set(_present(f, mine))))


@contextmanager
def run_writer(run_dir: str | os.PathLike, files: tuple[str, ...], rounds: bool = False) -> Iterator[OutFolder]:
    """Hold ``run_dir`` while one command writes ``files`` (and, with ``rounds``, the loop's round folders)
    into it: ``train`` :data:`train.runs.TRAIN_FILES`; ``evaluate`` :data:`train.runs.EVALUATE_FILES` (it
    reads the models; ``previous/`` never replaces a file); ``loop`` :data:`LOOP_FILES` and its rounds.
    Refused in one line, before any of them is written: a folder marked as another kind's
    (crater_synth.outfolder.MARKERS), one another writer holds (naming it), a file of these names the
    writer cannot prove it wrote (the refusal removes the lock, marker and folders the claim created). A
    run that fails having changed none of its files leaves the folder as it was."""
    mine = _names(files, rounds)
    f = OutFolder(Path(run_dir), KIND, flag="run_dir", prove=proved, names=mine).claim()
    try:
        adopt = _refuse_unproved(f)  # under the lock; a refusal removes what the claim created
        f.record(adopt)
        f.seal(adopt)
        f.record(files)  # listed before they are written: a run killed between two renames keeps them its own
        before = _present(f, mine)
    except BaseException:
        f.discard()
        raise
    try:
        yield f
    except BaseException:
        _settle(f, mine)
        if _present(f, mine) == before:
            f.discard()  # wrote nothing: removes the marker and lock only if this run created them
        else:
            f.release()
        raise
    _settle(f, mine)
    f.release()
