"""A user's frame on disk, as ``navigate`` and ``detect`` read it: the image (any file OpenImageIO reads, at
most :data:`train.realframes.MAX_FRAME_PIXELS`, read from its header before decoding), its georeference
sidecar ``IMAGE.geo.json`` (:class:`.georef.Georef`), and the checks of the options that describe a frame
(``--pixel-m``, ``--light-azimuth``) and of an output that would overwrite an input. Each failure is one
:class:`.georef.FrameError` (or :class:`UserError`) line naming the input."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Iterable

import numpy as np

from crater_synth.errors import UserError
from crater_synth.navigation.georef import FrameError, Georef, check_frame
from train.errors import RealSetError
from train.realframes import MAX_FRAME_PIXELS  # the largest frame read at once

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
