"""``crater-synth navigate IMAGE``: detections, identification, fix and an annotated PNG for one frame.

The frame is a north-up polar-stereographic nadir view (e.g. a mosaic window written by
:func:`write_window`). Its sidecar ``IMAGE.geo.json`` (pole, left_m, top_m, pixel_m) is the truth;
``--prior LAT,LON`` the coarse position (default: the truth centre moved by 5 km, as in ``nav-eval``).
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
from pathlib import Path

import click
import numpy as np

from crater_synth.cli_common import user_errors
from crater_synth.errors import UserError
from crater_synth.navigation.detect import detect, preset
from crater_synth.navigation.evaluate import prior_georef
from crater_synth.navigation.fix import FixParams, fix_frame
from crater_synth.navigation.frames import Frame, FrameError, Georef, ground_distance_km


# --------------------------------------------------------------------------------------------
# navigate IMAGE
# --------------------------------------------------------------------------------------------
def read_georef(image_path: Path) -> Georef | None:
    """The georeference of ``image_path``: its sidecar ``<image>.geo.json`` ({pole, left_m, top_m,
    pixel_m}), or None when it has none."""
    side = image_path.with_name(image_path.name + ".geo.json")
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


def write_window(path: Path, frame: Frame) -> None:
    """A frame as PNG plus its ``.geo.json`` sidecar (what ``navigate`` reads)."""
    from crater_core.schema import atomic_write_bytes, atomic_write_text

    atomic_write_bytes(path, _png_gray(frame.image))
    atomic_write_text(path.with_name(path.name + ".geo.json"), json.dumps(frame.georef.as_dict()) + "\n")


def _png_gray(img: np.ndarray) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    plt.imsave(buf, img, cmap="gray", vmin=0, vmax=255, format="png")
    return buf.getvalue()


def annotate(image, dets, landmarks, fix, prior: Georef | None, truth: Georef | None) -> bytes:
    """Annotated PNG: detections (red), identified landmarks with names (yellow), error arrow (cyan).
    ``prior`` (None for a lost-in-space fix) is not drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from crater_synth.navigation.nav_output import draw_detections, png_of
    from crater_synth.navigation.patches import PATCH_SOURCE

    h, w = image.shape
    fig, ax = plt.subplots(figsize=(8, 8))
    ax.imshow(image, cmap="gray")
    draw_detections(ax, dets, fix.inliers if fix.ok else [], landmarks)
    patch_fix = fix.ok and landmarks[fix.inliers[0][1]].source == PATCH_SOURCE
    what = "terrain patches (cyan)" if patch_fix else "landmarks"
    title = "no fix: " + fix.reason if not fix.ok else f"fix: {len(fix.inliers)} {what}, RMS {fix.rms_px:.1f} px"
    if fix.ok and truth is not None:
        tu, tv = truth.xy_to_uv(fix.x_m, fix.y_m)
        ax.annotate("", xy=(tu, tv), xytext=(w / 2, h / 2), arrowprops={"arrowstyle": "->", "color": "cyan", "lw": 2})
        err = float(ground_distance_km(fix.x_m, fix.y_m, *truth.uv_to_xy(w / 2, h / 2), truth.pole))
        title += f"; error {err:.2f} km (arrow: truth centre -> fix, x1)"
    return png_of(fig, ax, w, h, title)


