"""Typed settings of the training stage: ``model``, ``train`` (+ ``preprocess``, ``svm``, ``hog``),
``sensor`` and ``realset`` (part of :mod:`crater_core.settings`, which re-exports them; how to add a
key is explained there). Standard library only."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

from crater_core.sweep import AXES
from crater_core.typed_config import Group, need


@dataclass(frozen=True, kw_only=True)
class ConvSettings(Group):
    channels: int
    kernel: int
    stride: int

    def _check(self):
        for key in ("channels", "kernel", "stride"):
            need(getattr(self, key) >= 1, key, getattr(self, key), "must be >= 1")


@dataclass(frozen=True, kw_only=True)
class PoolSettings(Group):
    kernel: int
    stride: int

    def _check(self):
        for key in ("kernel", "stride"):
            need(getattr(self, key) >= 1, key, getattr(self, key), "must be >= 1")


@dataclass(frozen=True, kw_only=True)
class ModelSettings(Group):
    """``model.*``: LunarNet_ex layer sizes (configs/model/lunarnet_ex.yaml, docs/classifiers.md)."""

    name: str
    input_size: int
    num_classes: int
    conv1: ConvSettings
    pool: PoolSettings
    conv2: ConvSettings
    fc1: int
    dropout: float = 0.0

    def _check(self):
        need(self.input_size >= 8, "input_size", self.input_size, "must be >= 8")
        need(self.num_classes >= 2, "num_classes", self.num_classes, "must be >= 2")
        need(self.fc1 >= 1, "fc1", self.fc1, "must be >= 1")
        need(0.0 <= self.dropout < 1.0, "dropout", self.dropout, "must lie in [0, 1)")
        need(self.conv1.stride == 1, "conv1.stride", self.conv1.stride, "must be 1 (the paper fixes CONV1's stride)")
        c1, p, c2 = self.conv1, self.pool, self.conv2
        need(
            min(self.feature_sizes()) >= 1,
            "input_size",
            self.input_size,
            f"too small for conv1 kernel {c1.kernel}, pool {p.kernel}/{p.stride} and conv2 kernel {c2.kernel} "
            f"stride {c2.stride}",
        )

    def feature_sizes(self) -> Tuple[int, int, int]:
        """Sides (h1, hp, h2) of the CONV1, POOL and CONV2 output maps for an ``input_size`` square crop
        (CONV1 stride 1, no padding): the network's shape (train/models.py) and the check above."""
        h1 = self.input_size - self.conv1.kernel + 1
        hp = (h1 - self.pool.kernel) // self.pool.stride + 1
        h2 = (hp - self.conv2.kernel) // self.conv2.stride + 1
        return h1, hp, h2


@dataclass(frozen=True, kw_only=True)
class PreprocessSettings(Group):
    """``train.preprocess``: crop resampling and photometric normalisation (docs/preprocessing.md)."""

    antialias: bool
    interp_order: int
    max_outside_frac: float
    low_percentile: float
    high_percentile: float
    lit_threshold: float
    shadow_floor: float
    gamma: float
    support: str = "square"  # square | disc (docs/preprocessing.md)

    def _check(self):
        need(self.interp_order in (0, 1, 3), "interp_order", self.interp_order, "must be 0, 1 or 3")
        need(0.0 <= self.max_outside_frac < 1.0, "max_outside_frac", self.max_outside_frac, "must lie in [0, 1)")
        need(
            0.0 <= self.low_percentile < self.high_percentile,
            "low_percentile",
            self.low_percentile,
            "must lie in [0, high_percentile)",
        )
        need(self.high_percentile <= 100.0, "high_percentile", self.high_percentile, "must be <= 100")
        need(0.0 <= self.lit_threshold < 1.0, "lit_threshold", self.lit_threshold, "must lie in [0, 1)")
        need(0.0 <= self.shadow_floor < 1.0, "shadow_floor", self.shadow_floor, "must lie in [0, 1)")
        need(self.gamma > 0.0, "gamma", self.gamma, "must be > 0")
        need(self.support in ("square", "disc"), "support", self.support, "must be square or disc")


