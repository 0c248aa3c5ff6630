"""``python -m crater_synth.tools.detector_misses``: which catalogued craters a learned detector misses on the
south validation windows, split by whether the pole's DEM map also holds them, and write the table as JSON.

The catalogue (LU1319381) lists every crater its authors saw, degraded ones included; the landmark map holds
the craters that are closed depressions in the LOLA DEM (docs/navigation/map.md). A catalogued crater >= 15 km
counts as "in the map" when a map landmark lies within 0.25 D of it with a diameter within 25 % (the scoring's
own match rule), and then carries that landmark's depth / D. Recall is given for each part, by size and by
depth / D, for every catalogued crater and for those whose rim lies wholly inside the window. The detector
runs at ``model``/``threshold``/``variant`` as ``detector_choice`` runs it, on the south validation windows.
Nothing is chosen here. ``--pole north`` breaks down a frozen choice's north test instead: the model runs at
the threshold and variant a committed choice file froze for it (``--choice``, checked as ``detector_test``
checks it), on every north test window; it is that test's detections, split, not a new method.

    python -m crater_synth.tools.detector_misses --threshold 0.25 --every 2 \\
        --variant 'nav.detector.tta=4 nav.detector.half_octaves=true nav.detector.border_r=0' --out FILE
    python -m crater_synth.tools.detector_misses --pole north --choice CHOICE.json --out FILE
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from crater_core.schema import atomic_write_text
from crater_synth.errors import UserError
from crater_synth.navigation.protocol import MATCH_CENTRE_D, MATCH_DIAMETER
from crater_synth.navigation.windows.evaluate import (
    PRIOR_OFFSET_KM,
    catalogue_craters,
    evaluate_split,
    nav_eval_map,
    nav_eval_request,
)
from crater_synth.navigation.windows.mosaic import windows
from crater_synth.tools.detector_choice import POLE, SPLIT, command_line, detector_overrides, model_sha256
from crater_synth.tools.detector_test import frozen_choices

PROG = "python -m crater_synth.tools.detector_misses"
MIN_D_KM = 15.0
SIZE_BINS_KM = (15.0, 20.0, 30.0, 60.0, np.inf)
DEPTH_BINS_D = (0.0, 0.05, 0.1, 0.15, np.inf)


def map_match(listed, landmarks) -> tuple[np.ndarray, np.ndarray]:
    """(in map, the matched landmark's depth / D or NaN) of each of the catalogued craters ``listed``."""
    lx, ly, ld = (np.array([getattr(lm, k) for lm in landmarks]) for k in ("x_m", "y_m", "diameter_km"))
    depth = np.array([lm.depth_m for lm in landmarks]) / (1000.0 * ld)
    inside = np.zeros(len(listed), bool)
    dd = np.full(len(listed), np.nan)
    for k, c in enumerate(listed):
        dist = np.hypot(lx - c.x_m, ly - c.y_m) / (1000.0 * c.diameter_km)
        ok = (dist <= MATCH_CENTRE_D) & (np.abs(ld / c.diameter_km - 1.0) <= MATCH_DIAMETER)
        if ok.any():
            inside[k] = True
            dd[k] = depth[int(np.argmin(np.where(ok, dist, np.inf)))]
    return inside, dd


def crater_table(rows: list[dict], listed, split: str, pole: str, every: int) -> np.ndarray:
    """(catalogue index, found, D km, rim wholly inside) of every catalogued crater >= ``MIN_D_KM`` in view."""
    frames = {f.id: f for f in windows(split, pole)[::every]}
    out = []
    for r in rows:
        frame = frames[r["id"]]
        h, w = frame.image.shape
        found = {r["catalogue"][k] for k in r["catalogue_found"]}
        for i in r["catalogue"]:
            c = listed[i]
            if c.diameter_km < MIN_D_KM:
                continue
            u, v = (float(x[0]) for x in frame.georef.xy_to_uv(np.array([c.x_m]), np.array([c.y_m])))
            rad = c.diameter_km * 500.0 / frame.georef.pixel_m
            out.append((i, i in found, c.diameter_km, min(u, w - u, v, h - v) >= rad))
    return np.array(out, float).reshape(-1, 4)


def recall(found: np.ndarray, sel: np.ndarray) -> dict:
    n = int(sel.sum())
    return {"n": n, "recall": round(float(found[sel].mean()), 4) if n else None}


def binned(found: np.ndarray, part: np.ndarray, values: np.ndarray, edges) -> dict:
    """:func:`recall` of the craters of ``part`` in each [lo, hi) bin of ``values`` ("lo-hi", ">=lo" last)."""
    return {
        f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">={lo:g}": recall(found, part & (values >= lo) & (values < hi))
        for lo, hi in zip(edges[:-1], edges[1:])
    }


def tables(t: np.ndarray, listed, landmarks) -> dict:
    """Recall of the craters of :func:`crater_table` ``t``, in all, in the map and not (module docstring)."""
    found, d, whole = t[:, 1] == 1, t[:, 2], t[:, 3] == 1
    m, depth = map_match([listed[int(i)] for i in t[:, 0]], landmarks)
    out: dict = {"all": recall(found, np.ones(len(t), bool))}
    for name, part in (("in_map", m), ("not_in_map", ~m)):
        out[name] = recall(found, part) | {
            "rim_wholly_inside": recall(found, part & whole),
            "by_size_km": binned(found, part, d, SIZE_BINS_KM),
        }
    out["in_map"]["by_depth_d"] = binned(found, m, depth, DEPTH_BINS_D)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    ap.add_argument("--pole", choices=("south", "north"), default=POLE, help="south validation, or a frozen north test")
    ap.add_argument("--model", default="committed", help="a learned-detect model file (default: the committed one)")
    ap.add_argument("--threshold", type=float, help="the detector's heat threshold (south)")
    ap.add_argument("--variant", default="", help="more nav-eval overrides, one shell-quoted string (south)")
    ap.add_argument("--every", type=int, default=2, help="every Nth south validation window")
    ap.add_argument("--choice", type=Path, help="north: the committed detector_choice file that froze the model")
    ap.add_argument("--out", type=Path, required=True, help="JSON of the table")
    args = ap.parse_args(argv)
    try:
        if args.pole == "north":
            if args.choice is None:
                raise UserError("--pole north: give --choice, the committed choice file that froze the model")
            (chosen,) = frozen_choices(args.choice, [args.model])
            threshold, variant, split, every = chosen["threshold"], tuple(chosen.get("variant", ())), "test", 1
        else:
            if args.threshold is None:
                raise UserError("--threshold: required on the south validation windows")
            threshold, variant, split, every = args.threshold, tuple(shlex.split(args.variant)), SPLIT, args.every
        overrides = detector_overrides(args.model, threshold, variant)
        settings, _, _ = nav_eval_request(every, PRIOR_OFFSET_KM, False, False, overrides)
        nav = settings["learned-detect"]
        landmarks = nav_eval_map(args.pole, None)[0]
        listed = catalogue_craters(args.pole)
        t0 = time.perf_counter()
        _, rows = evaluate_split(split, landmarks, nav.detector, nav.fix, every=every, pole=args.pole, listed=listed)
        t = crater_table(rows, listed, split, args.pole, every)
        result = {
            "command": command_line(argv, PROG),
            "split": f"{args.pole} {split}, every {every}",
            "model": args.model,
            "model_sha256": model_sha256(args.model),
            "threshold": threshold,
            "variant": list(variant),
            "choice_file": str(args.choice) if args.choice else None,
            "min_diameter_km": MIN_D_KM,
            "in_map_rule": f"a map landmark within {MATCH_CENTRE_D} D, diameter within {MATCH_DIAMETER:.0%}",
            "seconds": round(time.perf_counter() - t0, 1),
            **tables(t, listed, landmarks),
        }
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    atomic_write_text(args.out, json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: result[k] for k in ("all", "in_map", "not_in_map")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
