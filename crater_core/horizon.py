"""Horizon maps: cast shadows of a height field under parallel sun rays, for every sun elevation at once.

Physics (docs/renderer.md, "Shadows: horizon maps"). Sun rays are parallel in the crater's ENU
frame, and the terrain vertices already include the Moon's curvature (terrain at distance d has
dropped by ~d^2 / 2R), so the horizon elevation of a surface point p along the sun azimuth phi is

    h(p) = max over t > 0 of atan((z(p + t d) - z(p)) / t),    d = (sin phi, cos phi)

over the near field and the far field. The Sun is a disc of angular radius
``SUN_RADIUS_RAD`` (half of ``geometry.SUN_ANGULAR_DIAMETER_DEG``); at sun elevation theta the
visible fraction of the disc above a locally straight horizon is the circular-segment area
:func:`disc_fraction_above` of x = (theta - h) / radius: 0 in the umbra, 1 in full sun, the penumbra
in between. One map per (terrain, sun azimuth) serves every sun elevation.

Numerics (all numpy, float32 where it is safe):
- The near field is read with Catmull-Rom (cubic convolution, Keys 1981, a = -0.5) interpolation of
  its vertex grid. It reproduces quadratics exactly, so a smooth rim crest running diagonally across
  the grid does not sag between vertices, as bilinear or triangle interpolation does; at a grazing
  sun each metre of sag moves the shadow edge by 1 / tan(theta) metres (358 m at 0.16 deg), which is
  the periodic saw-tooth of faceted shadow edges. The value is clamped to the range of its cell's
  four vertices (no ringing above a cliff). The far field (coarse, no detail) is bilinear.
- Per map level, heights are resampled onto a grid rotated so that its rows run along d, with the
  level's texel spacing: the ray from every sample then visits samples k = 1, 2, ... of its own row
  (shifted arrays, no per-step interpolation). Beyond k = 32 the row is read through max-pooled
  windows of width w <= k / 32 (divisor: the window's mid distance), so no crest between samples is
  missed and the elevation of the horizon is within ~1.5 % of its value.
- Occluders closer than ``MIN_OCCLUDER_DISTANCE_SPACINGS`` near-grid spacings are ignored: below
  that scale the surface between vertices is not known, and its slope is the shading normal's
  business (mu0 = N.s <= 0 is self-shadow), as in Cycles' smooth-shaded mesh. Chosen by measurement
  against direct mode (docs/renderer.md): on the real Shackleton terrain (12 paper items) the mean
  |bias| is 3.5 / 1.6 / 0.5 % for 0 / 1 / 2 spacings, on the synthetic test crater the worst 2.9 /
  0.5 / 0.5 %.
- Each texel also keeps the distance t* of the occluder that sets its horizon and the eye height z
  the horizon was computed for: the renderer corrects the slope to the height z' of the surface
  point the camera actually sees (the triangulated mesh, metres away from this interpolated surface
  on rough terrain), tan h' = tan h + (z - z') / t*. Without it the nearest occluders' slopes are
  noisy and their maximum biased high (fast renders 3.5 % too dark on the real terrain).
- Terrain outside the near field is handled on a coarse rotated grid at the far-field spacing; its
  best slope F, the occluder's distance t* and the eye height Z there are interpolated to each fine
  sample and corrected to first order for the fine eye height: F + (Z - z) / t*.
- The rotated-grid horizons are resampled bilinearly onto the nested square texel levels the
  renderer looks them up in (``levels`` x ``px`` x ``px``, level k of half-width halves[k]).
"""

from __future__ import annotations

import math

import numpy as np

from crater_core import geometry

SUN_RADIUS_RAD = math.radians(geometry.SUN_ANGULAR_DIAMETER_DEG) / 2.0
HORIZON_VERSION = 2  # bump when the maps' numerics change (part of the cache key)
# Beyond this many samples the row is read through max-pooled windows of width <= k / WINDOW_RATIO.
WINDOW_RATIO = 32
MIN_OCCLUDER_DISTANCE_SPACINGS = 2.0  # terrain closer than this (near-grid spacings) is left to the shading normal
NO_OCCLUDER_SLOPE = -1.0  # tan of -45 deg: "nothing above" (far below any sun the sweep uses)
NO_OCCLUDER_DISTANCE_M = 1e12
PLANES = ("slope", "distance", "eye_z")  # what a map holds per texel (see horizon_maps)
# Rows of a rotated grid scanned together: a few hundred kB per array, in cache (64-128 measured
# fastest on this 2-core machine, 2x a scan of the whole array).
ROW_BLOCK = 128