@dataclass(frozen=True, kw_only=True)
class SvmSettings(Group):
    """``train.svm``: the SGD linear SVM of LunarSVM_ex."""

    alpha: float
    max_iter: int
    tol: float

    def _check(self):
        need(self.alpha > 0.0, "alpha", self.alpha, "must be > 0")
        need(self.max_iter >= 1, "max_iter", self.max_iter, "must be >= 1")
        need(self.tol >= 0.0, "tol", self.tol, "must be >= 0")


@dataclass(frozen=True, kw_only=True)
class HogSettings(SvmSettings):
    """``train.hog``: HOG features + SGD linear SVM baseline."""

    orientations: int
    pixels_per_cell: int
    cells_per_block: int
    max_train_images: Optional[int] = None

    def _check(self):
        super()._check()
        for key in ("orientations", "pixels_per_cell", "cells_per_block"):
            need(getattr(self, key) >= 1, key, getattr(self, key), "must be >= 1")
        need(
            self.max_train_images is None or self.max_train_images >= 1,
            "max_train_images",
            self.max_train_images,
            "must be >= 1 (null = all)",
        )


@dataclass(frozen=True, kw_only=True)
class TrainSettings(Group):
    """``train.*`` (configs/train/default.yaml, docs/classifiers.md)."""

    dataset_dir: str
    seed: int  # split, augmentation, sensor noise and weight initialisation (${seed})
    val_fraction: float
    split_by: str
    sigmas: Optional[Tuple[float, ...]]
    select: Optional[Dict[str, Optional[Tuple[float, ...]]]]
    batch_size: int
    eval_batch_size: int
    lr: float
    weight_decay: float
    max_epochs: int
    target_val_accuracy: float
    num_threads: int
    device: str
    cache_dir: str
    cache_dtype: str
    cache_workers: int
    export_dir: Optional[str] = None  # a `crater-synth export --shape crop` of dataset_dir: crops read from it
    max_train_images: Optional[int] = None  # seeded subsample of the training samples (a budget cut)
    max_val_images: Optional[int] = None  # the same for the validation samples
    verify_sha256: bool
    augment: bool
    augment_rotation: str = "right_angles"  # right_angles | any (any needs preprocess.support=disc)
    augment_offset_frac: float = 0.0  # slewing: random shift up to this fraction of the side per axis
    tta_rotations: int = 1  # real crops: scores averaged over this many rolls, 360/n apart (>1 needs disc)
    progress: bool
    preprocess: PreprocessSettings
    svm: SvmSettings
    hog: HogSettings

    def _check(self):
        need(0.0 < self.val_fraction < 1.0, "val_fraction", self.val_fraction, "must lie in (0, 1)")
        need(self.split_by in ("camera", "sun"), "split_by", self.split_by, "must be 'camera' or 'sun'")
        need(self.sigmas is None or all(s > 0 for s in self.sigmas), "sigmas", self.sigmas, "must be > 0")
        unknown = sorted(set(self.select or {}) - set(AXES))
        need(not unknown, "select", unknown, f"unknown axis: use {', '.join(AXES)}")
        for key in ("batch_size", "eval_batch_size", "max_epochs"):
            need(getattr(self, key) >= 1, key, getattr(self, key), "must be >= 1")
        need(self.lr > 0.0, "lr", self.lr, "must be > 0")
        need(self.weight_decay >= 0.0, "weight_decay", self.weight_decay, "must be >= 0")
        need(
            0.0 <= self.target_val_accuracy <= 1.0,
            "target_val_accuracy",
            self.target_val_accuracy,
            "must lie in [0, 1]",
        )
        need(self.num_threads >= 0, "num_threads", self.num_threads, "must be >= 0 (0 = all cores)")
        need(self.device in ("auto", "cpu", "cuda"), "device", self.device, "must be auto, cpu or cuda")
        need(self.cache_dtype in ("float16", "float32"), "cache_dtype", self.cache_dtype, "must be float16 or float32")
        need(self.cache_workers >= 0, "cache_workers", self.cache_workers, "must be >= 0 (0 = one per core)")
        for key in ("max_train_images", "max_val_images"):
            value = getattr(self, key)
            need(value is None or value >= 1, key, value, "must be >= 1 (null = all)")
        need(
            self.augment_rotation in ("right_angles", "any"),
            "augment_rotation",
            self.augment_rotation,
            "must be right_angles or any",
        )
        need(
            0.0 <= self.augment_offset_frac <= 0.25,
            "augment_offset_frac",
            self.augment_offset_frac,
            "must lie in [0, 0.25]",
        )
        need(
            self.augment_offset_frac == 0.0 or self.preprocess.support == "disc",
            "augment_offset_frac",
            self.augment_offset_frac,
            "needs train.preprocess.support=disc (a shifted square crop has an empty strip)",
        )
        need(self.tta_rotations >= 1, "tta_rotations", self.tta_rotations, "must be >= 1 (1 = no roll averaging)")
        need(
            self.tta_rotations == 1 or self.preprocess.support == "disc",
            "tta_rotations",
            self.tta_rotations,
            "needs train.preprocess.support=disc (a square crop turned by any angle has empty corners)",
        )
        need(
            self.augment_rotation != "any" or self.preprocess.support == "disc",
            "augment_rotation",
            self.augment_rotation,
            "needs train.preprocess.support=disc (a square crop turned by any angle has empty corners)",
        )


