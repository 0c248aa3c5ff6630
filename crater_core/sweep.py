"""The Table 2 sweep grid: the one source of truth for index <-> render parameters.

Pure numpy + standard library (used by the host orchestration, the Blender worker's jobs and train/).

Sample positions (docs/specification.md, the project's reading of the paper's Table 2):
    sun elevation   theta1 = 0.16 deg * k,        k = 1..N
    sun azimuth     phi1   = 360 deg * k / N,     k = 0..N-1
    camera elevation theta2 = 90 deg - 4 deg * k, k = 0..N-1
    camera azimuth  phi2   = 360 deg * k / N,     k = 0..N-1
    ROI ratio       sigma  = 1.0 + 0.2 * k,       k = 0..N-1   (a crop of every render, not a render axis)

Sun model (``sweep.sun_model``): ``paper`` uses the positions above for every crater (Table 2's
0.16-1.6 deg is the paper's choice). ``physical`` (docs/validation.md) reads the sun-elevation values as
fractions f of the highest elevation the Sun really reaches at that crater in that direction,
theta = f * theta_max(lat, phi1) (``crater_core.illumination``), default f = 0.1 k, k = 1..N, so that
count 10 spans the crater's whole physical range and smaller counts are prefixes (the closed loop
stays nested); suns that would stand below ``min_sun_elevation_deg`` are not rendered. A physical
sweep's sun-azimuth values v are measured from the crater's noon direction, where the Sun stands highest
(``crater_core.geometry.noon_azimuth_deg``: local north at a south-polar crater, local south at a
north-polar one, whose local north points at the pole), towards local east (the morning side at both
poles): the rendered azimuth (clockwise from local north) is v in the south and 180 - v in the north, so
one sweep gives a crater and its mirror image about the equator mirrored suns. A manifest row keeps the
rendered azimuth as ``sun_azimuth`` and the grid value as ``sun_azimuth_param`` where they differ; at
the south pole they are the same number.

Render order is sun-major (sun elevation, sun azimuth, camera elevation, camera azimuth), so a
contiguous shard shares few sun directions: the fast renderer computes one shadow map per sun
direction and one G-buffer per camera pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Mapping, Sequence

import numpy as np

from crater_core.errors import ContractError
from crater_core.geometry import hemisphere, noon_azimuth_deg
from crater_core.illumination import max_sun_elevation_deg
from crater_core.schema import render_rel_path


class SweepError(ContractError):
    """A sweep configuration value is missing or physically meaningless."""


AXES = ("sun_elevation", "sun_azimuth", "cam_elevation", "cam_azimuth")
SUN_MODELS = ("paper", "physical")
# Physical sweeps: sun-elevation fractions 0.1 k (count 10 = the crater's whole range, like 0.16 k deg).
PHYSICAL_STEP_FRACTION = 0.1

# Largest sample count of one axis: 3600 azimuths are 0.1 deg apart, ten times the paper's finest grid
# (a count of 10^9 would first build a 15 GB value list). Checked before any list is built.
MAX_AXIS_COUNT = 3600
# Largest sweep of one crater (renders): ~440x the paper sweep (22,500), several TB of EXRs at ~0.5 MB each.
MAX_GRID_RENDERS = 10_000_000

# Physical limits used to reject nonsense configuration before any rendering starts.
_LIMITS = {
    "sun_elevation": (-90.0, 90.0, "sun elevation must lie in (-90, 90] degrees"),
    "sun_azimuth": (-360.0, 720.0, "sun azimuth must lie in [-360, 720] degrees"),
    "cam_elevation": (0.0, 90.0, "camera elevation must lie in (0, 90] degrees (above the horizon)"),
    "cam_azimuth": (-360.0, 720.0, "camera azimuth must lie in [-360, 720] degrees"),
}


def default_positions(axis: str, count: int, step_deg: float | None = None) -> list[float]:
    """The paper's sample positions for ``count`` samples of ``axis`` (see module docstring)."""
    if not 1 <= count <= MAX_AXIS_COUNT:
        raise SweepError(f"sweep.{axis}.count={count}: must lie in [1, {MAX_AXIS_COUNT}]")
    k = np.arange(count, dtype=np.float64)
    if axis == "sun_elevation":
        vals = (step_deg or 0.16) * (k + 1.0)
    elif axis in ("sun_azimuth", "cam_azimuth"):
        vals = 360.0 * k / count
    elif axis == "cam_elevation":
        vals = 90.0 - (step_deg or 4.0) * k
    elif axis == "sigma":
        vals = 1.0 + (step_deg or 0.2) * k
    else:
        raise SweepError(f"unknown sweep axis {axis!r}")
    return [round(float(v), 10) for v in vals]


