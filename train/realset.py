"""The real test set (docs/realset.md): labelled crops of real lunar images. Test data only.

1. Embedded default: the LROC WAC polar mosaics shipped inside the ``lunar-toolkit`` wheel (read
   as files, never imported): ``realset=wac_south`` (default) or ``realset=wac_north`` for the
   north-polar craters. For each crater, ``realset.per_crater`` (300) crops: a square ROI of
   side sigma x rim diameter (diameter_m / 400 m px) centred on the crater's projected centre, with a
   seeded "slewing" offset and a rotation of the sampling grid. This is ONE real observation per
   crater seen 300 ways, not 300 observations; every report says so.
2. User frames (LROC NAC, SELENE TC/HDTV, ...): a CSV labels file (``realset.labels_file``), one row
   per frame and crater, cropped at every sigma without code changes.

By construction this module has no path to the training loader: it imports nothing from
``train.data`` / ``train.trainer`` (a test checks the import graph), and the rows it produces are not
render-manifest rows (``train.data`` refuses them).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import OpenImageIO as oiio

from crater_core.errors import ContractError
from crater_core.geometry import hemisphere
from crater_core.schema import sha256_file
from crater_core.settings import RealsetSettings, Settings
from data_manifest.products import embedded_path
from train.errors import RealSetError
from train.preprocess import PreprocessConfig, outside_fraction, preprocess_crop
from train.realcrops import (  # noqa: F401 - re-exported: the crop protocol is defined there
    PolarGrid,
    ProtocolCrop,
    RealCrop,
    canonical_crater,
    product_pole,
    protocol_crops,
    resolve_product_image,
)
from train.realframes import plan_frames

LIMITS_NOTE = (
    "The embedded real test set is one real observation per crater (one LROC WAC polar "
    "mosaic, 400 m/px) seen many ways (sigma, slewing offsets, rotations): crops of the same "
    "crater are strongly correlated, so accuracies measure recognition of that single "
    "observation, not generalisation over real illumination conditions."
)


# ------------------------------------------------------------------------------------------------
# Products
# ------------------------------------------------------------------------------------------------
def embedded_product_path(product_id: str) -> Path:
    """Path of an embedded real product (e.g. the WAC mosaic) inside its installed distribution."""
    try:
        return embedded_path(product_id)
    except ContractError as exc:
        raise RealSetError(f"real test product {product_id!r}: {exc}") from None


@dataclass(frozen=True)
class Mosaic:
    """A polar-stereographic product: pixel (u right, v down, origin at the top-left corner)."""

    product_id: str
    path: Path
    image: np.ndarray  # (H, W) uint8
    extent_m: float  # half-width of the square extent
    pixel_m: float
    radius_m: float
    pole: str = "south"  # which polar stereographic projection (crater_core.geometry.polar_stereo_forward)

    @property
    def grid(self) -> PolarGrid:
        return PolarGrid(self.extent_m, self.pixel_m, self.radius_m, self.pole)

    def latlon_to_uv(self, lat_deg, lon_deg):
        """Pixel coordinates (u, v) of points given in degrees: floats for a scalar point, arrays for
        arrays (the same formula for both)."""
        return self.grid.latlon_to_uv(lat_deg, lon_deg)

    def uv_to_latlon(self, u, v):
        """Inverse of :meth:`latlon_to_uv`: (lat_deg, lon_deg) of pixel coordinates (u, v)."""
        return self.grid.uv_to_latlon(u, v)

    def check_crater(self, crater: Mapping) -> None:
        """Refuse a crater of the other hemisphere than this mosaic with one line naming both."""
        if hemisphere(crater["lat"]) != self.pole:
            raise RealSetError(
                f"crater {crater['name']} (lat {float(crater['lat']):g}) is in the {hemisphere(crater['lat'])}ern "
                f"hemisphere but real mosaic {self.product_id} is {self.pole}-polar: use realset=wac_"
                f"{hemisphere(crater['lat'])}"
            )


def load_mosaic(realset: RealsetSettings) -> Mosaic:
    """Locate, checksum and decode the embedded mosaic of ``realset.mosaic``."""
    m = realset.mosaic
    product_id = str(realset.source_product or m.product_id)
    path = Path(m.path) if m.path else embedded_product_path(product_id)
    expected = m.sha256
    extent, pixel, radius = m.extent_m, m.pixel_m, m.radius_m
    pole = m.pole or product_pole(product_id)
    if not path.is_file():
        raise RealSetError(f"real test product {product_id!r}: {path} does not exist")
    if expected:
        got = sha256_file(path)
        if got != expected:
            raise RealSetError(
                f"real test product {product_id!r}: {path} has sha256 {got}, expected {expected} "
                f"(corrupt or a different version)"
            )
    img = read_gray(path, keep_uint8=True)
    size = int(round(2.0 * extent / pixel))
    if img.shape != (size, size):
        raise RealSetError(
            f"real test product {product_id!r}: {path} is {img.shape[1]}x{img.shape[0]}, "
            f"expected {size}x{size} from extent_m={extent} and pixel_m={pixel}"
        )
    return Mosaic(product_id, path, img, extent, pixel, radius, pole)


def read_gray(path: str | Path, keep_uint8: bool = False, max_pixels: int | None = None) -> np.ndarray:
    """Read any image OpenImageIO understands as a 2-D array (mean of the colour channels).
    8-bit files stay uint8 when ``keep_uint8``; everything else becomes float32 (integers scaled to
    [0, 1] by their full range -- a pure scale, which the normalisation undoes). An image of more than
    ``max_pixels`` is refused from its header, before anything is decoded."""
    path = Path(path)
    if not path.is_file():
        raise RealSetError(f"real image {path} does not exist")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise RealSetError(f"cannot read real image {path}: {oiio.geterror()}")
    try:
        spec = inp.spec()
        if max_pixels is not None and spec.width * spec.height > max_pixels:
            raise RealSetError(
                f"real image {path} is {spec.width} x {spec.height} px, more than the {max_pixels} px read at once"
            )
        native8 = spec.format == oiio.TypeDesc(oiio.UINT8)
        fmt = oiio.UINT8 if (keep_uint8 and native8) else oiio.FLOAT
        data = inp.read_image(0, 0, 0, min(spec.nchannels, 3), fmt)
        if data is None:
            raise RealSetError(f"cannot decode real image {path}: {inp.geterror()}")
    finally:
        inp.close()
    data = np.asarray(data)
    if data.ndim == 3:
        data = data[..., 0] if data.shape[2] == 1 else data.astype(np.float32).mean(axis=2)
    return data if (keep_uint8 and native8 and data.dtype == np.uint8) else data.astype(np.float32)


# ------------------------------------------------------------------------------------------------
# Crops
# ------------------------------------------------------------------------------------------------
def plan_embedded_crops(
    mosaic_shape: tuple[int, int], mosaic: Mosaic | None, craters: Sequence[Mapping], realset: RealsetSettings
) -> list[RealCrop]:
    """The protocol's crops of the embedded mosaic (:func:`protocol_crops` on the mosaic's own grid).
    Every rotated box must lie inside the mosaic."""
    assert mosaic is not None
    for c in craters:
        mosaic.check_crater(c)
    out: list[RealCrop] = []
    for p in protocol_crops(mosaic.grid, craters, realset):
        box = p.box
        if outside_fraction(box, mosaic_shape, p.rotation_deg) > 0:
            raise RealSetError(
                f"realset: crop {p.index} of {p.crater} (sigma={p.sigma}, rotation={p.rotation_deg:.1f}) leaves the "
                f"{mosaic_shape[1]}x{mosaic_shape[0]} mosaic {mosaic.path.name}"
            )
        out.append(
            RealCrop(
                crater=p.crater,
                source=mosaic.product_id,
                image_path=str(mosaic.path),
                box=box,
                sigma=p.sigma,
                rotation_deg=p.rotation_deg,
                offset_px=p.offset_px,
                offset_frac=p.offset_frac,
                kind="embedded",
                index=p.index,
            )
        )
    return out


LABEL_COLUMNS = ("image_path", "crater", "source")
CENTER_COLUMNS = ("center_u", "center_v", "diameter_px")
BOX_COLUMNS = ("box_u0", "box_v0", "box_u1", "box_v1")


def load_labels_file(
    path: str | Path, class_names: Sequence[str], sigmas: Sequence[float], data_dir: str | Path | None = None
) -> list[RealCrop]:
    """Crops of user-provided real frames described by a CSV labels file (docs/realset.md).

    Columns: ``image_path`` (relative to the CSV's folder, absolute, or ``product:<id>`` for a product
    registered in data_manifest/products.yaml and fetched with ``crater-synth fetch-data``),
    ``crater`` (one of the trained
    classes; case, spaces and hyphens ignored), ``source`` (e.g. ``lroc_nac``, ``selene_tc``), and the
    rim either as ``center_u, center_v, diameter_px`` or as its bounding box ``box_u0, box_v0, box_u1,
    box_v1`` (image pixels: u right, v down, origin at the top-left corner). Optional: ``rotation_deg``.
    Each row yields one crop per sigma.
    """
    path = Path(path)
    if not path.is_file():
        raise RealSetError(f"labels file {path} does not exist")
    known = {canonical_crater(n): n for n in class_names}
    crops: list[RealCrop] = []
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        cols = set(reader.fieldnames or [])
        missing = [c for c in LABEL_COLUMNS if c not in cols]
        has_center = all(c in cols for c in CENTER_COLUMNS)
        has_box = all(c in cols for c in BOX_COLUMNS)
        if missing or not (has_center or has_box):
            raise RealSetError(
                f"labels file {path}: needs columns {list(LABEL_COLUMNS)} and either "
                f"{list(CENTER_COLUMNS)} or {list(BOX_COLUMNS)}; has {sorted(cols)}"
            )
        for lineno, rec in enumerate(reader, 2):
            where = f"labels file {path}:{lineno}"
            crater = known.get(canonical_crater(rec.get("crater") or ""))
            if crater is None:
                raise RealSetError(
                    f"{where}: unknown crater {rec.get('crater')!r}; the classifier knows {sorted(class_names)}"
                )
            spec = (rec.get("image_path") or "").strip()
            if not spec:
                raise RealSetError(f"{where}: empty image_path")
            if spec.startswith("product:"):
                img = resolve_product_image(spec, data_dir, where)
            else:
                img = Path(spec)
                if not img.is_absolute():
                    img = path.parent / img
                if not img.is_file():
                    raise RealSetError(f"{where}: image {img} does not exist")
            try:
                if has_center and all((rec.get(c) or "").strip() for c in CENTER_COLUMNS):
                    cu, cv, d = (float(rec[c]) for c in CENTER_COLUMNS)
                else:
                    u0, v0, u1, v1 = (float(rec[c]) for c in BOX_COLUMNS)
                    cu, cv, d = 0.5 * (u0 + u1), 0.5 * (v0 + v1), max(u1 - u0, v1 - v0)
                rot = float(rec.get("rotation_deg") or 0.0)
            except (TypeError, ValueError) as exc:
                raise RealSetError(f"{where}: bad number ({exc})") from None
            if not (d > 0 and all(map(math.isfinite, (cu, cv, d, rot)))):
                raise RealSetError(f"{where}: rim diameter must be > 0 and all values finite")
            source = (rec.get("source") or "").strip() or "user"
            for s in sigmas:
                side = float(s) * d
                crops.append(
                    RealCrop(
                        crater=crater,
                        source=source,
                        image_path=str(img),
                        box=(cu - side / 2, cv - side / 2, cu + side / 2, cv + side / 2),
                        sigma=float(s),
                        rotation_deg=rot,
                        kind="labels",
                        index=lineno,
                    )
                )
    if not crops:
        raise RealSetError(f"labels file {path} has no rows")
    return crops


# ------------------------------------------------------------------------------------------------
# The test set
# ------------------------------------------------------------------------------------------------
@dataclass
class RealTestSet:
    images: np.ndarray  # (N, size, size) float32, normalised
    labels: np.ndarray  # (N,) int64 class indices
    crops: list[RealCrop]
    class_names: list[str]
    skipped: list[str] = field(default_factory=list)  # one line per frame crop left out (it leaves its frame)

    @property
    def sources(self) -> list[str]:
        return sorted({c.source for c in self.crops})

    def rows(self) -> list[dict]:
        return [c.as_row() for c in self.crops]

    def image_sha256s(self) -> set[str]:
        """Checksums of every real image file used (training refuses any file with one of them)."""
        return {sha256_file(p) for p in sorted({c.image_path for c in self.crops})}


def plan_real_crops(
    rs: RealsetSettings,
    craters: Sequence[Mapping],
    class_names: Sequence[str],
    data_dir: str | Path | None = None,
    skipped: list[str] | None = None,
) -> tuple[list[RealCrop], dict]:
    """All crops of the real test set of ``realset`` (embedded mosaic, labels file and/or frames) plus the
    loaded images by path; ``data_dir`` holds the data products that ``product:<id>`` paths name; the
    frame crops left out (see :func:`train.realframes.plan_frames`) are appended to ``skipped``."""
    sigmas = list(rs.sigmas)
    crops: list[RealCrop] = []
    images: dict[str, np.ndarray] = {}
    if rs.include_embedded:
        mosaic = load_mosaic(rs)
        images[str(mosaic.path)] = mosaic.image
        known = {canonical_crater(n) for n in class_names}
        sel = [c for c in craters if canonical_crater(c["name"]) in known]
        crops += plan_embedded_crops(mosaic.image.shape, mosaic, sel, rs)
    if rs.labels_file:
        lab = load_labels_file(rs.labels_file, class_names, sigmas, data_dir)
        for c in lab:
            if c.image_path not in images:
                images[c.image_path] = read_gray(c.image_path, keep_uint8=True)
            shape = images[c.image_path].shape
            if outside_fraction(c.box, shape, c.rotation_deg) > 0.25:
                raise RealSetError(
                    f"labels file {rs.labels_file}:{c.index}: sigma={c.sigma} box {list(c.box)} "
                    f"leaves the {shape[1]}x{shape[0]} image {c.image_path} by more than 25 %"
                )
        crops += lab
    if rs.frames:
        known = {canonical_crater(n) for n in class_names}
        sel = [c for c in craters if canonical_crater(c["name"]) in known]
        frame_crops, frame_images = plan_frames(rs, sel, data_dir, skipped)
        crops += frame_crops
        images.update(frame_images)
    if not crops:  # the settings refuse a realset with no source; this is none of the classes' crops
        raise RealSetError(f"the real test set has no crop of the classes {list(class_names)}")
    return crops, images


def build_real_test_set(
    settings: Settings, craters: Sequence[Mapping], class_names: Sequence[str], pp: PreprocessConfig | None = None
) -> RealTestSet:
    """Cut, resample and normalise every real crop (same path as the synthetic images, no sensor model);
    ``pp``: the preprocessing (default: the configured one, :meth:`PreprocessConfig.from_settings`)."""
    pp = pp or PreprocessConfig.from_settings(settings.train.preprocess, settings.model.input_size)
    skipped: list[str] = []
    crops, images = plan_real_crops(settings.realset, craters, class_names, settings.data_dir, skipped)
    cls = {n: i for i, n in enumerate(class_names)}
    X = np.empty((len(crops), pp.size, pp.size), dtype=np.float32)
    for i, c in enumerate(crops):
        X[i] = preprocess_crop(images[c.image_path], c.box, pp, rotation_deg=c.rotation_deg, axes=c.axes)
    y = np.array([cls[c.crater] for c in crops], dtype=np.int64)
    return RealTestSet(X, y, crops, list(class_names), skipped)
