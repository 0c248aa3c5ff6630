"""``python -m crater_synth.tools.lis_choice``: choose lost-in-space settings on the south validation windows, and
write the runs and the choice as JSON.

A detector runs once per window at its lowest candidate threshold (``--detector``: nav overrides); every
``--variant`` then keeps the detections scoring at least its ``min_score=T`` and runs the lost-in-space fix with
its own ``nav.lost_in_space`` overrides, scored as ``nav-eval --lost-in-space`` scores it (the same row and
summary functions; a variant naming ``nav.lost_in_space.verify_detector`` adds that detector's new craters, run
once per window, to the verification). Keeping the detections >= T of a run at a lower threshold gives the
detections of a run at T: suppression is greedy, best score first, so only a higher-scoring detection ever drops
one. ``--null FAMILY`` (repeatable) also runs every variant on each window's detections moved so that no
similarity at the known pixel size maps them onto the map (:data:`NULLS`): ``mirror``, mirrored four ways
(left-right, top-bottom, both diagonals), and ``scale``, scaled about the centre by 1.3 and 1/1.3. Any fix of a
moved window is false (a variant confirmed by appearance searches the moved image too: :func:`null_image`). A
validation set's 120 windows bound a false-fix rate only to a few percent; the moved windows keep the
detections' number, sizes and scores, and test the gates on many windows that cannot be fixed. ``--places N``:
a variant confirmed by appearance also searches each window's image at N places where it is not
(:func:`places_elsewhere`), and ``--vote-places`` at every place its vote offers more than 5 km from where it is
(:func:`vote_places_elsewhere`); any place confirmed away from the window is chance (:func:`search_elsewhere`). The
rule: no false fix on any window (nor a fix of
any moved window, nor a place elsewhere confirmed), then the highest fix rate of the headline windows (rates
within one window of it are tied: then the lowest median error). The
north windows are a test: this tool never reads them; run ``nav-eval --pole north`` once with the choice, after
it is committed.

    python -m crater_synth.tools.lis_choice --detector 'nav/detector=learned-detect nav.detector.tta=4
        nav.detector.half_octaves=true nav.detector.threshold=0.05' --variant 'min_score=0.15' \\
        --variant 'min_score=0.1 nav/lost_in_space=two-tier' --out docs/results/FILE.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from functools import partial
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from crater_core.schema import atomic_write_text
from crater_synth.errors import UserError
from crater_synth.navigation.detectors.classical import Detection, detect, with_new
from crater_synth.navigation.fix.lost_in_space import (
    PLACE_MIN_KM,
    LostInSpaceParams,
    build_index,
    hypotheses,
    lost_in_space_search,
    moved_detections,
    places_elsewhere,
    window_heading_deg,
)
from crater_synth.navigation.fix.solve import FALSE_FIX_KM
from crater_synth.navigation.georef import ground_distance_km
from crater_synth.navigation.settings import compose_nav, verify_detector_settings
from crater_synth.navigation.windows.appearance import search_place
from crater_synth.navigation.windows.evaluate import (
    appearance_settings,
    catalogue_craters,
    nav_eval_map,
    score_window,
    summarise_windows,
    verify_detections,
    window_lost_in_space,
)
from crater_synth.navigation.windows.light import frame_light
from crater_synth.navigation.windows.mosaic import windows
from crater_synth.tools.detector_choice import POLE, SPLIT, command_line

PROG = "python -m crater_synth.tools.lis_choice"


def _scaled(side: float, k: float) -> np.ndarray:
    """Scaling by ``k`` about a square frame's centre, as :data:`NULLS` writes a move."""
    c = (1.0 - k) * side / 2.0
    return np.array([[k, 0.0, c], [0.0, k, c]])


# Windows no setting should fix: each window moved so that no similarity at the known pixel size maps its craters
# onto the map. A move is the affine map (u, v) -> A (u, v) + t of a square frame of side s (u right, v down,
# pixel-corner origin), applied to the detections (a radius scales by sqrt |det A|) and, for a confirmation by
# appearance, to the image. Mirror images keep every crater's size, score and neighbours; a window scaled about its
# centre (by 1.3 or 1/1.3, as if the altimeter were off by 30 %, craters leaving the frame dropped) keeps the
# pattern but not its scale, which the fix holds to 5 %.
NULLS: dict[str, dict[str, Callable[[float], np.ndarray]]] = {
    "mirror": {
        "left-right": lambda s: np.array([[-1.0, 0.0, s], [0.0, 1.0, 0.0]]),
        "top-bottom": lambda s: np.array([[1.0, 0.0, 0.0], [0.0, -1.0, s]]),
        "diagonal": lambda s: np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
        "anti-diagonal": lambda s: np.array([[0.0, -1.0, s], [-1.0, 0.0, s]]),
    },
    "scale": {f"x{k:.2f}": partial(_scaled, k=k) for k in (1.3, 1 / 1.3)},
}


