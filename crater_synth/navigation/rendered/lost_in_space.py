"""Lost in space on rendered perspective frames (``crater-synth nav-frames-lis DIR``): the pair vote of
:mod:`.lost_in_space` on detections rectified onto the ground with the known attitude and an altimeter,
then the 6-DOF pinhole fix from the vote's position.

A lander that has lost its position still knows its attitude (star tracker and ephemeris) and measures
its range to the ground along the boresight (altimeter). With both, a perspective frame's detections are
placed on the ground (:func:`rectify`: each detection's camera ray cut with the Moon's sphere through the
boresight's ground point, at its distance along the ground from the point under the camera): a nadir
map of the frame at a known scale, which is what the mosaic windows are. The frozen ``south-choice`` pair
vote then runs on it unchanged, its tolerances in the windows' 400 m pixels (:data:`LIS_PIXEL_M`), and
gives the map point under the camera. The camera placed over that point at the height the range and
attitude give is the prior of ``nav-frames-eval``'s 6-DOF fix (:func:`six_dof_fix`), which solves the
attitude and the 3-D position from the map landmarks that prior predicts. Nothing here was chosen on
rendered frames: the detector settings are the given ``nav/detector``'s (the ``synthetic`` preset's by
default), the vote's the windows'.

With the DEM on board (``nav.lost_in_space.confirm=appearance``, ``nav/lost_in_space=confirmed-frames``) the
vote's places are hypotheses instead (:func:`confirmed_six_dof`): each becomes the prior of the appearance
search's 6-DOF fix (``nav-frames-eval``'s appearance preset), and the frame is fixed where that search fixes it.
``--places N`` (:func:`places_null`) measures how often the search confirms a place where the frame is not.

Assumptions, as in ``nav-frames-eval``: the attitude relative to the local vertical is the true one; the
range is the rendered depth at the image centre (what a boresight altimeter measures); the light
direction in the image is given (attitude and ephemeris need no position). The rectified ground and the
polar stereographic map plane differ by the projection's scale (< 1 % poleward of 80 degrees of latitude)
and a rotation, which the vote's free heading absorbs. The vote's error is the horizontal distance between
the fixed and the true map point under the camera, the 6-DOF fix's the 3-D distance to the true camera; a
fix is false beyond 5 km.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import click
import numpy as np

from crater_core import exr, geometry
from crater_core.geometry import MOON_RADIUS_M
from crater_core.schema import atomic_write_json
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.errors import UserError
from crater_synth.navigation.detectors.classical import Detection, detect
from crater_synth.navigation.fix.lost_in_space import (
    PLACE_MIN_KM,
    build_index,
    confirm_places,
    lost_in_space_search,
    places_elsewhere,
)
from crater_synth.navigation.fix.patches import PatchParams
from crater_synth.navigation.fix.refine import Refiner, lander_dem
from crater_synth.navigation.fix.solve import FALSE_FIX_KM
from crater_synth.navigation.fix.terrain_places import shaded_map, terrain_places
from crater_synth.navigation.georef import FrameError, ground_distance_km, pole_of, stereo_forward, stereo_inverse
from crater_synth.navigation.map.landmarks import load_default_map
from crater_synth.navigation.protocol import fix_counts, lost_in_space_summary
from crater_synth.navigation.rendered.evaluate import (
    FrameRun,
    evaluate_frame,
    frame_run,
    match_pixels,
    perfect_detections,
    with_patch_fallback,
)
from crater_synth.navigation.rendered.ground_view import (
    camera_from_centre,
    ground_coords,
    ground_light,
    ground_view,
    inside_footprint,
    rays_to_ground,
    to_frame,
)
from crater_synth.navigation.rendered.labels import labelled_rows
from crater_synth.navigation.rendered.sunlight import rendered_light, row_to_sun
from crater_synth.navigation.settings import compose_nav, map_scales

LIS_PIXEL_M = 400.0  # the pair vote's pixel: its tolerances were chosen on 400 m/px mosaic windows
# The attitude rectify() assumes is measured (star tracker and camera alignment): its 1-sigma, with which the
# 6-DOF fix takes it as a measurement. A stated assumption of a typical budget (a tracker's own 1-10 arcsec
# plus a few hundredths of a degree of camera-to-tracker alignment), not tuned.
LIS_ATTITUDE_SIGMA_DEG = 0.05


def rectify(dets, row: dict, range_m: float) -> tuple[list[Detection], tuple[int, int], list[int]]:
    """``dets`` of the frame ``row`` moved onto the ground, as detections of a nadir frame of
    :data:`LIS_PIXEL_M` pixels whose centre lies under the camera; that frame's shape; the index in ``dets``
    of each (a detection whose ray misses the ground is dropped).

    The ground is the sphere of the Moon's radius through the boresight's ground point (``range_m`` along
    the boresight; the local vertical there is the frame's up). Each detection's ray is cut with it and the
    point placed by its azimuthal-equidistant coordinates about the point under the camera (distance along
    the sphere, bearing from the frame's east axis): an oblique frame reaches hundreds of km, where a flat
    plane would lie tens of km above the ground. A rim's radius is its pixel radius times its depth along
    the optical axis over the focal length."""
    r_wc, k, q = camera_from_centre(row, range_m)
    if not dets:
        return [], (1, 1), []
    pix = np.array([[d.u, d.v, 1.0] for d in dets])
    rays = np.linalg.solve(k, pix.T).T @ r_wc  # world directions, unit depth along the optical axis
    ground, t, keep = rays_to_ground(rays, q)
    east_m, north_m = ground_coords(ground, q)
    r_ground = np.array([d.r for d in dets]) * t / k[0, 0]
    half = (
        float(np.nanmax(np.abs(np.concatenate([east_m[keep], north_m[keep]])))) / LIS_PIXEL_M + 2.0
        if keep.any()
        else 1.0
    )
    size = int(math.ceil(2.0 * half))
    c = size / 2.0
    idx = [int(i) for i in np.nonzero(keep)[0]]
    out = [
        Detection(c + east_m[i] / LIS_PIXEL_M, c - north_m[i] / LIS_PIXEL_M, r_ground[i] / LIS_PIXEL_M, dets[i].score)
        for i in idx
    ]
    return out, (size, size), idx


def camera_height_m(row: dict, range_m: float) -> float:
    """The camera's height above the sphere of the Moon's radius through the boresight's ground point, from
    the altimeter's range and the attitude (what :func:`rectify` assumes)."""
    return float(np.linalg.norm(camera_from_centre(row, range_m)[2])) - MOON_RADIUS_M


def map_heading_deg(row: dict, pole: str) -> float:
    """The rectified frame's heading on the polar stereographic map: the angle of the map direction of
    the frame's east axis (its +u), which the camera's Moon-fixed attitude gives without its position."""
    lat0, lon0 = row["frame_origin"]["lat"], row["frame_origin"]["lon"]
    steps = geometry.enu_to_mc(np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0]]), lat0, lon0)
    lat, lon, _ = geometry.mc_to_latlon(steps)
    x, y = stereo_forward(lat, lon, pole)
    return math.degrees(math.atan2(float(y[1] - y[0]), float(x[1] - x[0])))


