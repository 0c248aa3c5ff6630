"""``crater-synth export``: a rendered dataset or navigation frames in the formats trainers load (docs/export.md).

- ``parquet``: Hugging Face's convention, ``<out>/data-00000-of-0000N.parquet``, loaded with
  ``datasets.load_dataset("parquet", data_files=...)`` (or pyarrow/pandas directly);
- ``webdataset``: tar shards ``<out>/shard-000000.tar`` ..., loaded with ``webdataset.WebDataset``.

Each sample (a *record*) carries its images losslessly as NPY bytes (the EXR channels as stored:
float32 I/F and depth, float16 normals and lit) and every label of its manifest row: crater, Sun and
camera angles, range and field of view, the rim ellipse, the sigma boxes, the EXR's sha256 (checked
against the file during the export), provenance; the whole row also travels verbatim as JSON.

Fixed-shape tensors (``--shape``, :class:`Shaping`): ``crop`` gives one sample per (row, sigma), the
sigma box resampled to the classifier's input by the crop cache's own function
(``train.preprocess.cached_crop``); ``pad`` pads every image to the export's largest, with a ``valid``
mask. Their images are float32 Hugging Face ``Array2D`` columns; ``native`` is the lossless default.
The Dataset classes that read exports are :mod:`crater_synth.data` (``train/exported.py``).

Streaming: the manifest is read row by row and each sample is written as soon as it is decoded, so
peak memory is one Parquet row group (``row_group_rows`` samples) or one sample, whatever the
dataset's size. Atomicity: each shard is written to a hidden temporary file and renamed when
complete; ``export.json`` (the index: shards, rows, channels, their SHA-256) is written last, and its
presence is what marks an export complete. An interrupted export leaves complete shards and no
half-written one (a killed process can leave a hidden ``.*.tmp``, which no loader's glob matches and
the next run removes); rerunning into the same directory starts it again cleanly. The output folder keeps
the output-folder contract (:mod:`crater_synth.outfolder`): its marker lists each shard before it is
written, only listed files are ever deleted, one export writes it at a time, and a source whose writer
is running is refused.

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
import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Callable, Iterator, Sequence

import click

from crater_core.progress import Progress
from crater_core.schema import ManifestError, atomic_write_text, sha256_file
from crater_core.verify_file import dataset_file, file_faults, row_files, trusted_paths
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.dataset.export_shapes import (  # noqa: F401 (re-exported: part of this API)
    SHAPES,
    Shaping,
    crop_defaults,
    plan_shaping,
    sigma_box,
    sigma_tag,
)
from crater_synth.dataset.export_writers import (  # noqa: F401 (re-exported: part of this API)
    EXPORT_WRITERS,
    FORMATS,
    VALID_COLUMN,
    ExportWriter,
    Layout,
    ParquetWriter,
    Sample,
    WebDatasetWriter,
    column_name,
    label_kind,
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
from crater_synth.dataset.verify import live_writer
from crater_synth.errors import DatasetBusyError
from crater_synth.outfolder import OutFolder, refuse_if_busy
from train.preprocess import PreprocessConfig

INDEX_FILE = "export.json"
EXPORT_VERSION = 1
DEFAULT_CHANNELS = ("IF",)


def iter_samples(
    kind: RecordKind, dataset_dir: Path, channels: Sequence[str], shaping: "Shaping | None" = None
) -> tuple[int, Iterator[Sample]]:
    """(sample count, lazy iterator of samples): each row's files are read only when its samples are
    drawn; a ``crop`` shaping gives one sample per (row, sigma). A bad dataset (no manifest, unmerged
    parts) fails here, before anything is written."""
    shaping = shaping or Shaping()
    n, rows = kind.rows(dataset_dir)
    trusted = trusted_paths(dataset_dir, kind.name)

    def gen() -> Iterator[Sample]:
        seen: set[str] = set()
        for row in rows:
            key = kind.key(row)
            if key in seen or "." in key or "/" in key:
                raise ExportError(f"dataset {dataset_dir}: sample key {key!r} is repeated or not a plain name")
            seen.add(key)
            check_row(kind.name, dataset_dir, row, trusted)
            arrays = kind.arrays(dataset_dir, row, channels)
            row = kind.inline(dataset_dir, row)
            labels = kind.labels(row)
            if shaping.layout.mode == "native":
                yield Sample(key, labels, row, {column_name(c): npy_bytes(arrays[c]) for c in channels})
            else:
                yield from shaping.samples(key, labels, row, arrays, f"dataset {dataset_dir}: {key}")

    return n * max(1, len(shaping.sigmas)), gen()


def check_row(kind: str, dataset_dir: Path, row: dict, trusted: set[str]) -> None:
    """verify's check of a row's files (:func:`crater_core.verify_file.file_faults` without decoding: their
    sha256 and the labels a header carries), unless a recorded verify covers the files unchanged
    (``trusted``). A path or link leading out of the dataset is refused either
    way. The first fault is an :class:`ExportError`."""
    rels = row_files(kind, row)
    try:
        for rel in rels:
            dataset_file(dataset_dir, rel)
    except ManifestError as exc:
        raise ExportError(f"dataset {dataset_dir}: {exc}: refused for export") from None
    if trusted.issuperset(rels):
        return
    faults = file_faults(kind, dataset_dir, row, decode=False)
    if faults:
        more = f" (and {len(faults) - 1} more)" if len(faults) > 1 else ""
        raise ExportError(
            f"{faults[0]}{more}: refused for export; `crater-synth verify {dataset_dir}` lists every fault"
        )


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


def _prepare_out(out: Path, overwrite: bool) -> OutFolder:
    """Claim ``out`` (crater_synth.outfolder, kind ``export``): a new or empty folder, an interrupted export
    of ours, or a complete one with ``overwrite``; then delete the files an earlier export listed there
    (the index first). A folder holding any file no export listed is refused, naming it: a shard-looking
    file is only deleted when the marker lists it, or (an export written before markers) when its
    ``export.json`` records it with the file's sha256."""
    folder = OutFolder(out, "export", flag="--out")
    legacy = _legacy_files(out) if not folder.marker.exists() else []
    folder.check_clean(lambda n: n in legacy)
    if (out / INDEX_FILE).exists() and not overwrite:
        raise ExportError(f"{out} already holds a complete export ({INDEX_FILE}); pass --overwrite to replace it")
    folder.claim()
    try:
        folder.record(legacy)
        if folder.owns(INDEX_FILE):
            folder.remove([INDEX_FILE])  # first: the folder is no longer a complete export
        folder.remove(sorted(folder.files))
    except BaseException:
        folder.discard()
        raise
    return folder


