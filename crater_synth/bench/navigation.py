"""``crater-synth bench --part navigation``: detection, identification and fix per second on a 1024 x 1024
real mosaic window, every method in the same run (the classical baseline first), timed on the very
functions ``nav-eval`` runs (:mod:`crater_synth.navigation.windows.evaluate`); and what ``crater-synth
navigate`` costs a user per window, a folder in one process against one process per window
(:func:`bench_navigate_folder`)."""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from crater_synth.bench.detect import run_command
from crater_synth.navigation.detectors.classical import detect
from crater_synth.navigation.detectors.registry import detectors
from crater_synth.navigation.fix.patches import PatchParams
from crater_synth.navigation.fix.solve import FixParams, fix_frame, identify, ransac_similarity
from crater_synth.navigation.georef import Frame, Georef
from crater_synth.navigation.map.landmarks import load_default_map
from crater_synth.navigation.settings import compose_nav
from crater_synth.navigation.windows.appearance import lander_refiner, window_detections, window_patch_fix
from crater_synth.navigation.windows.evaluate import prior_georef
from crater_synth.navigation.windows.light import frame_local_light
from crater_synth.navigation.windows.mosaic import load_mosaic_image, sector_of, windows
from crater_synth.navigation.windows.navigate import write_window

NAVIGATE_WINDOWS = 4  # south validation windows (development data) of the navigate comparison
NAVIGATE_EVERY = 30  # every this-th of them: spread over the sectors


def image_detectors() -> list[str]:
    """The registry's image detectors (:mod:`crater_synth.navigation.detectors.registry`), by name: every
    one but the appearance search, which needs the map and a prior."""
    return [name for name, entry in detectors().items() if entry.candidates is not None]


def bench_navigation(repeats: int = 3) -> dict:
    """Frames/s of detection, identification and fix, each timed apart, on one 1024 x 1024 mosaic window
    (the top-left corner of the south mosaic), for every method in the same run (the classical baseline,
    the template detector, the learned detector, and the appearance search: :func:`_bench_appearance`):
    median of ``repeats`` runs after one warm-up. The light direction is estimated on the frame where a
    detector uses it (its cost is part of detection)."""

    landmarks, _ = load_default_map("south")
    img, extent, pixel, _ = load_mosaic_image("south")
    frame = Frame(
        "bench", "bench", -1, np.ascontiguousarray(img[:1024, :1024]), Georef("south", -extent, extent, pixel)
    )
    prior = prior_georef(frame, 0)
    fparams = FixParams()
    lm_xy = np.array([[lm.x_m for lm in landmarks], [lm.y_m for lm in landmarks]]).T
    out: dict = {"frame_px": 1024, "repeats": repeats}
    for method in image_detectors():
        dparams = dataclasses.replace(compose_nav([f"nav/detector={method}"]).detector, light_scope="frame")
        t_det, t_id, t_fix = [], [], []
        fix = None
        for k in range(repeats + 1):
            t0 = time.perf_counter()
            dets, _ = detect(frame.image, dparams)
            t1 = time.perf_counter()
            pairs, _ = identify(dets, landmarks, prior, frame.image.shape, fparams)
            t2 = time.perf_counter()
            det_uv = np.array([[d.u, -d.v] for d in dets], float).reshape(-1, 2)
            ransac_similarity(det_uv, np.array([d.r for d in dets]), lm_xy, pairs, complex(pixel, 0.0), fparams)
            t3 = time.perf_counter()
            fix = fix_frame(dets, landmarks, prior, frame.image.shape, fparams)
            if k:
                t_det.append(t1 - t0)
                t_id.append(t2 - t1)
                t_fix.append(t3 - t2)
        det_s, id_s, fix_s = (float(np.median(t)) for t in (t_det, t_id, t_fix))
        total = det_s + id_s + fix_s
        out[method] = {
            "detection_s": round(det_s, 3),
            "identification_s": round(id_s, 4),
            "fix_s": round(fix_s, 4),
            "seconds_per_frame": round(total, 3),
            "frames_per_s": round(1.0 / total, 3),
            "detections": len(dets),
            "fix": bool(fix.ok) if fix else False,
        }
    out["appearance"] = _bench_appearance(frame, landmarks, prior, fparams, repeats)
    with tempfile.TemporaryDirectory(prefix="bench_navigate_") as work:
        out["navigate_folder"] = bench_navigate_folder(Path(work))
    return out


