"""Navigation metrics on real mosaic windows, ``crater-synth nav-eval``, ``crater-synth navigate`` and
the navigation benchmark.

Protocol (docs/navigation/overview.md): per pole and split (south: validation and test by the sector rule of
:mod:`.frames`; north: test only), every window is a nadir frame at 400 m/px, navigated against the
pole's landmark map, with the light model of :mod:`.light`. Truth landmarks are the map's landmarks
whose centre lies in the frame. A detection matches a truth landmark when its centre is within 0.25 D
and its diameter within 25 % (one-to-one, nearest first). The prior position is the truth frame centre
moved by a seeded random offset of ``PRIOR_OFFSET_KM`` in a random direction (the prior heading and
scale are exact: a lander knows its attitude; the fix still estimates both). A fix is false when its
position error exceeds ``FALSE_FIX_KM``. The headline rows are the windows with >= 3 landmarks of
D >= 15 km in view.

Length: the metrics and ``nav-eval`` (with the prior and lost in space) run the same per-frame pipeline
(:func:`navigate_window`, :func:`run_frame`) and scoring, kept in one module so they cannot drift apart
(the benchmark, :mod:`crater_synth.bench.navigation`, times the same functions).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
import zlib
from pathlib import Path
from typing import Callable

import click
import numpy as np

from crater_core.progress import Progress
from crater_core.schema import atomic_write_text
from crater_core.settings_nav import DetectorSettings
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.errors import UserError
from crater_synth.navigation.detectors import registry
from crater_synth.navigation.detectors.classical import detect, with_new
from crater_synth.navigation.fix.lost_in_space import build_index, lost_in_space_search, window_heading_deg
from crater_synth.navigation.fix.patches import PatchParams
from crater_synth.navigation.fix.solve import FALSE_FIX_KM, FixParams, fix_frame
from crater_synth.navigation.georef import Frame, Georef, check_frame, ground_distance_km
from crater_synth.navigation.map.check import LU_SOURCE, catalogue_craters
from crater_synth.navigation.map.landmarks import load_default_map, read_map
from crater_synth.navigation.protocol import (
    HEADLINE_MIN_D_KM,
    HEADLINE_MIN_LANDMARKS,
    MATCH_CENTRE_D,
    MATCH_DIAMETER,
    PRIOR_OFFSET_KM,
    TARGETS,
    check_prior_offset_km,
    match_detections,
    summarise,
    truth_in_frame,
)
from crater_synth.navigation.settings import compose_nav, detector_options, verify_detector_settings
from crater_synth.navigation.windows.appearance import (
    confirmed_fix,
    lander_refiner,
    patch_truth_correct,
    window_detections,
    window_patch_fix,
    window_terrain_places,
)
from crater_synth.navigation.windows.light import frame_light, frame_local_light
from crater_synth.navigation.windows.mosaic import MOSAIC_PRODUCTS, windows


def prior_georef(frame: Frame, seed: int, offset_km: float = PRIOR_OFFSET_KM) -> Georef:
    """The truth georeference shifted by ``offset_km`` in a seeded random direction (the coarse prior)."""
    rng = np.random.default_rng([seed, zlib.crc32(frame.id.encode())])
    phi = rng.uniform(0.0, 2.0 * math.pi)
    g = frame.georef
    return Georef(
        g.pole, g.left_m + offset_km * 1000.0 * math.cos(phi), g.top_m + offset_km * 1000.0 * math.sin(phi), g.pixel_m
    )


def navigate_window(
    frame: Frame,
    landmarks,
    dparams: DetectorSettings,
    fparams: FixParams,
    seed: int = 0,
    lis=None,
    prior_offset_km: float = PRIOR_OFFSET_KM,
):
    """Detection and fix of one mosaic window with its light model: (detections, light azimuth rad, fix,
    prior georef). ``lis``: (:class:`.lost_in_space.LostInSpaceParams`, its pair index) for the fix with
    no position prior (the prior georef is then not used; the pixel size is known). With several
    ``dparams.light_tries_deg`` the detector and the fix run once per offset
    added to the light direction, and the fix with most inliers (then the lowest RMS, then the first
    offset) is kept; with none fixed, the first offset's detections are returned."""
    prior = prior_georef(frame, seed, prior_offset_km)
    if registry.detector(dparams.method).candidates is None:  # the appearance search
        return _appearance_frame(frame, landmarks, dparams, fparams, prior, lis)
    dets0, theta0 = detect(frame.image, dparams, what=f"frame {frame.id}", **frame_light(frame, dparams))
    extra = [] if lis is None else verify_detections(frame, lis[0])
    terrain = None if lis is None else window_terrain_once(frame, lis[0])
    best = None
    for k, off in enumerate(dparams.light_tries_deg):
        if off == 0.0:
            dets, theta = dets0, theta0
        else:
            theta = (theta0 + math.radians(off)) % (2.0 * math.pi)
            dets, theta = detect(frame.image, dparams, light_dir=theta, what=f"frame {frame.id}")
        if lis is None:
            fix = fix_frame(dets, landmarks, prior, frame.image.shape, fparams)
        else:
            voters = len(dets)
            dets = with_new(dets, extra, verify_detector_settings(lis[0].verify_detector))
            dets, fix = window_lost_in_space(frame, dets, landmarks, lis, fparams, voters, terrain)
        key = (fix.ok, len(fix.inliers) if fix.ok else 0, -fix.rms_px if fix.ok else 0.0, -k)
        if best is None or key > best[0]:
            best = (key, dets, theta, fix)
    _, dets, theta, fix = best
    return dets, theta, fix, prior


