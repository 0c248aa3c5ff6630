"""A detection frame's labels as columns, in a file beside its frame (``frame_NNNNNN.labels.npz``).

A saturated crater field puts ~1,000 labels in a 256 px frame. As JSON in the manifest row they were
~400 KB a frame (9 GB for a 22,272-frame set, a third of its disk, parsed whole by every reader). As
columns (one array per label field) in a deflated ``.npz`` they are ~6 x smaller, and a reader that needs
a few columns (training's rim circles) takes them as arrays without building a dict per crater.

The file is a zip of ``.npy`` arrays, one per field of :data:`DETECTION_LABEL_FIELDS`, length N (an
``ellipse`` field is N x 5 in :data:`ELLIPSE_KEYS` order, a ``float list`` N x k), plus ``format``.
Floats are float64, so every value the labeller wrote reads back exactly; a float that is None in a label
is NaN in its column. It is written with fixed zip timestamps, so the same labels are the same bytes
(the frame's row records their sha256), and read with ``allow_pickle=False``.

The manifest row keeps ``labels`` as the file's reference, ``{"file", "sha256", "count", "format"}``.
Rows written before the file existed hold the labels inline as a list; every reader here takes both.
numpy and the standard library only: ``verify`` (crater_core) and ``train/`` read it too.
"""

from __future__ import annotations

import hashlib
import io
import os
import zipfile
from pathlib import Path
from typing import Iterable

import numpy as np

from crater_core import schema
from crater_core.errors import ContractError

LABEL_FILE_FORMAT = 1
LABEL_FILE_SUFFIX = ".labels.npz"
# A label's fields, in order, with their kinds (the typed columns of `crater-synth export --kind detection`).
DETECTION_LABEL_FIELDS = (
    ("id", "int"),
    ("source", "string"),
    ("ellipse", "ellipse"),
    ("centre_px", "float list"),
    ("x_m", "float"),
    ("y_m", "float"),
    ("diameter_m", "float"),
    ("rim_diameter_m", "float"),
    ("depth_m", "float"),
    ("rim_height_m", "float"),
    ("degradation", "float"),
    ("class", "string"),
    ("is_secondary", "bool"),
    ("visible_rim_fraction", "float"),
    ("emission_deg", "float"),
    ("rim_inside", "bool"),
    ("lit_rim_fraction", "float"),
    ("occluded_rim_fraction", "float"),
    ("occluded", "bool"),
)
ELLIPSE_KEYS = ("cu", "cv", "a", "b", "angle_rad")
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # the zip format's earliest date: fixed, so the bytes are the labels'
_DEFLATE_LEVEL = 6


class LabelFileError(ContractError):
    """A detection frame's label file is missing, unreadable or not what its row says."""


def label_file_name(frame_rel_path: str) -> str:
    """The label file of the frame ``frame_rel_path`` (``frame_000012.exr`` -> ``frame_000012.labels.npz``)."""
    p = Path(frame_rel_path)
    return str(p.with_name(p.stem + LABEL_FILE_SUFFIX))


def _float(v) -> float:
    return np.nan if v is None else float(v)


def to_columns(labels: list[dict]) -> dict[str, np.ndarray]:
    """The columns of ``labels`` (module docstring). A field is a column when every label has it, and
    absent when none has; a field some labels lack is a ValueError."""
    n = len(labels)
    cols: dict[str, np.ndarray] = {}
    for name, kind in DETECTION_LABEL_FIELDS:
        has = sum(1 for lb in labels if name in lb)
        if has == 0 and n:
            continue
        if has != n:
            raise ValueError(f"label field {name!r} is in {has} of {n} labels: in all or in none")
        values = [lb[name] for lb in labels]
        if kind == "int":
            cols[name] = np.array(values, dtype=np.int64)
        elif kind == "string":
            cols[name] = np.array(values, dtype=str) if n else np.zeros(0, dtype="<U1")
        elif kind == "bool":
            cols[name] = np.array(values, dtype=bool)
        elif kind == "float":
            cols[name] = np.array([_float(v) for v in values], dtype=np.float64)
        elif kind == "ellipse":
            cols[name] = np.array([[_float(e[k]) for k in ELLIPSE_KEYS] for e in values], np.float64).reshape(n, 5)
        else:  # float list, one length for every label
            rows = [[_float(x) for x in v] for v in values]
            cols[name] = np.array(rows, dtype=np.float64).reshape(n, len(rows[0]) if n else 0)
    return cols


def _value(kind: str, v):
    if kind == "int":
        return int(v)
    if kind == "string":
        return str(v)
    if kind == "bool":
        return bool(v)
    if kind == "float":
        return None if np.isnan(v) else float(v)
    if kind == "ellipse":
        return {k: _value("float", x) for k, x in zip(ELLIPSE_KEYS, v)}
    return [_value("float", x) for x in v]


def from_columns(cols: dict[str, np.ndarray]) -> list[dict]:
    """The label dicts of ``cols`` (:func:`to_columns` inverted exactly, fields in their order)."""
    fields = [(name, kind) for name, kind in DETECTION_LABEL_FIELDS if name in cols]
    n = len(cols[fields[0][0]]) if fields else 0
    lists = {name: cols[name].tolist() for name, _ in fields}
    return [{name: _value(kind, lists[name][i]) for name, kind in fields} for i in range(n)]


