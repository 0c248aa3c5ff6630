"""Procedural lunar terrain: a crater field on fractal ground, with the exact list of craters placed.

From a seed and :class:`~crater_core.settings_procedural.ProceduralSettings`, :func:`generate` returns a
height grid (metres, row i <-> y = i * spacing, column j <-> x = j * spacing) and every crater it holds
(docs/procedural.md has the relations, their sources and the figures):

1. Ground: fractional Brownian surface by spectral synthesis (Saupe 1988), scaled to an RMS slope
   over a 100 m baseline (the same surface statistics at any grid spacing).
2. Population: primaries from the Neukum (2001) lunar production function, their count set by the
   surface age through the Neukum chronology; their formation ages drawn from the same chronology.
   Secondaries: steep-SFD clusters along rays around the primaries big enough to throw them.
3. Morphometry (Pike 1977 and others): simple parabolic bowls, transitional, complex craters with
   flat floors, wall terraces and central peaks; ejecta ~ (r/R)^-3 (McGetchin et al. 1973).
4. Degradation: each crater's radial profile diffused for its own kappa t / D^2 (Soderblom 1970;
   Fassett & Thomson 2014), exactly (eigen-decomposition of the radial diffusion operator).
5. Emplacement oldest first: a crater excavates the surface it lands on (the inherited relief fades
   to nothing at its centre), so later craters overprint earlier ones; each crater's
   ``visible_rim_fraction`` says how much of its rim no later crater's interior covers.

The labels are the geometry used to build the grid: a fresh isolated crater's rim crest lies at D/2
and its rim-to-floor depth is the Pike depth (tests/test_procedural.py). numpy and stdlib only.

Length: one generator, kept whole: the constants with their sources, the production function, the
morphometry, the degradation, the population and the emplacement are read together to check that
every label is the geometry built; the spectral fBm is the one copy the sub-DEM detail imports too.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from crater_core.settings import FRESH_DEPTH_DIAMETER, DetailSettings
from crater_core.settings_procedural import ProceduralSettings

# --------------------------------------------------------------------------------------------
# Constants and their sources (docs/procedural.md)
# --------------------------------------------------------------------------------------------
# Pike (1977), "Size-dependence in the shape of fresh impact craters on the Moon", Impact and
# Explosion Cratering 489-509; D, d, h in km. Fresh simple craters:
PIKE_DEPTH_COEF, PIKE_DEPTH_EXP = FRESH_DEPTH_DIAMETER, 1.010
PIKE_RIM_COEF, PIKE_RIM_EXP = 0.036, 1.014
# Fresh complex craters (Pike 1977): depth, rim height and floor diameter.
PIKE_COMPLEX_DEPTH_COEF, PIKE_COMPLEX_DEPTH_EXP = 1.044, 0.301
PIKE_COMPLEX_RIM_COEF, PIKE_COMPLEX_RIM_EXP = 0.236, 0.399
PIKE_FLOOR_COEF, PIKE_FLOOR_EXP = 0.187, 1.249
FLOOR_MAX_FRACTION = 0.7  # the floor law, extrapolated, would reach the rim near 800 km
# Simple-to-complex transition on the Moon (Pike 1980, USGS PP 1046-C; Pike 1977's d/D inflection at
# 10-15 km): simple below 15 km, complex from 20 km, transitional (log-interpolated) in between.
TRANSITION_KM = (15.0, 20.0)
# Central peak height above the floor, h_cp = 0.0006 D^1.969 km (Hale & Grieve 1982, LPSC XIII),
# levelled off above 51 km where their crater-to-basin transition starts; basal diameter 0.22 D
# (Hale & Head 1979, LPSC X). Capped below the rim so the rim crest stays the crater's highest point.
PEAK_COEF, PEAK_EXP, PEAK_MAX_D_KM = 0.0006, 1.969, 51.0
PEAK_BASE_FRACTION = 0.22
PEAK_MAX_DEPTH_FRACTION = 0.8
# Wall terraces of complex craters (a model choice, not a fit): one at 20 km, one more every 15 km,
# at most 5; each a flat bench then a scarp, mixed into the smooth wall at this weight.
TERRACE_START_KM, TERRACE_STEP_KM, TERRACE_MAX = 20.0, 15.0, 5
TERRACE_WEIGHT = 0.6
# McGetchin, Settle & Head (1973), EPSL 20:226: ejecta thickness ~ (r/R)^-3 outside the rim.
EJECTA_DECAY_EXP = 3.0
EJECTA_EXTENT_RADII = 3.0  # blanket truncated (smoothly) at 3 crater radii
# Secondaries (Shoemaker 1965; McEwen & Bierhaus 2006, Annu. Rev. EPS 34:535): steep cumulative SFD,
# largest ~4 % of the primary (Melosh 1989, Impact Cratering, ch. 6), from ~2 to ~10 primary radii;
# shallow, d/D ~ 0.1 (Pike & Wilhelms 1978, LPSC IX).
SECONDARY_SFD_SLOPE = 4.0
LARGEST_SECONDARY_FRACTION = 0.04
SECONDARY_RANGE_RADII = (2.0, 10.0)
SECONDARY_DEPTH_DIAMETER = 0.1
SECONDARY_RAYS = 12  # rays per primary; secondaries cluster along them
SECONDARY_CLUSTERS_PER_RAY = 2
SECONDARY_AZIMUTH_JITTER_RAD = 0.05
SECONDARY_RADIAL_JITTER = 0.08  # relative scatter about a cluster's distance

# Neukum, Ivanov & Hartmann (2001), Space Sci. Rev. 96:55, Table 1 ("new" NPF): cumulative
# log10 N(>D) = sum a_n (log10 D)^n per km^2, D in km, for the reference 1 Gyr surface; valid
# 0.01-300 km (extended beyond as the power law tangent at the ends).
NPF_COEFS = (
    -3.0876,
    -3.557528,
    0.781027,
    1.021521,
    -0.156012,
    -0.444058,
    0.019977,
    0.086850,
    -0.005874,
    -0.006809,
    8.25e-4,
    5.54e-5,
)
NPF_VALID_KM = (0.01, 300.0)
# Neukum chronology (same paper, eq. 5): N(1 km) per km^2 = A (exp(B T) - 1) + C T, T in Gyr.
CHRONO_A, CHRONO_B, CHRONO_C = 5.44e-14, 6.93, 8.38e-4

# Fractal ground: RMS slope specified over this baseline, rescaled to the grid spacing by L^(H-1).
ROUGHNESS_BASELINE_M = 100.0

# Degradation. Profiles live on s = r / R in [0, PROFILE_EXTENT_RADII] every PROFILE_STEP; diffusion
# runs on cells out to DIFFUSION_EXTENT_RADII (no-flux edges far from the crater). Diffused profiles
# are tapered to 0 between TAPER_START and PROFILE_EXTENT radii: < 0.2 % of the fresh depth is cut
# there until d/D falls to 0.005 (docs/detail.md), long after the crater became a ghost. Simple
# craters' kappa t / D^2 beyond the table's last rung (2.0) take that rung: ghosts either way.
PROFILE_STEP = 0.01
PROFILE_EXTENT_RADII = 4.0
TAPER_START_RADII = 3.5
DIFFUSION_EXTENT_RADII = 8.0
DIFFUSION_TAU_RANGE = (1e-5, 2.0)  # tabulated kappa t / D^2 (simple craters), geometric ladder
DIFFUSION_TAU_COUNT = 160
# A "ghost": depth down to 0.014 D for a simple crater (the sub-DEM detail's calibrated recognition
# limit, docs/detail.md), i.e. 0.014 / 0.196 of its fresh depth. degradation = 1 - depth ratio, scaled
# to reach 1 there.
GHOST_DEPTH_RATIO = DetailSettings.min_depth_diameter / PIKE_DEPTH_COEF
# Overprinting: inside a new crater the old relief is kept with weight (r/R)^INHERIT_EXP (none at the
# centre, all of it at the rim); its interior (r <= R) marks the pixels it overprints.
INHERIT_EXP = 2.0
RIM_SAMPLES = 64  # rim points per crater for visible_rim_fraction
# Diffusion moves a rim crest out as it flattens it; a degraded crest is searched for within this many R
# (a near-ghost's flat crest may sit at the bound).
RIM_SEARCH_RADII = 1.5
PROFILE_CHUNK = 8192  # profile rows computed at once (memory-bound above ~10^4)
MAX_CRATERS = 2_000_000  # a population above this is a settings mistake, not a terrain

CLASSES = ("simple", "transitional", "complex")


# --------------------------------------------------------------------------------------------
# Spectral noise (also the sub-DEM detail's: crater_synth/terrain/detail.py)
# --------------------------------------------------------------------------------------------
def wavenumbers(shape: tuple[int, int], spacing_m: float) -> np.ndarray:
    """|k| (cycles per metre) on the rfft2 grid of ``shape``."""
    ky = np.fft.fftfreq(shape[0], d=spacing_m)[:, None]
    kx = np.fft.rfftfreq(shape[1], d=spacing_m)[None, :]
    return np.hypot(ky, kx)


def fbm_surface(shape: tuple[int, int], spacing_m: float, hurst: float, rng: np.random.Generator) -> np.ndarray:
    """Zero-mean periodic fractional Brownian surface (arbitrary amplitude), spectral synthesis."""
    k = wavenumbers(shape, spacing_m)
    amp = np.zeros_like(k)
    amp[k > 0] = k[k > 0] ** -(hurst + 1.0)
    noise = rng.standard_normal(shape)
    return np.fft.irfft2(np.fft.rfft2(noise) * amp, s=shape)


def fractal_ground(size: int, spacing_m: float, hurst: float, rms_slope_deg: float, rng) -> np.ndarray:
    """fBm ground whose RMS slope over ROUGHNESS_BASELINE_M is ``rms_slope_deg`` (slope ~ L^(H-1))."""
    field = fbm_surface((size, size), spacing_m, hurst, rng)
    if rms_slope_deg <= 0.0:
        return np.zeros((size, size))
    gx = np.diff(field, axis=1) / spacing_m
    gy = np.diff(field, axis=0) / spacing_m
    per_px = math.sqrt(float(np.mean(gx**2) + np.mean(gy**2)))
    target = math.tan(math.radians(rms_slope_deg)) * (spacing_m / ROUGHNESS_BASELINE_M) ** (hurst - 1.0)
    field *= target / per_px
    return field - field.mean()


# --------------------------------------------------------------------------------------------
# Production function and chronology
# --------------------------------------------------------------------------------------------
def _npf_log(x: np.ndarray) -> np.ndarray:
    """log10 N(>D) of the reference surface at x = log10 D (km), tangent power law outside the range."""
    lo, hi = (math.log10(v) for v in NPF_VALID_KM)
    xc = np.clip(x, lo, hi)
    powers = np.arange(len(NPF_COEFS))
    val = np.sum(np.asarray(NPF_COEFS) * xc[..., None] ** powers, axis=-1)
    slope = np.sum(np.asarray(NPF_COEFS[1:]) * powers[1:] * xc[..., None] ** (powers[1:] - 1), axis=-1)
    return val + slope * (x - xc)


def chronology_n1(age_gyr) -> np.ndarray:
    """N(>1 km) per km^2 accumulated on a surface of this age (Neukum et al. 2001)."""
    t = np.asarray(age_gyr, dtype=float)
    return CHRONO_A * (np.exp(CHRONO_B * t) - 1.0) + CHRONO_C * t


def production_cumulative(diameter_m, age_gyr: float) -> np.ndarray:
    """Cumulative production N(>=D) per m^2 on a surface of ``age_gyr`` (Neukum 2001 NPF x chronology)."""
    x = np.log10(np.asarray(diameter_m, dtype=float) / 1000.0)
    per_km2 = 10.0 ** (_npf_log(x) - NPF_COEFS[0]) * chronology_n1(age_gyr)
    return per_km2 / 1e6


def production_slope(diameter_m) -> np.ndarray:
    """Local cumulative slope d log N / d log D of the production function."""
    x = np.log10(np.asarray(diameter_m, dtype=float) / 1000.0)
    h = 1e-4
    return (_npf_log(x + h) - _npf_log(x - h)) / (2 * h)


def _draw_sfd(n: int, d_min: float, d_max: float, age_gyr: float, rng) -> np.ndarray:
    """``n`` diameters (m) from the production function truncated to [d_min, d_max] (inverse CDF)."""
    d = np.geomspace(d_min, d_max, 4096)
    cum = production_cumulative(d, age_gyr)
    cdf = (cum[0] - cum) / (cum[0] - cum[-1])
    return np.exp(np.interp(rng.random(n), cdf, np.log(d)))


def _draw_ages_myr(n: int, age_gyr: float, rng) -> np.ndarray:
    """Formation ages: P(age <= a) = N1(a) / N1(T), the chronology's own accumulation."""
    t = np.linspace(0.0, age_gyr, 2048)
    cdf = chronology_n1(t) / chronology_n1(age_gyr)
    return np.interp(rng.random(n), cdf, t) * 1000.0