def window_lost_in_space(frame: Frame, dets, landmarks, lis, fparams: FixParams, voters: int, terrain=None):
    """(the detections the fix indexes, the fix) of a window lost in space (``lis``: its settings and pair
    index; ``voters``: the first detections, which may vote). With ``confirm="appearance"`` the candidates
    are confirmed by the appearance search (:func:`.appearance.confirmed_fix`, the ``nav/detector=appearance``
    settings; the light's image direction that its light model gives the window, standing in for the ephemeris
    and attitude a lander has): a confirmed fix indexes the search's detections, a refusal the detector's.
    ``terrain``: the terrain's places (:func:`window_terrain_once`), found once for all light tries."""
    params, index = lis
    shape, pixel_m = frame.image.shape, frame.georef.pixel_m
    heading = window_heading_deg(params)
    fix, cands = lost_in_space_search(dets, landmarks, shape, pixel_m, params, fparams, index, heading, voters)
    if not params.confirm:
        return dets, fix
    light, pole, app = confirmation_light(frame), frame.georef.pole, appearance_settings()
    found, fix = confirmed_fix(frame.image, pole, pixel_m, cands, landmarks, light, params, app, fparams, None, terrain)
    return (found, fix) if fix.ok else (dets, fix)


def window_terrain_once(frame: Frame, lis_params):
    """The terrain's places of a window lost in space (:func:`.appearance.window_terrain_places`, under the light
    its appearance settings give), found once whatever the light tries; None without a confirmation."""
    if not lis_params.confirm:
        return None
    light, georef = confirmation_light(frame), frame.georef
    return window_terrain_places(frame.image, georef.pole, georef.pixel_m, light, lis_params, appearance_settings())


def confirmation_light(frame: Frame) -> float:
    """The image direction (radians) the light travels along in a window, as the confirmation by appearance
    takes it: its settings' light model, standing in for the ephemeris and attitude a lander has."""
    return frame_light(frame, appearance_settings())["light_dir"]


@functools.lru_cache(maxsize=1)
def appearance_settings() -> DetectorSettings:
    """The ``nav/detector=appearance`` settings a confirmation by appearance searches with."""
    return compose_nav(["nav/detector=appearance"]).detector


def verify_detections(frame: Frame, lis_params) -> list:
    """The detections of ``lis_params.verify_detector`` (none when "") on a window, with that detector's own
    light model: those the first detector lacks (:func:`.classical.new_detections`) join the lost-in-space
    verification after its own (never the vote)."""
    vparams = verify_detector_settings(lis_params.verify_detector)
    if vparams is None:
        return []
    return detect(frame.image, vparams, what=f"frame {frame.id}", **frame_light(frame, vparams))[0]


# With no position prior, the appearance search starts from this detector's lost-in-space fix (the best
# lost-in-space detector on the south and the north, docs/navigation/fix.md).
LOST_IN_SPACE_FIRST_STAGE = "template"