def encode(labels: list[dict]) -> bytes:
    """The label file's bytes for ``labels``: the same labels give the same bytes."""
    cols = to_columns(labels) | {"format": np.array(LABEL_FILE_FORMAT, dtype=np.int64)}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=_DEFLATE_LEVEL) as zf:
        for name, arr in cols.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            with zf.open(info, "w") as fh:
                np.lib.format.write_array(fh, arr, allow_pickle=False)
    return buf.getvalue()


def write_label_file(path: str | os.PathLike, labels: list[dict], rel: str) -> dict:
    """Write ``labels`` to ``path`` atomically; returns the row's reference to it (``rel``: its path in the
    folder)."""
    data = encode(labels)
    schema.atomic_write_bytes(path, data)
    return {"file": rel, "sha256": hashlib.sha256(data).hexdigest(), "count": len(labels), "format": LABEL_FILE_FORMAT}


def label_ref(row: dict) -> dict | None:
    """The row's reference to its label file; None for a row holding its labels inline."""
    labels = row.get("labels")
    return labels if isinstance(labels, dict) else None


def label_rel_paths(row: dict) -> list[str]:
    """The files of a frame's row besides its frame: its label file (none for inline labels)."""
    ref = label_ref(row)
    return [] if ref is None else [str(ref.get("file"))]


def label_count(row: dict) -> int:
    """How many labels the row's frame has (from the reference or the inline list)."""
    ref = label_ref(row)
    return int(ref["count"]) if ref is not None else len(row.get("labels") or [])


def label_path(dataset_dir: str | os.PathLike, row: dict) -> Path | None:
    """The row's label file (None: inline labels); a path leaving the folder is a LabelFileError."""
    ref = label_ref(row)
    if ref is None:
        return None
    try:
        return schema.row_file(dataset_dir, {"path": str(ref.get("file", ""))})
    except schema.ManifestError as exc:
        raise LabelFileError(f"frame {row.get('rel_path')}: label file: {exc}") from None


def decode(data: bytes, what: str, names: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """The columns in a label file's bytes (``names``: those of them the file has; each column is inflated
    only when asked for, ~65 us each); anything else is one LabelFileError naming ``what``."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            keep = None if names is None else {*names, "format"}
            cols = {k: npz[k] for k in npz.files if keep is None or k in keep}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise LabelFileError(f"{what}: not a detection label file ({exc})") from None
    if int(cols.pop("format", -1)) != LABEL_FILE_FORMAT:
        raise LabelFileError(f"{what}: label file format is not {LABEL_FILE_FORMAT}")
    lengths = {len(v) for v in cols.values()}
    if len(lengths) > 1:
        raise LabelFileError(f"{what}: label columns of different lengths {sorted(lengths)}")
    return cols


def read_label_columns(
    dataset_dir: str | os.PathLike, row: dict, names: Iterable[str] | None = None
) -> dict[str, np.ndarray]:
    """The row's labels as columns (module docstring): its label file's, or its inline labels'; ``names``:
    only those columns (a reader of a few columns skips inflating the others)."""
    path = label_path(dataset_dir, row)
    if path is None:
        cols = to_columns(row.get("labels") or [])
        keep = None if names is None else set(names)
        return {k: v for k, v in cols.items() if keep is None or k in keep}
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise LabelFileError(f"{path}: cannot read the frame's labels ({exc.strerror or exc})") from None
    cols = decode(data, str(path), names)
    fault = _count_fault(cols, row, path)
    if fault:
        raise LabelFileError(fault)
    return cols


def read_labels(dataset_dir: str | os.PathLike, row: dict) -> list[dict]:
    """The row's labels as dicts, as the labeller wrote them."""
    if label_ref(row) is None:
        return list(row.get("labels") or [])
    return from_columns(read_label_columns(dataset_dir, row))


def with_labels(dataset_dir: str | os.PathLike, row: dict) -> dict:
    """The row with its labels inline (a copy when they were in a file)."""
    return row if label_ref(row) is None else row | {"labels": read_labels(dataset_dir, row)}


def label_file_faults(dataset_dir: str | os.PathLike, row: dict, sha: bool = True) -> list[str]:
    """Every fault of the row's label file (none for inline labels): inside the folder, readable, hashing
    to the row's sha256 (``sha``), columns of the row's count."""
    ref = label_ref(row)
    if ref is None:
        return []
    try:
        path = label_path(dataset_dir, row)
        assert path is not None
        data = path.read_bytes()
    except LabelFileError as exc:
        return [str(exc)]
    except OSError as exc:
        return [f"{Path(dataset_dir) / str(ref.get('file'))}: label file missing or unreadable ({exc.strerror or exc})"]
    if sha and hashlib.sha256(data).hexdigest() != ref.get("sha256"):
        return [f"{path}: sha256 differs from the manifest row's"]
    try:
        cols = decode(data, str(path))
    except LabelFileError as exc:
        return [str(exc)]
    fault = _count_fault(cols, row, path)
    return [fault] if fault else []


def _count_fault(cols: dict[str, np.ndarray], row: dict, path: Path) -> str | None:
    """The fault of label columns whose length is not the row's count (None when it is)."""
    n = len(next(iter(cols.values()))) if cols else 0
    return None if n == label_count(row) else f"{path}: {n} labels, the row says {label_count(row)}"