# --------------------------------------------------------------------------------------------
# Morphometry
# --------------------------------------------------------------------------------------------
def _laws(d_km: np.ndarray) -> dict[str, np.ndarray]:
    """The fresh-crater laws (km) at ``d_km``, each taken as if the crater were of its kind."""
    return {
        "simple_depth": PIKE_DEPTH_COEF * d_km**PIKE_DEPTH_EXP,
        "simple_rim": PIKE_RIM_COEF * d_km**PIKE_RIM_EXP,
        "depth": PIKE_COMPLEX_DEPTH_COEF * d_km**PIKE_COMPLEX_DEPTH_EXP,
        "rim": PIKE_COMPLEX_RIM_COEF * d_km**PIKE_COMPLEX_RIM_EXP,
        "floor": np.minimum(PIKE_FLOOR_COEF * d_km**PIKE_FLOOR_EXP, FLOOR_MAX_FRACTION * d_km),
        "peak": PEAK_COEF * np.minimum(d_km, PEAK_MAX_D_KM) ** PEAK_EXP,
    }


def morphometry(diameter_m, is_secondary=None) -> dict[str, np.ndarray]:
    """Fresh shape of each crater (m): depth (rim crest to floor), rim height, floor diameter, central
    peak height above the floor, terrace count and class index into :data:`CLASSES`.

    Transitional craters (TRANSITION_KM): depth and rim log-linear in log D from the simple law at the
    start to the complex law at the end; floor diameter and peak grow linearly in that weight from 0."""
    d_m = np.atleast_1d(np.asarray(diameter_m, dtype=float))
    sec = np.zeros(d_m.shape, bool) if is_secondary is None else np.atleast_1d(np.asarray(is_secondary, bool))
    d_km = d_m / 1000.0
    lo, hi = TRANSITION_KM
    law = _laws(d_km)
    lo_law, hi_law = _laws(np.array([lo])), _laws(np.array([hi]))
    w = np.clip(np.log(d_km / lo) / math.log(hi / lo), 0.0, 1.0)
    kind = np.where(d_km < lo, 0, np.where(d_km < hi, 1, 2))

    def pick(simple, transitional, complex_):
        return np.select([kind == 0, kind == 1], [simple, transitional], complex_)

    def blend(key_lo: str, key_hi: str):
        return np.exp((1 - w) * np.log(lo_law[key_lo]) + w * np.log(hi_law[key_hi]))

    depth = pick(law["simple_depth"], blend("simple_depth", "depth"), law["depth"])
    rim = pick(law["simple_rim"], blend("simple_rim", "rim"), law["rim"])
    floor = pick(0.0, w * hi_law["floor"] * d_km / hi, law["floor"])
    peak = np.minimum(pick(0.0, w * hi_law["peak"], law["peak"]), PEAK_MAX_DEPTH_FRACTION * depth)
    terraces = np.minimum(1 + np.floor((d_km - TERRACE_START_KM) / TERRACE_STEP_KM), TERRACE_MAX)
    terraces = np.where(kind == 2, terraces, 0).astype(int)
    # Secondaries: shallow simple bowls, rim in Pike's simple rim/depth proportion.
    depth = np.where(sec, SECONDARY_DEPTH_DIAMETER * d_km, depth)
    rim = np.where(sec, SECONDARY_DEPTH_DIAMETER * d_km * PIKE_RIM_COEF / PIKE_DEPTH_COEF, rim)
    return {
        "diameter": d_m,
        "depth": depth * 1000.0,
        "rim": rim * 1000.0,
        "floor_diameter": np.where(sec, 0.0, floor) * 1000.0,
        "peak": np.where(sec, 0.0, peak) * 1000.0,
        "terraces": np.where(sec, 0, terraces),
        "cls": np.where(sec, 0, kind),
    }