@dataclass(frozen=True, kw_only=True)
class SensorSettings(Group):
    """``sensor.*``: the seeded sensor model applied to synthetic crops (docs/preprocessing.md)."""

    enabled: bool
    resolution_min_px: int
    resolution_prob: float
    psf_sigma_px: float
    auto_exposure: bool
    exposure_white_frac: Tuple[float, ...]
    full_well_if: float
    photons_at_full_well: float
    read_noise_dn: float
    gain_jitter: float
    quantize_bits: int
    gsd_m: Optional[float]  # the real product's ground sample distance (m/px); null = resolution jitter
    gsd_jitter: float  # relative jitter of that native grid
    jpeg_quality: Optional[int]  # JPEG quality of the real product; null = no JPEG
    mosaic_frames: int  # renders of one camera pose composited per image (1 = a single render)
    mosaic_blend: str  # max (per pixel) | patches (Voronoi cells)
    mosaic_patches: int  # cells for mosaic_blend=patches

    def _check(self):
        need(self.resolution_min_px >= 0, "resolution_min_px", self.resolution_min_px, "must be >= 0 (0 = off)")
        need(0.0 <= self.resolution_prob <= 1.0, "resolution_prob", self.resolution_prob, "must lie in [0, 1]")
        need(self.psf_sigma_px >= 0.0, "psf_sigma_px", self.psf_sigma_px, "must be >= 0")
        lo_hi = self.exposure_white_frac
        need(
            len(lo_hi) == 2 and 0.0 < lo_hi[0] <= lo_hi[1],
            "exposure_white_frac",
            lo_hi,
            "must be [lo, hi] with 0 < lo <= hi",
        )
        need(self.full_well_if > 0.0, "full_well_if", self.full_well_if, "must be > 0")
        need(self.photons_at_full_well > 0.0, "photons_at_full_well", self.photons_at_full_well, "must be > 0")
        need(self.read_noise_dn >= 0.0, "read_noise_dn", self.read_noise_dn, "must be >= 0")
        need(0.0 <= self.gain_jitter < 1.0, "gain_jitter", self.gain_jitter, "must lie in [0, 1)")
        need(1 <= self.quantize_bits <= 16, "quantize_bits", self.quantize_bits, "must lie in [1, 16]")
        need(self.gsd_m is None or self.gsd_m > 0.0, "gsd_m", self.gsd_m, "must be > 0 metres (or null)")
        need(0.0 <= self.gsd_jitter < 1.0, "gsd_jitter", self.gsd_jitter, "must lie in [0, 1)")
        need(
            self.jpeg_quality is None or 1 <= self.jpeg_quality <= 100,
            "jpeg_quality",
            self.jpeg_quality,
            "must lie in [1, 100] (or null)",
        )
        need(
            self.jpeg_quality is None or self.quantize_bits == 8,
            "jpeg_quality",
            self.jpeg_quality,
            "needs sensor.quantize_bits=8 (baseline JPEG is 8-bit)",
        )
        need(1 <= self.mosaic_frames <= 64, "mosaic_frames", self.mosaic_frames, "must lie in [1, 64]")
        need(self.mosaic_blend in ("max", "patches"), "mosaic_blend", self.mosaic_blend, "must be max or patches")
        need(1 <= self.mosaic_patches <= 256, "mosaic_patches", self.mosaic_patches, "must lie in [1, 256]")


