"""Render manifest: the one contract between the renderer (blender_gen/, crater_synth/) and train/.

Format (documented in docs/manifest.md): JSON Lines, one row per render, ``schema_version`` in every
row. While rendering, each writer appends rows to its own part file
(``manifest.parts/<name>.jsonl``; append + flush per row, fsync per row or per batch of rows:
:class:`RowAppender`), so a kill -9 can at worst leave a truncated last line, which readers skip.
``merge_parts`` writes the sorted, de-duplicated ``manifest.jsonl`` atomically. Rows carry no
timestamps: the same config and seed give byte-identical manifests.

Every EXR holds the channels of :data:`EXR_CHANNELS` (stored as :data:`EXR_CHANNEL_TYPES`, tiled,
losslessly compressed; readers get float32) and the render parameters in its header; pixel boxes in
rows are in the EXR's (crop) pixel coordinates.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, TextIO

from crater_core.errors import ContractError

SCHEMA_VERSION = 1
_UMASK = os.umask(0)
os.umask(_UMASK)
MANIFEST_NAME = "manifest.jsonl"
PARTS_DIR = "manifest.parts"

# EXR channel names: radiance factor, camera depth (m along the view axis), world-space (ENU) unit
# normal, and the fraction of the solar disk visible (1 lit, 0 in shadow, fractional in penumbra).
EXR_CHANNELS = ("IF", "depth", "N.X", "N.Y", "N.Z", "lit")
# Stored pixel type of each channel. I/F and depth stay float32 (depth is tens of km: half would step
# by 16 m). The unit normal and the lit fraction are bounded by 1, so half (11-bit significand) keeps
# them to <= 2.4e-4 (0.014 deg of normal direction): far below the shading's tolerances, and it takes
# 45 % off every EXR and off its encoding time (docs/renderer.md, "EXR size").
EXR_CHANNEL_TYPES = {"IF": "float", "depth": "float", "N.X": "half", "N.Y": "half", "N.Z": "half", "lit": "half"}

# One landmark label of a navigation frame's manifest row (``crater-synth nav-frames``), in order, with its
# value type: written by crater_synth.navigation.rendered.labels, exported column by column by
# crater_synth.dataset.record_kinds. "ellipse" is the projected rim (cu, cv, a, b, angle_rad; px, rad);
# the two fractions are null when under half of the rim lies in the frame (and the occluded one in
# frames labelled before it existed).
NAVFRAME_LANDMARK_FIELDS = (
    ("id", "string"),
    ("name", "string"),
    ("diameter_km", "float"),
    ("lat", "float"),
    ("lon", "float"),
    ("centre_px", "float list"),
    ("depth_m", "float"),
    ("ellipse", "ellipse"),
    ("rim_inside", "bool"),
    ("lit_rim_fraction", "float"),
    ("occluded_rim_fraction", "float"),
)
NAVFRAME_ELLIPSE_FIELDS = ("cu", "cv", "a", "b", "angle_rad")

REQUIRED_FIELDS = {
    "schema_version": int,
    "crater": str,
    "index": int,
    "indices": list,
    "sun_elevation": float,
    "sun_azimuth": float,
    "cam_elevation": float,
    "cam_azimuth": float,
    "range_m": float,
    "fov_deg": float,
    "width": int,
    "height": int,
    "frame_width": int,
    "crop_origin": list,
    "center_px": list,
    "rim_ellipse": dict,
    "sigma_boxes": dict,
    "lit_fraction": float,
    "mean_if": float,
    "path": str,
    "sha256": str,
    "seed": int,
    "code_version": str,
    "renderer": str,
    "terrain_id": str,
    "render_digest": str,
}


class ManifestError(ContractError):
    """A manifest or one of its rows is malformed."""


def params_key(
    crater: str, sun_elevation: float, sun_azimuth: float, cam_elevation: float, cam_azimuth: float
) -> tuple:
    """Identity of a render: its crater and angles (not the flat index, which depends on the grid,
    so a grown grid -- the closed loop -- resumes the same dataset)."""
    return (
        crater,
        round(float(sun_elevation), 6),
        round(float(sun_azimuth), 6),
        round(float(cam_elevation), 6),
        round(float(cam_azimuth), 6),
    )


def row_key(row: dict) -> tuple:
    return params_key(row["crater"], row["sun_elevation"], row["sun_azimuth"], row["cam_elevation"], row["cam_azimuth"])


def render_rel_path(
    crater: str, sun_elevation: float, sun_azimuth: float, cam_elevation: float, cam_azimuth: float
) -> str:
    """Deterministic file name of a render inside a dataset directory."""
    return f"{crater}/se{sun_elevation:06.3f}_sa{sun_azimuth:07.3f}_ce{cam_elevation:06.3f}_ca{cam_azimuth:07.3f}.exr"


def json_object(row, where: str = "manifest row") -> dict:
    """``row`` when it is a JSON object (the least any manifest's row is); a :class:`ManifestError` otherwise."""
    if not isinstance(row, dict):
        raise ManifestError(f"{where}: a JSON {_json_kind(row)} where a row (a JSON object) should be")
    return row


def validate_row(row: dict, where: str = "manifest row") -> dict:
    """Check that ``row`` is a JSON object with every required field of the right type and a ``path``
    that stays inside the dataset directory (:func:`check_rel_path`); returns it."""
    json_object(row, where)
    missing = [k for k in REQUIRED_FIELDS if k not in row]
    if missing:
        raise ManifestError(f"{where}: missing field(s) {missing}")
    for key, typ in REQUIRED_FIELDS.items():
        val = row[key]
        ok = isinstance(val, (int, float)) and not isinstance(val, bool) if typ is float else isinstance(val, typ)
        if not ok:
            raise ManifestError(f"{where}: field {key!r} should be {typ.__name__}, got {val!r}")
    if row["schema_version"] != SCHEMA_VERSION:
        raise ManifestError(f"{where}: schema_version {row['schema_version']} != {SCHEMA_VERSION}")
    check_rel_path(row["path"], where)
    return row


def _json_kind(value) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, (int, float)):
        return "number"
    names: dict[type, str] = {str: "string", list: "array"}
    return names.get(type(value), type(value).__name__)


