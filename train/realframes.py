"""Real test crops from georeferenced frames (docs/realset.md, "Georeferenced frames"). Test data only.

A frame is any raster GDAL reads (through rasterio) with a georeference: a map-projected GeoTIFF, an
ISIS3 cube or PDS3 image whose label carries a map projection, or an image with ground control
points. Each crater is located from the georeference, and the crops are the seeded protocol of the
mosaic (:func:`train.realcrops.protocol_crops`, one definition): the same sigma, slewing offset and
roll, planned on the reference grid (the mosaic's south polar stereographic pixels) and carried into
the frame by the local linear map of "reference pixel -> frame pixel" at each crop centre. A frame
and the mosaic therefore give crops of the same ground footprint, whatever the frame's projection
and resolution; the roll is measured from the reference grid's north (the mosaic's up).

Checks, each one :class:`RealSetError` naming the frame, raised before anything is written: the file
exists and decodes completely (a truncated file fails), it has a georeference (a CRS with an affine
transform or ground control points; a raw camera frame has none), its CRS is the Moon's (semi-major
axis within 1 % of 1737.4 km: an Earth or Mars CRS is refused), every crater asked for lies in the
frame. A crop that leaves the frame or covers no-data pixels (a crater near the frame's edge: the
protocol's largest sigma, offset and roll reach furthest) is skipped, not fatal: it is one line naming
the frame, the crop and the crater, handed to the caller (the evaluation reports each and counts them).
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.errors import NotGeoreferencedWarning, RasterioError
from rasterio.transform import from_gcps
from rasterio.warp import transform as warp_transform

from crater_core.settings import RealsetSettings
from train.errors import RealSetError
from train.realcrops import PolarGrid, RealCrop, canonical_crater, protocol_crops, resolve_product_image

# IAU mean radius of the Moon (Archinal et al. 2018, IAU WGCCRE report), and the tolerance on a
# frame CRS's semi-major axis: lunar CRSs use 1737.4 km or 1737.15 km; Mars (3396.19 km) and Earth
# (6378.137 km) are far outside.
MOON_RADIUS_M = 1737400.0
BODY_TOLERANCE = 0.01
_AXIS_RE = re.compile(r'(?:ELLIPSOID|SPHEROID)\[\s*"([^"]*)"\s*,\s*([0-9.eE+-]+)')
# Bodies named when a frame's CRS is refused (semi-major axes in m: IAU/IERS values).
_BODIES = {"Earth": 6378137.0, "Mars": 3396190.0, "Mercury": 2440530.0, "Venus": 6051800.0}

# The largest frame read at once (real test frames here, `crater-synth navigate`'s image): a 16384^2 PNG
# took 6 GB to read, so 8192^2 (about 1.5 GB) is the bound; cut a larger image into windows.
MAX_FRAME_PIXELS = 8192 * 8192

RAW_FRAME_HINT = (
    "a raw camera frame (e.g. an LROC CDR or SELENE TC level-2B0 image) has no map georeference: "
    "map-project it first (ISIS: lrowac2isis or kaguyatc2isis, spiceinit, cam2map) and give the "
    "resulting .cub or GeoTIFF"
)


@dataclass
class Frame:
    """A decoded georeferenced frame: its pixels (float32, NaN where no data) and georeference."""

    frame_id: str
    source: str
    path: Path
    image: np.ndarray
    crs: object  # rasterio.crs.CRS
    transform: object  # affine.Affine: pixel (col, row) corner coordinates -> projected (x, y)

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape

    def xy_to_uv(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Frame pixel coordinates (u right, v down, origin at the top-left corner) of projected points."""
        i = ~self.transform
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        return i.a * x + i.b * y + i.c, i.d * x + i.e * y + i.f

    def uv_to_xy(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Projected coordinates of frame pixel coordinates (the inverse of :meth:`xy_to_uv`)."""
        t = self.transform
        u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
        return t.a * u + t.b * v + t.c, t.d * u + t.e * v + t.f


def crs_semi_major_m(crs) -> float | None:
    """The semi-major axis (m) of a CRS's ellipsoid, read from its WKT; None if it names none."""
    m = _AXIS_RE.search(crs.to_wkt())
    return float(m.group(2)) if m else None


def check_lunar_crs(crs, where: str) -> None:
    """Refuse a CRS whose ellipsoid is not the Moon's (a frame in an Earth or Mars CRS)."""
    a = crs_semi_major_m(crs)
    if a is None:
        raise RealSetError(f"{where}: its CRS names no ellipsoid, so its body is unknown ({crs.to_string()[:120]})")
    if abs(a / MOON_RADIUS_M - 1.0) > BODY_TOLERANCE:
        guess = min(_BODIES, key=lambda b: abs(_BODIES[b] - a))
        body = f" ({guess}'s)" if abs(_BODIES[guess] / a - 1.0) < 0.01 else ""
        raise RealSetError(
            f"{where}: its CRS is on a body of radius {a / 1000:.3f} km{body}, not the Moon "
            f"({MOON_RADIUS_M / 1000:.1f} km +- {BODY_TOLERANCE:.0%}); real test frames must be lunar"
        )


def dataset_georeference(ds) -> tuple[object, object] | None:
    """(CRS, affine pixel-corner -> projected transform) of an open rasterio dataset: its own, else one fitted
    to its ground control points; None when it has neither (the CRS is not checked here)."""
    if ds.crs is not None and not ds.transform.is_identity:
        return ds.crs, ds.transform
    gcps, gcp_crs = ds.gcps
    if gcps and gcp_crs is not None:
        return gcp_crs, from_gcps(gcps)
    return None


def open_frame(path: str | Path, frame_id: str | None = None, source: str | None = None, band: int = 1) -> Frame:
    """Read one georeferenced frame completely (every check of the module docstring but the craters')."""
    path = Path(path)
    fid = frame_id or path.stem
    where = f"real frame {fid!r} ({path})"
    if not path.is_file():
        raise RealSetError(f"{where} does not exist")
    try:
        with warnings.catch_warnings():
            # A bare file is refused below with its own message, not rasterio's warning.
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            ds = rasterio.open(path)
        with ds:
            if not 1 <= band <= ds.count:
                raise RealSetError(f"{where}: band {band} asked for, the file has {ds.count}")
            found = dataset_georeference(ds)
            if found is None:
                raise RealSetError(
                    f"{where} has no georeference (no CRS and no ground control points); {RAW_FRAME_HINT}"
                )
            crs, transform = found
            check_lunar_crs(crs, where)
            if ds.width * ds.height > MAX_FRAME_PIXELS:  # from the header, before anything is decoded
                raise RealSetError(
                    f"{where} is {ds.width} x {ds.height} px, more than the {MAX_FRAME_PIXELS} px read at once: "
                    "cut it into smaller frames"
                )
            data = ds.read(band, masked=True)
    except RasterioError as exc:
        raise RealSetError(f"{where} cannot be read completely (truncated or corrupt?): {exc}") from None
    image = np.ma.filled(data.astype(np.float32), np.nan)
    if not np.isfinite(image).any():
        raise RealSetError(f"{where} holds no valid pixel")
    return Frame(fid, source or fid, path, image, crs, transform)


def reference_to_frame(grid: PolarGrid, frame: Frame, u, v) -> tuple[np.ndarray, np.ndarray]:
    """Frame pixel coordinates of reference-grid pixel coordinates (through the georeference)."""
    x, y = grid.uv_to_xy(np.atleast_1d(u), np.atleast_1d(v))
    fx, fy = warp_transform(CRS.from_proj4(grid.proj4), frame.crs, x.tolist(), y.tolist())
    return frame.xy_to_uv(fx, fy)


def _local_map(grid: PolarGrid, frame: Frame, center: tuple[float, float], h: float) -> tuple[np.ndarray, np.ndarray]:
    """(frame centre (2,), Jacobian d(frame px)/d(reference px) (2, 2)) at ``center``, by central
    differences over +-``h`` reference px (the crop's scale, so the linear map is the crop's secant)."""
    cu, cv = center
    us = np.array([cu, cu + h, cu - h, cu, cu])
    vs = np.array([cv, cv, cv, cv + h, cv - h])
    fu, fv = reference_to_frame(grid, frame, us, vs)
    if not (np.all(np.isfinite(fu)) and np.all(np.isfinite(fv))):
        raise RealSetError(f"real frame {frame.frame_id!r}: the point {center} cannot be projected into its CRS")
    jac = np.array(
        [[(fu[1] - fu[2]) / (2 * h), (fu[3] - fu[4]) / (2 * h)], [(fv[1] - fv[2]) / (2 * h), (fv[3] - fv[4]) / (2 * h)]]
    )
    return np.array([fu[0], fv[0]]), jac


def frame_crops(
    frame: Frame, grid: PolarGrid, craters: Sequence[Mapping], realset: RealsetSettings, skipped: list[str]
) -> list[RealCrop]:
    """The protocol's crops of ``craters`` in ``frame``; every crater must lie in the frame. A crop that
    leaves the frame or covers no-data pixels is left out, with one line naming it appended to ``skipped``."""
    from train.preprocess import axes_extent, box_axes

    H, W = frame.shape
    where = f"real frame {frame.frame_id!r} ({frame.path.name}, {W}x{H})"
    for c in craters:
        cu, cv = grid.latlon_to_uv(float(c["lat"]), float(c["lon"]))
        fu, fv = reference_to_frame(grid, frame, cu, cv)
        if not (0 <= fu[0] < W and 0 <= fv[0] < H):
            raise RealSetError(
                f"{where}: crater {c['name']} ({float(c['lat']):.3f}, {float(c['lon']):.3f}) lies outside the frame "
                f"(at pixel {fu[0]:.1f}, {fv[0]:.1f})"
            )
    out: list[RealCrop] = []
    for p in protocol_crops(grid, craters, realset):
        centre, jac = _local_map(grid, frame, p.center, p.side / 2)
        axes = jac @ box_axes(p.side, p.side, p.rotation_deg)
        u0, v0, u1, v1 = axes_extent(centre, axes)
        crop = f"{where}: crop {p.index} of {p.crater} (sigma={p.sigma}, roll={p.rotation_deg:.1f})"
        if u0 < 0 or v0 < 0 or u1 > W or v1 > H:
            skipped.append(f"{crop} spans pixels [{u0:.1f}, {v0:.1f}, {u1:.1f}, {v1:.1f}], outside the frame: skipped")
            continue
        win = frame.image[int(math.floor(v0)) : int(math.ceil(v1)), int(math.floor(u0)) : int(math.ceil(u1))]
        if not np.all(np.isfinite(win)):
            skipped.append(f"{crop} covers no-data pixels of the frame: skipped")
            continue
        out.append(
            RealCrop(
                crater=p.crater,
                source=frame.source,
                image_path=str(frame.path),
                box=(u0, v0, u1, v1),
                sigma=p.sigma,
                rotation_deg=p.rotation_deg,
                offset_px=p.offset_px,
                offset_frac=p.offset_frac,
                kind="frame",
                index=p.index,
                frame_id=frame.frame_id,
                axes=tuple(float(a) for a in axes.ravel()),
            )
        )
    return out


def _frame_path(spec: str, data_dir: str | Path | None, where: str) -> Path:
    """A frame's file: a path, or ``product:<id>`` for a product of data_manifest/products.yaml."""
    if spec.startswith("product:"):
        return resolve_product_image(spec, data_dir, where)
    return Path(spec).expanduser()


def plan_frames(
    realset: RealsetSettings,
    craters: Sequence[Mapping],
    data_dir: str | Path | None = None,
    skipped: list[str] | None = None,
) -> tuple[list[RealCrop], dict[str, np.ndarray]]:
    """Crops and decoded images of every frame of ``realset.frames``; one line per crop left out (it
    leaves its frame) is appended to ``skipped``, or warned (:mod:`warnings`) when no list is given.

    Each entry: ``path`` (a file, or ``product:<id>``), optional ``frame_id`` (default: the product
    id or the file stem), ``source`` (default: the frame id), ``band`` (default 1) and ``craters``
    (names; default: every selected crater whose centre lies in the frame, at least one)."""
    grid = PolarGrid.from_settings(realset)
    by_name = {canonical_crater(c["name"]): c for c in craters}
    crops: list[RealCrop] = []
    images: dict[str, np.ndarray] = {}
    left_out: list[str] = []
    for i, entry in enumerate(realset.frames):
        spec = entry.path.strip()
        where = f"realset.frames[{i}]"
        path = _frame_path(spec, data_dir, where)
        default_id = spec.split(":", 1)[1] if spec.startswith("product:") else None
        frame = open_frame(path, entry.frame_id or default_id, entry.source, entry.band)
        if entry.craters:
            sel = []
            for name in entry.craters:
                c = by_name.get(canonical_crater(name))
                if c is None:
                    raise RealSetError(f"{where}: crater {name!r} is not selected; selected: {sorted(by_name)}")
                sel.append(c)
        else:
            sel = [c for c in craters if _inside(grid, frame, c)]
            if not sel:
                raise RealSetError(
                    f"{where}: no selected crater ({', '.join(sorted(by_name))}) lies in frame {frame.frame_id!r}"
                )
        crops += frame_crops(frame, grid, sel, realset, left_out)
        images[str(frame.path)] = frame.image
    if skipped is None:
        for line in left_out:
            warnings.warn(line, stacklevel=2)
    else:
        skipped += left_out
    return crops, images


def _inside(grid: PolarGrid, frame: Frame, c: Mapping) -> bool:
    cu, cv = grid.latlon_to_uv(float(c["lat"]), float(c["lon"]))
    fu, fv = reference_to_frame(grid, frame, cu, cv)
    H, W = frame.shape
    return bool(0 <= fu[0] < W and 0 <= fv[0] < H)
