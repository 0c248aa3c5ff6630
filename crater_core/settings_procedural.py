"""Typed settings of the procedural crater-field terrain (``procedural.*``, configs/procedural/*.yaml).

The generator is :mod:`crater_core.procedural` (docs/procedural.md). Standard library only, like
:mod:`crater_core.settings`.
"""

from __future__ import annotations

from dataclasses import dataclass

from crater_core.typed_config import Group, need

# Grid side: below 64 px there is no room for a crater field; above 8192 the float64 grid exceeds 512 MB.
PROCEDURAL_SIZE_RANGE = (64, 8192)
# The Neukum et al. (2001) chronology is calibrated over the Moon's history: ages in (0, 4.5] Gyr.
MAX_SURFACE_AGE_GYR = 4.5


@dataclass(frozen=True, kw_only=True)
class ProceduralSettings(Group):
    """``procedural.*``: a square crater field on fractal ground (crater_core/procedural.py)."""

    size_px: int = 1024
    spacing_m: float = 50.0  # ground sample distance, m/px
    seed: int = 0
    surface_age_gyr: float = 3.5  # sets the crater count (Neukum chronology) and the oldest crater's age
    density_scale: float = 1.0  # multiplies the production-function count (1: the age's count)
    d_min_px: float = 3.0  # smallest crater drawn, in pixels across
    d_max_fraction: float = 0.5  # largest crater drawn, as a fraction of the grid side
    secondary_fraction: float = 0.3  # expected secondaries per primary (on the primaries that can throw them)
    diffusivity_m2_per_myr: float = 5.5  # topographic diffusivity (Fassett & Thomson 2014); 0: all fresh
    hurst: float = 0.85  # Hurst exponent of the fractal ground
    roughness_rms_slope_deg: float = 3.0  # RMS slope of the fractal ground over a 100 m baseline

    def _check(self) -> None:
        lo, hi = PROCEDURAL_SIZE_RANGE
        need(lo <= self.size_px <= hi, "size_px", self.size_px, f"must lie in [{lo}, {hi}]")
        need(self.spacing_m > 0.0, "spacing_m", self.spacing_m, "must be > 0 (metres per pixel)")
        need(
            0.0 < self.surface_age_gyr <= MAX_SURFACE_AGE_GYR,
            "surface_age_gyr",
            self.surface_age_gyr,
            f"must lie in (0, {MAX_SURFACE_AGE_GYR}] Gyr",
        )
        need(0.0 <= self.density_scale <= 100.0, "density_scale", self.density_scale, "must lie in [0, 100]")
        need(self.d_min_px >= 2.0, "d_min_px", self.d_min_px, "must be >= 2 (a crater needs pixels across)")
        need(0.0 < self.d_max_fraction <= 1.0, "d_max_fraction", self.d_max_fraction, "must lie in (0, 1]")
        need(
            self.d_max_fraction * self.size_px > self.d_min_px,
            "d_max_fraction",
            self.d_max_fraction,
            f"leaves no diameter range above d_min_px={self.d_min_px:g} on a {self.size_px} px grid",
        )
        need(
            0.0 <= self.secondary_fraction <= 10.0,
            "secondary_fraction",
            self.secondary_fraction,
            "must lie in [0, 10]",
        )
        need(self.diffusivity_m2_per_myr >= 0.0, "diffusivity_m2_per_myr", self.diffusivity_m2_per_myr, "must be >= 0")
        need(0.0 < self.hurst < 1.0, "hurst", self.hurst, "must lie in (0, 1)")
        need(
            0.0 <= self.roughness_rms_slope_deg < 45.0,
            "roughness_rms_slope_deg",
            self.roughness_rms_slope_deg,
            "must lie in [0, 45) degrees",
        )