def check_rel_path(rel: str, where: str = "manifest row") -> str:
    """A row's ``path`` must name a file inside the dataset directory: relative, without ``..``, empty
    or ``.`` parts, and without a NUL byte. Anything else is refused (a row is never allowed to make a
    reader hash, decode or train on a file outside the dataset). Returns ``rel``."""
    parts = rel.split("/")
    if not rel or rel.startswith("/") or "\0" in rel or any(p in ("", ".", "..") for p in parts):
        raise ManifestError(f"{where}: path {rel!r} leaves the dataset directory (a path relative to it is required)")
    return rel


def row_file(dataset_dir: str | os.PathLike, row: dict) -> Path:
    """The file of a validated row: ``dataset_dir / row["path"]``, refused with :class:`ManifestError`
    when a symbolic link takes it outside ``dataset_dir`` (the path itself is checked by
    :func:`validate_row`). A file that does not exist is returned as it is (callers report it)."""
    d = Path(dataset_dir)
    rel = check_rel_path(row["path"], f"{d}: row")
    cur = d
    for part in rel.split("/"):  # without a link below d, a checked relative path stays inside d
        cur = cur / part
        if cur.is_symlink():
            break
    else:
        return cur
    f = d / rel
    target = f.resolve()
    if not target.is_relative_to(d.resolve()):
        raise ManifestError(f"{f}: leaves the dataset directory (a link to {target})")
    return f


def duplicate_faults(rows: Iterable[dict]) -> list[str]:
    """Rows that must not stand side by side in one manifest: the same render twice (its crater and
    angles), one file under two rows, or two rows whose files have the same sha256 (a copied file
    under another label). One line per conflict, in manifest order."""
    faults: list[str] = []
    seen: dict[str, dict] = {"key": {}, "path": {}, "sha256": {}}
    for i, row in enumerate(rows):
        for what, value in (("path", row["path"]), ("sha256", row["sha256"]), ("key", row_key(row))):
            first = seen[what].setdefault(value, (i, row))
            if first[0] == i:
                continue
            other = first[1]
            if what == "key":
                faults.append(f"duplicate row {value}: one render listed twice ({other['path']} and {row['path']})")
            elif what == "path":
                faults.append(f"duplicate path {value}: one file under two rows ({_label(other)} and {_label(row)})")
            else:
                faults.append(
                    f"duplicate sha256 {value[:16]}...: {other['path']} ({_label(other)}) and {row['path']} "
                    f"({_label(row)}) are the same file"
                )
    return faults


