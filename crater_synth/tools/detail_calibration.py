"""Calibrate the sub-DEM detail against a real LOLA 200 m crop (docs/detail.md).

What it measures, on the same 200 m grid and the same background area:

- real: the registered LOLA-derived 200 m/px Shackleton crop, the embedded product
  ``shackleton_lola_200m`` (data_manifest/products.yaml; heights above the 1737.4 km sphere, lowered
  square repaired). Its grid comes from the product's georeferencing: the registration lives in
  :mod:`crater_synth.terrain.register` (``registration.json``), nowhere else;
- LDEM: the embedded 1600 m/px LDEM_256 sampled on that grid exactly as the terrain patch samples it
  (``Dem.sample``: bicubic);
- LDEM + detail: the same plus :func:`crater_synth.terrain.detail.synthesize_detail` (old and new model).

Statistics (:func:`terrain_statistics`): slope distributions over 200/400/800 m baselines, the
Laplacian (curvature) at 200/400 m, the height structure function at 200-3200 m lags and its
Hurst exponent over 400-3200 m, and the closed depressions (what a low Sun fills with shadow):
their number per 1000 km^2 by size and their depth/diameter. The background excludes the
Shackleton bowl (within 1.3 R of its centre); the repaired square is real data and is kept.

``python -m crater_synth.tools.calibrate_detail --out DIR`` prints the table and writes hillshades
(sun 0.5, 1.6 and 5 deg, cast shadows) of real / LDEM / old / new to ``DIR``. The numbers in
:data:`REAL_CROP_STATS` were produced by it (``measure_real``) and are what tests/test_detail.py
checks the generator against.

Length: one measurement, end to end: the real crop, the same statistics applied to real, LDEM and
LDEM + detail, the crater-population checks against published size-frequency curves, the refit and
its tables and hillshades. Each piece is short and only this calibration uses them; a split would
scatter one documented procedure (docs/detail.md) over several files.
"""

from __future__ import annotations

import io
import itertools
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from PIL import Image
from rasterio.warp import transform

from crater_core.procedural import chronology_n1, production_cumulative
from crater_core.schema import atomic_write_bytes
from crater_synth.errors import UserError
from crater_synth.terrain.dem import Dem
from crater_synth.terrain.detail import (
    LEGACY_PARAMETERS,
    DetailSettings,
    crater_population,
    crater_profile,
    degradation_table,
    degraded_population,
    degraded_profile,
    highpass_weights,
    synthesize_detail,
)
from crater_synth.terrain.register import block_mean
from crater_synth.terrain.stack import open_dem_entry
from data_manifest.products import resolve_product

# The registered real crop (data_manifest/products.yaml); --dem takes another product id or DEM file.
REAL_CROP_PRODUCT = "shackleton_lola_200m"
BASE_DEM_PRODUCT = "lola_ldem256_south"
DEFAULT_DATA_DIR = "data"
# The statistics' baselines and the detail's reference grid are in 200 m pixels.
REAL_CROP_SPACING_M = 200.0
MIN_CROP_PX = 64  # the band mask loses 8 px (one DEM pixel) per side; 48 px left for the 16 px lag
# Shackleton (IAU Gazetteer; docs/specification.md): the bowl and its inner rim flank are excluded within
# 1.3 R. The product's
# repaired square (rows/cols 103-152: the 40 m crop averaged to 200 m) is NOT excluded: in its interior
# it has the same 200 m statistics as the raw (lowered) square's native 200 m processing (Laplacian std,
# RMS slope, structure function within 1-3 %), docs/detail.md.
SHACKLETON_LAT, SHACKLETON_LON, SHACKLETON_DIAMETER_M = -89.67, 129.78, 21000.0
BOWL_EXCLUSION_RADII = 1.3
# Statistics: baselines (px of 200 m), structure-function lags (px), closed-depression threshold.
SLOPE_BASELINES_PX = (1, 2, 4)
LAPLACIAN_BASELINES_PX = (1, 2)
STRUCTURE_LAGS_PX = (1, 2, 4, 8, 16)
HURST_FIT_LAGS_PX = (2, 4, 8, 16)  # 400-3200 m
DEPRESSION_MIN_DEPTH_M = 2.0  # ~ LOLA's vertical precision at 200 m averaging (docs/detail.md)
DEPRESSION_SIZES_PX = (2, 4, 8)  # equivalent diameters 400, 800, 1600 m

