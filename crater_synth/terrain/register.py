"""Register an elevation crop without (or with doubtful) georeferencing against a reference DEM, and
build the embedded Shackleton 200 m / 40 m layers from their source EXRs (docs/dem_stack.md).

Registration model (fitted, never placed by hand):

- the crop is a north-up grid of square pixels of known size in the reference DEM's projected CRS,
  after one of the 8 axis orientations (4 rotations x optional transpose) of its array;
- a reference pixel holds the mean of the terrain over its footprint (LOLA LDEM_256 at 1600 m/px is
  a footprint average: this model fits it to 2.9 m RMS, a point-sample model to 23 m), so the
  model of a reference pixel is the exact mean of the piecewise-constant crop over that footprint,
  computed from a summed-area table;
- free parameters: orientation, the projected (x, y) of the crop's top-left corner, a vertical
  offset dz, and the crop's height frame: heights above the sphere, or heights above the plane
  tangent to the sphere at the projection origin (the pole), h_plane = h - (R - sqrt(R^2 - rho^2));
  the frame with the smaller residual wins (the Shackleton crops are in the pole's tangent plane:
  111 m RMS as sphere heights, 2.9 m after the correction).

Search: normalised cross-correlation of the crop block-averaged to the reference pixel, over the
whole reference raster, for each orientation (``skimage.feature.match_template``); then a
sub-pixel least-squares fit of (x0, y0) with dz profiled out. Uncertainty: formal (Jacobian and
residual variance), delete-one-block jackknife over 4 x 4 spatial blocks (accounts for spatially
correlated residuals), and the half-width of the misfit peak (shift at which the RMS doubles).

Run ``python -m crater_synth.tools.register_crop`` to rebuild ``data_manifest/embedded/shackleton_lola_200m``
(``--out DIR`` elsewhere; ``--check`` compares a rebuild with the committed files).

Length: the registration of one product, kept whole: orientation search, sub-pixel fit with its
uncertainty (jackknife), tangent-plane to sphere conversion, artefact repair and the GeoTIFF writer
form one reproducible rebuild (``--check``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from affine import Affine
from rasterio.io import MemoryFile
from skimage.feature import match_template

from crater_core.exr import ExrError, read_exr
from crater_core.geometry import MOON_RADIUS_M, curvature_drop_m
from crater_core.schema import atomic_write_bytes, atomic_write_json, sha256_file
from crater_synth.errors import UserError
from crater_synth.paths import EMBEDDED_DIR

# Source crops (AuroraRoboticsLab/GodotRobot demo/terrain_fixed/lunar_south_pole, commit 055ed87a,
# Unlicense): file name -> (pixel size m, sha256).
SHACKLETON_SOURCES = {
    "dem_shackridge_200m_256x256.exr": (200.0, "c94f432c92f4667e855ac1c8b8ac11a66387ab28063454184897db4f2be3e92a"),
    "dem_shackzoom_40m_256x256.exr": (40.0, "838fa3383988437c5977a0ee03a3f4e36e92128dd8bf0f174707e852b7c27bdb"),
}
# Their encoding (GodotRobot NOTES.txt: "-10 km .. +10 km scaled to 0-1"): elevation = (Y - 0.5) * 20 km.
EXR_HEIGHT_SPAN_M = 20_000.0
EXR_HEIGHT_ZERO = 0.5
# The 40 m crop is the centred 1024 x 1024 crop (10 m source pixels) of the 5120 x 5120 crop the 200 m
# one was scaled from: its top-left corner lies (5120 - 1024) / 2 * 10 m = 20.48 km = 102.4 200-m pixels
# from the 200 m crop's corner (NOTES.txt; fitted below: 102.38, 102.43).
ZOOM_ORIGIN_PX = 102.4
ZOOM_FACTOR = 5  # 200 m / 40 m
# The 200 m crop's lowered square (found from the data: rows/cols 103..152, the 200 m pixels whose
# footprints lie wholly inside the 40 m crop; the README's "51 x 51, 103-153" is one pixel too many).
SQUARE_START, SQUARE_SIZE = 103, 50
# Reference pixels whose footprint comes closer than this (reference pixels) to the crop's edge are
# not used, so the set of compared pixels stays fixed while the fit moves the crop by sub-pixels.
EDGE_INSET_PX = 1.0
JACKKNIFE_BLOCKS = 4
PRODUCT_DIR = EMBEDDED_DIR / "shackleton_lola_200m"
HEIGHT_FRAMES = ("sphere", "pole_tangent_plane")


class RegistrationError(UserError):
    """A crop cannot be registered (unreadable, wrong size ratio, outside the reference DEM...)."""


# --------------------------------------------------------------------------------------------
# Source crops
# --------------------------------------------------------------------------------------------
def read_godot_exr(path: str | Path) -> np.ndarray:
    """Elevations (m, float64) of a GodotRobot heightmap EXR: channel Y = elev / 20 km + 0.5, A = 1."""
    try:
        chans, _ = read_exr(path)
    except ExrError as exc:
        raise RegistrationError(str(exc)) from None
    if "Y" not in chans:
        raise RegistrationError(f"{path}: no 'Y' channel (channels {sorted(chans)})")
    y = chans["Y"].astype(np.float64)
    if not np.isfinite(y).all():
        raise RegistrationError(f"{path}: non-finite heights")
    if "A" in chans and not np.all(chans["A"] == 1.0):
        raise RegistrationError(f"{path}: alpha channel is not 1 everywhere (masked pixels are not supported)")
    return (y - EXR_HEIGHT_ZERO) * EXR_HEIGHT_SPAN_M


def block_mean(a: np.ndarray, factor: int) -> np.ndarray:
    """Mean over non-overlapping factor x factor blocks (trailing rows/cols that do not fill a block dropped)."""
    h, w = (a.shape[0] // factor) * factor, (a.shape[1] // factor) * factor
    return a[:h, :w].reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3))


def _second_difference_step(a: np.ndarray, edge: int, axis: int, span: slice) -> float:
    """Step (m) across the boundary between index edge-1 and edge along ``axis``, from second differences
    (a step s adds +s/2 to the second difference at edge-1 and -s/2 at edge), averaged over ``span``."""
    b = a if axis == 0 else a.T
    d2 = b[2:] - 2.0 * b[1:-1] + b[:-2]  # row i of d2 <-> index i + 1
    return float(np.mean(d2[edge - 1 - 1, span] - d2[edge - 1, span]) / 2.0)


def square_edge_steps(a: np.ndarray, start: int = SQUARE_START, size: int = SQUARE_SIZE) -> dict:
    """Steps (m) across the four edges of the square [start, start + size)^2, and the same statistic's
    spread on rows away from the square (the noise floor)."""
    inner = slice(start + 1, start + size - 1)
    steps = {
        "north": _second_difference_step(a, start, 0, inner),
        "south": -_second_difference_step(a, start + size, 0, inner),
        "west": _second_difference_step(a, start, 1, inner),
        "east": -_second_difference_step(a, start + size, 1, inner),
    }
    away = [k for k in range(8, a.shape[0] - 8) if abs(k - start) > 6 and abs(k - start - size) > 6]
    noise = float(np.std([_second_difference_step(a, k, 0, inner) for k in away]))
    return {"steps_m": {k: round(v, 2) for k, v in steps.items()}, "noise_m": round(noise, 2)}


def fit_zoom_origin(crop200: np.ndarray, crop40: np.ndarray) -> dict:
    """Fit where the 40 m crop sits in the 200 m grid (200 m pixel units, top-left corners) and the
    lowering of the square: 200 m pixel = 5 x 5 mean of the 40 m crop (sub-pixel, bicubic) - lowering."""
    from scipy import ndimage, optimize

    box = ndimage.uniform_filter(crop40, ZOOM_FACTOR, mode="nearest")  # odd size: centred
    idx = np.arange(SQUARE_START + 1, SQUARE_START + SQUARE_SIZE - 1)  # one pixel inside the square
    target = crop200[np.ix_(idx, idx)]

    def diff(p):
        rr = (idx + 0.5 - p[0]) * ZOOM_FACTOR - 0.5
        cc = (idx + 0.5 - p[1]) * ZOOM_FACTOR - 0.5
        rg, cg = np.meshgrid(rr, cc, indexing="ij")
        return target - ndimage.map_coordinates(box, [rg, cg], order=3, mode="nearest")

    sol = optimize.least_squares(lambda p: (d := diff(p)).ravel() - d.mean(), [ZOOM_ORIGIN_PX] * 2)
    d = diff(sol.x)
    return {
        "origin_px": [round(float(v), 4) for v in sol.x],
        "lowering_m": round(float(-d.mean()), 2),
        "lowering_rms_m": round(float(d.std()), 2),
    }


def repair_square(crop200: np.ndarray, crop40: np.ndarray) -> np.ndarray:
    """The 200 m crop with its lowered square replaced by the 40 m crop averaged to 200 m.

    With the 40 m crop's corner at 102.4 pixels, 200 m pixel 103 + k covers exactly 40 m pixels
    3 + 5k .. 7 + 5k, so the replacement is an exact 5 x 5 block mean (no interpolation).
    """
    first = round((SQUARE_START - ZOOM_ORIGIN_PX) * ZOOM_FACTOR)
    zoom = crop40[first : first + SQUARE_SIZE * ZOOM_FACTOR, first : first + SQUARE_SIZE * ZOOM_FACTOR]
    out = crop200.copy()
    sq = slice(SQUARE_START, SQUARE_START + SQUARE_SIZE)
    out[sq, sq] = block_mean(zoom, ZOOM_FACTOR)
    return out


# --------------------------------------------------------------------------------------------
# Registration
# --------------------------------------------------------------------------------------------
ORIENTATIONS = tuple((k, t) for t in (False, True) for k in range(4))


def orient(a: np.ndarray, rot90: int, transpose: bool) -> np.ndarray:
    """``np.rot90(a, rot90)``, then transposed if asked: the 8 axis orientations of a grid."""
    b = np.rot90(a, rot90)
    return np.ascontiguousarray(b.T if transpose else b)


def orientation_name(rot90: int, transpose: bool) -> str:
    return f"rot90 x{rot90}" + (" then transpose" if transpose else "") if (rot90 or transpose) else "identity"


@dataclass
class Registration:
    """A fitted placement: the oriented crop's top-left corner (x0, y0) in the reference CRS, rows
    running south (y decreasing), columns east; heights = crop + frame correction + dz_m."""

    rot90: int
    transpose: bool
    x0_m: float
    y0_m: float
    pixel_m: float
    dz_m: float
    height_frame: str
    rms_m: float
    correlation: float
    one_minus_correlation: float
    n_reference_pixels: int
    sigma_formal_m: dict = field(default_factory=dict)
    sigma_jackknife_m: dict = field(default_factory=dict)
    misfit_doubling_shift_m: dict = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["orientation"] = orientation_name(self.rot90, self.transpose)
        return d


def frame_correction(x: np.ndarray, y: np.ndarray, frame: str) -> np.ndarray:
    """Metres to add to a crop height in ``frame`` at projected (x, y) to get a height above the sphere."""
    if frame == "sphere":
        return np.zeros(np.broadcast_shapes(np.shape(x), np.shape(y)))
    if frame == "pole_tangent_plane":
        return curvature_drop_m(np.hypot(x, y))
    raise RegistrationError(f"unknown height frame {frame!r}; known: {HEIGHT_FRAMES}")


class _Model:
    """Reference pixels vs the footprint means of a crop placed at (x0, y0)."""

    def __init__(self, crop: np.ndarray, crop_px: float, ref_h: np.ndarray, ref_transform, rows, cols):
        self.crop_px = crop_px
        self.shape = crop.shape
        sat = np.zeros((crop.shape[0] + 1, crop.shape[1] + 1))
        sat[1:, 1:] = crop.cumsum(0).cumsum(1)
        self.sat = sat
        t = ref_transform
        self.ref_px = (abs(t.a), abs(t.e))
        self.rows, self.cols = rows, cols
        self.x = t.c + t.a * (cols + 0.5)
        self.y = t.f + t.e * (rows + 0.5)
        self.ref = ref_h[rows, cols]

    def _sat_at(self, r, c):
        from scipy import ndimage

        return ndimage.map_coordinates(self.sat, [r, c], order=1, mode="nearest")

    def footprint_mean(self, x0: float, y0: float) -> np.ndarray:
        """Mean of the crop over each reference pixel's footprint (exact for piecewise-constant pixels)."""
        hx, hy = 0.5 * self.ref_px[0] / self.crop_px, 0.5 * self.ref_px[1] / self.crop_px
        c = (self.x - x0) / self.crop_px
        r = (y0 - self.y) / self.crop_px
        s = (
            self._sat_at(r + hy, c + hx)
            - self._sat_at(r - hy, c + hx)
            - self._sat_at(r + hy, c - hx)
            + self._sat_at(r - hy, c - hx)
        )
        return s / (4.0 * hx * hy)

    def residual(self, x0: float, y0: float, frame: str, sel=None) -> tuple[np.ndarray, float]:
        """(reference - model - dz, dz) with dz the mean difference (profiled out)."""
        d = self.ref - self.footprint_mean(x0, y0) - frame_correction(self.x, self.y, frame)
        if sel is not None:
            d = d[sel]
        dz = float(d.mean())
        return d - dz, dz


