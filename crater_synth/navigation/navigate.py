"""``crater-synth navigate IMAGE|DIR``: one frame navigated, a real map window (PNG with its georeference) or a
rendered frame (``nav-frames`` EXR), each through its own part (:mod:`.windows.navigate`,
:mod:`.rendered.navigate`); or every map window of a folder in one process, each by the single window's
:func:`navigate_one_window`. The one module that sees both parts.

A map window that is not north-up (``--heading DEG``: its up points DEG clockwise from the map's up) is
turned north-up about its centre before anything else (:func:`.windows.navigate.turned_north_up`): every
detector, the prior, the fix and the appearance search then work on a north-up frame as they do on a
mosaic window, with no second georeference model; the detections found in the filled corners are dropped,
and the listing gives the detections in the frame's own pixels.

Length: the command dispatches a single image and a folder, and the folder run is a loop over the single
window's path; a module of its own would sit above this one and take the command with it.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import sys
import time
from pathlib import Path

import click
import numpy as np

from crater_core.errors import ContractError
from crater_core.schema import atomic_write_bytes
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.errors import UserError
from crater_synth.navigation.detectors import registry
from crater_synth.navigation.detectors.classical import detect, with_new
from crater_synth.navigation.fix.lost_in_space import lost_in_space_fix, lost_in_space_search, window_heading_deg
from crater_synth.navigation.fix.solve import fix_frame
from crater_synth.navigation.frame_file import (
    EXIT_SOME_FAILED,
    check_light_azimuth,
    check_pixel_m,
    checked_out,
    close_folder_run,
    error_text,
    folder_images,
    publish,
    read_window,
    refuse_overwrite,
    sidecar,
)
from crater_synth.navigation.georef import (
    Frame,
    FrameError,
    Georef,
    ground_distance_km,
    stereo_forward,
    stereo_inverse,
)
from crater_synth.navigation.map.landmarks import load_default_map, read_map
from crater_synth.navigation.output import detection_records, detections_text, write_detections
from crater_synth.navigation.rendered.navigate import navigate_rendered_frame
from crater_synth.navigation.settings import DEFAULT_FRAMES_PRESET, compose_nav, verify_detector_settings
from crater_synth.navigation.windows.appearance import confirmed_fix
from crater_synth.navigation.windows.evaluate import LOST_IN_SPACE_FIRST_STAGE, appearance_settings, prior_georef
from crater_synth.navigation.windows.navigate import (
    annotate,
    appearance_window_fix,
    inside_frame,
    turned_back,
    turned_footprint,
    turned_north_up,
)

# A map window's detector unless an override names another (nav/detector=): of the detectors that need neither
# the DEM nor the light, the one with no false fix and the most fixes on the south validation windows.
WINDOW_DETECTOR = "template"


@dataclasses.dataclass(frozen=True)
class NavigateRequest:
    """What ``navigate`` is told of one frame besides the settings: the image, where to write, and what the
    lander knows of a map window (prior, pixel size, pole, map, light, Sun, heading)."""

    image: Path
    out: Path
    prior: str | None = None
    pixel_m: float | None = None
    pole: str | None = None
    map_path: Path | None = None
    light_azimuth: float | None = None
    sun_elevation: float | None = None
    lost_in_space: bool = False
    known_heading: bool = False
    patches: bool | None = None
    six_dof: bool = False
    heading: float | None = None


# A folder run's files (navigate DIR --out FOLDER): per image <image name> + these, and the summary.
LIST_SUFFIX = ".nav.json"
PNG_SUFFIX = ".nav.png"
SUMMARY_NAME = "summary.json"
FOLDER_KIND = "navigation"  # crater_synth.outfolder.MARKERS


@click.command("navigate")
@click.argument("image", metavar="IMAGE|DIR", type=click.Path(path_type=Path))
@click.option("--prior", default=None, metavar="LAT,LON", help="Coarse position of the frame centre (deg).")
@click.option("--pixel-m", type=float, default=None, help="Map metres per pixel (default: from the georeference).")
@click.option("--pole", type=click.Choice(["south", "north"]), default=None, help="Default: from the georeference.")
@click.option("--map", "map_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Landmark map.")
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    default=None,
    help="IMAGE: the annotated PNG (default IMAGE.nav.png); DIR: the output folder (needed).",
)
@click.option("--png", is_flag=True, help="DIR: also draw each image's annotated PNG (slow; one image always has it).")
@click.option(
    "--light-azimuth",
    type=float,
    default=None,
    help="Light travel direction in the image, degrees from +u (right) towards +v (down), e.g. from the "
    "attitude and the ephemeris; default: estimated on the frame.",
)
@click.option(
    "--sun-elevation",
    type=float,
    default=None,
    help="nav/detector=appearance on a map window: the Sun's elevation in degrees (default: the settings', "
    "chosen on the WAC mosaic's south windows).",
)
@click.option(
    "--lost-in-space",
    "--no-prior",
    "lost_in_space",
    is_flag=True,
    help="Identify with no position prior: crater-pair votes over the whole map (nav/lost_in_space, "
    "docs/navigation/fix.md); needs the pixel size, not the position.",
)
@click.option(
    "--known-heading",
    is_flag=True,
    help="With --lost-in-space: the frame is north-up on the map, so only crater-pair votes at that heading "
    "count (docs/navigation/fix.md).",
)
@click.option(
    "--patches/--no-patches",
    default=None,
    help="Appearance search (on by default): a frame its craters do not fix is navigated with terrain patches "
    "(rendered frames: docs/navigation/rendered.md; map windows: section 6); --no-patches: craters only.",
)
@click.option(
    "--heading",
    type=float,
    default=None,
    metavar="DEG",
    help="A map window that is not north-up: the direction its up points on the map, degrees clockwise from "
    "the map's up (0: north-up); the frame is turned north-up before detection.",
)
@click.option(
    "--six-dof",
    is_flag=True,
    help="Rendered frames: the 6-DOF fix, attitude as well as position (nav-frames-eval nav.frames.solver=pnp; "
    "refined by appearance with the appearance search; docs/navigation/rendered.md).",
)
@OVERRIDES
@user_errors
def navigate_command(image, out, overrides, **options):
    """Detect craters in a frame, identify them against the landmark map and fix the position.

    A map window is a north-up polar-stereographic nadir view (a mosaic window). Its georeference sidecar
    `IMAGE.geo.json` gives the truth (the error is printed and drawn); `--prior LAT,LON` the coarse
    position (default: the georeference centre moved by 5 km). Its detector is `nav/detector=template`
    unless an override names another (classical, learned, learned-detect; `nav.detector.model=FILE` for the
    learned one); `nav/detector=appearance` searches for the map's landmarks by their appearance predicted
    from the DEM under the Sun: give `--light-azimuth` (and `--sun-elevation`); with `--lost-in-space` the
    template's lost-in-space fix is its prior. A rendered frame (`frame_NNNN.exr` of `crater-synth
    nav-frames`) is navigated as `nav-frames-eval` does it: pose and Sun from its manifest, prior the true
    camera moved by 5 km, `nav/preset=appearance` (default), `synthetic` or `learned`; `--six-dof` fixes its
    attitude too. The appearance search lets terrain patches fix a frame or window its craters do not
    (`--no-patches`: craters only). `--heading DEG`: a map window whose up points DEG clockwise from the
    map's up, turned north-up first. Settings are Hydra overrides (docs/navigation/settings.md). Prints one
    JSON line.

    DIR: every map window of the folder in one process into `--out FOLDER` (`<image>.nav.json` each, the
    single image's detection list; `--png`: `<image>.nav.png`; `summary.json`), one JSON line per window; a
    bad window is one error line, the others go on (exit status 1).
    """
    png = options.pop("png")
    if image.is_dir():
        failed = navigate_folder(NavigateRequest(image=image, out=out, **options), overrides, png)
        if failed:
            sys.exit(EXIT_SOME_FAILED)
        return
    if png:
        raise UserError(f"--png draws each image of a folder; the image {image} always gets its annotated PNG")
    if out is not None and out.is_dir():
        raise UserError(f"--out {out} is a folder: give the annotated PNG's file for the image {image}")
    request = NavigateRequest(image=image, out=out or image.with_name(image.stem + ".nav.png"), **options)
    if image.suffix.lower() == ".exr":  # a rendered frame of `crater-synth nav-frames`: its pose is in its manifest
        result = navigate_rendered_image(request, overrides)
    else:
        result = navigate_map_window(request, overrides)
    click.echo(json.dumps(result))


def navigate_rendered_image(request: NavigateRequest, overrides) -> dict:
    """A rendered frame navigated with a ``nav/preset`` (default :data:`.settings.DEFAULT_FRAMES_PRESET`);
    the options that describe a map window are refused."""
    given = {
        "--prior": request.prior,
        "--pixel-m": request.pixel_m,
        "--pole": request.pole,
        "--map": request.map_path,
        "--light-azimuth": request.light_azimuth,
        "--sun-elevation": request.sun_elevation,
        "--lost-in-space": request.lost_in_space or None,
        "--known-heading": request.known_heading or None,
        "--heading": request.heading,
    }
    extra = [name for name, value in given.items() if value is not None]
    if extra:
        raise UserError(
            f"{request.image}: a rendered frame is navigated with its manifest's pose, Sun and landmark map; "
            f"{', '.join(extra)} apply to map windows only"
        )
    nav = compose_nav(overrides, defaults=[f"nav/preset={DEFAULT_FRAMES_PRESET}"])
    if request.patches and not nav.appearance:
        preset = nav.preset or nav.choices["detector"]
        raise UserError(f"--patches needs the appearance search (nav/preset=appearance), not {preset}")
    patches = nav.appearance if request.patches is None else request.patches
    return navigate_rendered_frame(request.image, nav, request.out, patches=patches, six_dof=request.six_dof)


def check_window_request(request: NavigateRequest, nav) -> None:
    """The options of a map window that contradict each other or the settings: one error line each."""
    option = nav.choices["detector"]
    if nav.preset is not None:
        raise UserError(f"nav/preset={nav.preset}: presets are for rendered frames; a map window takes nav/detector=")
    if request.six_dof:
        raise UserError(
            f"{request.image}: --six-dof applies to rendered frames (a map window's fix is a 2-D similarity)"
        )
    if request.patches and not nav.appearance:
        raise UserError(f"--patches needs the appearance search (nav/detector=appearance), not nav/detector={option}")
    if request.lost_in_space and nav.appearance and nav.lost_in_space.confirm:
        raise UserError(
            "nav/detector=appearance lost in space starts the search from the template's vote; "
            "nav.lost_in_space.confirm=appearance confirms a crater detector's places: give one of them"
        )
    # lost in space confirmed by appearance searches like nav/detector=appearance
    searched = "nav/detector=appearance" if nav.appearance else ""
    if request.lost_in_space and nav.lost_in_space.confirm:
        searched = searched or "nav.lost_in_space.confirm=appearance"
    if searched and request.light_azimuth is None:
        raise UserError(
            f"{searched} on the map window {request.image} predicts each landmark under the Sun: give "
            "--light-azimuth (from the attitude and the ephemeris)"
        )
    elevation = request.sun_elevation
    if elevation is not None and (not searched or not 0.0 < elevation < 90.0):
        raise UserError(
            f"--sun-elevation {elevation}: only with nav/detector=appearance or lost in space confirmed by "
            "appearance, in (0, 90) degrees"
        )
    if request.known_heading and not request.lost_in_space:
        raise UserError("--known-heading applies to --lost-in-space only (a prior gives the heading already)")
    if request.lost_in_space and request.prior is not None:
        raise UserError(
            f"--prior {request.prior} with --lost-in-space: a lost-in-space fix takes no prior; give one of them"
        )


def parse_prior(text: str, pole: str) -> tuple[float, float]:
    """(lat, lon) of ``--prior LAT,LON``: finite degrees, latitude within +-90 and on ``pole``'s side."""
    try:
        lat, lon = (float(p) for p in text.split(","))
    except ValueError:
        raise UserError(f"--prior {text!r}: expected LAT,LON in degrees") from None
    if not (math.isfinite(lat) and math.isfinite(lon) and abs(lat) <= 90.0):
        raise UserError(f"--prior {text!r}: latitude must be within +-90 degrees and both finite")
    if (lat < 0.0) != (pole == "south"):
        raise UserError(f"--prior {text!r}: latitude {lat:g} is not on the {pole} pole's side (the frame's pole)")
    return lat, lon


def check_window_values(request: NavigateRequest) -> None:
    """The numbers and paths of a map window's options: one error line each, before any work."""
    check_pixel_m(request.pixel_m)
    check_light_azimuth(request.light_azimuth)
    check_heading(request.heading)
    inputs = [request.image, sidecar(request.image), *([request.map_path] if request.map_path else [])]
    refuse_overwrite((request.out, request.out.with_suffix(".json")), inputs)


def check_heading(heading: float | None) -> None:
    """``--heading``: None, or finite degrees (one error line)."""
    if heading is not None and not math.isfinite(heading):
        raise UserError(f"--heading {heading}: degrees clockwise from the map's up, finite")


def window_prior(request: NavigateRequest, img, truth, landmarks, pole: str, pixel: float) -> Georef | None:
    """The prior georeference of a map window: ``--prior``, else the truth moved by 5 km, else None (lost in
    space); a prior whose frame holds no landmark of the map is refused."""
    h, w = img.shape[:2]
    prior_g: Georef | None = None
    if request.prior is not None:
        lat, lon = parse_prior(request.prior, pole)
        prior_g = Georef.centred_on(pole, *stereo_forward(lat, lon, pole), img.shape, pixel)
    elif not request.lost_in_space:
        assert truth is not None
        prior_g = prior_georef(Frame(request.image.name, "user", -1, img, truth), 0)
    if prior_g is not None:
        u, v = prior_g.xy_to_uv(np.array([lm.x_m for lm in landmarks]), np.array([lm.y_m for lm in landmarks]))
        if not ((u > -w) & (u < 2 * w) & (v > -h) & (v < 2 * h)).any():
            lat0, lon0 = stereo_inverse(*prior_g.uv_to_xy(w / 2, h / 2), pole)
            raise FrameError(
                f"{request.image}: the frame at ({float(lat0):.2f}, {float(lon0):.2f}) lies outside the landmark map"
            )
    return prior_g


def lost_in_space_settings(request: NavigateRequest, nav):
    """``nav.lost_in_space`` with the heading known when ``--known-heading`` says so, or the settings do."""
    return dataclasses.replace(
        nav.lost_in_space, known_heading=request.known_heading or nav.lost_in_space.known_heading
    )


def window_fix(
    request: NavigateRequest, nav, img, prior_g: Georef | None, landmarks, pixel: float, keep=None, footprint=None
):
    """(detections, light, fix, the landmarks the fix indexes, "craters" or "patches") of a map window: its
    detector's craters fixed under the prior or by the lost-in-space vote; the appearance search under the
    prior, or under the first stage's lost-in-space fix without one (as nav-eval). ``keep`` (a frame
    turned north-up: :func:`.windows.navigate.inside_frame`) drops the detections outside the frame."""
    light = None if request.light_azimuth is None else math.radians(request.light_azimuth)
    lis = lost_in_space_settings(request, nav)
    extra: list = []  # the verify detector's craters: they join the lost-in-space verification, never the vote
    vparams = verify_detector_settings(lis.verify_detector) if prior_g is None else None
    if vparams is not None:
        found = detect(img, vparams, light_dir=light, what=str(request.image))[0]
        extra = found if keep is None else keep(found, vparams.border_r)

    def with_extra(dets):  # the verify detector's craters these lack, after them (the fix's inliers index both)
        return with_new(dets, extra, vparams)

    def vote_fix(dets):
        heading = window_heading_deg(lis)
        return lost_in_space_fix(
            with_extra(dets), landmarks, img.shape, pixel, lis, nav.fix, heading_deg=heading, voters=len(dets)
        )

    patches = nav.appearance if request.patches is None else request.patches
    if prior_g is None and lis.confirm and not nav.appearance:
        return confirmed_window_fix(request, nav, img, landmarks, pixel, lis, light, (keep, footprint), with_extra)
    if not nav.appearance:

        def fit(dets):
            return vote_fix(dets) if prior_g is None else fix_frame(dets, landmarks, prior_g, img.shape, nav.fix)

        dets, theta, fix = either_light_fix(img, nav.detector, light, fit, str(request.image), keep)
        if prior_g is None:
            dets = with_extra(dets)
        return dets, theta, fix, landmarks, "craters"
    assert light is not None
    if prior_g is None:
        first = compose_nav([f"nav/detector={LOST_IN_SPACE_FIRST_STAGE}"]).detector
        found = detect(img, first, light_dir=light, what=str(request.image))[0]
        coarse = vote_fix(found if keep is None else keep(found, first.border_r))
        if not coarse.ok:
            return (
                [],
                light,
                dataclasses.replace(coarse, reason=f"lost in space: {coarse.reason}"),
                landmarks,
                "craters",
            )
        prior_g = Georef.centred_on(request.pole, coarse.x_m, coarse.y_m, img.shape, pixel)
    args = (request.sun_elevation, nav.detector, nav.fix, patches)
    return appearance_window_fix(img, prior_g, landmarks, light, *args)


def confirmed_window_fix(request: NavigateRequest, nav, img, landmarks, pixel: float, lis, light, turned, with_extra):
    """:func:`window_fix` lost in space with ``nav.lost_in_space.confirm="appearance"``: the detector's craters
    vote, and the appearance search confirms one of the vote's places (:func:`.appearance.confirmed_fix`) under
    the light's image direction ``light`` (radians; ``--light-azimuth``, which the ephemeris and the attitude
    give), north-up (``turned``: (``keep``, ``footprint``) of a frame turned north-up, else Nones), with the
    pole's DEM."""
    assert light is not None  # check_window_request asks for --light-azimuth
    keep, footprint = turned
    found = detect(img, nav.detector, light_dir=light, what=str(request.image))[0]
    found = found if keep is None else keep(found, nav.detector.border_r)
    dets = with_extra(found)
    heading = window_heading_deg(lis)
    _, cands = lost_in_space_search(dets, landmarks, img.shape, pixel, lis, nav.fix, None, heading, len(found))
    app = appearance_settings()
    if request.sun_elevation is not None:
        app = dataclasses.replace(app, sun_el_deg=(float(request.sun_elevation),))
    confirmed, fix = confirmed_fix(img, request.pole, pixel, cands, landmarks, light, lis, app, nav.fix, footprint)
    return (confirmed if fix.ok else dets), light, fix, landmarks, "craters"


# A frame's light estimate can read 180 degrees wrong (a crater's lit wall and its shadow swap); the detector
# then shifts every centre against the light and the fix can still find 6-7 landmarks at ~2 px, 3-4 km off.
# Run with the opposite light too, and of two fixes further apart than LIGHT_AGREEMENT_KM keep the one with at
# least LIGHT_SUPPORT_RATIO times the other's landmarks; closer support is no fix. On 240 off-grid south
# validation windows the right fix had 1.5-3 x the wrong one's landmarks in all 75 frames both lights fixed
# (docs/history.md). A fix found only with the opposite light is not taken: 1 of those 15 was false.
LIGHT_AGREEMENT_KM = 1.0  # two fixes of one place agree to their own error (median 0.4-0.5 km there)
LIGHT_SUPPORT_RATIO = 1.4


def either_light_fix(img, dparams, light: float | None, fit, what: str, keep=None):
    """(detections, light azimuth, fix) of a frame's craters. With the light given, its fix. With the light
    estimated on the frame, the detector and the fix run with the opposite light too; of two disagreeing
    fixes the one with clearly more landmarks is kept, and neither when their support is close (the reason
    says to give ``--light-azimuth``). ``keep(detections, border_r)``: the detections kept (all: None)."""

    def found(light_dir):
        dets, theta = detect(img, dparams, light_dir=light_dir, what=what)
        return (dets if keep is None else keep(dets, dparams.border_r)), theta

    dets, theta = found(light)
    fix = fit(dets)
    if light is not None or math.isnan(theta) or not fix.ok:
        return dets, theta, fix
    flipped = (theta + math.pi) % (2.0 * math.pi)
    dets_f, _ = found(flipped)
    fix_f = fit(dets_f)
    if not fix_f.ok:
        return dets, theta, fix
    apart_km = math.hypot(fix.x_m - fix_f.x_m, fix.y_m - fix_f.y_m) / 1000.0
    if apart_km <= LIGHT_AGREEMENT_KM:
        return dets, theta, fix
    n, n_f = len(fix.inliers), len(fix_f.inliers)
    if n >= LIGHT_SUPPORT_RATIO * n_f:
        return dets, theta, fix
    if n_f >= LIGHT_SUPPORT_RATIO * n:
        return dets_f, flipped, fix_f
    reason = (
        f"the light estimated on the frame ({math.degrees(theta):.0f} deg, {n} landmarks) and its opposite "
        f"({n_f} landmarks) fix it {apart_km:.1f} km apart: give --light-azimuth"
    )
    return dets, theta, dataclasses.replace(fix, ok=False, reason=reason)


def window_result(request: NavigateRequest, nav, dets, theta: float, fix, landmarks, source: str) -> dict:
    """The JSON line of a map window's navigation."""
    prior = "--prior" if request.prior else "truth + 5 km"
    light = math.degrees(theta)
    if request.heading is not None:  # the light in the frame as given, not on the canvas turned north-up
        light = (light - request.heading) % 360.0
    result = {
        "image": str(request.image),
        "method": nav.choices["detector"],
        "position_prior": "none (lost in space)" if request.lost_in_space else prior,
        "detections": len(dets),
        "light_azimuth_deg": None if math.isnan(theta) else round(light, 1),
        "fix": fix.ok,
    }
    if request.heading is not None:
        result["heading_deg"] = request.heading
    if nav.appearance if request.patches is None else request.patches:
        result["fix_source"] = source if fix.ok else None
    if not fix.ok:
        result["reason"] = fix.reason
        return result
    lat, lon = stereo_inverse(fix.x_m, fix.y_m, request.pole)
    result.update(
        lat=round(float(lat), 5),
        lon=round(float(lon), 5),
        landmarks=[landmarks[li].name or landmarks[li].id for _, li in fix.inliers],
    )
    return result


@dataclasses.dataclass
class WindowNavigation:
    """One map window navigated: its JSON line, its detection listing (pixels of the image as given) and what
    :func:`.windows.navigate.annotate` draws (the frame north-up)."""

    result: dict
    records: list[dict]
    drawing: tuple


def window_settings(request: NavigateRequest, overrides):
    """The navigation settings of map windows (default detector :data:`WINDOW_DETECTOR`), composed once and
    checked against the request's options."""
    nav = compose_nav(overrides, defaults=[f"nav/detector={WINDOW_DETECTOR}"])
    check_window_request(request, nav)
    return nav


def window_map(request: NavigateRequest, pole: str, maps: dict):
    """The landmark map of ``pole`` (``--map`` or the committed one), read once per run into ``maps``."""
    if pole not in maps:
        maps[pole] = read_map(request.map_path) if request.map_path else load_default_map(pole)
    landmarks, provenance = maps[pole]
    if provenance.get("pole", pole) != pole:
        raise UserError(f"--map {request.map_path}: a map of the {provenance['pole']} pole for a {pole}-pole frame")
    return landmarks


def navigate_one_window(request: NavigateRequest, nav, maps: dict) -> WindowNavigation:
    """One map window navigated with the settings ``nav`` (:func:`window_settings`) and the maps read so far:
    the single image's path and each image of a folder run alike; writes nothing."""
    img, truth = read_window(request.image)
    if truth is None and request.prior is None and not request.lost_in_space:
        raise FrameError(
            f"{request.image} has no georeference ({request.image.name}.geo.json) and neither --prior LAT,LON nor "
            "--lost-in-space was given"
        )
    pole = request.pole or (truth.pole if truth else "south")
    pixel = request.pixel_m or (truth.pixel_m if truth else None)
    if pixel is None:
        raise FrameError(f"{request.image}: no georeference, so --pixel-m is needed (400 for a WAC mosaic window)")
    request = dataclasses.replace(request, pole=pole)
    landmarks = window_map(request, pole, maps)
    turn = keep = footprint = None
    if request.heading is not None:
        shape = img.shape
        img, truth, turn = turned_north_up(img, truth, request.heading)
        keep = functools.partial(inside_frame, turn=turn, shape=shape)
        footprint = turned_footprint(turn, shape, img.shape)
        if request.light_azimuth is not None:
            request = dataclasses.replace(request, light_azimuth=request.light_azimuth + request.heading)
    prior_g = window_prior(request, img, truth, landmarks, pole, pixel)
    dets, theta, fix, landmarks, source = window_fix(request, nav, img, prior_g, landmarks, pixel, keep, footprint)
    result = window_result(request, nav, dets, theta, fix, landmarks, source)
    if fix.ok and truth is not None:
        h, w = img.shape[:2]
        error = ground_distance_km(fix.x_m, fix.y_m, *truth.uv_to_xy(w / 2, h / 2), pole)
        result["error_km"] = round(float(error), 3)
    given = dets if turn is None else turned_back(dets, turn)
    records = detection_records(given, dict(fix.inliers) if fix.ok else {}, landmarks)
    return WindowNavigation(result, records, (img, dets, landmarks, fix, prior_g, truth))


def navigate_map_window(request: NavigateRequest, overrides) -> dict:
    """A map window navigated (:func:`navigate_one_window`); writes the annotated PNG and the detections listing
    beside it."""
    nav = window_settings(request, overrides)
    check_window_values(request)
    done = navigate_one_window(request, nav, {})
    listing = request.out.with_suffix(".json")
    write_detections(listing, request.image, done.records)
    atomic_write_bytes(request.out, annotate(*done.drawing))
    return done.result | {"annotated": str(request.out), "detections_file": str(listing)}


# ------------------------------------------------------------------------------------------------
# A folder of map windows in one process
# ------------------------------------------------------------------------------------------------
def check_folder_request(request: NavigateRequest) -> None:
    """The options of ``navigate DIR``: ``--out FOLDER`` (not the input), no ``--prior`` (each window's own
    georeference or ``--lost-in-space``) and no rendered frame's option; one line each, before any work."""
    folder, out = request.image, request.out
    if out is None:
        raise UserError(f"{folder} is a folder: give --out FOLDER for its results (one file per image)")
    if out.suffix.lower() in (".json", ".png"):
        raise UserError(f"--out {out}: the folder {folder} is navigated into an output folder, not one file")
    if out.resolve() == folder.resolve():
        raise UserError(f"--out {out} is the input folder: give another folder (nothing is written beside inputs)")
    if request.prior is not None:
        raise UserError(
            f"--prior {request.prior} with the folder {folder}: one prior cannot place every window; each is "
            "navigated under its own georeference (truth + 5 km), or give --lost-in-space"
        )
    check_pixel_m(request.pixel_m)
    check_light_azimuth(request.light_azimuth)
    check_heading(request.heading)


def navigate_folder(request: NavigateRequest, overrides, png: bool) -> list[dict]:
    """Every map window of the folder ``request.image`` navigated in this one process (settings, maps and
    model loaded once; each window by :func:`navigate_one_window`, as a single image) into the ``navigation``
    output folder ``request.out``: ``<image name>.nav.json`` (the single image's detection list), with
    ``png`` ``<image name>.nav.png``, and ``summary.json``. One JSON line per window; a bad window is one
    ``error:`` line and a failure of the summary, and the others go on. Returns the failures."""
    check_folder_request(request)
    folder, out = request.image, request.out
    images, others = folder_images(folder)
    rendered = [p.name for p in images if p.suffix.lower() == ".exr"]
    if rendered:
        raise UserError(
            f"{folder} holds rendered frames ({rendered[0]}): navigate each one alone (navigate FRAME.exr) or "
            "the folder with nav-frames-eval; a folder run takes map windows"
        )
    nav = window_settings(request, overrides)
    registry.preload_model(nav.detector)  # a corrupt model: one line, before any window
    maps: dict = {}
    results: list[dict] = []
    failed: list[dict] = []
    t0 = time.perf_counter()
    with checked_out(folder, out, FOLDER_KIND) as f:
        for path in images:
            t = time.perf_counter()
            try:
                done = navigate_one_window(dataclasses.replace(request, image=path), nav, maps)
            except (UserError, ContractError, OSError) as exc:
                line = error_text(path, exc)
                click.echo(f"error: {line}", err=True)
                failed.append({"image": path.name, "error": line})
                continue
            names = {path.name + LIST_SUFFIX: detections_text(path, done.records).encode("utf-8")}
            if png:
                names[path.name + PNG_SUFFIX] = annotate(*done.drawing)
            publish(f, names)
            result = done.result | {"list": path.name + LIST_SUFFIX, "png": path.name + PNG_SUFFIX if png else None}
            results.append(result | {"seconds": round(time.perf_counter() - t, 3)})
            click.echo(json.dumps(result))
        summary = navigation_summary(request, nav, results, failed, others, time.perf_counter() - t0)
        written = [*(r["list"] for r in results), *(r["png"] for r in results if r["png"])]
        brief = {k: summary[k] for k in ("source", "out", "method", "images", "fixes")}
        final = {SUMMARY_NAME: (json.dumps(summary, indent=1) + "\n").encode("utf-8")}
        close_folder_run(f, final, written, brief | {"failed": len(failed)})
    return failed


def navigation_summary(request: NavigateRequest, nav, results: list[dict], failed, others, seconds: float) -> dict:
    """``summary.json`` of a folder run: every window's result line (fix, position, error or the reason of no
    fix) and time, the failures, the entries not read."""
    return {
        "source": str(request.image),
        "out": str(request.out),
        "method": nav.choices["detector"],
        "heading_deg": request.heading,
        "images": len(results) + len(failed),
        "fixes": sum(bool(r["fix"]) for r in results),
        "seconds": round(seconds, 3),
        "results": results,
        "failed": failed,
        "not_images": others,
    }