def _legacy_files(out: Path) -> list[str]:
    """An export written before markers: its ``export.json`` and the shards it records whose bytes still
    have the recorded sha256 (nothing when there is no readable index)."""
    try:
        index = json.loads((out / INDEX_FILE).read_text(encoding="utf-8"))
        shards = [(str(s["file"]), str(s["sha256"])) for s in index["shards"]]
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError):
        return []
    proved = [f for f, sha in shards if "/" not in f and (out / f).is_file() and sha256_file(out / f) == sha]
    return [INDEX_FILE, *proved]


def _is_ours(name: str) -> bool:
    """A name an export writes (the index, a shard of a format, a shard's temp file): a name, no proof;
    what may be deleted is what the folder's marker lists (:func:`_prepare_out`)."""
    return (
        name == INDEX_FILE
        or any(w.is_shard_file(name) for w in EXPORT_WRITERS.values())
        or (name.startswith(".") and name.endswith(".tmp"))
    )


def _refuse_busy_source(dataset_dir: Path) -> None:
    """Refuse to export a dataset or frames folder while its writer runs: the rows would be half there."""
    who = live_writer(dataset_dir)
    if who:
        raise DatasetBusyError(
            f"dataset {dataset_dir} is being written by another crater-synth process ({who}): export it when "
            "the run has finished"
        )
    refuse_if_busy(dataset_dir, "dataset")


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
    shape: str = "native",
    sigmas: Sequence[float] | None = None,
    size: int | None = None,
    preprocess: PreprocessConfig | None = None,
    pad_value: float = 0.0,
) -> dict:
    """Export ``dataset_dir`` to ``out_dir`` as ``fmt`` (``parquet`` or ``webdataset``); returns the index
    written to ``out_dir/export.json``. Streams: at most one Parquet row group (``row_group_rows``
    samples) is held in memory for Parquet, one sample for WebDataset; each shard holds ``shard_rows``.
    ``progress(done, total)`` is called every ``row_group_rows`` samples and after each shard.

    ``shape``: ``native`` (NPY bytes as stored), ``crop`` (per sigma in ``sigmas``, the box resampled to
    ``size`` x ``size`` with ``preprocess``'s geometry; defaults: :func:`crop_defaults`, the composed
    settings) or ``pad`` (zero-padded, ``pad_value``, to the largest image, with a ``valid`` mask)."""
    if fmt not in FORMATS:
        raise ExportError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    rk = _record_kind(dataset_dir, kind)
    channels = list(dict.fromkeys(channels))
    dataset_dir, out = Path(dataset_dir), Path(out_dir)
    _check_request(rk, channels, shard_rows, row_group_rows, dataset_dir, out)
    _refuse_busy_source(dataset_dir)
    t0 = time.perf_counter()
    if shape == "crop" and (preprocess is None or not sigmas):
        default_sigmas, default_pp = crop_defaults()
        sigmas, preprocess = sigmas or default_sigmas, preprocess or default_pp
    if shape == "crop" and size is not None:
        preprocess = dataclasses.replace(preprocess, size=int(size))
    # A bad dataset or shape: an error before any file is touched.
    shaping = plan_shaping(rk, dataset_dir, shape, sigmas, preprocess, pad_value)
    n, samples = iter_samples(rk, dataset_dir, channels, shaping)
    folder = _prepare_out(out, overwrite)
    try:
        index = _write_export(folder, rk, fmt, channels, shaping, n, samples, shard_rows, row_group_rows, progress)
        if next(samples, None) is not None:
            raise ExportError(f"dataset {dataset_dir}: the manifest grew during the export; export it again")
        index |= {"dataset": str(dataset_dir.resolve()), "seconds": round(time.perf_counter() - t0, 3)}
        folder.record([INDEX_FILE])
        atomic_write_text(out / INDEX_FILE, json.dumps(index, indent=1, sort_keys=True) + "\n")
        folder.seal([INDEX_FILE])
    except BaseException:
        if not any((out / f).exists() for f in folder.files):  # nothing published: no litter
            folder.discard()
        raise
    finally:
        folder.release()
    return index