def _appearance_frame(frame: Frame, landmarks, dparams: DetectorSettings, fparams: FixParams, prior: Georef, lis):
    """:func:`navigate_window` for ``nav.detector.method="appearance"`` (:mod:`.appearance`): the landmarks
    searched for under the prior, the light of the local model, then the same fix. Lost in space
    (``lis``): the prior is the :data:`LOST_IN_SPACE_FIRST_STAGE` detector's lost-in-space fix, and a frame
    it cannot fix is "no fix"."""
    if lis is not None:  # no prior: the template's lost-in-space fix becomes the search's prior
        first = compose_nav([f"nav/detector={LOST_IN_SPACE_FIRST_STAGE}"]).detector
        _, _, coarse, _ = navigate_window(frame, landmarks, first, fparams, lis=lis)
        if not coarse.ok:
            return [], math.nan, dataclasses.replace(coarse, reason=f"lost in space: {coarse.reason}"), prior
        prior = Georef.centred_on(frame.georef.pole, coarse.x_m, coarse.y_m, frame.image.shape, frame.georef.pixel_m)
    if dparams.light_scope != "local":
        raise UserError(f"nav.detector.light_scope={dparams.light_scope!r}: the appearance method needs 'local'")
    image = check_frame(frame.image, f"frame {frame.id}")
    alpha = frame_local_light(frame, dparams)
    refiner = lander_refiner(frame.georef.pole)
    dets, _ = window_detections(image, prior, landmarks, alpha, dparams, fparams, refiner)
    theta = frame_light(frame, dparams)["light_dir"]
    return dets, theta, fix_frame(dets, landmarks, prior, frame.image.shape, fparams), prior


def run_frame(
    frame: Frame,
    landmarks,
    dparams: DetectorSettings,
    fparams: FixParams,
    seed: int = 0,
    lis=None,
    prior_offset_km: float = PRIOR_OFFSET_KM,
    listed=None,
    patches=None,
) -> dict:
    """Detection, identification and fix of one frame (:func:`navigate_window`; ``lis``: no prior;
    ``prior_offset_km``: how far the prior is from the truth), scored against its truth
    (:func:`score_window`, with the catalogue ``listed``). ``patches`` (:class:`.patches.PatchParams`,
    appearance method with a prior): the frame is also navigated with its terrain patches alone
    (:func:`with_window_patches`)."""
    dets, theta, fix, prior = navigate_window(frame, landmarks, dparams, fparams, seed, lis, prior_offset_km)
    row = score_window(frame, landmarks, fparams, dets, theta, fix, listed)
    if patches is not None:
        row = with_window_patches(row, frame, prior, dparams, fparams, patches)
    return row


def score_window(frame: Frame, landmarks, fparams: FixParams, dets, theta: float, fix, listed=None) -> dict:
    """A frame's row: its detections ``dets`` (light direction ``theta``) and ``fix`` (:func:`navigate_window`)
    scored against the map's landmarks in view. ``listed``: a complete crater catalogue
    (``map.check.catalogue_craters``) the detections are also scored against (:func:`catalogue_fields`), a
    diagnostic beside the map's truth (a detection of a crater the map lacks is no landmark, but it is a
    crater)."""
    truth_idx = truth_in_frame(landmarks, frame.georef, frame.image.shape, min_d_km=fparams.min_landmark_km)
    matched = match_detections(dets, landmarks, truth_idx, frame.georef)
    # A detection that matches no landmark of the map >= min size but does match a smaller one is not a
    # false positive of the >= min-size population: count it apart.
    small_idx = truth_in_frame(landmarks, frame.georef, frame.image.shape)
    matched_any = match_detections(dets, landmarks, small_idx, frame.georef)
    row = {
        "id": frame.id,
        "split": frame.split,
        "sector": frame.sector,
        "light_azimuth_deg": None if math.isnan(theta) else round(math.degrees(theta), 1),
        "n_detections": len(dets),
        "truth": [int(i) for i in truth_idx],
        "truth_d_km": [landmarks[i].diameter_km for i in truth_idx],
        "det_r_km": [d.r * frame.georef.pixel_m / 1000.0 for d in dets],
        "matched": {int(k): int(v) for k, v in matched.items()},
        "matched_any": sorted(int(k) for k in matched_any),
        "n_headline_landmarks": int(sum(landmarks[i].diameter_km >= HEADLINE_MIN_D_KM for i in truth_idx)),
        "fix": fix.ok,
        "reason": fix.reason,
    }
    if listed is not None:
        row.update(catalogue_fields(frame, dets, listed))
    if fix.ok:
        tx, ty = frame.centre_xy
        row["error_km"] = float(ground_distance_km(fix.x_m, fix.y_m, tx, ty, frame.georef.pole))
        row["identified"] = len(fix.inliers)
        # Identification is correct when the fix's landmark is the detection's truth match.
        row["identified_correct"] = int(sum(matched.get(d) == lm for d, lm in fix.inliers))
    return row


