"""Fixed-shape tensors of ``crater-synth export --shape crop|pad`` (docs/export.md): how a row's images become
samples of one shape. ``crop``: one sample per sigma, the sigma box resampled to the classifier's input by the
crop cache's own function (``train.preprocess.cached_crop``); ``pad``: every image zero-padded to the export's
largest, with a ``valid`` mask; ``native``: the stored arrays, unchanged (:mod:`.export`)."""

from __future__ import annotations

import contextlib
import dataclasses
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import pyarrow as pa

from crater_synth.config import load_settings
from crater_synth.dataset.export_writers import VALID_COLUMN, Layout, Sample, column_name
from crater_synth.dataset.record_kinds import ExportError, RecordKind
from train.errors import TrainError
from train.preprocess import PreprocessConfig, cached_crop

SHAPES = ("native", "crop", "pad")


# ------------------------------------------------------------------------------------------------
# Fixed-shape tensors (--shape crop | pad)
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Shaping:
    """How ``--shape`` turns a row's images into samples: ``native`` (one sample, NPY bytes as stored),
    ``crop`` (one sample per sigma: the sigma box resampled to ``pp.size`` by the crop cache's own
    function, :func:`train.preprocess.cached_crop`) or ``pad`` (one sample, every channel zero-padded
    (``pad_value``) at its bottom and right to ``layout.shape``, with a ``valid`` mask)."""

    layout: Layout = Layout()
    sigmas: tuple[float, ...] = ()
    pp: PreprocessConfig | None = None
    pad_value: float = 0.0

    def samples(self, key: str, labels: dict, row: dict, arrays: dict, where: str) -> Iterator[Sample]:
        if self.layout.mode == "pad":
            h, w = self.layout.shape
            out = {}
            for c, a in arrays.items():
                if a.shape[0] > h or a.shape[1] > w:
                    raise ExportError(f"{where}: {c} is {a.shape}, larger than the export's {h}x{w} (files changed?)")
                out[column_name(c)] = np.full((h, w), self.pad_value, np.float32)
                out[column_name(c)][: a.shape[0], : a.shape[1]] = a
            a = next(iter(arrays.values()))
            valid = np.zeros((h, w), np.uint8)
            valid[: a.shape[0], : a.shape[1]] = 1
            extra = {"orig_height": int(a.shape[0]), "orig_width": int(a.shape[1])}
            yield Sample(key, labels | extra, row, {}, out | {VALID_COLUMN: valid})
            return
        for sigma in self.sigmas:
            box = sigma_box(row, sigma, where)
            try:
                crops = {column_name(c): cached_crop(a, box, self.pp, where, sigma) for c, a in arrays.items()}
            except TrainError as exc:
                raise ExportError(str(exc)) from None
            extra = {"sigma": float(sigma), "crop_box": [float(b) for b in box]}
            yield Sample(f"{key}_s{sigma_tag(sigma)}", labels | extra, row, {}, crops)


def sigma_tag(sigma: float) -> str:
    """A sigma in a sample key: ``1.2`` -> ``1p2`` (keys have no dots)."""
    return f"{float(sigma):g}".replace(".", "p")


def sigma_box(row: dict, sigma: float, where: str) -> list[float]:
    """The row's box (u0, v0, u1, v1) for ``sigma`` (keys compared as numbers)."""
    for k, box in (row.get("sigma_boxes") or {}).items():
        with contextlib.suppress(TypeError, ValueError):
            if abs(float(k) - float(sigma)) < 1e-6:
                return [float(b) for b in box]
    raise ExportError(f"{where}: no sigma box for sigma={sigma} (has {sorted(row.get('sigma_boxes') or {})})")


def crop_defaults(overrides: Sequence[str] = ()) -> tuple[tuple[float, ...] | None, PreprocessConfig]:
    """The classifier's crop from the composed settings: ``train.sigmas`` (None: every sigma of the rows,
    as training takes them) and the preprocessing geometry at ``model.input_size``."""
    settings = load_settings(list(overrides))
    sigmas = settings.train.sigmas
    return (tuple(sigmas) if sigmas else None), PreprocessConfig.from_settings(
        settings.train.preprocess, settings.model.input_size
    )


def plan_shaping(
    rk: RecordKind,
    dataset_dir: Path,
    shape: str,
    sigmas: Sequence[float] | None,
    pp: PreprocessConfig | None,
    pad_value: float,
) -> Shaping:
    """The shaping of ``--shape``; ``crop`` and ``pad`` read every row once more (sigmas, largest shape)."""
    if shape not in SHAPES:
        raise ExportError(f"unknown export shape {shape!r}; choose one of {', '.join(SHAPES)}")
    if shape == "native":
        return Shaping()
    f64, i64 = pa.float64(), pa.int64()
    if shape == "pad":
        shapes = {rk.shape(dataset_dir, row) for row in rk.rows(dataset_dir)[1]}
        hw = (max(h for h, _ in shapes), max(w for _, w in shapes))
        record = {"mode": "pad", "shape": list(hw), "dtype": "float32", "pad_value": pad_value}
        record |= {"anchor": "top-left", "mask": VALID_COLUMN, "original_shape": ["orig_height", "orig_width"]}
        layout = Layout("pad", hw, (("orig_height", i64), ("orig_width", i64)), record)
        return Shaping(layout, pad_value=float(pad_value))
    if rk.name != "render":
        raise ExportError(f"--shape crop needs sigma boxes, which {rk.name} records have not: use --shape pad")
    if not sigmas:
        found = {round(float(k), 6) for row in rk.rows(dataset_dir)[1] for k in row.get("sigma_boxes") or {}}
        sigmas = sorted(found)
    if not sigmas:
        raise ExportError(f"dataset {dataset_dir}: its rows carry no sigma_boxes to crop")
    sigmas = tuple(sorted(float(s) for s in dict.fromkeys(sigmas)))
    record = {"mode": "crop", "shape": [pp.size, pp.size], "dtype": "float32", "sigmas": list(sigmas)}
    record |= {"size": pp.size, **pp.geometry_key(), "max_outside_frac": pp.max_outside_frac}
    record["resample"] = "train.preprocess.cached_crop (the crop cache's geometric step; no photometry)"
    layout = Layout("crop", (pp.size, pp.size), (("sigma", f64), ("crop_box", pa.list_(f64))), record)
    return Shaping(layout, sigmas, pp)
