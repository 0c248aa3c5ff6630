"""A user's frame on disk, as ``navigate`` and ``detect`` read it: the image (any file OpenImageIO reads, at
most :data:`train.realframes.MAX_FRAME_PIXELS`, read from its header before decoding), its georeference
sidecar ``IMAGE.geo.json`` (:class:`.georef.Georef`) or (``detect``) the map georeference a GeoTIFF or ISIS
cube carries itself (:class:`CrsGeoref`, any lunar CRS, read through rasterio), and the checks of the
options that describe a frame (``--pixel-m``, ``--light-azimuth``) and of an output that would overwrite an
input. Each failure is one :class:`.georef.FrameError` (or :class:`UserError`) line naming the input. A
folder run's images, error lines and output folder (:class:`crater_synth.outfolder.OutFolder`) are here too,
the same for ``detect DIR`` and ``navigate DIR``."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import click
import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.errors import NotGeoreferencedWarning, RasterioError
from rasterio.warp import transform as warp_transform

from crater_core.geometry import MOON_RADIUS_M
from crater_core.schema import atomic_write_bytes
from crater_synth.errors import UserError
from crater_synth.navigation.georef import FrameError, Georef, check_frame
from crater_synth.outfolder import OutFolder
from train.errors import RealSetError
from train.realframes import (
    MAX_FRAME_PIXELS,  # the largest frame read at once
    check_lunar_crs,
    dataset_georeference,
)

# Files whose own header may carry a map georeference (GeoTIFF, ISIS cube, PDS image, JPEG 2000).
GEOREFERENCED_SUFFIXES = (".tif", ".tiff", ".cub", ".img", ".jp2")
LUNAR_LONLAT = CRS.from_proj4(f"+proj=longlat +R={MOON_RADIUS_M:.0f} +no_defs")

# The images a folder run (detect DIR, navigate DIR) reads, by suffix; its exit status when one failed.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".pnm", ".ppm", ".exr")
EXIT_SOME_FAILED = 1

# Map metres per pixel a frame may claim: from a descent camera's decimetres to a whole-pole overview.
PIXEL_M_RANGE = (0.1, 20_000.0)


def sidecar(image: Path) -> Path:
    """The georeference sidecar of ``image``: ``<image name>.geo.json`` beside it."""
    return image.with_name(image.name + ".geo.json")


def read_georef(image_path: Path) -> Georef | None:
    """The georeference of ``image_path``: its sidecar ``<image>.geo.json`` ({pole, left_m, top_m,
    pixel_m}), or None when it has none."""
    side = sidecar(image_path)
    if not side.is_file():
        return None
    try:
        d = json.loads(side.read_text())
        g = Georef(str(d["pole"]), float(d["left_m"]), float(d["top_m"]), float(d["pixel_m"]))
    except (ValueError, KeyError, TypeError) as exc:
        raise FrameError(f"georeference {side} is corrupt: {exc}") from None
    if g.pole not in ("south", "north") or not g.pixel_m > 0:
        raise FrameError(f"georeference {side}: pole must be south or north and pixel_m > 0")
    return g


@dataclass(frozen=True)
class CrsGeoref:
    """A georeference the image file carries: a lunar CRS and the affine map of pixel (u, v) (from the
    top-left corner) to projected (x, y) (:func:`train.realframes.dataset_georeference`)."""

    crs: object  # rasterio.crs.CRS
    transform: object  # affine.Affine

    def latlon(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """(latitude, longitude) degrees of pixel points."""
        x, y = self.transform * (np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
        lon, lat = warp_transform(self.crs, LUNAR_LONLAT, np.atleast_1d(x).tolist(), np.atleast_1d(y).tolist())
        return np.asarray(lat), np.asarray(lon)

    def ground_km(self, u1, v1, u2, v2) -> np.ndarray:
        """Great-circle distance (km, on the Moon's mean sphere) between pixel points."""
        lat1, lon1 = np.radians(self.latlon(u1, v1))
        lat2, lon2 = np.radians(self.latlon(u2, v2))
        h = np.sin((lat2 - lat1) / 2) ** 2 + np.cos(lat1) * np.cos(lat2) * np.sin((lon2 - lon1) / 2) ** 2
        return 2.0 * MOON_RADIUS_M / 1000.0 * np.arcsin(np.sqrt(np.clip(h, 0.0, 1.0)))

    def as_dict(self) -> dict:
        return {"crs": self.crs.to_string(), "transform": list(self.transform)[:6]}


def file_georef(path: Path) -> CrsGeoref | None:
    """The map georeference ``path``'s own header carries (a file of :data:`GEOREFERENCED_SUFFIXES` with a
    CRS or ground control points), or None; a CRS that is not the Moon's is refused in one line."""
    if path.suffix.lower() not in GEOREFERENCED_SUFFIXES:
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(path) as ds:
                found = dataset_georeference(ds)
    except RasterioError:
        return None  # the pixel reader names what is wrong with the file
    if found is None:
        return None
    try:
        check_lunar_crs(found[0], str(path))
    except RealSetError as exc:
        raise FrameError(str(exc)) from None
    return CrsGeoref(*found)


def read_window(image: Path) -> tuple[np.ndarray, Georef | None]:
    """(image, its georeference or None) of a frame file: grey (a colour image is the mean of its first
    three channels: :func:`train.realset.read_gray`), at most :data:`MAX_FRAME_PIXELS`, checked by
    :func:`.georef.check_frame` (2-D, >= 32 px a side, finite, not constant)."""
    from train.realset import read_gray  # pulls scipy

    try:
        img = read_gray(image, max_pixels=MAX_FRAME_PIXELS)
    except RealSetError as exc:
        raise FrameError(str(exc)) from None
    check_frame(img, str(image))
    return img, read_georef(image)


def check_pixels(path: Path, width: int, height: int) -> None:
    """Refuse, from its header, an image of more than :data:`MAX_FRAME_PIXELS` (one line naming it)."""
    if width * height > MAX_FRAME_PIXELS:
        raise FrameError(
            f"{path} is {width} x {height} px, more than the {MAX_FRAME_PIXELS} px read at once: cut it into "
            "smaller frames"
        )


def check_pixel_m(pixel_m: float | None) -> None:
    """``--pixel-m``: None, or finite metres per pixel within :data:`PIXEL_M_RANGE` (one error line)."""
    lo, hi = PIXEL_M_RANGE
    if pixel_m is not None and not (math.isfinite(pixel_m) and lo <= pixel_m <= hi):
        raise UserError(f"--pixel-m {pixel_m}: map metres per pixel, finite, in [{lo:g}, {hi:g}]")


def check_light_azimuth(light_azimuth: float | None) -> None:
    """``--light-azimuth``: None, or finite degrees (one error line)."""
    if light_azimuth is not None and not math.isfinite(light_azimuth):
        raise UserError(f"--light-azimuth {light_azimuth}: degrees, finite")


def refuse_overwrite(outs: Iterable[Path], inputs: Iterable[Path], flag: str = "--out") -> None:
    """Refuse, in one line, an output path that is one of the inputs (compared resolved: a link, ``./``)."""
    resolved = {Path(p).resolve() for p in inputs}
    outs = list(outs)
    for out in outs:
        if Path(out).resolve() in resolved:
            raise UserError(f"{flag} {outs[0]}: it would overwrite the input {out} (give another file)")


# ------------------------------------------------------------------------------------------------
# A folder of frames (detect DIR, navigate DIR): one process, one output folder
# ------------------------------------------------------------------------------------------------
def folder_images(folder: Path) -> tuple[list[Path], list[str]]:
    """(the folder's images by suffix, sorted; the names of its other entries but the images' georeferences,
    which are not read)."""
    try:
        entries = sorted(folder.iterdir())
    except OSError as exc:
        raise UserError(f"{folder}: cannot list the folder ({exc.strerror})") from None
    images = [p for p in entries if p.suffix.lower() in IMAGE_SUFFIXES]
    sidecars = {sidecar(p).name for p in images}
    others = [p.name for p in entries if p.suffix.lower() not in IMAGE_SUFFIXES and p.name not in sidecars]
    if not images:
        raise UserError(f"{folder} holds no image ({', '.join(IMAGE_SUFFIXES)})")
    return images, others


def error_text(path: Path, exc: BaseException) -> str:
    """One line naming ``path`` for an image's failure."""
    text = " ".join(str(exc).split())
    return text if str(path) in text or path.name in text else f"{path}: {text}"


def checked_out(folder: Path, out: Path, kind: str) -> OutFolder:
    """``out`` as this input folder's output folder of ``kind`` (``detections``; ``navigate``'s
    ``navigation``), to claim (``with``): new, empty, or written by an earlier run on the same folder; a
    folder of another kind or input, or holding any file no run of ours wrote (a user's, or one of ours
    edited since), is refused naming it, and nothing is written."""
    return OutFolder(out, kind, subject=str(folder.resolve())).check_clean()


def publish(f: OutFolder, files: dict[str, bytes]) -> None:
    """``files`` (name -> bytes) listed in the folder's marker, written atomically, then sealed."""
    f.record(files)
    for name, data in files.items():
        atomic_write_bytes(f.path / name, data)
    f.published()  # the marker now lists written files: a later failure must not remove it
    f.seal(files)


def close_folder_run(f: OutFolder, final: dict[str, bytes], written: Iterable[str], brief: dict) -> None:
    """End a folder run (``detect DIR``, ``navigate DIR``): publish its ``final`` files (table, summary), remove
    this writer's files the run no longer produced (``written`` and ``final`` are kept), print ``brief``."""
    publish(f, final)
    keep = set(written) | set(final)
    stale = [n for n in f.files if n not in keep]
    if stale:
        f.remove(stale)
    click.echo(json.dumps(brief))
