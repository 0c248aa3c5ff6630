"""Sub-DEM detail: seeded roughness plus small craters, added only below the DEM's resolution.

The offline DEM (1600 m/px) is 4x coarser than the real test images (400 m/px), so the near-field
grid carries terrain the DEM cannot: this module synthesises it. Two models
(``terrain.detail.model``; sources, numbers and the calibration in docs/detail.md):

``calibrated`` (default), fitted to a real LOLA 200 m crop (crater_synth/tools/detail_calibration.py):

1. Roughness: fractional Brownian surface by spectral synthesis (Saupe 1988, in *The Science of
   Fractal Images*), power spectral density ``C |k|^-(2H+2)`` with a *physical* amplitude ``C``:
   the same surface statistics whatever the grid spacing. ``roughness_rms_slope_deg`` fixes ``C``
   as the expected RMS slope over 200 m of the roughness synthesised on the reference grid (200 m
   spacing below a 1600 m DEM), where it was calibrated.
2. Small craters: Poisson positions, diameters from the equilibrium cumulative SFD
   N(>=D) = 10^-1.1 D^-2 per m^2, D in m (Trask 1966; Gault 1970, Radio Sci. 5:273), times
   ``crater_density_scale``. Shape: Pike's (1977) fresh simple crater (parabolic bowl,
   d = 0.196 D^1.010, rim h = 0.036 D^1.014, ejecta ~ (r/R)^-3 to 3 R; McGetchin et al. 1973)
   degraded by linear topographic diffusion (Soderblom 1970, JGR 75:2655; Fassett & Thomson 2014,
   JGR 119:2255), which lowers the rim, widens and shallows the bowl and softens the wall.
   Degradation state: steady-state population (constant production, each crater visible until
   diffusion has brought its d/D down to ``min_depth_diameter``), so the nondimensional diffusion
   time kappa t / D^2 is uniform over each crater's visible lifetime: most small craters are shallow.
3. High-pass, exactly as below.

``legacy``: the pre-calibration model, kept bit for bit for ablations (parameters fixed in
:data:`LEGACY_PARAMETERS`): fBm scaled to 6 deg RMS slope per grid spacing, the equilibrium SFD,
fresh parabolic bowls scaled by a d/D drawn uniformly in [0.05, 0.196].

High-pass (both): the sum is filtered in the Fourier domain so that *all* content at wavelengths
>= 2 p (spatial frequency <= 1/(2 p), the DEM's Nyquist) is removed exactly, with a raised-cosine
ramp up to wavelength p. The DEM keeps sole authority over every scale it resolves.

Deterministic for (seed, key): one :class:`numpy.random.Generator` seeded from both.

Length: one model, kept whole: settings and their validation, the fBm, the crater population
(SFD, diffusion degradation), stamping and the high-pass are the terrain detail and nothing else.
"""

from __future__ import annotations

import functools
import hashlib
import math
from dataclasses import dataclass

import numpy as np

# Pike (1977) fresh simple craters, McGetchin et al. (1973) ejecta and the spectral fBm: one copy, in the core.
from crater_core.procedural import (
    EJECTA_DECAY_EXP,
    EJECTA_EXTENT_RADII,
    PIKE_DEPTH_COEF,
    PIKE_DEPTH_EXP,
    PIKE_RIM_COEF,
    PIKE_RIM_EXP,
    fbm_surface,
    radial_diffusion_operator,
)
from crater_core.procedural import wavenumbers as _wavenumbers
from crater_core.settings import DETAIL_MODELS as MODELS  # noqa: F401 - terrain.detail.model choices, re-exported
from crater_core.settings import DetailSettings, SettingsError

# Equilibrium cumulative SFD, N(>=D) = EQ_COEF * D^-EQ_SLOPE per m^2 with D in m
# (Trask 1966, JPL TR 32-800; Gault 1970, Radio Sci. 5:273); ~5 % of geometric saturation
# (1.54 D^-2, Gault 1970), "a few percent" in Minton et al. 2019, Icarus 326:63.
EQ_COEF = 10.0**-1.1
EQ_SLOPE = 2.0
# Smallest crater drawn, in grid spacings: below ~2 samples across, a bowl is not represented.
MIN_CRATER_SAMPLES = 2.0
# Cap on stamped samples per vectorised batch (memory bound, ~16 MB of float64 per array).
_BATCH_ELEMENTS = 2_000_000

