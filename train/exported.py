"""PyTorch datasets over a ``crater-synth export`` directory (docs/export.md, "Loading an export in PyTorch").

- :class:`ParquetExport`: a map-style ``torch.utils.data.Dataset`` over the Parquet shards: random access
  through the row groups (the last decoded row group is kept, per process, so a sequential pass decodes
  each row group once);
- :class:`WebDatasetExport`: an ``IterableDataset`` streaming the tar shards. Each DataLoader worker reads
  its own shards (worker ``k`` of ``n`` takes shards ``k, k + n, ...``), so every sample is read exactly once
  whatever ``num_workers``; a worker left without a shard yields nothing;
- :func:`open_export`: the one of the two that the export's format (``export.json``) calls for.

A sample is ``(image, labels)``: ``image`` a float32 tensor (C, H, W), the exported channels in the
index's order; ``labels`` a dict the default collate batches: ``key``, every typed label that is a
scalar (float, int, string, bool) or a struct of scalars (``rim_ellipse``), and what the shape mode
adds (``sigma`` for crops; ``orig_height``, ``orig_width`` and the bool mask ``valid`` (H, W) for
padded images). A missing value is NaN (float), -1 (int), ``""`` (string) or False, never None (which
the default collate refuses). Variable-length labels (``sigma_boxes``, ``landmarks``, ...) and the
verbatim manifest row are in :meth:`ParquetExport.record` and :func:`iter_records`. ``as_dict=True``
returns one dict with the image under ``"image"``.

Native (variable-shape) exports load too (each image at its own shape); a batch of them needs equal
shapes (``--shape crop`` or ``pad``) or a custom ``collate_fn``.

Reads with pyarrow and the standard library's ``tarfile``: no ``datasets``, ``webdataset``, click or
Hydra, and never ``crater_synth`` (train/ sits below it). ``crater_synth.data`` is the public name.
"""

from __future__ import annotations

import bisect
import io
import json
import math
import tarfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from torch.utils.data import Dataset, IterableDataset, get_worker_info

from train.errors import DatasetError

INDEX_FILE = "export.json"
VALID = "valid"  # the pad mask column / member
SCALARS = ("float64", "int64", "string", "bool")
_MISSING = {"float64": math.nan, "int64": -1, "string": "", "bool": False}


def read_index(export_dir: str | Path) -> dict:
    """The export's index (``export.json``); a directory without one is not a complete export."""
    path = Path(export_dir) / INDEX_FILE
    if not path.is_file():
        raise DatasetError(f"{export_dir}: no {INDEX_FILE}: not a complete `crater-synth export` (run it again)")
    try:
        index = json.loads(path.read_text())
        if not isinstance(index.get("channels"), dict) or not isinstance(index.get("shards"), list):
            raise ValueError("no channels or shards")
    except (OSError, ValueError, AttributeError) as exc:
        raise DatasetError(f"{path}: not an export index ({exc})") from None
    return index


@dataclass
class ExportRecord:
    """One exported sample as stored: ``arrays`` by channel (numpy), the typed ``labels`` (every column,
    lists included), the verbatim manifest ``row`` and, for a padded export, the ``valid`` mask."""

    key: str
    arrays: dict[str, np.ndarray]
    labels: dict
    row: dict
    valid: np.ndarray | None = None


def _collatable(index: dict) -> dict:
    """The label columns the default collate can batch: scalars and structs of scalars."""
    kinds = index.get("labels", {})
    return {
        name: kind
        for name, kind in kinds.items()
        if kind in SCALARS or (isinstance(kind, dict) and all(k in SCALARS for k in kind.values()))
    }


def _fill(kind, value):
    if isinstance(kind, dict):
        value = value if isinstance(value, dict) else {}
        return {k: _fill(sub, value.get(k)) for k, sub in kind.items()}
    return _MISSING[kind] if value is None else value


def _channels(index: dict, channels: Sequence[str] | None, export_dir) -> list[str]:
    chans = list(index["channels"]) if channels is None else list(channels)
    bad = [c for c in chans if c not in index["channels"]]
    if bad:
        raise DatasetError(f"export {export_dir} has no channel(s) {bad}; it has {', '.join(index['channels'])}")
    return chans