def _null_move(shape, family: str, how: str) -> np.ndarray:
    h, w = shape
    if h != w:
        raise UserError(f"--null needs square windows, not {w} x {h} px")
    return NULLS[family][how](float(w))


def null_window(dets: list[Detection], shape, family: str, how: str) -> list[Detection]:
    """``dets`` moved by ``NULLS[family][how]`` in a square frame of ``shape`` (scores kept; a detection whose
    centre leaves the frame is dropped)."""
    move = _null_move(shape, family, how)
    uv, r, kept = moved_detections([[d.u, d.v] for d in dets], [d.r for d in dets], move, shape)
    return [Detection(*uv[i].tolist(), float(r[i]), d.score) for i, d in enumerate(dets) if kept[i]]


def null_image(image: np.ndarray, family: str, how: str) -> np.ndarray:
    """``image`` moved as :func:`null_window` moves its craters (bilinear; outside the frame: reflected)."""
    m = _null_move(image.shape, family, how)
    # OpenCV's pixel coordinates sit at pixel centres: x = u - 0.5
    shift = m[:, :2] @ (0.5, 0.5) + m[:, 2] - 0.5
    pixel = np.concatenate([m[:, :2], shift[:, None]], axis=1)
    side = image.shape[0]
    return cv2.warpAffine(image, pixel, (side, side), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)


def vote_places_elsewhere(frame, dets, landmarks, lis, index, nav, voters: int) -> list[complex]:
    """Every place the window's vote offers (:func:`.lost_in_space.hypotheses`, with no cap on their number) more
    than :data:`.solve.FALSE_FIX_KM` from the window's true place: where the window's craters already line up
    with some landmarks, the places a confirmation by appearance is most likely to confirm by chance."""
    shape, pixel_m = frame.image.shape, frame.georef.pixel_m
    heading = window_heading_deg(lis)
    _, cands = lost_in_space_search(dets, landmarks, shape, pixel_m, lis, nav.fix, index, heading, voters)
    every = dataclasses.replace(lis, confirm_hypotheses=max(1, len(cands)))
    pole = frame.georef.pole
    out = []
    for place in hypotheses(cands, every):
        km = ground_distance_km(place.centre.real, place.centre.imag, *frame.centre_xy, pole)
        if km > FALSE_FIX_KM:
            out.append(place.centre)
    return out


def search_elsewhere(frame, landmarks, lis, nav, places: list[complex]) -> list[dict]:
    """The appearance search (:func:`.appearance.search_place`) of the window's own image at ``places`` where it
    is not: each place it confirms falsely (the fix more than :data:`.solve.FALSE_FIX_KM` from the window's true
    place), with its landmarks and that distance. A place a few km off can be confirmed at the true place, which
    the search reaches from there: that is no chance confirmation."""
    app = appearance_settings()
    light = frame_light(frame, app)["light_dir"]
    pole, pixel_m = frame.georef.pole, frame.georef.pixel_m
    confirmed = []
    for place in places:
        _, fix = search_place(frame.image, pole, pixel_m, place, landmarks, light, lis, app, nav.fix)
        km = ground_distance_km(fix.x_m, fix.y_m, *frame.centre_xy, pole) if fix.ok else 0.0
        if km > FALSE_FIX_KM:
            confirmed.append({"window": frame.id, "landmarks": len(fix.inliers), "km": round(float(km), 1)})
    return confirmed


def parse_variant(text: str, base: float) -> tuple[float, list[str]]:
    """(minimum detection score, nav overrides) of a ``--variant``: ``min_score=T`` (default: the detector's
    own threshold ``base``, below which no detection exists) and ``nav.lost_in_space`` overrides."""
    min_score, overrides = base, []
    for token in text.split():
        key, _, value = token.partition("=")
        if key == "min_score":
            try:
                min_score = float(value)
            except ValueError:
                raise UserError(f"--variant {text!r}: min_score must be a number, not {value!r}") from None
            if min_score < base:
                raise UserError(f"--variant {text!r}: min_score {min_score} is below the detector's threshold {base}")
        elif key.startswith(("nav.lost_in_space.", "nav/lost_in_space")):
            overrides.append(token)
        else:
            raise UserError(f"--variant {text!r}: {token!r} is neither min_score=T nor a nav.lost_in_space override")
    return min_score, overrides


def variant_settings(text: str, detector_overrides: list[str], nav) -> tuple[float, LostInSpaceParams]:
    """(minimum detection score, composed ``nav.lost_in_space`` settings) of a ``--variant``; ``nav``: the
    detector's composed settings."""
    min_score, overrides = parse_variant(text, nav.detector.threshold)
    return min_score, compose_nav([*detector_overrides, *overrides]).lost_in_space