# Measured by measure_real() on the registered product (docs/detail.md has the table; tests use them).
REAL_CROP_STATS = {
    "slope200_p50_deg": 9.87521,
    "slope200_p90_deg": 18.3143,
    "slope200_p99_deg": 23.8423,
    "slope200_rms_deg": 11.8056,
    "slope400_p50_deg": 9.7822,
    "slope400_p90_deg": 18.1408,
    "slope400_p99_deg": 23.735,
    "slope400_rms_deg": 11.7104,
    "slope800_p50_deg": 9.60268,
    "slope800_p90_deg": 17.8849,
    "slope800_p99_deg": 23.5047,
    "slope800_rms_deg": 11.5334,
    "laplacian200_std_per_km": 0.35819,
    "laplacian200_p99abs_per_km": 1.26427,
    "laplacian400_std_per_km": 0.245722,
    "laplacian400_p99abs_per_km": 0.797808,
    "sf200_m": 29.9503,
    "sf400_m": 59.3462,
    "sf800_m": 116.63,
    "sf1600_m": 225.286,
    "sf3200_m": 420.129,
    "hurst_400_3200": 0.942063,
    "pits400_per_1000km2": 25.5343,
    "pits800_per_1000km2": 9.32982,
    "pits1600_per_1000km2": 2.45522,
    "pits400_median_depth_diameter": 0.0378355,
    "band_rms_height_m": 10.4182,
    "band_slope200_rms_deg": 2.78701,
    "band_slope200_p99_deg": 10.0771,
    "band_laplacian200_std_per_km": 0.319446,
    "band_sf200_m": 6.93386,
    "band_sf400_m": 11.6761,
    "band_sf800_m": 16.0124,
    "band_sf1600_m": 14.7653,
    "band_sf3200_m": 15.0481,
}


class CalibrationDataError(UserError):
    """The real crop is missing, unreadable, or not a complete north-up 200 m grid."""


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------
@dataclass
class RealCrop:
    """A registered real crop: heights (m above the sphere) on its own georeferenced grid."""

    heights: np.ndarray
    top_left_xy_m: tuple[float, float]  # centre of pixel (0, 0), projected metres; columns +x, rows -y
    spacing_m: float
    name: str  # product id or file name
    path: Path


def load_real_crop(entry: str = REAL_CROP_PRODUCT, data_dir: str | Path = DEFAULT_DATA_DIR) -> RealCrop:
    """The real crop from a registered DEM product id (default ``shackleton_lola_200m``) or a DEM file
    (through :func:`crater_synth.terrain.stack.open_dem_entry`), with its grid from its georeferencing.

    It must be north-up with square 200 m pixels, at least ``MIN_CROP_PX`` on a side, and have no
    nodata; anything else is one :class:`CalibrationDataError` naming the entry.
    """

    dem, _ = open_dem_entry(entry, data_dir, what="real crop (--dem)")
    where = f"real crop {entry!r} ({dem.path})"
    t = dem.transform
    if not (
        math.isclose(t.a, REAL_CROP_SPACING_M, rel_tol=1e-6) and math.isclose(-t.e, REAL_CROP_SPACING_M, rel_tol=1e-6)
    ):
        raise CalibrationDataError(
            f"{where}: pixels {t.a:g} x {t.e:g} m; the calibration needs a north-up "
            f"grid of {REAL_CROP_SPACING_M:g} m square pixels"
        )
    if min(dem.height, dem.width) < MIN_CROP_PX:
        raise CalibrationDataError(
            f"{where}: {dem.height} x {dem.width} px, at least {MIN_CROP_PX} x {MIN_CROP_PX} needed"
        )
    heights, valid = dem.read_heights()
    if not valid.all():
        raise CalibrationDataError(
            f"{where}: {int((~valid).sum())} nodata pixels; the calibration needs a complete crop"
        )
    return RealCrop(
        heights=heights,
        top_left_xy_m=(t.c + 0.5 * t.a, t.f + 0.5 * t.e),
        spacing_m=float(t.a),
        name=dem.product,
        path=dem.path,
    )


