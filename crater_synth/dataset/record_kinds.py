"""Record kinds of ``crater-synth export`` (docs/export.md, "Record kinds"): what one exported sample is.

- ``render``: a ``crater-synth dataset`` directory (crater-centred crops, crater_core.schema's manifest);
- ``navframe``: a ``crater-synth nav-frames`` directory (whole frames along a trajectory, their pose, Sun
  and the landmarks in view with projected rim ellipses and lit-rim fractions). Its manifest is read as
  data: this layer (dataset/) sits below crater_synth.navigation and never imports it;
- ``detection``: a ``crater-synth detection-frames`` directory (whole frames of procedural crater fields,
  their camera, Sun and the labels of every crater in view: :mod:`crater_synth.dataset.detection`).

:func:`detect_kind` tells the manifests apart by their rows' fields. The formats' writers are in
:mod:`crater_synth.dataset.export_writers`, the export loop in :mod:`crater_synth.dataset.export`.
"""

from __future__ import annotations

import functools
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np
import pyarrow as pa

from crater_core.detection_labels import DETECTION_LABEL_FIELDS, with_labels
from crater_core.exr import ExrError, exr_info, read_channel, read_exr, stored_dtype
from crater_core.schema import (
    EXR_CHANNELS,
    MANIFEST_NAME,
    NAVFRAME_ELLIPSE_FIELDS,
    NAVFRAME_LANDMARK_FIELDS,
    PARTS_DIR,
    iter_rows,
    json_object,
    manifest_lines,
)
from crater_core.verify_file import KIND_FIELDS
from crater_synth.errors import UserError


class ExportError(UserError):
    """The dataset cannot be exported as asked (bad dataset, channel, output directory)."""


# ------------------------------------------------------------------------------------------------
# Record kinds
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RecordKind:
    """What one exported sample is. A new kind (e.g. navigation frames and their landmarks) supplies:

    - ``rows(dataset_dir)``: (row count, iterator over its manifest rows, in a stable order);
    - ``key(row)``: a unique sample key without dots or slashes (WebDataset splits names at the dot);
    - ``arrays(dataset_dir, row, channels)``: ``{channel: ndarray}``, the lossless images;
    - ``label_fields()``: ``[(name, pyarrow type)]`` of the typed label columns;
    - ``labels(row)``: the typed label values (JSON-able) for those columns, of the row :attr:`inline` gives;
    - ``inline(dataset_dir, row)``: the row as a self-contained record (a detection row's labels read from
      the label file beside its frame; other rows as they are);
    - ``channels``: the channel names a user may ask for;
    - ``shape(dataset_dir, row)``: the (height, width) of its images (``export --shape pad``).
    """

    name: str
    rows: Callable[[Path], tuple[int, Iterator[dict]]]
    key: Callable[[dict], str]
    arrays: Callable[[Path, dict, Sequence[str]], dict[str, np.ndarray]]
    label_fields: Callable[[], list]
    labels: Callable[[dict], dict]
    channels: tuple[str, ...]
    shape: Callable[[Path, dict], tuple[int, int]]
    inline: Callable[[Path, dict], dict] = lambda _dataset_dir, row: row


def _render_rows(dataset_dir: Path) -> tuple[int, Iterator[dict]]:
    manifest = dataset_dir / MANIFEST_NAME
    if not manifest.is_file():
        raise ExportError(f"dataset {dataset_dir}: no {MANIFEST_NAME} (render it with `crater-synth dataset`)")
    parts = [p for p in (dataset_dir / PARTS_DIR).glob("*.jsonl") if p.stat().st_size] if dataset_dir.is_dir() else []
    if parts:
        raise ExportError(
            f"dataset {dataset_dir} has {len(parts)} unmerged manifest part(s) in {PARTS_DIR}/ (a run is going on or "
            "was killed): finish it with `crater-synth dataset` first"
        )
    # Every row is read once before the export starts: a bad line (not UTF-8, not JSON, not a row) is one
    # error naming it, and no shard is written from the rows above it.
    n = sum(1 for _ in iter_rows(manifest, strict=True))
    if n == 0:
        raise ExportError(f"dataset {dataset_dir}: {MANIFEST_NAME} has no rows")
    return n, iter_rows(manifest, strict=True)