def catalogue_fields(frame: Frame, dets, listed) -> dict:
    """The catalogue part of a frame's row: ``catalogue``, the indices into ``listed`` of the catalogued
    craters whose centre lies in the frame, ``catalogue_d_km`` their diameters, ``catalogue_found`` the
    positions among them that a detection matches and ``matched_catalogue`` those detections' indices (the
    map's matching rule, :func:`.protocol.match_detections`; scored by :func:`.protocol.catalogue_split`)."""
    listed_idx = truth_in_frame(listed, frame.georef, frame.image.shape)
    hits = match_detections(dets, listed, listed_idx, frame.georef)
    return {
        "catalogue": [int(i) for i in listed_idx],
        "catalogue_d_km": [listed[i].diameter_km for i in listed_idx],
        "catalogue_found": sorted(listed_idx.index(i) for i in hits.values()),
        "matched_catalogue": sorted(int(k) for k in hits),
    }


def window_patches_alone(frame: Frame, prior: Georef, dparams, fparams, patches):
    """(scores, patches, detections, fix) of the window navigated with its terrain patches alone
    (:func:`.appearance.window_patch_fix`) under ``prior`` and the light of the appearance method
    ``dparams``. A patch identification is correct when its detection lies within ``fix.inlier_px`` of
    where the true georeference places the patch's point."""
    if dparams.method != "appearance" or prior is None:
        raise UserError("terrain patches need the appearance method and a position prior (not lost in space)")
    image = check_frame(frame.image, f"frame {frame.id}")
    alpha = frame_local_light(frame, dparams)
    refiner = lander_refiner(frame.georef.pole)
    found, dets, fix = window_patch_fix(image, prior, alpha, dparams, fparams, refiner, patches)
    info: dict = {"n_patches": len(found), "n_detections": len(dets), "fix": fix.ok, "reason": fix.reason}
    if fix.ok:
        info["error_km"] = float(ground_distance_km(fix.x_m, fix.y_m, *frame.centre_xy, frame.georef.pole))
        info["identified"] = len(fix.inliers)
        info["identified_correct"] = patch_truth_correct(dets, found, fix.inliers, frame.georef, fparams.inlier_px)
    return info, found, dets, fix


def with_window_patches(row: dict, frame: Frame, prior: Georef, dparams, fparams, patches) -> dict:
    """``row`` with the window's terrain-patch navigation (:func:`window_patches_alone`, under the same
    prior and light) in ``row["patches_alone"]``, scored alone; a window its craters do not fix takes the
    patches' fix (``fix_source`` says which fixed it), as a lander would use them. The row's detection
    metrics stay the craters'."""
    info = window_patches_alone(frame, prior, dparams, fparams, patches)[0]
    out = {**row, "patches_alone": info, "fix_source": "craters" if row["fix"] else None}
    if not row["fix"] and info["fix"]:
        keys = ("error_km", "identified", "identified_correct")
        out.update(fix=True, reason="", fix_source="patches", **{k: info[k] for k in keys})
    return out


def navigate_windows(frames: list, per_window: Callable[[Frame], dict], desc: str, progress: bool) -> list[dict]:
    """``per_window`` of every frame, in order; ``progress``: the windows done, with rate and ETA, on stderr."""
    rows = []
    with Progress(len(frames), desc, "window", "auto" if progress else "off") as bar:
        for f in frames:
            rows.append(per_window(f))
            bar.update()
    return rows


def evaluate_split(
    split: str,
    landmarks,
    dparams,
    fparams,
    every: int = 1,
    progress: bool = False,
    pole: str = "south",
    lis_params=None,
    prior_offset_km: float = PRIOR_OFFSET_KM,
    listed=None,
    patches=None,
) -> tuple[dict, list[dict]]:
    """Metrics of one split of ``pole``'s windows ("all": every window, both splits), all windows and the
    headline windows, and the per-window rows. ``lis_params``: the lost-in-space fix with these
    :class:`.lost_in_space.LostInSpaceParams` (no position prior) instead of the prior-gated one;
    ``patches``: each window also navigated with its terrain patches (:func:`with_window_patches`)."""
    frames = windows(None if split == "all" else split, pole)[::every]
    if not frames:
        raise UserError(f"no {split} window in the {pole} mosaic (north windows are all test)")
    lis = None
    if lis_params is not None:
        lis = (lis_params, build_index(landmarks, lis_params))
    rows = navigate_windows(
        frames,
        lambda f: run_frame(
            f, landmarks, dparams, fparams, lis=lis, prior_offset_km=prior_offset_km, listed=listed, patches=patches
        ),
        f"nav-eval {pole} {split}",
        progress,
    )
    out = summarise_windows(rows)
    if patches is not None:  # where the craters cannot serve: fewer than the headline's landmarks in view
        out["few_landmarks"] = summarise([r for r in rows if r["n_headline_landmarks"] < HEADLINE_MIN_LANDMARKS])
    return out, rows


