"""Typed settings: the configuration validated once, as frozen dataclasses that every layer shares.

``configs/`` (Hydra) is where the values live; this module is where their *types and ranges* live.
The host composes the yaml files with the user's overrides (``crater_synth.config``), Hydra checks
types and unknown keys against schemas derived from the classes below, and the result is converted
once, by :meth:`Settings.from_config`, into a :class:`Settings`. Every range check runs in the
classes' ``__post_init__``; each failure is a :class:`SettingsError` naming the full key as the user
types it (``render.samples=0: must be >= 1``). Below the CLI, functions take these objects, never the
raw mapping.

Standard library only (plus the core's own Hapke and sweep classes): ``train/`` and ``blender_gen/``
may import it; it never imports omegaconf or Hydra. The training groups live in
:mod:`crater_core.settings_train` and the mapping -> dataclass converter in
:mod:`crater_core.typed_config`; both are re-exported here.

How to add a key (e.g. ``render.shadow_method``)
-------------------------------------------------
1. Add a field to the group's class below, with a type annotation (``int``, ``float``, ``bool``,
   ``str``, ``Optional[...]``, ``Tuple[X, ...]`` for a list, ``Dict[str, X]``, or a nested settings
   class). Give it a default only if a yaml file may omit it; otherwise the yaml supplies the value
   (one source of truth) and a yaml lacking it is a "missing mandatory value" error.
2. Check its range in the class's ``_check`` with ``need(ok, "shadow_method", value, "must be ...")``.
3. Add the value, with a comment, to every ``configs/<group>/*.yaml``.
Hydra's schema is derived from these classes (``crater_synth.config.register_schemas``), so there is
no second list to update. A new group: a class here, a field of :class:`Settings`, an entry in
:data:`GROUPS`, and ``defaults: [<group>_schema, _self_]`` at the top of each of its yaml files.

Length: one short dataclass per configuration group with its range checks, and the registry that
binds them to Hydra; the training groups already live in :mod:`crater_core.settings_train`. Splitting
the rest further would scatter the single list of groups this module exists to keep.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any, Dict, Mapping, Optional, Tuple

from crater_core.hapke import HapkeParams
from crater_core.settings_detection import DetectionSettings
from crater_core.settings_procedural import ProceduralSettings
from crater_core.settings_train import (
    ConvSettings,
    FrameSettings,
    HogSettings,
    ModelSettings,
    MosaicSettings,
    PoolSettings,
    PreprocessSettings,
    RealsetSettings,
    SensorSettings,
    SvmSettings,
    TrainSettings,
)
from crater_core.sweep import AXES, MAX_AXIS_COUNT, SweepGrid, grid_from_config
from crater_core.typed_config import Group, SettingsError, as_plain, build, need, need_plain_name, replace

# The solar disc's angular radius (deg): the whole Sun is below a flat horizon below -this.
SUN_ANGULAR_RADIUS_DEG = 0.2665


# ------------------------------------------------------------------------------------------------
# Crater entries, DEM, terrain
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class CraterSettings(Group):
    """One crater entry, ``crater.<key>`` (configs/crater/<key>.yaml); ``crater=[a,b,c]`` selects several."""

    name: str
    lat: float  # deg, planetocentric
    lon: float  # deg east
    diameter_km: float
    source: str = ""

    def _check(self):
        need_plain_name("name", self.name)
        need(-90.0 <= self.lat <= 90.0, "lat", self.lat, "must lie in [-90, 90] degrees")
        need(-360.0 <= self.lon <= 360.0, "lon", self.lon, "must lie in [-360, 360] degrees")
        need(0.0 < self.diameter_km < 2000.0, "diameter_km", self.diameter_km, "must lie in (0, 2000) km")


# dem.blend_pixels: the stack's transition band in coarse pixels (crater_synth/terrain/stack.py, docs/dem_stack.md).
BLEND_PIXELS_RANGE = (0.5, 50.0)


@dataclass(frozen=True, kw_only=True)
class DemSettings(Group):
    """``dem.*``: the base DEM product (or an explicit file), finer stack layers over it, the far-field one."""

    product: Optional[str]
    path: Optional[str]
    stack: Tuple[str, ...]  # finer DEMs over the base, finest first: product ids or file paths
    blend_pixels: float  # stack layers blend into the coarser data over this many coarse pixels
    far_product: Optional[str]
    far_path: Optional[str]
    max_nodata_fraction: float

    def _check(self):
        need(bool(self.product or self.path), "product", self.product, "dem.product or dem.path must be set")
        lo, hi = BLEND_PIXELS_RANGE
        need(
            lo <= self.blend_pixels <= hi,
            "blend_pixels",
            self.blend_pixels,
            f"must lie in [{lo:g}, {hi:g}] (coarse pixels)",
        )
        need(
            0.0 <= self.max_nodata_fraction <= 1.0,
            "max_nodata_fraction",
            self.max_nodata_fraction,
            "must lie in [0, 1]",
        )


# Pike (1977) fresh simple craters: depth/diameter 0.196 (kept equal to crater_synth.terrain.detail's constant).
FRESH_DEPTH_DIAMETER = 0.196
# terrain.detail.model: calibrated (fitted to a real LOLA 200 m crop) or legacy (pre-calibration, for ablations).
DETAIL_MODELS = ("calibrated", "legacy")
# Allowed min_depth_diameter: the recognition limit of a degraded crater (docs/detail.md). Above 0.005
# every allowed diffusion time keeps the 4 R stamp cut below 0.2 % of the fresh depth.
MIN_RECOGNITION_DEPTH_DIAMETER, MAX_RECOGNITION_DEPTH_DIAMETER = 0.005, 0.15


@dataclass(frozen=True, kw_only=True)
class DetailSettings(Group):
    """``terrain.detail``: sub-DEM detail (crater_synth/terrain/detail.py, docs/detail.md); defaults are the
    calibrated values. ``hurst``, ``roughness_rms_slope_deg``, ``crater_density_scale``,
    ``min_crater_diameter_m`` and ``min_depth_diameter`` apply to ``model=calibrated``; ``model=legacy``
    uses crater_synth.terrain.detail.LEGACY_PARAMETERS."""

    enabled: bool = True
    seed: int = 0
    model: str = "calibrated"
    hurst: float = 0.8
    roughness_rms_slope_deg: float = 1.25
    crater_density_scale: float = 0.8
    min_crater_diameter_m: float = 300.0
    min_depth_diameter: float = 0.014

    @classmethod
    def from_config(cls, mapping: Mapping | None, path: str = "terrain.detail"):
        return build(cls, mapping or {}, path)

    def _check(self):
        need(self.model in DETAIL_MODELS, "model", self.model, f"must be one of {list(DETAIL_MODELS)}")
        need(0.0 < self.hurst < 1.0, "hurst", self.hurst, "must lie in (0, 1)")
        need(
            0.0 <= self.roughness_rms_slope_deg < 60.0,
            "roughness_rms_slope_deg",
            self.roughness_rms_slope_deg,
            "must lie in [0, 60) degrees",
        )
        need(
            0.0 <= self.crater_density_scale <= 100.0,
            "crater_density_scale",
            self.crater_density_scale,
            "must lie in [0, 100]",
        )
        need(self.min_crater_diameter_m > 0.0, "min_crater_diameter_m", self.min_crater_diameter_m, "must be > 0")
        lo, hi = MIN_RECOGNITION_DEPTH_DIAMETER, MAX_RECOGNITION_DEPTH_DIAMETER
        need(
            lo <= self.min_depth_diameter < hi,
            "min_depth_diameter",
            self.min_depth_diameter,
            f"must lie in [{lo}, {hi}) (fresh craters: {FRESH_DEPTH_DIAMETER}, Pike 1977)",
        )


# Near-field vertices per side: below 16 the rim is not resolved; above 8193 the mesh does not fit memory.
NEAR_VERTICES_RANGE = (16, 8193)


@dataclass(frozen=True, kw_only=True)
class TerrainSettings(Group):
    """``terrain.*``: near/far field of the patch around each crater (crater_synth/terrain/patch.py)."""

    near_radius_factor: float
    near_vertices: int
    far_radius_km: float
    far_spacing_km: float
    detail: DetailSettings

    def _check(self):
        lo, hi = NEAR_VERTICES_RANGE
        need(lo <= self.near_vertices <= hi, "near_vertices", self.near_vertices, f"must lie in [{lo}, {hi}]")
        need(
            0.6 <= self.near_radius_factor <= 50.0,
            "near_radius_factor",
            self.near_radius_factor,
            "must lie in [0.6, 50] crater diameters (the near field must contain the rim)",
        )
        need(self.far_radius_km >= 0.0, "far_radius_km", self.far_radius_km, "must be >= 0 (0 = no far field)")
        need(self.far_spacing_km > 0.0, "far_spacing_km", self.far_spacing_km, "must be > 0")


# ------------------------------------------------------------------------------------------------
# Rendering: render, sweep, launcher
# ------------------------------------------------------------------------------------------------
RENDER_MODES = ("fast", "direct")
# Cycles' compute backends: the CPU, or the GPU API Cycles renders with (CUDA or OPTIX on NVIDIA, HIP on
# AMD, ONEAPI on Intel, METAL on Apple). The shader-node Hapke material runs on all of them (no OSL).
RENDER_DEVICES = ("CPU", "CUDA", "OPTIX", "HIP", "ONEAPI", "METAL")
# Upper bounds of the render sizes that drive each render's memory and disk:
# - roi_min_px: the crop's side is about roi_min_px x sigma_max / sigma_min (1.4 x in the paper sweep) and
#   the frame is wider still; at 4096 a paper crop is ~5,700 px a side (33 Mpx): ~530 MB of EXR channels
#   (16 B/px) and several GB of fast-mode G-buffer and shading arrays per worker. The classifier reads 150 px.
MAX_ROI_MIN_PX = 4096
# - shadow_map_px: every level of a horizon map holds 3 float32 planes of shadow_map_px^2 texels, one map per
#   sun azimuth, in memory and in the on-disk cache: 4096 is 200 MB per level and azimuth (512: 3 MB).
MAX_SHADOW_MAP_PX = 4096
# - shadow_map_levels: level k has half-width extent / 2^k, so 8 levels reach 1/128 of the outer map
#   (~1 % of a crater diameter), finer than the DEM they resample; each level costs a whole map.
MAX_SHADOW_MAP_LEVELS = 8


@dataclass(frozen=True, kw_only=True)
class RenderSettings(Group):
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
    horizon_cache_dir: Optional[str]  # fast path: shared horizon-map cache (null: <terrain dir>/horizon)
    gbuffer_samples: int
    workers: int
    max_retries: int = 2  # restarts of a dying Blender worker on its unfinished renders
    # A Blender binary to run the workers with (``blender --background --python blender_gen/worker.py``);
    # null: the bpy module of the host's Python. Its version is checked when the workers start.
    blender: Optional[str] = None

    def _check(self):
        need(self.mode in RENDER_MODES, "mode", self.mode, "must be 'fast' or 'direct'")
        need(self.device in RENDER_DEVICES, "device", self.device, f"must be one of {', '.join(RENDER_DEVICES)}")
        need(self.samples >= 1, "samples", self.samples, "must be >= 1")
        need(self.max_bounces >= 0, "max_bounces", self.max_bounces, "must be >= 0")
        need(self.threads >= 0, "threads", self.threads, "must be >= 0 (0 = all cores)")
        need(
            8 <= self.roi_min_px <= MAX_ROI_MIN_PX, "roi_min_px", self.roi_min_px, f"must lie in [8, {MAX_ROI_MIN_PX}]"
        )
        need(
            1 <= self.shadow_map_px <= MAX_SHADOW_MAP_PX,
            "shadow_map_px",
            self.shadow_map_px,
            f"must lie in [1, {MAX_SHADOW_MAP_PX}]",
        )
        need(
            1 <= self.shadow_map_levels <= MAX_SHADOW_MAP_LEVELS,
            "shadow_map_levels",
            self.shadow_map_levels,
            f"must lie in [1, {MAX_SHADOW_MAP_LEVELS}]",
        )
        need(
            self.shadow_map_extent_factor > 0, "shadow_map_extent_factor", self.shadow_map_extent_factor, "must be > 0"
        )
        need(self.gbuffer_samples >= 0, "gbuffer_samples", self.gbuffer_samples, "must be >= 0 (0 = samples)")
        need(self.workers >= 1, "workers", self.workers, "must be >= 1")
        need(self.max_retries >= 0, "max_retries", self.max_retries, "must be >= 0")
        need(
            self.blender is None or bool(self.blender.strip()),
            "blender",
            self.blender,
            "must be the path of a Blender binary (or null: the bpy module)",
        )


@dataclass(frozen=True, kw_only=True)
class AxisSettings(Group):
    """One sweep axis: ``count`` paper positions (crater_core/sweep.py), or explicit ``values``."""

    count: int
    values: Optional[Tuple[float, ...]] = None
    step_deg: Optional[float] = None
    step_fraction: Optional[float] = None  # physical sun elevations: fraction step (null: 0.1)

    def _check(self):
        need(1 <= self.count <= MAX_AXIS_COUNT, "count", self.count, f"must lie in [1, {MAX_AXIS_COUNT}]")
        need(self.values is None or len(self.values) > 0, "values", self.values, "must not be empty (null = count)")


@dataclass(frozen=True, kw_only=True)
class SweepSettings(Group):
    """``sweep.*``: Table 2 grid (configs/sweep/*.yaml). The grid is built, and so checked, at once."""

    name: str
    sun_elevation: AxisSettings
    sun_azimuth: AxisSettings
    cam_elevation: AxisSettings
    cam_azimuth: AxisSettings
    sigma: AxisSettings
    fov_deg: float
    range_factor: float
    # Defaults (a sweep file written before the physical model may omit them) as in crater_core.sweep:
    sun_model: str = "paper"  # paper: Table 2 positions; physical: fractions of each crater's highest sun
    min_sun_elevation_deg: float = 0.0  # physical sweeps: suns below this are not rendered

    def _check(self):
        need_plain_name("name", self.name)  # it names out_dir and run_dir
        self.grid  # noqa: B018 - raises SweepError naming the axis for a nonsense grid

    @cached_property
    def grid(self) -> SweepGrid:
        return grid_from_config(self.as_dict())

    def warnings(self) -> list[str]:
        if self.sun_model != "paper":  # physical: the values are fractions in (0, 1], checked by the grid
            return []
        low = [v for v in self.grid.sun_elevation if v <= 0.0]
        if not low:
            return []
        below = "below" if max(low) < -SUN_ANGULAR_RADIUS_DEG else "at or below"
        return [
            f"sweep.sun_elevation values {low} put the Sun {below} the local horizon at the crater: "
            "those renders will be (almost) all black"
        ]


@dataclass(frozen=True, kw_only=True)
class LauncherSettings(Group):
    """``launcher.*``: one machine (optionally one shard) or a Dask cluster (docs/distributed.md)."""

    name: str
    shard: Optional[str] = None  # "i/n": render only slice i of n
    address: Optional[str] = None  # dask: scheduler address; null starts a local cluster
    n_workers: int = 2  # dask local cluster: worker processes
    shards: Optional[int] = None  # dask: shards per run; null = 4 x n_workers
    retries: int = 3  # dask: reschedules of a task whose worker died

    def _check(self):
        need(self.name in ("local", "dask"), "name", self.name, "must be 'local' or 'dask'")
        self.shard_slice  # noqa: B018 - parses (and so checks) "i/n"
        need(self.n_workers >= 1, "n_workers", self.n_workers, "must be >= 1")
        need(self.shards is None or self.shards >= 1, "shards", self.shards, "must be >= 1 (null = 4 x n_workers)")
        need(self.retries >= 0, "retries", self.retries, "must be >= 0")

    @cached_property
    def shard_slice(self) -> Optional[Tuple[int, int]]:
        """``(i, n)`` of ``shard`` (None: the whole sweep)."""
        if self.shard in (None, "", "null"):
            return None
        try:
            i, n = (int(x) for x in str(self.shard).split("/"))
        except ValueError:
            raise SettingsError("shard", "expected 'i/n', e.g. 0/4", self.shard) from None
        need(n >= 1 and 0 <= i < n, "shard", self.shard, "need 0 <= i < n")
        return i, n


# ------------------------------------------------------------------------------------------------
# Closed loop, Figure 6 experiments, validation protocol, ablation, data fetching
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class LoopSettings(Group):
    """``loop.*``: the closed loop of the paper's Fig. 3."""

    threshold: float
    sun_elevation_schedule: Tuple[int, ...]

    def _check(self):
        need(0.0 < self.threshold <= 1.0, "threshold", self.threshold, "must lie in (0, 1]")
        s = list(self.sun_elevation_schedule)
        need(
            bool(s) and s == sorted(set(s)) and s[0] >= 1,
            "sun_elevation_schedule",
            s,
            "must be increasing positive counts",
        )


@dataclass(frozen=True, kw_only=True)
class CountsSettings(Group):
    """``figure6.counts``: the sample counts of each axis for Figure 6."""

    sun_elevation: Optional[Tuple[int, ...]]  # null: this axis is not varied
    sun_azimuth: Optional[Tuple[int, ...]]
    cam_elevation: Optional[Tuple[int, ...]]
    cam_azimuth: Optional[Tuple[int, ...]]

    def _check(self):
        for axis in AXES:
            counts = getattr(self, axis) or ()
            need(all(c >= 1 for c in counts), axis, counts, "counts must be >= 1")


@dataclass(frozen=True, kw_only=True)
class Figure6Settings(Group):
    """``figure6.*``: Figure 6 (crater_synth/evaluation/figure6.py)."""

    counts: CountsSettings
    sigmas: Optional[Tuple[float, ...]]

    def _check(self):
        need(self.sigmas is None or all(s > 0 for s in self.sigmas), "sigmas", self.sigmas, "must be > 0")


@dataclass(frozen=True, kw_only=True)
class ValidateSettings(Group):
    """``validate.*``: the real validation protocol (crater_synth/evaluation/validation.py, docs/validation.md). The
    groups' rules (disjoint, in the catalogue, no test crater) are checked there, against configs/crater/."""

    groups: Tuple[Tuple[str, ...], ...]  # validation crater groups (configs/crater/ names)
    test: Tuple[str, ...]  # the test group: reported, never used to choose
    holdout: Tuple[Tuple[str, ...], ...] = ()  # held-out crater groups: reported, never used to choose
    seeds: Tuple[int, ...]  # training seeds per group
    out_dir: str
    # Which roles this run trains and evaluates (the others are planned and checked, not run).
    roles: Tuple[str, ...] = ("validation", "holdout", "test")
    # Overrides every north-polar group gets (its DEM and real mosaic; the config's own are south-polar).
    north_overrides: Tuple[str, ...] = ()

    def _check(self):
        need(bool(self.seeds), "seeds", self.seeds, "must list at least one seed")
        bad = [r for r in self.roles if r not in ("validation", "holdout", "test")]
        need(bool(self.roles) and not bad, "roles", self.roles, "must list some of validation, holdout, test")
        need(bool(self.out_dir.strip()), "out_dir", self.out_dir, "must not be empty")


@dataclass(frozen=True, kw_only=True)
class LeverSettings(Group):
    """``ablation.levers.<name>``: one fidelity lever; ``when_off`` are the overrides that turn it off."""

    why: str = ""
    when_off: Tuple[str, ...] = ()  # empty: crater_synth/evaluation/ablation.py names the lever in its error


@dataclass(frozen=True, kw_only=True)
class AblationSettings(Group):
    """``ablation.*``: each fidelity lever on and off under the validation protocol (evaluation/ablation.py)."""

    out_dir: str
    docs_file: Optional[str]  # the generated table goes between its markers (null: docs untouched)
    train: Dict[str, Any]  # train.<key> overrides: the same training budget for every variant
    levers: Dict[str, LeverSettings]

    def _check(self):
        need(bool(self.out_dir.strip()), "out_dir", self.out_dir, "must not be empty")


@dataclass(frozen=True, kw_only=True)
class FetchSettings(Group):
    """``fetch.*``: ``crater-synth fetch-data`` (crater_synth/fetch.py, docs/data.md)."""

    base_url: Optional[str]
    timeout_s: float
    retries: int
    chunk_bytes: int
    backoff_s: float

    def _check(self):
        need(self.timeout_s > 0, "timeout_s", self.timeout_s, "must be > 0")
        need(self.retries >= 1, "retries", self.retries, "must be >= 1")
        need(self.chunk_bytes >= 1024, "chunk_bytes", self.chunk_bytes, "must be >= 1024")
        need(self.backoff_s >= 0, "backoff_s", self.backoff_s, "must be >= 0")
        url = (self.base_url or "").strip()
        need(
            not url or url.startswith(("http://", "https://", "file://")),
            "base_url",
            self.base_url,
            "must start with http://, https:// or file://",
        )


# ------------------------------------------------------------------------------------------------
# Navigation frames: a camera trajectory (crater_core/trajectory.py, docs/navigation/rendered.md)
# ------------------------------------------------------------------------------------------------
SUN_MODES = ("physical", "explicit")


@dataclass(frozen=True, kw_only=True)
class TrajectorySettings(Group):
    """``trajectory.*`` (configs/trajectory/*.yaml): camera poses of a run of navigation frames.

    The ground track is the great circle from ``start`` to ``end`` (lat, lon deg); the altitude runs
    linearly from ``altitude_km[0]`` to ``altitude_km[1]`` over ``frames`` evenly spaced frames. The
    boresight is tilted ``off_nadir_deg`` from nadir towards ``off_nadir_azimuth_deg`` (clockwise from
    the direction of flight); image up is the direction of flight. The Sun: ``physical`` puts it at
    the sub-solar point (``subsolar_lat_deg``, ``subsolar_lon_deg``), ``explicit`` at
    (``sun_elevation_deg``, ``sun_azimuth_deg``) above each frame's ground point."""

    name: str
    start: Tuple[float, ...]  # (lat, lon) deg of the first frame's sub-camera point
    end: Tuple[float, ...]  # (lat, lon) deg of the last frame's
    altitude_km: Tuple[float, ...]  # (first, last) frame altitude above the 1737.4 km sphere
    frames: int
    off_nadir_deg: float
    off_nadir_azimuth_deg: float
    fov_deg: float
    width_px: int
    sun: str
    subsolar_lat_deg: float
    subsolar_lon_deg: float
    sun_elevation_deg: float
    sun_azimuth_deg: float

    def _check(self):
        need_plain_name("name", self.name)  # it names the frames' folder
        for key in ("start", "end"):
            v = getattr(self, key)
            need(len(v) == 2, key, list(v), "must be [lat, lon] in degrees")
            need(-90.0 <= v[0] <= 90.0, key, list(v), "latitude must lie in [-90, 90] degrees")
        need(len(self.altitude_km) == 2, "altitude_km", list(self.altitude_km), "must be [first, last] in km")
        need(
            all(0.5 <= a <= 2000.0 for a in self.altitude_km),
            "altitude_km",
            list(self.altitude_km),
            "must lie in [0.5, 2000] km",
        )
        need(self.frames >= 1, "frames", self.frames, "must be >= 1")
        need(0.0 <= self.off_nadir_deg < 60.0, "off_nadir_deg", self.off_nadir_deg, "must lie in [0, 60) degrees")
        need(1.0 <= self.fov_deg <= 120.0, "fov_deg", self.fov_deg, "must lie in [1, 120] degrees")
        need(16 <= self.width_px <= 4096, "width_px", self.width_px, "must lie in [16, 4096] px")
        need(self.sun in SUN_MODES, "sun", self.sun, "must be 'physical' or 'explicit'")
        need(-90.0 <= self.subsolar_lat_deg <= 90.0, "subsolar_lat_deg", self.subsolar_lat_deg, "must lie in [-90, 90]")
        need(
            -90.0 <= self.sun_elevation_deg <= 90.0,
            "sun_elevation_deg",
            self.sun_elevation_deg,
            "must lie in [-90, 90]",
        )


# ------------------------------------------------------------------------------------------------
# The root
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class Settings(Group):
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
    figure6: Figure6Settings
    fetch: FetchSettings
    validate: ValidateSettings
    ablation: AblationSettings
    seed: int
    data_dir: str
    out_dir: str
    run_dir: str
    # Not in configs/config.yaml's defaults (no other command reads it): ``crater-synth nav-frames
    # trajectory=NAME`` selects one.
    trajectory: Optional[TrajectorySettings] = None
    # Not in the defaults either: the procedural crater field (crater_core/procedural.py), ``procedural=NAME``.
    procedural: Optional[ProceduralSettings] = None
    # Not in the defaults either: detection frames' conditions and grouping, ``detection=NAME``.
    detection: Optional[DetectionSettings] = None

    def _check(self):
        if not self.crater:
            raise SettingsError("crater", "no crater selected (crater=NAME or crater=[a,b,...])")
        seen: dict[str, str] = {}
        for key, entry in self.crater.items():
            need(
                entry.name not in seen,
                f"crater.{key}.name",
                entry.name,
                f"repeats crater.{seen.get(entry.name)}'s name (names label renders and classes)",
            )
            seen[entry.name] = key
        for key in ("data_dir", "out_dir", "run_dir"):
            need(bool(str(getattr(self, key)).strip()), key, getattr(self, key), "must not be empty")

    @property
    def craters(self) -> Tuple[CraterSettings, ...]:
        """The selected crater entries, in configuration order."""
        return tuple(self.crater.values())

    def warnings(self) -> list[str]:
        """Settings that are legal but almost surely a mistake (printed as ``warning:`` lines)."""
        return self.sweep.warnings()


# Config groups of configs/ and their settings class (Hydra registers ``<group>_schema`` for each).
GROUPS: Dict[str, type] = {
    "crater": CraterSettings,
    "dem": DemSettings,
    "terrain": TerrainSettings,
    "hapke": HapkeParams,
    "render": RenderSettings,
    "sweep": SweepSettings,
    "launcher": LauncherSettings,
    "model": ModelSettings,
    "train": TrainSettings,
    "sensor": SensorSettings,
    "realset": RealsetSettings,
    "loop": LoopSettings,
    "figure6": Figure6Settings,
    "fetch": FetchSettings,
    "validate": ValidateSettings,
    "ablation": AblationSettings,
    "trajectory": TrajectorySettings,
    "procedural": ProceduralSettings,
    "detection": DetectionSettings,
}

__all__ = [
    "GROUPS",
    "AblationSettings",
    "AxisSettings",
    "ConvSettings",
    "CountsSettings",
    "CraterSettings",
    "DemSettings",
    "DetailSettings",
    "FetchSettings",
    "Figure6Settings",
    "FrameSettings",
    "HapkeParams",
    "HogSettings",
    "LauncherSettings",
    "LeverSettings",
    "LoopSettings",
    "ModelSettings",
    "MosaicSettings",
    "PoolSettings",
    "PreprocessSettings",
    "ProceduralSettings",
    "RealsetSettings",
    "RenderSettings",
    "SensorSettings",
    "Settings",
    "SettingsError",
    "SvmSettings",
    "SweepSettings",
    "TerrainSettings",
    "TrainSettings",
    "TrajectorySettings",
    "ValidateSettings",
    "as_plain",
    "build",
    "replace",
]