def fresh_profile(s: np.ndarray, depth, rim, floor_frac=0.0, peak=0.0, terraces=0) -> np.ndarray:
    """Height (m) relative to the pre-impact surface at s = r / R of a fresh crater.

    Inside (s <= 1): floor at rim - depth out to ``floor_frac``, then the wall rises as the square of
    the distance across it (a parabolic bowl when floor_frac = 0), stepped by ``terraces``; a central
    peak of ``peak`` above the floor, raised-cosine, basal radius PEAK_BASE_FRACTION R. Rim crest at s = 1.
    Outside: rim (s^-3 - S^-3) / (1 - S^-3) out to S = EJECTA_EXTENT_RADII.
    """
    s = np.asarray(s, dtype=float)
    t = np.clip((s - floor_frac) / (1.0 - floor_frac), 0.0, 1.0)
    u = t**2
    if terraces > 0:
        k = np.minimum(np.floor(u * terraces), terraces - 1)
        stepped = (k + (u * terraces - k) ** 3) / terraces
        u = (1.0 - TERRACE_WEIGHT) * u + TERRACE_WEIGHT * stepped
    inside = rim - depth + depth * u
    if peak > 0.0:
        inside = inside + peak * 0.5 * (1.0 + np.cos(np.pi * np.minimum(s / PEAK_BASE_FRACTION, 1.0)))
    tail = EJECTA_EXTENT_RADII**-EJECTA_DECAY_EXP
    outside = rim * (np.maximum(s, 1.0) ** -EJECTA_DECAY_EXP - tail) / (1.0 - tail)
    return np.where(s <= 1.0, inside, np.where(s <= EJECTA_EXTENT_RADII, outside, 0.0))