def summarise_windows(rows: list[dict]) -> dict:
    """The metrics of a split's window rows: all windows, and the headline windows (>= 3 landmarks of
    D >= 15 km in view)."""
    head = [r for r in rows if r["n_headline_landmarks"] >= HEADLINE_MIN_LANDMARKS]
    return {"all_windows": summarise(rows), "headline": summarise(head)}


def _row_md(name: str, s: dict) -> str:
    def f(x, fmt):
        return "-" if x is None else format(x, fmt)

    return (
        f"| {name} | {s['windows']} | {f(s.get('fix_rate'), '.3f')} | {f(s.get('median_error_km'), '.2f')} | "
        f"{f(s.get('p90_error_km'), '.2f')} | {f(s.get('false_fix_rate'), '.3f')} | "
        f"{f(s.get('identification_accuracy'), '.3f')} | {f(s.get('recall_15km'), '.3f')} | "
        f"{f(s.get('precision_15km'), '.3f')} |"
    )


def _patches_markdown(methods: dict) -> list[str]:
    """The terrain-patch table (``nav-eval --patches``): per split and window set, the patches alone and the
    craters with the patches where the craters give no fix."""
    lines = [
        "",
        "Terrain patches (fix rate, median and p90 error km, false fixes, identification; patches: alone; "
        "fallback: the craters' fix, else the patches'):",
        "",
        "| method | split | windows | n | patches alone | fallback | fixed by patches |",
        "|---|---|---|---|---|---|---|",
    ]

    def cell(s: dict) -> str:
        if s.get("fix_rate") is None:
            return "-"
        med, p90 = s.get("median_error_km"), s.get("p90_error_km")
        errors = "-" if med is None else f"{med:.2f} / {p90:.2f}"
        ident = s.get("identification_accuracy")
        return f"{s['fix_rate']:.3f}, {errors}, {s['false_fixes']}, {'-' if ident is None else f'{ident:.3f}'}"

    rows = 0
    for m, res in methods.items():
        for split, r in res["splits"].items():
            for name in ("headline", "all_windows", "few_landmarks"):
                s = r.get(name, {})
                if "patches_alone" not in s:
                    continue
                rows += 1
                lines.append(
                    f"| {m} | {split} | {name} | {s['windows']} | {cell(s['patches_alone'])} | {cell(s)} | "
                    f"{s['fixed_by_patches']} |"
                )
    return lines if rows else []