class _ExportBase:
    """What both datasets share: the index, the channels, and a record as a collate-able sample."""

    format = ""

    def __init__(self, export_dir: str | Path, channels: Sequence[str] | None = None, as_dict: bool = False):
        self.export_dir = Path(export_dir)
        self.index = read_index(export_dir)
        if self.index.get("format") != self.format:
            raise DatasetError(
                f"export {export_dir} is in {self.index.get('format')} format, not {self.format}: use open_export()"
            )
        self.channels = _channels(self.index, channels, export_dir)
        self.as_dict = bool(as_dict)
        self.shape_mode = self.index.get("shape", {}).get("mode", "native")
        self._kinds = _collatable(self.index)
        self.shards = [self.export_dir / s["file"] for s in self.index["shards"]]

    def __len__(self) -> int:
        return int(self.index["rows"])

    def sample(self, rec: ExportRecord):
        """``(image, labels)`` (or one dict with ``as_dict``) of a record."""
        image = torch.from_numpy(np.stack([np.asarray(rec.arrays[c], dtype=np.float32) for c in self.channels]))
        labels = {"key": rec.key} | {name: _fill(kind, rec.labels.get(name)) for name, kind in self._kinds.items()}
        if rec.valid is not None:
            labels[VALID] = torch.from_numpy(np.asarray(rec.valid) != 0)
        return labels | {"image": image} if self.as_dict else (image, labels)


# ------------------------------------------------------------------------------------------------
# Parquet
# ------------------------------------------------------------------------------------------------
def _array2d(column: pa.ChunkedArray, shape: Sequence[int]) -> np.ndarray:
    """An ``Array2D`` column (Hugging Face extension type, or its list-of-lists storage when ``datasets``
    is not imported) as an (N, H, W) array."""
    arr = column.combine_chunks()
    if isinstance(arr.type, pa.ExtensionType):
        arr = arr.storage
    values = arr.flatten().flatten().to_numpy(zero_copy_only=False)
    return values.reshape(len(arr), *shape)


class _RowGroup:
    """One decoded row group: its records, built on demand."""

    def __init__(self, table: pa.Table, index: dict, channels: Sequence[str]):
        fixed = index.get("shape", {}).get("mode", "native") != "native"
        self.keys = table.column("key").to_pylist()
        self.rows = table.column("labels_json").to_pylist()
        images = {c: index["channels"][c]["column"] for c in channels}
        if fixed:
            shape = index["shape"]["shape"]
            self.images = {c: _array2d(table.column(col), shape) for c, col in images.items()}
        else:
            self.images = {c: table.column(col).to_pylist() for c, col in images.items()}
        self.fixed = fixed
        self.valid = _array2d(table.column(VALID), index["shape"]["shape"]) if VALID in table.column_names else None
        label_cols = [n for n in index.get("labels", {}) if n in table.column_names]
        self.labels = table.select(label_cols).to_pylist()

    def record(self, i: int) -> ExportRecord:
        arrays = {
            c: (a[i] if self.fixed else np.load(io.BytesIO(a[i]), allow_pickle=False)) for c, a in self.images.items()
        }
        valid = None if self.valid is None else self.valid[i]
        return ExportRecord(self.keys[i], arrays, self.labels[i], json.loads(self.rows[i]), valid)


