"""``crater-synth detect IMAGE|DIR``: the craters one of navigation's detectors finds in an image, or in every
image of a folder in one process (settings composed and the model loaded once).

The default detector is ``nav/detector=learned-detect`` (:data:`DEFAULT_DETECTOR`): the learned network at its
detection operating point, by far the most precise of the image detectors on the real windows (precision for
D >= 15 km against the LU1319381 catalogue, docs/results/navigation.json: south validation 0.929, against
template 0.450, classical 0.290, learned 0.204; north test 0.910, the others <= 0.36), at a low recall (0.38
on the north): few of the craters it reports are false. It needs no light direction.
``--detector classical|template|learned`` (or ``nav/detector=``) picks another; the filter detectors
estimate the light on each image unless ``--light-azimuth`` gives it, as ``navigate`` does
(:func:`.detectors.classical.detect`).

An image is read as ``navigate`` reads a map window (:mod:`.frame_file`): any file OpenImageIO reads, at most
8192 x 8192 px; 8- and 16-bit and float pixels alike (integers scaled by their full range); a colour image is
read as grey (the mean of R, G, B; an alpha channel is ignored) with a ``note:`` line naming it; a two-channel
or deeper image is refused, but for a rendered frame (an EXR of ``dataset`` or ``nav-frames``), whose I/F
channel is read. Its georeference is the ``IMAGE.geo.json`` sidecar (polar stereographic, as
``navigate``'s; D is the map diameter over the projection's scale factor at the crater), or else the map
georeference a GeoTIFF or ISIS cube carries (any lunar CRS, :class:`.frame_file.CrsGeoref`; D is the mean
great-circle length of the rim's two pixel-axis diameters); with it each crater gets latitude, longitude and
D in km. Without one, ``--pixel-m`` gives D in km.

Outputs (nothing is ever written beside the inputs): a single image prints one JSON line per crater, or with
``--out FILE.geojson|FILE.csv`` writes that file atomically (never an input) and prints a summary line; a
folder needs ``--out FOLDER``, claimed as a ``detections`` output folder (:class:`crater_synth.outfolder.OutFolder`:
marker, lock, only files it wrote), holding ``<image name>.craters.geojson`` per image, ``craters.csv`` (every
crater, one row each) and ``summary.json``. ``--png`` adds an annotated PNG beside each list. In a folder one
bad image is one ``error:`` line and an entry of the summary; the others go on, and the exit status is 1.
"""

from __future__ import annotations

import csv
import io
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import cv2
import numpy as np
import OpenImageIO as oiio

from crater_core.errors import ContractError
from crater_core.exr import read_channel
from crater_core.schema import EXR_CHANNELS, atomic_write_bytes, atomic_write_text
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.errors import UserError
from crater_synth.navigation.detectors import learned, registry
from crater_synth.navigation.detectors.classical import Detection, detect
from crater_synth.navigation.frame_file import (
    EXIT_SOME_FAILED,
    CrsGeoref,
    check_light_azimuth,
    check_pixel_m,
    check_pixels,
    checked_out,
    close_folder_run,
    error_text,
    file_georef,
    folder_images,
    publish,
    read_georef,
    read_window,
    refuse_overwrite,
    sidecar,
)
from crater_synth.navigation.georef import FrameError, Georef, check_frame, scale_factor, stereo_inverse
from crater_synth.navigation.settings import compose_nav, detector_options

# The most precise detector on the real north test windows (module docstring).
DEFAULT_DETECTOR = "learned-detect"
FORMATS = (".geojson", ".csv")
RENDER_CHANNEL = EXR_CHANNELS[0]  # a rendered frame's I/F
LIST_SUFFIX = ".craters.geojson"  # a folder run's list of one image: <image name> + this
PNG_SUFFIX = ".craters.png"
TABLE_NAME = "craters.csv"
SUMMARY_NAME = "summary.json"
COLUMNS = ("image", "u", "v", "a", "b", "angle_deg", "score", "lat", "lon", "d_km")


@dataclass(frozen=True)
class Detector:
    """The detector a run uses, composed once: its ``nav/detector`` option, settings and light (radians)."""

    name: str
    params: Any
    light: float | None