def _label(row: dict) -> str:
    sun, cam = f"{row['sun_elevation']}/{row['sun_azimuth']}", f"{row['cam_elevation']}/{row['cam_azimuth']}"
    return f"{row['crater']} sun {sun} cam {cam}"


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def dumps_row(row: dict) -> str:
    """Canonical one-line JSON (sorted keys) so manifests are byte-comparable."""
    return json.dumps(row, sort_keys=True, separators=(",", ":"))


def append_row(part_path: str | os.PathLike, row: dict) -> None:
    """Durably append one validated row to a part file (write + flush + fsync)."""
    with RowAppender(part_path, max_rows=1) as out:
        out.add(row)


class RowAppender:
    """Appends validated rows to a part file: each row is written at once (a full disk fails on that
    row; a process killed with -9 leaves it in the file), and fsynced in batches, once per ``max_rows``
    rows or ``max_age_s`` seconds (at 50+ renders/s a per-row fsync dominated the host's time). Only a
    machine crash can lose the rows written since the last fsync; their EXRs are rendered again."""

    def __init__(self, part_path: str | os.PathLike, max_rows: int = 256, max_age_s: float = 2.0):
        self.path, self.max_rows, self.max_age_s = Path(part_path), max_rows, max_age_s
        self._fh: TextIO | None = None
        self._unsynced = 0
        self._t_first = 0.0

    def add(self, row: dict) -> None:
        line = dumps_row(validate_row(row)) + "\n"
        if self._fh is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = open(self.path, "a", encoding="utf-8")
        self._fh.write(line)
        self._fh.flush()
        if not self._unsynced:
            self._t_first = time.monotonic()
        self._unsynced += 1
        if self._unsynced >= self.max_rows or time.monotonic() - self._t_first >= self.max_age_s:
            self.sync()

    def sync(self) -> None:
        if self._fh is not None and self._unsynced:
            os.fsync(self._fh.fileno())
            self._unsynced = 0

    def close(self) -> None:
        """fsync what is left and close the file (again: a no-op)."""
        if self._fh is None:
            return
        try:
            self.sync()
        finally:
            fh, self._fh = self._fh, None
            fh.close()

    def __enter__(self) -> "RowAppender":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def manifest_lines(
    path: str | os.PathLike, validate: Callable[[Any, str], dict] = validate_row
) -> Iterator[tuple[int, dict | None, str | None]]:
    """``(line number, row, None)`` for every valid row of a JSONL manifest and ``(line number, None,
    "<path>:<line>: unreadable row (<why>)")`` for every line that is not one: a truncated or corrupt
    line, JSON that is not an object (``null``, ``42``), bytes that are not UTF-8, a row failing
    ``validate`` (:func:`validate_row`, a render manifest's: a missing field, a path leaving the dataset;
    :func:`json_object` for the frame manifests). Blank lines are skipped."""
    path = Path(path)
    with open(path, "rb") as fh:  # bytes: one bad line must not make the whole file unreadable
        for lineno, raw in enumerate(fh, 1):
            if not raw.strip():
                continue
            where = f"{path}:{lineno}"
            try:
                yield lineno, validate(json.loads(raw.decode("utf-8")), where), None
            except UnicodeDecodeError as exc:
                bad = f"byte 0x{raw[exc.start]:02x} at column {exc.start + 1}"
                yield lineno, None, f"{where}: unreadable row (not UTF-8 text: {bad})"
            except json.JSONDecodeError as exc:
                yield lineno, None, f"{where}: unreadable row (not JSON: {exc.msg} at column {exc.colno})"
            except (ManifestError, RecursionError) as exc:
                yield lineno, None, f"{where}: unreadable row ({exc})"