def _render_key(row: dict) -> str:
    return row["path"].rsplit(".", 1)[0].replace("/", "_").replace(".", "p")


def _exr_arrays(dataset_dir: Path, rel: str, sha256: str, channels: Sequence[str]) -> dict[str, np.ndarray]:
    """The EXR's channels as stored (lossless), after checking the file against the manifest's sha256."""
    path = dataset_dir / rel
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ExportError(f"dataset {dataset_dir}: cannot read {rel} ({exc.strerror})") from None
    got = hashlib.sha256(data).hexdigest()
    if got != sha256:
        raise ExportError(
            f"dataset {dataset_dir}: {rel} has sha256 {got}, the manifest says {sha256} (run `crater-synth verify`)"
        )
    try:
        if len(channels) <= 2:  # decode only what is exported (the default is I/F alone)
            chans = {c: read_channel(path, c) for c in channels}
        else:
            chans, _ = read_exr(path)
    except ExrError as exc:
        raise ExportError(str(exc)) from None
    missing = [c for c in channels if c not in chans]
    if missing:
        raise ExportError(f"{path} has no channel(s) {missing}; it has {sorted(chans)}")
    # Readers get float32; a half channel converts back to float16 exactly: the file's own values and type.
    return {c: chans[c].astype(stored_dtype(c)) for c in channels}


def _render_arrays(dataset_dir: Path, row: dict, channels: Sequence[str]) -> dict[str, np.ndarray]:
    return _exr_arrays(dataset_dir, row["path"], row["sha256"], channels)


@functools.lru_cache(maxsize=None)
def _render_label_fields() -> list:
    f64, i64, s = pa.float64(), pa.int64(), pa.string()
    return [
        ("crater", s),
        ("sun_elevation", f64),
        ("sun_azimuth", f64),
        ("cam_elevation", f64),
        ("cam_azimuth", f64),
        ("range_m", f64),
        ("fov_deg", f64),
        ("frame_width", i64),
        ("width", i64),
        ("height", i64),
        ("crop_origin", pa.list_(f64)),
        ("center_px", pa.list_(f64)),
        ("rim_ellipse", pa.struct([("cu", f64), ("cv", f64), ("a", f64), ("b", f64), ("angle_rad", f64)])),
        ("sigma_boxes", pa.list_(pa.struct([("sigma", f64), ("box", pa.list_(f64))]))),
        ("lit_fraction", f64),
        ("mean_if", f64),
        ("path", s),
        ("sha256", s),
        ("index", i64),
        ("indices", pa.list_(i64)),
        ("seed", i64),
        ("terrain_id", s),
        ("render_digest", s),
        ("renderer", s),
        ("code_version", s),
        ("schema_version", i64),
    ]


def _render_labels(row: dict) -> dict:
    out = {name: row.get(name) for name, _ in _render_label_fields()}
    out["crop_origin"] = [float(v) for v in row.get("crop_origin") or []]
    out["sigma_boxes"] = [
        {"sigma": float(k), "box": [float(b) for b in v]}
        for k, v in sorted((row.get("sigma_boxes") or {}).items(), key=lambda kv: float(kv[0]))
    ]
    return out


RENDER = RecordKind(
    name="render",
    rows=_render_rows,
    key=_render_key,
    arrays=_render_arrays,
    label_fields=_render_label_fields,
    labels=_render_labels,
    channels=EXR_CHANNELS,
    shape=lambda _dataset_dir, row: (int(row["height"]), int(row["width"])),
)


# Navigation frames (``crater-synth nav-frames``, docs/navigation/rendered.md): ``frame_NNNN.exr``
# and a manifest row per frame with its pose and landmark labels. Read as data: this layer sits below
# crater_synth.navigation and never imports it.
_NAVFRAME_REQUIRED = ("trajectory", "index", "rel_path", "sha256", "landmarks")


