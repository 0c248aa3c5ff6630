"""The crater catalogue checked against the DEM: is each entry a closed depression of its size?

Every catalogue entry (``configs/crater/<name>.yaml``: IAU Gazetteer lat, lon, diameter D) must be a
real crater in the DEM the terrain is built from, or the renders of "crater X" show something else.
:func:`measure_depression` measures the depression around a catalogue position (docs/catalogue.md):

1. **Local grid.** The DEM is sampled (bicubic, :meth:`crater_synth.terrain.dem.Dem.sample`) on a square grid
   in the crater's local horizontal plane -- the terrain patch's own construction (the sphere point
   below each tangent-plane point (e, n), ``crater_synth.terrain.patch``), half-width
   ``GRID_HALF_WIDTH_D`` x D, spacing D / ``GRID_CELLS_PER_D`` but no coarser than half a DEM pixel.
   Heights are above the reference sphere, so the Moon's curvature does not tilt the profiles.
2. **Rim crest.** From a centre c, ``N_AZIMUTHS`` radial height profiles are read (bilinear on the
   grid) between ``RIM_SEARCH_FRAC`` x the catalogue radius: twice the 25 % diameter tolerance on
   each side, so a rim outside the tolerance is measured as such, not clipped into it. Beyond the
   inner wall (the steepest rise of the profile), the crest is the first point where the profile turns
   down by at least ``MIN_RIM_DROP_D`` x D; where it never turns down (terrain rising beyond the rim),
   the knee where the steep wall gives way to the gentler rise (:func:`_first_crest`).
3. **Centre.** Starting at the catalogue position, c moves (half steps) to the centre of the
   least-squares circle through the crest points, outliers rejected (:func:`robust_circle`), until it
   moves by less than ``CENTRE_TOLERANCE_D`` x D. The converged c is the depression's centre: the
   catalogue position only seeds the search; the offset is measured, not chosen.
4. **Rim diameter** = 2 x the mean crest radius about c over the azimuths on the rim circle.
5. **Closed depression.** Water has left the crater once it is beyond every crest point on the rim
   circle. The spill height is the water level the floor holds when it can drain only there: the
   lowest possible maximum height along any path from the floor across the crest ring
   (:func:`_spill_level`), i.e. the lowest point of the rim crest ring. The floor is the lowest point
   within ``FLOOR_RADIUS_FRAC`` x the rim radius of c. spill depth = spill height - floor height; the
   crater is a closed depression when it is at least ``MIN_SPILL_DEPTH_D`` x D.

An entry passes (:func:`check`) when it is a closed depression, its centre lies within
``MAX_CENTRE_OFFSET_D`` x D of the catalogue position, its rim diameter within
``MAX_DIAMETER_ERROR`` of the catalogue diameter (docs/catalogue.md: these two are never loosened), and its
default terrain patch (near field +-``terrain.near_radius_factor`` x D) lies inside the DEM.

Length: one stage, the catalogue check, kept whole: the depression measurement (rim-circle fit,
spill depth by 2-D filling), the CLI listing and the contact sheets all read the same sampled grid.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import click
import numpy as np
from skimage.morphology import reconstruction

from crater_core.geometry import hemisphere
from crater_core.schema import atomic_write_bytes
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import catalogue_names, compose_settings, craters
from crater_synth.errors import UserError
from crater_synth.terrain import patch
from crater_synth.terrain.dem import DemError, check_hemisphere
from crater_synth.terrain.grid import bilinear, sphere_points
from crater_synth.terrain.patch import terrain_settings

# ---- acceptance thresholds (docs/catalogue.md: fixed, never loosened)
MAX_CENTRE_OFFSET_D = 0.15  # measured centre within 0.15 D of the catalogue position
MAX_DIAMETER_ERROR = 0.25  # measured rim diameter within 25 % of the catalogue diameter
# "Clearly below the spill point" (the project's choice, docs/catalogue.md): the crater must hold water
# at least 1 % of D deep (200 m for a 20 km crater). Fresh lunar craters are 0.1-0.2 D deep (Pike 1977)
# and the paper's three hold 0.06-0.17 D in LDEM_256, while the interpolation and down-sampling errors
# of its 1600 m grid are tens of metres: 1 % of D is far above noise without asking a breached, degraded
# crater to be fresh.
MIN_SPILL_DEPTH_D = 0.01

# ---- measurement settings
# Local grid +-1.25 D: the rim window (0.75 D) about a centre up to 0.5 D away, so offsets well past the
# 0.15 D tolerance are measured, not capped.
GRID_HALF_WIDTH_D = 1.25
GRID_CELLS_PER_D = 50  # grid spacing D / 50 (420 m for Shackleton) ...
GRID_MAX_SPACING_DEM_PX = 0.5  # ... but no coarser than half a DEM pixel
N_AZIMUTHS = 120  # radial profiles, every 3 deg: arc spacing at the rim < 0.03 D
RIM_SEARCH_FRAC = (0.5, 1.5)  # crest search window, fractions of the catalogue radius
PROFILE_STEP_D = 0.005  # radial sampling step along a profile
# A rim crest turns down by at least this (x D) on its outer side: the same 1 % of D as the
# closed-depression threshold, for the same reason (well above interpolation noise).
MIN_RIM_DROP_D = 0.01
FLOOR_RADIUS_FRAC = 0.5  # the floor is sought within half the measured rim radius of the centre
OUTLIER_MADS = 3.0  # crest points further than 3 robust sigmas from the rim circle are not rim
OUTLIER_PASSES = 5
# RANSAC start of the rim-circle fit: 200 draws find an all-inlier triple with probability > 0.9999
# at half the points outliers (1 - (1 - 0.5**3)**200).
RANSAC_SAMPLES = 200
RANSAC_SEED = 0
# ... and replaces the fit from all points only when its circle has more than twice the support: on a
# real rim with two near-equal candidates (Cabeus) a merely better start flips between them from one
# centre iteration to the next, while a fit pulled off the rim by outliers keeps almost no support.
RANSAC_MARGIN = 3.0
CENTRE_TOLERANCE_D = 0.002  # the centre iteration stops when a step is shorter than this
MAX_CENTRE_ITERATIONS = 40


@dataclass(frozen=True)
class Depression:
    """What :func:`measure_depression` found around one catalogue position."""

    centre_east_m: float  # measured centre in the catalogue position's local frame (east, north)
    centre_north_m: float
    centre_lat: float  # measured centre, planetocentric degrees
    centre_lon: float
    centre_offset_d: float  # |measured centre - catalogue position| / catalogue D
    rim_diameter_km: float  # 2 x mean crest radius about the measured centre (rim-circle azimuths)
    rim_diameter_ratio: float  # rim diameter / catalogue D
    rim_inlier_share: float  # share of azimuths whose crest lies on the fitted rim circle
    rim_crest_height_m: float  # mean crest height (above the sphere)
    spill_height_m: float  # lowest point of the crest ring
    spill_azimuth_deg: float  # where the water leaves, clockwise from north about the centre (NaN: nowhere)
    floor_height_m: float  # lowest point within FLOOR_RADIUS_FRAC x rim radius of the centre
    spill_depth_m: float  # spill height - floor height (> 0: water poured in the middle stays)
    spill_depth_d: float  # spill depth / catalogue D
    no_crest_share: float  # share of azimuths whose profile never turns down (the knee is used)
    iterations: int  # circle-fit iterations used
    converged: bool

    @property
    def closed(self) -> bool:
        return self.spill_depth_d >= MIN_SPILL_DEPTH_D

    def failures(self) -> list[str]:
        """Which acceptance criteria fail (empty: the entry passes)."""
        out = []
        if not self.closed:
            out.append(f"not a closed depression: spill depth {self.spill_depth_m:.0f} m < {MIN_SPILL_DEPTH_D:g} D")
        if self.centre_offset_d > MAX_CENTRE_OFFSET_D:
            out.append(f"centre {self.centre_offset_d:.3f} D from the catalogue position > {MAX_CENTRE_OFFSET_D:g} D")
        if not self.converged:
            out.append(f"no stable centre: the rim-circle fit did not settle in {MAX_CENTRE_ITERATIONS} iterations")
        if abs(self.rim_diameter_ratio - 1.0) > MAX_DIAMETER_ERROR:
            out.append(
                f"rim diameter {self.rim_diameter_km:.1f} km is {self.rim_diameter_ratio:.2f} x the "
                f"catalogue value (tolerance {MAX_DIAMETER_ERROR:.0%})"
            )
        return out

    def as_dict(self) -> dict:
        return {**asdict(self), "closed": self.closed}


def _local_grid(dem, lat: float, lon: float, diameter_m: float, what: str):
    """DEM heights on the crater's local horizontal grid: (heights (n, n), half_width_m, spacing_m)."""

    spacing = min(diameter_m / GRID_CELLS_PER_D, GRID_MAX_SPACING_DEM_PX * dem.pixel_size_m)
    cells = int(math.ceil(GRID_HALF_WIDTH_D * diameter_m / spacing))
    half_width = cells * spacing
    coords = np.linspace(-half_width, half_width, 2 * cells + 1)
    ee, nn = np.meshgrid(coords, coords)  # [i, j] = (e_j, n_i)
    _, plat, plon = sphere_points(ee, nn, lat, lon)
    heights = dem.sample(plat, plon, spacing_m=spacing, what=what).heights
    return heights, half_width, spacing