# --------------------------------------------------------------------------------------------
# Degradation: radial diffusion, exact in time
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Diffusion:
    s_cells: np.ndarray  # (C,) cell centres, units of R
    root: np.ndarray  # (C,) sqrt(cell areas)
    lam: np.ndarray  # (C,) eigenvalues of M^-1/2 K M^-1/2 (<= 0)
    u: np.ndarray  # (C, C) eigenvectors
    s: np.ndarray  # (S,) output samples, 0..PROFILE_EXTENT_RADII
    taper: np.ndarray  # (S,)


@functools.lru_cache(maxsize=1)
def radial_diffusion_operator(n: int, ds: float):
    """(cell centres s, sqrt of the cell areas, diagonal, off-diagonal) of the symmetric tridiagonal
    M^-1/2 K M^-1/2 of dh/dt = (1/r) d/dr (r dh/dr) on ``n`` finite volumes of width ``ds`` (no flux at the
    centre and the far edge; M = diag(cell areas), K the face-flux matrix). Its eigen-decomposition
    U diag(lam) U^T gives h(t) = M^-1/2 U exp(lam t) U^T M^1/2 h0 for any t (here and terrain/detail.py)."""
    s = (np.arange(n) + 0.5) * ds
    faces = np.arange(1, n) * ds
    area = s * ds
    main = np.zeros(n)
    main[:-1] -= faces / ds
    main[1:] -= faces / ds
    root = np.sqrt(area)
    return s, root, main / area, (faces / ds) / (root[:-1] * root[1:])


