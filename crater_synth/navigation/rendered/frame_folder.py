"""The folder ``crater-synth nav-frames`` writes: one trajectory's frames and their manifest, kept to the
output-folder contract of :mod:`crater_synth.outfolder` (docs/architecture.md, "Output folders").

- Its marker (``.crater-synth-navframes``) names the trajectory and lists the files the command wrote. A
  folder of another kind or trajectory is refused, as is one holding a file the marker does not list,
  unless that file proves itself: a frame of this trajectory (its header, then its sha256 recorded by a
  manifest row of this trajectory or its pixel seal), or a manifest of this trajectory's frames (a folder
  written before markers existed).
- The manifest is merged, never replaced: rows of frames not rendered in this run stay while their file
  still has the sha256 they record.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from crater_core import exr, schema
from crater_synth.outfolder import OutFolder

FRAME_FILE = re.compile(r"frame_\d{4,}\.exr")
KIND = "navframes"


def manifest_rows(out_dir: Path) -> list[dict] | None:
    """The rows of ``out_dir``'s manifest as JSON objects (None: no manifest, or a line that is not one)."""
    try:
        with open(Path(out_dir) / schema.MANIFEST_NAME, encoding="utf-8") as fh:
            rows = [json.loads(line) for line in fh if line.strip()]
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    return rows if all(isinstance(r, dict) for r in rows) else None


def _is_trajectory_manifest(out_dir: Path, trajectory: str) -> bool:
    """A manifest every row of which is a frame of ``trajectory`` (nav-frames' own, before markers)."""
    rows = manifest_rows(out_dir)
    return bool(rows) and all(
        r.get("trajectory") == trajectory and FRAME_FILE.fullmatch(str(r.get("rel_path", ""))) for r in rows
    )


def _looks_like_frame(path: Path, trajectory: str) -> bool:
    """An EXR whose header says it is a frame of ``trajectory`` at the index its name gives (proved later)."""
    try:
        attrs = exr.read_header(path)
    except (exr.ExrError, OSError, ValueError):
        return False
    return attrs.get("trajectory") == trajectory and f"frame_{int(attrs.get('frame', -1)):04d}.exr" == path.name


def claim_frames_folder(out_dir: Path, trajectory: str) -> OutFolder:
    """Check, create, lock and mark ``out_dir`` for ``trajectory``'s frames. Refused at once (nothing
    written): another kind's or trajectory's folder, and unlisted files that cannot be this trajectory's
    frames or manifest; the frames that may be are proved by :func:`adopt_unlisted` after planning."""
    folder = OutFolder(out_dir, KIND, subject=trajectory, prove=lambda p: _may_be_ours(p.parent, p.name, trajectory))
    folder.check_clean(lambda n: _may_be_ours(folder.path, n, trajectory))
    return folder.claim()


def _may_be_ours(folder: Path, name: str, trajectory: str) -> bool:
    """A manifest of ``trajectory``'s frames, or an EXR whose header says it is one of them."""
    if name == schema.MANIFEST_NAME:
        return _is_trajectory_manifest(folder, trajectory)
    return bool(FRAME_FILE.fullmatch(name)) and _looks_like_frame(folder / name, trajectory)


def adopt_unlisted(folder: OutFolder, proved: set[str], recorded: dict[str, str]) -> None:
    """List the unlisted files that prove themselves: a manifest of this trajectory's frames, a frame kept
    by this run (``proved``: header and sha256 or seal) or one whose bytes a manifest row records
    (``recorded``: rel_path -> sha256). Any other unlisted file refuses the run."""
    adopt, bad = [], []
    for name in folder.unlisted():
        if name == schema.MANIFEST_NAME and _is_trajectory_manifest(folder.path, folder.subject or ""):
            adopt.append(name)
        elif name in proved or (name in recorded and schema.sha256_file(folder.path / name) == recorded[name]):
            adopt.append(name)
        else:
            bad.append(name)
    if bad:
        folder.refuse(bad)
    folder.record(adopt)
    folder.seal(adopt)


def merged_rows(out_dir: Path, new_rows: dict[int, dict], reused: set[int]) -> list[dict]:
    """The manifest after a run: its rows of frames this run did not render (while their file still has
    the sha256 they record) and this run's rows, by frame index. A kept frame whose recorded row has its
    sha256 keeps the row's render time, so an unchanged frame keeps an identical row."""
    old = {}
    for r in manifest_rows(out_dir) or []:
        if isinstance(r.get("index"), int) and FRAME_FILE.fullmatch(str(r.get("rel_path", ""))):
            old[r["index"]] = r
    rows = {}
    for i, r in old.items():
        if i in new_rows:
            continue
        f = Path(out_dir) / r["rel_path"]
        if f.is_file() and schema.sha256_file(f) == r.get("sha256"):
            rows[i] = r
    for i, r in new_rows.items():
        prev = old.get(i)
        if i in reused and prev is not None and prev.get("sha256") == r["sha256"] and "render_seconds" in prev:
            r = dict(r, render_seconds=prev["render_seconds"])
        rows[i] = r
    return [rows[i] for i in sorted(rows)]