def _json_rows(manifest: Path) -> Iterator[tuple[int, dict]]:
    """``(line number, row)`` of a JSON Lines file; a line that is not a JSON object is one error naming it."""
    for lineno, row, error in manifest_lines(manifest, json_object):
        if row is None:
            raise ExportError(str(error))
        yield lineno, row


def _navframe_rows(dataset_dir: Path) -> tuple[int, Iterator[dict]]:
    return _frame_rows(dataset_dir, _NAVFRAME_REQUIRED, "nav-frames")


def _frame_rows(
    dataset_dir: Path, required: tuple[str, ...], command: str, compact: bool = False
) -> tuple[int, Iterator[dict]]:
    """The rows of a whole-frame manifest written by ``crater-synth <command>``, each with ``required``.
    ``compact``: the manifest must be as a finished run leaves it (frame indices strictly increasing, the
    last line whole); a detection-frames run appends its rows chunk by chunk and compacts them when it ends,
    so a hard-killed run's manifest is refused, naming the command that compacts it."""
    manifest = dataset_dir / MANIFEST_NAME
    if not manifest.is_file():
        raise ExportError(
            f"dataset {dataset_dir}: no {MANIFEST_NAME} (render the frames with `crater-synth {command}`)"
        )
    uncompacted = (
        f"dataset {dataset_dir}: {MANIFEST_NAME} is the appended manifest of an interrupted `crater-synth {command}` "
        f"run: rerun that command on {dataset_dir} (same overrides) to finish and compact it, then export"
    )
    if compact and not _ends_whole(manifest):
        raise ExportError(uncompacted)

    def gen() -> Iterator[dict]:
        # the frame commands leave their manifest sorted by frame index: file order is the stable order.
        last = -1
        for lineno, row in _json_rows(manifest):
            missing = [f for f in required if f not in row]
            rel = str(row.get("rel_path", ""))
            if missing or rel.startswith("/") or ".." in Path(rel).parts:
                why = f"missing field(s) {missing}" if missing else f"rel_path {rel!r} leaves the directory"
                raise ExportError(f"{manifest}:{lineno}: not a {command} row ({why})")
            if compact:
                if not isinstance(row["index"], int) or row["index"] <= last:
                    raise ExportError(uncompacted)
                last = row["index"]
            yield row

    # Every row is checked once before the export starts, so a bad line writes no shard (as for renders).
    n = sum(1 for _ in gen())
    if n == 0:
        raise ExportError(f"dataset {dataset_dir}: {MANIFEST_NAME} has no rows")
    return n, gen()


def _ends_whole(path: Path) -> bool:
    """The file is empty or its last byte is a newline (a killed append leaves a torn last line)."""
    with open(path, "rb") as fh:
        end = fh.seek(0, os.SEEK_END)
        if end == 0:
            return True
        fh.seek(end - 1)
        return fh.read(1) == b"\n"


def _navframe_key(row: dict) -> str:
    return f"{row['trajectory']}_{Path(row['rel_path']).stem}".replace("/", "_").replace(".", "p")


def _navframe_arrays(dataset_dir: Path, row: dict, channels: Sequence[str]) -> dict[str, np.ndarray]:
    return _exr_arrays(dataset_dir, row["rel_path"], row["sha256"], channels)


def _navframe_shape(dataset_dir: Path, row: dict) -> tuple[int, int]:
    """A frame's (height, width) from its EXR header (the manifest records the width only)."""
    try:
        info = exr_info(dataset_dir / row["rel_path"], decode=False)
    except ExrError as exc:
        raise ExportError(str(exc)) from None
    return int(info["height"]), int(info["width"])


