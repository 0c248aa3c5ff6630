"""The one contract of every folder a crater-synth command writes (docs/architecture.md, "Output folders").

- A folder holds one kind of output, named by its marker file (:data:`MARKERS`: ``.crater-synth-<kind>``).
  A writer refuses a folder marked for another kind, or (``subject``) for another subject of its kind
  (another trajectory's frames).
- The marker lists every file the writer wrote (``files``: name -> its size and mtime once written, null
  while being written), recorded *before* the file is written, so an interrupted write is still provably
  the writer's. A listed file whose size or mtime changed since is the writer's only if the writer's own
  ``prove`` accepts it (a nav frame: its header names this trajectory and index). A writer never deletes
  or overwrites a file it cannot prove it wrote; a folder holding any such file is refused, in one line
  naming it, and nothing is written.
- One writer at a time: an exclusive ``flock`` on :data:`LOCK_NAME`, taken without waiting; the kernel
  drops the lock of a killed writer, so a stale lock never blocks. The second writer is refused naming the
  holder (``pid N on HOST, since ...``).
- Files are published atomically (a hidden temp file renamed). A leftover temp file of a listed file is
  tolerated (no loader's glob matches it); it is deleted only when the marker lists it.
- A refused run removes what it created (its marker and lock file, the folders it made while they are
  empty) and nothing else.
- A folder several writers share (:data:`SHARED`: a ``run_dir``) is claimed by none: each writer's marker
  entries and checks cover only its own file names (``names``); every other file is another writer's.

``crater-synth dataset`` keeps its own marker text, lock (crater_synth.dataset.disk.DatasetLock: shards of a
sweep share a dataset) and recovery of renders (crater_synth.dataset.marker); the other writers use
:class:`OutFolder`.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterable, Iterator

from crater_core import schema
from crater_core.files import ensure_writable_dir
from crater_core.verify_file import RECORD_NAME as VERIFIED_RECORD
from crater_synth.errors import DatasetBusyError, UserError

# The marker of each kind of output folder (the dataset's name predates the others and stays).
MARKERS = {
    "dataset": ".crater-synth-dataset",
    "navframes": ".crater-synth-navframes",
    "navdetector-survey": ".crater-synth-navdetector-survey",
    "export": ".crater-synth-export",
    "report": ".crater-synth-report",
    "detection-frames": ".crater-synth-detection-frames",
    "detection-shards": ".crater-synth-detection-shards",
    "detections": ".crater-synth-detections",
    "navigation": ".crater-synth-navigation",
}
WHAT = {
    "dataset": "rendered dataset (docs/manifest.md)",
    "navframes": "navigation frames (docs/navigation/rendered.md)",
    "navdetector-survey": "detector survey tracks, one navframes folder each (docs/navigation/rendered.md)",
    "export": "crater-synth export shards and their export.json (docs/export.md)",
    "report": "a crater-synth run report (docs/report.md)",
    "detection-frames": "detection frames of procedural crater fields (docs/procedural.md)",
    "detection-shards": "a sharded detection set, one detection-frames folder a shard (docs/procedural.md)",
    "detections": "crater-synth detect's crater lists (docs/navigation/commands.md)",
    "navigation": "crater-synth navigate's fixes and detection lists (docs/navigation/commands.md)",
}
LOCK_NAME = ".crater-synth.lock"
JOBS_DIR = ".jobs"  # worker job files and logs (crater_synth.dataset.dispatch)
MAX_NAMED = 10
# Folders several writers share (a run_dir: train, evaluate, loop; the navigation demo and report write their own
# subfolders of it): the marker lists the files of the writers that keep it, and claims no kind for the folder.
SHARED = {"run": (".crater-synth-run", "a train, evaluate or loop run (docs/classifiers.md)")}


class FolderError(UserError):
    """An output folder a writer may not write into (another kind, another subject, files it did not write)."""


def temp_target(name: str) -> str | None:
    """The file an interrupted atomic write ``.<name>.<random>.tmp[.exr]`` was writing, or None."""
    if not name.startswith(".") or not (name.endswith(".tmp") or name.endswith(".tmp.exr")):
        return None
    stem = name[1 : name.rindex(".tmp")]
    return stem.rsplit(".", 1)[0] if "." in stem else None


def what(kind: str) -> str:
    """What a folder of ``kind`` (exclusive, :data:`MARKERS`, or shared, :data:`SHARED`) holds, in words."""
    return WHAT[kind] if kind in WHAT else SHARED[kind][1]


def matplotlib_png(path: Path) -> bool:
    """``path`` is a PNG matplotlib wrote (its ``Software`` text chunk comes before the pixels): how a
    writer of figures proves an existing file of a figure's name is a figure, before replacing it."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    return head.startswith(b"\x89PNG\r\n\x1a\n") and b"Matplotlib" in head


