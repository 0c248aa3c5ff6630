"""``python -m crater_synth.tools.navigate_offgrid``: ``navigate``'s defaults on real mosaic windows placed off
the evaluation grid, for its false-fix rate (docs/navigation/fix.md, "No confident wrong fix").

``nav-eval`` measures each method on the split rule's grid of windows (512 px, stride 64) with the light
model pooled over the split's windows. A user runs ``navigate IMAGE --prior LAT,LON`` on one frame, with the
light estimated on that frame alone. This tool places ``--n`` windows of a pole's split at seeded random
pixel offsets (each wholly inside one sector of the split, as the grid's are), and navigates each exactly as
the command does (``navigate.navigate_map_window``'s detection and fix, its default detector and settings
plus any overrides), with the prior the true centre moved by 5 km in a seeded direction. It prints one
JSON object: fixes, false fixes (> 5 km off), errors, and per window the fix, its error and the reason.

    python -m crater_synth.tools.navigate_offgrid --pole south --split validation --n 120 --seed 1 [--out F]

South validation sectors choose; the north windows are a test: run them once, after the rule is frozen.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from crater_core.schema import atomic_write_text
from crater_synth.navigation.fix.solve import FALSE_FIX_KM
from crater_synth.navigation.georef import Frame, Georef, ground_distance_km, stereo_inverse
from crater_synth.navigation.map.landmarks import load_default_map
from crater_synth.navigation.navigate import WINDOW_DETECTOR, NavigateRequest, window_fix, window_prior
from crater_synth.navigation.settings import compose_nav
from crater_synth.navigation.windows.evaluate import prior_georef
from crater_synth.navigation.windows.mosaic import SPLITS, WINDOW_PX, load_mosaic_image, sector_of

MAX_DRAWS = 100_000  # placements tried before giving up (a split's sectors cover about half the mosaic)


def offgrid_windows(pole: str, split: str, n: int, seed: int, size: int = WINDOW_PX) -> list[Frame]:
    """``n`` windows of ``split`` at seeded random pixel offsets, each inside one sector of the split."""
    img, extent, pixel, _ = load_mosaic_image(pole)
    rng = np.random.default_rng(seed)
    frames: list[Frame] = []
    for _ in range(MAX_DRAWS):
        if len(frames) == n:
            return frames
        u0, v0 = (int(c) for c in rng.integers(0, img.shape[0] - size + 1, size=2))
        us = np.array([u0, u0 + size, u0, u0 + size], dtype=float)
        vs = np.array([v0, v0, v0 + size, v0 + size], dtype=float)
        x, y = us * pixel - extent, extent - vs * pixel
        s = sector_of(x, y, pole)
        if not (np.all(s == s[0]) and np.all(np.hypot(x, y) > 0)) or SPLITS[pole][int(s[0])] != split:
            continue
        geo = Georef(pole, -extent + u0 * pixel, extent - v0 * pixel, pixel)
        wid = f"{pole[0].upper()}{int(s[0])}r_{u0:04d}_{v0:04d}"
        frames.append(Frame(wid, split, int(s[0]), np.ascontiguousarray(img[v0 : v0 + size, u0 : u0 + size]), geo))
    raise ValueError(f"only {len(frames)} of {n} windows of {pole} {split} placed in {MAX_DRAWS} draws")


def navigate_offgrid(frames: list[Frame], overrides=(), seed: int = 0) -> dict:
    """Each frame navigated as ``navigate IMAGE --prior LAT,LON`` does it; the summary and the rows."""
    nav = compose_nav(list(overrides), defaults=[f"nav/detector={WINDOW_DETECTOR}"])
    maps = {pole: load_default_map(pole)[0] for pole in {f.georef.pole for f in frames}}  # read once per pole
    rows = []
    for frame in frames:
        pole, h, w = frame.georef.pole, *frame.image.shape[:2]
        landmarks = maps[pole]
        lat, lon = stereo_inverse(*prior_georef(frame, seed).uv_to_xy(w / 2, h / 2), pole)
        request = NavigateRequest(image=Path(frame.id), out=Path("-"), prior=f"{float(lat)},{float(lon)}", pole=pole)
        t0 = time.perf_counter()
        prior = window_prior(request, frame.image, frame.georef, landmarks, pole, frame.georef.pixel_m)
        _, _, fix, _, _ = window_fix(request, nav, frame.image, prior, landmarks, frame.georef.pixel_m)
        row = {"window": frame.id, "fix": fix.ok, "seconds": round(time.perf_counter() - t0, 2)}
        if fix.ok:
            error = ground_distance_km(fix.x_m, fix.y_m, *frame.georef.uv_to_xy(w / 2, h / 2), pole)
            row.update(error_km=round(float(error), 3), landmarks=len(fix.inliers), rms_px=round(fix.rms_px, 2))
        else:
            row["reason"] = fix.reason
        rows.append(row)
    errors = sorted(r["error_km"] for r in rows if r["fix"])
    false = [r for r in rows if r["fix"] and r["error_km"] > FALSE_FIX_KM]
    return {
        "windows": len(rows),
        "method": nav.choices["detector"],
        "overrides": list(overrides),
        "fixes": len(errors),
        "false_fixes": len(false),
        "false_fix_km": FALSE_FIX_KM,
        "fixes_over_2_km": sum(e > 2.0 for e in errors),
        "median_error_km": round(float(np.median(errors)), 3) if errors else None,
        "rows": rows,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m crater_synth.tools.navigate_offgrid", description=__doc__)
    ap.add_argument("--pole", choices=sorted(SPLITS), default="south")
    ap.add_argument("--split", default="validation")
    ap.add_argument("--n", type=int, default=120)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None, help="Write the JSON here too (atomically).")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides of the navigation settings, as navigate takes.")
    args = ap.parse_args(argv)
    if args.split not in set(SPLITS[args.pole].values()):
        ap.error(f"--split {args.split}: {args.pole} has {', '.join(sorted(set(SPLITS[args.pole].values())))}")
    frames = offgrid_windows(args.pole, args.split, args.n, args.seed)
    result = {"pole": args.pole, "split": args.split, "seed": args.seed, **navigate_offgrid(frames, args.overrides)}
    text = json.dumps(result, indent=1) + "\n"
    if args.out is not None:
        atomic_write_text(args.out, text)
    summary = {k: v for k, v in result.items() if k != "rows"}
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