@dataclass
class Found:
    """One image's craters: the records written (:func:`crater_records`), what was read, and the time."""

    image: Path
    records: list[dict]
    pixels: np.ndarray | None  # dropped once drawn: a folder run keeps only the records
    georef: Georef | CrsGeoref | None
    light: float
    seconds: float
    note: str | None = None


def image_detectors() -> list[str]:
    """The ``nav/detector`` options that find craters in an image (the appearance search needs a map)."""
    return [o for o in detector_options() if o != "appearance"]


@click.command("detect")
@click.argument("source", metavar="IMAGE|DIR", type=click.Path(path_type=Path))
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    default=None,
    help="IMAGE: a .geojson or .csv file (default: one JSON line per crater on stdout); DIR: a folder (needed).",
)
@click.option("--pixel-m", type=float, default=None, help="Metres per pixel (default: from the georeference).")
@click.option("--png", is_flag=True, help="Also draw each image's craters into a PNG beside its list.")
@click.option(
    "--detector",
    "detector_name",
    type=click.Choice(image_detectors()),
    default=None,
    help=f"Detector (nav/detector=; default {DEFAULT_DETECTOR}, the most precise on the real test windows).",
)
@click.option(
    "--light-azimuth",
    type=float,
    default=None,
    help="Classical and template detectors, and a sun-aligned learned model (which needs it): the light travel "
    "direction in the image, degrees from +u (right) towards +v (down); default: estimated on each image.",
)
@OVERRIDES
@user_errors
def detect_command(source, out, pixel_m, png, detector_name, light_azimuth, overrides):
    """Find craters in an image, or in every image of a folder, with one of navigation's detectors.

    Writes each crater's ellipse in pixels (centre `u`, `v`, semi-axes `a`, `b`, `angle_deg`; the detectors
    give circles today, so a = b) and its score; where the image has a georeference (`IMAGE.geo.json`, or
    a GeoTIFF's or ISIS cube's own), latitude, longitude and D in km; with only `--pixel-m`, D. IMAGE: one
    JSON line per crater on stdout, or `--out FILE.geojson|FILE.csv`. DIR: `--out FOLDER` gets one GeoJSON
    per image, `craters.csv` and `summary.json`; a bad image is one error line, the others go on (exit
    status 1). Settings are `nav.detector.*` overrides (docs/navigation/settings.md), e.g.
    `nav.detector.model=FILE`.
    """
    check_pixel_m(pixel_m)
    check_light_azimuth(light_azimuth)
    if source.is_dir():
        check_folder_out(source, out)
        detector = load_detector(detector_name, overrides, light_azimuth)
        failed = detect_folder(source, out, detector, pixel_m, png)
        if failed:
            sys.exit(EXIT_SOME_FAILED)
        return
    if out is None and png:
        raise UserError(f"--png draws beside the output: give --out FILE.geojson|FILE.csv for {source}")
    detector = load_detector(detector_name, overrides, light_azimuth)
    if out is not None:
        check_file_out(source, out, png, detector)
    found = detect_image(source, detector, pixel_m)
    if out is None:
        for rec in found.records:
            click.echo(json.dumps(rec))
        return
    write_image_outputs(found, detector, out, png_path(out) if png else None)
    drawn = str(png_path(out)) if png else None
    click.echo(json.dumps(image_summary(found, detector) | {"out": str(out), "png": drawn}))