def _coarse_search(crop: np.ndarray, crop_px: float, ref_h: np.ndarray, ref_valid: np.ndarray, transform):
    """Best whole-reference-pixel placement per orientation by normalised cross-correlation."""
    factor = round(abs(transform.a) / crop_px)
    filled = np.where(ref_valid, ref_h, np.nanmean(np.where(ref_valid, ref_h, np.nan)))
    out = []
    for rot, tr in ORIENTATIONS:
        a = orient(crop, rot, tr)
        tmpl = block_mean(a, factor)
        if tmpl.shape[0] > filled.shape[0] or tmpl.shape[1] > filled.shape[1]:
            raise RegistrationError("the crop is larger than the reference DEM")
        ncc = match_template(filled, tmpl)
        i, j = np.unravel_index(int(np.argmax(ncc)), ncc.shape)
        out.append(
            {
                "rot90": rot,
                "transpose": tr,
                "ncc": float(ncc[i, j]),
                "x0_m": float(transform.c + transform.a * j),
                "y0_m": float(transform.f + transform.e * i),
            }
        )
    return sorted(out, key=lambda d: -d["ncc"])


def _compared_pixels(ref, ref_valid: np.ndarray, best: dict, shape: tuple, crop_px: float, excl):
    """(rows, cols) of the valid reference pixels whose footprint lies inside the crop (``shape``, oriented)
    at the coarse placement ``best``, inset by one pixel, and clear of the excluded crop pixels ``excl``."""
    h, w = shape
    t = ref.transform
    cols = np.arange(ref.width)
    rows = np.arange(ref.height)
    xc = t.c + t.a * (cols + 0.5)
    yc = t.f + t.e * (rows + 0.5)
    half = 0.5 * abs(t.a) + EDGE_INSET_PX * abs(t.a)
    col_ok = (xc - half >= best["x0_m"]) & (xc + half <= best["x0_m"] + w * crop_px)
    row_ok = (yc + half <= best["y0_m"]) & (yc - half >= best["y0_m"] - h * crop_px)
    rg, cg = np.meshgrid(rows[row_ok], cols[col_ok], indexing="ij")
    keep = ref_valid[rg, cg]
    if excl is not None and excl.any():
        # Drop reference pixels whose footprint (plus the inset) overlaps an excluded crop pixel.
        er, ec = np.nonzero(excl)
        ex = best["x0_m"] + (ec + 0.5) * crop_px
        ey = best["y0_m"] - (er + 0.5) * crop_px
        near = (np.abs(xc[cg][..., None] - ex) <= half + crop_px) & (np.abs(yc[rg][..., None] - ey) <= half + crop_px)
        keep &= ~near.any(axis=-1)
    rows_sel, cols_sel = rg[keep], cg[keep]
    if rows_sel.size < 16:
        raise RegistrationError(f"only {rows_sel.size} reference pixels under the crop: too few to register it")
    return rows_sel, cols_sel