def _diffusion() -> _Diffusion:
    """The radial diffusion of :func:`radial_diffusion_operator` on the profile cells, decomposed once."""
    ds = PROFILE_STEP
    s, root, diag, off = radial_diffusion_operator(round(DIFFUSION_EXTENT_RADII / ds), ds)
    lam, u = np.linalg.eigh(np.diag(diag) + np.diag(off, 1) + np.diag(off, -1))
    s_out = np.arange(0.0, PROFILE_EXTENT_RADII + 1e-9, ds)
    ramp = np.clip((PROFILE_EXTENT_RADII - s_out) / (PROFILE_EXTENT_RADII - TAPER_START_RADII), 0.0, 1.0)
    return _Diffusion(s, root, lam, u, s_out, 0.5 - 0.5 * np.cos(np.pi * ramp))


def diffuse(h0_cells: np.ndarray, tau_d) -> np.ndarray:
    """Profiles (rows of ``h0_cells``, sampled on the diffusion cells) diffused for kappa t / D^2 =
    ``tau_d`` (time in units of R^2 / kappa is 4 tau_d), resampled on the output grid and tapered."""
    f = _diffusion()
    h0 = np.atleast_2d(h0_cells)
    tau = np.atleast_1d(np.asarray(tau_d, dtype=float))
    coef = (h0 * f.root) @ f.u
    prof = ((coef * np.exp(np.outer(4.0 * tau, f.lam))) @ f.u.T) / f.root
    s_ext = np.concatenate([[-f.s_cells[0]], f.s_cells])
    out = np.stack([np.interp(f.s, s_ext, np.concatenate([[p[0]], p])) for p in prof])
    return out * f.taper


@functools.lru_cache(maxsize=1)
def _simple_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """tau ladder and the diffused unit-rim (A) and unit-depth (B) parts of a simple crater: its
    profile is rim A + depth B at any tau (diffusion is linear). Row 0 is the fresh shape exactly."""
    f = _diffusion()
    tau = np.concatenate([[0.0], np.geomspace(*DIFFUSION_TAU_RANGE, DIFFUSION_TAU_COUNT - 1)])
    a0 = fresh_profile(f.s_cells, 0.0, 1.0)
    b0 = fresh_profile(f.s_cells, 1.0, 0.0)
    a, b = diffuse(a0, tau), diffuse(b0, tau)
    a[0], b[0] = fresh_profile(f.s, 0.0, 1.0), fresh_profile(f.s, 1.0, 0.0)
    return tau, a, b


def degraded_profiles(shape: dict[str, np.ndarray], tau_d: np.ndarray) -> np.ndarray:
    """(N, S) radial profiles (m) on s = 0..PROFILE_EXTENT_RADII of craters of fresh ``shape``
    (:func:`morphometry`) diffused for ``tau_d``: simple ones from the tables (linear in tau between
    ladder rungs), the others diffused one by one from their own fresh profile. Rows are filled
    PROFILE_CHUNK at a time: a saturated field holds ~10^6 craters, whose whole-table temporaries
    (~3 GB each) made this step memory-bound."""
    f = _diffusion()
    tau_d = np.asarray(tau_d, dtype=float)
    tau_tab, ta, tb = _simple_tables()
    pos = np.interp(tau_d, tau_tab, np.arange(tau_tab.size))
    i0 = np.minimum(np.floor(pos).astype(int), tau_tab.size - 2)
    w = (pos - i0)[:, None]
    rim, depth = shape["rim"][:, None], shape["depth"][:, None]
    out = np.empty((tau_d.size, f.s.size))
    for a in range(0, tau_d.size, PROFILE_CHUNK):
        c, j = slice(a, a + PROFILE_CHUNK), i0[a : a + PROFILE_CHUNK]
        out[c] = rim[c] * ((1 - w[c]) * ta[j] + w[c] * ta[j + 1]) + depth[c] * ((1 - w[c]) * tb[j] + w[c] * tb[j + 1])
    for i in np.flatnonzero(shape["cls"] > 0):
        d_m = float(shape["diameter"][i])
        args = (
            float(shape["depth"][i]),
            float(shape["rim"][i]),
            float(shape["floor_diameter"][i]) / d_m,
            float(shape["peak"][i]),
            int(shape["terraces"][i]),
        )
        if tau_d[i] > 0.0:
            out[i] = diffuse(fresh_profile(f.s_cells, *args), tau_d[i])[0]
        else:
            out[i] = fresh_profile(f.s, *args)
    return out


def profile_labels(profiles: np.ndarray, fresh_depth: np.ndarray) -> dict[str, np.ndarray]:
    """From each radial profile: rim crest radius (units of R), rim height above the pre-impact
    surface, rim-to-floor depth, and the degradation state (0 fresh .. 1 ghost). PROFILE_CHUNK rows
    at a time, as :func:`degraded_profiles`."""
    s = _diffusion().s
    inner = s <= RIM_SEARCH_RADII
    crest = np.empty(len(profiles), dtype=np.int64)
    floor = np.empty(len(profiles))
    for a in range(0, len(profiles), PROFILE_CHUNK):
        p = profiles[a : a + PROFILE_CHUNK]
        k = np.argmax(np.where(inner, p, -np.inf), axis=1)
        crest[a : a + PROFILE_CHUNK] = k
        floor[a : a + PROFILE_CHUNK] = np.min(np.where(s[None, :] <= s[k][:, None], p, np.inf), axis=1)
    rim_h = profiles[np.arange(len(profiles)), crest]
    depth = rim_h - floor
    ratio = depth / np.maximum(fresh_depth, 1e-12)
    state = np.clip((1.0 - ratio) / (1.0 - GHOST_DEPTH_RATIO), 0.0, 1.0)
    return {"rim_radius": s[crest], "rim_height": rim_h, "depth": depth, "degradation": state}


