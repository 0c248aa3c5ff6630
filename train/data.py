"""Synthetic training data: manifest rows -> cached 150x150 crops -> a torch Dataset (docs/classifiers.md).

- One sample per (manifest row, sigma).
- The geometric part of the preprocessing (sigma box -> 150x150, anti-aliased) is done once and kept in
  an on-disk cache, ``<train.cache_dir>/crops-<manifest digest>-<preprocessing and file identity
  hash>/images.npy`` (a numpy memmap), so epochs after the first never decode an EXR; a file changed
  or deleted since makes another key. The sensor model and the
  photometric normalisation run per sample at load time (fresh, seeded noise every epoch).
- Train/validation split by render parameters: whole camera poses (or sun directions) are held out,
  seeded, so a validation image never has a near-duplicate (same pose, other sun / other sigma) in
  training.
- Only synthetic render rows are accepted: anything else -- a row marked as real/test, or a file whose
  checksum is that of a real test image -- is refused with :class:`RealDataLeakError`.

Length: the one path from a manifest to training batches (leak guard, class selection, split, crop
cache, the dataset with its sensor model and mosaic partners); each stage is short and used only here,
and the leak guard must sit next to the loader it guards.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import multiprocessing
import os
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from crater_core.exr import ExrError, read_channel_and_header
from crater_core.files import ensure_writable_dir, umask
from crater_core.progress import Progress
from crater_core.schema import (
    MANIFEST_NAME,
    PARTS_DIR,
    ManifestError,
    duplicate_faults,
    load_manifest,
    manifest_digest,
    row_file,
    validate_row,
)
from crater_core.settings import Settings, TrainSettings, as_plain
from crater_core.sweep import rows_in_selection
from crater_core.verify_file import file_faults, identity_digest, trusted_paths
from train.errors import DatasetError, RealDataLeakError
from train.exported import iter_records, read_index
from train.preprocess import (
    PreprocessConfig,
    SensorModel,
    apply_support,
    cached_crop,
    mosaic_composite,
    normalize,
    rotate_crop,
)

SYNTHETIC = "synthetic"
CACHE_FORMAT = 1


# ------------------------------------------------------------------------------------------------
# EXR reading
# ------------------------------------------------------------------------------------------------
def read_exr_channel(path: str | Path, channel: str = "IF") -> np.ndarray:
    """One channel of a dataset EXR as float32 (H, W) (``crater_core.exr.read_channel``); a missing or
    corrupt file is a :class:`DatasetError` naming it."""
    return read_exr_channel_and_header(path, channel)[0]


def read_exr_channel_and_header(path: str | Path, channel: str = "IF") -> tuple[np.ndarray, dict]:
    """:func:`read_exr_channel` and the EXR's header (the render's labels), from one open."""

    try:
        return read_channel_and_header(path, channel)
    except ExrError as exc:
        raise DatasetError(f"{exc} (listed in the manifest)") from None


# ------------------------------------------------------------------------------------------------
# Rows, classes, leak guard, split
# ------------------------------------------------------------------------------------------------
def class_names_of(settings: Settings) -> list[str]:
    """Class names in configuration order (the ``crater`` group; the settings refuse an empty one)."""
    return [c.name for c in settings.craters]


def cache_dir_of(train: TrainSettings) -> str:
    """``train.cache_dir`` (default: ``<train.dataset_dir>/.cache``)."""
    return str(train.cache_dir or Path(train.dataset_dir) / ".cache")


def require_classes(class_names: Sequence[str]) -> list[str]:
    """A classifier needs two classes at least: checked before anything is loaded or trained (the SVMs
    would refuse a single class only after LunarNet_ex had trained)."""
    if len(class_names) < 2:
        raise DatasetError(
            f"crater= selects one crater ({', '.join(class_names)}): a classifier needs at least two; "
            "select two or more, e.g. crater=[shackleton,de_gerlache]"
        )
    return list(class_names)


def require_manifest(dataset_dir: str | Path) -> Path:
    """``<dataset_dir>/manifest.jsonl``, or a clear error when it is missing."""

    p = Path(dataset_dir) / MANIFEST_NAME
    if not p.is_file():
        raise DatasetError(
            f"no {MANIFEST_NAME} in {Path(dataset_dir)}: render a dataset first (crater-synth dataset) "
            f"or set train.dataset_dir"
        )
    return p


def load_rows(dataset_dir: str | Path) -> list[dict]:
    """Strictly read ``<dataset_dir>/manifest.jsonl``: every line a valid row inside the dataset, no render,
    file or file content listed twice (a duplicate row with another crater would train on a wrong
    label), no unmerged ``manifest.parts/``. The checks ``verify`` makes without opening a file; each
    file is checked (:func:`crater_core.verify_file.file_faults`) where the crop cache decodes it
    (:func:`build_cache`), and the cache is keyed by the files' identity."""

    d = Path(dataset_dir)
    manifest = require_manifest(d)
    parts = [p for p in (d / PARTS_DIR).glob("*.jsonl") if p.stat().st_size] if (d / PARTS_DIR).is_dir() else []
    if parts:  # rows a killed (or running) `crater-synth dataset` never merged: the manifest is not the dataset
        raise DatasetError(
            f"{d} has {len(parts)} unmerged manifest part(s) in {PARTS_DIR}/ (a run is going on or was killed): "
            "finish it with `crater-synth dataset` (same settings) before training"
        )
    try:
        rows = load_manifest(d)
    except ManifestError as exc:
        raise DatasetError(str(exc)) from None
    conflicts = duplicate_faults(rows)
    if conflicts:
        more = f" (and {len(conflicts) - 1} more)" if len(conflicts) > 1 else ""
        raise DatasetError(
            f"{manifest}: {conflicts[0]}{more}: refused for training; `crater-synth verify {d}` lists every fault"
        )
    return rows