# ------------------------------------------------------------------------------------------------
# Settings and checks, before any image is read
# ------------------------------------------------------------------------------------------------
def load_detector(name: str | None, overrides, light_azimuth: float | None) -> Detector:
    """The detector's settings composed once (``--detector`` or ``nav/detector=``, default
    :data:`DEFAULT_DETECTOR`) and, for a trained one, its model loaded once (a corrupt file: one line)."""
    picked = [o for o in overrides if o.lstrip("+").startswith("nav/detector=")]
    if name is not None and picked:
        raise UserError(f"--detector {name} and {picked[0]}: give one of them")
    if any(o.lstrip("+~").startswith("nav/preset") for o in overrides):
        raise UserError("nav/preset: presets are for rendered frames; detect takes --detector or nav/detector=")
    nav = compose_nav(overrides, defaults=[f"nav/detector={name or DEFAULT_DETECTOR}"])
    option = nav.choices["detector"] or name or DEFAULT_DETECTOR
    entry = registry.detector(nav.detector.method)
    if entry.candidates is None:
        raise UserError(
            f"nav/detector={option} searches a landmark map under a position prior; detect takes one of "
            f"{', '.join(image_detectors())}"
        )
    registry.preload_model(nav.detector)
    aligned = nav.detector.method == "learned" and learned.model_sun_aligned(nav.detector)
    if light_azimuth is not None and not (entry.spectrum or nav.detector.refine or aligned):
        raise UserError(f"--light-azimuth: nav/detector={option} uses no light direction")
    if aligned and light_azimuth is None:
        raise UserError(f"{learned.model_path(nav.detector)} is sun-aligned: give the light with --light-azimuth")
    light = None if light_azimuth is None else math.radians(light_azimuth)
    return Detector(option, nav.detector, light)


def model_inputs(detector: Detector) -> list[Path]:
    """The detector's own input files (a trained detector's models and its verifier's), which no output may
    replace."""
    verifier = getattr(detector.params, "verifier", "")
    return registry.model_files(detector.params) + ([Path(verifier)] if verifier else [])


def png_path(out: Path) -> Path:
    """The annotated PNG written beside a single image's ``--out`` list."""
    return out.with_suffix(".png")


def check_file_out(image: Path, out: Path, png: bool, detector: Detector) -> None:
    """A single image's ``--out``: a .geojson or .csv file that is no input (nor is its PNG)."""
    if out.suffix.lower() not in FORMATS:
        raise UserError(f"--out {out}: give a {' or '.join(FORMATS)} file for the image {image}")
    if out.is_dir():
        raise UserError(f"--out {out} is a folder: give a {' or '.join(FORMATS)} file for the image {image}")
    outs = [out, *([png_path(out)] if png else [])]
    refuse_overwrite(outs, [image, sidecar(image), *model_inputs(detector)])


def check_folder_out(folder: Path, out: Path | None) -> None:
    """A folder's ``--out``: needed, a folder, and not the input folder (nothing is written beside inputs)."""
    if out is None:
        raise UserError(f"{folder} is a folder: give --out FOLDER for its crater lists (one file per image)")
    if out.suffix.lower() in FORMATS:
        raise UserError(f"--out {out}: the folder {folder} is written into an output folder, not one file")
    if out.resolve() == folder.resolve():
        raise UserError(f"--out {out} is the input folder: give another folder (nothing is written beside inputs)")


# ------------------------------------------------------------------------------------------------
# One image
# ------------------------------------------------------------------------------------------------
def read_image(path: Path) -> tuple[np.ndarray, Georef | CrsGeoref | None, str | None]:
    """(pixels, georeference or None, a ``note:`` or None) of one image. A rendered frame (an EXR with an
    :data:`RENDER_CHANNEL` channel: ``dataset``, ``nav-frames``) is its I/F; a colour image is read as grey
    with a note; a two-channel or deeper image is refused (its second channel is no colour). The header
    is probed first; a file it cannot open is left to the reader's own error."""
    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec() if inp is not None else None
    if inp is not None:
        inp.close()
    if spec is not None and RENDER_CHANNEL in spec.channelnames:
        check_pixels(path, spec.width, spec.height)
        return check_frame(read_channel(path, RENDER_CHANNEL), str(path)), read_georef(path), None
    n = spec.nchannels if spec is not None else 1
    if n == 2 or n > 4:
        raise FrameError(f"{path}: {n} channels; detect reads grey (1), RGB (3) or RGBA (4) images")
    note = f"{path}: {n} channels (RGB{'A' if n == 4 else ''}), read as grey: the mean of R, G, B" if n >= 3 else None
    img, georef = read_window(path)
    return img, georef or file_georef(path), note


