"""DEM ingestion: any raster GDAL reads (GeoTIFF, PDS3 IMG/LBL, ...) in a projected lunar CRS.

Heights are sampled at (lat, lon) on the reference sphere by transforming to the DEM's own CRS
with PROJ (``rasterio.warp.transform``; for the spherical polar stereographic projection of the LOLA polar
products the same formula in numpy, checked against PROJ when the DEM is opened) and interpolating with a
cubic B-spline (interpolating, via ``scipy.ndimage.map_coordinates(order=3)``). Only the window a patch
needs is read, from the raster kept open per process. When the
requested grid is much coarser than the DEM, the window is box-averaged to about the grid spacing
first, so the coarse grid does not alias the fine DEM.

Nodata (the dataset's nodata value or mask, and NaN) is filled by inverse-distance interpolation
(GDAL ``FillNodata``) and counted; a patch whose share of nodata vertices exceeds
``dem.max_nodata_fraction`` is refused.

Height convention (docs/terrain.md): metres above the lunar reference sphere of the DEM's CRS. Band
scale/offset are applied (PDS3 LOLA labels: DN * 0.5 m + 1737400 m); a value that is a planetary
*radius* (offset, or values, near the sphere radius) has the radius subtracted; ``km`` units are
converted to metres.

Pixel coordinates reported (``crater_center_px``) are continuous (col, row) of the full-resolution
raster, origin at the top-left corner of the top-left pixel (pixel centres at integer + 0.5).
"""

from __future__ import annotations

import logging
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.errors import RasterioError
from rasterio.fill import fillnodata
from rasterio.warp import transform
from rasterio.windows import Window

from crater_core.geometry import hemisphere, polar_stereo_forward
from crater_synth.errors import UserError

# IAU/LOLA lunar reference sphere (Archinal et al. 2018); the same value as crater_core.geometry.
MOON_RADIUS_M = 1_737_400.0
# A DEM whose CRS body radius differs from the lunar sphere by more than this is not lunar
# (e.g. an Earth CRS, R = 6371 km); the Moon's polar flattening is ~1 km at most.
LUNAR_RADIUS_TOLERANCE_M = 10_000.0
# Cubic-spline support margin (pixels) read around a patch: the B-spline prefilter's influence
# decays by a factor (2 - sqrt 3) ~ 0.268 per pixel, so 8 px leaves < 3e-5 of an edge effect.
SPLINE_MARGIN_PX = 8
_KM_UNITS = {"km", "kilometer", "kilometers", "kilometre", "kilometres"}
_M_UNITS = {"", "m", "meter", "meters", "metre", "metres"}

# Libraries should not print: keep rasterio/GDAL log records out of stderr unless the application
# configures logging (our errors carry the message instead).
logging.getLogger("rasterio").addHandler(logging.NullHandler())


class DemError(UserError):
    """A DEM cannot serve the requested patch."""


class DemReadError(DemError):
    """The DEM file is missing, corrupt, truncated, or not a usable projected raster."""


class DemCoverageError(DemError):
    """The requested points lie (partly) outside the DEM."""


class DemNodataError(DemError):
    """Too much of the requested patch is nodata."""


# The embedded LDEM_256 polar DEMs (configs/dem/), named in the wrong-hemisphere error.
POLAR_DEM_OPTION = {"south": "dem=lola_ldem256_south", "north": "dem=lola_ldem256_north"}


def check_hemisphere(dem, name: str, lat_deg: float) -> None:
    """Refuse a crater given in the other hemisphere than its DEM with one line naming both.

    ``dem``: a :class:`Dem` or a DEM stack (its base DEM decides). A DEM spanning the equator accepts
    both hemispheres (the coverage checks then decide)."""
    base = getattr(dem, "base", dem)
    dem_side = base.hemisphere()
    side = hemisphere(lat_deg)
    if dem_side is not None and dem_side != side:
        raise DemCoverageError(
            f"crater {name} (lat {float(lat_deg):g}) is in the {side}ern hemisphere but DEM {base.product} is "
            f"{dem_side}-polar: use {POLAR_DEM_OPTION[side]} (or a {side}-polar dem.path)"
        )


