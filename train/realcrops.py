"""The real-crop protocol (docs/realset.md), shared by the embedded mosaic (train/realset.py) and
georeferenced frames (train/realframes.py): the reference grid, the seeded sigma / slewing / roll
draws, and the crop record. Test data only; nothing here reaches the training loader."""

from __future__ import annotations

import re
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from crater_core.geometry import polar_stereo_forward, polar_stereo_inverse
from crater_core.settings import RealsetSettings
from data_manifest.products import get_product, resolve_product
from train.errors import RealSetError


def product_pole(product_id: str) -> str:
    """The pole (``"south"``/``"north"``) of a registered polar-stereographic product, read from its CRS
    in data_manifest/products.yaml (``+lat_0=-90`` or ``+lat_0=90``)."""
    try:
        crs = str(get_product(product_id).get("crs") or "")
    except Exception as exc:  # noqa: BLE001 - ProductError: unknown id, named below
        raise RealSetError(f"real test product {product_id!r}: {exc}") from None
    m = re.search(r"\+lat_0=(-?[0-9.]+)", crs)
    if not m or abs(abs(float(m.group(1))) - 90.0) > 1e-9:
        raise RealSetError(
            f"real test product {product_id!r} is not polar stereographic (crs {crs!r}); set realset.mosaic.pole"
        )
    return "north" if float(m.group(1)) > 0 else "south"