def detect_image(path: Path, detector: Detector, pixel_m: float | None) -> Found:
    """The craters of one image (every check of :func:`.frame_file.read_window`, one error line each)."""
    t0 = time.perf_counter()
    if not path.is_file():
        raise FrameError(f"{path}: no such image file" if not path.exists() else f"{path}: not a file")
    img, georef, note = read_image(path)
    if isinstance(georef, CrsGeoref) and pixel_m is not None:
        raise FrameError(f"{path}: --pixel-m {pixel_m:g} given for an image whose own georeference gives its scale")
    if isinstance(georef, Georef) and pixel_m is not None and abs(pixel_m / georef.pixel_m - 1.0) > 1e-6:
        raise FrameError(
            f"{path}: --pixel-m {pixel_m:g} disagrees with its georeference {sidecar(path)} ({georef.pixel_m:g} m)"
        )
    dets, theta = detect(img, detector.params, light_dir=detector.light, what=str(path))
    if note:
        click.echo(f"note: {note}", err=True)
    records = crater_records(dets, georef, pixel_m)
    return Found(path, records, img, georef, theta, time.perf_counter() - t0, note)


def crater_records(dets: list[Detection], georef: Georef | CrsGeoref | None, pixel_m: float | None) -> list[dict]:
    """Per crater: ellipse (px: centre ``u``, ``v`` from the top-left corner, semi-axes ``a`` >= ``b``,
    ``angle_deg`` of ``a`` from +u towards +v) and ``score``; with ``georef`` ``lat``, ``lon`` (degrees) and
    ``d_km`` (the ground diameter: a sidecar's map distance over the polar stereographic scale factor; in a
    file's own CRS, the mean great-circle length of the rim's two pixel-axis diameters); with only
    ``pixel_m``, ``d_km``."""
    if not dets:
        return []
    u, v, r = (np.array([getattr(d, k) for d in dets]) for k in ("u", "v", "r"))
    out = [
        {"u": round(d.u, 2), "v": round(d.v, 2), "a": round(d.r, 2), "b": round(d.r, 2), "angle_deg": 0.0}
        | {"score": round(d.score, 4)}
        for d in dets
    ]
    if isinstance(georef, CrsGeoref):
        lat, lon = georef.latlon(u, v)
        d_km = 0.5 * (georef.ground_km(u - r, v, u + r, v) + georef.ground_km(u, v - r, u, v + r))
    elif georef is not None:
        lat, lon = stereo_inverse(*georef.uv_to_xy(u, v), georef.pole)
        d_km = 2.0 * r * georef.pixel_m / scale_factor(lat, georef.pole) / 1000.0
    if georef is not None:
        for rec, la, lo, dk in zip(out, np.atleast_1d(lat), np.atleast_1d(lon), d_km, strict=True):
            rec.update(lat=round(float(la), 6), lon=round(float(lo), 6), d_km=round(float(dk), 4))
    elif pixel_m is not None:
        for rec, rr in zip(out, r, strict=True):
            rec["d_km"] = round(2.0 * float(rr) * pixel_m / 1000.0, 4)
    return out


def image_summary(found: Found, detector: Detector) -> dict:
    """The one-line summary of one image's detection."""
    return {
        "image": str(found.image),
        "detector": detector.name,
        "craters": len(found.records),
        "georeferenced": found.georef is not None,
        "light_azimuth_deg": None if math.isnan(found.light) else round(math.degrees(found.light), 1),
        "seconds": round(found.seconds, 3),
    }


def geojson_text(found: Found, detector: Detector) -> str:
    """A FeatureCollection, one Point per crater at (lon, lat) (no geometry without a georeference), the
    crater's record as its properties; the image, detector and georeference under ``crater_synth``."""
    features = [
        {
            "type": "Feature",
            "geometry": {"type": "Point", "coordinates": [rec["lon"], rec["lat"]]} if "lat" in rec else None,
            "properties": rec,
        }
        for rec in found.records
    ]
    about = image_summary(found, detector) | {"georef": found.georef.as_dict() if found.georef else None}
    del about["seconds"]  # the file is the same whatever the machine's speed
    return json.dumps({"type": "FeatureCollection", "crater_synth": about, "features": features}, indent=1) + "\n"