@dataclass
class SampleResult:
    """Heights sampled from a DEM, with what was done to get them."""

    heights: np.ndarray  # metres above the reference sphere, shape of the query
    nodata_fraction: float  # share of query points whose DEM cell was nodata (before filling)
    filled_pixels: int  # nodata pixels interpolated in the window read
    filled_holes: int  # connected nodata regions interpolated in the window read
    decimation: int  # box-average factor applied to the DEM before sampling (1 = native)
    window: tuple[int, int, int, int] = field(default=(0, 0, 0, 0))  # col_off, row_off, width, height (native px)


def _raster_error(path: Path, exc: Exception) -> DemReadError:
    cause = exc.__cause__ or exc.__context__
    detail = str(exc)
    if cause is not None and str(cause) and str(cause) not in detail:
        detail = f"{detail} ({str(cause).splitlines()[0]})"
    detail = detail.replace(" See previous exception for details.", "")
    return DemReadError(
        f"cannot read DEM {path}: {detail.splitlines()[0] if detail else type(exc).__name__} "
        "(corrupt, truncated or not a raster GDAL reads)"
    )


def _linear_unit_is_metre(crs) -> bool:
    """True when the projected CRS's axes are in metres (GDAL's PDS driver reports the unit name as
    'unknown' with a factor of 1, hence the fallbacks)."""
    if (crs.linear_units or "").lower() in ("metre", "meter", "m"):
        return True
    if crs.to_dict().get("units") == "m":
        return True
    try:
        return float(crs.linear_units_factor[1]) == 1.0
    except Exception:  # noqa: BLE001 - rasterio raises CRSError for CRSs without linear units
        return False


def _body_radii(crs) -> tuple[float, float]:
    """(equatorial, polar) radii of the body in the CRS's datum, metres."""
    d = crs.to_dict()
    if "R" in d:
        r = float(d["R"])
        return r, r
    if "a" in d:
        a = float(d["a"])
        if "b" in d:
            return a, float(d["b"])
        if "rf" in d and float(d["rf"]) != 0.0:
            return a, a * (1.0 - 1.0 / float(d["rf"]))
        return a, a

    m = re.search(r'SPHEROID\["[^"]*",\s*([0-9.eE+-]+),\s*([0-9.eE+-]+)', crs.to_wkt())
    if m:
        a, inv_f = float(m.group(1)), float(m.group(2))
        return a, a if inv_f == 0.0 else a * (1.0 - 1.0 / inv_f)
    raise DemReadError("cannot determine the body radius of the DEM's CRS")


def _polar_stereo_pole(dem) -> str | None:
    """``"south"`` or ``"north"`` when the DEM's CRS is the spherical polar stereographic projection that
    :func:`crater_core.geometry.polar_stereo_forward` computes (the LOLA polar products), checked
    against PROJ on the raster's :meth:`Dem.outline_points` to 1 mm; else None. Then (lat, lon) -> (x, y) runs
    in numpy: PROJ's ``transform`` builds its pipeline on every call (~1 ms, a third of reading a
    landmark's terrain window)."""
    d = dem.crs.to_dict()
    if d.get("proj") != "stere" or abs(abs(float(d.get("lat_0", 0.0))) - 90.0) > 1e-12:
        return None
    pole = "north" if float(d["lat_0"]) > 0 else "south"
    x, y, lat, lon = dem.outline_points()
    fx, fy = polar_stereo_forward(lat, lon, pole, dem.body_radius_m)
    return pole if max(np.max(np.abs(fx - x)), np.max(np.abs(fy - y))) < 1e-3 else None


