"""Export formats of ``crater-synth export`` (docs/export.md): how one format writes its shards.

An :class:`ExportWriter` names its shard files, opens a shard, writes one :class:`Sample` at a time and
closes it, and says what the index (``export.json``) records of each channel. ``EXPORT_WRITERS``:

- ``parquet`` (:class:`ParquetWriter`): Hugging Face's convention, ``data-00000-of-0000N.parquet``;
- ``webdataset`` (:class:`WebDatasetWriter`): tar shards ``shard-000000.tar`` ...

The export loop, the temporary files and the index are in :mod:`crater_synth.dataset.export`, once for
every format.
"""

from __future__ import annotations

import io
import json
import tarfile
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from crater_synth.dataset.record_kinds import ExportError, RecordKind


# ------------------------------------------------------------------------------------------------
# Samples
# ------------------------------------------------------------------------------------------------
def column_name(channel: str) -> str:
    """The column / WebDataset extension stem of a channel: ``IF`` -> ``if``, ``N.X`` -> ``n_x``."""
    return channel.lower().replace(".", "_")


def npy_bytes(a: np.ndarray) -> bytes:
    """An array as the bytes of a ``.npy`` file (``numpy.load(io.BytesIO(b))`` gives it back exactly)."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
    return buf.getvalue()


@dataclass
class Sample:
    """One exported sample: its key, typed labels, verbatim manifest row and its images: NPY-encoded
    channels (``native`` layout) or fixed-shape float32 arrays (``crop`` and ``pad``)."""

    key: str
    labels: dict  # typed label columns
    row: dict  # the manifest row, verbatim
    npy: dict[str, bytes]  # column name -> NPY bytes (native layout)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)  # column name -> (H, W) array (fixed layouts)


VALID_COLUMN = "valid"  # pad layout: 1 where a pixel is the image's own, 0 where it is padding


@dataclass(frozen=True)
class Layout:
    """How a sample's images are laid out (``export --shape``, docs/export.md "Fixed-shape tensors").

    ``native``: each channel's NPY bytes as the EXR stores it, shapes as rendered (``shape`` None).
    ``crop`` and ``pad``: every image float32 of one ``shape`` (H, W), stored as Hugging Face
    ``Array2D`` columns in Parquet and as fixed-shape ``.npy`` members in WebDataset; ``extra_fields``
    are the typed label columns the mode adds (pyarrow types) and ``record`` what export.json, the
    Parquet schema metadata and each WebDataset sample's JSON record of it (mode, sigma, size, pad)."""

    mode: str = "native"
    shape: tuple[int, int] | None = None
    extra_fields: tuple = ()
    record: dict = field(default_factory=lambda: {"mode": "native"})

    @property
    def fixed(self) -> bool:
        return self.shape is not None

    def image_columns(self, channels: Sequence[str]) -> list[str]:
        """The image columns of a sample: one per channel, plus the pad mask."""
        cols = [column_name(c) for c in channels]
        return cols + [VALID_COLUMN] if self.mode == "pad" else cols


# ------------------------------------------------------------------------------------------------
# Export formats: one writer each
# ------------------------------------------------------------------------------------------------
class ExportWriter(ABC):
    """How one export format writes its shards. The export loop (``export.export_dataset``) is the same for
    every format: it names the shards (:meth:`shard_name`), and for each one calls :meth:`open` on the
    shard's temporary file, :meth:`write` once per sample, then :meth:`close` (the file complete) or, on
    an error, :meth:`abort`. A writer also says which files are its shards (:meth:`is_shard_file`) and
    what the index records of each channel (:meth:`channel_entry`)."""

    name: str

    def __init__(self, kind: RecordKind, channels: Sequence[str], row_group_rows: int, layout: Layout = Layout()):
        self.kind, self.channels, self.row_group_rows = kind, list(channels), row_group_rows
        self.layout = layout

    @staticmethod
    @abstractmethod
    def shard_name(i: int, n_shards: int) -> str:
        """The file name of shard ``i`` of ``n_shards``."""

    @staticmethod
    @abstractmethod
    def is_shard_file(name: str) -> bool:
        """Whether ``name`` is a shard file of this format."""

    @abstractmethod
    def channel_entry(self, channel: str) -> dict:
        """What the index records of an exported channel: where a loader finds it in a sample."""

    @abstractmethod
    def open(self, path: Path) -> None:
        """Start a shard at ``path``."""

    @abstractmethod
    def write(self, sample: Sample) -> None:
        """Add one sample to the open shard."""

    @abstractmethod
    def close(self) -> None:
        """Complete the open shard's file."""

    @abstractmethod
    def abort(self) -> None:
        """Release the open shard's file after an error (the export removes it)."""