def detect_windows(nav, every: int):
    """(frames, detections of each with its light direction) of ``nav``'s detector on every ``every``-th south
    validation window."""
    frames = windows(SPLIT, POLE)[::every]
    found = [detect(f.image, nav.detector, what=f"frame {f.id}", **frame_light(f, nav.detector)) for f in frames]
    return frames, found


def moved_window_fix(frame, together, n_kept: int, family: str, how: str, landmarks, lis, nav):
    """(the fix, its record or None) of a window's detections ``together`` (the first ``n_kept`` vote) moved by
    ``NULLS[family][how]``, lost in space with ``lis`` (settings, pair index); a confirmation by appearance
    searches the moved image. A fix is recorded with its landmarks and its distance from the window's true place
    (both moves keep the frame's centre)."""
    shape = frame.image.shape
    moved = null_window(together, shape, family, how)
    voters = len(null_window(together[:n_kept], shape, family, how))  # the voters lead the moved list, as unmoved
    moved_frame = dataclasses.replace(frame, image=null_image(frame.image, family, how)) if lis[0].confirm else frame
    _, fix = window_lost_in_space(moved_frame, moved, landmarks, lis, nav.fix, voters)
    if not fix.ok:
        return fix, None
    km = ground_distance_km(fix.x_m, fix.y_m, *frame.centre_xy, frame.georef.pole)
    return fix, {
        "window": frame.id,
        "null": f"{family} {how}",
        "landmarks": len(fix.inliers),
        "km": round(float(km), 2),
    }


def run_variant(
    text: str,
    min_score: float,
    lis,
    frames,
    found,
    nav,
    landmarks,
    listed,
    extras=None,
    nulls=(),
    places=0,
    vote_places=False,
) -> dict:
    """One variant's rows on every window (its detections scoring >= ``min_score``, lost in space with
    ``lis``; ``extras``: each window's detections by ``lis.verify_detector``), summarised as ``nav-eval``
    summarises them; ``nulls``: also the fixes of each window moved by those families of :data:`NULLS`
    (``"null"``); ``places``: a variant confirmed by appearance also searches each window's image at that many
    places elsewhere (:func:`places_elsewhere`, ``"elsewhere"``) and, with ``vote_places``, at every place its vote
    offers elsewhere (:func:`vote_places_elsewhere`, ``"elsewhere"["vote"]``)."""
    index = build_index(landmarks, lis)
    t0 = time.perf_counter()
    extras = extras if extras is not None else [[] for _ in frames]
    rows, null_fixed, fixed_support, null_support, fixed_landmarks, elsewhere, voted = [], [], [], [], [], [], []
    n_voted = 0
    moves = [(family, how) for family in nulls for how in NULLS[family]]
    for frame, (dets, theta), extra in zip(frames, found, extras):
        kept = [d for d in dets if d.score >= min_score]
        # a verify detector's new craters after the voters' (nav-eval's order)
        together = with_new(kept, extra, verify_detector_settings(lis.verify_detector))
        used, fix = window_lost_in_space(frame, together, landmarks, (lis, index), nav.fix, len(kept))
        rows.append(score_window(frame, landmarks, nav.fix, used, theta, fix, listed))
        if fix.ok:
            fixed_support.append(fix.support)
            fixed_landmarks.append(len(fix.inliers))
        if lis.confirm and places:
            spots = places_elsewhere(frame.id, frame.centre_xy, landmarks, places, lis.min_landmark_km)
            elsewhere += search_elsewhere(frame, landmarks, lis, nav, spots)
        if lis.confirm and vote_places:
            spots = vote_places_elsewhere(frame, together, landmarks, lis, index, nav, len(kept))
            n_voted += len(spots)
            voted += search_elsewhere(frame, landmarks, lis, nav, spots)
        for family, how in moves:
            nfix, where = moved_window_fix(frame, together, len(kept), family, how, landmarks, (lis, index), nav)
            if math.isfinite(nfix.support):
                null_support.append(nfix.support)
            if where is not None:
                null_fixed.append(where)
    summary = summarise_windows(rows)
    run = {
        "variant": text,
        "min_score": min_score,
        "lost_in_space": lis.as_dict(),
        "headline": summary["headline"],
        "all_windows": summary["all_windows"],
        "seconds": round(time.perf_counter() - t0, 1),
    }
    if moves:
        run["null"] = {"families": list(nulls), "windows": len(frames) * len(moves), "fixes": len(null_fixed)}
        run["null"]["fixed"] = null_fixed
        # The support of the best verified candidate (inliers, or -log10 chance) of each moved window where one
        # verified, fixed or not, beside that of the windows' own fixes: where chance reaches, what a gate needs.
        run["null"]["supports_verified"] = sorted((round(x, 2) for x in null_support), reverse=True)
        run["fixed_supports"] = sorted(round(x, 2) for x in fixed_support)
    if lis.confirm and (places or vote_places):
        run["elsewhere"] = {}
        if places:
            run["elsewhere"].update({"places": places * len(frames), "min_km": PLACE_MIN_KM, "confirmed": elsewhere})
        if vote_places:
            run["elsewhere"]["vote"] = {"places": n_voted, "min_km": FALSE_FIX_KM, "confirmed": voted}
        # beside the landmarks of the windows' own fixes: what a confirmation's landmark gate must exceed
        run["fixed_landmarks"] = sorted(fixed_landmarks)
    return run


