"""Sub-DEM detail: seeded fractal roughness plus small craters, added only below the DEM's resolution.

The offline DEM (1600 m/px) is 4x coarser than the real test images (400 m/px), so the near-field
grid carries terrain the DEM cannot: this module synthesises it (model and sources in
docs/terrain.md).

Model, on the regular near-field grid (spacing ``ds``), periodic in both directions:

1. Roughness: fractional Brownian surface by spectral synthesis (Saupe 1988, in *The Science of
   Fractal Images*; Mandelbrot & Van Ness 1968): white Gaussian noise filtered by
   ``|k|^-(H+1)`` (power spectrum ``|k|^-(2H+2)``), Hurst exponent ``H``. Lunar topography is
   self-affine over metres to kilometres with H ~ 0.75-0.95 (Rosenburg et al. 2011, JGR 116,
   E02001). Scaled so the added field's RMS slope over one grid spacing is ``rms_slope_deg``.
2. Small craters: positions uniform (Poisson), diameters from the empirical equilibrium
   cumulative size-frequency distribution N(>=D) = 10^-1.1 D^-2 per m^2, D in m (Trask 1966;
   Gault 1970, Radio Sci. 5:273), times ``crater_density_scale``, for
   ``max(min_crater_diameter_m, 2 ds) <= D <= 2 p`` (p = DEM pixel: larger craters are in the DEM).
   Shape: parabolic bowl with Pike's (1977) fresh simple-crater depth d = 0.196 D^1.010 and rim
   height h = 0.036 D^1.014 (D, d, h in km), and an ejecta blanket decaying as (r/R)^-3
   (McGetchin, Settle & Head 1973, EPSL 20:226) to 3 R. Each crater's degradation is drawn
   uniformly between fresh (d/D = 0.196) and ``min_depth_diameter`` (equilibrium populations
   span fresh to very subdued craters; Soderblom 1970, JGR 75:2655; Basilevsky 1976, Proc. LSC 7).
3. High-pass: the sum is filtered in the Fourier domain so that *all* content at wavelengths
   >= 2 p (spatial frequency <= 1/(2 p), the DEM's Nyquist) is removed exactly, with a raised-cosine
   ramp up to wavelength p. The DEM keeps sole authority over every scale it resolves.

Deterministic for (seed, key): one :class:`numpy.random.Generator` seeded from both.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np

from crater_core.settings import FRESH_DEPTH_DIAMETER, DetailSettings, SettingsError

# Pike (1977), "Size-dependence in the shape of fresh impact craters on the Moon", in Impact and
# Explosion Cratering, 489-509: fresh simple craters, D/d/h in km.
PIKE_DEPTH_COEF, PIKE_DEPTH_EXP = FRESH_DEPTH_DIAMETER, 1.010
PIKE_RIM_COEF, PIKE_RIM_EXP = 0.036, 1.014
# McGetchin, Settle & Head (1973), EPSL 20:226: ejecta thickness ~ (r/R)^-3 outside the rim.
EJECTA_DECAY_EXP = 3.0
EJECTA_EXTENT_RADII = 3.0  # blanket truncated (smoothly) at 3 crater radii
# Equilibrium cumulative SFD, N(>=D) = EQ_COEF * D^-EQ_SLOPE per m^2 with D in m
# (Trask 1966, JPL TR 32-800; Gault 1970, Radio Sci. 5:273).
EQ_COEF = 10.0 ** -1.1
EQ_SLOPE = 2.0
# Smallest crater drawn, in grid spacings: below ~2 samples across, a bowl is not represented.
MIN_CRATER_SAMPLES = 2.0
# Cap on stamped samples per vectorised batch (memory bound, ~16 MB of float64 per array).
_BATCH_ELEMENTS = 2_000_000


# ``terrain.detail`` settings and their validation live with every other setting (one source of truth).
DetailConfigError = SettingsError


def _rng(seed: int, key: str) -> np.random.Generator:
    key_int = int.from_bytes(hashlib.sha256(key.encode()).digest()[:8], "little")
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFFFFFFFFFF, key_int]))


def _wavenumbers(shape: tuple[int, int], spacing_m: float) -> np.ndarray:
    """|k| (cycles per metre) on the rfft2 grid of ``shape``."""
    ky = np.fft.fftfreq(shape[0], d=spacing_m)[:, None]
    kx = np.fft.rfftfreq(shape[1], d=spacing_m)[None, :]
    return np.hypot(ky, kx)


def highpass_weights(shape: tuple[int, int], spacing_m: float, dem_pixel_m: float) -> np.ndarray:
    """rfft2 weights: 0 for wavelengths >= 2 p, raised-cosine to 1 at wavelength p, 1 beyond."""
    k = _wavenumbers(shape, spacing_m)
    k_cut = 1.0 / (2.0 * dem_pixel_m)  # DEM Nyquist
    t = np.clip((k - k_cut) / k_cut, 0.0, 1.0)  # 0 at 1/(2p), 1 at 1/p
    w = 0.5 - 0.5 * np.cos(np.pi * t)
    w[k <= k_cut] = 0.0
    return w


def lowpass(field: np.ndarray, spacing_m: float, dem_pixel_m: float) -> np.ndarray:
    """Content of ``field`` at wavelengths >= 2 p (ideal low-pass at the DEM's Nyquist)."""
    k = _wavenumbers(field.shape, spacing_m)
    return np.fft.irfft2(np.fft.rfft2(field) * (k <= 1.0 / (2.0 * dem_pixel_m)), s=field.shape)


def _rms_slope(field: np.ndarray, spacing_m: float) -> float:
    """RMS gradient magnitude over one grid spacing (periodic forward differences)."""
    gx = (np.roll(field, -1, axis=1) - field) / spacing_m
    gy = (np.roll(field, -1, axis=0) - field) / spacing_m
    return float(np.sqrt(np.mean(gx**2 + gy**2)))


def fbm_surface(shape: tuple[int, int], spacing_m: float, hurst: float, rng: np.random.Generator) -> np.ndarray:
    """Zero-mean periodic fractional Brownian surface (arbitrary amplitude), spectral synthesis."""
    k = _wavenumbers(shape, spacing_m)
    amp = np.zeros_like(k)
    amp[k > 0] = k[k > 0] ** -(hurst + 1.0)
    noise = rng.standard_normal(shape)
    return np.fft.irfft2(np.fft.rfft2(noise) * amp, s=shape)


def crater_profile(s: np.ndarray, depth_m: np.ndarray, rim_m: np.ndarray) -> np.ndarray:
    """Height relative to the pre-impact surface at normalised radius s = r / R.

    Bowl: rim - depth * (1 - s^2) for s <= 1 (floor at rim - depth, rim crest at s = 1).
    Ejecta: rim * (s^-3 - S^-3) / (1 - S^-3) for 1 < s <= S (continuous at the rim, 0 at S = 3).
    """
    s_max = EJECTA_EXTENT_RADII
    tail = s_max**-EJECTA_DECAY_EXP
    inside = rim_m - depth_m * (1.0 - s**2)
    outside = rim_m * (np.maximum(s, 1.0) ** -EJECTA_DECAY_EXP - tail) / (1.0 - tail)
    return np.where(s <= 1.0, inside, np.where(s <= s_max, outside, 0.0))


def crater_population(area_m2: float, d_min: float, d_max: float, density_scale: float,
                      min_depth_diameter: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Diameters, depths and rim heights (m) of a Poisson draw from the equilibrium SFD."""
    if d_max <= d_min or density_scale <= 0.0:
        z = np.zeros(0)
        return {"diameter": z, "depth": z, "rim": z}
    expected = density_scale * area_m2 * EQ_COEF * (d_min**-EQ_SLOPE - d_max**-EQ_SLOPE)
    n = int(rng.poisson(expected))
    u = rng.random(n)
    # Inverse CDF of the truncated power law N(>=D) ~ D^-b on [d_min, d_max].
    diam = (d_min**-EQ_SLOPE - u * (d_min**-EQ_SLOPE - d_max**-EQ_SLOPE)) ** (-1.0 / EQ_SLOPE)
    d_km = diam / 1000.0
    fresh_depth = PIKE_DEPTH_COEF * d_km**PIKE_DEPTH_EXP * 1000.0
    fresh_rim = PIKE_RIM_COEF * d_km**PIKE_RIM_EXP * 1000.0
    # Degradation: depth/diameter uniform between min_depth_diameter and fresh; rim scales alike.
    keep = rng.uniform(min_depth_diameter / PIKE_DEPTH_COEF, 1.0, n)
    return {"diameter": diam, "depth": fresh_depth * keep, "rim": fresh_rim * keep}


def stamp_craters(shape: tuple[int, int], spacing_m: float, centres_px: np.ndarray, diameters_m: np.ndarray,
                  depths_m: np.ndarray, rims_m: np.ndarray) -> np.ndarray:
    """Sum of crater profiles on a periodic grid (vectorised per stamp-size batch)."""
    ny, nx = shape
    out = np.zeros(ny * nx)
    if len(diameters_m) == 0:
        return out.reshape(shape)
    half_px = np.ceil(EJECTA_EXTENT_RADII * 0.5 * diameters_m / spacing_m).astype(int)
    half_px = np.minimum(half_px, max(ny, nx) // 2)
    for k in np.unique(half_px):
        sel = np.flatnonzero(half_px == k)
        offs = np.arange(-k, k + 1)
        oy, ox = np.meshgrid(offs, offs, indexing="ij")
        per = oy.size
        for chunk in np.array_split(sel, max(1, math.ceil(len(sel) * per / _BATCH_ELEMENTS))):
            cy, cx = centres_px[chunk, 0], centres_px[chunk, 1]
            iy = np.floor(cy).astype(int)[:, None, None] + oy
            ix = np.floor(cx).astype(int)[:, None, None] + ox
            r_m = np.hypot(iy - cy[:, None, None], ix - cx[:, None, None]) * spacing_m
            s = r_m / (0.5 * diameters_m[chunk])[:, None, None]
            z = crater_profile(s, depths_m[chunk][:, None, None], rims_m[chunk][:, None, None])
            idx = (iy % ny) * nx + (ix % nx)
            out += np.bincount(idx.ravel(), weights=z.ravel(), minlength=ny * nx)
    return out.reshape(shape)


def synthesize_detail(shape: tuple[int, int], spacing_m: float, dem_pixel_m: float,
                      settings: DetailSettings, key: str = "") -> tuple[np.ndarray, dict]:
    """Sub-DEM height detail (m) on a regular grid of ``shape`` and ``spacing_m``.

    Returns (field, stats). The field is zero when detail is disabled or the grid cannot represent
    anything finer than the DEM (spacing >= DEM pixel). ``key`` (e.g. the crater name) varies the
    draw between patches for the same seed.
    """
    ny, nx = (int(v) for v in shape)
    stats = {"enabled": bool(settings.enabled), "active": False, "cutoff_wavelength_m": 2.0 * dem_pixel_m,
             "n_craters": 0, "rms_height_m": 0.0, "rms_slope_deg": 0.0, "settings": settings.as_dict()}
    if not settings.enabled:
        return np.zeros((ny, nx)), stats
    if spacing_m >= dem_pixel_m:
        stats["reason"] = "grid spacing >= DEM pixel: no sub-DEM band to fill"
        return np.zeros((ny, nx)), stats
    rng = _rng(settings.seed, key)
    weights = highpass_weights((ny, nx), spacing_m, dem_pixel_m)

    def hp(f: np.ndarray) -> np.ndarray:
        return np.fft.irfft2(np.fft.rfft2(f) * weights, s=(ny, nx))

    rough = np.zeros((ny, nx))
    if settings.rms_slope_deg > 0.0:
        rough = hp(fbm_surface((ny, nx), spacing_m, settings.hurst, rng))
        slope = _rms_slope(rough, spacing_m)
        rough *= math.tan(math.radians(settings.rms_slope_deg)) / slope if slope > 0 else 0.0

    d_min = max(settings.min_crater_diameter_m, MIN_CRATER_SAMPLES * spacing_m)
    d_max = 2.0 * dem_pixel_m
    pop = crater_population(ny * nx * spacing_m**2, d_min, d_max, settings.crater_density_scale,
                            settings.min_depth_diameter, rng)
    n = len(pop["diameter"])
    centres = np.column_stack([rng.uniform(0, ny, n), rng.uniform(0, nx, n)]) if n else np.zeros((0, 2))
    craters = hp(stamp_craters((ny, nx), spacing_m, centres, pop["diameter"], pop["depth"], pop["rim"]))

    field = rough + craters
    stats.update(active=True, n_craters=n, crater_diameter_range_m=[d_min, d_max],
                 rms_height_m=float(np.sqrt(np.mean(field**2))),
                 rms_slope_deg=float(math.degrees(math.atan(_rms_slope(field, spacing_m)))),
                 roughness_rms_slope_deg=float(math.degrees(math.atan(_rms_slope(rough, spacing_m)))))
    return field, stats