def _open_ldem(data_dir: str | Path = DEFAULT_DATA_DIR):

    return Dem(resolve_product(BASE_DEM_PRODUCT, data_dir), product=BASE_DEM_PRODUCT)


def grid_xy(top_left_xy: tuple[float, float], shape: tuple[int, int], spacing: float):
    """Projected (x, y) of a grid's pixel centres from its top-left centre: columns +x, rows -y."""
    i = np.arange(shape[0])[:, None]
    j = np.arange(shape[1])[None, :]
    x = np.broadcast_to(top_left_xy[0] + j * spacing, shape)
    y = np.broadcast_to(top_left_xy[1] - i * spacing, shape)
    return x, y


def sample_ldem(dem, top_left_xy, shape, spacing) -> np.ndarray:
    """LDEM heights on a grid through ``Dem.sample`` (bicubic), as terrain.py samples."""

    x, y = grid_xy(top_left_xy, shape, spacing)
    lon, lat = transform(dem.crs, dem.geographic_crs, x.ravel(), y.ravel())
    res = dem.sample(np.reshape(lat, shape), np.reshape(lon, shape), spacing_m=spacing, what="calibration crop")
    return res.heights


def background_mask(top_left_xy, shape, spacing, dem) -> np.ndarray:
    """True on background pixels: outside Shackleton's bowl and inner flank (1.3 R of its centre)."""
    cx, cy = dem.latlon_to_xy(SHACKLETON_LAT, SHACKLETON_LON)
    x, y = grid_xy(top_left_xy, shape, spacing)
    return np.hypot(x - float(cx), y - float(cy)) > BOWL_EXCLUSION_RADII * SHACKLETON_DIAMETER_M / 2.0


# --------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------
def slopes_deg(z: np.ndarray, mask: np.ndarray, k: int, spacing: float) -> np.ndarray:
    """Slope (deg) over a k-pixel baseline: forward differences in x and y from the same corner."""
    gx = z[:-k, k:] - z[:-k, :-k]
    gy = z[k:, :-k] - z[:-k, :-k]
    ok = mask[:-k, :-k] & mask[:-k, k:] & mask[k:, :-k]
    return np.degrees(np.arctan(np.hypot(gx, gy)[ok] / (k * spacing)))


def laplacian(z: np.ndarray, mask: np.ndarray, k: int, spacing: float) -> np.ndarray:
    """Five-point Laplacian (1/m) over a k-pixel baseline, on pixels whose stencil is in the mask."""
    c = z[k:-k, k:-k]
    lap = (z[2 * k :, k:-k] + z[: -2 * k, k:-k] + z[k:-k, 2 * k :] + z[k:-k, : -2 * k] - 4.0 * c) / (k * spacing) ** 2
    ok = mask[k:-k, k:-k] & mask[2 * k :, k:-k] & mask[: -2 * k, k:-k] & mask[k:-k, 2 * k :] & mask[k:-k, : -2 * k]
    return lap[ok]


def structure_function(z: np.ndarray, mask: np.ndarray, k: int) -> float:
    """RMS height difference (m) over a k-pixel lag, x and y pairs inside the mask."""
    dx = (z[:, k:] - z[:, :-k])[mask[:, k:] & mask[:, :-k]]
    dy = (z[k:] - z[:-k])[mask[k:] & mask[:-k]]
    return float(np.sqrt(np.mean(np.concatenate([dx, dy]) ** 2)))