# --------------------------------------------------------------------------------------------
# Populations
# --------------------------------------------------------------------------------------------
def _rim_touches_grid(x: np.ndarray, y: np.ndarray, radius: np.ndarray, side_m: float) -> np.ndarray:
    """True where the rim circle reaches the grid square [0, side]^2 (centre within R of it)."""
    dx = np.maximum(np.maximum(-x, x - side_m), 0.0)
    dy = np.maximum(np.maximum(-y, y - side_m), 0.0)
    return np.hypot(dx, dy) <= radius


def _primaries(st: ProceduralSettings, rng: np.random.Generator) -> dict[str, np.ndarray]:
    side = (st.size_px - 1) * st.spacing_m
    d_min, d_max = st.d_min_px * st.spacing_m, st.d_max_fraction * st.size_px * st.spacing_m
    ext = side + d_max  # centres drawn over the grid plus a margin of the largest radius on each side
    per_m2 = production_cumulative(np.array([d_min, d_max]), st.surface_age_gyr)
    expected = st.density_scale * ext**2 * float(per_m2[0] - per_m2[1])
    if expected > MAX_CRATERS:
        raise ValueError(
            f"procedural settings ask for ~{expected:.3g} craters (> {MAX_CRATERS}): raise d_min_px or "
            "spacing_m, or lower size_px, surface_age_gyr or density_scale"
        )
    n = int(rng.poisson(expected))
    diam = _draw_sfd(n, d_min, d_max, st.surface_age_gyr, rng)
    x = rng.uniform(-0.5 * d_max, side + 0.5 * d_max, n)
    y = rng.uniform(-0.5 * d_max, side + 0.5 * d_max, n)
    age = _draw_ages_myr(n, st.surface_age_gyr, rng)
    keep = _rim_touches_grid(x, y, 0.5 * diam, side)
    return {"diameter": diam[keep], "x": x[keep], "y": y[keep], "age_myr": age[keep]}


def _secondaries(prim: dict[str, np.ndarray], st: ProceduralSettings, rng) -> dict[str, np.ndarray]:
    """Clusters along rays around the primaries that can throw craters >= d_min; their count is
    ``secondary_fraction`` x the primaries', shared in proportion to each parent's expected number
    above d_min under the steep secondary SFD."""
    d_min = st.d_min_px * st.spacing_m
    side = (st.size_px - 1) * st.spacing_m
    d_top = LARGEST_SECONDARY_FRACTION * prim["diameter"]
    parents = np.flatnonzero(d_top > d_min)
    empty = {k: np.zeros(0) for k in ("diameter", "x", "y", "age_myr")} | {"parent": np.zeros(0, int)}
    if parents.size == 0 or st.secondary_fraction <= 0.0:
        return empty
    weight = (d_top[parents] / d_min) ** SECONDARY_SFD_SLOPE - 1.0
    counts = rng.poisson(st.secondary_fraction * prim["diameter"].size * weight / weight.sum())
    parent = np.repeat(parents, counts)
    n = parent.size
    if n == 0:
        return empty
    top = d_top[parent]
    u = rng.random(n)  # truncated power law, cumulative slope -SECONDARY_SFD_SLOPE, in [d_min, top]
    b = SECONDARY_SFD_SLOPE
    diam = (d_min**-b - u * (d_min**-b - top**-b)) ** (-1.0 / b)
    # Rays and clusters are drawn per parent; each secondary picks one of its parent's.
    ray_az = rng.uniform(0.0, 2 * np.pi, (prim["diameter"].size, SECONDARY_RAYS))
    lo, hi = np.log(SECONDARY_RANGE_RADII)
    cluster_r = np.exp(rng.uniform(lo, hi, (prim["diameter"].size, SECONDARY_RAYS, SECONDARY_CLUSTERS_PER_RAY)))
    ray = rng.integers(0, SECONDARY_RAYS, n)
    cl = rng.integers(0, SECONDARY_CLUSTERS_PER_RAY, n)
    az = ray_az[parent, ray] + rng.normal(0.0, SECONDARY_AZIMUTH_JITTER_RAD, n)
    r = cluster_r[parent, ray, cl] * (1.0 + rng.normal(0.0, SECONDARY_RADIAL_JITTER, n))
    r *= 0.5 * prim["diameter"][parent]
    x = prim["x"][parent] + r * np.cos(az)
    y = prim["y"][parent] + r * np.sin(az)
    keep = _rim_touches_grid(x, y, 0.5 * diam, side)
    return {
        "diameter": diam[keep],
        "x": x[keep],
        "y": y[keep],
        "age_myr": prim["age_myr"][parent][keep],
        "parent": parent[keep],
    }