# ------------------------------------------------------------------------------------------------
# Solar disc
# ------------------------------------------------------------------------------------------------
def disc_fraction_above(sun_elevation_rad, horizon_rad, radius_rad: float = SUN_RADIUS_RAD) -> np.ndarray:
    """Visible fraction of a uniform disc of angular ``radius_rad`` centred at ``sun_elevation_rad``
    above a straight horizon at ``horizon_rad`` (circular segment area / disc area)."""
    x = np.clip((np.asarray(sun_elevation_rad, dtype=np.float32) - horizon_rad) / np.float32(radius_rad), -1.0, 1.0)
    return (1.0 - (np.arccos(x) - x * np.sqrt(1.0 - x * x)) / np.float32(math.pi)).astype(np.float32)


def disc_lit_factor(
    sun_elevation_rad, horizon_rad, mu0, dmu0_delevation, radius_rad: float = SUN_RADIUS_RAD
) -> np.ndarray:
    """<max(N.l, 0) V(l)>_disc / mu0: the factor the disc-centre radiance factor is multiplied by.

    The disc element at vertical offset delta (in the sun's elevation direction) has
    N.l ~= mu0 + g delta with g = d(N.s)/d(elevation); over the part above the horizon
    (delta > -x r, x = (theta - h) / r) its mean is mu0 * fraction + g * (2/3) r^3 (1 - x^2)^{3/2} / (pi r^2).
    Within a solar radius of the local horizon the second term matters (the visible upper part of the
    disc is lit more steeply than its centre), as in Cycles' disc sampling; the value may exceed 1
    there, like direct mode's. ``mu0`` must be > 0."""
    x = np.clip((np.asarray(sun_elevation_rad, dtype=np.float32) - horizon_rad) / np.float32(radius_rad), -1.0, 1.0)
    fraction = 1.0 - (np.arccos(x) - x * np.sqrt(1.0 - x * x)) / np.float32(math.pi)
    moment = np.float32(2.0 * radius_rad / (3.0 * math.pi)) * (1.0 - x * x) ** 1.5
    return (fraction + dmu0_delevation * moment / mu0).astype(np.float32)


def mean_disc_lit_factor(sun_elevation_rad, horizons_rad, mu0, dmu0_delevation, radius_rad: float = SUN_RADIUS_RAD):
    """Mean of :func:`disc_lit_factor` over sub-pixel horizons ``horizons_rad`` (k, n), for n points.

    Only points with a sub-pixel horizon within a solar radius of the Sun's centre (the penumbra band,
    usually a few % of them) need the disc integral; every other sub-pixel sees the whole disc (1) or
    none of it (0), exactly what the formula gives at x = +-1."""
    theta = np.float32(sun_elevation_rad)
    r = np.float32(radius_rad)
    h = np.asarray(horizons_rad, dtype=np.float32)
    out = (h <= theta - r).sum(axis=0, dtype=np.float32) / np.float32(h.shape[0])
    band = (np.abs(h - theta) < r).any(axis=0)
    if band.any():
        mu0_b, slope_b = np.asarray(mu0)[band], np.asarray(dmu0_delevation)[band]
        total = sum(disc_lit_factor(theta, hk[band], mu0_b, slope_b, radius_rad) for hk in h)
        out[band] = total / np.float32(h.shape[0])
    return out.astype(np.float32, copy=False)