def csv_text(found_all: list[Found]) -> str:
    """Every crater of ``found_all`` as one CSV row (:data:`COLUMNS`; empty where unknown)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for found in found_all:
        for rec in found.records:
            writer.writerow({"image": str(found.image.name)} | rec)
    return buf.getvalue()


def annotated_png(found: Found) -> bytes:
    """The image stretched to 8 bits (0.5-99.5 percentiles) with every crater's ellipse drawn in green."""
    a = found.pixels
    assert a is not None
    lo, hi = np.percentile(a, [0.5, 99.5])
    if hi <= lo:
        lo, hi = float(a.min()), float(a.max())
    grey = np.clip((a - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)
    canvas = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    width = max(1, round(min(a.shape) / 512))
    scale = 16  # cv2 draws sub-pixel positions with 4 fractional bits (shift=4)
    for rec in found.records:
        # detections' u, v are from the top-left pixel's corner; cv2's from its centre
        centre = (round((rec["u"] - 0.5) * scale), round((rec["v"] - 0.5) * scale))
        axes = (round(rec["a"] * scale), round(rec["b"] * scale))
        cv2.ellipse(canvas, centre, axes, rec["angle_deg"], 0, 360, (0, 220, 0), width, cv2.LINE_AA, shift=4)
    ok, data = cv2.imencode(".png", canvas)
    if not ok:
        raise UserError(f"{found.image}: the annotated PNG could not be encoded")
    return data.tobytes()


def write_image_outputs(found: Found, detector: Detector, out: Path, png: Path | None) -> None:
    """A single image's list (GeoJSON or CSV by ``out``'s suffix) and PNG, each written atomically."""
    text = csv_text([found]) if out.suffix.lower() == ".csv" else geojson_text(found, detector)
    drawn = annotated_png(found) if png is not None else None
    atomic_write_text(out, text)
    if png is not None and drawn is not None:
        atomic_write_bytes(png, drawn)


# ------------------------------------------------------------------------------------------------
# A folder
# ------------------------------------------------------------------------------------------------
def detect_folder(folder: Path, out: Path, detector: Detector, pixel_m: float | None, png: bool) -> list[dict]:
    """Every image of ``folder`` detected into the output folder ``out``; returns the failures (each also an
    ``error:`` line). Files of an earlier run into ``out`` that this run does not write again are removed."""
    images, others = folder_images(folder)
    done: list[Found] = []
    failed: list[dict] = []
    written: list[str] = []
    t0 = time.perf_counter()
    with checked_out(folder, out, "detections") as f:
        for path in images:
            try:
                found = detect_image(path, detector, pixel_m)
            except (UserError, ContractError, OSError) as exc:
                line = error_text(path, exc)
                click.echo(f"error: {line}", err=True)
                failed.append({"image": path.name, "error": line})
                continue
            names = {path.name + LIST_SUFFIX: geojson_text(found, detector).encode("utf-8")}
            if png:
                names[path.name + PNG_SUFFIX] = annotated_png(found)
            publish(f, names)
            written += names
            found.pixels = None
            done.append(found)
        summary = folder_summary(folder, out, detector, done, failed, others, time.perf_counter() - t0)
        final = {TABLE_NAME: csv_text(done).encode("utf-8"), SUMMARY_NAME: json.dumps(summary, indent=1).encode()}
        brief = {k: summary[k] for k in ("source", "out", "detector", "images", "craters")}
        close_folder_run(f, final, written, brief | {"failed": len(failed)})
    return failed


def folder_summary(folder, out, detector: Detector, done: list[Found], failed, others, seconds: float) -> dict:
    """``summary.json`` of a folder run: every image's craters, file and time, the failures, what was not read."""
    return {
        "source": str(folder),
        "out": str(out),
        "detector": detector.name,
        "images": len(done) + len(failed),
        "craters": sum(len(d.records) for d in done),
        "seconds": round(seconds, 3),
        "results": [
            image_summary(d, detector)
            | {"image": d.image.name, "list": d.image.name + LIST_SUFFIX}
            | ({"note": d.note} if d.note else {})
            for d in done
        ],
        "failed": failed,
        "not_images": others,
    }