def crater_table(
    diameter_m, x_m, y_m, age_myr, diffusivity_m2_per_myr: float, is_secondary=None, parent=None
) -> dict[str, np.ndarray]:
    """Every label of the given craters except the overprint flags, in emplacement order (oldest first;
    a parent before its secondaries): fresh morphometry, kappa t / D^2, the degraded profile's labels
    and the profiles themselves (``profile``, (N, S) on s = 0..PROFILE_EXTENT_RADII)."""
    d = np.atleast_1d(np.asarray(diameter_m, dtype=float))
    sec = np.zeros(d.shape, bool) if is_secondary is None else np.asarray(is_secondary, bool)
    par = np.full(d.shape, -1) if parent is None else np.asarray(parent, int)
    age = np.broadcast_to(np.asarray(age_myr, dtype=float), d.shape)
    order = np.lexsort((sec, -age))
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    par = np.where(par >= 0, rank[np.maximum(par, 0)], -1)  # parents renumbered into the new order
    d, sec, par, age = d[order], sec[order], par[order], age[order]
    x = np.broadcast_to(np.asarray(x_m, dtype=float), rank.shape)[order]
    y = np.broadcast_to(np.asarray(y_m, dtype=float), rank.shape)[order]
    shape = morphometry(d, sec)
    tau = diffusivity_m2_per_myr * age / d**2
    prof = degraded_profiles(shape, tau)
    lab = profile_labels(prof, shape["depth"])
    return {
        "x": x,
        "y": y,
        "diameter": d,
        "age_myr": age,
        "tau_d": tau,
        "is_secondary": sec,
        "parent": par,
        "fresh_depth": shape["depth"],
        "fresh_rim_height": shape["rim"],
        "floor_diameter": shape["floor_diameter"],
        "peak_height": shape["peak"],
        "terraces": shape["terraces"],
        "cls": shape["cls"],
        "rim_diameter": lab["rim_radius"] * d,
        "rim_height": lab["rim_height"],
        "depth": lab["depth"],
        "degradation": lab["degradation"],
        "profile": prof,
    }


# --------------------------------------------------------------------------------------------
# Emplacement
# --------------------------------------------------------------------------------------------
def emplace(height: np.ndarray, spacing_m: float, table: dict[str, np.ndarray]) -> np.ndarray:
    """Stamp the craters of ``table`` (emplacement order) into ``height`` in place; returns, per pixel,
    the index of the last crater whose interior (r <= R) covers it (-1: none).

    Each crater excavates what it lands on: inside it the old relief is kept with weight (r/R)^2
    about the old surface's mean over its interior, so the floor is the crater's own and the rim
    follows the ground; outside, its ejecta add to the ground."""
    ny, nx = height.shape
    last = np.full(height.shape, -1, dtype=np.int64)
    s_grid = _diffusion().s
    for i in range(table["diameter"].size):
        radius = 0.5 * table["diameter"][i]
        cx, cy = table["x"][i] / spacing_m, table["y"][i] / spacing_m
        half = PROFILE_EXTENT_RADII * radius / spacing_m
        r0, r1 = max(int(math.floor(cy - half)), 0), min(int(math.ceil(cy + half)) + 1, ny)
        c0, c1 = max(int(math.floor(cx - half)), 0), min(int(math.ceil(cx + half)) + 1, nx)
        if r0 >= r1 or c0 >= c1:
            continue
        rows = np.arange(r0, r1)[:, None]
        cols = np.arange(c0, c1)[None, :]
        s = np.hypot(rows - cy, cols - cx) * (spacing_m / radius)
        old = height[r0:r1, c0:c1]
        inside = s <= 1.0
        ref = float(old[inside].mean()) if inside.any() else float(old.mean())
        keep = np.where(inside, s**INHERIT_EXP, 1.0)
        height[r0:r1, c0:c1] = ref + keep * (old - ref) + np.interp(s, s_grid, table["profile"][i], right=0.0)
        last[r0:r1, c0:c1][inside] = i
    return last


def visible_rim_fraction(last: np.ndarray, spacing_m: float, table: dict[str, np.ndarray]) -> tuple:
    """Per crater: the share of its rim points (RIM_SAMPLES, nearest pixel) inside the grid that no
    later crater's interior covers, and the share of rim points inside the grid at all."""
    ny, nx = last.shape
    n = table["diameter"].size
    az = np.linspace(0.0, 2 * np.pi, RIM_SAMPLES, endpoint=False)
    radius_px = 0.5 * table["diameter"][:, None] / spacing_m
    col = np.rint(table["x"][:, None] / spacing_m + radius_px * np.cos(az)).astype(np.int64)
    row = np.rint(table["y"][:, None] / spacing_m + radius_px * np.sin(az)).astype(np.int64)
    ok = (row >= 0) & (row < ny) & (col >= 0) & (col < nx)
    cover = last[np.clip(row, 0, ny - 1), np.clip(col, 0, nx - 1)]
    seen = ok & (cover <= np.arange(n)[:, None])
    in_grid = ok.sum(axis=1)
    return seen.sum(axis=1) / np.maximum(in_grid, 1), in_grid / RIM_SAMPLES