@dataclass(frozen=True)
class RenderParams:
    """Parameters of one render of the sweep (angles in degrees)."""

    index: int
    indices: tuple[int, int, int, int]
    sun_elevation: float
    sun_azimuth: float
    cam_elevation: float
    cam_azimuth: float

    sun_elevation_param: float | None = None  # the grid value (physical sweeps: the fraction f)
    sun_azimuth_param: float | None = None  # the grid value (physical sweeps: from the noon direction)

    @property
    def sun_key(self) -> tuple[int, int]:
        return self.indices[0], self.indices[1]

    @property
    def camera_key(self) -> tuple[int, int]:
        return self.indices[2], self.indices[3]

    def as_dict(self) -> dict:
        return {
            "index": self.index,
            "indices": list(self.indices),
            "sun_elevation": self.sun_elevation,
            "sun_azimuth": self.sun_azimuth,
            "cam_elevation": self.cam_elevation,
            "cam_azimuth": self.cam_azimuth,
        }


@dataclass(frozen=True)
class SweepGrid:
    """The Cartesian product of the four angular axes, plus the ROI ratios and fixed camera values."""

    sun_elevation: tuple[float, ...]
    sun_azimuth: tuple[float, ...]
    cam_elevation: tuple[float, ...]
    cam_azimuth: tuple[float, ...]
    sigmas: tuple[float, ...]
    fov_deg: float = 90.0
    range_factor: float = 1.5
    sun_model: str = "paper"  # "paper" | "physical" (see module docstring)
    min_sun_elevation_deg: float = 0.0  # physical sweeps: suns below this are not rendered

    def __post_init__(self):
        if len(self) > MAX_GRID_RENDERS:
            raise SweepError(
                f"sweep of {' x '.join(map(str, self.shape))} = {len(self):,} renders per crater: at most "
                f"{MAX_GRID_RENDERS:,} (lower sweep.<axis>.count)"
            )
        if self.sun_model not in SUN_MODELS:
            raise SweepError(f"invalid sweep.sun_model={self.sun_model!r}: choose one of {list(SUN_MODELS)}")
        if self.sun_model == "physical":
            bad = [v for v in self.sun_elevation if not 0.0 < v <= 1.0]
            if bad:
                raise SweepError(
                    f"invalid sweep.sun_elevation values {bad}: with sweep.sun_model=physical they are "
                    "fractions of the crater's highest sun elevation, in (0, 1]"
                )
        for axis in AXES:
            vals = getattr(self, axis)
            if len(vals) == 0:
                raise SweepError(f"sweep.{axis} has no values")
            if axis == "sun_elevation" and self.sun_model == "physical":
                if len(set(vals)) != len(vals):
                    raise SweepError(f"sweep.{axis} has duplicate values {list(vals)}")
                continue
            lo, hi, msg = _LIMITS[axis]
            bad = [v for v in vals if not (lo < v <= hi) and not (axis.endswith("azimuth") and v == lo)]
            if bad:
                shown = f"{bad[:5]}" if len(bad) <= 5 else f"{bad[:5]} (and {len(bad) - 5} more)"
                raise SweepError(f"invalid sweep.{axis} values {shown}: {msg}")
            if len(set(vals)) != len(vals):
                raise SweepError(f"sweep.{axis} has duplicate values {list(vals)}")
        self._check_unique_names()
        if not self.sigmas or any(s <= 0 for s in self.sigmas):
            raise SweepError(f"invalid sweep.sigma values {list(self.sigmas)}: ROI ratio must be > 0")
        if not (0.0 < self.fov_deg < 180.0):
            raise SweepError(f"invalid sweep.fov_deg={self.fov_deg}: field of view must lie in (0, 180)")
        if not self.range_factor > 0:
            raise SweepError(f"invalid sweep.range_factor={self.range_factor}: must be > 0")

    def _check_unique_names(self) -> None:
        """Every render needs its own file name (:func:`crater_core.schema.render_rel_path`, angles to
        0.001 deg) and its own manifest key (angles to 1e-6 deg): two values of an axis that the name
        rounds together would write two renders into one file. Physical sun elevations depend on the
        crater; the planner checks their names per crater."""
        for i, axis in enumerate(AXES):
            if axis == "sun_elevation" and self.sun_model == "physical":
                continue
            seen: dict[str, float] = {}
            for v in getattr(self, axis):
                angles = [0.0] * 4
                angles[i] = v
                name = render_rel_path("c", *angles)
                if name in seen:
                    values = ",".join(f"{x:g}" for x in getattr(self, axis))
                    raise SweepError(
                        f"sweep.{axis}.values=[{values}]: {seen[name]:g} and {v:g} would share one file name "
                        "(angles are named to 0.001 deg): space the values at least 0.001 deg apart"
                    )
                seen[name] = v

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return tuple(len(getattr(self, a)) for a in AXES)  # type: ignore[return-value]

    def __len__(self) -> int:
        return int(np.prod(self.shape))

    def params(self, index: int, lat_deg: float | None = None) -> RenderParams:
        """Deterministic flat index -> render parameters (sun-major order). Physical sweeps need the
        crater's latitude: the sun elevation is the grid's fraction of the local maximum."""
        if not 0 <= index < len(self):
            raise IndexError(f"sweep index {index} outside [0, {len(self)})")
        i0, i1, i2, i3 = (int(i) for i in np.unravel_index(index, self.shape))
        idx = (i0, i1, i2, i3)
        param = self.sun_elevation[idx[0]]
        elevation = param
        if self.sun_model == "physical":
            if lat_deg is None:
                raise SweepError("a physical sweep needs the crater latitude to place its suns")

            # South: the grid value itself (the same number as before the north pole was supported);
            # north: mirrored about the noon direction, so that a value v is on the same (morning, east)
            # side of noon at both poles and a mirrored crater sees the mirrored suns.
            v = self.sun_azimuth[idx[1]]
            azimuth = v if hemisphere(lat_deg) == "south" else round((noon_azimuth_deg(lat_deg) - v) % 360.0, 6)
            elevation = round(float(param * max_sun_elevation_deg(lat_deg, azimuth)), 6)
        else:
            azimuth = self.sun_azimuth[idx[1]]
        return RenderParams(
            index,
            idx,
            elevation,
            azimuth,
            self.cam_elevation[idx[2]],
            self.cam_azimuth[idx[3]],
            sun_elevation_param=param,
            sun_azimuth_param=self.sun_azimuth[idx[1]],
        )

    def renders(self, params: RenderParams) -> bool:
        """Whether a render is part of the sweep: physical sweeps skip suns that never rise high enough
        in that direction (below ``min_sun_elevation_deg``); paper sweeps render everything."""
        return self.sun_model != "physical" or params.sun_elevation >= self.min_sun_elevation_deg

    def index_of(self, indices: Sequence[int]) -> int:
        return int(np.ravel_multi_index(tuple(indices), self.shape))

    def __iter__(self) -> Iterator[RenderParams]:
        return (self.params(i) for i in range(len(self)))

    def shard(self, shard_index: int, shard_count: int) -> range:
        """Contiguous block of flat indices for shard ``shard_index`` of ``shard_count``."""
        if shard_count < 1 or not 0 <= shard_index < shard_count:
            raise SweepError(f"invalid shard {shard_index}/{shard_count}: need 0 <= i < n, n >= 1")
        n = len(self)
        return range(shard_index * n // shard_count, (shard_index + 1) * n // shard_count)

    def as_dict(self) -> dict:
        return {a: list(getattr(self, a)) for a in AXES} | {
            "sigmas": list(self.sigmas),
            "fov_deg": self.fov_deg,
            "range_factor": self.range_factor,
            "sun_model": self.sun_model,
            "min_sun_elevation_deg": self.min_sun_elevation_deg,
        }


def _axis_values(cfg_axis: Mapping, axis: str, sun_model: str = "paper") -> tuple[float, ...]:
    values = cfg_axis.get("values")
    if values is not None:
        return tuple(float(v) for v in values)
    count = int(cfg_axis["count"])
    if not 1 <= count <= MAX_AXIS_COUNT:  # before default_positions builds the list
        raise SweepError(f"sweep.{axis}.count={count}: must lie in [1, {MAX_AXIS_COUNT}]")
    step = cfg_axis.get("step_deg")
    if axis == "sun_elevation" and sun_model == "physical":
        step = cfg_axis.get("step_fraction") or PHYSICAL_STEP_FRACTION
    return tuple(default_positions(axis, count, step))


def grid_from_config(sweep_cfg: Mapping) -> SweepGrid:
    """Build the grid from a ``configs/sweep/*.yaml`` mapping (counts, or explicit value lists)."""
    sun_model = str(sweep_cfg.get("sun_model") or "paper")
    try:
        return SweepGrid(
            sun_elevation=_axis_values(sweep_cfg["sun_elevation"], "sun_elevation", sun_model),
            sun_azimuth=_axis_values(sweep_cfg["sun_azimuth"], "sun_azimuth"),
            cam_elevation=_axis_values(sweep_cfg["cam_elevation"], "cam_elevation"),
            cam_azimuth=_axis_values(sweep_cfg["cam_azimuth"], "cam_azimuth"),
            sigmas=_axis_values(sweep_cfg["sigma"], "sigma"),
            fov_deg=float(sweep_cfg.get("fov_deg", 90.0)),
            range_factor=float(sweep_cfg.get("range_factor", 1.5)),
            sun_model=sun_model,
            min_sun_elevation_deg=float(sweep_cfg.get("min_sun_elevation_deg") or 0.0),
        )
    except KeyError as exc:
        raise SweepError(f"sweep config is missing key {exc}") from None


def rows_in_selection(rows: Sequence[Mapping], selection: Mapping[str, Sequence[float] | None] | None) -> list:
    """Rows whose angles lie in ``selection`` ({axis: values or None}); None/empty keeps every row.

    This is how a grid subset (a closed-loop round, a Figure 6 point) is taken from one rendered
    dataset without re-rendering.
    """
    if not selection:
        return list(rows)
    wanted = {}
    for axis, values in selection.items():
        if axis not in AXES:
            raise SweepError(f"unknown selection axis {axis!r} (expected one of {AXES})")
        if values is not None:
            wanted[axis] = {round(float(v), 6) for v in values}
    return [r for r in rows if all(round(float(_axis_value(r, a)), 6) in vals for a, vals in wanted.items())]


def _axis_value(row: Mapping, axis: str) -> float:
    """A row's grid value on ``axis`` (physical sweeps: the sun-elevation fraction, not the angle, and
    the sun azimuth from the noon direction)."""
    if axis in ("sun_elevation", "sun_azimuth") and row.get(f"{axis}_param") is not None:
        return row[f"{axis}_param"]
    return row[axis]


def nearest_subset(available: Sequence[float], axis: str, count: int) -> list[float]:
    """``count`` of the ``available`` (rendered, grid-ordered) values for a Figure 6 point.

    Elevation axes: the paper's positions for N samples are the first N of its grid (sun 0.16 deg * k,
    camera 90 - 4 deg * k), so the subset is the first ``count`` rendered values in grid order -- exact
    for the paper grid, and the same rule for explicit value lists. Azimuth axes: 360 k / N for 6, 9 or
    12 samples are not subsets of the 15-sample grid, so each target snaps to the nearest rendered
    azimuth (circular distance, ties to the smaller angle). Raises if two targets snap to one value.
    """
    avail = [float(v) for v in available]
    if count > len(avail):
        raise SweepError(f"{axis}: {count} samples requested but only {len(avail)} rendered")
    if not axis.endswith("azimuth"):
        return avail[:count]
    avail = sorted(avail)
    out = []
    for target in default_positions(axis, count):
        dist = [min(abs(v - target) % 360.0, 360.0 - abs(v - target) % 360.0) for v in avail]
        out.append(avail[int(np.argmin(np.round(dist, 9)))])
    if len(set(out)) != count:
        raise SweepError(
            f"{axis}: {count} samples cannot be taken from the rendered values {avail} without repeats ({out})"
        )
    return out
