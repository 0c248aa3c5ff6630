"""A training frame's row as the detector's training reads it: its labels as rim circles, held in memory or
streamed from disk.

- :func:`label_circles` (a survey frame's landmarks, a detection frame's labels, or a slimmed row's arrays)
  and :func:`column_circles` (a label file's columns) give the rims a training targets, with the rims it
  treats as neither (:func:`hidden_rims`).
- :func:`slim_row` keeps a held training row's circles only; :func:`streamed_row` keeps where a streamed
  row's frame and label file are (``nav.detector_train.stream``), :class:`StreamedFrames` reads them when a
  crop of them is drawn, and :func:`record_frame` when a held-out frame is scored.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from crater_core import exr
from crater_core.detection_labels import label_ref, read_label_columns, with_labels
from crater_synth.errors import UserError
from crater_synth.navigation.rendered.sunlight import rendered_light
from train.light_turn import turn_to_light, turned_shape

MIN_LIT_RIM = 0.05  # a rim less lit than this is in shadow all round: invisible, trained as neither


def labels_in_frame(row: dict, shape) -> list[dict]:
    """The frame's labels whose rim-ellipse centre lies inside a frame of ``shape``: a survey frame's
    landmarks, or a detection frame's procedural craters (``crater-synth detection-frames``)."""
    h, w = shape
    labels = row["landmarks"] if "landmarks" in row else row["labels"]
    return [lm for lm in labels if 0 <= lm["ellipse"]["cu"] < w and 0 <= lm["ellipse"]["cv"] < h]


def label_circles(row: dict, shape) -> tuple[np.ndarray, ...]:
    """Labelled rims whose centre is in the frame: (u, v, r px, diameter km, hidden), ``hidden`` where the
    label's lit-rim fraction is below ``MIN_LIT_RIM`` (unknown lit fraction: not hidden) or, for a
    detection frame's label, where nearer relief hides most of its rim (``occluded``). A row slimmed by
    :func:`slim_row` carries these arrays already (``circles``)."""
    if "circles" in row:
        u, v, r, d, hidden = row["circles"]
        h, w = shape
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        return u[inside], v[inside], r[inside], d[inside], hidden[inside]
    lms = labels_in_frame(row, shape)
    u = np.array([lm["ellipse"]["cu"] for lm in lms], float)
    v = np.array([lm["ellipse"]["cv"] for lm in lms], float)
    r = np.array([lm["ellipse"]["a"] for lm in lms], float)
    d = np.array([lm["diameter_km"] if "diameter_km" in lm else lm["diameter_m"] / 1000.0 for lm in lms], float)
    lit = np.array([np.nan if lm.get("lit_rim_fraction") is None else lm["lit_rim_fraction"] for lm in lms], float)
    occluded = np.array([bool(lm.get("occluded", False)) for lm in lms], bool)
    return u, v, r, d, hidden_rims(lit, occluded)


def hidden_rims(lit: np.ndarray, occluded: np.ndarray) -> np.ndarray:
    """Labels training treats as neither: a lit-rim fraction below ``MIN_LIT_RIM`` (NaN, unknown: lit) or
    a rim mostly hidden by nearer relief."""
    return (np.nan_to_num(lit, nan=1.0) < MIN_LIT_RIM) | occluded


CIRCLE_COLUMNS = ("ellipse", "diameter_m", "lit_rim_fraction", "occluded")  # what column_circles reads