# Reference grid of roughness_rms_slope_deg: where the roughness was calibrated against the real
# 200 m crop (docs/detail.md). The PSD amplitude it implies is used on every grid.
ROUGHNESS_REFERENCE_SPACING_M = 200.0
ROUGHNESS_REFERENCE_DEM_PIXEL_M = 1600.0
ROUGHNESS_REFERENCE_SIZE = 256
# Degraded-crater profiles (topographic diffusion of Pike's fresh shape): radial grid in units of
# the crater radius R, and the stamp extent. Diffusion spreads the ejecta beyond 3 R; up to the
# largest diffusion time allowed (d/D down to MIN_RECOGNITION_DEPTH_DIAMETER) what lies beyond 4 R
# is < 0.2 % of the fresh depth, so stamps are cut at 4 R with a smooth taper from 3.5 R.
DIFFUSION_GRID_STEP_R = 0.02
DIFFUSION_GRID_EXTENT_R = 8.0
DEGRADED_EXTENT_RADII = 4.0
DEGRADED_TAPER_START_RADII = 3.5
# Nondimensional diffusion times kappa t / D^2 tabulated (0 and a geometric ladder).
DIFFUSION_TAU_D_RANGE = (1e-5, 2.0)
DIFFUSION_TAU_D_COUNT = 160
# The allowed range of min_depth_diameter (the most degraded crater drawn) is checked with the other
# terrain.detail settings: crater_core.settings.MIN/MAX_RECOGNITION_DEPTH_DIAMETER.

# The pre-calibration model (kept for ablations; docs/detail.md "old").
LEGACY_PARAMETERS = {
    "hurst": 0.8,
    "rms_slope_deg": 6.0,
    "crater_density_scale": 1.0,
    "min_crater_diameter_m": 300.0,
    "min_depth_diameter": 0.05,
}


# ``terrain.detail`` settings and their validation live with every other setting (one source of truth).
DetailConfigError = SettingsError


# --------------------------------------------------------------------------------------------
# Spectral helpers
# --------------------------------------------------------------------------------------------
def _rng(seed: int, key: str) -> np.random.Generator:
    key_int = int.from_bytes(hashlib.sha256(key.encode()).digest()[:8], "little")
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFFFFFFFFFF, key_int]))


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


def _unit_psd_amplitude(shape: tuple[int, int], spacing_m: float, hurst: float) -> np.ndarray:
    """rfft2 filter turning unit white noise into a surface of PSD |k|^-(2H+2) (m^4, k in cycles/m).

    With numpy's unnormalised DFT, white noise of unit variance has E|n_k|^2 = N M, and the
    filtered field's variance is (1 / N M) sum |A_k|^2, while a PSD P gives sum P dkx dky with
    dk = 1 / (N ds): hence A = sqrt(P) / ds.
    """
    k = _wavenumbers(shape, spacing_m)
    amp = np.zeros_like(k)
    amp[k > 0] = k[k > 0] ** -(hurst + 1.0) / spacing_m
    return amp


@functools.lru_cache(maxsize=64)
def roughness_psd_coefficient(rms_slope_deg: float, hurst: float) -> float:
    """PSD amplitude C (m^(-2H) ...) such that C |k|^-(2H+2), high-passed below a 1600 m DEM and
    sampled at 200 m, has the expected RMS slope ``rms_slope_deg`` over one 200 m step.

    Exact expectation over the reference grid's modes (no random draw): a forward difference over
    one step multiplies mode k by |exp(2 pi i k ds) - 1|^2 = 4 sin^2(pi k ds).
    """
    if rms_slope_deg <= 0.0:
        return 0.0
    n, ds = ROUGHNESS_REFERENCE_SIZE, ROUGHNESS_REFERENCE_SPACING_M
    ky = np.fft.fftfreq(n, d=ds)[:, None]
    kx = np.fft.fftfreq(n, d=ds)[None, :]
    k = np.hypot(ky, kx)
    k_cut = 1.0 / (2.0 * ROUGHNESS_REFERENCE_DEM_PIXEL_M)
    w = np.where(k <= k_cut, 0.0, 0.5 - 0.5 * np.cos(np.pi * np.clip((k - k_cut) / k_cut, 0.0, 1.0)))
    psd = np.zeros_like(k)
    psd[k > 0] = k[k > 0] ** -(2.0 * hurst + 2.0)
    diff = 4.0 * (np.sin(np.pi * kx * ds) ** 2 + np.sin(np.pi * ky * ds) ** 2) / ds**2
    mean_sq_slope = float(np.sum(psd * w**2 * diff)) / (n * ds) ** 2
    return math.tan(math.radians(rms_slope_deg)) ** 2 / mean_sq_slope