# --------------------------------------------------------------------------------------------
# The terrain
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Crater:
    """One crater placed, as built (lengths in m, centre in the grid's x = column, y = row frame)."""

    order: int  # emplacement order: 0 is the oldest; a later crater overprints an earlier one
    x_m: float
    y_m: float
    diameter_m: float  # fresh rim-crest diameter, the label's D
    rim_diameter_m: float  # rim crest after degradation (diffusion moves it out: docs/procedural.md)
    rim_height_m: float  # rim crest above the pre-impact surface, after degradation
    depth_m: float  # rim crest to floor, after degradation
    fresh_depth_m: float
    floor_diameter_m: float
    peak_height_m: float  # central peak above the fresh floor
    terraces: int
    morph_class: str  # simple, transitional or complex
    degradation: float  # 0 fresh .. 1 ghost (depth down to GHOST_DEPTH_RATIO of fresh)
    tau_d: float  # kappa t / D^2
    age_myr: float
    is_secondary: bool
    parent: int  # order of the primary that threw it (-1: a primary)
    visible_rim_fraction: float  # of the rim inside the grid, the share no later crater covers
    rim_in_grid_fraction: float

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class ProceduralTerrain:
    height: np.ndarray  # (size, size) metres
    spacing_m: float
    craters: tuple[Crater, ...]
    # detectable()'s answers: every frame of a field asks, and a saturated field holds ~10^6 craters.
    _detectable: dict = field(default_factory=dict, compare=False, repr=False)

    def detectable(self, min_visible_rim: float = 0.5, max_degradation: float = 0.9) -> list[Crater]:
        """Craters a detector's label set may hold: not a ghost, most of the rim neither overprinted
        nor off the grid."""
        key = (min_visible_rim, max_degradation)
        if key not in self._detectable:
            self._detectable[key] = [
                c
                for c in self.craters
                if c.visible_rim_fraction * c.rim_in_grid_fraction >= min_visible_rim
                and c.degradation <= max_degradation
            ]
        return list(self._detectable[key])


def _craters(table: dict[str, np.ndarray], visible: np.ndarray, in_grid: np.ndarray) -> tuple[Crater, ...]:
    cols = {k: v.tolist() for k, v in table.items() if k != "profile"}
    return tuple(
        Crater(
            order=i,
            x_m=cols["x"][i],
            y_m=cols["y"][i],
            diameter_m=cols["diameter"][i],
            rim_diameter_m=cols["rim_diameter"][i],
            rim_height_m=cols["rim_height"][i],
            depth_m=cols["depth"][i],
            fresh_depth_m=cols["fresh_depth"][i],
            floor_diameter_m=cols["floor_diameter"][i],
            peak_height_m=cols["peak_height"][i],
            terraces=cols["terraces"][i],
            morph_class=CLASSES[cols["cls"][i]],
            degradation=cols["degradation"][i],
            tau_d=cols["tau_d"][i],
            age_myr=cols["age_myr"][i],
            is_secondary=cols["is_secondary"][i],
            parent=cols["parent"][i],
            visible_rim_fraction=float(visible[i]),
            rim_in_grid_fraction=float(in_grid[i]),
        )
        for i in range(table["diameter"].size)
    )


def build(base: np.ndarray, spacing_m: float, table: dict[str, np.ndarray]) -> ProceduralTerrain:
    """The terrain of the craters of ``table`` (:func:`crater_table`) emplaced on ``base`` (copied)."""
    height = np.array(base, dtype=float, copy=True)
    last = emplace(height, spacing_m, table)
    visible, in_grid = visible_rim_fraction(last, spacing_m, table)
    return ProceduralTerrain(height=height, spacing_m=spacing_m, craters=_craters(table, visible, in_grid))


def generate(settings: ProceduralSettings) -> ProceduralTerrain:
    """The crater field of ``settings``: deterministic for its seed."""
    ground_rng, prim_rng, sec_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(settings.seed).spawn(3))
    prim = _primaries(settings, prim_rng)  # first: it refuses a population too large to build
    base = fractal_ground(
        settings.size_px, settings.spacing_m, settings.hurst, settings.roughness_rms_slope_deg, ground_rng
    )
    sec = _secondaries(prim, settings, sec_rng)
    n_prim = prim["diameter"].size
    table = crater_table(
        np.concatenate([prim["diameter"], sec["diameter"]]),
        np.concatenate([prim["x"], sec["x"]]),
        np.concatenate([prim["y"], sec["y"]]),
        np.concatenate([prim["age_myr"], sec["age_myr"]]),
        settings.diffusivity_m2_per_myr,
        is_secondary=np.concatenate([np.zeros(n_prim, bool), np.ones(sec["diameter"].size, bool)]),
        parent=np.concatenate([np.full(n_prim, -1), sec["parent"]]).astype(int),
    )
    return build(base, settings.spacing_m, table)