class ParquetWriter(ExportWriter):
    """Hugging Face's Parquet convention: ``data-00000-of-0000N.parquet``, one column per label, per
    channel (NPY bytes) and the row as JSON. Row groups are written as they fill: at most
    ``row_group_rows`` samples are held."""

    name = "parquet"

    def __init__(self, kind: RecordKind, channels: Sequence[str], row_group_rows: int, layout: Layout = Layout()):
        super().__init__(kind, channels, row_group_rows, layout)
        self.schema = _parquet_schema(kind, self.channels, layout)
        self._writer = None
        self._batch: list[Sample] = []

    @staticmethod
    def shard_name(i: int, n_shards: int) -> str:
        return f"data-{i:05d}-of-{n_shards:05d}.parquet"

    @staticmethod
    def is_shard_file(name: str) -> bool:
        return name.startswith("data-") and name.endswith(".parquet")

    def channel_entry(self, channel: str) -> dict:
        if self.layout.fixed:
            return {"column": column_name(channel), "shape": list(self.layout.shape), "dtype": "float32"}
        return {"column": f"{column_name(channel)}_npy"}

    def open(self, path: Path) -> None:

        images = {f"{column_name(c)}_npy" for c in self.channels} | set(self.layout.image_columns(self.channels))
        labels = [f.name for f in self.schema if f.name not in images]
        # Dictionaries and min/max statistics only for the label columns: the image columns are large
        # unique binaries, for which a dictionary only costs memory and time before falling back.
        self._writer = pq.ParquetWriter(
            path, self.schema, compression="zstd", use_dictionary=labels, write_statistics=labels
        )
        self._batch = []

    def write(self, sample: Sample) -> None:
        self._batch.append(sample)
        if len(self._batch) == self.row_group_rows:
            self._write_group()

    def _write_group(self) -> None:
        batch, self._batch = self._batch, []
        self._writer.write_table(_parquet_table(batch, self.kind, self.channels, self.schema, self.layout))

    def close(self) -> None:
        if self._batch:
            self._write_group()
        self.abort()

    def abort(self) -> None:
        self._batch = []
        if self._writer is not None:
            self._writer.close()
            self._writer = None


class WebDatasetWriter(ExportWriter):
    """WebDataset tar shards ``shard-000000.tar`` ...: per sample, one ``KEY.<channel>.npy`` member per
    channel and ``KEY.json`` (the typed labels and the manifest row)."""

    name = "webdataset"

    def __init__(self, kind: RecordKind, channels: Sequence[str], row_group_rows: int, layout: Layout = Layout()):
        super().__init__(kind, channels, row_group_rows, layout)
        self._tar: tarfile.TarFile | None = None

    @staticmethod
    def shard_name(i: int, n_shards: int) -> str:
        return f"shard-{i:06d}.tar"

    @staticmethod
    def is_shard_file(name: str) -> bool:
        return name.startswith("shard-") and name.endswith(".tar")

    def channel_entry(self, channel: str) -> dict:
        if self.layout.fixed:
            return {"column": f"{column_name(channel)}.npy", "shape": list(self.layout.shape), "dtype": "float32"}
        return {"column": f"{column_name(channel)}.npy"}

    def open(self, path: Path) -> None:
        self._tar = tarfile.open(path, "w", format=tarfile.PAX_FORMAT)

    def write(self, sample: Sample) -> None:
        for col, data in sample.npy.items():
            _tar_member(self._tar, f"{sample.key}.{col}.npy", data)
        for col, arr in sample.arrays.items():
            _tar_member(self._tar, f"{sample.key}.{col}.npy", npy_bytes(arr))
        meta = {"key": sample.key, "record_kind": self.kind.name, **sample.labels, "manifest_row": sample.row}
        if self.layout.fixed:  # native shards stay as they always were (no "export" entry)
            meta["export"] = self.layout.record
        _tar_member(self._tar, f"{sample.key}.json", json.dumps(meta, sort_keys=True).encode())

    def close(self) -> None:
        self.abort()

    def abort(self) -> None:
        if self._tar is not None:
            self._tar.close()
            self._tar = None


EXPORT_WRITERS: dict[str, type[ExportWriter]] = {w.name: w for w in (ParquetWriter, WebDatasetWriter)}
FORMATS = tuple(EXPORT_WRITERS)


def _parquet_schema(kind: RecordKind, channels: Sequence[str], layout: Layout = Layout()):

    fields = [("key", pa.string()), ("record_kind", pa.string())]
    fields += kind.label_fields() + list(layout.extra_fields)
    if not layout.fixed:
        fields += [(f"{column_name(c)}_npy", pa.binary()) for c in channels]
        fields += [("labels_json", pa.string())]
        return pa.schema(fields)  # native: the schema exports have always had, no metadata
    fields += [(column_name(c), HfArray2D(layout.shape, "float32")) for c in channels]
    if layout.mode == "pad":
        fields += [(VALID_COLUMN, HfArray2D(layout.shape, "uint8"))]
    fields += [("labels_json", pa.string())]
    features = {name: hf_feature(t) for name, t in fields}
    meta = {"huggingface": json.dumps({"info": {"features": features}}), "crater_synth": json.dumps(layout.record)}
    return pa.schema(fields, metadata=meta)


