"""Typed settings of detection frames (``detection.*``, configs/detection/*.yaml): the conditions a frame of
``crater-synth detection-frames`` draws, and how frames share a worker's work (docs/procedural.md,
"Detection frames"). Each range is a dataset lever the ablation varies. Standard library only, like
:mod:`crater_core.settings`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

from crater_core.typed_config import Group, need

# A frame below 16 px holds no crater of the labels' 3 px; above 4096 px one frame's channels pass 400 MB.
WIDTH_RANGE = (16, 4096)


def _need_range(key: str, value, lo: float, hi: float, what: str) -> None:
    need(len(value) == 2 and lo <= value[0] <= value[1] <= hi, key, value, f"must be [low, high] within {what}")


@dataclass(frozen=True, kw_only=True)
class DetectionSettings(Group):
    """``detection.*``: one detection frame's conditions and the set's grouping."""

    width_px: int = 256  # frame side (square frame)
    fov_deg: float = 30.0  # full field of view; the ground sample varies ~7 % across a nadir frame
    sun_elevation_deg: Tuple[float, ...] = (0.5, 60.0)  # drawn uniform: polar low Sun to mid-latitude morning
    nadir_share: float = 0.25  # frames looking straight down (mapping passes); the others oblique
    off_nadir_deg: Tuple[float, ...] = (0.0, 45.0)  # oblique frames: off-nadir angle drawn uniform
    gsd_max_factor: float = 2.0  # ground sample drawn log-uniform in [1, this] x the field's grid spacing
    # Grid spacing of each field (m/px), drawn log-uniform per field; null: procedural.spacing_m for all
    spacing_m: Optional[Tuple[float, ...]] = None
    views_per_field: int = 64  # frames per field (one patch, scene and BVH)
    suns_per_view: int = 4  # consecutive frames sharing one camera (one G-buffer), each under its own Sun
    azimuths_per_field: int = 4  # Sun azimuths of a field, evenly spaced (one horizon map each); 0: own

    def _check(self) -> None:
        lo, hi = WIDTH_RANGE
        need(lo <= self.width_px <= hi, "width_px", self.width_px, f"must lie in [{lo}, {hi}] px")
        need(1.0 <= self.fov_deg <= 120.0, "fov_deg", self.fov_deg, "must lie in [1, 120] degrees")
        _need_range("sun_elevation_deg", self.sun_elevation_deg, 0.0, 90.0, "[0, 90] degrees")
        need(0.0 <= self.nadir_share <= 1.0, "nadir_share", self.nadir_share, "must lie in [0, 1]")
        _need_range("off_nadir_deg", self.off_nadir_deg, 0.0, 60.0, "[0, 60] degrees")
        need(1.0 <= self.gsd_max_factor <= 16.0, "gsd_max_factor", self.gsd_max_factor, "must lie in [1, 16]")
        if self.spacing_m is not None:
            _need_range("spacing_m", self.spacing_m, 1.0, 10000.0, "[1, 10000] m per pixel")
        need(self.views_per_field >= 1, "views_per_field", self.views_per_field, "must be >= 1")
        need(self.suns_per_view >= 1, "suns_per_view", self.suns_per_view, "must be >= 1")
        need(
            self.views_per_field % self.suns_per_view == 0,
            "views_per_field",
            self.views_per_field,
            f"must be a multiple of suns_per_view={self.suns_per_view} (a view's frames lie in one field)",
        )
        need(self.azimuths_per_field >= 0, "azimuths_per_field", self.azimuths_per_field, "must be >= 0")
