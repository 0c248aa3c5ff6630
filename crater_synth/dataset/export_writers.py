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
from dataclasses import dataclass
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
    """One exported sample: its key, typed labels, verbatim manifest row and NPY-encoded channels."""

    key: str
    labels: dict  # typed label columns
    row: dict  # the manifest row, verbatim
    npy: dict[str, bytes]  # column name -> NPY bytes


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

    def __init__(self, kind: RecordKind, channels: Sequence[str], row_group_rows: int):
        self.kind, self.channels, self.row_group_rows = kind, list(channels), row_group_rows

    @staticmethod
    @abstractmethod
    def shard_name(i: int, n_shards: int) -> str:
        """The file name of shard ``i`` of ``n_shards``."""

    @staticmethod
    @abstractmethod
    def is_shard_file(name: str) -> bool:
        """Whether ``name`` is a shard file of this format."""

    @staticmethod
    @abstractmethod
    def channel_entry(channel: str) -> dict:
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

    def __init__(self, kind: RecordKind, channels: Sequence[str], row_group_rows: int):
        super().__init__(kind, channels, row_group_rows)
        self.schema = _parquet_schema(kind, self.channels)
        self._writer = None
        self._batch: list[Sample] = []

    @staticmethod
    def shard_name(i: int, n_shards: int) -> str:
        return f"data-{i:05d}-of-{n_shards:05d}.parquet"

    @staticmethod
    def is_shard_file(name: str) -> bool:
        return name.startswith("data-") and name.endswith(".parquet")

    @staticmethod
    def channel_entry(channel: str) -> dict:
        return {"column": f"{column_name(channel)}_npy"}

    def open(self, path: Path) -> None:

        labels = [f.name for f in self.schema if not f.name.endswith("_npy")]
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
        self._writer.write_table(_parquet_table(batch, self.kind, self.channels, self.schema))

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

    def __init__(self, kind: RecordKind, channels: Sequence[str], row_group_rows: int):
        super().__init__(kind, channels, row_group_rows)
        self._tar: tarfile.TarFile | None = None

    @staticmethod
    def shard_name(i: int, n_shards: int) -> str:
        return f"shard-{i:06d}.tar"

    @staticmethod
    def is_shard_file(name: str) -> bool:
        return name.startswith("shard-") and name.endswith(".tar")

    @staticmethod
    def channel_entry(channel: str) -> dict:
        return {"column": f"{column_name(channel)}.npy"}

    def open(self, path: Path) -> None:
        self._tar = tarfile.open(path, "w", format=tarfile.PAX_FORMAT)

    def write(self, sample: Sample) -> None:
        for col, data in sample.npy.items():
            _tar_member(self._tar, f"{sample.key}.{col}.npy", data)
        meta = {"key": sample.key, "record_kind": self.kind.name, **sample.labels, "manifest_row": sample.row}
        _tar_member(self._tar, f"{sample.key}.json", json.dumps(meta, sort_keys=True).encode())

    def close(self) -> None:
        self.abort()

    def abort(self) -> None:
        if self._tar is not None:
            self._tar.close()
            self._tar = None


EXPORT_WRITERS: dict[str, type[ExportWriter]] = {w.name: w for w in (ParquetWriter, WebDatasetWriter)}
FORMATS = tuple(EXPORT_WRITERS)


def _parquet_schema(kind: RecordKind, channels: Sequence[str]):

    fields = [("key", pa.string()), ("record_kind", pa.string())]
    fields += kind.label_fields()
    fields += [(f"{column_name(c)}_npy", pa.binary()) for c in channels]
    fields += [("labels_json", pa.string())]
    return pa.schema(fields)


def _parquet_table(batch: list[Sample], rk: RecordKind, channels, schema):

    cols = {"key": [s.key for s in batch], "record_kind": [rk.name] * len(batch)}
    for name, _ in rk.label_fields():
        cols[name] = [s.labels.get(name) for s in batch]
    for c in channels:
        cols[f"{column_name(c)}_npy"] = [s.npy[column_name(c)] for s in batch]
    cols["labels_json"] = [json.dumps(s.row, sort_keys=True) for s in batch]
    try:
        return pa.table(cols, schema=schema)
    except (pa.ArrowInvalid, pa.ArrowTypeError) as exc:
        raise ExportError(
            f"labels of samples {batch[0].key} .. {batch[-1].key} do not fit the export schema: {exc}"
        ) from None


def _tar_member(tf: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size, info.mode, info.mtime = len(data), 0o644, 0  # mtime 0: the same dataset gives the same bytes
    tf.addfile(info, io.BytesIO(data))