def forbidden_sha256_of(settings: Settings) -> set[str]:
    """Checksums of real test products named in the configuration (training must never read them)."""
    sha = settings.realset.mosaic.sha256
    return {sha} if sha else set()


def check_synthetic_rows(
    rows: Iterable[dict],
    dataset_dir: str | Path,
    forbidden_sha256: Iterable[str] = (),
    forbidden_paths: Iterable[str | Path] = (),
) -> list[dict]:
    """Refuse anything that is not a synthetic render row: a row that fails the render-manifest schema,
    one marked with a non-synthetic ``source``/``role``, or one whose file (by manifest checksum or
    resolved path) is a real test image. Returns the rows."""
    bad_sha = set(forbidden_sha256)
    bad_paths = {Path(p).resolve() for p in forbidden_paths}
    out = []
    for i, row in enumerate(rows):
        where = f"training row {i} ({row.get('path', '?')})"
        if (
            str(row.get("source", SYNTHETIC)) != SYNTHETIC
            or str(row.get("role", "train")) == "test"
            or "image_path" in row
        ):
            raise RealDataLeakError(
                f"{where} is not a synthetic render (source={row.get('source')!r}, "
                f"role={row.get('role')!r}): real images are only ever test data"
            )
        try:
            validate_row(row, where)
        except ManifestError as exc:
            raise RealDataLeakError(f"{where} is not a render-manifest row, refused for training: {exc}") from None
        if row["sha256"] in bad_sha:
            raise RealDataLeakError(f"{where} has the sha256 of a real test image: refused for training")
        if bad_paths and row_path(dataset_dir, row).resolve() in bad_paths:
            raise RealDataLeakError(f"{where} points at a real test image: refused for training")
        out.append(row)
    return out


def row_path(dataset_dir: str | Path, row: dict) -> Path:
    """The file of a row (``crater_core.schema.row_file``): a :class:`DatasetError` when a link takes
    it outside the dataset."""

    try:
        return row_file(dataset_dir, row)
    except ManifestError as exc:
        raise DatasetError(f"{exc}: refused for training") from None


def select_rows(rows: Sequence[dict], class_names: Sequence[str]) -> tuple[list[dict], dict[str, int]]:
    """Rows of the configured craters; every class must have rows (clear error otherwise)."""
    counts = {n: 0 for n in class_names}
    others: dict[str, int] = {}
    keep = []
    for r in rows:
        if r["crater"] in counts:
            counts[r["crater"]] += 1
            keep.append(r)
        else:
            others[r["crater"]] = others.get(r["crater"], 0) + 1
    empty = [n for n, c in counts.items() if c == 0]
    if empty:
        extra = f"; the manifest also has {others}" if others else ""
        raise DatasetError(
            f"empty class(es) {empty}: no rendered rows for them in the manifest (rows per class: {counts}{extra})"
        )
    return keep, others


def _group_key(row: dict, split_by: str) -> tuple:
    """The render group of ``row``: its camera pose (``split_by="camera"``) or its sun direction (``"sun"``)."""
    elevation, azimuth = ("sun_elevation", "sun_azimuth") if split_by == "sun" else ("cam_elevation", "cam_azimuth")
    return round(float(row[elevation]), 6), round(float(row[azimuth]), 6)