@functools.lru_cache(maxsize=None)
def _navframe_label_fields() -> list:
    f64, i64, s = pa.float64(), pa.int64(), pa.string()
    ellipse = pa.struct([(name, f64) for name in NAVFRAME_ELLIPSE_FIELDS])
    types = {"string": s, "float": f64, "float list": pa.list_(f64), "ellipse": ellipse, "bool": pa.bool_()}
    landmark = pa.struct([(name, types[kind]) for name, kind in NAVFRAME_LANDMARK_FIELDS])
    return [
        ("trajectory", s),
        ("frame_index", i64),
        ("rel_path", s),
        ("sha256", s),
        ("width_px", i64),
        ("fov_deg", f64),
        ("altitude_m", f64),
        ("frame_origin_lat", f64),
        ("frame_origin_lon", f64),
        ("camera_position_m", pa.list_(f64)),  # in the frame's ENU (origin: frame_origin_lat/lon)
        ("camera_rotation", pa.list_(pa.list_(f64))),  # 3 x 3, rows as in the manifest
        ("camera_position_mc_m", pa.list_(f64)),  # Moon-centred
        ("sun_elevation_deg", f64),
        ("sun_azimuth_deg", f64),
        ("ground_sample_m", f64),
        ("footprint_half_width_m", f64),
        ("lit_fraction", f64),
        ("mean_if", f64),
        ("landmarks", pa.list_(landmark)),
        ("mode", s),
        ("terrain_id", s),
        ("label_version", i64),
        ("landmark_map_sha256", s),  # the map the labels name landmarks from (null: labels before version 3)
        ("schema_version", i64),
    ]


def _navframe_labels(row: dict) -> dict:
    pose, cam, sun = row.get("pose") or {}, row.get("camera_enu") or {}, row.get("sun_enu") or {}
    origin = row.get("frame_origin") or {}
    landmarks = [
        {name: lm.get(name) for name, _ in NAVFRAME_LANDMARK_FIELDS}
        | {"id": None if lm.get("id") is None else str(lm["id"])}
        for lm in row.get("landmarks") or []
    ]
    return {
        "trajectory": row.get("trajectory"),
        "frame_index": row.get("index"),
        "rel_path": row.get("rel_path"),
        "sha256": row.get("sha256"),
        "width_px": pose.get("width_px"),
        "fov_deg": pose.get("fov_deg"),
        "altitude_m": pose.get("altitude_m"),
        "frame_origin_lat": origin.get("lat"),
        "frame_origin_lon": origin.get("lon"),
        "camera_position_m": cam.get("position_m"),
        "camera_rotation": cam.get("rotation"),
        "camera_position_mc_m": pose.get("position_mc_m"),
        "sun_elevation_deg": sun.get("elevation_deg"),
        "sun_azimuth_deg": sun.get("azimuth_deg"),
        "ground_sample_m": row.get("ground_sample_m"),
        "footprint_half_width_m": row.get("footprint_half_width_m"),
        "lit_fraction": row.get("lit_fraction"),
        "mean_if": row.get("mean_if"),
        "landmarks": landmarks,
        "mode": row.get("mode"),
        "terrain_id": row.get("terrain_id"),
        "label_version": row.get("label_version"),
        "landmark_map_sha256": (row.get("landmark_map") or {}).get("sha256"),
        "schema_version": row.get("schema_version"),
    }


NAVFRAME = RecordKind(
    name="navframe",
    rows=_navframe_rows,
    key=_navframe_key,
    arrays=_navframe_arrays,
    label_fields=_navframe_label_fields,
    labels=_navframe_labels,
    channels=RENDER.channels,
    shape=_navframe_shape,
)


# Detection frames (``crater-synth detection-frames``, docs/procedural.md): ``frame_NNNNNN.exr``, its label file
# (crater_core.detection_labels) and a row per frame with its camera, Sun, terrain and the label file's reference.
_DETECTION_REQUIRED = ("index", "rel_path", "sha256", "terrain", "labels")