def boresight_range_m(depth: np.ndarray) -> float:
    """The altimeter's range: the rendered depth (along the view axis) at the image centre (2 x 2 pixels)."""
    h, w = depth.shape
    return float(np.mean(depth[h // 2 - 1 : h // 2 + 1, w // 2 - 1 : w // 2 + 1]))


def found(dets, labels: list[dict]) -> list[int]:
    """[labels a detection matches (:func:`.evaluate.match_pixels`), labels]."""
    return [len(match_pixels(dets, labels)) if labels else 0, len(labels)]


def recall(rows: list[dict], key: str) -> float | None:
    """The share of the rows' labels in ``key`` (:func:`found`) that a detection matches."""
    n = sum(r[key][1] for r in rows)
    return round(sum(r[key][0] for r in rows) / n, 4) if n else None


def lis_frame(row: dict, image, depth: np.ndarray, landmarks, nav, index, detections=None, refiner=None) -> dict:
    """Detection, lost-in-space identification and horizontal fix of one rendered frame, scored against
    its pose and labels, with the settings ``nav`` (its detector, fix and ``lost_in_space``; ``index``: the
    map's pair index). ``detections`` replaces the detector's (the perfect-detection check). With
    ``nav.lost_in_space.known_heading`` the vote keeps only the heading the attitude gives (:func:`map_heading_deg`).
    With ``nav.lost_in_space.confirm`` and the pole's ``refiner`` (:class:`.refine.Refiner`), the 6-DOF fix is the
    vote's places confirmed by appearance (:func:`confirmed_six_dof`; not for given ``detections``)."""
    fparams, lis = nav.fix, nav.lost_in_space
    gsd = float(row["ground_sample_m"])
    # No prior predicts the landmarks in view: search up to the largest landmark that fits in the frame.
    biggest = min(max(lm.diameter_km for lm in landmarks) * 500.0, float(row["footprint_half_width_m"]))
    rng = boresight_range_m(depth)
    # The frame on the ground, built once for the detector and the terrain's places (~0.3 s).
    wants_view = detections is None and (nav.frames.ground_view or (lis.confirm and lis.terrain_places))
    view = ground_view(image, row, rng) if wants_view else None
    blank = ""
    try:
        if detections is not None:
            dets = list(detections)
        elif nav.frames.ground_view:
            dets = ground_view_detections(image, row, rng, nav, biggest, view)
        else:
            dparams = map_scales(nav.detector, fparams, gsd, [biggest / gsd])
            dets, _ = detect(image, dparams, light_dir=rendered_light(row), what=f"frame {row['rel_path']}")
    except FrameError as exc:  # a frame all in shadow: nothing to detect, an answer of "no fix" (as nav-frames-eval)
        dets, blank = [], str(exc)
    flat, shape, kept = rectify(dets, row, rng)
    pole = pole_of(row["frame_origin"]["lat"])
    heading = map_heading_deg(row, pole) if lis.known_heading else None
    fix, cands = lost_in_space_search(flat, landmarks, shape, LIS_PIXEL_M, lis, fparams, index, heading_deg=heading)
    truth = true_place(row)
    out = {
        "index": row["index"],
        "altitude_km": row["pose"]["altitude_m"] / 1000.0,
        # Found, of the labelled landmarks: those whose rim spans >= 10 px, and those the vote uses.
        "found_span10": found(dets, [lb for lb in row["landmarks"] if 2.0 * lb["ellipse"]["a"] >= 10.0]),
        "found_lis": found(dets, [lb for lb in row["landmarks"] if lb["diameter_km"] >= lis.min_landmark_km]),
        "range_km": rng / 1000.0,
        "detections": len(dets),
        "rectified": len(flat),
        "fix": fix.ok,
        "reason": blank or fix.reason,
    }
    if fix.ok:
        # Which landmark each identified detection is, by the frame's labels.
        truth_of = match_pixels(dets, row["landmarks"])
        ids = {lm.id: i for i, lm in enumerate(landmarks)}
        label_ids = [ids.get(lb["id"]) for lb in row["landmarks"]]
        out["error_km"] = float(math.hypot(fix.x_m - truth.real, fix.y_m - truth.imag)) / 1000.0
        out["identified"] = len(fix.inliers)
        out["identified_correct"] = int(
            sum(1 for fi, li in fix.inliers if kept[fi] in truth_of and label_ids[truth_of[kept[fi]]] == li)
        )
    if lis.confirm and detections is None:
        out["six_dof"] = confirmed_six_dof(row, image, cands, rng, landmarks, lis, refiner, view)
    elif fix.ok:
        out["six_dof"] = six_dof_fix(row, image, dets, place_prior(row, complex(fix.x_m, fix.y_m), rng), landmarks, nav)
    else:
        out["six_dof"] = {"fix": False, "reason": fix.reason}
    return out


def ground_view_detections(image, row: dict, range_m: float, nav, biggest_m: float, view=None) -> list[Detection]:
    """The detector run on the frame resampled onto the ground (:func:`.ground_view.ground_view`, or the
    given ``view`` of it) at that view's one ground sample, from the smallest landmark's radius to
    ``biggest_m``, the light crossing the view along the Sun's ground direction under the camera; rims cut by
    the footprint's edge dropped, and the rest carried back into the frame's pixels."""
    view = ground_view(image, row, range_m) if view is None else view
    light = ground_light(row, range_m)
    dparams = map_scales(nav.detector, nav.fix, view.pixel_m, [biggest_m / view.pixel_m])
    dets, _ = detect(view.image, dparams, light_dir=light, what=f"frame {row['rel_path']} on the ground")
    return to_frame(inside_footprint(dets, view), view, row, range_m)


SIX_DOF_KEYS = ("fix", "reason", "error_km", "error_horizontal_km", "attitude_error_deg", "identified",
                "identified_correct", "rms_px")  # fmt: skip


def place_prior(row: dict, centre: complex, range_m: float) -> np.ndarray:
    """The camera (frame ENU) over map point ``centre`` (x + iy) at the height the altimeter and attitude give
    (:func:`camera_height_m`): a lost-in-space place as the prior of a perspective fix."""
    lat0, lon0 = row["frame_origin"]["lat"], row["frame_origin"]["lon"]
    lat, lon = stereo_inverse(centre.real, centre.imag, pole_of(lat0))
    camera = geometry.latlon_to_mc(float(lat), float(lon), camera_height_m(row, range_m))
    return geometry.mc_to_enu(np.atleast_2d(camera), lat0, lon0)[0]


def six_dof_fix(row: dict, image, dets, prior: np.ndarray, landmarks, nav) -> dict:
    """The 6-DOF pose from a lost-in-space place (``prior``: :func:`place_prior`), which is the prior of
    ``nav-frames-eval``'s pinhole fix (``nav.frames.solver=pnp``: the landmarks that prior predicts paired with
    ``dets``, RANSAC over P3P, attitude and position solved together, the attitude rectification assumed taken
    as a measurement of 1-sigma :data:`LIS_ATTITUDE_SIGMA_DEG`). Its fields of the frame's row
    (:data:`SIX_DOF_KEYS`); ``image`` is not searched again (``dets`` are the frame's detections)."""
    r = evaluate_frame(
        row,
        image,
        landmarks,
        frame_run(nav, method="pnp", refine=False, pnp_attitude_sigma_deg=LIS_ATTITUDE_SIGMA_DEG),
        detections=list(dets),
        prior_enu=prior,
    )
    return {k: r[k] for k in SIX_DOF_KEYS if k in r}


# The appearance search a confirmation runs at each place: nav-frames-eval's appearance preset (its search,
# identification, refinement and terrain patches) with the 6-DOF fix, none of it chosen again here.
CONFIRM_PRESET = ("nav/preset=appearance", "nav.frames.solver=pnp")


@functools.lru_cache(maxsize=4)  # composing the preset takes ~0.2 s; every frame and place-elsewhere run asks
def confirm_run(lis) -> FrameRun:
    """The settings of :data:`CONFIRM_PRESET` a confirmation searches each place with: the 6-DOF fix refined by
    appearance and taking the attitude as a measurement (1-sigma :data:`LIS_ATTITUDE_SIGMA_DEG`), its prior gate
    ``lis.confirm_reach_km``, its fix at least ``lis.confirm_min_landmarks`` landmarks (craters or patches)."""
    app = compose_nav(list(CONFIRM_PRESET))
    fparams = lis.confirm_params(app.fix)
    return frame_run(app, fparams=fparams, refine_pnp=True, pnp_attitude_sigma_deg=LIS_ATTITUDE_SIGMA_DEG)


def search_frame_place(row: dict, image, centre: complex, range_m: float, landmarks, run: FrameRun, refiner) -> dict:
    """The appearance search's 6-DOF fix of a frame from one place (map point ``centre`` under the camera), its
    terrain patches where its craters give none (:func:`.evaluate.with_patch_fallback`)."""
    prior = place_prior(row, centre, range_m)
    r = evaluate_frame(row, image, landmarks, run, refiner=refiner, prior_enu=prior)
    return with_patch_fallback(r, row, image, landmarks, refiner, PatchParams(), run, prior)


def confirmed_six_dof(row: dict, image, cands, range_m: float, landmarks, lis, refiner, view=None) -> dict:
    """The 6-DOF fix of a frame lost in space, its vote's candidates confirmed by appearance: each place
    :func:`.lost_in_space.hypotheses` keeps, best supported first, searched by :func:`search_frame_place`
    (:func:`confirm_run`'s settings). The first confirmed place is the fix; a second one whose camera lies more
    than ``lis.rival_km`` from it makes the frame ambiguous (no fix). The terrain's places
    (:func:`frame_terrain_places`) are searched first, then the vote's more than ``lis.rival_km`` from them. Its
    fields of the row (:data:`SIX_DOF_KEYS`, ``fix_source``) and ``places``: each place searched, where it came
    from, how far it lies from the truth (km; scoring only) and what the search gave. ``view``: the frame's
    ground view, where the detector already built it."""
    if refiner is None:
        raise UserError("nav.lost_in_space.confirm=appearance needs the lander's DEM (a refiner)")
    places = confirm_places(frame_terrain_places(row, image, range_m, lis, view), cands, lis)
    if not places:
        return {
            "fix": False,
            "reason": lis.no_place_reason(),
            "places": [],
        }
    run, truth = confirm_run(lis), true_place(row)
    pole = pole_of(row["frame_origin"]["lat"])
    tried, confirmed = [], []
    for source, centre, support in places:
        r = search_frame_place(row, image, centre, range_m, landmarks, run, refiner)
        km = float(ground_distance_km(centre.real, centre.imag, truth.real, truth.imag, pole))
        tried.append({"source": source, "support": round(float(support), 3), "place_km": round(km, 2),
                      "fix": r["fix"], "reason": r["reason"], "error_km": r.get("error_km")})  # fmt: skip
        if r["fix"]:
            confirmed.append(r)
    if not confirmed:
        out = {"fix": False, "reason": f"no place confirmed by appearance ({len(places)} searched)"}
        return out | {"places": tried}
    best = confirmed[0]
    for other in confirmed[1:]:
        apart = np.hypot(*(np.subtract(best["position_enu_m"], other["position_enu_m"])[:2])) / 1000.0
        if apart > lis.rival_km:
            reason = f"ambiguous: appearance confirms places {apart:.0f} km apart"
            return {"fix": False, "reason": reason, "places": tried}
    keep = {k: best[k] for k in SIX_DOF_KEYS if k in best}
    return keep | {"fix_source": best.get("fix_source"), "places": tried}


def frame_terrain_places(row: dict, image, range_m: float, lis, view=None) -> list[tuple[complex, float]]:
    """The ``lis.terrain_places`` map points (with their correlation) where the frame's ground view
    (:func:`.ground_view.ground_view`, or the given ``view`` of it) best matches the lander's DEM shaded under
    the frame's Sun and seen along its boresight (:func:`.terrain_places.shaded_map`), turned to the map by the
    attitude (:func:`map_heading_deg`); two places at least twice ``lis.confirm_reach_km`` apart. The Sun and the
    boresight are Moon-fixed directions (ephemeris and attitude): the frame's own ENU only carries them."""
    if not lis.terrain_places:
        return []
    view = ground_view(image, row, range_m) if view is None else view
    lat0, lon0 = row["frame_origin"]["lat"], row["frame_origin"]["lon"]
    to_mc = geometry.enu_basis(lat0, lon0).T
    to_sun = row_to_sun(row)
    boresight = camera_from_centre(row, range_m)[0][2]
    pole = pole_of(lat0)
    shaded = shaded_map(pole, lis.terrain_pixel_m, to_mc @ to_sun, to_mc @ -boresight)
    under = (-view.origin_m[0] / view.pixel_m, view.origin_m[1] / view.pixel_m)  # the point under the camera
    heading = map_heading_deg(row, pole)
    apart = 2.0 * lis.confirm_reach_km
    return terrain_places(view.image, view.valid, view.pixel_m, under, heading, shaded, lis.terrain_places, apart)


def true_place(row: dict) -> complex:
    """The map point (x + iy) under the frame's true camera: where its lost-in-space fix should be."""
    lat, lon, _ = geometry.mc_to_latlon(np.array(row["pose"]["position_mc_m"], dtype=np.float64))
    x, y = stereo_forward(float(lat), float(lon), pole_of(row["frame_origin"]["lat"]))
    return complex(float(x), float(y))


def places_null(row: dict, image, range_m: float, landmarks, lis, refiner, n: int) -> list[dict]:
    """The frame's image searched at ``n`` places where it is not (:func:`.lost_in_space.places_elsewhere`, >= 300
    km from its true place) as a confirmation searches a place: each one confirmed more than
    :data:`.solve.FALSE_FIX_KM` from the truth (a chance confirmation), with its landmarks and error."""
    truth, run = true_place(row), confirm_run(lis)
    chance = []
    for centre in places_elsewhere(row["rel_path"], (truth.real, truth.imag), landmarks, n, lis.min_landmark_km):
        r = search_frame_place(row, image, centre, range_m, landmarks, run, refiner)
        if r["fix"] and r["error_km"] > FALSE_FIX_KM:
            chance.append({"frame": row["index"], "landmarks": r["identified"], "error_km": round(r["error_km"], 1)})
    return chance


def six_dof_summary(rows: list[dict]) -> dict:
    """Fix rate, false fixes (3-D error > FALSE_FIX_KM), median position and attitude errors of the 6-DOF
    fixes of lost-in-space rows."""
    fixed = [r["six_dof"] for r in rows if r["six_dof"]["fix"]]
    err = np.array([r["error_km"] for r in fixed])
    att = np.array([r["attitude_error_deg"] for r in fixed])
    return fix_counts(len(rows), err) | {
        "median_error_km": round(float(np.median(err)), 3) if err.size else None,
        "median_attitude_error_deg": round(float(np.median(att)), 4) if att.size else None,
    }


def evaluate_lis_dir(frames_dir: Path, nav, places: int = 0) -> dict:
    """Every frame of a ``nav-frames`` directory lost in space with the settings ``nav`` (a crater detector's;
    the pair vote's are ``nav.lost_in_space``), with the detector and with perfect detections; per-frame
    rows and both summaries. With a confirmation by appearance (``nav.lost_in_space.confirm``), ``places`` > 0
    also searches each frame's image at that many places where it is not (:func:`places_null`)."""
    if nav.appearance:
        raise UserError("lost in space needs a crater detector (the appearance search needs a prior)")
    lis = nav.lost_in_space
    if lis.verify_detector:
        raise UserError(
            f"nav.lost_in_space.verify_detector={lis.verify_detector}: rendered frames take one detector "
            "(a second one's detections verify on map windows only: nav-eval, navigate)"
        )
    if places and not lis.confirm:
        raise UserError(f"--places {places}: places elsewhere test a confirmation (nav/lost_in_space=confirmed)")
    maps: dict[str, tuple] = {}
    out, chance = [], []
    for row in labelled_rows(frames_dir):
        pole = pole_of(row["frame_origin"]["lat"])
        if pole not in maps:
            lms = load_default_map(pole)[0]
            maps[pole] = (lms, build_index(lms, lis), Refiner(lander_dem(pole)) if lis.confirm else None)
        lms, index, refiner = maps[pole]
        path = Path(frames_dir) / row["rel_path"]
        channels = exr.read_channels(path, ("IF", "depth"))
        image, depth = channels["IF"], channels["depth"]
        r = lis_frame(row, image, depth, lms, nav, index, refiner=refiner)
        # The chain (rectification, pair vote, verification) with every labelled landmark of the map's sizes
        # given as a detection (its own ellipse): what the detector's result is to be read against.
        big = [
            d for d, lb in zip(perfect_detections(row), row["landmarks"]) if lb["diameter_km"] >= lis.min_landmark_km
        ]
        r["perfect"] = lis_frame(row, None, depth, lms, nav, index, detections=big)
        if places:
            chance += places_null(row, image, boresight_range_m(depth), lms, lis, refiner, places)
        out.append(r)
    result = {
        "frames_dir": str(frames_dir),
        "preset": nav.preset,
        "lis_preset": nav.choices["lost_in_space"],
        "lis_settings": lis.as_dict(),
        "summary": lost_in_space_summary(out),
        "perfect_summary": lost_in_space_summary([r["perfect"] for r in out]),
        "six_dof_summary": six_dof_summary(out),
        "detector_recall": {"rim_span_10px": recall(out, "found_span10"), "lis_landmarks": recall(out, "found_lis")},
        "perfect_six_dof_summary": six_dof_summary([r["perfect"] for r in out]),
        "rows": out,
    }
    if lis.confirm:
        result["confirmation"] = confirmation_summary(out, places, chance)
    return result


def confirmation_summary(rows: list[dict], places: int, chance: list[dict]) -> dict:
    """What the confirmations searched: the vote's places, those more than :data:`.solve.FALSE_FIX_KM` from the
    truth, and how many of these the search fixed that far from it (chance confirmations); with ``places`` > 0,
    the places elsewhere (:func:`places_null`) and those confirmed by chance."""
    tried = [p for r in rows for p in r["six_dof"].get("places", [])]
    wrong = [p for p in tried if p["place_km"] > FALSE_FIX_KM]
    out = {
        "places_searched": len(tried),
        "wrong_places_searched": len(wrong),
        "wrong_places_confirmed": sum(1 for p in wrong if p["fix"] and p["error_km"] > FALSE_FIX_KM),
    }
    if places:
        out["elsewhere"] = {"places": places * len(rows), "min_km": PLACE_MIN_KM, "confirmed": chance}
    return out


@click.command("nav-frames-lis")
@click.argument("frames_dir", type=click.Path(path_type=Path))
@click.option(
    "--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Write the rows."
)
@click.option(
    "--places",
    type=click.IntRange(0, 100),
    default=0,
    help="With nav/lost_in_space=confirmed: also search each frame at N places >= 300 km from it (chance).",
)
@OVERRIDES
@user_errors
def nav_frames_lis_command(frames_dir, json_path, places, overrides):
    """Lost in space on rendered frames: no position prior; attitude, altimeter range and pixel scale known.
    Settings are Hydra overrides (docs/navigation/settings.md): the detector of `nav/preset=synthetic` (the
    default), the pair vote's `nav.lost_in_space.<name>=<value>`.

    Example: `crater-synth nav-frames-lis data/navframes/descent_ridge`
    """
    result = evaluate_lis_dir(frames_dir, compose_nav(overrides, defaults=["nav/preset=synthetic"]), places)
    for r in result["rows"]:
        p = r["perfect"]
        tail = f"error {r['error_km']:.2f} km, {r['identified']} landmarks" if r["fix"] else r["reason"]
        tail += "; perfect detections: " + (f"error {p['error_km']:.2f} km" if p["fix"] else p["reason"])
        six = r["six_dof"]
        tail += "; 6-DOF: " + (f"error {six['error_km']:.2f} km" if six["fix"] else six["reason"])
        click.echo(
            f"frame {r['index']:3d} alt {r['altitude_km']:6.1f} km det {r['detections']:4d} fix {r['fix']}: {tail}",
            err=True,
        )
    if json_path is not None:
        atomic_write_json(json_path, result)
    click.echo(
        json.dumps(
            {
                "detector": result["summary"],
                "perfect_detections": result["perfect_summary"],
                "six_dof": result["six_dof_summary"],
                "perfect_six_dof": result["perfect_six_dof_summary"],
                "detector_recall": result["detector_recall"],
            }
            | ({"confirmation": result["confirmation"]} if "confirmation" in result else {})
        )
    )