def split_rows(
    rows: Sequence[dict], val_fraction: float, split_by: str, seed: int, class_names: Sequence[str]
) -> tuple[list[int], list[int], dict]:
    """Hold out whole render groups (camera poses, or sun directions) for validation, seeded.

    Falls back to the other axis when the chosen one has a single value. Returns (train row indices,
    val row indices, info). ``split_by`` and ``val_fraction`` come from the validated ``train`` settings."""
    order = [split_by] + [a for a in ("camera", "sun") if a != split_by]
    for axis in order:
        keys = sorted({_group_key(r, axis) for r in rows})
        if len(keys) >= 2:
            break
    else:
        raise DatasetError(
            "cannot split train/validation without leakage: the manifest has a single camera "
            "pose and a single sun direction; render at least two of either"
        )
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5EED])
    perm = rng.permutation(len(keys))
    n_val = min(len(keys) - 1, max(1, int(round(val_fraction * len(keys)))))
    val_keys = {keys[i] for i in perm[:n_val]}
    tr, va = [], []
    for i, r in enumerate(rows):
        (va if _group_key(r, axis) in val_keys else tr).append(i)
    for part, idx in (("training", tr), ("validation", va)):
        have = {rows[i]["crater"] for i in idx}
        missing = [n for n in class_names if n not in have]
        if missing:
            raise DatasetError(
                f"the {part} split has no rows of {missing} (split by {axis}, {len(keys)} groups): "
                f"render the same poses for every crater or change train.val_fraction"
            )
    info = {
        "split_by": axis,
        "groups": len(keys),
        "val_groups": sorted([list(k) for k in val_keys]),
        "train_rows": len(tr),
        "val_rows": len(va),
    }
    return tr, va, info


# ------------------------------------------------------------------------------------------------
# Cache
# ------------------------------------------------------------------------------------------------
def _sigma_box(row: dict, sigma: float, where: str) -> list[float]:
    for k, box in row["sigma_boxes"].items():
        try:
            if abs(float(k) - sigma) < 1e-6:
                return [float(b) for b in box]
        except (TypeError, ValueError):
            continue
    raise DatasetError(f"{where}: no sigma box for sigma={sigma} (has {sorted(row['sigma_boxes'])})")


def row_sigmas(rows: Sequence[dict], sigmas: Sequence[float] | None) -> list[float]:
    """The sigmas to use: configured ones, else the union over the rows' ``sigma_boxes``."""
    if sigmas:
        return sorted(float(s) for s in sigmas)
    found = set()
    for r in rows:
        for k in r["sigma_boxes"]:
            try:
                found.add(round(float(k), 6))
            except ValueError:
                raise DatasetError(f"row {r.get('path')}: sigma_boxes key {k!r} is not a number") from None
    if not found:
        raise DatasetError("manifest rows carry no sigma_boxes")
    return sorted(found)


@dataclass
class CropCache:
    """The cached resampled (pre-photometry) I/F crops of a set of rows."""

    path: Path
    images: np.ndarray  # (N, size, size) memmap
    samples: list[tuple[int, float]]  # (row index, sigma) per cached image
    built: bool = False  # True when this call decoded EXRs
    seconds: float = 0.0


def cache_key(rows: Sequence[dict], sigmas: Sequence[float], pp: PreprocessConfig, dtype: str, files: str = "") -> str:
    """The crop cache's name: the rows, the preprocessing and ``files``, the identity of the files the
    crops come from (:func:`crater_core.verify_file.identity_digest`): a file rewritten, replaced or
    deleted since the cache was built makes another key, so its crops are never reused unchecked."""
    h = hashlib.sha256(
        json.dumps(
            {
                "format": CACHE_FORMAT,
                "pp": pp.geometry_key(),
                "sigmas": list(sigmas),
                "dtype": dtype,
                "max_outside": pp.max_outside_frac,
                "files": files,
            },
            sort_keys=True,
        ).encode()
    )
    return f"crops-{manifest_digest(rows)}-{h.hexdigest()[:10]}"


def files_identity(rows: Sequence[dict], dataset_dir: str | Path) -> str:
    """:func:`crater_core.verify_file.identity_digest` of the rows' files; a missing one is a
    :class:`DatasetError` naming it."""
    try:
        return identity_digest(dataset_dir, "render", rows)
    except FileNotFoundError as exc:
        raise DatasetError(
            f"EXR {exc.filename} does not exist (listed in the manifest): refused for training"
        ) from None
    except OSError as exc:
        raise DatasetError(
            f"EXR {exc.filename}: {exc.strerror} (listed in the manifest): refused for training"
        ) from None
    except ManifestError as exc:
        raise DatasetError(f"{exc}: refused for training") from None