def marker_kind(folder: Path) -> str | None:
    """The kind whose marker ``folder`` holds (None: no marker)."""
    found = [k for k, m in MARKERS.items() if (Path(folder) / m).is_file()]
    return found[0] if found else None


def refuse_kind(folder: Path, kind: str, flag: str) -> None:
    """Refuse ``folder`` when it is marked for another kind than ``kind``."""
    other = [k for k, m in MARKERS.items() if k != kind and (Path(folder) / m).is_file()]
    if other:
        raise FolderError(
            f"{flag}={folder} holds {WHAT[other[0]]} ({MARKERS[other[0]]}), not {what(kind)}: give another folder"
        )


def probe_lock(lock: Path) -> str | None:
    """Who holds ``lock`` exclusively now (its holder line), or None. A shared, non-blocking flock taken and
    released at once; no lock file is created."""
    try:
        fh = open(lock)
    except OSError:
        return None
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                fh.seek(0)
                return fh.read().strip() or "another process"
            return None
        fcntl.flock(fh, fcntl.LOCK_UN)
    return None


def refuse_if_busy(folder: Path, what: str) -> None:
    """Refuse to read ``folder`` while one of its writers (:class:`OutFolder`) holds its lock."""
    who = probe_lock(Path(folder) / LOCK_NAME)
    if who:
        raise DatasetBusyError(f"{what} {folder} is being written by another crater-synth process ({who}): wait for it")


def mark_filled(folder: Path, kind: str) -> None:
    """Mark a folder a writer has just filled, every file in it listed (a temp folder published whole)."""
    f = OutFolder(folder, kind)
    names = f.unlisted()
    f.record(names)
    f.seal(names)


def check_replaceable(folder: Path, kind: str, flag: str, legacy: Callable[[Path], bool] | None = None) -> None:
    """Refuse to replace ``folder`` (a writer that publishes a whole folder in its place) unless every file
    in it is the writer's: listed by its marker, or (no marker) ``legacy`` recognises the folder."""
    f = OutFolder(folder, kind, flag=flag)
    if not folder.exists():
        return
    f.check()
    if not f.marker.exists() and legacy is not None and legacy(folder):
        return
    bad = f.unlisted()
    if bad:
        f.refuse(bad)


def take_lock(lock: Path, what_: str, other: str):
    """The exclusive ``flock`` on ``lock`` (an open file holding this process's holder line), taken without
    waiting; held by another: refused naming the holder (``what_`` names the output, ``other`` what to give
    instead)."""
    fh = open(lock, "a+")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        fh.close()
        if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise
        who = lock.read_text(errors="replace").strip() or "another process"
        raise DatasetBusyError(
            f"{what_} is being written by another crater-synth process ({who}): wait for it to finish, or give "
            f"another {other}"
        ) from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"pid {os.getpid()} on {socket.gethostname()}, since {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
    fh.flush()
    return fh


@contextmanager
def file_lock(target: Path, flag: str) -> Iterator[None]:
    """One writer of a single output file at a time (``landmarks --out``): the lock is ``.<name>.lock``
    beside it, removed when the writer is done. A missing folder is created, and removed again (while
    empty) when the writer fails."""
    target = Path(target)
    missing = [p for p in [target.parent, *target.parent.parents] if not p.exists()]
    ensure_writable_dir(target.parent, flag.lstrip("-"))
    lock = target.with_name(f".{target.name}.lock")
    ok = False
    try:
        fh = take_lock(lock, f"{flag} {target}", "file")
        try:
            yield
            ok = True
        finally:
            lock.unlink(missing_ok=True)  # while held: a second writer either saw it held or sees none
            fh.close()
    finally:
        for d in [] if ok else missing:
            try:
                d.rmdir()
            except OSError:
                break