def results_markdown(results: dict) -> str:
    """The results tables of docs/navigation/overview.md (generated by ``crater-synth nav-eval``): every method on
    the same windows with the same matching, one table."""
    methods = results.get("methods") or {results.get("primary_method", "classical"): results}
    lines = [
        "| method | split (windows) | n | fix rate | median error km | p90 error km | false-fix rate | "
        "identification | recall D>=15 | precision D>=15 |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m, res in methods.items():
        for split, r in res["splits"].items():
            lines.append(f"| {m} " + _row_md(f"{split}, >= 3 landmarks D >= 15 km", r["headline"]))
            lines.append(f"| {m} " + _row_md(f"{split}, all windows", r["all_windows"]))
    lines += _patches_markdown(methods)
    lines += ["", "Detection by size bin (all windows; recall of map landmarks, precision of detections):", ""]
    lines.append("| method | split | bin km | recall | precision | truth | detections |")
    lines.append("|---|---|---|---|---|---|---|")
    for m, res in methods.items():
        for split, r in res["splits"].items():
            for b, v in r["all_windows"].get("by_size_km", {}).items():
                rec = "-" if v["recall"] is None else f"{v['recall']:.3f}"
                pre = "-" if v["precision"] is None else f"{v['precision']:.3f}"
                lines.append(f"| {m} | {split} | {b} | {rec} | {pre} | {v['n_truth']} | {v['n_detections']} |")
    cat = [
        (m, split, r["all_windows"]["against_catalogue"])
        for m, res in methods.items()
        for split, r in res["splits"].items()
        if "against_catalogue" in r["all_windows"]
    ]
    if cat:
        lines += ["", "Detections D >= 15 km against the complete crater catalogue as well (all windows):", ""]
        lines.append("| method | split | catalogue recall | precision (map or catalogue) | catalogued | detections |")
        lines.append("|---|---|---|---|---|---|")
        for m, split, c in cat:
            rec = "-" if c["recall_15km"] is None else f"{c['recall_15km']:.3f}"
            pre = "-" if c["precision_15km"] is None else f"{c['precision_15km']:.3f}"
            lines.append(f"| {m} | {split} | {rec} | {pre} | {c['n_catalogue_15km']} | {c['n_detections_15km']} |")
    return "\n".join(lines) + "\n"


def method_description(option: str, method: str) -> str:
    """The description of a ``nav/detector`` option: its detector's one line from the registry
    (:mod:`.detectors.registry`), naming the option when it is a second setting of that detector."""
    text = registry.detector(method).description
    return text if option == method else f"{text}; settings {option}"


PRIMARY_METHOD = "classical"  # the method of the top-level "detector"/"splits" entries of the results JSON


SPLITS_OF_POLE = {"south": ("validation", "test"), "north": ("test",)}
PATCHES_METHOD = "appearance+patches"  # nav-eval --patches nav/detector=appearance: its results' method key


def merge_results(path: Path, pole: str, results: dict) -> dict:
    """The results file's content with ``pole``'s results put in, the other entries kept: the south at the
    top level (the structure of earlier files; a south result it replaces moves to ``history``), the other
    poles under ``regions``; the rendered frames' ``synthetic`` entry and other regions are never dropped."""
    old = json.loads(path.read_text()) if path.exists() else {}
    if pole == "south":
        merged = {k: old[k] for k in ("synthetic", "history") if k in old}
        if "methods" in old:
            # A south result is never deleted: the one replaced moves to the history (e.g. the second
            # round's, with which the south test split was run once).
            replaced = {k: v for k, v in old.items() if k not in ("synthetic", "history", "regions")}
            merged["history"] = [*old.get("history", []), replaced]
        merged.update(results)
    else:
        merged = dict(old)
    regions = {k: v for k, v in old.get("regions", {}).items() if k != pole}
    if pole != "south":
        regions[pole] = results
    if "methods" in merged:
        regions["south"] = "the top level of this file"  # a pointer, not a second copy
    merged["regions"] = dict(sorted(regions.items()))
    return merged


def add_methods(path: Path, pole: str, results: dict) -> dict:
    """The results file's content with the methods of ``results`` added to (or replaced in) ``pole``'s
    entry, everything else kept; the protocol must be the entry's own."""
    old = json.loads(path.read_text()) if path.exists() else {}
    entry = old if pole == "south" else old.get("regions", {}).get(pole)
    if not isinstance(entry, dict) or "methods" not in entry:
        raise UserError(f"{path}: no {pole} result to add {sorted(results['methods'])} to (run nav-eval in full first)")
    mine, theirs = results["protocol"], entry.get("protocol", {})
    shared = (set(mine) & set(theirs)) - {"every"}  # keys added to the protocol since are not compared
    if any(mine[k] != theirs[k] for k in shared) or results["landmark_map"] != entry.get("landmark_map"):
        raise UserError(f"{path}: the {pole} entry was made with another protocol or map; rerun every method")
    entry["methods"] = {**entry["methods"], **results["methods"]}
    return old


def nav_eval_settings(overrides) -> dict:
    """The settings of each ``nav/detector`` option ``nav-eval`` runs, by option: the one the overrides
    select, else every option (one table); the other overrides apply to each."""
    chosen = [o.partition("=")[2] for o in overrides if o.partition("=")[0] == "nav/detector"]
    rest = [o for o in overrides if o.partition("=")[0] != "nav/detector"]
    options = chosen or detector_options()
    return {option: compose_nav([f"nav/detector={option}", *rest]) for option in options}


def nav_eval_protocol(pole: str, every: int, prior_offset_km: float, lost_in_space: bool, patch_params) -> dict:
    """The protocol entry of a ``nav-eval`` results file (what every method of the run shares)."""
    return {
        "pole": pole,
        "mosaic": f"{MOSAIC_PRODUCTS[pole]} (400 m/px, polar stereographic)",
        "split_rule": "45-degree longitude sectors; even validation, odd test; window inside one sector"
        if pole == "south"
        else "every window test (no setting chosen on this pole); window inside one 45-degree sector",
        "window_px": 512,
        "stride_px": 64,
        "windows_overlap": True,
        "prior_offset_km": prior_offset_km,
        "false_fix_km": FALSE_FIX_KM,
        "match": {"centre_within_d": MATCH_CENTRE_D, "diameter_within": MATCH_DIAMETER},
        "headline": f">= {HEADLINE_MIN_LANDMARKS} landmarks of D >= {HEADLINE_MIN_D_KM:g} km in view",
        "every": every,
        "position_prior": "none (lost in space)" if lost_in_space else f"truth + {prior_offset_km:g} km",
        "catalogue_diagnostic": f"{LU_SOURCE}: detections D >= 15 km also scored against it (against_catalogue)",
        **({"terrain_patches": dataclasses.asdict(patch_params)} if patch_params else {}),
    }


def nav_eval_method(option: str, nav, lis_params, splits, run_split) -> dict:
    """One method's entry of the results: its settings and, per split, ``run_split(split, nav)``."""
    dparams, fparams = nav.detector, nav.fix
    entry = {
        "detector": {"method": method_description(option, dparams.method), **dparams.as_dict()},
        "fix": {
            "method": "prior-gated identification + RANSAC 2-D similarity (orthographic nadir)",
            **fparams.as_dict(),
        },
        "splits": {},
    }
    if lis_params is not None:
        entry["fix"]["method"] = "lost in space: crater-pair votes over the map + RANSAC 2-D similarity"
        if nav.appearance:
            entry["fix"]["method"] += f" ({LOST_IN_SPACE_FIRST_STAGE}), then the appearance search around it"
        entry["lost_in_space"] = {"preset": nav.choices.get("lost_in_space") or "south-choice", **lis_params.as_dict()}
    for split in splits:
        entry["splits"][split] = run_split(split, nav)
    return entry


def write_nav_eval_results(out: Path, pole: str, results: dict, full: bool) -> None:
    """Write ``results`` to ``out``: a full run (the pole's splits, every window, no setting overridden) is
    merged into the file's entries (:func:`merge_results` when both the classical and the template detector
    ran, else :func:`add_methods`: a method run on its own joins the pole's entry); any other run replaces
    the file."""
    if not full:
        atomic_write_text(out, json.dumps(results, indent=1) + "\n")
        click.echo(f"wrote {out}", err=True)
        return
    merge = merge_results if {"classical", "template"} <= set(results["methods"]) else add_methods
    atomic_write_text(out, json.dumps(merge(out, pole, results), indent=1) + "\n")
    click.echo(f"wrote {out} ({pole}: {', '.join(results['methods'])})", err=True)


def nav_eval_request(every: int, prior_offset_km: float, lost_in_space: bool, patches: bool, overrides):
    """``nav-eval``'s options checked, and its settings composed: (settings per detector option, the
    lost-in-space settings or None, the terrain patches' settings or None)."""
    if every < 1:
        raise UserError(f"--every={every} must be >= 1")
    check_prior_offset_km(prior_offset_km)
    settings = nav_eval_settings(overrides)
    if any(o.startswith("nav.lost_in_space.") or o.startswith("nav/lost_in_space") for o in overrides):
        if not lost_in_space:
            raise UserError("nav.lost_in_space settings need --lost-in-space")
    lis_params = next(iter(settings.values())).lost_in_space if lost_in_space else None
    patch_params = None
    if patches:
        if tuple(settings) != ("appearance",) or lost_in_space:
            raise UserError("--patches needs nav/detector=appearance alone and a position prior (not --lost-in-space)")
        patch_params = PatchParams()
    return settings, lis_params, patch_params


def nav_eval_map(pole: str, map_path):
    """The landmark map ``nav-eval`` navigates against: ``--map`` or the pole's committed map."""
    landmarks, prov = read_map(map_path) if map_path else load_default_map(pole)
    if prov.get("pole", pole) != pole:
        raise UserError(f"--map {map_path}: a {prov.get('pole')} map, but --pole {pole}")
    return landmarks, prov


@click.command("nav-eval")
@click.option(
    "--pole",
    "--region",
    "pole",
    type=click.Choice(["south", "north"]),
    default="south",
    show_default=True,
    help="Mosaic whose windows are evaluated (north: all windows are test).",
)
@click.option(
    "--split",
    "splits",
    type=click.Choice(["validation", "test", "all"]),
    multiple=True,
    help="Default: both splits (south), test (north). 'all': every window of the pole in one row.",
)
@click.option("--every", type=int, default=1, show_default=True, help="Use every N-th window (quick looks).")
@click.option(
    "--lost-in-space",
    "--no-prior",
    "lost_in_space",
    is_flag=True,
    help="Identify with no position prior (crater-pair votes over the whole map, crater_synth.navigation.fix."
    "lost_in_space); settings nav.lost_in_space.<name>=<value>.",
)
@click.option(
    "--prior-offset-km",
    type=float,
    default=PRIOR_OFFSET_KM,
    show_default=True,
    help="How far the position prior is from the truth (seeded direction); the identification gate is "
    "nav.fix.prior_sigma_km. Results with another offset are not merged into a results file.",
)
@click.option(
    "--patches",
    is_flag=True,
    help="nav/detector=appearance: navigate each window with its terrain patches too (scored alone, and used "
    f"where the craters give no fix; docs/navigation/fix.md); recorded as the method {PATCHES_METHOD!r}.",
)
@click.option("--map", "map_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Landmark map.")
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Results JSON. A full run (the pole's splits, every window, no setting overridden) is merged into it "
    "(e.g. --out docs/results/navigation.json, the committed record); otherwise it is replaced. Default: none "
    "(the table only).",
)
@OVERRIDES
@user_errors
def nav_eval_command(pole, splits, every, lost_in_space, prior_offset_km, patches, map_path, out, overrides):
    """Real-window navigation metrics per split and detector setting: detection, identification, fix
    (docs/navigation/overview.md). Settings are Hydra overrides (docs/navigation/settings.md):
    `nav/detector=template` runs one detector setting (default: every option of nav/detector, one table),
    `nav.detector.threshold=0.8`, `nav.fix.min_inliers=4`, `nav.lost_in_space.gate_km=6`.

    Choose settings on south windows (the defaults were: the light model on the whole south mosaic,
    `--split all`, the other settings on `--split validation`); never on the north. Without `--split`, the
    pole's splits run (south: validation and test; north: test). The map is the pole's committed landmark
    map unless `--map` names one.
    """
    settings, lis_params, patch_params = nav_eval_request(every, prior_offset_km, lost_in_space, patches, overrides)
    options = tuple(settings)
    landmarks, prov = nav_eval_map(pole, map_path)
    listed = catalogue_craters(pole)
    splits = splits or SPLITS_OF_POLE[pole]
    if "validation" in splits and "validation" not in SPLITS_OF_POLE[pole]:
        raise UserError(f"--split validation: the {pole} windows are test only (docs/navigation/protocol.md)")
    results = {
        "protocol": nav_eval_protocol(pole, every, prior_offset_km, lost_in_space, patch_params),
        "landmark_map": {
            "dem_product": prov.get("dem_product"),
            "dem_sha256": prov.get("dem_sha256"),
            "landmarks": len(landmarks),
        },
        "targets": TARGETS,
        "primary_method": PRIMARY_METHOD if PRIMARY_METHOD in options else PATCHES_METHOD if patches else options[0],
        "methods": {},
    }

    def run_split(split: str, nav) -> dict:
        click.echo(f"{nav.choices['detector']}: {pole} {split}", err=True)
        summary, _ = evaluate_split(
            split,
            landmarks,
            nav.detector,
            nav.fix,
            every=every,
            progress=True,
            pole=pole,
            lis_params=lis_params,
            prior_offset_km=prior_offset_km,
            listed=listed,
            patches=patch_params,
        )
        return summary

    t0 = time.time()
    for option, nav in settings.items():
        entry = nav_eval_method(option, nav, lis_params, splits, run_split)
        if patch_params is not None:  # its own entry: the appearance search's record stays craters only
            entry["detector"]["method"] += "; terrain patches scored alone and used where the craters give no fix"
            option = PATCHES_METHOD
        results["methods"][option] = entry
    # The primary method also at the top level (the structure of earlier results files).
    primary = results["methods"][results["primary_method"]]
    results.update(detector=primary["detector"], fix=primary["fix"], splits=primary["splits"])
    results["seconds"] = round(time.time() - t0, 1)
    if out:
        settings_overridden = any(o.partition("=")[0] != "nav/detector" for o in overrides)
        full = set(splits) == set(SPLITS_OF_POLE[pole]) and every == 1 and not map_path and not lost_in_space
        full = full and prior_offset_km == PRIOR_OFFSET_KM and not settings_overridden
        write_nav_eval_results(out, pole, results, full)
    click.echo(results_markdown(results))