@dataclass(frozen=True)
class PolarGrid:
    """The crop protocol's reference grid: the mosaic's pixel grid (polar stereographic at ``pole`` on
    the ``radius_m`` sphere, square extent +-``extent_m``, ``pixel_m`` per pixel; u right, v down, origin
    at the top-left corner). Crops are planned on it, whatever image they are cut from."""

    extent_m: float
    pixel_m: float
    radius_m: float
    pole: str = "south"  # crater_core.geometry.polar_stereo_forward

    @classmethod
    def from_settings(cls, realset: RealsetSettings) -> "PolarGrid":
        """The grid of ``realset.mosaic`` (its pole: ``realset.mosaic.pole``, else the product's CRS)."""
        m = realset.mosaic
        product_id = realset.source_product or m.product_id or ""
        pole = m.pole or (product_pole(product_id) if product_id else "south")
        return cls(m.extent_m, m.pixel_m, m.radius_m, pole)

    def latlon_to_uv(self, lat_deg, lon_deg):
        """Pixel coordinates (u, v) of points given in degrees: floats for a scalar point, arrays for
        arrays (the same formula for both)."""
        x, y = polar_stereo_forward(lat_deg, lon_deg, self.pole, self.radius_m)
        u = (np.asarray(x, dtype=np.float64) + self.extent_m) / self.pixel_m
        v = (self.extent_m - np.asarray(y, dtype=np.float64)) / self.pixel_m
        return (float(u), float(v)) if np.ndim(u) == 0 else (u, v)

    def uv_to_latlon(self, u, v):
        """Inverse of :meth:`latlon_to_uv`: (lat_deg, lon_deg) of pixel coordinates (u, v)."""
        x, y = self.uv_to_xy(u, v)
        return polar_stereo_inverse(x, y, self.pole, self.radius_m)

    def uv_to_xy(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Projected metres (x, y) of grid pixel coordinates (the inverse of the affine part)."""
        x = np.asarray(u, dtype=np.float64) * self.pixel_m - self.extent_m
        y = self.extent_m - np.asarray(v, dtype=np.float64) * self.pixel_m
        return x, y

    @property
    def proj4(self) -> str:
        """The grid's projection as a PROJ string (the same as the registry's ``crs`` of the mosaic)."""
        lat0 = 90 if self.pole == "north" else -90
        return (
            f"+proj=stere +lat_0={lat0} +lat_ts={lat0} +lon_0=0 +k=1 +x_0=0 +y_0=0 +R={self.radius_m:g} "
            "+units=m +no_defs"
        )


@dataclass(frozen=True)
class RealCrop:
    """One labelled real crop: where it comes from and how it was cut. Not a render-manifest row."""

    crater: str
    source: str  # product id (embedded) or the labels file's ``source`` column
    image_path: str
    box: tuple[float, float, float, float]  # axis-aligned (u0, v0, u1, v1) before rotation, image px
    sigma: float
    rotation_deg: float = 0.0
    offset_px: tuple[float, float] = (0.0, 0.0)
    offset_frac: tuple[float, float] = (0.0, 0.0)
    kind: str = "embedded"  # embedded | labels | frame
    index: int = 0
    extra: dict = field(default_factory=dict)
    frame_id: str = ""  # kind "frame": the frame's identifier (product id or file stem)
    # kind "frame": the sampling parallelogram's axes in frame pixels, row-major 2x2 (train.preprocess.
    # resample_affine); ``box`` is then its axis-aligned bounds and ``rotation_deg`` the protocol's roll.
    axes: tuple[float, float, float, float] | None = None

    def as_row(self) -> dict:
        d = asdict(self)
        d["box"] = [round(float(b), 4) for b in self.box]
        if self.axes is not None:
            d["axes"] = [round(float(a), 6) for a in self.axes]
        d["offset_px"] = [round(float(o), 4) for o in self.offset_px]
        d["offset_frac"] = [round(float(o), 6) for o in self.offset_frac]
        d["rotation_deg"] = round(float(self.rotation_deg), 6)
        d["role"] = "test"
        return d


def _crater_seed(seed: int, name: str) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode())])


@dataclass(frozen=True)
class ProtocolCrop:
    """One crop of the seeded protocol, on the reference grid (:class:`PolarGrid` pixels): the box of
    side ``sigma`` x rim diameter centred on the crater's projected centre plus a slewing offset, and a
    roll of the sampling grid. The mosaic's crops are these boxes as they are; a frame's crops are the
    same ground footprints carried into the frame by its georeference (train/realframes.py)."""

    crater: str
    index: int
    sigma: float
    center: tuple[float, float]  # crater centre + offset, reference px
    side: float  # reference px
    rotation_deg: float
    offset_px: tuple[float, float]
    offset_frac: tuple[float, float]

    @property
    def box(self) -> tuple[float, float, float, float]:
        (cu, cv), h = self.center, self.side / 2
        return (cu - h, cv - h, cu + h, cv + h)


def protocol_crops(grid: PolarGrid, craters: Sequence[Mapping], realset: RealsetSettings) -> list[ProtocolCrop]:
    """The seeded crop protocol (docs/realset.md), the one definition for the mosaic and for frames:
    ``per_crater`` crops per crater, sigmas cycled, uniform offsets in [-max_offset_frac,
    max_offset_frac] x side per axis, rolls uniform in [-max_rotation_deg, max_rotation_deg], drawn
    from ``default_rng([seed, crc32(name)])``."""
    per, sigmas, seed = realset.per_crater, realset.sigmas, realset.seed
    max_off, max_rot = realset.max_offset_frac, realset.max_rotation_deg
    out: list[ProtocolCrop] = []
    for c in craters:
        name = str(c["name"])
        cu, cv = grid.latlon_to_uv(float(c["lat"]), float(c["lon"]))
        d_px = float(c["diameter_km"]) * 1000.0 / grid.pixel_m
        rng = _crater_seed(seed, name)
        offs = rng.uniform(-max_off, max_off, size=(per, 2))
        rots = rng.uniform(-max_rot, max_rot, size=per)
        for i in range(per):
            s = sigmas[i % len(sigmas)]
            side = s * d_px
            du, dv = offs[i] * side
            out.append(
                ProtocolCrop(
                    crater=name,
                    index=i,
                    sigma=s,
                    center=(cu + du, cv + dv),
                    side=side,
                    rotation_deg=float(rots[i]),
                    offset_px=(float(du), float(dv)),
                    offset_frac=(float(offs[i, 0]), float(offs[i, 1])),
                )
            )
    return out


def canonical_crater(name: str) -> str:
    return "_".join(str(name).strip().lower().replace("-", " ").split())


def resolve_product_image(spec: str, data_dir: str | Path | None, where: str) -> Path:
    """``product:<id>`` -> the verified local file of a registered data product (data_manifest/products.yaml)."""
    pid = spec.split(":", 1)[1].strip()
    try:
        return Path(resolve_product(pid, data_dir or "data"))
    except Exception as exc:  # noqa: BLE001 - ProductError & co: report with the labels-file line
        raise RealSetError(f"{where}: cannot resolve {spec!r}: {exc}") from None


def crop_pixels(image: np.ndarray, crop: "RealCrop", size: int, antialias: bool = True, order: int = 1) -> np.ndarray:
    """The crop's pixels resampled to ``size`` x ``size`` (no photometry): the rotated box of a mosaic or
    labels-file crop, the georeferenced parallelogram (``axes``) of a frame crop."""
    from train.preprocess import box_center_side, resample_affine, resample_box

    if crop.axes is None:
        return resample_box(image, crop.box, size, crop.rotation_deg, antialias, order)
    cu, cv, _, _ = box_center_side(crop.box)
    return resample_affine(image, (cu, cv), crop.axes, size, antialias, order)