CACHE_ROWS_PER_CHUNK = 256  # rows per task of the cache build (a few seconds of work each)


def _fill_cache_rows(chunk: tuple, sigmas: tuple, pp: PreprocessConfig, verify_sha256: bool, on_row=None) -> int:
    """Resample one chunk of rows into the cache's memmap (``chunk`` = images path, dataset dir, rows,
    first sample index); returns the number of rows. Runs in a pool process or in the caller (which
    may pass ``on_row``, called after each row)."""

    images_path, dataset_dir, rows, j, trusted = chunk
    arr = np.load(images_path, mmap_mode="r+")
    for row, known in zip(rows, trusted):
        path = row_path(dataset_dir, row)
        where = f"EXR {path}"
        if not path.is_file():
            raise DatasetError(f"{where} does not exist (manifest row {row['crater']} index {row['index']})")
        # verify's check of the file (sha256, header labels), unless a recorded verify covers it unchanged
        wrong = [] if known else file_faults("render", dataset_dir, row, decode=False, sha=verify_sha256)
        if wrong:  # e.g. an edited crater or Sun angle: the file's own labels contradict the row
            more = f" (and {len(wrong) - 1} more)" if len(wrong) > 1 else ""
            raise DatasetError(
                f"{wrong[0]}{more}: refused for training; `crater-synth verify {dataset_dir}` lists every fault"
            )
        img = read_exr_channel(path, "IF")
        if img.shape != (int(row["height"]), int(row["width"])):
            raise DatasetError(
                f"{where} is {img.shape[1]}x{img.shape[0]}, the manifest says {row['width']}x{row['height']}"
            )
        for s in sigmas:
            arr[j] = cached_crop(img, _sigma_box(row, s, where), pp, where, s)
            j += 1
        if on_row is not None:
            on_row()
    arr.flush()
    return len(rows)


def _reuse_cache(final: Path, samples: list, size: int):
    """The images of a complete cache at ``final`` holding exactly ``samples``, or None (an unreadable or
    different cache there is removed, to be rebuilt)."""
    if not (final / "index.json").is_file():
        return None
    try:
        meta = json.loads((final / "index.json").read_text())
        images = np.load(final / "images.npy", mmap_mode="r")
        if [tuple(x) for x in meta["samples"]] == samples and images.shape == (len(samples), size, size):
            return images
    except (OSError, ValueError, KeyError, json.JSONDecodeError):
        pass  # unreadable cache: rebuild
    shutil.rmtree(final, ignore_errors=True)
    return None