def roughness_surface(
    shape: tuple[int, int],
    spacing_m: float,
    hurst: float,
    psd_coef: float,
    weights: np.ndarray,
    rng: np.random.Generator,
) -> np.ndarray:
    """High-passed fBm of PSD ``psd_coef |k|^-(2H+2)``: physical amplitude, any grid spacing."""
    noise = rng.standard_normal(shape)
    amp = _unit_psd_amplitude(shape, spacing_m, hurst) * math.sqrt(psd_coef) * weights
    return np.fft.irfft2(np.fft.rfft2(noise) * amp, s=shape)


# --------------------------------------------------------------------------------------------
# Crater shapes
# --------------------------------------------------------------------------------------------
def fresh_depth_m(diameter_m: np.ndarray) -> np.ndarray:
    """Pike (1977) fresh rim-to-floor depth (m) of a simple crater of diameter D (m)."""
    return PIKE_DEPTH_COEF * (np.asarray(diameter_m) / 1000.0) ** PIKE_DEPTH_EXP * 1000.0


def fresh_rim_m(diameter_m: np.ndarray) -> np.ndarray:
    """Pike (1977) fresh rim height (m) above the surroundings."""
    return PIKE_RIM_COEF * (np.asarray(diameter_m) / 1000.0) ** PIKE_RIM_EXP * 1000.0


def crater_profile(s: np.ndarray, depth_m: np.ndarray, rim_m: np.ndarray) -> np.ndarray:
    """Fresh-shape height relative to the pre-impact surface at normalised radius s = r / R.

    Bowl: rim - depth * (1 - s^2) for s <= 1 (floor at rim - depth, rim crest at s = 1).
    Ejecta: rim * (s^-3 - S^-3) / (1 - S^-3) for 1 < s <= S (continuous at the rim, 0 at S = 3).
    """
    s_max = EJECTA_EXTENT_RADII
    tail = s_max**-EJECTA_DECAY_EXP
    inside = rim_m - depth_m * (1.0 - s**2)
    outside = rim_m * (np.maximum(s, 1.0) ** -EJECTA_DECAY_EXP - tail) / (1.0 - tail)
    return np.where(s <= 1.0, inside, np.where(s <= s_max, outside, 0.0))


@dataclass(frozen=True)
class DegradationTable:
    """Pike's fresh profile (unit depth) diffused for nondimensional times tau_D = kappa t / D^2."""

    tau_d: np.ndarray  # (T,) ascending, tau_d[0] = 0
    s: np.ndarray  # (S,) radial samples, units of R, from 0
    profile: np.ndarray  # (T, S) height / fresh depth, tapered to 0 at DEGRADED_EXTENT_RADII
    depth_ratio: np.ndarray  # (T,) rim-to-floor depth / fresh depth (1 at tau 0, decreasing)
    max_wall_slope: np.ndarray  # (T,) steepest inner-wall gradient, per unit (fresh depth / R)