def fill_depressions(z: np.ndarray) -> np.ndarray:
    """Depression-filled surface: the lowest surface >= z draining to the grid edge (morphological
    reconstruction by erosion, iterated to convergence; Soille 2003, *Morphological Image Analysis*)."""
    from scipy import ndimage

    filled = np.full_like(z, np.inf)
    for sl in ((0, slice(None)), (-1, slice(None)), (slice(None), 0), (slice(None), -1)):
        filled[sl] = z[sl]
    footprint = np.ones((3, 3), dtype=bool)
    for _ in range(z.size):
        nxt = np.minimum(filled, np.maximum(z, ndimage.grey_erosion(filled, footprint=footprint, mode="nearest")))
        if np.array_equal(nxt, filled):
            break
        filled = nxt
    return filled


def closed_depressions(
    z: np.ndarray, mask: np.ndarray, spacing: float, min_depth_m: float = DEPRESSION_MIN_DEPTH_M
) -> tuple[np.ndarray, np.ndarray]:
    """(equivalent diameter m, depth m) of the closed depressions deeper than ``min_depth_m`` that
    lie wholly inside ``mask`` (8-connected regions where the filled surface is above z)."""
    from scipy import ndimage

    depth = fill_depressions(z) - z
    labels, n = ndimage.label(depth > min_depth_m, structure=np.ones((3, 3)))
    if n == 0:
        return np.zeros(0), np.zeros(0)
    idx = np.arange(1, n + 1)
    area = ndimage.sum_labels(np.ones_like(depth), labels, idx) * spacing**2
    deepest = ndimage.maximum(depth, labels, idx)
    inside = ndimage.minimum(mask.astype(float), labels, idx) > 0
    return 2.0 * np.sqrt(area[inside] / np.pi), deepest[inside]


def terrain_statistics(z: np.ndarray, mask: np.ndarray, spacing: float = REAL_CROP_SPACING_M) -> dict:
    """Slope, curvature, structure-function and closed-depression statistics of ``z`` on ``mask``."""
    out: dict = {}
    for k in SLOPE_BASELINES_PX:
        s = slopes_deg(z, mask, k, spacing)
        b = int(k * spacing)
        for q in (50, 90, 99):
            out[f"slope{b}_p{q}_deg"] = float(np.percentile(s, q))
        out[f"slope{b}_rms_deg"] = float(np.sqrt(np.mean(s**2)))
    for k in LAPLACIAN_BASELINES_PX:
        lap = laplacian(z, mask, k, spacing) * 1e3  # 1/km
        b = int(k * spacing)
        out[f"laplacian{b}_std_per_km"] = float(lap.std())
        out[f"laplacian{b}_p99abs_per_km"] = float(np.percentile(np.abs(lap), 99))
    sf = {k: structure_function(z, mask, k) for k in STRUCTURE_LAGS_PX}
    for k, v in sf.items():
        out[f"sf{int(k * spacing)}_m"] = v
    lags = np.array(HURST_FIT_LAGS_PX, dtype=float)
    out["hurst_400_3200"] = float(np.polyfit(np.log(lags), np.log([sf[k] for k in HURST_FIT_LAGS_PX]), 1)[0])
    diam, depth = closed_depressions(z, mask, spacing)
    area_km2 = float(mask.sum()) * spacing**2 / 1e6
    for k in DEPRESSION_SIZES_PX:
        big = diam >= k * spacing
        out[f"pits{int(k * spacing)}_per_1000km2"] = float(big.sum()) * 1000.0 / area_km2
    big = diam >= DEPRESSION_SIZES_PX[0] * spacing
    out["pits400_median_depth_diameter"] = float(np.median(depth[big] / diam[big])) if big.any() else 0.0
    return out