def _fill_cache(
    images_path: Path,
    rows: list,
    dataset_dir,
    sigmas,
    pp: PreprocessConfig,
    verify_sha256: bool,
    workers: int,
    progress: bool,
) -> None:
    """Resample every (row, sigma) into the memmap at ``images_path``. Decoding and resampling are
    CPU-bound: chunks of rows go to ``workers`` processes, each writing its own slice of the memmap
    (bars on a terminal, otherwise a line every few seconds)."""

    n_jobs = max(1, min(workers or os.cpu_count() or 1, len(rows) // CACHE_ROWS_PER_CHUNK))
    trusted = trusted_paths(dataset_dir, "render")
    known = [r["path"] in trusted for r in rows]
    chunks = [
        (
            str(images_path),
            str(dataset_dir),
            rows[lo : lo + CACHE_ROWS_PER_CHUNK],
            lo * len(sigmas),
            known[lo : lo + CACHE_ROWS_PER_CHUNK],
        )
        for lo in range(0, len(rows), CACHE_ROWS_PER_CHUNK)
    ]
    fill = functools.partial(_fill_cache_rows, sigmas=tuple(sigmas), pp=pp, verify_sha256=verify_sha256)
    with Progress(len(rows), "cache crops", "exr", "auto" if progress else "lines") as bar:
        if n_jobs == 1:
            for chunk in chunks:
                fill(chunk, on_row=bar.update)
        else:
            # spawn, not fork: this process has torch's thread pools, which a forked child inherits broken
            pool = ProcessPoolExecutor(n_jobs, mp_context=multiprocessing.get_context("spawn"))
            try:
                for done in as_completed([pool.submit(fill, chunk) for chunk in chunks]):
                    bar.update(done.result())
            finally:  # on an error, do not wait for the other chunks
                pool.shutdown(wait=True, cancel_futures=True)


def crop_export_index(export_dir: str | Path) -> dict:
    """The index of a ``train.export_dir``: an ``export --shape crop`` holding the IF channel."""
    index = read_index(export_dir)
    mode = (index.get("shape") or {}).get("mode", "native")
    if mode != "crop" or "IF" not in index["channels"] or index.get("record_kind") != "render":
        raise DatasetError(
            f"train.export_dir={export_dir}: training reads a `crater-synth export --shape crop` of a rendered "
            f"dataset with the IF channel; this one is {mode} {index.get('record_kind')} {list(index['channels'])}"
        )
    return index


def _fill_from_export(images_path: Path, rows: list, export_dir, sigmas, pp: PreprocessConfig) -> None:
    """The cache's arrays from a ``crater-synth export --shape crop`` of the same rows (read through
    :mod:`train.exported`): the export wrote each crop with the cache's own function
    (:func:`train.preprocess.cached_crop`), so at the same geometry they are the same arrays and no EXR
    is decoded. A different geometry, or a (row, sigma) the export lacks, is a :class:`DatasetError`."""
    shape = crop_export_index(export_dir)["shape"]
    want = pp.geometry_key() | {"max_outside_frac": pp.max_outside_frac}
    got = {k: shape.get(k) for k in want}
    if got != want:
        raise DatasetError(
            f"train.export_dir={export_dir} was cropped with {got}; training needs {want}: export it again "
            "(`crater-synth export DATASET --shape crop` with the same train.preprocess and model.input_size)"
        )
    slot = {(r["sha256"], round(float(s), 6)): (i, float(s)) for i, r in enumerate(rows) for s in sigmas}
    arr = np.load(images_path, mmap_mode="r+")
    filled = np.zeros(len(arr), dtype=bool)
    for rec in iter_records(export_dir, ["IF"]):
        hit = slot.get((rec.row.get("sha256"), round(float(rec.labels.get("sigma", math.nan)), 6)))
        if hit is not None:
            j = hit[0] * len(sigmas) + list(sigmas).index(hit[1])
            arr[j], filled[j] = rec.arrays["IF"], True
    arr.flush()
    if not filled.all():
        j = int(np.argmin(filled))
        raise DatasetError(
            f"train.export_dir={export_dir} has no crop of {rows[j // len(sigmas)]['path']} at "
            f"sigma={sigmas[j % len(sigmas)]}: export the dataset again with --shape crop"
        )


def load_export_rows(export_dir: str | Path) -> list[dict]:
    """The manifest rows a ``train.export_dir`` export carries (each once, in its order), with the
    duplicate checks of :func:`load_rows`."""
    rows, seen = [], set()
    for rec in iter_records(export_dir, []):
        if rec.row.get("sha256") not in seen:
            seen.add(rec.row.get("sha256"))
            rows.append(rec.row)
    conflicts = duplicate_faults(rows)
    if conflicts:
        raise DatasetError(f"train.export_dir={export_dir}: {conflicts[0]}: refused for training")
    return rows


def _publish_cache_dir(tmp: Path, final: Path) -> None:
    """Make ``tmp``'s files shareable and durable (files and their directory entries), then rename it
    to ``final``; when another process finished the same cache first, drop ``tmp``."""

    for f in tmp.iterdir():
        os.chmod(f, 0o666 & ~umask())
        with open(f, "rb") as fh:
            os.fsync(fh.fileno())
    dir_fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    try:
        os.replace(tmp, final)
    except OSError:  # another process finished the same cache first
        shutil.rmtree(tmp, ignore_errors=True)


def build_cache(
    rows: Sequence[dict],
    dataset_dir: str | Path,
    sigmas: Sequence[float],
    pp: PreprocessConfig,
    cache_dir: str | Path,
    dtype: str = "float16",
    verify_sha256: bool = True,
    progress: bool = False,
    workers: int = 1,
    export_dir: str | Path | None = None,
) -> CropCache:
    """Resample every (row, sigma) once into ``cache_dir`` (atomic: built in a temp dir, then renamed);
    reuse it when present. ``workers`` processes share the work (0: one per core; small caches are
    built in this process). Missing/corrupt EXR, checksum mismatch or a box outside its EXR raise
    :class:`DatasetError` naming the file. With ``export_dir`` (``train.export_dir``) the arrays are
    read from that ``crater-synth export --shape crop`` instead (:func:`_fill_from_export`)."""

    t0 = time.perf_counter()
    rows = list(rows)
    key = cache_key(rows, sigmas, pp, dtype, "" if export_dir is not None else files_identity(rows, dataset_dir))
    if export_dir is not None:  # its own entry: the arrays come from the export's files
        key += "-export-" + hashlib.sha256(json.dumps(read_index(export_dir)["shards"]).encode()).hexdigest()[:10]
    final = Path(cache_dir) / key
    samples = [(i, float(s)) for i in range(len(rows)) for s in sigmas]
    images = _reuse_cache(final, samples, pp.size)
    if images is not None:
        return CropCache(final, images, samples, built=False, seconds=time.perf_counter() - t0)
    ensure_writable_dir(final.parent, "train.cache_dir")
    tmp = Path(tempfile.mkdtemp(prefix=f".{key}.", dir=final.parent))
    try:
        os.chmod(tmp, 0o777 & ~umask())  # mkdtemp makes 0700: a cache is shared like the dataset
        arr = np.lib.format.open_memmap(
            tmp / "images.npy", mode="w+", dtype=np.dtype(dtype), shape=(len(samples), pp.size, pp.size)
        )
        del arr
        if export_dir is None:
            _fill_cache(tmp / "images.npy", rows, dataset_dir, sigmas, pp, verify_sha256, workers, progress)
        else:
            _fill_from_export(tmp / "images.npy", rows, export_dir, sigmas, pp)
        index = {
            "format": CACHE_FORMAT,
            "key": key,
            "dataset_dir": str(dataset_dir),
            "export_dir": None if export_dir is None else str(export_dir),
            "samples": samples,
            "sigmas": list(sigmas),
            "pp": pp.geometry_key(),
            "dtype": dtype,
        }
        (tmp / "index.json").write_text(json.dumps(index))
        _publish_cache_dir(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    images = np.load(final / "images.npy", mmap_mode="r")
    return CropCache(final, images, samples, built=True, seconds=time.perf_counter() - t0)


# ------------------------------------------------------------------------------------------------
# Dataset
# ------------------------------------------------------------------------------------------------
class SyntheticCropDataset(Dataset):
    """Normalised synthetic crops, one per (row, sigma), for the cached samples ``indices``.

    ``__getitem__`` -> (float tensor (1, N, N), int label). ``train=True`` draws fresh sensor noise
    every epoch (:meth:`set_epoch`) and random rotations (``augment``: by right angles, or by any angle
    with ``rotation="any"`` on disc-support crops); ``train=False``
    uses one fixed noise draw per sample (a stable validation set).
    """

    def __init__(
        self,
        cache: CropCache,
        indices: Sequence[int],
        labels: Sequence[int],
        rows: Sequence[dict],
        pp: PreprocessConfig,
        sensor: SensorModel | None,
        seed: int,
        train: bool,
        augment: bool = False,
        diameters_m: Mapping[str, float] | None = None,
        rotation: str = "right_angles",
        offset_frac: float = 0.0,
    ):
        self.cache = cache
        self.indices = np.asarray(indices, dtype=np.int64)
        self.labels = np.asarray(labels, dtype=np.int64)
        self.rows = rows
        self.pp = pp
        self.sensor = sensor if (sensor is not None and sensor.enabled) else None
        self.seed = int(seed) & 0xFFFFFFFF
        self.train = train
        self.augment = augment and train
        # rotation and offset_frac: train.augment_rotation / augment_offset_frac, whose ranges and need of
        # disc support the settings check (crater_core.settings.TrainSettings).
        self.rotation = rotation
        self.offset_frac = float(offset_frac)
        self.epoch = 0
        self.diameters_m = dict(diameters_m or {})  # crater -> rim diameter: a crop's ground width is sigma x D
        # Mosaic composites draw their extra frames among the same camera pose's renders in this split.
        self.partners = (
            same_pose_partners(cache, self.indices, rows)
            if self.sensor is not None and self.sensor.mosaic_frames > 1
            else None
        )
        if len(self.indices) != len(self.labels):
            raise DatasetError("internal: indices and labels differ in length")

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.indices)

    def sample_info(self, i: int) -> dict:
        ri, s = self.cache.samples[int(self.indices[i])]
        r = self.rows[ri]
        return {"crater": r["crater"], "sigma": s, "path": r["path"]}

    def image(self, i: int) -> np.ndarray:
        j = int(self.indices[i])
        x = np.asarray(self.cache.images[j], dtype=np.float32)
        rng = np.random.default_rng([self.seed, self.epoch + 1 if self.train else 0, j])
        if self.partners is not None:
            others = self.partners[j]
            k = min(int(self.sensor.mosaic_frames) - 1, len(others))
            if k > 0:
                extra = [
                    np.asarray(self.cache.images[o], dtype=np.float32)
                    for o in rng.choice(others, size=k, replace=False)
                ]
                x = mosaic_composite([x] + extra, rng, self.sensor.mosaic_blend, self.sensor.mosaic_patches)
        if self.sensor is not None:
            ri, sigma = self.cache.samples[j]
            d = self.diameters_m.get(self.rows[ri]["crater"])
            x = self.sensor.apply(x, rng, box_side_m=None if d is None else sigma * d)
        y = normalize(x, self.pp)
        if self.augment and (self.rotation == "any" or self.offset_frac > 0.0):
            # A camera roll about the boresight and a slewing offset, as the real crops are taken.
            angle = float(rng.uniform(0.0, 360.0)) if self.rotation == "any" else 90.0 * int(rng.integers(4))
            du, dv = rng.uniform(-self.offset_frac, self.offset_frac, size=2) * y.shape[-1]
            y = rotate_crop(y, angle, (float(du), float(dv)))
        elif self.augment:  # exact right angles, as before the roll and slewing options existed
            y = np.ascontiguousarray(np.rot90(y, int(rng.integers(4))))
        return apply_support(y, self.pp)

    def __getitem__(self, i: int):
        return torch.from_numpy(self.image(i)[None]), int(self.labels[i])

    def iter_arrays(self, batch_size: int = 256, positions: Sequence[int] | None = None):
        """Deterministic (no augmentation, epoch-0 noise) batches ``(X (B, N, N) float32, y (B,))`` over
        ``positions`` (default: all), streamed so a large dataset never sits in memory at once."""
        pos = np.arange(len(self)) if positions is None else np.asarray(positions, dtype=np.int64)
        saved = (self.augment, self.epoch)
        self.augment, self.epoch = False, 0
        try:
            for k in range(0, len(pos), batch_size):
                chunk = pos[k : k + batch_size]
                yield np.stack([self.image(int(i)) for i in chunk]), self.labels[chunk].copy()
        finally:
            self.augment, self.epoch = saved

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """All images and labels at once (small datasets only; see :meth:`iter_arrays`)."""
        parts = list(self.iter_arrays(1024))
        if not parts:
            return np.zeros((0, self.pp.size, self.pp.size), np.float32), np.zeros(0, np.int64)
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def same_pose_partners(cache: CropCache, indices: Sequence[int], rows: Sequence[dict]) -> dict[int, np.ndarray]:
    """For each cached sample in ``indices``: the other samples in ``indices`` of the same crater,
    camera pose (elevation, azimuth) and sigma -- the same crop of the same view under other suns."""
    groups: dict[tuple, list[int]] = {}
    for j in indices:
        ri, sigma = cache.samples[int(j)]
        r = rows[ri]
        key = (r["crater"], round(float(r["cam_elevation"]), 6), round(float(r["cam_azimuth"]), 6), sigma)
        groups.setdefault(key, []).append(int(j))
    out = {}
    for members in groups.values():
        arr = np.asarray(members, dtype=np.int64)
        for j in members:
            out[j] = arr[arr != j]
    return out


def seeded_subsample(n: int, limit: int | None, seed: int, stream: int) -> np.ndarray:
    """Sorted positions of at most ``limit`` of ``n`` items, drawn without replacement from the random
    stream (``seed``, ``stream``); every position if ``limit`` is None or not smaller than ``n``."""
    if not limit or limit >= n:
        return np.arange(n)
    return np.sort(np.random.default_rng([int(seed) & 0xFFFFFFFF, stream]).choice(n, size=int(limit), replace=False))


def budget_subsample(indices: list[int], limit: int | None, seed: int, stream: int) -> list[int]:
    """At most ``limit`` of ``indices``, drawn without replacement by ``seed`` (order kept); all if None."""
    return [indices[k] for k in seeded_subsample(len(indices), limit, seed, stream)]


def selected_positions(rows: Sequence[dict], selection: Mapping | None, dataset_dir: str | Path) -> list[int]:
    """Positions in ``rows`` of the rows inside ``train.select`` (a grid subset; None: every row)."""
    if not selection:
        return list(range(len(rows)))

    inside = {id(r) for r in rows_in_selection(rows, dict(selection))}
    used = [i for i, r in enumerate(rows) if id(r) in inside]
    if not used:
        raise DatasetError(f"{dataset_dir}: no manifest row matches train.select={as_plain(dict(selection))}")
    return used


def _train_sigmas(ts: TrainSettings, rows: Sequence[dict], used_rows: Sequence[dict]) -> tuple[list, list]:
    """(the sigmas trained on, the sigmas the crop cache holds): every sigma of the manifest, so that the
    subsets of one dataset share one cache; with ``train.export_dir``, the export's sigmas."""
    if not ts.export_dir:
        sigmas = row_sigmas(used_rows, ts.sigmas)
        return sigmas, sorted({round(s, 6) for s in sigmas} | set(row_sigmas(rows, None)))
    exported = sorted(round(float(s), 6) for s in crop_export_index(ts.export_dir)["shape"]["sigmas"])
    sigmas = row_sigmas(used_rows, ts.sigmas or exported)
    missing = [s for s in sigmas if round(s, 6) not in exported]
    if missing:
        raise DatasetError(f"train.sigmas {missing} are not in train.export_dir={ts.export_dir} (sigmas {exported})")
    return sigmas, exported


@dataclass
class SyntheticData:
    train: SyntheticCropDataset
    val: SyntheticCropDataset
    class_names: list[str]
    info: dict = field(default_factory=dict)


def build_datasets(
    settings: Settings,
    forbidden_sha256: Iterable[str] = (),
    forbidden_paths: Iterable[str | Path] = (),
    progress: bool = False,
) -> SyntheticData:
    """From the validated settings: manifest -> leak guard -> classes -> split -> cache -> datasets."""
    ts = settings.train
    # train.export_dir: the rows and crops come from an export of the dataset (its files named relative to it).
    dataset_dir = Path(crop_export_index(ts.export_dir)["dataset"] if ts.export_dir else ts.dataset_dir)
    class_names = class_names_of(settings)
    # The crop cache covers every row of the configured craters at every sigma of the manifest, so the
    # subsets of one dataset (Figure 6 points, closed-loop rounds, a sigma) share one cache: a subset
    # is a choice of cached samples, never a second decode of the EXRs.
    source = load_export_rows(ts.export_dir) if ts.export_dir else load_rows(dataset_dir)
    rows = check_synthetic_rows(
        source, dataset_dir, set(forbidden_sha256) | forbidden_sha256_of(settings), forbidden_paths
    )
    rows, others = select_rows(rows, class_names)
    used = selected_positions(rows, ts.select, dataset_dir)
    used_rows = [rows[i] for i in used]
    select_rows(used_rows, class_names)  # every class keeps rows in the selection
    seed = ts.seed
    tr_used, va_used, split_info = split_rows(used_rows, ts.val_fraction, ts.split_by, seed, class_names)
    tr_rows, va_rows = [used[i] for i in tr_used], [used[i] for i in va_used]
    sigmas, cache_sigmas = _train_sigmas(ts, rows, used_rows)
    pp = PreprocessConfig.from_settings(settings.train.preprocess, settings.model.input_size)
    cache = build_cache(
        rows,
        dataset_dir,
        cache_sigmas,
        pp,
        cache_dir_of(ts),
        ts.cache_dtype,
        ts.verify_sha256,
        progress,
        ts.cache_workers,
        ts.export_dir,
    )
    sensor = SensorModel.from_settings(settings.sensor)
    diameters = {c.name: c.diameter_km * 1000.0 for c in settings.craters}
    cls = {n: i for i, n in enumerate(class_names)}
    tr_set, va_set, wanted = set(tr_rows), set(va_rows), {round(s, 6) for s in sigmas}
    tr_idx = [j for j, (ri, s) in enumerate(cache.samples) if ri in tr_set and round(s, 6) in wanted]
    va_idx = [j for j, (ri, s) in enumerate(cache.samples) if ri in va_set and round(s, 6) in wanted]
    # A budget cut (train.max_train_images / max_val_images) keeps a seeded subsample, in cache order.
    tr_idx = budget_subsample(tr_idx, ts.max_train_images, seed, 0x7A1)
    va_idx = budget_subsample(va_idx, ts.max_val_images, seed, 0x7A2)
    lab = [cls[rows[ri]["crater"]] for ri, _ in cache.samples]
    train_ds = SyntheticCropDataset(
        cache,
        tr_idx,
        [lab[j] for j in tr_idx],
        rows,
        pp,
        sensor,
        seed,
        train=True,
        augment=ts.augment,
        diameters_m=diameters,
        rotation=ts.augment_rotation,
        offset_frac=ts.augment_offset_frac,
    )
    val_ds = SyntheticCropDataset(
        cache, va_idx, [lab[j] for j in va_idx], rows, pp, sensor, seed, train=False, diameters_m=diameters
    )
    info = split_info | {
        "sigmas": sigmas,
        "cache": str(cache.path),
        "cache_built": cache.built,
        "cache_seconds": round(cache.seconds, 3),
        "cache_bytes": int(cache.images.nbytes),
        "train_images": len(tr_idx),
        "val_images": len(va_idx),
        "ignored_craters": others,
        "class_counts_train": {n: int(np.sum(np.asarray(train_ds.labels) == i)) for n, i in cls.items()},
    }
    return SyntheticData(train_ds, val_ds, class_names, info)