@functools.lru_cache(maxsize=1)
def degradation_table() -> DegradationTable:
    """Diffuse Pike's fresh crater exactly in time: dh/dt = kappa (1/r) d/dr (r dh/dr).

    Finite volumes on cells of width ``DIFFUSION_GRID_STEP_R`` out to ``DIFFUSION_GRID_EXTENT_R``
    (no flux at the centre or the far edge), M dh/dt = K h with M = diag(cell areas) and K the
    symmetric face-flux matrix. The symmetric tridiagonal M^-1/2 K M^-1/2 = U diag(lam) U^T gives
    h(tau) = M^-1/2 U exp(lam tau) U^T M^1/2 h0 for every tabulated time at once (no stepping error).
    Time in units of R^2 / kappa: tau_R = 4 tau_D.
    """
    from scipy.linalg import eigh_tridiagonal

    ds = DIFFUSION_GRID_STEP_R
    s, root, diag, off = radial_diffusion_operator(round(DIFFUSION_GRID_EXTENT_R / ds), ds)
    lam, u = eigh_tridiagonal(diag, off)
    rim_ratio = PIKE_RIM_COEF / PIKE_DEPTH_COEF
    h0 = crater_profile(s, 1.0, rim_ratio)
    coef = u.T @ (root * h0)
    tau_d = np.concatenate([[0.0], np.geomspace(*DIFFUSION_TAU_D_RANGE, DIFFUSION_TAU_D_COUNT - 1)])
    prof = ((np.exp(np.outer(4.0 * tau_d, lam)) * coef) @ u.T) / root  # (T, S)
    # Tabulate on a radial grid starting at s = 0 (the cell-centred solution, extended by symmetry).
    s_tab = np.arange(0.0, DEGRADED_EXTENT_RADII + 1e-9, ds / 2.0)
    table = np.stack([np.interp(s_tab, np.concatenate([[-s[0]], s]), np.concatenate([[p[0]], p])) for p in prof])
    table[0] = crater_profile(s_tab, 1.0, rim_ratio)  # the fresh shape exactly (sharp rim)
    depth_ratio = table.max(axis=1) - table[:, 0]
    slope = np.diff(table, axis=1) / (s_tab[1] - s_tab[0])
    inner = s_tab[1:] <= np.maximum(1.0, s_tab[np.argmax(table, axis=1)])[:, None]
    max_wall_slope = np.where(inner, slope, 0.0).max(axis=1)
    taper = np.clip((DEGRADED_EXTENT_RADII - s_tab) / (DEGRADED_EXTENT_RADII - DEGRADED_TAPER_START_RADII), 0, 1)
    table *= 0.5 - 0.5 * np.cos(np.pi * taper)
    return DegradationTable(
        tau_d=tau_d,
        s=s_tab,
        profile=table,
        depth_ratio=np.minimum.accumulate(depth_ratio),
        max_wall_slope=max_wall_slope,
    )


def depth_ratio_after_diffusion(tau_d) -> np.ndarray:
    """Rim-to-floor depth / fresh depth after nondimensional diffusion time kappa t / D^2."""
    t = degradation_table()
    return np.interp(np.asarray(tau_d, dtype=float), t.tau_d, t.depth_ratio)


def diffusion_time_for_depth_ratio(ratio) -> np.ndarray:
    """kappa t / D^2 at which diffusion has reduced the depth to ``ratio`` x fresh (0 < ratio <= 1)."""
    t = degradation_table()
    ratio = np.asarray(ratio, dtype=float)
    if np.any(ratio < t.depth_ratio[-1]) or np.any(ratio > 1.0):
        raise ValueError(f"depth ratio must lie in [{t.depth_ratio[-1]:.4f}, 1]")
    return np.interp(-ratio, -t.depth_ratio, t.tau_d)


def degraded_profile(s: np.ndarray, tau_d: np.ndarray) -> np.ndarray:
    """Height / fresh depth at normalised radius s of a crater diffused for kappa t / D^2 = tau_d
    (broadcast together; bilinear in (tau, s) over the table, 0 beyond DEGRADED_EXTENT_RADII)."""
    from scipy.ndimage import map_coordinates

    t = degradation_table()
    ti = np.interp(np.asarray(tau_d, dtype=float), t.tau_d, np.arange(t.tau_d.size))
    si = np.asarray(s, dtype=float) / (t.s[1] - t.s[0])
    ti, si = np.broadcast_arrays(ti, si)
    out = map_coordinates(t.profile, [ti.ravel(), si.ravel()], order=1, mode="nearest").reshape(si.shape)
    return np.where(si <= t.s.size - 1, out, 0.0)


# --------------------------------------------------------------------------------------------
# Populations
# --------------------------------------------------------------------------------------------
def _draw_diameters(
    area_m2: float, d_min: float, d_max: float, density_scale: float, rng: np.random.Generator
) -> np.ndarray:
    """Poisson number, then inverse-CDF diameters of the truncated equilibrium power law."""
    expected = density_scale * area_m2 * EQ_COEF * (d_min**-EQ_SLOPE - d_max**-EQ_SLOPE)
    n = int(rng.poisson(expected))
    u = rng.random(n)
    return (d_min**-EQ_SLOPE - u * (d_min**-EQ_SLOPE - d_max**-EQ_SLOPE)) ** (-1.0 / EQ_SLOPE)