def choose(runs: list[dict]) -> dict:
    """No false fix on any window, nor a fix of a moved one (``--null``), nor a place elsewhere confirmed by
    appearance (``--places``, ``--vote-places``); then the highest headline fix rate, rates within one headline
    window of it tied; among the tied, the lowest median error."""

    def is_safe(r: dict) -> bool:
        elsewhere = r.get("elsewhere", {})
        chance = (
            r.get("null", {}).get("fixes") or elsewhere.get("confirmed") or elsewhere.get("vote", {}).get("confirmed")
        )
        return not r["all_windows"].get("false_fixes") and not chance

    safe = [r for r in runs if is_safe(r)]
    if not safe:
        return {
            "variant": None,
            "why": "every variant made a false fix (or fixed a moved window, or confirmed a place elsewhere)",
        }
    top = max(r["headline"].get("fix_rate") or 0.0 for r in safe)
    tied = [r for r in safe if (top - (r["headline"].get("fix_rate") or 0.0)) * r["headline"]["windows"] <= 1.0 + 1e-9]
    best = min(tied, key=lambda r: r["headline"].get("median_error_km") or 1e9)
    return {"variant": best["variant"], "headline_fix_rate": best["headline"].get("fix_rate")}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--detector", required=True, help="the detector's nav overrides (space-separated), lowest threshold")
    p.add_argument("--variant", action="append", required=True, help="'min_score=T [overrides]', repeatable")
    p.add_argument("--every", type=int, default=1, help="every Nth south validation window")
    p.add_argument(
        "--null",
        action="append",
        default=[],
        choices=sorted(NULLS),
        help="also run every variant on each window moved so that it cannot be fixed (repeatable)",
    )
    p.add_argument(
        "--places",
        type=int,
        default=0,
        help="variants confirmed by appearance: also search each window's image at this many places elsewhere",
    )
    p.add_argument(
        "--vote-places",
        action="store_true",
        help="variants confirmed by appearance: also search each window's image at every place its vote offers "
        "elsewhere",
    )
    p.add_argument("--out", type=Path, default=None, help="JSON of the runs and the choice")
    args = p.parse_args(argv)
    try:
        detector_overrides = args.detector.split()
        nav = compose_nav(detector_overrides)
        # Every variant is composed (and so checked) before the detector runs.
        variants = [(v, *variant_settings(v, detector_overrides, nav)) for v in args.variant]
        landmarks, _ = nav_eval_map(POLE, None)
        listed = catalogue_craters(POLE)
        t0 = time.perf_counter()
        frames, found = detect_windows(nav, args.every)
        detect_s = round(time.perf_counter() - t0, 1)
        runs = []
        verify: dict[str, list] = {}  # verify detector -> its detections on each window, run once for every variant
        for v, min_score, lis in variants:
            name = lis.verify_detector
            if name and name not in verify:
                verify[name] = [verify_detections(f, lis) for f in frames]
            args_v = (frames, found, nav, landmarks, listed, verify.get(name), args.null, args.places, args.vote_places)
            r = run_variant(v, min_score, lis, *args_v)
            rate, false = r["headline"].get("fix_rate"), r["all_windows"].get("false_fixes")
            moved = f", moved windows fixed {r['null']['fixes']} of {r['null']['windows']}" if args.null else ""
            print(f"{v}: headline fix rate {rate}, false fixes {false}{moved}", flush=True)
            runs.append(r)
    except UserError as exc:
        raise SystemExit(f"error: {exc}") from None
    doc = {
        "command": command_line(argv, PROG),
        "split": f"{POLE} {SPLIT}, every {args.every}th window",
        "detector": {"overrides": detector_overrides, "settings": nav.detector.as_dict(), "seconds": detect_s},
        "rule": "no false fix on any window (nor a fix of a moved window, with --null, nor a place elsewhere "
        "confirmed, with --places or --vote-places), then the highest headline fix rate (within one headline "
        "window: tied, then the lowest median error)",
        "runs": runs,
        "chosen": choose(runs),
    }
    print(json.dumps(doc["chosen"]))
    if args.out:
        atomic_write_text(args.out, json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
