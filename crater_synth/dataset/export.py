"""``crater-synth export``: a rendered dataset or navigation frames in the formats trainers load (docs/export.md).

- ``parquet``: Hugging Face's convention, ``<out>/data-00000-of-0000N.parquet``, loaded with
  ``datasets.load_dataset("parquet", data_files=...)`` (or pyarrow/pandas directly);
- ``webdataset``: tar shards ``<out>/shard-000000.tar`` ..., loaded with ``webdataset.WebDataset``.

Each sample (a *record*) carries its images losslessly as NPY bytes (the EXR channels as stored:
float32 I/F and depth, float16 normals and lit) and every label of its manifest row: crater, Sun and
camera angles, range and field of view, the rim ellipse, the sigma boxes, the EXR's sha256 (checked
against the file during the export), provenance; the whole row also travels verbatim as JSON.

Streaming: the manifest is read row by row and each sample is written as soon as it is decoded, so
peak memory is one Parquet row group (``row_group_rows`` samples) or one sample, whatever the
dataset's size. Atomicity: each shard is written to a hidden temporary file and renamed when
complete; ``export.json`` (the index: shards, rows, channels, their SHA-256) is written last, and its
presence is what marks an export complete. An interrupted export leaves complete shards and no
half-written one (a killed process can leave a hidden ``.*.tmp``, which no loader's glob matches and
the next run removes); rerunning into the same directory starts it again cleanly.

Record kinds: what a sample is comes from a :class:`RecordKind` (``RECORD_KINDS``): its rows, key,
arrays and typed labels: ``render`` (a ``crater-synth dataset`` directory) and ``navframe`` (a
``crater-synth nav-frames`` directory: whole frames with their pose, Sun and landmark labels, the
landmarks a list of structs). The kind is detected from the manifest's row fields (:func:`detect_kind`).

Formats: how a shard is written comes from an ``ExportWriter`` (:mod:`crater_synth.dataset.export_writers`,
``EXPORT_WRITERS``: its shard names, open / write a sample / close, and what the index records of a
channel): ``ParquetWriter`` and ``WebDatasetWriter``. The export loop below, the temporary files and the
index are the same for both.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import time
from pathlib import Path
from typing import Callable, Iterator, Sequence

import click

from crater_core.progress import Progress
from crater_core.schema import atomic_write_text, sha256_file
from crater_synth.cli_common import user_errors
from crater_synth.dataset.export_writers import (  # noqa: F401 (re-exported: part of this API)
    EXPORT_WRITERS,
    FORMATS,
    ExportWriter,
    ParquetWriter,
    Sample,
    WebDatasetWriter,
    column_name,
    npy_bytes,
)
from crater_synth.dataset.record_kinds import (  # noqa: F401 (re-exported: part of this API)
    NAVFRAME,
    RECORD_KINDS,
    RENDER,
    ExportError,
    RecordKind,
    detect_kind,
)

INDEX_FILE = "export.json"
EXPORT_VERSION = 1
DEFAULT_CHANNELS = ("IF",)


def iter_samples(kind: RecordKind, dataset_dir: Path, channels: Sequence[str]) -> tuple[int, Iterator[Sample]]:
    """(row count, lazy iterator of samples): each row's files are read only when its sample is drawn.
    A bad dataset (no manifest, unmerged parts) fails here, before anything is written."""
    n, rows = kind.rows(dataset_dir)

    def gen() -> Iterator[Sample]:
        seen: set[str] = set()
        for row in rows:
            key = kind.key(row)
            if key in seen or "." in key or "/" in key:
                raise ExportError(f"dataset {dataset_dir}: sample key {key!r} is repeated or not a plain name")
            seen.add(key)
            arrays = kind.arrays(dataset_dir, row, channels)
            yield Sample(key, kind.labels(row), row, {column_name(c): npy_bytes(arrays[c]) for c in channels})

    return n, gen()


# ------------------------------------------------------------------------------------------------
# Shards: temporary file + rename
# ------------------------------------------------------------------------------------------------
def _tmp_path(final: Path) -> Path:
    return final.with_name(f".{final.name}.{os.getpid()}.tmp")


def _finish(tmp: Path, final: Path) -> str:
    """fsync ``tmp``, rename it to ``final``; return its sha256."""

    with open(tmp, "rb") as fh:
        os.fsync(fh.fileno())
    digest = sha256_file(tmp)
    os.replace(tmp, final)
    return digest


def _prepare_out(out: Path, overwrite: bool) -> None:
    """An empty directory, an interrupted export of ours (cleaned), or a complete one with ``overwrite``."""
    out.mkdir(parents=True, exist_ok=True)
    index = out / INDEX_FILE
    if index.exists() and not overwrite:
        raise ExportError(f"{out} already holds a complete export ({INDEX_FILE}); pass --overwrite to replace it")
    ours = [p for p in out.iterdir() if _is_ours(p.name)]
    others = [p.name for p in out.iterdir() if not _is_ours(p.name)]
    if others:
        raise ExportError(
            f"output directory {out} holds other files ({', '.join(sorted(others)[:5])}); use an empty one"
        )
    index.unlink(missing_ok=True)  # first: the directory is no longer a complete export
    for p in ours:
        p.unlink(missing_ok=True)


def _is_ours(name: str) -> bool:
    return (
        name == INDEX_FILE
        or any(w.is_shard_file(name) for w in EXPORT_WRITERS.values())
        or (name.startswith(".") and name.endswith(".tmp"))
    )


# ------------------------------------------------------------------------------------------------
# The export
# ------------------------------------------------------------------------------------------------
def _record_kind(dataset_dir, kind: str | None) -> RecordKind:
    """The record kind asked for (``kind``) or detected from the manifest; a mismatch is an error."""
    if kind is not None and kind not in RECORD_KINDS:
        raise ExportError(f"unknown record kind {kind!r}; known: {', '.join(RECORD_KINDS)}")
    found = detect_kind(dataset_dir)
    if kind is not None and found is not None and found != kind:
        raise ExportError(
            f"dataset {dataset_dir} holds {found} records, not {kind} ones: pass --kind {found} or leave --kind out"
        )
    return RECORD_KINDS[kind or found or "render"]


def _check_request(rk: RecordKind, channels: list, shard_rows: int, row_group_rows: int, dataset_dir: Path, out: Path):
    """Channels the kind has, positive sizes, a dataset directory and an output outside it."""
    bad = [c for c in channels if c not in rk.channels]
    if not channels or bad:
        raise ExportError(f"export channels {bad or channels}: choose among {', '.join(rk.channels)}")
    if shard_rows < 1 or row_group_rows < 1:
        raise ExportError(f"shard_rows={shard_rows} and row_group_rows={row_group_rows} must be >= 1")
    if not dataset_dir.is_dir():
        raise ExportError(f"dataset {dataset_dir} is not a directory")
    if out.resolve() == dataset_dir.resolve() or dataset_dir.resolve() in out.resolve().parents:
        raise ExportError(f"export directory {out} must lie outside the dataset {dataset_dir}")


def _write_shard(writer: ExportWriter, final: Path, samples: Iterator[Sample], count: int, tick) -> str:
    """Write ``count`` samples into one shard (a temporary file renamed to ``final`` when complete);
    ``tick(k)`` after every ``row_group_rows``-th sample but the last. Returns the shard's sha256."""
    tmp = _tmp_path(final)
    try:
        writer.open(tmp)
        try:
            for k in range(1, count + 1):
                writer.write(next(samples))
                if k < count and k % writer.row_group_rows == 0:
                    tick(k)
        except BaseException:
            with contextlib.suppress(OSError):  # the error being raised is the one to report
                writer.abort()
            raise
        writer.close()
        return _finish(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def export_dataset(
    dataset_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    fmt: str,
    *,
    channels: Sequence[str] = DEFAULT_CHANNELS,
    shard_rows: int = 2048,
    row_group_rows: int = 128,
    kind: str | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Export ``dataset_dir`` to ``out_dir`` as ``fmt`` (``parquet`` or ``webdataset``); returns the index
    written to ``out_dir/export.json``. Streams: at most one Parquet row group (``row_group_rows``
    samples) is held in memory for Parquet, one sample for WebDataset; each shard holds ``shard_rows``.
    ``progress(done, total)`` is called every ``row_group_rows`` samples and after each shard."""
    if fmt not in FORMATS:
        raise ExportError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    rk = _record_kind(dataset_dir, kind)
    channels = list(dict.fromkeys(channels))
    dataset_dir, out = Path(dataset_dir), Path(out_dir)
    _check_request(rk, channels, shard_rows, row_group_rows, dataset_dir, out)
    t0 = time.perf_counter()
    n, samples = iter_samples(rk, dataset_dir, channels)  # bad dataset: an error before any file is touched
    _prepare_out(out, overwrite)
    writer = EXPORT_WRITERS[fmt](rk, channels, row_group_rows)
    n_shards = math.ceil(n / shard_rows)
    shards, done = [], 0
    for i in range(n_shards):
        name = writer.shard_name(i, n_shards)
        count = min(shard_rows, n - i * shard_rows)
        digest = _write_shard(writer, out / name, samples, count, lambda k, d=done: progress and progress(d + k, n))
        done += count
        if progress:
            progress(done, n)
        shards.append({"file": name, "rows": count, "sha256": digest, "bytes": (out / name).stat().st_size})
    if next(samples, None) is not None:
        raise ExportError(f"dataset {dataset_dir}: the manifest grew during the export; export it again")
    index = {
        "export_version": EXPORT_VERSION,
        "format": fmt,
        "record_kind": rk.name,
        "dataset": str(dataset_dir.resolve()),
        "rows": n,
        "channels": {c: writer.channel_entry(c) for c in channels},
        "images": "lossless: NPY bytes of each channel as stored in the EXR (float32 IF, depth; float16 N.*, lit)",
        "shards": shards,
        "seconds": round(time.perf_counter() - t0, 3),
    }

    atomic_write_text(out / INDEX_FILE, json.dumps(index, indent=1, sort_keys=True) + "\n")
    return index


# ------------------------------------------------------------------------------------------------
# CLI
# ------------------------------------------------------------------------------------------------
@click.command("export")
@click.argument("dataset", type=click.Path(file_okay=False))
@click.option("--format", "fmt", type=click.Choice(FORMATS), required=True, help="Output format.")
@click.option(
    "--out",
    type=click.Path(file_okay=False),
    default=None,
    help="Output directory [default: DATASET-<format> beside the dataset].",
)
@click.option(
    "--channels",
    default=",".join(DEFAULT_CHANNELS),
    show_default=True,
    help="EXR channels to export, comma-separated: IF, depth, N.X, N.Y, N.Z, lit (or 'all').",
)
@click.option("--shard-rows", type=click.IntRange(min=1), default=2048, show_default=True, help="Samples per shard.")
@click.option(
    "--row-group-rows", type=click.IntRange(min=1), default=128, show_default=True, help="Parquet row-group size."
)
@click.option(
    "--kind",
    type=click.Choice(sorted(RECORD_KINDS)),
    default=None,
    help="Record kind: render (a `dataset` directory) or navframe (a `nav-frames` directory) "
    "[default: detected from the manifest's rows].",
)
@click.option("--overwrite", is_flag=True, help="Replace a complete export in the output directory.")
@user_errors
def export_command(dataset, fmt, out, channels, shard_rows, row_group_rows, kind, overwrite):
    """Export a rendered dataset or navigation frames to Parquet (Hugging Face) or WebDataset tar shards.

    Images go losslessly as NPY bytes; every manifest label goes along (for navigation frames, the landmarks
    in view with their projected rim ellipses). Prints the index (export.json) as one JSON line. Example:
    ``crater-synth export data/synth/demo --format parquet``.
    """
    ds = Path(dataset)
    chans = (
        list(RENDER.channels) if channels.strip() == "all" else [c.strip() for c in channels.split(",") if c.strip()]
    )
    out_dir = Path(out) if out else ds.with_name(f"{ds.name}-{fmt}")

    bars: list[Progress] = []  # made at the first call: export_dataset knows the total

    def progress(done: int, total: int) -> None:
        if not bars:
            bars.append(Progress(total, "export", "sample"))
        bars[0].update_to(done)

    index = export_dataset(
        ds,
        out_dir,
        fmt,
        channels=chans,
        shard_rows=shard_rows,
        row_group_rows=row_group_rows,
        kind=kind,
        overwrite=overwrite,
        progress=progress,
    )
    for bar in bars:
        bar.close()
    click.echo(
        json.dumps(
            {k: v for k, v in index.items() if k != "shards"} | {"out": str(out_dir), "shards": len(index["shards"])}
        )
    )
