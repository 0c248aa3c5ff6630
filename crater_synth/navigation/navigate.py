"""``crater-synth navigate IMAGE``: one frame navigated, a real map window (PNG with its georeference) or a
rendered frame (``nav-frames`` EXR), each through its own part (:mod:`.windows.navigate`,
:mod:`.rendered.navigate`). The one module that sees both parts."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import click
import numpy as np

from crater_synth.cli_common import user_errors
from crater_synth.errors import UserError
from crater_synth.navigation.detectors.classical import detect, preset
from crater_synth.navigation.fix.solve import FixParams, fix_frame
from crater_synth.navigation.georef import Frame, FrameError, Georef, ground_distance_km
from crater_synth.navigation.windows.evaluate import prior_georef
from crater_synth.navigation.windows.navigate import annotate, appearance_window_fix, read_georef


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
    help="Detection method (docs/navigation/detectors.md compares them); appearance: map landmarks searched for by "
    "their predicted appearance (a map window needs --light-azimuth).",
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
    "settings, docs/navigation/fix.md); needs the pixel size, not the position.",
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
    "(rendered frames: docs/navigation/rendered.md; map windows: docs/navigation/fix.md); --no-patches: craters only.",
)
@click.option(
    "--six-dof",
    is_flag=True,
    help="Rendered frames: the 6-DOF fix, attitude as well as position (nav-frames-eval --method pnp; refined by "
    "appearance with the appearance search; docs/navigation/rendered.md).",
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

        from crater_synth.navigation.rendered.navigate import navigate_rendered_frame
        from crater_synth.navigation.settings import DEFAULT_FRAMES_PRESET

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
        click.echo(json.dumps(navigate_rendered_frame(image, name, nav_png, patches=patches, six_dof=six_dof)))
        return
    if six_dof:
        raise UserError(f"{image}: --six-dof applies to rendered frames (a map window's fix is a 2-D similarity)")
    if patches and method != "appearance":
        raise UserError(f"--patches needs the appearance search (--method appearance), not --method {method}")
    patches = method == "appearance" if patches is None else patches
    from crater_core.schema import atomic_write_bytes
    from crater_synth.navigation.georef import stereo_forward, stereo_inverse
    from crater_synth.navigation.map.landmarks import load_default_map, read_map
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
    from crater_synth.navigation.georef import check_frame

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
        from crater_synth.navigation.fix.lost_in_space import LIS_PRESETS, lost_in_space_fix, window_heading_deg

        lis = dataclasses.replace(LIS_PRESETS["south-choice"], known_heading=known_heading)
        return lost_in_space_fix(dets, landmarks, img.shape, pixel, lis, fparams, heading_deg=window_heading_deg(lis))

    source = "craters"
    if method == "appearance":
        assert light is not None
        if prior_g is None:  # no prior: the first stage's lost-in-space fix is the search's prior (as nav-eval)
            from crater_synth.navigation.windows.evaluate import LOST_IN_SPACE_FIRST_STAGE

            coarse = vote_fix(detect(img, preset(LOST_IN_SPACE_FIRST_STAGE), light_dir=light, what=str(image))[0])
            if coarse.ok:
                prior_g = Georef.centred_on(pole, coarse.x_m, coarse.y_m, img.shape, pixel)
        if prior_g is None:
            dets, theta, fix = [], light, dataclasses.replace(coarse, reason=f"lost in space: {coarse.reason}")
        else:
            dets, theta, fix, landmarks, source = appearance_window_fix(
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
    from crater_synth.navigation.output import detection_records, write_detections

    write_detections(listing, image, detection_records(dets, dict(fix.inliers) if fix.ok else {}, landmarks))
    atomic_write_bytes(out, annotate(img, dets, landmarks, fix, prior_g, truth))
    result.update(annotated=str(out), detections_file=str(listing))
    click.echo(json.dumps(result))