def _parquet_table(batch: list[Sample], rk: RecordKind, channels, schema, layout: Layout = Layout()):

    cols = {"key": [s.key for s in batch], "record_kind": [rk.name] * len(batch)}
    for name, _ in rk.label_fields() + list(layout.extra_fields):
        cols[name] = [s.labels.get(name) for s in batch]
    if layout.fixed:
        for col in layout.image_columns(channels):
            cols[col] = _array2d_column(np.stack([s.arrays[col] for s in batch]), schema.field(col).type)
    else:
        for c in channels:
            cols[f"{column_name(c)}_npy"] = [s.npy[column_name(c)] for s in batch]
    cols["labels_json"] = [json.dumps(s.row, sort_keys=True) for s in batch]
    try:
        return pa.table(cols, schema=schema)
    except (pa.ArrowInvalid, pa.ArrowTypeError) as exc:
        raise ExportError(
            f"labels of samples {batch[0].key} .. {batch[-1].key} do not fit the export schema: {exc}"
        ) from None


# ------------------------------------------------------------------------------------------------
# Hugging Face feature types (the ``huggingface`` key of the Arrow schema metadata, as `datasets` writes it)
# ------------------------------------------------------------------------------------------------
class HfArray2D(pa.ExtensionType):
    """The Arrow type of a Hugging Face ``Array2D(shape, dtype)`` column: its storage (list of lists)
    under the extension name and serialisation ``datasets`` registers, so that ``datasets`` reads the
    column back as ``Array2D`` (and ``with_format("torch")`` gives tensors) while this module needs no
    ``datasets`` import (a test-only dependency). Never registered here: readers without ``datasets``
    (pyarrow alone) see the plain list-of-lists storage."""

    def __init__(self, shape: Sequence[int], dtype: str):
        self.shape, self.value_type = tuple(int(n) for n in shape), dtype
        storage = pa.list_(pa.list_(pa.from_numpy_dtype(np.dtype(dtype))))
        pa.ExtensionType.__init__(self, storage, "datasets.features.features.Array2DExtensionType")

    def __arrow_ext_serialize__(self) -> bytes:
        return json.dumps((list(self.shape), self.value_type)).encode()

    @classmethod
    def __arrow_ext_deserialize__(cls, storage_type, serialized):
        shape, dtype = json.loads(serialized)
        return cls(shape, dtype)


def _array2d_column(stack: np.ndarray, typ: HfArray2D) -> pa.Array:
    """A (N, H, W) stack as an ``Array2D`` column of N rows (zero-copy offsets, no per-pixel Python)."""
    n, h, w = stack.shape
    values = pa.array(np.ascontiguousarray(stack, dtype=np.dtype(typ.value_type)).reshape(-1))
    rows = pa.ListArray.from_arrays(pa.array(np.arange(0, n * h * w + 1, w, dtype=np.int32)), values)
    images = pa.ListArray.from_arrays(pa.array(np.arange(0, n * h + 1, h, dtype=np.int32)), rows)
    return pa.ExtensionArray.from_storage(typ, images)


def label_kind(t: pa.DataType):
    """What export.json records of a label column's type, for loaders without pyarrow's schema (the
    WebDataset JSON): ``float64``, ``int64``, ``string``, ``bool``, ``list``, or a struct's
    ``{field: kind}``."""
    if pa.types.is_list(t):
        return "list"
    if pa.types.is_struct(t):
        return {t.field(i).name: label_kind(t.field(i).type) for i in range(t.num_fields)}
    return _HF_VALUES[str(t)]


_HF_VALUES = {"string": "string", "int64": "int64", "double": "float64", "bool": "bool", "binary": "binary"}


def hf_feature(t: pa.DataType) -> dict:
    """The Hugging Face feature dict of an Arrow type, as ``datasets.Features.to_dict`` writes it."""
    if isinstance(t, HfArray2D):
        return {"shape": list(t.shape), "dtype": t.value_type, "_type": "Array2D"}
    if pa.types.is_list(t):
        return {"feature": hf_feature(t.value_type), "_type": "List"}
    if pa.types.is_struct(t):
        return {t.field(i).name: hf_feature(t.field(i).type) for i in range(t.num_fields)}
    return {"dtype": _HF_VALUES[str(t)], "_type": "Value"}


def _tar_member(tf: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size, info.mode, info.mtime = len(data), 0o644, 0  # mtime 0: the same dataset gives the same bytes
    tf.addfile(info, io.BytesIO(data))