@click.command("navigate")
@click.argument("image", type=click.Path(path_type=Path))
@click.option("--prior", default=None, metavar="LAT,LON", help="Coarse position of the frame centre (deg).")
@click.option("--pixel-m", type=float, default=None, help="Map metres per pixel (default: from the georeference).")
@click.option("--pole", type=click.Choice(["south", "north"]), default=None, help="Default: from the georeference.")
@click.option("--map", "map_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Landmark map.")
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Annotated PNG (default IMAGE.nav.png).",
)
@click.option(
    "--method",
    type=click.Choice(["classical", "template", "learned", "learned-detect", "appearance"]),
    default="template",
    show_default=True,
    help="Detection method (docs/navigation.md compares them); appearance: map landmarks searched for by their "
    "predicted appearance (a map window needs --light-azimuth).",
)
@click.option(
    "--model",
    "model_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Learned detector's model file (default: the committed south model; --method learned only).",
)
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
    help="--method appearance on a map window: the Sun's elevation in degrees (default: the preset's, chosen "
    "on the WAC mosaic's south windows).",
)
@click.option(
    "--lost-in-space",
    "--no-prior",
    "lost_in_space",
    is_flag=True,
    help="Identify with no position prior: crater-pair votes over the whole map (the frozen `south-choice` "
    "settings, docs/navigation.md 'Lost in space'); needs the pixel size, not the position.",
)
@click.option(
    "--known-heading",
    is_flag=True,
    help="With --lost-in-space: the frame is north-up on the map, so only crater-pair votes at that heading "
    "count (docs/navigation.md, 'Lost in space with the heading known').",
)
@click.option(
    "--patches/--no-patches",
    default=None,
    help="Appearance search (on by default): a frame its craters do not fix is navigated with terrain patches "
    "(rendered frames: docs/navigation.md section 9; map windows: section 6); --no-patches: craters only.",
)
@click.option(
    "--six-dof",
    is_flag=True,
    help="Rendered frames: the 6-DOF fix, attitude as well as position (nav-frames-eval --method pnp; refined by "
    "appearance with the appearance search; docs/navigation.md, section 9).",
)
@user_errors
def navigate_command(
    image,
    prior,
    pixel_m,
    pole,
    map_path,
    out,
    method,
    model_path,
    light_azimuth,
    sun_elevation,
    lost_in_space,
    known_heading,
    patches,
    six_dof,
):
    """Detect craters in a frame, identify them against the landmark map and fix the position.

    A map window is a north-up polar-stereographic nadir view (a mosaic window). Its georeference sidecar
    `IMAGE.geo.json` gives the truth (the error is printed and drawn); `--prior LAT,LON` the coarse
    position (default: the georeference centre moved by 5 km). `--method appearance` searches for the map's
    landmarks by their appearance predicted from the DEM under the Sun: give `--light-azimuth` (and
    `--sun-elevation`); with `--lost-in-space` the template's lost-in-space fix is its prior. A rendered
    frame (`frame_NNNN.exr` of `crater-synth nav-frames`) is navigated as `nav-frames-eval` does it: pose
    and Sun from its manifest, prior the true camera moved by 5 km, `--method appearance` (default),
    `classical` or `learned`; `--six-dof` fixes its attitude too. The appearance search lets terrain patches
    fix a frame or window its craters do not (`--no-patches`: craters only). Prints one JSON line.
    """
    if image.suffix.lower() == ".exr":  # a rendered frame of `crater-synth nav-frames`: its pose is in its manifest
        given = {
            "--prior": prior,
            "--pixel-m": pixel_m,
            "--pole": pole,
            "--map": map_path,
            "--model": model_path,
            "--light-azimuth": light_azimuth,
            "--sun-elevation": sun_elevation,
            "--lost-in-space": lost_in_space or None,
            "--known-heading": known_heading or None,
        }
        extra = [name for name, value in given.items() if value is not None]
        if extra:
            raise UserError(
                f"{image}: a rendered frame is navigated with its manifest's pose, Sun and landmark map; "
                f"{', '.join(extra)} apply to map windows only"
            )
        from click.core import ParameterSource

        from crater_synth.navigation.frames_presets import DEFAULT_FRAMES_PRESET
        from crater_synth.navigation.navigate_frame import navigate_frame

        chosen = click.get_current_context().get_parameter_source("method") != ParameterSource.DEFAULT
        # --method -> the nav-frames-eval preset it names for rendered frames.
        frame_presets = {"classical": "synthetic", "learned": "learned", "appearance": "appearance"}
        if chosen and method not in frame_presets:
            raise UserError(f"--method {method}: rendered frames have presets for {sorted(frame_presets)} only")
        name = frame_presets[method] if chosen else DEFAULT_FRAMES_PRESET
        if patches and name != "appearance":
            raise UserError(f"--patches needs the appearance search (--method appearance), not --method {method}")
        patches = name == "appearance" if patches is None else patches
        nav_png = out or image.with_name(image.stem + ".nav.png")
        click.echo(json.dumps(navigate_frame(image, name, nav_png, patches=patches, six_dof=six_dof)))
        return
    if six_dof:
        raise UserError(f"{image}: --six-dof applies to rendered frames (a map window's fix is a 2-D similarity)")
    if patches and method != "appearance":
        raise UserError(f"--patches needs the appearance search (--method appearance), not --method {method}")
    patches = method == "appearance" if patches is None else patches
    from crater_core.schema import atomic_write_bytes
    from crater_synth.navigation.landmarks import load_default_map, read_map
    from crater_synth.navigation.polar import stereo_forward, stereo_inverse
    from train.errors import RealSetError
    from train.realset import read_gray

    if method == "appearance" and light_azimuth is None:
        raise UserError(
            f"--method appearance on the map window {image} predicts each landmark under the Sun: give "
            "--light-azimuth (from the attitude and the ephemeris)"
        )
    if sun_elevation is not None and (method != "appearance" or not 0.0 < sun_elevation < 90.0):
        raise UserError(f"--sun-elevation {sun_elevation}: only with --method appearance, in (0, 90) degrees")
    try:
        img = read_gray(image)
    except RealSetError as exc:
        raise FrameError(str(exc)) from None
    from crater_synth.navigation.frames import check_frame

    check_frame(img, str(image))
    truth = read_georef(image)
    if known_heading and not lost_in_space:
        raise UserError("--known-heading applies to --lost-in-space only (a prior gives the heading already)")
    if lost_in_space and prior is not None:
        raise UserError(f"--prior {prior} with --lost-in-space: a lost-in-space fix takes no prior; give one of them")
    if truth is None and prior is None and not lost_in_space:
        raise FrameError(
            f"{image} has no georeference ({image.name}.geo.json) and neither --prior LAT,LON nor --lost-in-space "
            "was given"
        )
    pole = pole or (truth.pole if truth else "south")
    pixel = pixel_m or (truth.pixel_m if truth else None)
    if pixel is None:
        raise FrameError(f"{image}: no georeference, so --pixel-m is needed (400 for a WAC mosaic window)")
    landmarks, _ = read_map(map_path) if map_path else load_default_map(pole)
    h, w = img.shape[:2]
    prior_g: Georef | None = None
    if prior is not None:
        try:
            lat, lon = (float(p) for p in prior.split(","))
        except ValueError:
            raise UserError(f"--prior {prior!r}: expected LAT,LON in degrees") from None
        cx, cy = stereo_forward(lat, lon, pole)
        prior_g = Georef.centred_on(pole, cx, cy, img.shape, pixel)
    elif not lost_in_space:
        assert truth is not None
        fr = Frame(image.name, "user", -1, img, truth)
        prior_g = prior_georef(fr, 0)
    if prior_g is not None:
        xs = np.array([lm.x_m for lm in landmarks])
        ys = np.array([lm.y_m for lm in landmarks])
        u, v = prior_g.xy_to_uv(xs, ys)
        if not ((u > -w) & (u < 2 * w) & (v > -h) & (v < 2 * h)).any():
            lat0, lon0 = stereo_inverse(*prior_g.uv_to_xy(w / 2, h / 2), pole)
            raise FrameError(
                f"{image}: the frame at ({float(lat0):.2f}, {float(lon0):.2f}) lies outside the landmark map"
            )
    if model_path is not None and not method.startswith("learned"):
        raise UserError(f"--model {model_path}: only the learned detector (--method learned) takes a model file")
    dparams, fparams = preset(method, {"learned_model": str(model_path)} if model_path else None), FixParams()
    light = None if light_azimuth is None else math.radians(light_azimuth)

    def vote_fix(dets):
        from crater_synth.navigation.lost_in_space import LIS_PRESETS, lost_in_space_fix, window_heading_deg

        lis = dataclasses.replace(LIS_PRESETS["south-choice"], known_heading=known_heading)
        return lost_in_space_fix(dets, landmarks, img.shape, pixel, lis, fparams, heading_deg=window_heading_deg(lis))

    source = "craters"
    if method == "appearance":
        assert light is not None
        if prior_g is None:  # no prior: the first stage's lost-in-space fix is the search's prior (as nav-eval)
            from crater_synth.navigation.evaluate import LOST_IN_SPACE_FIRST_STAGE

            coarse = vote_fix(detect(img, preset(LOST_IN_SPACE_FIRST_STAGE), light_dir=light, what=str(image))[0])
            if coarse.ok:
                prior_g = Georef.centred_on(pole, coarse.x_m, coarse.y_m, img.shape, pixel)
        if prior_g is None:
            dets, theta, fix = [], light, dataclasses.replace(coarse, reason=f"lost in space: {coarse.reason}")
        else:
            dets, theta, fix, landmarks, source = _appearance_window(
                img, prior_g, landmarks, light, sun_elevation, dparams, fparams, patches
            )
    else:
        dets, theta = detect(img, dparams, light_dir=light, what=str(image))
        fix = vote_fix(dets) if prior_g is None else fix_frame(dets, landmarks, prior_g, img.shape, fparams)
    result = {
        "image": str(image),
        "method": method,
        "position_prior": "none (lost in space)" if lost_in_space else ("--prior" if prior else "truth + 5 km"),
        "detections": len(dets),
        "light_azimuth_deg": None if math.isnan(theta) else round(math.degrees(theta), 1),
        "fix": fix.ok,
    }
    if patches:
        result["fix_source"] = source if fix.ok else None
    if fix.ok:
        lat, lon = stereo_inverse(fix.x_m, fix.y_m, pole)
        result.update(
            lat=round(float(lat), 5),
            lon=round(float(lon), 5),
            landmarks=[landmarks[li].name or landmarks[li].id for _, li in fix.inliers],
        )
        if truth is not None:
            result["error_km"] = round(
                float(ground_distance_km(fix.x_m, fix.y_m, *truth.uv_to_xy(w / 2, h / 2), pole)), 3
            )
    else:
        result["reason"] = fix.reason
    out = out or image.with_name(image.stem + ".nav.png")
    listing = out.with_suffix(".json")
    from crater_synth.navigation.nav_output import detection_records, write_detections

    write_detections(listing, image, detection_records(dets, dict(fix.inliers) if fix.ok else {}, landmarks))
    atomic_write_bytes(out, annotate(img, dets, landmarks, fix, prior_g, truth))
    result.update(annotated=str(out), detections_file=str(listing))
    click.echo(json.dumps(result))