def _first_crest(prof: np.ndarray, min_drop: float) -> tuple[np.ndarray, np.ndarray]:
    """Index of the rim crest on each row of ``prof`` (radial profiles, inside to outside).

    The crest is the first point beyond the inner wall (the steepest outward rise of the profile) that
    the profile drops below by at least ``min_drop`` before it ever rises above it again: the top of
    the wall where the rim turns down into its outer flank. This is not always the highest point: a
    degraded rim on a regional slope, or next to a neighbour's higher rim, is lower than terrain further
    out. Where the profile
    never turns down (the terrain keeps rising beyond the rim), the rim is the knee of the profile:
    the point furthest above the chord from the profile's start to its highest point.
    Returns (index per row, True where the knee was used).
    """
    rows, n = prof.shape
    ahead = np.arange(n)[None, :] > np.arange(n)[:, None]  # [k, j]: j lies outside k
    higher = (prof[:, None, :] > prof[:, :, None]) & ahead[None]  # [row, k, j]: prof[j] > prof[k], j > k
    # Outer flank of k: the points between k and the first point higher than k (or the profile's end).
    first_higher = np.where(higher.any(axis=2), higher.argmax(axis=2), n)
    flank = ahead[None] & (np.arange(n)[None, None, :] < first_higher[:, :, None])
    lowest_after = np.where(flank, prof[:, None, :], np.inf).min(axis=2)
    is_crest = (prof - lowest_after) >= min_drop
    # Only beyond the inner wall (its steepest outward rise): a hill on the floor with a pit behind it
    # is not the rim.
    wall = np.diff(prof, axis=1).argmax(axis=1)
    is_crest &= np.arange(n)[None, :] > wall[:, None]
    fallback = ~is_crest.any(axis=1)
    # Knee: the point furthest above the chord from the profile's start to its highest point, i.e.
    # where the steep inner wall gives way to the gentler rise beyond it.
    top = prof.argmax(axis=1)
    idx = np.arange(n)[None, :]
    frac = np.clip(idx / np.maximum(top, 1)[:, None], 0.0, 1.0)
    chord = prof[:, :1] + frac * (prof[np.arange(rows), top] - prof[:, 0])[:, None]
    knee = np.where(idx <= top[:, None], prof - chord, -np.inf).argmax(axis=1)
    return np.where(fallback, knee, is_crest.argmax(axis=1)), fallback