class Dem:
    """A DEM file opened for sampling; metadata is read once, pixels on demand (windowed)."""

    def __init__(self, path: str | Path, product: str | None = None):
        self.path = Path(path)
        self.product = product or self.path.name
        self._open = None  # (pid, open rasterio dataset): see _dataset
        if not self.path.exists():
            raise DemReadError(f"DEM file {self.path} does not exist")
        try:
            with rasterio.open(self.path) as ds:
                self.crs = ds.crs
                self.transform = ds.transform
                self.width, self.height = ds.width, ds.height
                self.count = ds.count
                self.nodata = ds.nodata
                self.dtype = ds.dtypes[0] if ds.count else None
                self.scale = float(ds.scales[0]) if ds.count else 1.0
                self.offset = float(ds.offsets[0]) if ds.count else 0.0
                self.units = (ds.units[0] or "").strip().lower() if ds.count else ""
                self.driver = ds.driver
        except RasterioError as exc:
            raise _raster_error(self.path, exc) from None
        where = f"DEM {self.path}"
        if self.count < 1:
            raise DemReadError(f"{where} has no raster band")
        if self.crs is None:
            raise DemReadError(f"{where} has no coordinate reference system")
        if not self.crs.is_projected:
            raise DemReadError(
                f"{where} is in a geographic CRS; reproject it to a projected one "
                "(e.g. gdalwarp -t_srs '+proj=stere +lat_0=-90 +R=1737400', or +lat_0=90 at the north pole)"
            )
        if not _linear_unit_is_metre(self.crs):
            raise DemReadError(f"{where}: CRS linear unit {self.crs.linear_units!r} is not metres")
        t = self.transform
        if abs(t.b) > 1e-9 * abs(t.a) or abs(t.d) > 1e-9 * abs(t.e):
            raise DemReadError(f"{where}: rotated/sheared pixel grids are not supported ({t})")
        self.pixel_size_xy = (abs(t.a), abs(t.e))
        # Nominal spacing (projected metres); the larger of the two for non-square pixels.
        self.pixel_size_m = float(max(self.pixel_size_xy))
        a, b = _body_radii(self.crs)
        self.body_radius_m = a
        if abs(a - MOON_RADIUS_M) > LUNAR_RADIUS_TOLERANCE_M or abs(b - MOON_RADIUS_M) > LUNAR_RADIUS_TOLERANCE_M:
            raise DemReadError(
                f"{where}: CRS body radii ({a:.0f}, {b:.0f}) m are not lunar ({MOON_RADIUS_M:.0f} m expected)"
            )
        self.geographic_crs = CRS.from_proj4(
            f"+proj=longlat +R={a!r} +no_defs" if a == b else f"+proj=longlat +a={a!r} +b={b!r} +no_defs"
        )
        self.stereo_pole = _polar_stereo_pole(self)
        if self.units in _KM_UNITS:
            self.unit_factor = 1000.0
        elif self.units in _M_UNITS:
            self.unit_factor = 1.0
        else:
            raise DemReadError(f"{where}: unsupported height unit {self.units!r} (metres or kilometres)")
        # A band offset equal to the sphere radius means the stored quantity is a radius.
        self.stores_radius = abs(self.offset * self.unit_factor - a) < 0.01 * a

    # ------------------------------------------------------------------------------ metadata
    def info(self) -> dict:
        """JSON-ready description: product, path, CRS, pixel size, shape, height convention."""
        return {
            "product": self.product,
            "path": str(self.path),
            "driver": self.driver,
            "crs_wkt": self.crs.to_wkt(),
            "crs_proj": self.crs.to_proj4(),
            "pixel_size_m": self.pixel_size_m,
            "pixel_size_xy_m": list(self.pixel_size_xy),
            "shape": [self.height, self.width],
            "bounds_m": list(self.bounds),
            "nodata": self.nodata,
            "scale": self.scale,
            "offset": self.offset,
            "units": self.units or "m",
            "stores_radius": bool(self.stores_radius),
            "body_radius_m": self.body_radius_m,
        }

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(left, bottom, right, top) in projected metres."""
        t = self.transform
        xs = (t.c, t.c + t.a * self.width)
        ys = (t.f, t.f + t.e * self.height)
        return min(xs), min(ys), max(xs), max(ys)

    # ------------------------------------------------------------------------------ coordinates
    def latlon_to_xy(self, lat_deg, lon_deg) -> tuple[np.ndarray, np.ndarray]:
        """Projected (x, y) metres of planetocentric (lat, lon) degrees: PROJ's, or the same projection in
        numpy for a spherical polar stereographic CRS (:func:`_polar_stereo_pole`)."""
        lat = np.asarray(lat_deg, dtype=np.float64)
        lon = np.asarray(lon_deg, dtype=np.float64)
        shape = np.broadcast_shapes(lat.shape, lon.shape)
        lat, lon = np.broadcast_to(lat, shape).ravel(), np.broadcast_to(lon, shape).ravel()
        # Normalise longitudes to (-180, 180] so every PROJ pipeline sees the same convention.
        lon = (lon + 180.0) % 360.0 - 180.0
        if self.stereo_pole is not None:
            x, y = polar_stereo_forward(lat, lon, self.stereo_pole, self.body_radius_m)
        else:
            x, y = transform(self.geographic_crs, self.crs, lon, lat)
        return np.asarray(x, dtype=np.float64).reshape(shape), np.asarray(y, dtype=np.float64).reshape(shape)

    def xy_to_pixel(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Continuous (col, row) of the full-resolution raster (origin: top-left pixel corner)."""
        t = self.transform
        return ((np.asarray(x) - t.c) / t.a), ((np.asarray(y) - t.f) / t.e)

    def latlon_to_pixel(self, lat_deg, lon_deg) -> tuple[np.ndarray, np.ndarray]:
        return self.xy_to_pixel(*self.latlon_to_xy(lat_deg, lon_deg))

    def outline_points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, lat, lon) of the raster's corners, edge midpoints and centre (projected metres, and their
        planetocentric degrees through PROJ)."""
        left, bottom, right, top = self.bounds
        xs = [left, (left + right) / 2, right]
        ys = [bottom, (bottom + top) / 2, top]
        x, y = (np.array(v, dtype=np.float64).ravel() for v in np.meshgrid(xs, ys))
        lon, lat = transform(self.crs, self.geographic_crs, x, y)
        return x, y, np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64)

    def hemisphere(self) -> str | None:
        """``"north"`` or ``"south"`` when the whole raster (its :meth:`outline_points`) lies in that
        hemisphere, else None (a DEM spanning the equator, e.g. a global one)."""
        _, _, lat, _ = self.outline_points()
        if np.all(lat > 0.0):
            return "north"
        if np.all(lat < 0.0):
            return "south"
        return None

    def inside(self, col, row) -> np.ndarray:
        """True where a continuous pixel position lies within the hull of pixel centres."""
        col, row = np.asarray(col), np.asarray(row)
        return (col >= 0.5) & (col <= self.width - 0.5) & (row >= 0.5) & (row <= self.height - 0.5)

    def _decimation(self, spacing_m: float | None) -> int:
        """Box-average factor so that the sampled DEM's pixel is about the grid spacing."""
        if not spacing_m or spacing_m <= 0:
            return 1
        return max(1, int(math.floor(spacing_m / self.pixel_size_m)))

    # ------------------------------------------------------------------------------ reading
    def _dataset(self):
        """The raster, opened once per process and kept open: opening it costs ~2 ms, as much as reading
        a landmark's window. Reopened in a forked or spawned worker (a GDAL handle is not shared)."""
        if self._open is None or self._open[0] != os.getpid():
            self._open = (os.getpid(), rasterio.open(self.path))
        return self._open[1]

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_open"] = None  # a pickled Dem (a worker's argument) opens its own handle
        return state

    def _read_window(self, col, row, factor: int, margin_px: int | None = None):
        """Read the window around continuous positions (col, row), decimated by ``factor``.

        ``margin_px``: native pixels read beyond the positions (default: the spline margin).
        Returns (values float64 with NaN for nodata, valid mask per cell, (col_off, row_off),
        native window shape).
        """
        margin = SPLINE_MARGIN_PX * factor if margin_px is None else int(margin_px)
        c0 = max(0, int(math.floor(np.min(col))) - margin)
        r0 = max(0, int(math.floor(np.min(row))) - margin)
        c1 = min(self.width, int(math.ceil(np.max(col))) + margin)
        r1 = min(self.height, int(math.ceil(np.max(row))) + margin)
        # Whole decimated cells only, so the decimated grid stays aligned with the native one.
        w = max(factor, (c1 - c0) // factor * factor)
        h = max(factor, (r1 - r0) // factor * factor)
        w, h = min(w, self.width - c0), min(h, self.height - r0)
        out_shape = (max(1, h // factor), max(1, w // factor))
        win = Window(c0, r0, w, h)
        kw = dict(window=win, out_shape=out_shape, resampling=Resampling.average) if factor > 1 else dict(window=win)
        try:
            ds = self._dataset()
            data = ds.read(1, masked=False, **kw).astype(np.float64)
            mask = ds.read_masks(1, **kw).astype(np.float64) / 255.0
        except RasterioError as exc:
            raise _raster_error(self.path, exc) from None
        valid = (mask >= 0.5) & np.isfinite(data)
        if self.nodata is not None and factor == 1:
            valid &= data != self.nodata
        values = np.where(valid, data * self.scale + self.offset, np.nan) * self.unit_factor
        return values, valid, (c0, r0), (h, w)

    def read_heights(self) -> tuple[np.ndarray, np.ndarray]:
        """(heights m above the sphere, NaN where nodata; valid mask) of the whole raster, native pixels."""
        values, valid, _, _ = self._read_window(
            np.array([0.0, self.width]), np.array([0.0, self.height]), 1, margin_px=0
        )
        return self._to_height(values), valid

    def _to_height(self, values: np.ndarray) -> np.ndarray:
        if self.stores_radius or (np.isfinite(values).any() and np.nanmedian(values) > 0.5 * self.body_radius_m):
            return values - self.body_radius_m
        return values

    def coverage(self, lat_deg, lon_deg, spacing_m: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(inside, valid) booleans per point: within the raster, and on a non-nodata cell."""
        col, row = self.latlon_to_pixel(lat_deg, lon_deg)
        inside = self.inside(col, row)
        valid = np.zeros(col.shape, dtype=bool)
        if inside.any():
            factor = self._decimation(spacing_m)
            _, ok, (c0, r0), _ = self._read_window(col[inside], row[inside], factor)
            ci = np.clip(((col[inside] - c0) / factor).astype(int), 0, ok.shape[1] - 1)
            ri = np.clip(((row[inside] - r0) / factor).astype(int), 0, ok.shape[0] - 1)
            valid[inside] = ok[ri, ci]
        return inside, valid

    def sample(
        self, lat_deg, lon_deg, *, spacing_m: float | None = None, max_nodata_fraction: float = 1.0, what: str = "patch"
    ) -> SampleResult:
        """Heights (m above the sphere) at (lat, lon), bicubic; nodata filled, counted and bounded.

        ``spacing_m``: the query grid's spacing, for anti-alias decimation of a finer DEM.
        ``what``: names the patch in error messages.
        """
        from scipy import ndimage

        col, row = self.latlon_to_pixel(lat_deg, lon_deg)
        inside = self.inside(col, row)
        if not inside.all():
            share = 1.0 - float(inside.mean())
            left, bottom, right, top = self.bounds
            raise DemCoverageError(
                f"{what} extends outside DEM {self.product} ({share:.1%} of its points; DEM covers "
                f"x [{left / 1e3:.1f}, {right / 1e3:.1f}] km, y [{bottom / 1e3:.1f}, {top / 1e3:.1f}] km "
                f"in {self.crs.to_proj4()})"
            )
        factor = self._decimation(spacing_m)
        values, valid, (c0, r0), (h, w) = self._read_window(col, row, factor)
        # Continuous decimated-grid coordinates; array index of a cell centre = coordinate - 0.5.
        cc = (col - c0) / factor - 0.5
        rr = (row - r0) / factor - 0.5
        ci = np.clip(np.rint(cc).astype(int), 0, values.shape[1] - 1)
        ri = np.clip(np.rint(rr).astype(int), 0, values.shape[0] - 1)
        nodata_fraction = float(1.0 - valid[ri, ci].mean()) if col.size else 0.0
        if nodata_fraction > max_nodata_fraction:
            raise DemNodataError(
                f"{what}: {nodata_fraction:.1%} of the patch is nodata in DEM {self.product}, more than "
                f"dem.max_nodata_fraction={max_nodata_fraction:g}"
            )
        values = self._to_height(values)
        holes = ~valid
        filled_pixels = int(holes.sum())
        filled_holes = 0
        if filled_pixels:
            if valid.sum() < 1:
                raise DemNodataError(f"{what}: the DEM window read from {self.product} is entirely nodata")
            filled_holes = int(ndimage.label(holes, structure=np.ones((3, 3)))[1])
            filled = fillnodata(
                np.where(valid, values, 0.0).astype(np.float32),
                mask=valid.astype(np.uint8),
                max_search_distance=float(max(values.shape)) * 2.0,
                smoothing_iterations=0,
            )
            values = np.where(valid, values, filled.astype(np.float64))
            if not np.isfinite(values).all():  # pragma: no cover - GDAL fills everything reachable
                raise DemNodataError(f"{what}: nodata holes in DEM {self.product} could not be filled")
        heights = ndimage.map_coordinates(
            values, [rr.ravel(), cc.ravel()], order=3, mode="nearest", prefilter=True
        ).reshape(col.shape)
        return SampleResult(
            heights=heights,
            nodata_fraction=nodata_fraction,
            filled_pixels=filled_pixels,
            filled_holes=filled_holes,
            decimation=factor,
            window=(c0, r0, w, h),
        )