@dataclass(frozen=True, kw_only=True)
class MosaicSettings(Group):
    """``realset.mosaic``: the embedded real image product (data_manifest/products.yaml)."""

    package: str
    package_path: str
    path: Optional[str]
    sha256: Optional[str]
    extent_m: float
    pixel_m: float
    radius_m: float
    product_id: Optional[str] = None
    # south | north polar stereographic; null: from the product's CRS in data_manifest/products.yaml
    pole: Optional[str] = None

    def _check(self):
        for key in ("extent_m", "pixel_m", "radius_m"):
            need(getattr(self, key) > 0.0, key, getattr(self, key), "must be > 0")
        need(self.pole in (None, "south", "north"), "pole", self.pole, "must be south, north or null")


@dataclass(frozen=True, kw_only=True)
class FrameSettings(Group):
    """One entry of ``realset.frames``: a georeferenced real frame (docs/realset.md, train/realframes.py)."""

    path: str  # a file GDAL reads, or product:<id> (data_manifest/products.yaml)
    frame_id: Optional[str] = None  # default: the product id or the file stem
    source: Optional[str] = None  # reported per source; default: the frame id
    band: int = 1
    craters: Optional[Tuple[str, ...]] = None  # default: every selected crater inside the frame

    def _check(self):
        need(bool(str(self.path).strip()), "path", self.path, "must name a file or product:<id>")
        need(self.band >= 1, "band", self.band, "must be >= 1")


@dataclass(frozen=True, kw_only=True)
class RealsetSettings(Group):
    """``realset.*``: the real test set (docs/realset.md)."""

    source_product: str
    per_crater: int
    sigmas: Tuple[float, ...]
    max_offset_frac: float
    max_rotation_deg: float
    seed: int
    include_embedded: bool
    labels_file: Optional[str]
    mosaic: MosaicSettings
    frames: Tuple[FrameSettings, ...] = ()  # georeferenced real frames (train/realframes.py)

    def _check(self):
        need(self.per_crater >= 1, "per_crater", self.per_crater, "must be >= 1")
        need(
            len(self.sigmas) > 0 and all(s > 0 for s in self.sigmas),
            "sigmas",
            self.sigmas,
            "must be a non-empty list of ratios > 0",
        )
        need(0.0 <= self.max_offset_frac < 0.5, "max_offset_frac", self.max_offset_frac, "must lie in [0, 0.5)")
        need(0.0 <= self.max_rotation_deg <= 180.0, "max_rotation_deg", self.max_rotation_deg, "must lie in [0, 180]")
        need(
            self.include_embedded or bool(self.labels_file) or bool(self.frames),
            "include_embedded",
            self.include_embedded,
            "leaves the real test set empty: give realset.labels_file or realset.frames, or keep the embedded mosaic",
        )