def _rim_crest(grid, half_width, spacing, centre, radius_m, sin_az, cos_az, min_drop):
    """Per-azimuth rim crest (radius, height, knee flag) of the radial profiles about ``centre``."""
    lo, hi = RIM_SEARCH_FRAC
    step = PROFILE_STEP_D * 2.0 * radius_m
    radii = np.arange(lo * radius_m, hi * radius_m + 0.5 * step, step)
    e = centre[0] + np.outer(sin_az, radii)
    n = centre[1] + np.outer(cos_az, radii)
    prof = bilinear(grid, half_width, spacing, e, n)
    k, no_crest = _first_crest(prof, min_drop)
    return radii[k], prof[np.arange(k.size), k], no_crest


def _fit_circle(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Least-squares (Kasa) circle through points (x, y): (centre x, centre y, radius)."""
    a = np.stack([x, y, np.ones_like(x)], axis=1)
    sol, *_ = np.linalg.lstsq(a, x * x + y * y, rcond=None)
    cx, cy = 0.5 * float(sol[0]), 0.5 * float(sol[1])
    return cx, cy, math.sqrt(max(float(sol[2]) + cx * cx + cy * cy, 0.0))


def _refine_circle(x: np.ndarray, y: np.ndarray, inliers: np.ndarray, min_tolerance: float, scale_of_inliers: bool):
    """The outlier-rejecting refit of :func:`robust_circle` from the start ``inliers``: (cx, cy, r,
    inlier mask, tolerance). The robust sigma is the median residual of all points, or with
    ``scale_of_inliers`` of the current inliers only (a median over all points is an outlier's once
    half of them are outliers)."""
    tolerance = min_tolerance
    for _ in range(OUTLIER_PASSES):
        cx, cy, r = _fit_circle(x[inliers], y[inliers])
        residual = np.abs(np.hypot(x - cx, y - cy) - r)
        mad = float(np.median(residual[inliers] if scale_of_inliers else residual))
        tolerance = max(OUTLIER_MADS * 1.4826 * mad, min_tolerance)
        new = residual <= tolerance
        if new.sum() < 3 or np.array_equal(new, inliers):
            break
        inliers = new
    cx, cy, r = _fit_circle(x[inliers], y[inliers])
    return cx, cy, r, inliers, tolerance


def _ransac_start(x: np.ndarray, y: np.ndarray, threshold: float) -> np.ndarray | None:
    """Points within ``threshold`` of the best-supported circle through 3 of them (``RANSAC_SAMPLES``
    seeded draws: the same points give the same start); None when every draw is degenerate."""
    rng = np.random.default_rng(RANSAC_SEED)
    idx = rng.integers(0, x.size, size=(RANSAC_SAMPLES, 3))
    # Circumcircles about the points' mean (better conditioned than about the origin).
    px, py = x - x.mean(), y - y.mean()
    ax, bx, cx = px[idx].T
    ay, by, cy = py[idx].T
    d = 2.0 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by))
    a2, b2, c2 = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = (a2 * (by - cy) + b2 * (cy - ay) + c2 * (ay - by)) / d
        uy = (a2 * (cx - bx) + b2 * (ax - cx) + c2 * (bx - ax)) / d
    valid = np.isfinite(ux) & np.isfinite(uy) & (np.abs(d) > 1e-12 * (a2 + b2 + c2) ** 1.5)
    if not valid.any():
        return None
    ux, uy = ux[valid], uy[valid]
    rad = np.hypot(ax[valid] - ux, ay[valid] - uy)
    residual = np.abs(np.hypot(px[None, :] - ux[:, None], py[None, :] - uy[:, None]) - rad[:, None])
    support = residual <= threshold
    return support[int(np.argmax(support.sum(axis=1)))]


def robust_circle(x: np.ndarray, y: np.ndarray, min_tolerance: float, ransac: bool = False):
    """Circle through the crest points that agree on one: (centre (2,), radius, inlier mask, tolerance).

    Points whose distance to the fitted circle exceeds ``OUTLIER_MADS`` robust standard deviations
    (1.4826 x the median absolute residual, at least ``min_tolerance``) are dropped and the circle is
    refitted (``OUTLIER_PASSES`` times): an azimuth whose crest is a neighbour's rim or a massif beyond
    the crater must not pull the rim circle. With ``ransac`` the refit starts from all points and from a RANSAC start
    (the points within ``min_tolerance`` -- always inliers under the refit's rule -- of the best of
    ``RANSAC_SAMPLES`` seeded 3-point circles; its robust sigma is taken over its current inliers);
    the RANSAC one is kept only when its circle has more than ``RANSAC_MARGIN`` times as many points
    within ``min_tolerance`` as the other. From all points alone the fit is pulled off the rim once about
    30 % of the points are outliers; the RANSAC start holds it to about half
    (tests/test_robust_circle.py). Off by default: on real crests it locks onto a sub-arc where the plain
    fit does not (the catalogue's Idel'son centre offset 0.029 -> 0.092 D, Scott's rim 1.023 -> 0.936 D;
    the classical detector's rims: ``rim_ransac``, docs/history.md).
    """
    everything = np.ones(x.size, dtype=bool)
    cx, cy, r, inliers, tolerance = _refine_circle(x, y, everything, min_tolerance, False)
    if ransac and x.size > 3:
        start = _ransac_start(x, y, min_tolerance)
        if start is not None and start.sum() >= 3:
            alt = _refine_circle(x, y, start, min_tolerance, True)

            def support(c):
                return int(np.sum(np.abs(np.hypot(x - c[0], y - c[1]) - c[2]) <= min_tolerance))

            if support(alt) > RANSAC_MARGIN * support((cx, cy, r)):
                cx, cy, r, inliers, tolerance = alt
    return np.array([cx, cy]), r, inliers, tolerance


def _spill_level(grid: np.ndarray, outlet: np.ndarray) -> np.ndarray:
    """Water level each grid point holds when water may leave only through ``outlet`` (bool grid).

    The level at a point is the lowest possible maximum height along any path from it to the outlet
    (the "fill" of a depression-filling algorithm), computed by grey-scale reconstruction by erosion.
    """
    seed = np.where(outlet, grid, grid.max())
    return reconstruction(seed, grid, method="erosion")


def _spill_azimuth(grid, level, spill_height, dist, ring_radius, coords, centre) -> float:
    """Azimuth (deg clockwise from north, about ``centre``) of the spill point: the saddle where the
    crater's water, at the spill level, first touches ground that drains lower. Of several saddles,
    the one nearest the rim circle. NaN when there is none (the floor itself drains)."""
    from scipy.ndimage import binary_dilation

    eps = 1e-6 * max(1.0, abs(spill_height))
    drains = level < spill_height - eps
    saddle = (
        binary_dilation(drains, structure=np.ones((3, 3), bool))
        & ~drains
        & (np.abs(level - spill_height) <= eps)
        & (np.abs(grid - level) <= eps)
    )
    if not saddle.any():
        return float("nan")
    i, j = np.unravel_index(np.argmin(np.where(saddle, np.abs(dist - ring_radius), np.inf)), grid.shape)
    return float(np.degrees(np.arctan2(coords[j] - centre[0], coords[i] - centre[1])) % 360.0)


def measure_depression(dem, lat: float, lon: float, diameter_km: float, *, name: str = "crater") -> Depression:
    """Measure the depression around catalogue position (lat, lon) of diameter ``diameter_km`` in ``dem``.

    ``dem``: a :class:`crater_synth.terrain.dem.Dem`. Raises :class:`crater_synth.terrain.dem.DemCoverageError` when
    the measuring grid (+-1.25 D) leaves the DEM. Method: module docstring and docs/catalogue.md.
    """

    diameter_m = float(diameter_km) * 1000.0
    radius_m = 0.5 * diameter_m
    what = f"catalogue check of crater {name} (+-{GRID_HALF_WIDTH_D * diameter_km:.0f} km)"
    grid, half_width, spacing = _local_grid(dem, lat, lon, diameter_m, what=what)
    az = np.radians(np.arange(N_AZIMUTHS) * 360.0 / N_AZIMUTHS)
    sin_az, cos_az = np.sin(az), np.cos(az)

    min_drop = MIN_RIM_DROP_D * diameter_m
    centre = np.zeros(2)
    converged, iterations = False, 0
    # Keep the rim window inside the grid: the centre may not wander further than the grid allows.
    limit = half_width - RIM_SEARCH_FRAC[1] * radius_m
    for iterations in range(1, MAX_CENTRE_ITERATIONS + 1):
        r, _, _ = _rim_crest(grid, half_width, spacing, centre, radius_m, sin_az, cos_az, min_drop)
        new, _, _, _ = robust_circle(centre[0] + r * sin_az, centre[1] + r * cos_az, spacing)
        if iterations > 1:
            # Half steps: a crest that flips between two neighbouring bumps would otherwise make the
            # centre oscillate between two positions ~0.01 D apart instead of settling between them.
            new = 0.5 * (centre + new)
        new = np.clip(new, -limit, limit)
        moved = float(np.hypot(*(new - centre)))
        centre = new
        if moved < CENTRE_TOLERANCE_D * diameter_m:
            converged = True
            break

    r, h, no_crest = _rim_crest(grid, half_width, spacing, centre, radius_m, sin_az, cos_az, min_drop)
    _, fit_radius, inliers, tolerance = robust_circle(centre[0] + r * sin_az, centre[1] + r * cos_az, spacing)
    rim_radius = float(r[inliers].mean())
    # Closed depression: water has left the crater once it is beyond every rim-circle crest point.
    coords = np.linspace(-half_width, half_width, grid.shape[0])
    dist = np.hypot(coords[None, :] - centre[0], coords[:, None] - centre[1])
    level = _spill_level(grid, dist > fit_radius + tolerance)
    middle = dist <= FLOOR_RADIUS_FRAC * rim_radius
    floor_index = np.unravel_index(np.argmin(np.where(middle, grid, np.inf)), grid.shape)
    floor = float(grid[floor_index])
    spill_height = float(level[floor_index])
    spill_azimuth = _spill_azimuth(grid, level, spill_height, dist, fit_radius, coords, centre)
    _, clat, clon = sphere_points(np.array(centre[0]), np.array(centre[1]), lat, lon)
    spill_depth = spill_height - floor
    return Depression(
        centre_east_m=float(centre[0]),
        centre_north_m=float(centre[1]),
        centre_lat=float(clat),
        centre_lon=float(clon),
        centre_offset_d=float(np.hypot(*centre)) / diameter_m,
        rim_diameter_km=2.0 * rim_radius / 1000.0,
        rim_diameter_ratio=2.0 * rim_radius / diameter_m,
        rim_inlier_share=float(inliers.mean()),
        rim_crest_height_m=float(h[inliers].mean()),
        spill_height_m=spill_height,
        spill_azimuth_deg=spill_azimuth,
        floor_height_m=floor,
        spill_depth_m=spill_depth,
        spill_depth_d=spill_depth / diameter_m,
        no_crest_share=float(no_crest.mean()),
        iterations=iterations,
        converged=converged,
    )


# --------------------------------------------------------------------------------------------
# Catalogue listing
# --------------------------------------------------------------------------------------------
def open_dem(cfg):
    """The DEM the terrain of ``cfg`` is built from (``dem.path`` or ``dem.product``)."""
    s = patch.terrain_settings(cfg)
    return patch.open_dem(s["dem"]["product"], s["dem"]["path"], s["data_dir"])[0]


def square_inside(dem, lat: float, lon: float, half_width_m: float, points_per_side: int = 41) -> bool:
    """True when the local square (e, n) in [-half_width_m, half_width_m]^2 lies inside the DEM.

    Its border is tested (the DEM is convex in its own projection, the square's image is not a square).
    """

    t = np.linspace(-half_width_m, half_width_m, points_per_side)
    one = np.full_like(t, half_width_m)
    e = np.concatenate([t, t, -one, one])
    n = np.concatenate([-one, one, t, t])
    _, plat, plon = sphere_points(e, n, lat, lon)
    return bool(dem.inside(*dem.latlon_to_pixel(plat, plon)).all())


def check(dem, crater: dict, near_radius_factor: float) -> dict:
    """One catalogue row: the entry, its measured depression (None when it could not be measured) and
    the failed criteria (empty: the entry passes). ``near_radius_factor``: the terrain patch's near-field
    half-width in diameters (``terrain.near_radius_factor``), which must fit inside the DEM."""
    try:
        check_hemisphere(dem, crater["name"], crater["lat"])
    except DemError as exc:  # nothing else about the entry can be measured in this DEM
        return {**crater, "measured": None, "failures": [str(exc)], "passes": False}
    failures = []
    try:
        m = measure_depression(dem, crater["lat"], crater["lon"], crater["diameter_km"], name=crater["name"])
        measured = m.as_dict()
        failures += m.failures()
    except DemError as exc:
        measured = None
        failures.append(str(exc))
    half_width = near_radius_factor * crater["diameter_km"] * 1000.0
    if not square_inside(dem, crater["lat"], crater["lon"], half_width):
        failures.append(
            f"terrain near field (+-{near_radius_factor:g} D = +-{half_width / 1e3:.0f} km) leaves DEM {dem.product}"
        )
    return {**crater, "measured": measured, "failures": failures, "passes": not failures}


def format_table(rows: list[dict]) -> str:
    """Plain-text table of :func:`check` rows."""
    head = (
        f"{'crater':<14}{'lat':>8}{'lon':>9}{'D km':>7}{'offset/D':>9}{'rim D/D':>8}{'spill m':>8}"
        f"{'spill/D':>8}  result"
    )
    lines = [head, "-" * len(head)]
    for row in rows:
        m = row["measured"]
        cells = (
            (
                f"{m['centre_offset_d']:>9.3f}{m['rim_diameter_ratio']:>8.2f}{m['spill_depth_m']:>8.0f}"
                f"{m['spill_depth_d']:>8.3f}"
            )
            if m
            else f"{'-':>9}{'-':>8}{'-':>8}{'-':>8}"
        )
        lines.append(
            f"{row['name']:<14}{row['lat']:>8.2f}{row['lon']:>9.2f}{row['diameter_km']:>7.1f}{cells}  "
            + ("ok" if row["passes"] else "FAIL: " + "; ".join(row["failures"]))
        )
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Contact sheets: the real WAC crop and the DEM hillshade of each entry's sigma box
# --------------------------------------------------------------------------------------------
SHEET_TILE_PX = 160  # each box resampled to this many pixels per side
DARK_DN, SATURATED_DN = 8, 250  # WAC crop statistics: near-black (shadow or no data) and saturated pixels
HILLSHADE_SUN = (315.0, 45.0)  # (azimuth from image up, clockwise; elevation) deg: the cartographic default


def _box_uv(mosaic, crater: dict, sigma: float):
    """Centre (u, v) and side (px) of the real-crop box of ``sigma`` (as ``train.realset`` cuts it:
    side = sigma x D / mosaic pixel, axis-aligned in the mosaic, centred on the catalogue position)."""
    cu, cv = mosaic.latlon_to_uv(crater["lat"], crater["lon"])
    return cu, cv, sigma * crater["diameter_km"] * 1000.0 / mosaic.pixel_m


def _tile_points(mosaic, cu: float, cv: float, side: float):
    """Mosaic (u, v) of the tile's pixel centres, (n, n) each, row 0 at the top."""
    t = (np.arange(SHEET_TILE_PX) + 0.5) / SHEET_TILE_PX * side - side / 2
    return np.meshgrid(cu + t, cv + t)


def _hillshade(h: np.ndarray, spacing: float) -> np.ndarray:
    """Lambertian hillshade in [0, 1] of heights ``h`` (rows down, columns right, ``spacing`` m)."""
    az, el = np.radians(HILLSHADE_SUN[0]), np.radians(HILLSHADE_SUN[1])
    dz_dv, dz_du = np.gradient(h, spacing)
    # Normal of z(u, v) with v pointing down the image: (-dz/du, +dz/dv, 1); the sun towards the image's
    # upper left at azimuth 315 deg.
    sun = np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])
    shade = (-dz_du * sun[0] + dz_dv * sun[1] + sun[2]) / np.sqrt(1.0 + dz_du**2 + dz_dv**2)
    return np.clip(shade, 0.0, 1.0)


def box_images(dem, mosaic, crater: dict, sigma: float) -> dict:
    """The WAC crop (float, 0-255) and the DEM hillshade (0-1) of an entry's sigma box, and the crop's
    statistics: share of near-black pixels (<= DARK_DN: shadow or no data) and saturated ones."""
    from scipy.ndimage import map_coordinates

    cu, cv, side = _box_uv(mosaic, crater, sigma)
    uu, vv = _tile_points(mosaic, cu, cv, side)
    wac = map_coordinates(mosaic.image.astype(np.float32), [vv - 0.5, uu - 0.5], order=1, mode="nearest")
    nearest = map_coordinates(mosaic.image, [vv - 0.5, uu - 0.5], order=0, mode="nearest")
    lat, lon = mosaic.uv_to_latlon(uu, vv)
    spacing = side * mosaic.pixel_m / SHEET_TILE_PX
    h = dem.sample(lat, lon, spacing_m=spacing, what=f"sheet box of crater {crater['name']}").heights
    return {
        "wac": wac,
        "hillshade": _hillshade(h, spacing),
        "centre_uv": (cu, cv),
        "side_px": side,
        "dark_share": float((nearest <= DARK_DN).mean()),
        "saturated_share": float((nearest >= SATURATED_DN).mean()),
    }


def write_sheets(rows: list[dict], dem, mosaic, sigma: float, wac_png: Path | None, dem_png: Path | None) -> dict:
    """Contact sheets of every row's sigma box: the real WAC crop and/or the DEM hillshade, with the
    catalogue circle (dashed) and the measured rim circle (solid). Returns {name: crop statistics}."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    images = {r["name"]: box_images(dem, mosaic, r, sigma) for r in rows}
    cols = min(7, len(rows))
    nrows = -(-len(rows) // cols)
    for kind, path in (("wac", wac_png), ("hillshade", dem_png)):
        if path is None:
            continue
        fig = Figure(figsize=(2.3 * cols, 2.75 * nrows + 0.4), dpi=110)
        axes = fig.subplots(nrows, cols, squeeze=False)
        for ax in axes.ravel():
            ax.axis("off")
        for ax, row in zip(axes.ravel(), rows):
            im = images[row["name"]]
            (cu, cv), side = im["centre_uv"], im["side_px"]
            if kind == "wac":
                ax.imshow(im["wac"], cmap="gray", vmin=0, vmax=255, interpolation="nearest")
            else:
                ax.imshow(im["hillshade"], cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            to_tile = SHEET_TILE_PX / side
            # Circles in the mosaic: polar stereographic scale k = 2 / (1 + sin|lat|) at the crater.
            k = 2.0 / (1.0 + math.sin(math.radians(abs(row["lat"]))))
            t = np.linspace(0.0, 2.0 * np.pi, 181)
            r_cat = 0.5 * k * row["diameter_km"] * 1000.0 / mosaic.pixel_m * to_tile
            ax.plot(
                SHEET_TILE_PX / 2 + r_cat * np.cos(t),
                SHEET_TILE_PX / 2 + r_cat * np.sin(t),
                "--",
                color="#50c0ff",
                lw=0.8,
            )
            m = row["measured"]
            if m:
                mu, mv = mosaic.latlon_to_uv(m["centre_lat"], m["centre_lon"])
                r_rim = 0.5 * k * m["rim_diameter_km"] * 1000.0 / mosaic.pixel_m * to_tile
                ax.plot(
                    (mu - cu) * to_tile + SHEET_TILE_PX / 2 + r_rim * np.cos(t),
                    (mv - cv) * to_tile + SHEET_TILE_PX / 2 + r_rim * np.sin(t),
                    "-",
                    color="#ff5050",
                    lw=0.7,
                )
            title = f"{row['name']}  D {row['diameter_km']:.0f} km"
            if m:
                title += (
                    f"\noff {m['centre_offset_d']:.2f}D  rim {m['rim_diameter_ratio']:.2f}D  "
                    f"spill {m['spill_depth_d']:.3f}D"
                )
            if kind == "wac":
                title += f"\ndark {im['dark_share']:.0%}  saturated {im['saturated_share']:.0%}"
            ax.set_title(title, fontsize=6.5, color="black" if row["passes"] else "#c00000")
        what = "real LROC WAC mosaic (400 m/px)" if kind == "wac" else f"{dem.product} hillshade"
        fig.suptitle(
            f"{what}: box side {sigma:g} D about the catalogue position, image up = mosaic up; "
            "blue dashed: catalogue D; red: measured rim",
            fontsize=8,
        )
        fig.tight_layout(rect=(0, 0, 1, 0.98))
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=110, facecolor="white")
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, buf.getvalue())
    return {
        name: {"dark_share": im["dark_share"], "saturated_share": im["saturated_share"]} for name, im in images.items()
    }


@click.command("catalogue")
@click.option("--json", "as_json", is_flag=True, help="One JSON line per crater instead of a table.")
@click.option(
    "--wac-sheet",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also write a contact sheet of the real WAC crops of every entry to this PNG.",
)
@click.option(
    "--dem-sheet",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also write a contact sheet of the DEM hillshade of the same boxes to this PNG.",
)
@click.option("--sigma", type=float, default=1.4, show_default=True, help="Box side of the sheets, in D.")
@OVERRIDES
@user_errors
def catalogue_command(as_json, wac_sheet, dem_sheet, sigma, overrides):
    """Measure each catalogue crater in the DEM: centre offset, rim diameter, spill depth (docs/catalogue.md).

    Default: every entry of configs/crater/ in the DEM's hemisphere (the south-polar ones with the
    default DEM, the north-polar ones with ``dem=lola_ldem256_north``). With a ``crater=[a,b,...]``
    override, those entries.
    Exit status 1 when an entry fails the catalogue test. Example: ``crater-synth catalogue
    'crater=[haworth,faustini]'``
    """
    selected = any(o.split("=", 1)[0].lstrip("+~") == "crater" for o in overrides)
    if not selected:
        overrides = (f"crater=[{','.join(catalogue_names())}]", *overrides)
    cfg, settings = compose_settings(overrides)
    dem = open_dem(cfg)
    factor = terrain_settings(cfg)["near_radius_factor"]
    entries = craters(cfg)
    if not selected and dem.hemisphere() is not None:
        entries = [c for c in entries if hemisphere(c["lat"]) == dem.hemisphere()]
    rows = [check(dem, c, factor) for c in entries]
    if as_json:
        for row in rows:
            click.echo(json.dumps(row))
    else:
        click.echo(
            f"DEM {dem.product} ({dem.pixel_size_m:g} m/px). Pass: centre offset <= {MAX_CENTRE_OFFSET_D:g} D, "
            f"|rim D / D - 1| <= {MAX_DIAMETER_ERROR:g}, spill depth >= {MIN_SPILL_DEPTH_D:g} D, "
            f"terrain near field (+-{factor:g} D) inside the DEM."
        )
        click.echo(format_table(rows))
    if wac_sheet or dem_sheet:
        from train.realset import load_mosaic

        if not sigma > 0:
            raise UserError(f"--sigma={sigma} must be > 0")
        stats = write_sheets(rows, dem, load_mosaic(settings.realset), sigma, wac_sheet, dem_sheet)
        for path in (wac_sheet, dem_sheet):
            if path:
                click.echo(f"wrote {path}", err=True)
        if as_json:
            click.echo(json.dumps({"sheet_stats": stats}))
    if not all(r["passes"] for r in rows):
        raise SystemExit(1)
