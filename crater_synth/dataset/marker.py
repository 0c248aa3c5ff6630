"""Which directories are datasets, and which files in them ``crater-synth dataset`` may remove.

A dataset directory holds a marker file, :data:`MARKER_NAME`, written when ``crater-synth dataset``
first claims the directory (a directory written before markers existed is recognised by its
``manifest.jsonl`` or ``manifest.parts/`` and gets its marker then). ``dataset`` refuses a directory
that is neither empty nor a dataset, naming a file in it, and writes nothing there; a directory marked for
another kind of output (crater_synth.outfolder: navigation frames, an export), or an unmarked one whose
``manifest.jsonl`` holds navigation frames, is no dataset.

In a dataset the only files ``dataset`` ever removes are its own bookkeeping (merged manifest parts,
``.jobs/`` entries, the lock and marker of a refused run in a directory it had just created) and the
temp files of interrupted writes of the manifest or of a planned render's file. A rendered file is
never deleted: one that cannot be proved (crater_synth.dataset.recover) is rendered again in place.
Every other file is left alone; those in the renders' directories are named in a warning.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from crater_core import schema
from crater_core.files import ensure_writable_dir
from crater_core.verify_file import RECORD_NAME as VERIFIED_RECORD
from crater_synth.dataset.disk import JOBS_DIR, LOCK_FILE, MARKER_NAME, temp_target
from crater_synth.errors import UserError
from crater_synth.outfolder import marker_kind, refuse_kind

MANIFEST_LOCK = ".manifest.lock"
# Names in a dataset's top level that crater-synth writes besides the renders' directories.
BOOKKEEPING = frozenset(
    {MARKER_NAME, LOCK_FILE, MANIFEST_LOCK, JOBS_DIR, schema.PARTS_DIR, schema.MANIFEST_NAME, VERIFIED_RECORD}
)


def _is_bookkeeping(name: str) -> bool:
    """A top-level name crater-synth writes (or its temp file while another run writes it)."""
    if name.startswith(".") and (name.endswith(".tmp") or name.endswith(".tmp.exr")):
        name = temp_target(Path(name)) or name
    return name in BOOKKEEPING or (name.startswith(".dataset-shard") and name.endswith(".lock"))


def is_dataset(out_dir: Path) -> bool:
    """A dataset directory: it has the marker, or (written before markers) no other kind's marker and a
    render manifest or manifest parts."""
    d = Path(out_dir)
    if (d / MARKER_NAME).is_file():
        return True
    if marker_kind(d) is not None or _holds_navframes(d):
        return False
    return (d / schema.MANIFEST_NAME).is_file() or (d / schema.PARTS_DIR).is_dir()


def _holds_navframes(d: Path) -> bool:
    """An unmarked directory whose manifest's first row is a navigation frame's (``crater-synth nav-frames``
    wrote it before markers existed)."""
    try:
        with open(d / schema.MANIFEST_NAME, encoding="utf-8") as fh:
            first = next((line for line in fh if line.strip()), "")
        row = json.loads(first)
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(row, dict) and "trajectory" in row and "rel_path" in row


def _foreign(out_dir: Path) -> list[Path]:
    """Files of a directory that is no dataset, other than crater-synth's bookkeeping (sorted, capped)."""
    found: list[Path] = []
    for root, dirs, files in os.walk(out_dir):
        dirs.sort()
        here = Path(root)
        for name in sorted(files):
            if here == out_dir and _is_bookkeeping(name):
                continue
            found.append(here / name)
            if len(found) > 10:
                return found
        if here == out_dir:
            dirs[:] = [d for d in dirs if d not in (JOBS_DIR, schema.PARTS_DIR)]
    return found


class DatasetClaim:
    """``crater-synth dataset``'s hold on ``out_dir``: checks that the directory is new, empty or a
    dataset (:meth:`check`), creates it (:meth:`create`), writes the marker (:meth:`mark`), and undoes
    all of it for a run refused before it rendered anything (:meth:`discard`)."""

    def __init__(self, out_dir: Path):
        self.out_dir = Path(out_dir)
        self._new_dirs: list[Path] = []
        self._new_files: list[Path] = []

    def check(self) -> None:
        """Refuse (one line naming a file in it) a directory that is neither empty nor a dataset."""
        d = self.out_dir
        if not d.is_dir():
            return
        refuse_kind(d, "dataset", "out_dir")
        if not (d / MARKER_NAME).is_file() and _holds_navframes(d):
            raise UserError(
                f"out_dir={d} holds navigation frames ({d / schema.MANIFEST_NAME} of `crater-synth nav-frames`), "
                "not a dataset: give another directory"
            )
        if is_dataset(d):
            return
        foreign = _foreign(d)
        if foreign:
            more = f" and {len(foreign) - 1}{'+' if len(foreign) > 10 else ''} more" if len(foreign) > 1 else ""
            raise UserError(
                f"out_dir={d} is not a crater-synth dataset (no {MARKER_NAME}) and is not empty: it holds "
                f"{foreign[0]}{more}; give a new or empty directory (crater-synth writes and deletes only "
                "in directories it created)"
            )

    def create(self) -> None:
        """Create ``out_dir`` (and missing parents), remembering what was new; check it is writable."""
        self.check()
        missing = [p for p in [self.out_dir, *self.out_dir.parents] if not p.exists()]
        ensure_writable_dir(self.out_dir, "out_dir")
        self._new_dirs = missing  # deepest first
        self._remember_new(LOCK_FILE, MANIFEST_LOCK, JOBS_DIR, schema.PARTS_DIR)

    def _remember_new(self, *names: str) -> None:
        self._new_files += [self.out_dir / n for n in names if not (self.out_dir / n).exists()]

    def mark(self) -> None:
        """Write the marker (atomically) unless it is there."""
        marker = self.out_dir / MARKER_NAME
        if marker.is_file():
            return
        self._remember_new(MARKER_NAME)
        text = json.dumps({"written_by": "crater-synth", "what": "rendered dataset (docs/manifest.md)"}) + "\n"
        schema.atomic_write_text(marker, text)

    def discard(self) -> None:
        """Remove what this run created, for a run refused before rendering: the bookkeeping files it
        created (never anything else), then the directories it created, if they are empty."""
        for p in self._new_files:
            try:
                p.rmdir() if p.is_dir() else p.unlink(missing_ok=True)
            except OSError:
                pass  # not empty or gone: left as it is
        for d in self._new_dirs:
            try:
                d.rmdir()
            except OSError:
                break  # not empty: the user's, or another run's
