"""Typed settings: the configuration validated once, as frozen dataclasses that every layer shares.

``configs/`` (Hydra) is where the values live; this module is where their *types and ranges* live.
The host composes the yaml files with the user's overrides (``crater_synth.config``), Hydra checks
types and unknown keys against schemas derived from the classes below, and the result is converted
once, by :meth:`Settings.from_config`, into a :class:`Settings`. Every range check runs in the
classes' ``__post_init__``; each failure is a :class:`SettingsError` naming the full key as the user
types it (``render.samples=0: must be >= 1``). Below the CLI, functions take these objects, never the
raw mapping.

Standard library only (plus the core's own Hapke and sweep classes): ``train/`` and ``blender_gen/``
may import it; it never imports omegaconf or Hydra.

How to add a key (e.g. ``render.shadow_method``)
-------------------------------------------------
1. Add a field to the group's class below, with a type annotation (``int``, ``float``, ``bool``,
   ``str``, ``Optional[...]``, ``Tuple[X, ...]`` for a list, ``Dict[str, X]``, or a nested settings
   class). Give it a default only if a yaml file may omit it; otherwise the yaml supplies the value
   (one source of truth) and a yaml lacking it is a "missing mandatory value" error.
2. Check its range in the class's ``_check`` with ``_need(ok, "shadow_method", value, "must be ...")``.
3. Add the value, with a comment, to every ``configs/<group>/*.yaml``.
Hydra's schema is derived from these classes (``crater_synth.config.register_schemas``), so there is
no second list to update. A new group: a class here, a field of :class:`Settings`, an entry in
:data:`GROUPS`, and ``defaults: [<group>_schema, _self_]`` at the top of each of its yaml files.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Dict, Mapping, Optional, Tuple

from crater_core.errors import ContractError
from crater_core.hapke import HapkeParams
from crater_core.sweep import AXES, SweepGrid, grid_from_config

# The solar disc's angular radius (deg): the whole Sun is below a flat horizon below -this.
SUN_ANGULAR_RADIUS_DEG = 0.2665


class SettingsError(ContractError):
    """A configuration value has the wrong type, lies out of range, is missing or unknown.

    ``key`` is the dotted path (relative while a class validates itself, made absolute by the
    converter); the message reads ``<key>=<value>: <why>`` or ``<key>: <why>``."""

    _NO_VALUE = object()

    def __init__(self, key: str, why: str, value: Any = _NO_VALUE):
        self.key, self.why, self.value = key, why, value
        shown = "" if value is self._NO_VALUE else f"={_show(value)}"
        super().__init__(f"{key}{shown}: {why}")

    def under(self, path: str) -> "SettingsError":
        """The same error with ``path`` prefixed to its key."""
        return SettingsError(_join(path, self.key), self.why, self.value)


def _show(value: Any) -> str:
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, tuple):
        return repr(list(value))
    return str(value)


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path and key else (path or key)


def _need(ok: bool, key: str, value: Any, why: str) -> None:
    if not ok:
        raise SettingsError(key, why, value)


class _Group:
    """Shared behaviour of the settings classes: conversion from a mapping, back to a plain dict."""

    @classmethod
    def from_config(cls, mapping: Mapping | None, path: str = ""):
        """Build and validate from a plain (resolved) mapping; errors name ``path.<key>``."""
        return build(cls, mapping or {}, path)

    def as_dict(self) -> dict:
        """Plain nested dict (tuples as lists): the resolved-mapping form older code takes."""
        return as_plain(self)

    def __post_init__(self):
        self._check()

    def _check(self) -> None:  # overridden by groups with ranges to check
        pass


# ------------------------------------------------------------------------------------------------
# Crater entries, DEM, terrain
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class CraterSettings(_Group):
    """One crater entry, ``crater.<key>`` (configs/crater/<key>.yaml); ``crater=[a,b,c]`` selects several."""

    name: str
    lat: float                # deg, planetocentric
    lon: float                # deg east
    diameter_km: float
    source: str = ""

    def _check(self):
        _need(bool(self.name.strip()), "name", self.name, "must not be empty")
        _need(-90.0 <= self.lat <= 90.0, "lat", self.lat, "must lie in [-90, 90] degrees")
        _need(-360.0 <= self.lon <= 360.0, "lon", self.lon, "must lie in [-360, 360] degrees")
        _need(0.0 < self.diameter_km < 2000.0, "diameter_km", self.diameter_km, "must lie in (0, 2000) km")


@dataclass(frozen=True, kw_only=True)
class DemSettings(_Group):
    """``dem.*``: the DEM product (or an explicit file) and the far-field one."""

    product: Optional[str]
    path: Optional[str]
    far_product: Optional[str]
    far_path: Optional[str]
    max_nodata_fraction: float

    def _check(self):
        _need(bool(self.product or self.path), "product", self.product, "dem.product or dem.path must be set")
        _need(0.0 <= self.max_nodata_fraction <= 1.0, "max_nodata_fraction", self.max_nodata_fraction,
              "must lie in [0, 1]")


# Pike (1977) fresh simple craters: depth/diameter 0.196 (kept equal to crater_synth.detail's constant).
FRESH_DEPTH_DIAMETER = 0.196


@dataclass(frozen=True, kw_only=True)
class DetailSettings(_Group):
    """``terrain.detail``: sub-DEM detail (crater_synth/detail.py, docs/terrain.md)."""

    enabled: bool = True
    seed: int = 0
    hurst: float = 0.8
    rms_slope_deg: float = 6.0
    crater_density_scale: float = 1.0
    min_crater_diameter_m: float = 300.0
    min_depth_diameter: float = 0.05

    @classmethod
    def from_config(cls, mapping: Mapping | None, path: str = "terrain.detail"):
        return build(cls, mapping or {}, path)

    def _check(self):
        _need(0.0 < self.hurst < 1.0, "hurst", self.hurst, "must lie in (0, 1)")
        _need(0.0 <= self.rms_slope_deg < 60.0, "rms_slope_deg", self.rms_slope_deg, "must lie in [0, 60) degrees")
        _need(0.0 <= self.crater_density_scale <= 100.0, "crater_density_scale", self.crater_density_scale,
              "must lie in [0, 100]")
        _need(self.min_crater_diameter_m > 0.0, "min_crater_diameter_m", self.min_crater_diameter_m, "must be > 0")
        _need(0.0 < self.min_depth_diameter <= FRESH_DEPTH_DIAMETER, "min_depth_diameter", self.min_depth_diameter,
              f"must lie in (0, {FRESH_DEPTH_DIAMETER}] (fresh craters, Pike 1977)")


# Near-field vertices per side: below 16 the rim is not resolved; above 8193 the mesh does not fit memory.
NEAR_VERTICES_RANGE = (16, 8193)


@dataclass(frozen=True, kw_only=True)
class TerrainSettings(_Group):
    """``terrain.*``: near/far field of the patch around each crater (crater_synth/terrain.py)."""

    near_radius_factor: float
    near_vertices: int
    far_radius_km: float
    far_spacing_km: float
    detail: DetailSettings

    def _check(self):
        lo, hi = NEAR_VERTICES_RANGE
        _need(lo <= self.near_vertices <= hi, "near_vertices", self.near_vertices, f"must lie in [{lo}, {hi}]")
        _need(0.6 <= self.near_radius_factor <= 50.0, "near_radius_factor", self.near_radius_factor,
              "must lie in [0.6, 50] crater diameters (the near field must contain the rim)")
        _need(self.far_radius_km >= 0.0, "far_radius_km", self.far_radius_km, "must be >= 0 (0 = no far field)")
        _need(self.far_spacing_km > 0.0, "far_spacing_km", self.far_spacing_km, "must be > 0")


# ------------------------------------------------------------------------------------------------
# Rendering: render, sweep, launcher
# ------------------------------------------------------------------------------------------------
RENDER_MODES = ("fast", "direct")


@dataclass(frozen=True, kw_only=True)
class RenderSettings(_Group):
    """``render.*`` (configs/render/cycles_cpu.yaml, docs/renderer.md)."""

    mode: str
    device: str
    samples: int
    max_bounces: int
    denoise: bool
    threads: int
    crop_to_roi: bool
    roi_min_px: int
    shadow_map_px: int
    shadow_map_levels: int
    shadow_map_extent_factor: float
    shadow_map_samples: int
    gbuffer_samples: int
    workers: int
    max_retries: int = 2      # restarts of a dying Blender worker on its unfinished renders

    def _check(self):
        _need(self.mode in RENDER_MODES, "mode", self.mode, "must be 'fast' or 'direct'")
        _need(self.samples >= 1, "samples", self.samples, "must be >= 1")
        _need(self.max_bounces >= 0, "max_bounces", self.max_bounces, "must be >= 0")
        _need(self.threads >= 0, "threads", self.threads, "must be >= 0 (0 = all cores)")
        _need(self.roi_min_px >= 8, "roi_min_px", self.roi_min_px, "must be >= 8")
        _need(self.shadow_map_px >= 1, "shadow_map_px", self.shadow_map_px, "must be >= 1")
        _need(self.shadow_map_levels >= 1, "shadow_map_levels", self.shadow_map_levels, "must be >= 1")
        _need(self.shadow_map_extent_factor > 0, "shadow_map_extent_factor", self.shadow_map_extent_factor,
              "must be > 0")
        _need(self.shadow_map_samples >= 0, "shadow_map_samples", self.shadow_map_samples, "must be >= 0 (0 = samples)")
        _need(self.gbuffer_samples >= 0, "gbuffer_samples", self.gbuffer_samples, "must be >= 0 (0 = samples)")
        _need(self.workers >= 1, "workers", self.workers, "must be >= 1")
        _need(self.max_retries >= 0, "max_retries", self.max_retries, "must be >= 0")


@dataclass(frozen=True, kw_only=True)
class AxisSettings(_Group):
    """One sweep axis: ``count`` paper positions (crater_core/sweep.py), or explicit ``values``."""

    count: int
    values: Optional[Tuple[float, ...]] = None
    step_deg: Optional[float] = None

    def _check(self):
        _need(self.count >= 1, "count", self.count, "must be >= 1")
        _need(self.values is None or len(self.values) > 0, "values", self.values, "must not be empty (null = count)")


@dataclass(frozen=True, kw_only=True)
class SweepSettings(_Group):
    """``sweep.*``: Table 2 grid (configs/sweep/*.yaml). The grid is built, and so checked, at once."""

    name: str
    sun_elevation: AxisSettings
    sun_azimuth: AxisSettings
    cam_elevation: AxisSettings
    cam_azimuth: AxisSettings
    sigma: AxisSettings
    fov_deg: float
    range_factor: float

    def _check(self):
        _need(bool(self.name.strip()), "name", self.name, "must not be empty (it names out_dir and run_dir)")
        self.grid  # noqa: B018 - raises SweepError naming the axis for a nonsense grid

    @cached_property
    def grid(self) -> SweepGrid:
        return grid_from_config(self.as_dict())

    def warnings(self) -> list[str]:
        low = [v for v in self.grid.sun_elevation if v <= 0.0]
        if not low:
            return []
        below = "below" if max(low) < -SUN_ANGULAR_RADIUS_DEG else "at or below"
        return [f"sweep.sun_elevation values {low} put the Sun {below} the local horizon at the crater: "
                "those renders will be (almost) all black"]


@dataclass(frozen=True, kw_only=True)
class LauncherSettings(_Group):
    """``launcher.*``: one machine (optionally one shard) or a Dask cluster (docs/distributed.md)."""

    name: str
    shard: Optional[str] = None     # "i/n": render only slice i of n
    address: Optional[str] = None   # dask: scheduler address; null starts a local cluster
    n_workers: int = 2              # dask local cluster: worker processes
    shards: Optional[int] = None    # dask: shards per run; null = 4 x n_workers
    retries: int = 3                # dask: reschedules of a task whose worker died

    def _check(self):
        _need(self.name in ("local", "dask"), "name", self.name, "must be 'local' or 'dask'")
        self.shard_slice  # noqa: B018 - parses (and so checks) "i/n"
        _need(self.n_workers >= 1, "n_workers", self.n_workers, "must be >= 1")
        _need(self.shards is None or self.shards >= 1, "shards", self.shards, "must be >= 1 (null = 4 x n_workers)")
        _need(self.retries >= 0, "retries", self.retries, "must be >= 0")

    @cached_property
    def shard_slice(self) -> Optional[Tuple[int, int]]:
        """``(i, n)`` of ``shard`` (None: the whole sweep)."""
        if self.shard in (None, "", "null"):
            return None
        try:
            i, n = (int(x) for x in str(self.shard).split("/"))
        except ValueError:
            raise SettingsError("shard", "expected 'i/n', e.g. 0/4", self.shard) from None
        _need(n >= 1 and 0 <= i < n, "shard", self.shard, "need 0 <= i < n")
        return i, n


# ------------------------------------------------------------------------------------------------
# Training: model, train (+ preprocess, svm, hog), sensor, real test set
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class ConvSettings(_Group):
    channels: int
    kernel: int
    stride: int

    def _check(self):
        for key in ("channels", "kernel", "stride"):
            _need(getattr(self, key) >= 1, key, getattr(self, key), "must be >= 1")


@dataclass(frozen=True, kw_only=True)
class PoolSettings(_Group):
    kernel: int
    stride: int

    def _check(self):
        for key in ("kernel", "stride"):
            _need(getattr(self, key) >= 1, key, getattr(self, key), "must be >= 1")


@dataclass(frozen=True, kw_only=True)
class ModelSettings(_Group):
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
        _need(self.input_size >= 8, "input_size", self.input_size, "must be >= 8")
        _need(self.num_classes >= 2, "num_classes", self.num_classes, "must be >= 2")
        _need(self.fc1 >= 1, "fc1", self.fc1, "must be >= 1")
        _need(0.0 <= self.dropout < 1.0, "dropout", self.dropout, "must lie in [0, 1)")


@dataclass(frozen=True, kw_only=True)
class PreprocessSettings(_Group):
    """``train.preprocess``: crop resampling and photometric normalisation (docs/preprocessing.md)."""

    antialias: bool
    interp_order: int
    max_outside_frac: float
    low_percentile: float
    high_percentile: float
    lit_threshold: float
    shadow_floor: float
    gamma: float

    def _check(self):
        _need(self.interp_order in (0, 1, 3), "interp_order", self.interp_order, "must be 0, 1 or 3")
        _need(0.0 <= self.max_outside_frac < 1.0, "max_outside_frac", self.max_outside_frac, "must lie in [0, 1)")
        _need(0.0 <= self.low_percentile < self.high_percentile, "low_percentile", self.low_percentile,
              "must lie in [0, high_percentile)")
        _need(self.high_percentile <= 100.0, "high_percentile", self.high_percentile, "must be <= 100")
        _need(0.0 <= self.lit_threshold < 1.0, "lit_threshold", self.lit_threshold, "must lie in [0, 1)")
        _need(0.0 <= self.shadow_floor < 1.0, "shadow_floor", self.shadow_floor, "must lie in [0, 1)")
        _need(self.gamma > 0.0, "gamma", self.gamma, "must be > 0")


@dataclass(frozen=True, kw_only=True)
class SvmSettings(_Group):
    """``train.svm``: the SGD linear SVM of LunarSVM_ex."""

    alpha: float
    max_iter: int
    tol: float

    def _check(self):
        _need(self.alpha > 0.0, "alpha", self.alpha, "must be > 0")
        _need(self.max_iter >= 1, "max_iter", self.max_iter, "must be >= 1")
        _need(self.tol >= 0.0, "tol", self.tol, "must be >= 0")


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
            _need(getattr(self, key) >= 1, key, getattr(self, key), "must be >= 1")
        _need(self.max_train_images is None or self.max_train_images >= 1, "max_train_images",
              self.max_train_images, "must be >= 1 (null = all)")


@dataclass(frozen=True, kw_only=True)
class TrainSettings(_Group):
    """``train.*`` (configs/train/default.yaml, docs/classifiers.md)."""

    dataset_dir: str
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
    verify_sha256: bool
    augment: bool
    progress: bool
    preprocess: PreprocessSettings
    svm: SvmSettings
    hog: HogSettings

    def _check(self):
        _need(0.0 < self.val_fraction < 1.0, "val_fraction", self.val_fraction, "must lie in (0, 1)")
        _need(self.split_by in ("camera", "sun"), "split_by", self.split_by, "must be 'camera' or 'sun'")
        _need(self.sigmas is None or all(s > 0 for s in self.sigmas), "sigmas", self.sigmas, "must be > 0")
        unknown = sorted(set(self.select or {}) - set(AXES))
        _need(not unknown, "select", unknown, f"unknown axis: use {', '.join(AXES)}")
        for key in ("batch_size", "eval_batch_size", "max_epochs"):
            _need(getattr(self, key) >= 1, key, getattr(self, key), "must be >= 1")
        _need(self.lr > 0.0, "lr", self.lr, "must be > 0")
        _need(self.weight_decay >= 0.0, "weight_decay", self.weight_decay, "must be >= 0")
        _need(0.0 <= self.target_val_accuracy <= 1.0, "target_val_accuracy", self.target_val_accuracy,
              "must lie in [0, 1]")
        _need(self.num_threads >= 0, "num_threads", self.num_threads, "must be >= 0 (0 = all cores)")
        _need(self.device in ("auto", "cpu", "cuda"), "device", self.device, "must be auto, cpu or cuda")
        _need(self.cache_dtype in ("float16", "float32"), "cache_dtype", self.cache_dtype, "must be float16 or float32")


@dataclass(frozen=True, kw_only=True)
class SensorSettings(_Group):
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

    def _check(self):
        _need(self.resolution_min_px >= 0, "resolution_min_px", self.resolution_min_px, "must be >= 0 (0 = off)")
        _need(0.0 <= self.resolution_prob <= 1.0, "resolution_prob", self.resolution_prob, "must lie in [0, 1]")
        _need(self.psf_sigma_px >= 0.0, "psf_sigma_px", self.psf_sigma_px, "must be >= 0")
        lo_hi = self.exposure_white_frac
        _need(len(lo_hi) == 2 and 0.0 < lo_hi[0] <= lo_hi[1], "exposure_white_frac", lo_hi,
              "must be [lo, hi] with 0 < lo <= hi")
        _need(self.full_well_if > 0.0, "full_well_if", self.full_well_if, "must be > 0")
        _need(self.photons_at_full_well > 0.0, "photons_at_full_well", self.photons_at_full_well, "must be > 0")
        _need(self.read_noise_dn >= 0.0, "read_noise_dn", self.read_noise_dn, "must be >= 0")
        _need(0.0 <= self.gain_jitter < 1.0, "gain_jitter", self.gain_jitter, "must lie in [0, 1)")
        _need(1 <= self.quantize_bits <= 16, "quantize_bits", self.quantize_bits, "must lie in [1, 16]")


@dataclass(frozen=True, kw_only=True)
class MosaicSettings(_Group):
    """``realset.mosaic``: the embedded real image product (data_manifest/products.yaml)."""

    package: str
    package_path: str
    path: Optional[str]
    sha256: Optional[str]
    extent_m: float
    pixel_m: float
    radius_m: float
    product_id: Optional[str] = None

    def _check(self):
        for key in ("extent_m", "pixel_m", "radius_m"):
            _need(getattr(self, key) > 0.0, key, getattr(self, key), "must be > 0")


@dataclass(frozen=True, kw_only=True)
class RealsetSettings(_Group):
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

    def _check(self):
        _need(self.per_crater >= 1, "per_crater", self.per_crater, "must be >= 1")
        _need(len(self.sigmas) > 0 and all(s > 0 for s in self.sigmas), "sigmas", self.sigmas,
              "must be a non-empty list of ratios > 0")
        _need(0.0 <= self.max_offset_frac < 0.5, "max_offset_frac", self.max_offset_frac, "must lie in [0, 0.5)")
        _need(0.0 <= self.max_rotation_deg <= 180.0, "max_rotation_deg", self.max_rotation_deg, "must lie in [0, 180]")


# ------------------------------------------------------------------------------------------------
# Closed loop, Figure 6 experiments, data fetching
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class LoopSettings(_Group):
    """``loop.*``: the closed loop of the paper's Fig. 3."""

    threshold: float
    sun_elevation_schedule: Tuple[int, ...]

    def _check(self):
        _need(0.0 < self.threshold <= 1.0, "threshold", self.threshold, "must lie in (0, 1]")
        s = list(self.sun_elevation_schedule)
        _need(bool(s) and s == sorted(set(s)) and s[0] >= 1, "sun_elevation_schedule", s,
              "must be increasing positive counts")


@dataclass(frozen=True, kw_only=True)
class CountsSettings(_Group):
    """``experiments.counts``: the sample counts of each axis for Figure 6."""

    sun_elevation: Optional[Tuple[int, ...]]   # null: this axis is not varied
    sun_azimuth: Optional[Tuple[int, ...]]
    cam_elevation: Optional[Tuple[int, ...]]
    cam_azimuth: Optional[Tuple[int, ...]]

    def _check(self):
        for axis in AXES:
            counts = getattr(self, axis) or ()
            _need(all(c >= 1 for c in counts), axis, counts, "counts must be >= 1")


@dataclass(frozen=True, kw_only=True)
class ExperimentsSettings(_Group):
    """``experiments.*``: Figure 6 (crater_synth/experiments.py)."""

    counts: CountsSettings
    sigmas: Optional[Tuple[float, ...]]

    def _check(self):
        _need(self.sigmas is None or all(s > 0 for s in self.sigmas), "sigmas", self.sigmas, "must be > 0")


@dataclass(frozen=True, kw_only=True)
class FetchSettings(_Group):
    """``fetch.*``: ``crater-synth fetch-data`` (crater_synth/fetch.py, docs/data.md)."""

    base_url: Optional[str]
    timeout_s: float
    retries: int
    chunk_bytes: int
    backoff_s: float

    def _check(self):
        _need(self.timeout_s > 0, "timeout_s", self.timeout_s, "must be > 0")
        _need(self.retries >= 1, "retries", self.retries, "must be >= 1")
        _need(self.chunk_bytes >= 1024, "chunk_bytes", self.chunk_bytes, "must be >= 1024")
        _need(self.backoff_s >= 0, "backoff_s", self.backoff_s, "must be >= 0")
        url = (self.base_url or "").strip()
        _need(not url or url.startswith(("http://", "https://", "file://")), "base_url", self.base_url,
              "must start with http://, https:// or file://")


# ------------------------------------------------------------------------------------------------
# The root
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class Settings(_Group):
    """The whole configuration (configs/config.yaml and its groups), validated."""

    crater: Dict[str, CraterSettings]
    dem: DemSettings
    terrain: TerrainSettings
    hapke: HapkeParams
    render: RenderSettings
    sweep: SweepSettings
    launcher: LauncherSettings
    model: ModelSettings
    train: TrainSettings
    sensor: SensorSettings
    realset: RealsetSettings
    loop: LoopSettings
    experiments: ExperimentsSettings
    fetch: FetchSettings
    seed: int
    data_dir: str
    out_dir: str
    run_dir: str

    def _check(self):
        if not self.crater:
            raise SettingsError("crater", "no crater selected (crater=NAME or crater=[a,b,...])")
        seen: dict[str, str] = {}
        for key, entry in self.crater.items():
            _need(entry.name not in seen, f"crater.{key}.name", entry.name,
                  f"repeats crater.{seen.get(entry.name)}'s name (names label renders and classes)")
            seen[entry.name] = key
        for key in ("data_dir", "out_dir", "run_dir"):
            _need(bool(str(getattr(self, key)).strip()), key, getattr(self, key), "must not be empty")

    @property
    def craters(self) -> Tuple[CraterSettings, ...]:
        """The selected crater entries, in configuration order."""
        return tuple(self.crater.values())

    def warnings(self) -> list[str]:
        """Settings that are legal but almost surely a mistake (printed as ``warning:`` lines)."""
        return self.sweep.warnings()


# Config groups of configs/ and their settings class (Hydra registers ``<group>_schema`` for each).
GROUPS: Dict[str, type] = {
    "crater": CraterSettings, "dem": DemSettings, "terrain": TerrainSettings, "hapke": HapkeParams,
    "render": RenderSettings, "sweep": SweepSettings, "launcher": LauncherSettings, "model": ModelSettings,
    "train": TrainSettings, "sensor": SensorSettings, "realset": RealsetSettings, "loop": LoopSettings,
    "experiments": ExperimentsSettings, "fetch": FetchSettings,
}


# ------------------------------------------------------------------------------------------------
# Conversion: plain mapping -> settings objects (types first, then each class's range checks)
# ------------------------------------------------------------------------------------------------
def build(cls: type, data: Mapping, path: str = ""):
    """An instance of the dataclass ``cls`` from the plain mapping ``data`` (keys under ``path``).

    Unknown keys, missing values (absent, or Hydra's ``???``), wrong types and out-of-range values
    raise :class:`SettingsError` naming the full key. A :class:`ContractError` raised by a class's own
    validation (e.g. :class:`crater_core.sweep.SweepError`) passes through unchanged."""
    if not isinstance(data, Mapping):
        raise SettingsError(path, f"must be a mapping of {_type_name(cls)} keys", data)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = [k for k in data if k not in fields]
    if unknown:
        key = str(unknown[0])
        close = difflib.get_close_matches(key, list(fields), n=1)
        hint = f" (did you mean {_join(path, close[0])}?)" if close else f"; known: {', '.join(fields)}"
        raise SettingsError(_join(path, key), f"unknown key{hint}")
    kwargs = {}
    for name, f in fields.items():
        key = _join(path, name)
        if name not in data or data[name] == "???":
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise SettingsError(key, "missing mandatory config value (give it as an override)")
            continue
        kwargs[name] = _convert(data[name], hints[name], key)
    try:
        return cls(**kwargs)
    except SettingsError as exc:
        raise exc.under(path) from None
    except ContractError:
        raise
    except (TypeError, ValueError) as exc:  # e.g. HapkeParams' own range check
        raise SettingsError(path, str(exc)) from None


def _type_name(tp) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(value: Any, tp: Any, key: str) -> Any:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any:
        return value
    if origin is typing.Union:
        if value is None and type(None) in args:
            return None
        (inner,) = [a for a in args if a is not type(None)]
        return _convert(value, inner, key)
    if value is None:
        raise SettingsError(key, "must not be null", value)
    if dataclasses.is_dataclass(tp):
        return build(tp, value, key)
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise SettingsError(key, "must be a list", value)
        inner = args[0] if args else Any
        return tuple(_convert(v, inner, f"{key}[{i}]") for i, v in enumerate(value))
    if origin in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise SettingsError(key, "must be a mapping", value)
        inner = args[1] if len(args) == 2 else Any
        return {str(k): _convert(v, inner, _join(key, str(k))) for k, v in value.items()}
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false"):
            return value.lower() == "true"
        raise SettingsError(key, "must be true or false", value)
    if tp is int:
        if isinstance(value, bool):
            raise SettingsError(key, "must be an integer", value)
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str):
            try:
                return int(value.strip())
            except ValueError:
                pass
        raise SettingsError(key, "must be an integer", value)
    if tp is float:
        if isinstance(value, bool):
            raise SettingsError(key, "must be a number", value)
        try:
            num = float(value)
        except (TypeError, ValueError):
            raise SettingsError(key, "must be a number", value) from None
        if not math.isfinite(num):
            raise SettingsError(key, "must be finite", value)
        return num
    if tp is str:
        if isinstance(value, (str, int, float)) and not isinstance(value, bool):
            return str(value)
        raise SettingsError(key, "must be a string", value)
    raise TypeError(f"settings field {key}: unsupported annotation {tp!r}")


def as_plain(obj: Any) -> Any:
    """Settings object -> plain nested dicts/lists (the inverse of :func:`build`)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: as_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [as_plain(v) for v in obj]
    if isinstance(obj, Mapping):
        return {k: as_plain(v) for k, v in obj.items()}
    return obj


def replace(obj, **changes):
    """``dataclasses.replace`` with dotted keys: ``replace(s, **{"render.workers": 1})``."""
    direct, nested = {}, {}
    for key, value in changes.items():
        head, _, rest = key.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            direct[head] = value
    for head, sub in nested.items():
        direct[head] = replace(getattr(obj, head), **sub)
    return dataclasses.replace(obj, **direct)


__all__ = [name for name in dir() if name.endswith("Settings")] + [
    "GROUPS", "HapkeParams", "SettingsError", "as_plain", "build", "replace"]