def bench_navigate_folder(work: Path) -> dict:
    """``crater-synth navigate`` on :data:`NAVIGATE_WINDOWS` south validation windows (default detector),
    each command a child process timed from outside (start-up included): the folder in one process (no
    PNG, and with ``--png``) against the command once per window (which always draws its PNG), in the
    same run; seconds per window each way, and inside the folder run (its summary: reading, detection, fix,
    writing)."""
    src = work / "windows"
    src.mkdir(parents=True)
    for f in windows("validation", "south")[::NAVIGATE_EVERY][:NAVIGATE_WINDOWS]:
        write_window(src / f"{f.id}.png", f)
    images = sorted(src.glob("*.png"))
    n = len(images)
    load = [round(x, 2) for x in os.getloadavg()]  # the machine may be shared: the timings are this run's
    folder = run_command(work / "log_folder", "navigate", src, "--out", work / "out")
    drawn = run_command(work / "log_folder_png", "navigate", src, "--out", work / "out_png", "--png")
    single = [run_command(work / f"log_{p.stem}", "navigate", p, "--out", work / f"{p.stem}.nav.png") for p in images]
    summary = json.loads((work / "out" / "summary.json").read_text())
    per_image_s = sum(r["wall_s"] for r in single) / n
    return {
        "windows": n,
        "load_average": load,
        "fixes": summary["fixes"],
        "folder_s_per_window": round(folder["wall_s"] / n, 3),
        "folder_png_s_per_window": round(drawn["wall_s"] / n, 3),
        "inside_s_per_window": round(summary["seconds"] / n, 3),
        "process_per_window_s": round(per_image_s, 3),
        "speedup": round(per_image_s * n / folder["wall_s"], 2),
        "peak_rss_mb": folder["peak_rss_mb"],
    }


def _bench_appearance(frame: Frame, landmarks, prior: Georef, fparams: FixParams, repeats: int) -> dict:
    """The appearance search's part of :func:`bench_navigation`: the search (prediction and NCC of every
    landmark the prior places in the frame; its light from the local model of the frame's quadrant, pooled
    once before timing) in place of detection, then the same identification and fix; and the same window
    navigated with its terrain patches alone (``patches``, with ``fallback_worst_s``: a window its craters
    do not fix pays the crater search and then its patches). Timed twice: "cold",
    every landmark's window read from the DEM and its horizon computed in the frame, and "warm", those
    windows kept from an earlier frame (:meth:`.refine.Refiner.terrain`), as on a descent whose
    landmarks were prepared for its Sun before it began. Cold once more with the new windows computed in two
    worker processes while the search correlates (``cold_2_workers``, :meth:`.refine.Refiner.prepare`;
    the same detections)."""

    dparams = compose_nav(["nav/detector=appearance"]).detector
    frame = dataclasses.replace(frame, sector=int(sector_of(*frame.centre_xy, frame.georef.pole)))
    alpha = frame_local_light(frame, dparams)
    out: dict = {}
    found: dict = {}
    for mode in ("cold", "warm", "cold_2_workers"):
        refiner = lander_refiner(frame.georef.pole, workers=2 if mode == "cold_2_workers" else 1)
        t_search, t_fix = [], []
        for k in range(repeats + 1):
            if mode.startswith("cold"):
                refiner.clear_terrains()
            t0 = time.perf_counter()
            dets, _ = window_detections(frame.image, prior, landmarks, alpha, dparams, fparams, refiner)
            t1 = time.perf_counter()
            fix = fix_frame(dets, landmarks, prior, frame.image.shape, fparams)
            if k:
                t_search.append(t1 - t0)
                t_fix.append(time.perf_counter() - t1)
        search_s, fix_s = float(np.median(t_search)), float(np.median(t_fix))
        out[mode] = {
            "search_s": round(search_s, 3),
            "identification_and_fix_s": round(fix_s, 4),
            "seconds_per_frame": round(search_s + fix_s, 3),
            "frames_per_s": round(1.0 / (search_s + fix_s), 3),
            "detections": len(dets),
            "fix": bool(fix.ok),
        }
        found[mode] = [(d.u, d.v, d.r, d.score) for d in dets]
    out["cold_2_workers"]["same_detections_as_cold"] = found["cold_2_workers"] == found["cold"]
    # A window its craters do not fix: the failed crater search, then its patches (the default fallback).
    for name, search, workers in (("patches", "cold", 1), ("patches_2_workers", "cold_2_workers", 2)):
        out[name] = _bench_window_patches(frame, prior, alpha, dparams, fparams, repeats, workers)
        out[name]["fallback_worst_s"] = round(out[search]["search_s"] + out[name]["seconds_per_frame"], 3)
    return out


def _bench_window_patches(frame: Frame, prior: Georef, alpha: float, dparams, fparams, repeats: int, workers: int):
    """The window navigated with its terrain patches alone (:func:`.windows.appearance.window_patch_fix`: 16
    new windows, none kept from an earlier frame, as every frame's patches lie elsewhere), their windows
    computed in ``workers`` processes."""

    refiner = lander_refiner(frame.georef.pole, workers=workers)
    times = []
    for k in range(repeats + 1):
        refiner.clear_terrains()
        t0 = time.perf_counter()
        patches, dets, fix = window_patch_fix(frame.image, prior, alpha, dparams, fparams, refiner, PatchParams())
        if k:
            times.append(time.perf_counter() - t0)
    seconds = float(np.median(times))
    return {
        "seconds_per_frame": round(seconds, 3),
        "frames_per_s": round(1.0 / seconds, 3),
        "patches": len(patches),
        "detections": len(dets),
        "fix": bool(fix.ok),
    }