@functools.lru_cache(maxsize=None)
def _detection_label_fields() -> list:
    f64, i64, s = pa.float64(), pa.int64(), pa.string()
    ellipse = pa.struct([(name, f64) for name in NAVFRAME_ELLIPSE_FIELDS])
    types = {"int": i64, "string": s, "float": f64, "float list": pa.list_(f64), "ellipse": ellipse, "bool": pa.bool_()}
    label = pa.struct([(name, types[kind]) for name, kind in DETECTION_LABEL_FIELDS])
    return [
        ("frame_index", i64),
        ("rel_path", s),
        ("sha256", s),
        ("width_px", i64),
        ("fov_deg", f64),
        ("camera_position_m", pa.list_(f64)),  # in the patch's ENU frame (origin: patch_lat/lon)
        ("camera_rotation", pa.list_(pa.list_(f64))),  # 3 x 3, rows as in the manifest
        ("sun_elevation_deg", f64),
        ("sun_azimuth_deg", f64),
        ("off_nadir_deg", f64),
        ("view_azimuth_deg", f64),
        ("range_m", f64),
        ("ground_sample_m", f64),
        ("lit_fraction", f64),
        ("mean_if", f64),
        ("terrain_field", i64),
        ("terrain_seed", i64),
        ("terrain_id", s),
        ("terrain_size_px", i64),
        ("terrain_spacing_m", f64),
        ("patch_lat", f64),
        ("patch_lon", f64),
        ("labels", pa.list_(label)),
        ("mode", s),
        ("label_version", i64),
        ("schema_version", i64),
    ]


def _detection_labels(row: dict) -> dict:
    cam, sun = row.get("camera_enu") or {}, row.get("sun_enu") or {}
    view, terrain = row.get("view") or {}, row.get("terrain") or {}
    return {
        "frame_index": row.get("index"),
        "rel_path": row.get("rel_path"),
        "sha256": row.get("sha256"),
        "width_px": cam.get("width_px"),
        "fov_deg": cam.get("fov_deg"),
        "camera_position_m": cam.get("position_m"),
        "camera_rotation": cam.get("rotation"),
        "sun_elevation_deg": sun.get("elevation_deg"),
        "sun_azimuth_deg": sun.get("azimuth_deg"),
        "off_nadir_deg": view.get("off_nadir_deg"),
        "view_azimuth_deg": view.get("view_azimuth_deg"),
        "range_m": view.get("range_m"),
        "ground_sample_m": row.get("ground_sample_m"),
        "lit_fraction": row.get("lit_fraction"),
        "mean_if": row.get("mean_if"),
        "terrain_field": terrain.get("field"),
        "terrain_seed": terrain.get("seed"),
        "terrain_id": terrain.get("terrain_id"),
        "terrain_size_px": terrain.get("size_px"),
        "terrain_spacing_m": terrain.get("spacing_m"),
        "patch_lat": terrain.get("patch_lat"),
        "patch_lon": terrain.get("patch_lon"),
        "labels": [{name: lb.get(name) for name, _ in DETECTION_LABEL_FIELDS} for lb in row.get("labels") or []],
        "mode": row.get("mode"),
        "label_version": row.get("label_version"),
        "schema_version": row.get("schema_version"),
    }


DETECTION = RecordKind(
    name="detection",
    rows=lambda d: _frame_rows(d, _DETECTION_REQUIRED, "detection-frames", compact=True),
    key=lambda row: Path(row["rel_path"]).stem.replace(".", "p"),
    arrays=_navframe_arrays,
    label_fields=_detection_label_fields,
    labels=_detection_labels,
    channels=RENDER.channels,
    shape=_navframe_shape,
    inline=with_labels,
)
RECORD_KINDS: dict[str, RecordKind] = {k.name: k for k in (RENDER, NAVFRAME, DETECTION)}

_KIND_FIELDS = KIND_FIELDS  # the fields that tell the manifests apart (shared with verify)


def detect_kind(dataset_dir: str | os.PathLike) -> str | None:
    """The record kind of ``dataset_dir``'s manifest, from its first row's fields (None: no readable row)."""
    manifest = Path(dataset_dir) / MANIFEST_NAME
    if not manifest.is_file():
        return None
    _, first = next(_json_rows(manifest), (0, None))
    if first is None:
        return None
    found = [k for k, fields in _KIND_FIELDS.items() if all(f in first for f in fields)]
    if len(found) != 1:
        raise ExportError(
            f"dataset {dataset_dir}: {MANIFEST_NAME} is neither a render manifest (rows with path, crater), a "
            "nav-frames manifest (rows with rel_path, trajectory, landmarks) nor a detection-frames manifest "
            "(rows with rel_path, terrain, labels)"
        )
    return found[0]