def column_circles(cols: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
    """:func:`label_circles` of a detection frame's label columns (its label file), every label."""
    ellipse = cols["ellipse"]
    n = len(ellipse)
    lit = cols.get("lit_rim_fraction", np.full(n, np.nan))
    occluded = cols.get("occluded", np.zeros(n, bool))
    d = cols["diameter_m"] / 1000.0
    return ellipse[:, 0].copy(), ellipse[:, 1].copy(), ellipse[:, 2].copy(), d, hidden_rims(lit, occluded)


def slim_row(row: dict, folder: Path | None = None) -> dict:
    """A detection row with its labels replaced by the arrays training reads (:func:`label_circles`):
    ~1,000 labels a frame of a dense surface are ~150 KB of Python objects, their circles ~40 KB. A row
    whose labels are in a label file (``folder``: the set's folder) has them read as columns."""
    inf = (np.inf, np.inf)
    if label_ref(row) is not None:
        if folder is None:
            raise ValueError("slim_row: a row with a label file needs its folder")
        circles = column_circles(read_label_columns(folder, row, CIRCLE_COLUMNS))
    else:
        circles = label_circles(row, inf)
    kept = {k: row[k] for k in ("index", "rel_path", "ground_sample_m", "terrain")}
    return kept | {"off_nadir_deg": off_nadir_deg(row), "light_rad": rendered_light(row), "circles": circles}


def off_nadir_deg(row: dict) -> float:
    """The frame's boresight angle from nadir in degrees: a detection frame's view, else (a survey frame, or a
    slimmed row) what the row carries, nadir when nothing does."""
    return float(row["view"]["off_nadir_deg"]) if "view" in row else float(row.get("off_nadir_deg", 0.0))


def streamed_row(row: dict, folder: Path) -> dict:
    """A detection row as a streamed training keeps it: where its frame and labels are (the label file's
    reference; a row with inline labels keeps their circles, :func:`slim_row`) and what selection reads."""
    kept = {k: row[k] for k in ("index", "rel_path", "ground_sample_m", "terrain")}
    width = (row.get("camera_enu") or {}).get("width_px")
    kept |= {"off_nadir_deg": off_nadir_deg(row), "light_rad": rendered_light(row), "folder": folder, "width_px": width}
    ref = label_ref(row)
    return kept | ({"labels": ref} if ref is not None else {"circles": slim_row(row)["circles"]})


def record_frame(record: tuple) -> tuple[np.ndarray, dict]:
    """(I/F image, row with its labels) of a training or held-out record, read now if it was streamed."""
    image, row = record
    if image is not None:
        return image, row
    folder = row["folder"]
    return exr.read_channel(folder / row["rel_path"], "IF"), with_labels(folder, row)


def streamed_circles(row: dict, shape) -> tuple[np.ndarray, ...]:
    """:func:`label_circles` of a :func:`streamed_row`: its rim columns read from its label file."""
    if "circles" in row:
        return label_circles(row, shape)
    circles = column_circles(read_label_columns(row["folder"], row, CIRCLE_COLUMNS))
    return label_circles({"circles": circles}, shape)


def known_light(row: dict) -> float:
    """:func:`.sunlight.rendered_light` of a frame a sun-aligned training turns; a row without it is one error
    naming it."""
    light = rendered_light(row)
    if not math.isfinite(light):
        raise UserError(f"{row['rel_path']}: nav.detector_train.sun_aligned needs the frame's Sun and camera")
    return light


def training_levels(image: np.ndarray, row: dict, circles, sun_aligned: bool = False) -> list:
    """The level samples (:func:`train.crater_detector.level_samples`) of a training frame and its label
    ``circles`` (:func:`label_circles`); ``sun_aligned``: the frame and its rims turned so that its light
    travels along +u (:func:`train.light_turn.turn_to_light`, ``nav.detector_train.sun_aligned``)."""
    from train.crater_detector import level_samples

    u, v, r, _, hidden = circles
    if sun_aligned:
        turned = turn_to_light(image, known_light(row))
        image = turned.image
        u, v = turned.points(u, v)
    return level_samples(image, u, v, r, hidden)


class PartedSequence(Sequence):
    """A sequence of parts of ``counts`` items each, item i being :meth:`item` (part, index within it)."""

    def __init__(self, counts):
        self.first = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)])

    def __len__(self) -> int:
        return int(self.first[-1])

    def _locate(self, i) -> tuple[int, int]:
        if not 0 <= i < len(self):
            raise IndexError(i)
        j = int(np.searchsorted(self.first, i, side="right")) - 1
        return j, int(i - self.first[j])

    def __getitem__(self, i):
        return self.item(*self._locate(i))

    def shape(self, i) -> tuple[int, int]:
        """Item i's level image shape, without building the item (``train.crater_detector.sample_shape``)."""
        return self.item_shape(*self._locate(i))

    def item(self, part: int, k: int):
        raise NotImplementedError

    def item_shape(self, part: int, k: int) -> tuple[int, int]:
        raise NotImplementedError


class StreamedFrames(PartedSequence):
    """The level samples of streamed detection records (:func:`detection_set_records` with ``stream``), in
    the order a list of them held in memory has (frame by frame, level by level), each built when drawn: its
    frame's EXR and rim columns read, its pyramid made. Memory holds a few values a frame, no image."""

    def __init__(self, rows: list[dict], sun_aligned: bool = False):
        from train.crater_detector import level_count

        self.rows, self.sun_aligned = rows, sun_aligned
        shapes = [self._shape(r) for r in rows]
        if sun_aligned:  # the frame turned to its light (training_levels)
            shapes = [turned_shape(shape, known_light(r)) for shape, r in zip(shapes, rows)]
        self.shapes = np.array(shapes, np.int32).reshape(-1, 2)  # 8 bytes a frame
        super().__init__([level_count(shape) for shape in self.shapes])

    def item_shape(self, part: int, k: int) -> tuple[int, int]:
        from train.crater_detector import level_shapes

        return level_shapes(self.shapes[part])[k]

    @staticmethod
    def _shape(row: dict) -> tuple[int, int]:
        if row.get("width_px"):
            return int(row["width_px"]), int(row["width_px"])
        info = exr.exr_info(row["folder"] / row["rel_path"], decode=False)
        return int(info["height"]), int(info["width"])

    def item(self, part: int, k: int):
        row = self.rows[part]
        image = exr.read_channel(row["folder"] / row["rel_path"], "IF")
        return training_levels(image, row, streamed_circles(row, image.shape), self.sun_aligned)[k]


class ChainedSamples(PartedSequence):
    """Several sources' level samples as one sequence (a list held in memory, :class:`StreamedFrames`)."""

    def __init__(self, parts: list):
        self.parts = parts
        super().__init__([len(p) for p in parts])

    def item(self, part: int, k: int):
        return self.parts[part][k]

    def item_shape(self, part: int, k: int) -> tuple[int, int]:
        from train.crater_detector import sample_shape

        return sample_shape(self.parts[part], k)