def _write_export(folder: OutFolder, rk, fmt, channels, shaping, n, samples, shard_rows, row_group_rows, progress):
    """Write every shard into the claimed ``folder`` (each listed in its marker before it is written);
    return the index less the dataset and the time."""
    out = folder.path
    writer = EXPORT_WRITERS[fmt](rk, channels, row_group_rows, shaping.layout)
    n_shards = math.ceil(n / shard_rows)
    shards, done = [], 0
    for i in range(n_shards):
        name = writer.shard_name(i, n_shards)
        count = min(shard_rows, n - i * shard_rows)
        folder.record([name, _tmp_path(out / name).name])  # before the bytes: an interrupted shard is ours
        digest = _write_shard(writer, out / name, samples, count, lambda k, d=done: progress and progress(d + k, n))
        folder.seal([name, _tmp_path(out / name).name])
        done += count
        if progress:
            progress(done, n)
        shards.append({"file": name, "rows": count, "sha256": digest, "bytes": (out / name).stat().st_size})
    return {
        "export_version": EXPORT_VERSION,
        "format": fmt,
        "record_kind": rk.name,
        "rows": n,
        "channels": {c: writer.channel_entry(c) for c in channels},
        "images": _IMAGES[shaping.layout.mode],
        "shape": shaping.layout.record,
        "labels": {name: label_kind(t) for name, t in rk.label_fields() + list(shaping.layout.extra_fields)},
        "shards": shards,
    }


_IMAGES = {
    "native": "lossless: NPY bytes of each channel as stored in the EXR (float32 IF, depth; float16 N.*, lit)",
    "crop": "float32 sigma-box crops resampled to the classifier's input size (the crop cache's arrays)",
    "pad": "float32 channels padded at the bottom and right to the largest image; mask column 'valid'",
}


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
@click.option(
    "--shape",
    type=click.Choice(SHAPES),
    default="native",
    show_default=True,
    help="native: NPY bytes as stored; crop: each sigma box resampled to the classifier's input (one sample per "
    "sigma); pad: zero-padded to the largest image, with a 'valid' mask.",
)
@click.option(
    "--sigma",
    "sigma_text",
    default=None,
    help="--shape crop: sigmas, comma-separated [default: train.sigmas, else every sigma of the rows].",
)
@click.option(
    "--size",
    type=click.IntRange(min=8),
    default=None,
    help="--shape crop: crop side in px [default: model.input_size].",
)
@click.option("--pad-value", type=float, default=0.0, show_default=True, help="--shape pad: value of padded pixels.")
@OVERRIDES
@user_errors
def export_command(
    dataset,
    fmt,
    out,
    channels,
    shard_rows,
    row_group_rows,
    kind,
    overwrite,
    shape,
    sigma_text,
    size,
    pad_value,
    overrides,
):
    """Export a rendered dataset or navigation frames to Parquet (Hugging Face) or WebDataset tar shards.

    Images go losslessly as NPY bytes (``--shape native``) or as fixed-shape float32 tensors (``--shape crop``:
    the classifier's crops; ``--shape pad``); every manifest label goes along (for navigation frames, the
    landmarks in view with their projected rim ellipses). OVERRIDES (e.g. ``train.sigmas=[1.2]``) set the
    crop's defaults. Prints the index (export.json) as one JSON line. Example:
    ``crater-synth export data/synth/demo --format parquet --shape crop``.
    """
    ds = Path(dataset)
    chans = (
        list(RENDER.channels) if channels.strip() == "all" else [c.strip() for c in channels.split(",") if c.strip()]
    )
    out_dir = Path(out) if out else ds.with_name(f"{ds.name}-{fmt}")
    if shape != "crop" and (sigma_text or size or overrides):
        raise ExportError("--sigma, --size and OVERRIDES set the crop: they go with --shape crop")
    sigmas, pp = crop_defaults(overrides) if shape == "crop" else (None, None)
    if sigma_text:
        try:
            sigmas = [float(v) for v in sigma_text.split(",") if v.strip()]
        except ValueError:
            raise ExportError(f"--sigma {sigma_text!r}: give numbers, comma-separated (e.g. 1.0,1.2)") from None

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
        shape=shape,
        sigmas=sigmas,
        size=size,
        preprocess=pp,
        pad_value=pad_value,
    )
    for bar in bars:
        bar.close()
    click.echo(
        json.dumps(
            {k: v for k, v in index.items() if k not in ("shards", "labels")}
            | {"out": str(out_dir), "shards": len(index["shards"])}
        )
    )