class OutFolder:
    """A writer's hold on an output folder of one ``kind`` (and ``subject``): :meth:`claim` checks, creates,
    locks and marks it; :meth:`record` lists files before they are written; :meth:`remove` deletes only
    listed files; :meth:`discard` undoes a refused run; :meth:`release` unlocks."""

    def __init__(
        self,
        path: Path,
        kind: str,
        subject: str | None = None,
        flag: str = "--out",
        prove: Callable[[Path], bool] | None = None,
        names: Callable[[str], bool] | None = None,
    ):
        self.path, self.kind, self.subject, self.flag, self.prove = Path(path), kind, subject, flag, prove
        # In a shared folder (SHARED), the relative paths this writer writes: only these are its to check;
        # every other file is another writer's, left alone.
        self.names = names
        self.marker = self.path / (MARKERS[kind] if kind in MARKERS else SHARED[kind][0])
        self.files: dict[str, list[int] | None] = {}  # relative path -> [size, mtime_ns] once written
        self._new_dirs: list[Path] = []  # the folders this run created, deepest first
        self._new_files: list[Path] = []  # the files this run created (lock, marker)
        self._lock = None

    # -- the check -------------------------------------------------------------------------------
    def _read_marker(self) -> dict | None:
        if not self.marker.is_file():
            return None
        try:
            doc = json.loads(self.marker.read_text(encoding="utf-8"))
            files = doc["files"]
            if doc.get("kind") != self.kind or not isinstance(files, dict):
                raise ValueError
            if not all(v is None or (isinstance(v, list) and len(v) == 2) for v in files.values()):
                raise ValueError
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError):
            raise FolderError(f"{self.flag}={self.path}: its marker {self.marker.name} is unreadable") from None
        return doc

    def check(self) -> None:
        """Refuse a folder of another kind or subject (writing nothing); read the files the marker lists."""
        refuse_kind(self.path, self.kind, self.flag)
        if self.path.exists() and not self.path.is_dir():
            raise FolderError(f"{self.flag}={self.path} is a file, not a folder")
        doc = self._read_marker()
        if doc is None:
            return
        if doc.get("subject") != self.subject:
            raise FolderError(
                f"{self.flag}={self.path} holds {what(self.kind)} of {doc.get('subject')!r}, not of "
                f"{self.subject!r}: give another folder"
            )
        self.files = {f: v for f, v in doc["files"].items() if (self.path / f).exists()}  # never written: forgotten

    def check_clean(self, tolerate: Callable[[str], bool] | None = None) -> "OutFolder":
        """:meth:`check`, then refuse the folder, naming the first, when it holds an unlisted file (not
        this writer's bookkeeping) that ``tolerate`` does not accept. Nothing is written either way."""
        self.check()
        bad = [n for n in self.unlisted() if tolerate is None or not tolerate(n)]
        if bad:
            self.refuse(bad)
        return self

    def proved(self, rel: str) -> bool:
        """``rel`` is this writer's: listed, and unchanged since written (or being written when the writer
        stopped), or accepted by ``prove``."""
        if rel not in self.files:
            return False
        stamp = self.files[rel]
        try:
            st = (self.path / rel).stat()
        except OSError:
            return True  # gone: nothing to lose
        if stamp is None or stamp == [st.st_size, st.st_mtime_ns]:
            return True
        return self.prove is not None and self.prove(self.path / rel)

    def _is_bookkeeping(self, rel: str) -> bool:
        name = rel.rsplit("/", 1)[-1]
        target = temp_target(name)
        if target is not None:
            # a listed file's interrupted write, or the marker's or verify's record's own (another writer's,
            # caught between its temp file and the rename)
            target_rel = rel[: -len(name)] + target
            return target_rel in self.files or target_rel in (self.marker.name, VERIFIED_RECORD)
        # verify's record of a pass (crater_core.verify_file) describes the folder; it is never a user's file
        return rel in (self.marker.name, LOCK_NAME, VERIFIED_RECORD) or rel.startswith(JOBS_DIR + "/")

    def unlisted(self) -> list[str]:
        """Files (relative paths, sorted) that the marker does not list and that are not this writer's
        bookkeeping: the marker and lock, verify's record, ``.jobs/``, the temp files of listed files. In a
        shared folder, only files of the writer's ``names``."""
        found: list[str] = []
        if not self.path.is_dir():
            return found
        for root, dirs, files in os.walk(self.path):
            dirs.sort()
            rel_root = Path(root).relative_to(self.path).as_posix()
            for name in sorted(files):
                rel = name if rel_root == "." else f"{rel_root}/{name}"
                if self.names is not None and not self.names(rel):
                    continue
                if not self._is_bookkeeping(rel) and not self.proved(rel):
                    found.append(rel)
        return found

    def refuse(self, names: list[str]) -> None:
        """Raise the refusal naming the first of ``names`` (files this writer did not write)."""
        more = f" and {len(names) - 1} more" if len(names) > 1 else ""
        raise FolderError(
            f"{self.flag}={self.path} holds {self.path / names[0]}{more}, which crater-synth did not write "
            f"there as {what(self.kind)}: give a new or empty folder, or move the file away"
        )

    # -- claiming --------------------------------------------------------------------------------
    def claim(self) -> "OutFolder":
        """:meth:`check`, create the folder (and missing parents), take the lock, write the marker. A busy
        folder is refused naming its holder; any other refusal removes what this run created."""
        self.check()
        missing = [p for p in [self.path, *self.path.parents] if not p.exists()]
        ensure_writable_dir(self.path, self.flag.lstrip("-"))
        self._new_dirs = missing
        if not (self.path / LOCK_NAME).exists():
            self._new_files.append(self.path / LOCK_NAME)
        try:
            self._take_lock()
            self.check()  # the holder may have changed the folder while this run waited for nothing
            if not self.marker.exists():
                self._new_files.append(self.marker)
            self._write_marker()
        except DatasetBusyError:
            self._new_dirs, self._new_files = [], []  # another writer's folder now: nothing of it is ours
            raise
        except BaseException:
            self.discard()
            raise
        return self

    def lock(self) -> "OutFolder":
        """Take only the lock of an existing folder (no check, no marker): a command that changes a file of
        a folder another writer keeps (``nav-frames-relabel``) or reads one while writing beside it
        (``report``). Busy: refused naming the holder. :meth:`release` unlocks, the lock file staying;
        :meth:`discard` (a refused run) also removes it if this created it."""
        if not (self.path / LOCK_NAME).exists():
            self._new_files.append(self.path / LOCK_NAME)
        try:
            self._take_lock()
        except DatasetBusyError:
            self._new_files = []
            raise
        return self

    def _take_lock(self) -> None:
        self._lock = take_lock(self.path / LOCK_NAME, f"{self.flag}={self.path}", "folder")

    def _write_marker(self) -> None:
        doc = {"written_by": "crater-synth", "kind": self.kind, "what": what(self.kind), "subject": self.subject}
        doc["files"] = dict(sorted(self.files.items()))
        schema.atomic_write_text(self.marker, json.dumps(doc, indent=1, sort_keys=True) + "\n")

    def record(self, names: Iterable[str]) -> None:
        """List ``names`` (relative paths) as this writer's, in the marker, before they are written."""
        new = [n for n in names if n not in self.files]
        if new:
            self.files.update(dict.fromkeys(new))
            self._write_marker()

    def seal(self, names: Iterable[str]) -> None:
        """Record the size and mtime of ``names`` (written now, by this writer); a missing one is forgotten."""
        for n in names:
            try:
                st = (self.path / n).stat()
                self.files[n] = [st.st_size, st.st_mtime_ns]
            except FileNotFoundError:
                self.files.pop(n, None)
        self._write_marker()

    def owns(self, name: str) -> bool:
        return name in self.files

    def remove(self, names: Iterable[str]) -> None:
        """Delete ``names``, every one of which must be this writer's (:meth:`proved`), else the refusal."""
        names = list(names)
        foreign = [n for n in names if not self.proved(n)]
        if foreign:
            self.refuse(foreign)
        for n in names:
            (self.path / n).unlink(missing_ok=True)
            self.files.pop(n, None)
        self._write_marker()

    # -- ending ----------------------------------------------------------------------------------
    def discard(self) -> None:
        """Undo a refused run: remove the files it created (lock, marker), then the folders it created while
        they are empty. Nothing else."""
        self.release()
        for p in self._new_files:
            p.unlink(missing_ok=True)
        for d in self._new_dirs:
            try:
                d.rmdir()
            except OSError:
                break  # not empty: holds another's files
        self._new_dirs, self._new_files = [], []

    def release(self) -> None:
        if self._lock is not None:
            try:
                self._lock.seek(0)
                self._lock.truncate()  # no holder any more
                fcntl.flock(self._lock, fcntl.LOCK_UN)
            except OSError:
                pass
            finally:
                self._lock.close()
                self._lock = None

    def published(self) -> None:
        """The run wrote something: what it created is no longer to be undone."""
        self._new_dirs, self._new_files = [], []

    def __enter__(self) -> "OutFolder":
        return self.claim()

    def __exit__(self, exc_type, *_exc) -> None:
        if exc_type is None:
            self.release()
        else:
            self.discard()  # undoes only what a run that published nothing created