def _appearance_window(img, prior_g: Georef, landmarks, light: float, sun_elevation, dparams, fparams, patches):
    """(detections, light, fix, the landmarks the fix indexes, "craters" or "patches") of the appearance search
    (:mod:`.appearance_window`) on a map window: the light's image direction ``light`` (radians) turned into
    its local azimuth at the prior's frame centre; with ``patches``, a window its craters do not fix is
    navigated with its terrain patches (:func:`.appearance_window.window_patch_fix`)."""
    from crater_synth.navigation.appearance_window import lander_refiner, window_detections, window_patch_fix
    from crater_synth.navigation.polar import local_north_image_angle

    h, w = img.shape[:2]
    alpha = light - float(local_north_image_angle(*prior_g.uv_to_xy(w / 2, h / 2), prior_g.pole))
    if sun_elevation is not None:
        dparams = dataclasses.replace(dparams, appearance_sun_el_deg=(float(sun_elevation),))
    refiner = lander_refiner(prior_g.pole)
    dets, _ = window_detections(img, prior_g, landmarks, alpha, dparams, fparams, refiner)
    fix = fix_frame(dets, landmarks, prior_g, img.shape, fparams)
    if patches and not fix.ok:
        from crater_synth.navigation.patches import PatchParams

        found, patch_dets, patch_fix = window_patch_fix(img, prior_g, alpha, dparams, fparams, refiner, PatchParams())
        if patch_fix.ok:
            return patch_dets, light, patch_fix, found, "patches"
    return dets, light, fix, landmarks, "craters"