# ------------------------------------------------------------------------------------------------
# Height fields
# ------------------------------------------------------------------------------------------------
class GridSurface:
    """z(x, y) of a terrain grid (rows, cols, 3) of ENU vertices on a (near-)regular x/y lattice.

    ``cubic``: Catmull-Rom interpolation (else bilinear). ``keep_quads``: cells that exist (far field);
    points in a dropped cell, or outside the grid, are NaN."""

    def __init__(self, xyz: np.ndarray, cubic: bool, keep_quads: np.ndarray | None = None):
        xyz = np.asarray(xyz, dtype=np.float64)
        self.rows, self.cols = xyz.shape[:2]
        rm, cm = self.rows // 2, self.cols // 2
        self.x0 = float(xyz[rm, 0, 0])
        self.dx = float(xyz[rm, -1, 0] - self.x0) / (self.cols - 1)
        self.y0 = float(xyz[0, cm, 1])
        self.dy = float(xyz[-1, cm, 1] - self.y0) / (self.rows - 1)
        self.z = np.ascontiguousarray(xyz[..., 2], dtype=np.float32).ravel()
        self.cubic = cubic
        if cubic:
            self.z_padded = np.pad(self.z.reshape(self.rows, self.cols), 1, mode="edge").ravel()
        self.keep = None if keep_quads is None else np.asarray(keep_quads, dtype=bool)
        xs = (self.x0, self.x0 + self.dx * (self.cols - 1))
        ys = (self.y0, self.y0 + self.dy * (self.rows - 1))
        self.bounds = (min(xs), max(xs), min(ys), max(ys))
        self.spacing = max(abs(self.dx), abs(self.dy))

    def inside(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x0, x1, y0, y1 = self.bounds
        return (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        fc = ((x - self.x0) / self.dx).astype(np.float32)
        fr = ((y - self.y0) / self.dy).astype(np.float32)
        ok = (fc >= 0) & (fc <= self.cols - 1) & (fr >= 0) & (fr <= self.rows - 1)
        c1 = np.clip(np.floor(fc), 0, self.cols - 2).astype(np.int64)
        r1 = np.clip(np.floor(fr), 0, self.rows - 2).astype(np.int64)
        tc = fc - c1
        tr = fr - r1
        if self.keep is not None:
            ok &= self.keep[r1, c1]
        if self.cubic:
            # Edge-replicated padding: the 4 x 4 stencil needs no index clipping.
            stride = self.cols + 2
            base = (r1 + 1) * stride + (c1 + 1)
            zp = self.z_padded
            wc, wr = _catmull_rom_weights(tc), _catmull_rom_weights(tr)
            out = np.zeros(fc.shape, dtype=np.float32)
            for i in range(4):
                ri = base + (i - 1) * stride
                row = np.zeros(fc.shape, dtype=np.float32)
                for j in range(4):
                    row += wc[j] * zp[ri + (j - 1)]
                out += wr[i] * row
            # No overshoot: clamp to the range of the cell's four vertices (a cliff spanning one cell
            # would otherwise ring ~5 % above its top and lengthen its shadow accordingly).
            a, b, c, d = zp[base], zp[base + 1], zp[base + stride], zp[base + stride + 1]
            out = np.clip(
                out, np.minimum(np.minimum(a, b), np.minimum(c, d)), np.maximum(np.maximum(a, b), np.maximum(c, d))
            )
        else:
            base = r1 * self.cols + c1
            top = self.z[base] * (1 - tc) + self.z[base + 1] * tc
            bot = self.z[base + self.cols] * (1 - tc) + self.z[base + self.cols + 1] * tc
            out = top * (1 - tr) + bot * tr
        return np.where(ok, out, np.float32(np.nan))


def _catmull_rom_weights(t: np.ndarray) -> list[np.ndarray]:
    t2 = t * t
    t3 = t2 * t
    return [-0.5 * t3 + t2 - 0.5 * t, 1.5 * t3 - 2.5 * t2 + 1.0, -1.5 * t3 + 2.0 * t2 + 0.5 * t, 0.5 * t3 - 0.5 * t2]


class Terrain:
    """The near field (Catmull-Rom) and, outside it, the far field (bilinear, kept quads only)."""

    def __init__(
        self, near_xyz: np.ndarray, far_xyz: np.ndarray | None = None, far_keep_quads: np.ndarray | None = None
    ):
        self.near = GridSurface(near_xyz, cubic=True)
        self.far = None
        if far_xyz is not None and np.size(far_xyz) and far_xyz.shape[0] > 1 and far_xyz.shape[1] > 1:
            self.far = GridSurface(far_xyz, cubic=False, keep_quads=far_keep_quads)

    @property
    def extent(self) -> float:
        """Half-width of the square holding all the terrain (m)."""
        b = self.far.bounds if self.far is not None else self.near.bounds
        return float(max(abs(v) for v in b))

    def heights(self, x: np.ndarray, y: np.ndarray, near: bool = True, far: bool = True) -> np.ndarray:
        """z at (x, y); NaN where no terrain. ``near``/``far`` select which field may answer."""
        in_near = self.near.inside(x, y)
        z = np.full(np.shape(x), np.nan, dtype=np.float32)
        if near and in_near.any():
            z[in_near] = self.near.sample(x[in_near], y[in_near])
        if far and self.far is not None and (~in_near).any():
            z[~in_near] = self.far.sample(x[~in_near], y[~in_near])
        return z


# ------------------------------------------------------------------------------------------------
# Horizons along rows of a rotated grid
# ------------------------------------------------------------------------------------------------
def _row_horizon_slopes(
    z_occluder: np.ndarray, z_eye: np.ndarray, spacing: float, k_min: int = 1, n_eye: int | None = None
):
    """(best slope, distance of its occluder) with best slope = max over k >= k_min of
    (z_occluder[:, j + k] - z_eye[:, j]) / (k * spacing), for every (i, j) with j < ``n_eye`` (the
    eyes the map needs; occluders run to the row's end); NaN occluders never win. Windows of
    max-pooled occluders beyond k = WINDOW_RATIO (module doc).

    Rows are independent: they are scanned in blocks of ``ROW_BLOCK`` that stay in cache (same result
    as one scan of the whole array, bit for bit, ~2x faster)."""
    rows, n = z_occluder.shape
    m = n if n_eye is None else max(1, min(int(n_eye), n))
    occ_all = np.where(np.isnan(z_occluder), np.float32(-1e30), z_occluder).astype(np.float32)
    eye_all = np.where(np.isnan(z_eye[:, :m]), np.float32(1e30), z_eye[:, :m]).astype(np.float32)
    best_all = np.full((rows, m), NO_OCCLUDER_SLOPE, dtype=np.float32)
    dist_all = np.full((rows, m), NO_OCCLUDER_DISTANCE_M, dtype=np.float32)
    cand_buf = np.empty((ROW_BLOCK, m), dtype=np.float32)
    mask_buf = np.empty((ROW_BLOCK, m), dtype=bool)
    for r0 in range(0, rows, ROW_BLOCK):
        r1 = min(rows, r0 + ROW_BLOCK)
        occ, eye, best, best_t = occ_all[r0:r1], eye_all[r0:r1], best_all[r0:r1], dist_all[r0:r1]
        pooled, width = occ, 1  # pooled[:, j] = max(occ[:, j : j + width])
        k = max(1, int(k_min))
        while k < n:
            while k >= WINDOW_RATIO * 2 * width and 2 * width < n:
                nxt = pooled.copy()
                nxt[:, :-width] = np.maximum(pooled[:, :-width], pooled[:, width:])
                pooled, width = nxt, 2 * width
            dist = (k + 0.5 * (width - 1)) * spacing
            w = min(m, n - k)
            cand, better = cand_buf[: r1 - r0, :w], mask_buf[: r1 - r0, :w]
            np.subtract(pooled[:, k : k + w], eye[:, :w], out=cand)
            cand *= np.float32(1.0 / dist)
            np.greater(cand, best[:, :w], out=better)
            np.copyto(best[:, :w], cand, where=better)
            np.copyto(best_t[:, :w], np.float32(dist), where=better)
            k += width
    return best_all, dist_all


def _far_row_horizon(z_occluder: np.ndarray, z_eye: np.ndarray, spacing: float):
    """(best slope, distance of the best occluder) along rows; every k, no pooling (coarse grid)."""
    rows, n = z_occluder.shape
    occ = np.where(np.isnan(z_occluder), np.float32(-1e30), z_occluder).astype(np.float32)
    eye = np.where(np.isnan(z_eye), np.float32(1e30), z_eye).astype(np.float32)
    best = np.full((rows, n), NO_OCCLUDER_SLOPE, dtype=np.float32)
    best_t = np.full((rows, n), NO_OCCLUDER_DISTANCE_M, dtype=np.float32)
    for k in range(1, n):
        slope = (occ[:, k:] - eye[:, :-k]) * np.float32(1.0 / (k * spacing))
        better = slope > best[:, :-k]
        best[:, :-k] = np.where(better, slope, best[:, :-k])
        best_t[:, :-k] = np.where(better, np.float32(k * spacing), best_t[:, :-k])
    return best, best_t


class _RotatedGrid:
    """Samples (c_i, a_j) = (c0 + i ds, a0 + j ds): a along the sun azimuth, c across it."""

    def __init__(self, azimuth_deg: float, c_half: float, a_start: float, a_end: float, spacing: float):
        phi = math.radians(azimuth_deg)
        self.d = (math.sin(phi), math.cos(phi))  # towards the sun (x east, y north)
        self.e = (math.cos(phi), -math.sin(phi))  # across
        self.ds = float(spacing)
        self.c0 = -float(c_half)
        self.a0 = float(a_start)
        self.nc = int(math.ceil(2 * c_half / spacing)) + 1
        self.na = max(2, int(math.ceil((a_end - a_start) / spacing)) + 1)
        self.i_lo = self.j_lo = 0  # first lattice row / column kept (see crop)

    def crop(self, half_extent: float) -> int:
        """Keep the lattice rows with |c| <= ``half_extent`` and the columns from a >= -``half_extent``
        on (one sample of margin each way), with the same sample positions; returns how many of the
        kept columns have a <= ``half_extent``: the eyes a map of that half-width needs. Along a row,
        an eye only looks at the samples after it, so what is dropped changes no kept value."""
        i_lo = max(0, int(math.floor((-half_extent - self.c0) / self.ds)) - 1)
        i_hi = min(self.nc - 1, int(math.ceil((half_extent - self.c0) / self.ds)) + 1)
        j_lo = max(0, int(math.floor((-half_extent - self.a0) / self.ds)) - 1)
        j_hi = min(self.na - 1, int(math.ceil((half_extent - self.a0) / self.ds)) + 1)
        self.nc, self.na = i_hi - i_lo + 1, self.na - j_lo
        self.i_lo, self.j_lo = i_lo, j_lo
        return j_hi - j_lo + 1

    def points(self):
        i = np.arange(self.i_lo, self.i_lo + self.nc, dtype=np.float64)
        j = np.arange(self.j_lo, self.j_lo + self.na, dtype=np.float64)
        c = (self.c0 + self.ds * i)[:, None]
        a = (self.a0 + self.ds * j)[None, :]
        return a * self.d[0] + c * self.e[0], a * self.d[1] + c * self.e[1]

    def fractional_index(self, x: np.ndarray, y: np.ndarray):
        """(row i, column j) float indices of ENU points into the kept samples."""
        a = x * self.d[0] + y * self.d[1]
        c = x * self.e[0] + y * self.e[1]
        return (c - self.c0) / self.ds - self.i_lo, (a - self.a0) / self.ds - self.j_lo


def _bilinear_weights(shape: tuple, fi: np.ndarray, fj: np.ndarray):
    """(flat index of the top-left neighbour, ti, tj, row stride) of float indices into an array of
    ``shape``, clamped to it: computed once, applied to several planes by :func:`_bilinear_apply`."""
    n0, n1 = shape
    fi = np.clip(fi, 0.0, n0 - 1.000001)
    fj = np.clip(fj, 0.0, n1 - 1.000001)
    i0 = np.floor(fi).astype(np.int64)
    j0 = np.floor(fj).astype(np.int64)
    return i0 * n1 + j0, (fi - i0).astype(np.float32), (fj - j0).astype(np.float32), n1


def _bilinear_apply(values: np.ndarray, weights) -> np.ndarray:
    base, ti, tj, n1 = weights
    v = values.ravel()
    top = v[base] * (1 - tj) + v[base + 1] * tj
    bot = v[base + n1] * (1 - tj) + v[base + n1 + 1] * tj
    return top * (1 - ti) + bot * ti


def texel_centres(half_width: float, px: int):
    """ENU (x, y) of a level's texel centres: row 0 north, column 0 west."""
    d = 2.0 * half_width / px
    c = -half_width + (np.arange(px) + 0.5) * d
    x, y = np.meshgrid(c, c[::-1])
    return x, y


def horizon_maps(terrain: Terrain, azimuth_deg: float, halves, px: int) -> np.ndarray:
    """Horizon along ``azimuth_deg`` at the texel centres of every nested level: float32
    (levels, 3, px, px) holding, per texel, the horizon slope tan(h), the distance of the occluder
    that sets it (m; ``NO_OCCLUDER_DISTANCE_M`` if none) and the eye height z it was computed for.
    A point at height z' near the texel sees the same occluder at slope tan(h) + (z - z') / t*:
    the renderer corrects to the height of the surface the camera sees (the mesh), which differs
    from this interpolated surface by metres on rough terrain (:func:`pixel_slope`)."""
    phi = math.radians(azimuth_deg)
    reach = abs(math.sin(phi)) + abs(math.cos(phi))  # max of p.d over the unit square
    near_half = max(abs(v) for v in terrain.near.bounds)
    outer = max(halves)
    # Far part: terrain outside the near field, on a coarse rotated grid over the whole map.
    far = None
    if terrain.far is not None:
        coarse = max(terrain.far.spacing, terrain.near.spacing)
        c_half = outer * math.sqrt(2.0) + 2 * coarse
        g = _RotatedGrid(azimuth_deg, c_half, -c_half, terrain.extent * reach + coarse, coarse)
        x, y = g.points()
        z_eye = terrain.heights(x, y)
        z_occ = np.where(terrain.near.inside(x, y), np.float32(np.nan), z_eye)
        slope, dist = _far_row_horizon(z_occ, z_eye, coarse)
        far = (g, slope, dist, z_eye)
    maps = []
    for half in halves:
        spacing = 2.0 * half / px
        c_half = half * math.sqrt(2.0) + 2 * spacing
        g = _RotatedGrid(azimuth_deg, c_half, -c_half, max(c_half, near_half * reach) + spacing, spacing)
        # Only the samples around the map square are eyes: |a|, |c| <= half x reach (its corners along
        # this azimuth); the occluders beyond it run to the terrain's edge.
        n_eye = g.crop(half * reach)
        x, y = g.points()
        z_eye = terrain.heights(x, y)
        z_occ = np.where(terrain.near.inside(x, y), z_eye, np.float32(np.nan))  # the near field's occluders
        k_min = int(math.ceil(MIN_OCCLUDER_DISTANCE_SPACINGS * terrain.near.spacing / spacing - 1e-9))
        slope, dist = _row_horizon_slopes(z_occ, z_eye, spacing, k_min, n_eye)
        x, y, z_eye = x[:, :n_eye], y[:, :n_eye], z_eye[:, :n_eye]
        eye = np.nan_to_num(z_eye, nan=0.0).astype(np.float32)
        if far is not None:
            fg, f_slope, f_dist, f_eye = far
            wf = _bilinear_weights(f_eye.shape, *fg.fractional_index(x, y))
            zc = _bilinear_apply(np.nan_to_num(f_eye, nan=0.0), wf)
            t_far = _bilinear_apply(f_dist, wf)
            corrected = (_bilinear_apply(f_slope, wf) + (zc - eye) / t_far).astype(np.float32)
            better = corrected > slope
            slope = np.where(better, corrected, slope)
            dist = np.where(better, t_far, dist)
        tx, ty = texel_centres(half, px)
        wt = _bilinear_weights(slope.shape, *g.fractional_index(tx, ty))
        planes = (np.maximum(slope, NO_OCCLUDER_SLOPE), dist, eye)
        maps.append(np.stack([_bilinear_apply(plane, wt) for plane in planes]))
    return np.stack(maps).astype(np.float32)


def pixel_slope(slope: np.ndarray, distance: np.ndarray, eye_z: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Horizon slope seen from height ``z`` instead of the map's ``eye_z`` (same occluder)."""
    return slope + (eye_z - z) / distance