def iter_rows(path: str | os.PathLike, strict: bool = False) -> Iterator[dict]:
    """Rows of a JSONL manifest. An unreadable line (:func:`manifest_lines`: a truncated line of a
    killed writer, a corrupt or hand-edited one) is skipped unless ``strict``, in which case it raises
    :class:`ManifestError` naming the file and line."""
    path = Path(path)
    if not path.exists():
        if strict:
            raise ManifestError(f"manifest {path} does not exist")
        return
    for _, row, error in manifest_lines(path):
        if row is not None:
            yield row
        elif strict:
            raise ManifestError(str(error))


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temp file in the same directory and an atomic rename: readers
    see the old file or the new one, never a half-written one."""
    atomic_write_chunks(path, [data])


def atomic_write_chunks(path: str | os.PathLike, chunks: Iterable[bytes]) -> None:
    """:func:`atomic_write_bytes` of the bytes ``chunks`` yields, written as they come (a file larger
    than the memory it may take)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file normal permissions
        with os.fdopen(fd, "wb") as fh:
            for chunk in chunks:
                fh.write(chunk)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """UTF-8 text through :func:`atomic_write_bytes`."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj, indent: int = 1) -> None:
    """``obj`` as the project's JSON layout (indented, sorted keys, trailing newline), written atomically."""
    atomic_write_text(path, json.dumps(obj, indent=indent, sort_keys=True) + "\n")


def content_key(obj, length: int = 16) -> str:
    """A short content hash of a JSON-able object: the first ``length`` hex digits of the SHA-256 of its
    canonical JSON (sorted keys; non-JSON values by ``str``). Fingerprints of terrain patches, renders
    and training runs all use this one definition, so equal inputs give equal keys everywhere."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:length]


def sorted_unique(rows: Iterable[dict]) -> list[dict]:
    """Rows sorted by :func:`row_key`; for duplicate keys the last one wins."""
    by_key = {row_key(r): r for r in rows}
    return [by_key[k] for k in sorted(by_key)]


def write_manifest(path: str | os.PathLike, rows: Iterable[dict]) -> int:
    rows = sorted_unique(rows)
    atomic_write_text(path, "".join(dumps_row(r) + "\n" for r in rows))
    return len(rows)


def dataset_rows(dataset_dir: str | os.PathLike) -> list[dict]:
    """All rows known in a dataset directory: the merged manifest plus any part files."""
    d = Path(dataset_dir)
    rows = list(iter_rows(d / MANIFEST_NAME))
    parts = d / PARTS_DIR
    if parts.is_dir():
        for part in sorted(parts.glob("*.jsonl")):
            rows.extend(iter_rows(part))
    return sorted_unique(rows)


def merge_parts(
    dataset_dir: str | os.PathLike, parts: Iterable[str | os.PathLike] | None = None, keep: set[tuple] | None = None
) -> int:
    """Merge part files (default: all of them) into ``manifest.jsonl`` atomically, under an exclusive
    lock so concurrent shards cannot lose each other's rows; merged part files are removed.
    ``keep`` optionally restricts the result to those row keys. Returns the row count."""
    d = Path(dataset_dir)
    d.mkdir(parents=True, exist_ok=True)
    with open(d / ".manifest.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        part_files = sorted((d / PARTS_DIR).glob("*.jsonl")) if parts is None else [Path(p) for p in parts]
        rows = list(iter_rows(d / MANIFEST_NAME))
        for part in part_files:
            rows.extend(iter_rows(part))
        rows = sorted_unique(rows)
        if keep is not None:
            rows = [r for r in rows if row_key(r) in keep]
        n = write_manifest(d / MANIFEST_NAME, rows)
        for part in part_files:
            Path(part).unlink(missing_ok=True)
    return n


def load_manifest(dataset_dir_or_file: str | os.PathLike) -> list[dict]:
    """Strictly read a merged manifest (a file, or a dataset directory containing one)."""
    p = Path(dataset_dir_or_file)
    if p.is_dir():
        p = p / MANIFEST_NAME
    return list(iter_rows(p, strict=True))


def manifest_digest(rows: Iterable[dict]) -> str:
    """Content hash of a set of rows (keys the training cache)."""
    h = hashlib.sha256()
    for r in sorted_unique(rows):
        h.update(dumps_row(r).encode())
    return h.hexdigest()[:16]