def subdem_band(
    real: np.ndarray,
    ldem: np.ndarray,
    mask: np.ndarray,
    dem_pixel_m: float = 1600.0,
    spacing: float = REAL_CROP_SPACING_M,
) -> tuple[np.ndarray, np.ndarray]:
    """The real terrain's sub-DEM band: (real - LDEM) outside the mask set to 0, mirror-padded to
    twice its size (no wrap-around step), high-passed with the detail's own weights; returned with
    the mask eroded by one DEM pixel (where the filter's reach of masked pixels is negligible)."""
    from scipy import ndimage

    res = np.where(mask, real - ldem, 0.0)
    ny, nx = res.shape
    padded = np.pad(res, ((ny // 2, ny - ny // 2), (nx // 2, nx - nx // 2)), mode="symmetric")
    w = highpass_weights(padded.shape, spacing, dem_pixel_m)
    band = np.fft.irfft2(np.fft.rfft2(padded) * w, s=padded.shape)[ny // 2 : ny // 2 + ny, nx // 2 : nx // 2 + nx]
    reach = round(dem_pixel_m / spacing)
    return band, ndimage.binary_erosion(mask, iterations=reach, border_value=0)


def band_statistics(field: np.ndarray, mask: np.ndarray, spacing: float = REAL_CROP_SPACING_M) -> dict:
    """RMS height, slope and curvature of a sub-DEM band field (detail alone) on ``mask``."""
    s = slopes_deg(field, mask, 1, spacing)
    out = {
        "band_rms_height_m": float(np.sqrt(np.mean(field[mask] ** 2))),
        "band_slope200_rms_deg": float(np.sqrt(np.mean(s**2))),
        "band_slope200_p99_deg": float(np.percentile(s, 99)),
        "band_laplacian200_std_per_km": float(laplacian(field, mask, 1, spacing).std() * 1e3),
    }
    for k in STRUCTURE_LAGS_PX:
        out[f"band_sf{int(k * spacing)}_m"] = structure_function(field, mask, k)
    return out


# --------------------------------------------------------------------------------------------
# Published size-frequency distributions (comparison only)
# --------------------------------------------------------------------------------------------
# Neukum, Ivanov & Hartmann (2001): the production function and chronology of crater_core.procedural.
def neukum_n1(age_ga: float) -> float:
    """N(>=1 km) per km^2 of a surface of age T (Neukum et al. 2001 chronology, Eq. 5)."""
    return float(chronology_n1(age_ga))


def neukum_cumulative(d_km, age_ga: float) -> np.ndarray:
    """Neukum production function N(>=D) per km^2 at age ``age_ga``."""
    return production_cumulative(np.asarray(d_km, dtype=float) * 1000.0, age_ga) * 1e6


def _interior_shadow(z_over_r: np.ndarray, x: np.ndarray, rim: np.ndarray, sun_deg: float) -> np.ndarray:
    """Shadowed share of each crater's rim-to-rim diameter along the Sun's line on level ground.

    ``z_over_r`` (n, X): heights / R along x (units of R, Sun towards -x); ``rim`` (n,): rim crest
    radius / R. A sample is shadowed when z + x tan(e) is below its running maximum from the Sun's side.
    """
    w = z_over_r + x[None, :] * math.tan(math.radians(sun_deg))
    prev = np.maximum.accumulate(np.concatenate([np.full((w.shape[0], 1), -np.inf), w[:, :-1]], 1), axis=1)
    inside = np.abs(x)[None, :] <= rim[:, None]
    return np.sum((w < prev) & inside, axis=1) / np.maximum(np.sum(inside, axis=1), 1)


def population_summary(settings, area_m2: float = 1e10, d_range_m=(400.0, 3200.0), seed: int = 0) -> dict:
    """SFD and degradation state of a drawn crater population (no terrain): densities per km^2,
    d/D percentiles and shares, and how dark the craters are at a low Sun on level ground: the mean
    shadowed share of the diameter along the Sun's line and the share of craters more than 90 %
    shadowed ("black pits"), at 0.5 and 1.6 deg."""

    rng = np.random.default_rng(seed)
    x = np.linspace(-4.0, 4.0, 1601)
    if settings.model == "legacy":
        p = LEGACY_PARAMETERS
        pop = crater_population(area_m2, *d_range_m, p["crater_density_scale"], p["min_depth_diameter"], rng)
        radius = pop["diameter"][:, None] / 2.0
        z = crater_profile(np.abs(x)[None, :], pop["depth"][:, None], pop["rim"][:, None]) / radius
        rim = np.ones(len(pop["diameter"]))
    else:
        pop = degraded_population(area_m2, *d_range_m, settings.crater_density_scale, settings.min_depth_diameter, rng)
        t = degradation_table()
        depth_ratio = 2.0 * pop["fresh_depth"] / pop["diameter"]
        z = degraded_profile(np.abs(x)[None, :], pop["tau_d"][:, None]) * depth_ratio[:, None]
        rim_rows = t.s[np.argmax(t.profile, axis=1)]
        rim = np.maximum(np.interp(pop["tau_d"], t.tau_d, rim_rows), 1.0)
    dd = pop["depth"] / pop["diameter"]
    area_km2 = area_m2 / 1e6
    out = {
        f"N(>={d / 1000:g} km)_per_km2": float(np.sum(pop["diameter"] >= d)) / area_km2 for d in (400.0, 800.0, 1600.0)
    }
    out.update({f"d/D_p{q}": float(np.percentile(dd, q)) for q in (10, 50, 90)})
    out.update(
        {
            "share_d/D<0.05": float(np.mean(dd < 0.05)),
            "share_d/D>0.1": float(np.mean(dd > 0.1)),
            "share_d/D>0.15": float(np.mean(dd > 0.15)),
        }
    )
    for sun in (0.5, 1.6):
        shadow = _interior_shadow(z, x, rim, sun)
        out[f"mean_shadowed_diameter_share_sun{sun:g}"] = float(shadow.mean())
        out[f"share_black_pits_sun{sun:g}"] = float(np.mean(shadow > 0.9))
    return out


# --------------------------------------------------------------------------------------------
# Real vs model
# --------------------------------------------------------------------------------------------
def measure_real(crop: RealCrop | None = None, data_dir: str | Path = DEFAULT_DATA_DIR) -> dict:
    """Measure the real crop (default: the registered ``shackleton_lola_200m``) on its own grid: its
    statistics, its sub-DEM band's statistics, and the LDEM, mask and band on the same grid."""
    crop = load_real_crop(data_dir=data_dir) if crop is None else crop
    dem = _open_ldem(data_dir)
    real, top_left, spacing = crop.heights, crop.top_left_xy_m, crop.spacing_m
    ldem = sample_ldem(dem, top_left, real.shape, spacing)
    mask = background_mask(top_left, real.shape, spacing, dem)
    band, band_mask = subdem_band(real, ldem, mask, dem.pixel_size_m, spacing)
    stats = {**terrain_statistics(real, mask, spacing), **band_statistics(band, band_mask, spacing)}
    return {
        "crop": crop.name,
        "path": str(crop.path),
        "top_left_xy_m": top_left,
        "real": real,
        "ldem": ldem,
        "mask": mask,
        "band_mask": band_mask,
        "stats": stats,
        "residual_rms_m": float(np.std((real - ldem)[mask])),
    }


def model_statistics(ldem: np.ndarray, mask: np.ndarray, band_mask: np.ndarray, settings, seeds=range(4)) -> dict:
    """Mean statistics of LDEM + detail (and of the detail alone, on ``band_mask``) over seeds."""

    runs = []
    for seed in seeds:
        field, _ = synthesize_detail(
            ldem.shape, REAL_CROP_SPACING_M, 1600.0, replace(settings, seed=int(seed)), key="calibration"
        )
        runs.append({**terrain_statistics(ldem + field, mask), **band_statistics(field, band_mask)})
    return {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}


def ldem_only_statistics(ldem: np.ndarray, mask: np.ndarray, band_mask: np.ndarray) -> dict:
    return {**terrain_statistics(ldem, mask), **band_statistics(np.zeros_like(ldem), band_mask)}


# The calibrated parameters: roughness amplitude and crater density fitted to these statistics;
# Hurst exponent (Rosenburg et al. 2011) and the recognition limit d/D (Fassett & Thomson 2014)
# are taken from the literature (docs/detail.md). The pits' depth/diameter is a fit key because the
# other eight leave a ridge (roughness traded for craters at equal misfit) along which it is the
# statistic that moves: roughness makes shallow closed depressions, craters deep ones.
FIT_KEYS = (
    "band_rms_height_m",
    "band_slope200_rms_deg",
    "band_laplacian200_std_per_km",
    "band_sf400_m",
    "band_sf1600_m",
    "laplacian200_std_per_km",
    "pits400_per_1000km2",
    "pits800_per_1000km2",
    "pits400_median_depth_diameter",
)
FIT_GRID = {
    "roughness_rms_slope_deg": (0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5),
    "crater_density_scale": (0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2),
}


def fit_misfit(model: dict, real: dict, keys=FIT_KEYS) -> float:
    """Sum of squared log ratios model / real over ``keys``."""
    return float(sum(math.log(model[k] / real[k]) ** 2 for k in keys))


def fit_parameters(m: dict, seeds=range(4)) -> list[tuple[float, dict]]:
    """Grid search of FIT_GRID (other settings at their defaults); best first."""

    out = []
    names = list(FIT_GRID)
    for values in itertools.product(*FIT_GRID.values()):
        kw = dict(zip(names, values))
        stats = model_statistics(m["ldem"], m["mask"], m["band_mask"], replace(DetailSettings(), **kw), seeds)
        out.append((fit_misfit(stats, m["stats"]), kw))
    return sorted(out, key=lambda t: t[0])


OLD_SETTINGS_KW = {"model": "legacy"}


def comparison_rows(m: dict, seeds=range(4)) -> dict:
    """{name: stats} for real, LDEM only, LDEM + old detail, LDEM + new detail."""

    args = (m["ldem"], m["mask"], m["band_mask"])
    return {
        "real 200 m crop": m["stats"],
        "LDEM 1600 m (bicubic)": ldem_only_statistics(*args),
        "LDEM + old detail": model_statistics(*args, DetailSettings(**OLD_SETTINGS_KW), seeds),
        "LDEM + new detail": model_statistics(*args, DetailSettings(), seeds),
    }


TRANSFER_KEYS = ("band_rms_height_m", "band_slope200_rms_deg", "band_laplacian200_std_per_km")


def grid_transfer_rows(m: dict, factors=(2, 4), seeds=range(4)) -> dict:
    """Sub-DEM band on coarser grids (400, 800 m: the de Gerlache / Shoemaker near grids are 318 and
    499 m): the real crop block-averaged by ``factor`` (what a grid of that spacing can carry) against
    the detail synthesised at that spacing. Keys keep their 200 m names but are per grid step."""

    dem = _open_ldem()
    rows = {}
    for f in factors:
        spacing = REAL_CROP_SPACING_M * f
        real = block_mean(m["real"], f)
        half = (f - 1) * REAL_CROP_SPACING_M / 2.0  # block centres
        top_left = (m["top_left_xy_m"][0] + half, m["top_left_xy_m"][1] - half)
        ldem = sample_ldem(dem, top_left, real.shape, spacing)
        band, band_mask = subdem_band(
            real, ldem, background_mask(top_left, real.shape, spacing, dem), dem.pixel_size_m, spacing
        )
        row = {"real (block average)": band_statistics(band, band_mask, spacing)}
        for name, settings in (("old detail", DetailSettings(**OLD_SETTINGS_KW)), ("new detail", DetailSettings())):
            runs = []
            for seed in seeds:
                field, _ = synthesize_detail(
                    (2 * real.shape[0], 2 * real.shape[1]),
                    spacing,
                    dem.pixel_size_m,
                    replace(settings, seed=int(seed)),
                    key="calibration",
                )
                runs.append(band_statistics(field, np.ones(field.shape, dtype=bool), spacing))
            row[name] = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}
        rows[f"{spacing:g} m"] = row
    return rows


def markdown_table(rows: dict, keys=None) -> str:
    names = list(rows)
    keys = keys or list(rows[names[0]])
    lines = ["| statistic | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for k in keys:
        lines.append(f"| {k} | " + " | ".join(f"{rows[n][k]:.3g}" for n in names) + " |")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Hillshades
# --------------------------------------------------------------------------------------------
SUN_DISC_DEG = 0.53  # apparent diameter of the Sun from the Moon
HILLSHADE_DISC_SAMPLES = 7


def hillshade(z: np.ndarray, spacing: float, sun_elevation_deg: float) -> np.ndarray:
    """Lambert shading times the visible fraction of the solar disc, Sun in the -x direction (left).

    A point is lit by the part of the disc above its horizon: for each of
    ``HILLSHADE_DISC_SAMPLES`` elevations across the 0.53 deg disc, it is lit when
    z + x tan(e) is at least its running maximum from the left (flat plane, no curvature).
    """
    x = np.arange(z.shape[1]) * spacing
    lit = np.zeros_like(z)
    offsets = SUN_DISC_DEG * ((np.arange(HILLSHADE_DISC_SAMPLES) + 0.5) / HILLSHADE_DISC_SAMPLES - 0.5)
    for e in sun_elevation_deg + offsets:
        w = z + x[None, :] * math.tan(math.radians(e))
        prev = np.maximum.accumulate(np.concatenate([np.full((z.shape[0], 1), -np.inf), w[:, :-1]], 1), axis=1)
        lit += w >= prev
    lit /= HILLSHADE_DISC_SAMPLES
    gy, gx = np.gradient(z, spacing)
    e = math.radians(sun_elevation_deg)
    cos_i = (math.sin(e) - math.cos(e) * gx) / np.sqrt(1.0 + gx**2 + gy**2)
    return np.clip(cos_i, 0.0, None) * lit


def write_hillshades(
    fields: dict, out_dir: Path, elevations=(0.5, 1.6, 5.0), spacing=REAL_CROP_SPACING_M
) -> list[Path]:
    """One PNG per sun elevation (panels left to right in ``fields`` order, same grey scale, set by
    the first panel's 99.5th percentile) and one per field; written atomically."""

    out_dir.mkdir(parents=True, exist_ok=True)
    written = []

    def save(img: np.ndarray, path: Path):

        buf = io.BytesIO()
        Image.fromarray((np.clip(img, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)).save(buf, format="PNG")
        atomic_write_bytes(path, buf.getvalue())
        written.append(path)

    for e in elevations:
        shades = {name: hillshade(z, spacing, e) for name, z in fields.items()}
        first = next(iter(shades.values()))
        scale = float(np.percentile(first[first > 0], 99.5)) if (first > 0).any() else 1.0
        gap = np.ones((first.shape[0], 4))
        panels = []
        for name, sh in shades.items():
            save(sh / scale, out_dir / f"detail_{_slug(name)}_sun{e:g}.png")
            panels += [sh / scale, gap]
        save(np.concatenate(panels[:-1], axis=1), out_dir / f"detail_panels_sun{e:g}.png")
    return written


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name.lower()).strip("_").replace("__", "_")