def crater_population(
    area_m2: float,
    d_min: float,
    d_max: float,
    density_scale: float,
    min_depth_diameter: float,
    rng: np.random.Generator,
) -> dict[str, np.ndarray]:
    """Legacy model: diameters, depths and rim heights (m); d/D uniform in [min, fresh]."""
    if d_max <= d_min or density_scale <= 0.0:
        z = np.zeros(0)
        return {"diameter": z, "depth": z, "rim": z}
    diam = _draw_diameters(area_m2, d_min, d_max, density_scale, rng)
    n = diam.size
    # Degradation: depth/diameter uniform between min_depth_diameter and fresh; rim scales alike.
    keep = rng.uniform(min_depth_diameter / PIKE_DEPTH_COEF, 1.0, n)
    return {"diameter": diam, "depth": fresh_depth_m(diam) * keep, "rim": fresh_rim_m(diam) * keep}


def degraded_population(
    area_m2: float,
    d_min: float,
    d_max: float,
    density_scale: float,
    min_depth_diameter: float,
    rng: np.random.Generator,
) -> dict[str, np.ndarray]:
    """Calibrated model: equilibrium SFD, steady-state diffusive degradation.

    Each crater's nondimensional diffusion time tau_D = kappa t / D^2 is uniform in [0, tau_vis]:
    with constant production the ages of the craters still visible are uniform over their visible
    lifetime, which ends when d/D reaches ``min_depth_diameter`` (Soderblom 1970). Returns diameter,
    tau_d, fresh_depth (m) and depth (m, rim crest to floor after diffusion).
    """
    if d_max <= d_min or density_scale <= 0.0:
        z = np.zeros(0)
        return {"diameter": z, "tau_d": z, "fresh_depth": z, "depth": z}
    diam = _draw_diameters(area_m2, d_min, d_max, density_scale, rng)
    fresh = fresh_depth_m(diam)
    ratio_vis = np.clip(min_depth_diameter * diam / np.maximum(fresh, 1e-12), None, 1.0)
    tau_vis = diffusion_time_for_depth_ratio(ratio_vis)
    tau = rng.random(diam.size) * tau_vis
    return {"diameter": diam, "tau_d": tau, "fresh_depth": fresh, "depth": fresh * depth_ratio_after_diffusion(tau)}


def _stamp(
    shape: tuple[int, int],
    spacing_m: float,
    centres_px: np.ndarray,
    diameters_m: np.ndarray,
    extent_radii: float,
    heights,
) -> np.ndarray:
    """Sum of per-crater height functions on a periodic grid (vectorised per stamp-size batch).

    ``heights(s, idx)``: heights (m) at normalised radii s (n, k, k) of the craters ``idx`` (n,).
    """
    ny, nx = shape
    out = np.zeros(ny * nx)
    if len(diameters_m) == 0:
        return out.reshape(shape)
    half_px = np.ceil(extent_radii * 0.5 * diameters_m / spacing_m).astype(int)
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
            z = heights(s, chunk)
            idx = (iy % ny) * nx + (ix % nx)
            out += np.bincount(idx.ravel(), weights=z.ravel(), minlength=ny * nx)
    return out.reshape(shape)


def stamp_craters(
    shape: tuple[int, int],
    spacing_m: float,
    centres_px: np.ndarray,
    diameters_m: np.ndarray,
    depths_m: np.ndarray,
    rims_m: np.ndarray,
) -> np.ndarray:
    """Sum of fresh-shape (legacy) crater profiles on a periodic grid."""
    return _stamp(
        shape,
        spacing_m,
        centres_px,
        diameters_m,
        EJECTA_EXTENT_RADII,
        lambda s, i: crater_profile(s, depths_m[i][:, None, None], rims_m[i][:, None, None]),
    )


def stamp_degraded_craters(
    shape: tuple[int, int],
    spacing_m: float,
    centres_px: np.ndarray,
    diameters_m: np.ndarray,
    fresh_depths_m: np.ndarray,
    tau_d: np.ndarray,
) -> np.ndarray:
    """Sum of diffusion-degraded crater profiles on a periodic grid."""
    return _stamp(
        shape,
        spacing_m,
        centres_px,
        diameters_m,
        DEGRADED_EXTENT_RADII,
        lambda s, i: fresh_depths_m[i][:, None, None] * degraded_profile(s, tau_d[i][:, None, None]),
    )