def _fit_offset(model: _Model, frame: str, p0, crop_px: float, sel=None):
    """Least-squares (x0, y0) of the crop in height frame ``frame`` from ``p0``, over the compared pixels
    ``sel`` (all when None); scipy's result."""
    from scipy import optimize

    return optimize.least_squares(
        lambda p: model.residual(p[0], p[1], frame, sel)[0], p0, x_scale=[crop_px, crop_px], diff_step=1e-4
    )


def _jackknife_sigma(model: _Model, frame: str, rows_sel, cols_sel, x0: float, y0: float, crop_px: float) -> dict:
    """Delete-one-block jackknife 1-sigma of (x, y, dz) over JACKKNIFE_BLOCKS^2 spatial blocks of the
    compared pixels."""
    rb = np.minimum((rows_sel - rows_sel.min()) * JACKKNIFE_BLOCKS // (np.ptp(rows_sel) + 1), JACKKNIFE_BLOCKS - 1)
    cb = np.minimum((cols_sel - cols_sel.min()) * JACKKNIFE_BLOCKS // (np.ptp(cols_sel) + 1), JACKKNIFE_BLOCKS - 1)
    block = rb * JACKKNIFE_BLOCKS + cb
    jk = []
    for b in np.unique(block):
        sel = block != b
        s = _fit_offset(model, frame, [x0, y0], crop_px, sel)
        jk.append([*s.x, model.residual(*s.x, frame, sel)[1]])
    jk = np.asarray(jk)
    m = len(jk)
    jsig = np.sqrt((m - 1) / m * np.sum((jk - jk.mean(axis=0)) ** 2, axis=0))
    return {"x": float(jsig[0]), "y": float(jsig[1]), "dz": float(jsig[2]), "blocks": int(m)}


def _misfit_width(model: _Model, frame: str, x0: float, y0: float, rms0: float, crop_px: float, ref_px: float) -> dict:
    """Misfit peak width: the shift along x / y at which the RMS residual doubles (mean of both sides)."""
    shifts = np.arange(crop_px / 20.0, 4.0 * ref_px, crop_px / 20.0)
    width = {}
    for axis in ("x", "y"):
        sides = []
        for sign in (-1.0, 1.0):
            for s in shifts:
                px, py = (x0 + sign * s, y0) if axis == "x" else (x0, y0 + sign * s)
                if np.sqrt(np.mean(model.residual(px, py, frame)[0] ** 2)) >= 2.0 * rms0:
                    sides.append(float(s))
                    break
            else:
                sides.append(float("inf"))
        width[axis] = float(np.mean(sides))
    return width


def register_crop(crop: np.ndarray, crop_px: float, ref, *, exclude: np.ndarray | None = None) -> Registration:
    """Fit the placement of ``crop`` (heights m, pixel ``crop_px`` m) on the reference :class:`Dem`.

    ``exclude``: boolean mask in the *unoriented* crop of pixels not to compare (e.g. an artefact);
    a reference pixel whose footprint touches one is dropped.
    """
    ratio = abs(ref.transform.a) / crop_px
    if ratio < 2.0 or abs(ref.transform.a) != abs(ref.transform.e):
        raise RegistrationError(
            f"reference pixel {ref.pixel_size_m:g} m must be square and >= 2 crop pixels ({crop_px:g} m)"
        )
    ref_h, ref_valid = ref.read_heights()
    coarse = _coarse_search(crop, crop_px, ref_h, ref_valid, ref.transform)
    best = coarse[0]
    a = orient(crop, best["rot90"], best["transpose"])
    excl = None if exclude is None else orient(exclude, best["rot90"], best["transpose"])
    rows_sel, cols_sel = _compared_pixels(ref, ref_valid, best, a.shape, crop_px, excl)
    model = _Model(a, crop_px, ref_h, ref.transform, rows_sel, cols_sel)

    fits = {f: _fit_offset(model, f, [best["x0_m"], best["y0_m"]], crop_px) for f in HEIGHT_FRAMES}
    rms = {f: float(np.sqrt(np.mean(fits[f].fun ** 2))) for f in HEIGHT_FRAMES}
    frame = min(HEIGHT_FRAMES, key=lambda f: rms[f])
    sol = fits[frame]
    x0, y0 = (float(v) for v in sol.x)
    res, dz = model.residual(x0, y0, frame)
    n = res.size
    model_h = model.footprint_mean(x0, y0) + frame_correction(model.x, model.y, frame) + dz
    corr = float(np.corrcoef(model_h, model.ref)[0, 1])

    # Formal 1-sigma: residual variance x (J^T J)^-1 (dz profiled out: 3 parameters).
    s2 = float(np.sum(res**2)) / max(1, n - 3)
    cov = s2 * np.linalg.inv(sol.jac.T @ sol.jac)
    sigma_formal = {"x": float(math.sqrt(cov[0, 0])), "y": float(math.sqrt(cov[1, 1])), "dz": float(math.sqrt(s2 / n))}
    sigma_jk = _jackknife_sigma(model, frame, rows_sel, cols_sel, x0, y0, crop_px)
    rms0 = float(np.sqrt(np.mean(res**2)))
    width = _misfit_width(model, frame, x0, y0, rms0, crop_px, abs(ref.transform.a))

    # Diagnostics: free curvature coefficient, free rotation/scale about the crop centre.
    rho2 = model.x**2 + model.y**2
    d_free = model.ref - model.footprint_mean(x0, y0)
    design = np.column_stack([np.ones(n), rho2])
    coef, *_ = np.linalg.lstsq(design, d_free, rcond=None)
    diagnostics = {
        "coarse_ncc_by_orientation": [
            {k: (round(v, 4) if isinstance(v, float) else v) for k, v in c.items()} for c in coarse
        ],
        "rms_by_height_frame_m": {f: round(v, 3) for f, v in rms.items()},
        "curvature_coefficient_over_1_by_2R": round(float(coef[1] * 2.0 * MOON_RADIUS_M), 4),
        "rotation_scale_free_fit": _rotation_scale_fit(a, crop_px, model, frame, x0, y0),
    }
    return Registration(
        rot90=best["rot90"],
        transpose=best["transpose"],
        x0_m=x0,
        y0_m=y0,
        pixel_m=crop_px,
        dz_m=dz,
        height_frame=frame,
        rms_m=rms0,
        correlation=corr,
        one_minus_correlation=1.0 - corr,
        n_reference_pixels=int(n),
        sigma_formal_m=sigma_formal,
        sigma_jackknife_m=sigma_jk,
        misfit_doubling_shift_m=width,
        diagnostics=diagnostics,
    )


def _rotation_scale_fit(a, crop_px, model: _Model, frame, x0, y0) -> dict:
    """Refit with a free rotation and scale about the crop centre (a check that neither is needed)."""
    from scipy import ndimage, optimize

    h, w = a.shape
    box_r = round(model.ref_px[0] / crop_px)
    smooth = ndimage.uniform_filter(a, box_r, mode="nearest")
    shift = 0.5 if box_r % 2 == 0 else 0.0  # even box: the filtered value at i is centred at i - 0.5

    def resid(p, rot_scale=True):
        th, sc = (p[2], p[3]) if rot_scale else (0.0, 1.0)
        cx, cy = p[0] + 0.5 * w * crop_px, p[1] - 0.5 * h * crop_px
        du, dv = model.x - cx, cy - model.y
        u = (math.cos(th) * du + math.sin(th) * dv) / sc
        v = (-math.sin(th) * du + math.cos(th) * dv) / sc
        c = (u + 0.5 * w * crop_px) / crop_px - 0.5 + shift
        r = (v + 0.5 * h * crop_px) / crop_px - 0.5 + shift
        d = (
            model.ref
            - ndimage.map_coordinates(smooth, [r, c], order=3, mode="nearest")
            - frame_correction(model.x, model.y, frame)
        )
        return d - d.mean()

    base = optimize.least_squares(lambda p: resid(p, False), [x0, y0], x_scale=[crop_px] * 2, diff_step=1e-4)
    free = optimize.least_squares(resid, [x0, y0, 0.0, 1.0], x_scale=[crop_px, crop_px, 1e-3, 1e-3], diff_step=1e-4)
    return {
        "rotation_deg": round(math.degrees(float(free.x[2])), 4),
        "scale": round(float(free.x[3]), 5),
        "rms_m": round(float(np.sqrt(np.mean(free.fun**2))), 3),
        "rms_without_m": round(float(np.sqrt(np.mean(base.fun**2))), 3),
        "model": f"{box_r}x{box_r} box filter, bicubic (an approximation of the exact footprint mean)",
    }


# --------------------------------------------------------------------------------------------
# Products
# --------------------------------------------------------------------------------------------
def layer_heights(
    crop: np.ndarray, reg: Registration, x0: float | None = None, y0: float | None = None, pixel_m: float | None = None
) -> tuple[np.ndarray, tuple]:
    """(heights above the sphere on the oriented grid, GDAL geotransform tuple) for a crop placed by ``reg``
    (or at (x0, y0) with ``pixel_m``, in the same orientation and height frame)."""
    a = orient(crop, reg.rot90, reg.transpose)
    x0 = reg.x0_m if x0 is None else x0
    y0 = reg.y0_m if y0 is None else y0
    px = reg.pixel_m if pixel_m is None else pixel_m
    xs = x0 + (np.arange(a.shape[1]) + 0.5) * px
    ys = y0 - (np.arange(a.shape[0]) + 0.5) * px
    heights = a + frame_correction(xs[None, :], ys[:, None], reg.height_frame) + reg.dz_m
    return heights, Affine(px, 0.0, x0, 0.0, -px, y0)


def geotiff_bytes(heights: np.ndarray, transform, crs, description: str) -> bytes:
    """A float32 GeoTIFF (deflate, floating-point predictor, metres above the sphere) as bytes."""
    h, w = heights.shape
    with MemoryFile() as mem:
        with mem.open(
            driver="GTiff",
            width=w,
            height=h,
            count=1,
            dtype="float32",
            crs=crs,
            transform=transform,
            compress="deflate",
            predictor=3,
            nodata=None,
        ) as dst:
            dst.write(heights.astype(np.float32), 1)
            dst.units = ("m",)
            dst.update_tags(1, DESCRIPTION=description)
            dst.update_tags(AREA_OR_POINT="Area")
        return mem.read()


def _round(d):
    if isinstance(d, dict):
        return {k: _round(v) for k, v in d.items()}
    if isinstance(d, list):
        return [_round(v) for v in d]
    if isinstance(d, float):
        return round(d, 4) if abs(d) >= 0.01 or d == 0.0 else float(f"{d:.3g}")
    return d


def build_shackleton(src_dir: Path, out_dir: Path, ref) -> dict:
    """Verify the source EXRs, repair the 200 m crop, register it on ``ref`` and write
    ``shackleton_lola_200m.tif``, ``shackleton_lola_40m.tif`` and ``registration.json`` into ``out_dir``."""
    crops = {}
    for name, (px, sha) in SHACKLETON_SOURCES.items():
        path = Path(src_dir) / name
        if not path.is_file():
            raise RegistrationError(f"source crop {path} does not exist")
        if sha256_file(path) != sha:
            raise RegistrationError(f"source crop {path}: sha256 differs from the pinned {sha}")
        crops[px] = read_godot_exr(path)
    c200, c40 = crops[200.0], crops[40.0]
    if c200.shape != (256, 256) or c40.shape != (256, 256):
        raise RegistrationError("the Shackleton source crops must be 256 x 256")

    zoom = fit_zoom_origin(c200, c40)
    repaired = repair_square(c200, c40)
    shifted = c200.copy()
    sq = slice(SQUARE_START, SQUARE_START + SQUARE_SIZE)
    shifted[sq, sq] += zoom["lowering_m"]
    artefact = {
        "square_rows_cols": [SQUARE_START, SQUARE_START + SQUARE_SIZE - 1],
        "zoom_fit": zoom,
        "edge_steps_raw": square_edge_steps(c200),
        "edge_steps_constant_added_back": square_edge_steps(shifted),
        "edge_steps_replaced_by_40m_mean": square_edge_steps(repaired),
        "correction": "replaced by the 40 m crop averaged 5 x 5 to 200 m",
    }
    reg = register_crop(repaired, 200.0, ref)
    # Cross-checks on the LDEM residual: with the raw (lowered) square and with the square masked.
    mask = np.zeros_like(c200, dtype=bool)
    mask[sq, sq] = True
    raw = register_crop(c200, 200.0, ref)
    masked = register_crop(repaired, 200.0, ref, exclude=mask)
    checks = {
        name: {"x0_m": r.x0_m, "y0_m": r.y0_m, "dz_m": r.dz_m, "rms_m": r.rms_m, "n": r.n_reference_pixels}
        for name, r in (("raw_square", raw), ("square_masked", masked))
    }

    crs = ref.crs
    h200, t200 = layer_heights(repaired, reg)
    if reg.rot90 or reg.transpose:  # the 40 m crop's placement below assumes the identity orientation
        raise RegistrationError(f"unexpected orientation {orientation_name(reg.rot90, reg.transpose)}")
    zx = reg.x0_m + zoom["origin_px"][1] * reg.pixel_m
    zy = reg.y0_m - zoom["origin_px"][0] * reg.pixel_m
    h40, t40 = layer_heights(c40, reg, x0=zx, y0=zy, pixel_m=40.0)
    out_dir = Path(out_dir)
    files = {}
    for name, heights, transform, what in (
        ("shackleton_lola_200m.tif", h200, t200, "Shackleton LOLA-derived 200 m DEM (lowered square repaired)"),
        ("shackleton_lola_40m.tif", h40, t40, "Shackleton west rim LOLA-derived 40 m DEM"),
    ):
        data = geotiff_bytes(
            heights,
            transform,
            crs,
            f"{what}; m above the 1737.4 km sphere; registered on LDEM_256 (crater_synth.terrain.register)",
        )
        atomic_write_bytes(out_dir / name, data)
        files[name] = {
            "sha256": sha256_file(out_dir / name),
            "size_bytes": len(data),
            "shape": list(heights.shape),
            "transform": list(transform)[:6],
        }
    doc = _round(
        {
            "reference": {"product": ref.product, "pixel_size_m": ref.pixel_size_m, "crs": crs.to_proj4()},
            "registration": reg.as_dict(),
            "artefact": artefact,
            "checks": checks,
            "outputs": files,
            "sources": {n: {"pixel_m": px, "sha256": sha} for n, (px, sha) in SHACKLETON_SOURCES.items()},
        }
    )
    atomic_write_json(out_dir / "registration.json", doc)
    return doc