class ParquetExport(_ExportBase, Dataset):
    """Map-style dataset over a Parquet export: ``ds[i]`` -> ``(image (C, H, W) float32, labels dict)``."""

    format = "parquet"

    def __init__(self, export_dir: str | Path, channels: Sequence[str] | None = None, as_dict: bool = False):
        super().__init__(export_dir, channels, as_dict)
        self._groups: list[tuple[int, int]] = []  # (shard, row group)
        self._starts: list[int] = []
        total = 0
        for si, path in enumerate(self.shards):
            meta = pq.ParquetFile(path).metadata
            for g in range(meta.num_row_groups):
                self._groups.append((si, g))
                self._starts.append(total)
                total += meta.row_group(g).num_rows
        if total != len(self):
            raise DatasetError(f"export {export_dir}: its shards hold {total} rows, {INDEX_FILE} says {len(self)}")
        self._columns = ["key", "labels_json"] + [self.index["channels"][c]["column"] for c in self.channels]
        self._columns += [VALID] if self.shape_mode == "pad" else []
        self._columns += [n for n in self.index.get("labels", {}) if n not in self._columns]
        self._cached: tuple[int, _RowGroup] | None = None

    def __getstate__(self):  # a worker process decodes its own row groups
        return self.__dict__ | {"_cached": None}

    def _group(self, gi: int) -> _RowGroup:
        if self._cached is None or self._cached[0] != gi:
            si, g = self._groups[gi]
            table = pq.ParquetFile(self.shards[si]).read_row_group(g, columns=self._columns)
            self._cached = (gi, _RowGroup(table, self.index, self.channels))
        return self._cached[1]

    def record(self, i: int) -> ExportRecord:
        """Sample ``i`` as stored (every label, the manifest row)."""
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"sample {i} of an export of {n}")
        i %= n
        gi = bisect.bisect_right(self._starts, i) - 1
        return self._group(gi).record(i - self._starts[gi])

    def __getitem__(self, i: int):
        return self.sample(self.record(int(i)))


# ------------------------------------------------------------------------------------------------
# WebDataset
# ------------------------------------------------------------------------------------------------
def _tar_samples(path: Path) -> Iterator[tuple[str, dict[str, bytes]]]:
    """(key, {extension: bytes}) of a WebDataset tar shard, streamed (members of a key are adjacent)."""
    key, parts = None, {}
    with tarfile.open(path, "r|") as tf:
        for member in tf:
            if not member.isfile():
                continue
            k, _, ext = member.name.partition(".")
            if k != key and key is not None:
                yield key, parts
                parts = {}
            key = k
            parts[ext] = tf.extractfile(member).read()
    if key is not None:
        yield key, parts


def _tar_record(key: str, parts: dict[str, bytes], index: dict, channels: Sequence[str], path) -> ExportRecord:
    try:
        meta = json.loads(parts["json"])
        arrays = {c: np.load(io.BytesIO(parts[index["channels"][c]["column"]])) for c in channels}
    except (KeyError, ValueError) as exc:
        raise DatasetError(f"{path}: sample {key} is incomplete or unreadable ({exc})") from None
    valid = np.load(io.BytesIO(parts[f"{VALID}.npy"])) if f"{VALID}.npy" in parts else None
    return ExportRecord(key, arrays, meta, meta.get("manifest_row", {}), valid)


class WebDatasetExport(_ExportBase, IterableDataset):
    """Streaming dataset over a WebDataset export, its shards split across DataLoader workers."""

    format = "webdataset"

    def worker_shards(self) -> list[Path]:
        """The shards of this DataLoader worker (all of them outside a worker)."""
        info = get_worker_info()
        return self.shards if info is None else self.shards[info.id :: info.num_workers]

    def records(self) -> Iterator[ExportRecord]:
        for path in self.worker_shards():
            for key, parts in _tar_samples(path):
                yield _tar_record(key, parts, self.index, self.channels, path)

    def __iter__(self):
        return (self.sample(rec) for rec in self.records())


def open_export(export_dir: str | Path, channels: Sequence[str] | None = None, as_dict: bool = False):
    """:class:`ParquetExport` or :class:`WebDatasetExport`, as the export's format says."""
    fmt = read_index(export_dir).get("format")
    cls = {"parquet": ParquetExport, "webdataset": WebDatasetExport}.get(fmt)
    if cls is None:
        raise DatasetError(f"export {export_dir}: unknown format {fmt!r}")
    return cls(export_dir, channels, as_dict)


def iter_records(export_dir: str | Path, channels: Sequence[str] | None = None) -> Iterator[ExportRecord]:
    """Every record of an export, in shard order, in this process."""
    ds = open_export(export_dir, channels)
    if isinstance(ds, ParquetExport):
        return (ds.record(i) for i in range(len(ds)))
    return ds.records()
