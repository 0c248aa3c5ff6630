"""One verification for every record kind: a manifest row against its EXR (docs/manifest.md, "What
verify checks").

Two record kinds hold EXRs beside a ``manifest.jsonl`` (``crater_synth.dataset.record_kinds``):
``render`` (``crater-synth dataset``: one crater-centred crop per row) and ``navframe``
(``crater-synth nav-frames``: one whole frame per row, its pose, Sun and landmarks in view). For one row
:func:`file_faults` checks, one line per fault naming the file:

- the file stays inside the dataset (no path or link leading out), exists and hashes to the row's sha256;
- it opens as a tiled EXR with the contract's channels and the row's size;
- its header carries the labels the row states -- renders: :func:`crater_core.render_labels.label_faults`;
  navigation frames: the trajectory, frame index, pose, terrain, render mode, patch Sun and the worker's
  stats, and the row's frame-ENU camera and Sun computed again from that pose;
- with ``decode``: every pixel is finite and the pixels and sealed attributes give the header's seal
  (:func:`crater_core.exr.sealed_attrs`), so no pixel changed since the renderer wrote the file, even
  when the row's sha256 was written anew to match.

The landmarks of a navigation frame are computed from its pose and the landmark map after the frame is
rendered, so its header does not carry them: they are checked through the pose they were computed
from (and, by the navigation readers, the map identity the row records).

``crater-synth verify`` records a passing result in ``<dataset>/.verified.json`` (:func:`write_record`):
the manifest's sha256 and each file's identity (size, mtime_ns, inode). Consumers (train, export,
nav-frames-eval, navigate) trust it for the files whose identity is unchanged (:func:`trusted_paths`)
and run :func:`file_faults` on the others (:func:`rows_faults`).

numpy and the standard library only (EXRs through :mod:`crater_core.exr`): ``train/`` uses it too.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from crater_core import schema
from crater_core.detection_labels import label_file_faults, label_rel_paths
from crater_core.exr import SEAL_ATTR, ExrError, exr_info, read_exr, sealed_attrs
from crater_core.render_labels import label_faults
from crater_core.trajectory import FramePose

RECORD_NAME = ".verified.json"
RECORD_FORMAT = 1
STATS_ATTR = "crater_synth:stats"
NAVFRAME_REQUIRED = ("trajectory", "index", "rel_path", "sha256", "frame_origin", "pose", "mode", "terrain_id")
# Row values recomputed from the recorded pose agree with the row to the last printed digit of a float.
DERIVED_TOLERANCE = 1e-9
STATS_TOLERANCE = 1e-12


# The fields that tell one manifest from the other (each kind's rows carry all of its own, none of the other's).
KIND_FIELDS = {
    "render": ("path", "crater"),
    "navframe": ("rel_path", "trajectory", "landmarks"),
    "detection": ("rel_path", "terrain", "labels"),
}


def manifest_kind(dataset_dir: str | os.PathLike) -> str | None:
    """The record kind whose fields the first row of the dataset's manifest carries; None where there is
    no manifest, no row, an unreadable first line, or a row of neither kind (the kind's reader says why)."""
    try:
        with open(Path(dataset_dir) / schema.MANIFEST_NAME, "rb") as fh:
            first = next((line for line in fh if line.strip()), b"")
        row = json.loads(first.decode("utf-8")) if first else None
    except (OSError, UnicodeDecodeError, ValueError, RecursionError):
        return None
    if not isinstance(row, dict):
        return None
    found = [k for k, fields in KIND_FIELDS.items() if all(f in row for f in fields)]
    return found[0] if len(found) == 1 else None


def rel_path_of(kind: str, row: dict) -> str:
    """The file a row names, relative to its dataset."""
    return str(row["path"] if kind == "render" else row["rel_path"])


def row_files(kind: str, row: dict) -> list[str]:
    """Every file a row names, relative to its dataset: its frame and, for a detection row, its label file."""
    return [rel_path_of(kind, row), *(label_rel_paths(row) if kind == "detection" else [])]


def dataset_file(dataset_dir: str | os.PathLike, rel: str) -> Path:
    """``dataset_dir / rel``; a :class:`crater_core.schema.ManifestError` when the path or a link in it
    leads outside the dataset (:func:`crater_core.schema.row_file`)."""
    return schema.row_file(dataset_dir, {"path": rel})


def file_identity(path: str | os.PathLike) -> list[int]:
    """(size, mtime_ns, inode) of a file: changes whenever its bytes are rewritten or replaced."""
    st = os.stat(path)
    return [int(st.st_size), int(st.st_mtime_ns), int(st.st_ino)]


# ------------------------------------------------------------------------------------------------
# One row against its file
# ------------------------------------------------------------------------------------------------
def _open_faults(f: Path, sha256: str, decode: bool, sha: bool) -> tuple[list[str], dict | None]:
    """(faults, the file's facts) of what every kind shares: exists, hashes right, opens as a tiled EXR
    with the contract's channels, finite pixels and an intact seal (``decode``). Facts: None when the
    file cannot be read at all."""
    if not f.is_file():
        return [f"{f}: missing"], None
    if sha and schema.sha256_file(f) != sha256:
        return [f"{f}: sha256 mismatch (corrupt or changed)"], None
    channels: dict[str, np.ndarray] = {}
    info: dict
    try:
        if decode:
            channels, header = read_exr(f)
            shape = next(iter(channels.values())).shape if channels else (0, 0)
            info = {
                "channels": tuple(channels),
                "height": shape[0],
                "width": shape[1],
                "tiled": int(header.get("tile_width") or 0) > 0,
                "finite": all(bool(np.isfinite(a).all()) for a in channels.values()),
                "header": header,
            }
        else:
            info = exr_info(f, decode=False)
    except ExrError as exc:
        return [str(exc)], None
    faults = []
    expected = set(schema.EXR_CHANNELS)
    if set(info["channels"]) != expected:
        faults.append(f"{f}: channels {sorted(info['channels'])} != {sorted(expected)}")
    if not info["tiled"]:
        faults.append(f"{f}: not tiled")
    if info["finite"] is False:
        faults.append(f"{f}: non-finite pixels")
    # A header without any crater-synth attribute is one fault of the kind's label check, not two.
    ours = any(str(k).startswith("crater_synth:") for k in info["header"])
    if decode and ours and not faults and sealed_attrs(channels, info["header"]) is None:
        why = "carries no pixel seal" if SEAL_ATTR not in info["header"] else "pixel seal broken"
        faults.append(f"{f}: {why} (its pixels or header are not those its renderer wrote)")
    return faults, info


def _size_fault(f: Path, info: dict, width, height) -> list[str]:
    if (info["width"], info["height"]) != (width, height):
        return [f"{f}: size {info['width']}x{info['height']} != row {width}x{height}"]
    return []


def _stats_faults(f: Path, row: dict, header: dict) -> list[str]:
    """The row's lit_fraction and mean_if against the worker's stats in the header (where it wrote them)."""
    if STATS_ATTR not in header:
        return []
    try:
        stats = json.loads(header[STATS_ATTR])
        return [
            f"{f}: row {k} {row.get(k)!r} but the EXR header says {stats[k]!r}"
            for k in ("lit_fraction", "mean_if")
            if not _close(row.get(k), stats[k], STATS_TOLERANCE)
        ]
    except (TypeError, ValueError, KeyError):
        return [f"{f}: the EXR header's {STATS_ATTR} is not the worker's stats"]


def render_faults(dataset_dir: str | os.PathLike, row: dict, decode: bool = True, sha: bool = True) -> list[str]:
    """Faults of a (validated) render row's file; ``sha=False`` leaves the hash to the caller."""
    faults, f, info = _file_faults(dataset_dir, row["path"], row["sha256"], (row["width"], row["height"]), decode, sha)
    if info is None:
        return faults
    header = info["header"]
    return faults + label_faults(row, header, str(f)) + _stats_faults(f, row, header)


def _file_faults(dataset_dir, rel: str, sha256: str, size, decode: bool, sha: bool):
    """(faults, file, facts) every kind's check starts with: the file inside the dataset, exists, hashes
    right, opens with the contract's channels (:func:`_open_faults`) at the row's ``size`` (width, height).
    Facts None: nothing more can be read of the file."""
    try:
        f = dataset_file(dataset_dir, rel)
    except schema.ManifestError as exc:
        return [str(exc)], None, None
    faults, info = _open_faults(f, sha256, decode, sha)
    if info is not None:
        faults += _size_fault(f, info, *size)
    return faults, f, info


def _close(a, b, tol: float = DERIVED_TOLERANCE) -> bool:
    """Equal JSON-like values, numbers to ``tol`` (relative and absolute)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k], tol) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_close(x, y, tol) for x, y in zip(a, b))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return math.isclose(a, b, rel_tol=tol, abs_tol=tol)
    return a == b


def navframe_header_for_row(row: dict) -> dict:
    """The header entries :func:`navframe_faults` reads, from a nav-frames row (for writers other than
    ``crater-synth nav-frames``, e.g. test fixtures, so that their frames carry their labels the same way;
    the patch's Sun and origin are checked only where a header has them)."""
    return {
        "trajectory": str(row["trajectory"]),
        "frame": int(row["index"]),
        "pose_mc": json.dumps(row["pose"], sort_keys=True),
        "terrain_id": str(row["terrain_id"]),
        "crater_synth:mode": str(row["mode"]),
        STATS_ATTR: json.dumps({"lit_fraction": row.get("lit_fraction"), "mean_if": row.get("mean_if")}),
    }


def _navframe_header_faults(f: Path, row: dict, header: dict) -> list[str]:
    """The row's frame labels against what ``crater-synth nav-frames`` wrote into the frame's header."""
    if "pose_mc" not in header or "trajectory" not in header:
        return [f"{f}: the EXR header carries no frame pose (not written by `crater-synth nav-frames`)"]
    try:
        pose_mc = json.loads(header["pose_mc"])
        patch_origin = json.loads(header.get("patch_origin") or "null")
    except (TypeError, ValueError):
        return [f"{f}: the EXR header's pose_mc or patch_origin is not JSON"]
    patch = row.get("patch") or {}
    checks = [
        ("trajectory", row["trajectory"], header.get("trajectory")),
        ("index", row["index"], header.get("frame")),
        ("pose", row["pose"], pose_mc),
        ("terrain_id", row["terrain_id"], header.get("terrain_id")),
        ("mode", row["mode"], header.get("crater_synth:mode")),
    ]
    if patch_origin is not None:
        checks.append(("patch lat, lon", [patch.get("lat"), patch.get("lon")], patch_origin))
    if "crater_synth:sun_elevation" in header:
        sun = patch.get("sun_enu") or {}
        for k in ("elevation", "azimuth"):  # header floats are float32
            got = float(np.float32(header[f"crater_synth:sun_{k}"]))
            row_v = sun.get(f"{k}_deg")
            checks.append((f"patch sun_enu {k}_deg", None if row_v is None else float(np.float32(row_v)), got))
    return [_differs(f, name, want, got) for name, want, got in checks if not _close(want, got)]


def _differs(f: Path, name: str, want, got) -> str:
    """One line naming the row's field (and, for a record such as the pose, its entries) that the header contradicts."""
    if isinstance(want, dict) and isinstance(got, dict):
        keys = sorted(k for k in set(want) | set(got) if not _close(want.get(k), got.get(k)))
        parts = []
        for k in keys:
            a, b = want.get(k), got.get(k)
            try:  # a position: by how far
                off = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
                parts.append(f"{name}.{k} (off by {float(np.linalg.norm(off)):.6g})")
            except (TypeError, ValueError):
                parts.append(f"{name}.{k}")
        return f"{f}: row {', '.join(parts)} differs from what the EXR header records"
    return f"{f}: row {name} {_show(want)} but the EXR header says {_show(got)}"


def _show(v) -> str:
    text = json.dumps(v) if isinstance(v, (dict, list)) else repr(v)
    return text if len(text) <= 80 else text[:77] + "..."


def _navframe_derived_faults(f: Path, row: dict) -> list[str]:
    """The row's frame-ENU labels computed again from its pose (the header proves the pose)."""
    try:
        pose = FramePose.from_dict(row["pose"])
        lat0, lon0 = float(row["frame_origin"]["lat"]), float(row["frame_origin"]["lon"])
    except (KeyError, TypeError, ValueError):
        return [f"{f}: row pose or frame_origin is not a frame pose"]
    faults = []
    if not _close([lat0, lon0], [pose.target_lat, pose.target_lon]):
        faults.append(f"{f}: row frame_origin ({lat0}, {lon0}) is not the pose's target")
    cam = pose.pose_enu(lat0, lon0)
    want = {"position_m": [float(v) for v in cam.position], "rotation": cam.rotation.tolist()}
    if "camera_enu" in row and not _close(row["camera_enu"], want, 1e-6):
        faults.append(f"{f}: row camera_enu is not the camera of the row's pose")
    sun_el, sun_az = pose.sun_enu(lat0, lon0)
    if "sun_enu" in row and not _close(row["sun_enu"], {"elevation_deg": sun_el, "azimuth_deg": sun_az}, 1e-6):
        faults.append(f"{f}: row sun_enu is not the Sun of the row's pose")
    return faults


def navframe_faults(dataset_dir: str | os.PathLike, row: dict, decode: bool = True, sha: bool = True) -> list[str]:
    """Faults of a nav-frames row's frame; ``sha=False`` leaves the hash to the caller."""
    missing = [k for k in NAVFRAME_REQUIRED if k not in row]
    if missing:
        return [f"{dataset_dir}: frame row {row.get('index')!r} lacks {missing} (not a nav-frames row)"]
    width = (row.get("pose") or {}).get("width_px")
    faults, f, info = _file_faults(dataset_dir, str(row["rel_path"]), row["sha256"], (width, width), decode, sha)
    if info is None:
        return faults
    header = info["header"]
    return (
        faults
        + _navframe_header_faults(f, row, header)
        + _navframe_derived_faults(f, row)
        + _stats_faults(f, row, header)
    )


def detection_faults(dataset_dir: str | os.PathLike, row: dict, decode: bool = True, sha: bool = True) -> list[str]:
    """A detection frame's row (``crater-synth detection-frames``): its file inside the folder, its sha256,
    the contract's channels at the row's size and, with ``decode``, finite pixels under an intact seal; its
    label file inside the folder, hashing to the row's sha256, of the row's count
    (:func:`crater_core.detection_labels.label_file_faults`). Its labels come from the procedural crater
    table, not from the header, so there is no header label to compare."""
    width = (row.get("camera_enu") or {}).get("width_px")
    faults = _file_faults(dataset_dir, str(row["rel_path"]), row["sha256"], (width, width), decode, sha)[0]
    return faults + label_file_faults(dataset_dir, row, sha)


FILE_CHECKS: dict[str, Callable[..., list[str]]] = {
    "render": render_faults,
    "navframe": navframe_faults,
    "detection": detection_faults,
}


def file_faults(
    kind: str, dataset_dir: str | os.PathLike, row: dict, decode: bool = True, sha: bool = True
) -> list[str]:
    """Every fault of one row's file, the check of its record kind (:data:`FILE_CHECKS`)."""
    return FILE_CHECKS[kind](dataset_dir, row, decode, sha)


# ------------------------------------------------------------------------------------------------
# The recorded result
# ------------------------------------------------------------------------------------------------
def manifest_sha256(dataset_dir: str | os.PathLike) -> str:
    return schema.sha256_file(Path(dataset_dir) / schema.MANIFEST_NAME)


def write_record(dataset_dir: str | os.PathLike, kind: str, rows: Iterable[dict], decode: bool) -> Path:
    """Record a passing verification of ``rows`` (the whole manifest) in ``<dataset_dir>/.verified.json``."""
    d = Path(dataset_dir)
    files = {}
    for row in rows:
        for rel in row_files(kind, row):
            files[rel] = file_identity(dataset_file(d, rel))
    record = {
        "format": RECORD_FORMAT,
        "kind": kind,
        "decode": bool(decode),
        "manifest_sha256": manifest_sha256(d),
        "files": files,
    }
    schema.atomic_write_json(d / RECORD_NAME, record)
    return d / RECORD_NAME


def read_record(dataset_dir: str | os.PathLike, kind: str, decode: bool = False) -> dict | None:
    """The recorded verification of the dataset's current manifest (of ``kind``; with ``decode``: one
    that decoded the pixels), or None."""
    d = Path(dataset_dir)
    try:
        record = json.loads((d / RECORD_NAME).read_text(encoding="utf-8"))
        ok = (
            record["format"] == RECORD_FORMAT
            and record["kind"] == kind
            and (record["decode"] or not decode)
            and record["manifest_sha256"] == manifest_sha256(d)
            and isinstance(record["files"], dict)
        )
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return record if ok else None


def trusted_paths(dataset_dir: str | os.PathLike, kind: str, decode: bool = False) -> set[str]:
    """The files (relative paths) a still-valid recorded verification covers: same manifest, same identity."""
    record = read_record(dataset_dir, kind, decode)
    if record is None:
        return set()
    out = set()
    for rel, ident in record["files"].items():
        try:
            if file_identity(dataset_file(dataset_dir, rel)) == ident:
                out.add(rel)
        except (OSError, schema.ManifestError):
            continue
    return out


def rows_faults(
    kind: str, dataset_dir: str | os.PathLike, rows: Sequence[dict], decode: bool = False, sha: bool = True
) -> list[str]:
    """Faults of ``rows``' files, each checked unless a valid recorded verification covers it unchanged."""
    trusted = trusted_paths(dataset_dir, kind, decode)
    faults: list[str] = []
    for row in rows:
        if not trusted.issuperset(row_files(kind, row)):
            faults += file_faults(kind, dataset_dir, row, decode, sha)
    return faults


def identity_digest(dataset_dir: str | os.PathLike, kind: str, rows: Iterable[dict]) -> str:
    """A digest of the identity of every row's file (size, mtime_ns, inode): it changes when any file is
    rewritten, replaced or deleted (then :class:`OSError` naming it). Keys caches built from the files."""
    h = hashlib.sha256()
    for row in rows:
        for rel in row_files(kind, row):
            h.update(json.dumps([rel, file_identity(dataset_file(dataset_dir, rel))]).encode())
    return h.hexdigest()[:16]