# --------------------------------------------------------------------------------------------
# Synthesis
# --------------------------------------------------------------------------------------------
def _synthesize_legacy(shape, spacing_m, dem_pixel_m, seed, key, hp):
    p = LEGACY_PARAMETERS
    ny, nx = shape
    rng = _rng(seed, key)
    rough = hp(fbm_surface((ny, nx), spacing_m, p["hurst"], rng))
    slope = _rms_slope(rough, spacing_m)
    rough *= math.tan(math.radians(p["rms_slope_deg"])) / slope if slope > 0 else 0.0
    d_min = max(p["min_crater_diameter_m"], MIN_CRATER_SAMPLES * spacing_m)
    d_max = 2.0 * dem_pixel_m
    pop = crater_population(
        ny * nx * spacing_m**2, d_min, d_max, p["crater_density_scale"], p["min_depth_diameter"], rng
    )
    n = len(pop["diameter"])
    centres = np.column_stack([rng.uniform(0, ny, n), rng.uniform(0, nx, n)]) if n else np.zeros((0, 2))
    craters = hp(stamp_craters((ny, nx), spacing_m, centres, pop["diameter"], pop["depth"], pop["rim"]))
    return rough, craters, pop, (d_min, d_max)


def _synthesize_calibrated(shape, spacing_m, dem_pixel_m, s: DetailSettings, key, weights, hp):
    ny, nx = shape
    rng = _rng(s.seed, key)
    rough = np.zeros((ny, nx))
    if s.roughness_rms_slope_deg > 0.0:
        coef = roughness_psd_coefficient(float(s.roughness_rms_slope_deg), float(s.hurst))
        rough = roughness_surface((ny, nx), spacing_m, s.hurst, coef, weights, rng)
    d_min = max(s.min_crater_diameter_m, MIN_CRATER_SAMPLES * spacing_m)
    d_max = 2.0 * dem_pixel_m
    pop = degraded_population(ny * nx * spacing_m**2, d_min, d_max, s.crater_density_scale, s.min_depth_diameter, rng)
    n = len(pop["diameter"])
    centres = np.column_stack([rng.uniform(0, ny, n), rng.uniform(0, nx, n)]) if n else np.zeros((0, 2))
    craters = hp(
        stamp_degraded_craters((ny, nx), spacing_m, centres, pop["diameter"], pop["fresh_depth"], pop["tau_d"])
    )
    return rough, craters, pop, (d_min, d_max)


def synthesize_detail(
    shape: tuple[int, int], spacing_m: float, dem_pixel_m: float, settings: DetailSettings, key: str = ""
) -> tuple[np.ndarray, dict]:
    """Sub-DEM height detail (m) on a regular grid of ``shape`` and ``spacing_m``.

    Returns (field, stats). The field is zero when detail is disabled or the grid cannot represent
    anything finer than the DEM (spacing >= DEM pixel). ``key`` (e.g. the crater name) varies the
    draw between patches for the same seed.
    """
    ny, nx = (int(v) for v in shape)
    stats = {
        "enabled": bool(settings.enabled),
        "active": False,
        "model": settings.model,
        "cutoff_wavelength_m": 2.0 * dem_pixel_m,
        "n_craters": 0,
        "rms_height_m": 0.0,
        "rms_slope_deg": 0.0,
        "settings": settings.as_dict(),
    }
    if not settings.enabled:
        return np.zeros((ny, nx)), stats
    if spacing_m >= dem_pixel_m:
        stats["reason"] = "grid spacing >= DEM pixel: no sub-DEM band to fill"
        return np.zeros((ny, nx)), stats
    weights = highpass_weights((ny, nx), spacing_m, dem_pixel_m)

    def hp(f: np.ndarray) -> np.ndarray:
        return np.fft.irfft2(np.fft.rfft2(f) * weights, s=(ny, nx))

    if settings.model == "legacy":
        rough, craters, pop, (d_min, d_max) = _synthesize_legacy(
            (ny, nx), spacing_m, dem_pixel_m, settings.seed, key, hp
        )
    else:
        rough, craters, pop, (d_min, d_max) = _synthesize_calibrated(
            (ny, nx), spacing_m, dem_pixel_m, settings, key, weights, hp
        )
    field = rough + craters
    n = len(pop["diameter"])
    d_over_d = pop["depth"] / pop["diameter"] if n else np.zeros(0)
    stats.update(
        active=True,
        n_craters=n,
        crater_diameter_range_m=[d_min, d_max],
        crater_depth_diameter_percentiles={
            str(q): float(np.percentile(d_over_d, q)) if n else 0.0 for q in (10, 50, 90)
        },
        rms_height_m=float(np.sqrt(np.mean(field**2))),
        rms_slope_deg=float(math.degrees(math.atan(_rms_slope(field, spacing_m)))),
        roughness_rms_slope_deg=float(math.degrees(math.atan(_rms_slope(rough, spacing_m)))),
    )
    return field, stats
