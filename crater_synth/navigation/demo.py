"""``make navigate-demo``: a small end-to-end navigation run on the embedded data.

A few real south-mosaic windows of each split (fixed, spread over the sectors), the three detection methods
and the appearance search with their frozen settings, and the appearance search's terrain patches alone
(``patches``: no crater), the committed landmark map: per window and method an annotated PNG
(detections, identified landmarks, error arrow) and one table of the metrics over these windows, written
to ``OUT/table.md`` and printed, and the same per window and per method/split in ``OUT/navigation.json``
(:data:`DEMO_JSON`, read by ``crater-synth report`` from ``RUN_DIR/navigation/``). Nothing heavy is
built (no landmark map, no rendering). The numbers are a smoke view of a handful of windows; the
evaluation is ``crater-synth nav-eval`` (docs/navigation/commands.md).

Run: ``python -m crater_synth.navigation.demo --out outputs/navigate-demo``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import click

from crater_core.schema import atomic_write_bytes, atomic_write_text
from crater_synth.cli_common import user_errors
from crater_synth.errors import UserError
from crater_synth.navigation import DEMO_JSON
from crater_synth.navigation.fix.patches import PatchParams
from crater_synth.navigation.map.check import catalogue_check
from crater_synth.navigation.map.landmarks import DATA_DIR, DEM_PRODUCTS, load_default_map
from crater_synth.navigation.protocol import FALSE_FIX_KM, HEADLINE_MIN_LANDMARKS, PRIOR_OFFSET_KM, summarise
from crater_synth.navigation.settings import compose_nav
from crater_synth.navigation.windows.evaluate import (
    navigate_window,
    prior_georef,
    results_markdown,
    run_frame,
    window_patches_alone,
)
from crater_synth.navigation.windows.mosaic import windows
from crater_synth.navigation.windows.navigate import annotate
from crater_synth.terrain.stack import open_dem_entry

DEMO_WINDOWS_PER_SECTOR = 1
# The per-window fields of navigation.json (crater_synth.navigation.windows.evaluate.run_frame's scalars).
WINDOW_FIELDS = ("id", "split", "sector", "light_azimuth_deg", "n_detections", "fix", "reason", "error_km")


def window_entry(method: str, row: dict, png_name: str) -> dict:
    """One window of ``navigation.json``: the scalars of a :func:`.evaluate.run_frame` row, the counts
    of map landmarks in view (>= the fix's minimum size), matched and identified, and the PNG's name."""
    return {
        "method": method,
        **{k: row.get(k) for k in WINDOW_FIELDS},
        "landmarks_in_view": len(row["truth"]),
        "headline_landmarks": row["n_headline_landmarks"],
        "matched": len(row["matched"]),
        "identified": row.get("identified", 0),
        "identified_correct": row.get("identified_correct", 0),
        "png": png_name,
    }


def demo_frames(per_sector: int = DEMO_WINDOWS_PER_SECTOR):
    """``per_sector`` windows of every sector (the middle ones of its list), both splits."""
    out = []
    all_frames = windows(None)
    for sector in range(8):
        fs = [f for f in all_frames if f.sector == sector]
        if not fs:
            continue
        step = max(1, len(fs) // (per_sector + 1))
        out += fs[step::step][:per_sector]
    return out


def _splits_summary(splits: dict, summarise, headline_min: int) -> dict:
    """A method's metrics per split: the headline windows and all windows."""
    return {
        "splits": {
            s: {
                "headline": summarise([r for r in rows if r["n_headline_landmarks"] >= headline_min]),
                "all_windows": summarise(rows),
            }
            for s, rows in splits.items()
        }
    }


def patch_row(row: dict, scores: dict) -> dict:
    """A window's :func:`.evaluate.run_frame` ``row`` turned into the row of its terrain patches alone
    (``scores``: :func:`.evaluate.window_patches_alone`'s): the patches' fix in place of the craters', no
    crater detection to score."""
    keys = ("error_km", "identified", "identified_correct")
    out = {k: v for k, v in row.items() if k not in (*keys, "fix_source", "patches_alone", "catalogue_d_km")}
    out.update(truth=[], truth_d_km=[], det_r_km=[], matched={}, matched_any=[], n_detections=scores["n_detections"])
    out.update(fix=scores["fix"], reason=scores["reason"], **{k: scores[k] for k in keys if k in scores})
    return out


def _demo_crater_methods(frames, landmarks, out: Path, windows_out: list) -> tuple[dict, dict]:
    """Every crater method on every window, each annotated into ``out`` and listed in ``windows_out``:
    (summary per method, the appearance search's row of each window)."""
    methods = {}
    appearance_rows = {}  # the appearance search's row of each window: the patches' rows start from it
    for method in ("classical", "template", "learned", "appearance"):
        nav = compose_nav([f"nav/detector={method}"])
        dparams, fparams = nav.detector, nav.fix
        splits: dict = {}
        for f in frames:
            row = run_frame(f, landmarks, dparams, fparams)
            if method == "appearance":
                appearance_rows[f.id] = row
            splits.setdefault(f.split, []).append(row)
            dets, _, fix, prior = navigate_window(f, landmarks, dparams, fparams)
            png = out / f"{f.id}_{method}.png"
            atomic_write_bytes(png, annotate(f.image, dets, landmarks, fix, prior, f.georef))
            err = f"{row['error_km']:.2f} km" if row["fix"] else f"no fix ({row['reason']})"
            click.echo(f"{method:9s} {f.split:10s} {f.id}: {row['n_detections']} detections, {err} -> {png}")
            windows_out.append(window_entry(method, row, png.name))
        methods[method] = _splits_summary(splits, summarise, HEADLINE_MIN_LANDMARKS)
    return methods, appearance_rows


def _demo_patches_alone(frames, appearance_rows: dict, out: Path, windows_out: list) -> dict:
    """The appearance search's terrain patches alone (no crater): the same windows, prior and light,
    annotated into ``out`` and listed in ``windows_out``; their summary."""
    splits: dict = {}
    nav = compose_nav(["nav/detector=appearance"])
    dparams, fparams = nav.detector, nav.fix
    for f in frames:
        prior = prior_georef(f, 0)  # run_frame's
        scores, patches, dets, fix = window_patches_alone(f, prior, dparams, fparams, PatchParams())
        row = patch_row(appearance_rows[f.id], scores)
        splits.setdefault(f.split, []).append(row)
        png = out / f"{f.id}_patches.png"
        atomic_write_bytes(png, annotate(f.image, dets, patches, fix, prior, f.georef))
        err = f"{row['error_km']:.2f} km" if row["fix"] else f"no fix ({row['reason']})"
        click.echo(f"{'patches':9s} {f.split:10s} {f.id}: {row['n_detections']} patches found, {err} -> {png}")
        windows_out.append({**window_entry("patches", row, png.name), "landmarks_in_view": len(patches)})
    return _splits_summary(splits, summarise, HEADLINE_MIN_LANDMARKS)


def _demo_map_check(landmarks) -> dict:
    """The map itself, against the complete crater catalogue (its own landmarks; a finer layer's apart)."""
    own = [lm for lm in landmarks if not lm.dem_product]
    return catalogue_check(own, "south", open_dem_entry(DEM_PRODUCTS["south"], DATA_DIR)[0])


@click.command("navigate-demo")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=Path("outputs/navigate-demo"))
@click.option("--per-sector", type=int, default=DEMO_WINDOWS_PER_SECTOR, show_default=True)
@user_errors
def main(out: Path, per_sector: int):
    """Annotated real windows and one table, every method (module docstring)."""
    if per_sector < 1:
        raise UserError(f"--per-sector={per_sector} must be >= 1")
    t0 = time.time()
    out.mkdir(parents=True, exist_ok=True)
    landmarks, _ = load_default_map("south")
    frames = demo_frames(per_sector)
    windows_out = []
    methods, appearance_rows = _demo_crater_methods(frames, landmarks, out, windows_out)
    methods["patches"] = _demo_patches_alone(frames, appearance_rows, out, windows_out)
    map_check = _demo_map_check(landmarks)
    table = results_markdown({"methods": methods})
    head = f"Demo: {len(frames)} real south-mosaic windows ({per_sector} per sector), {len(methods)} methods.\n\n"
    atomic_write_text(out / "table.md", head + table)
    record = {
        "kind": "crater-synth navigate-demo",
        "schema_version": 1,
        "per_sector": per_sector,
        "windows_per_method": len(frames),
        "min_landmark_km": compose_nav(["nav/detector=appearance"]).fix.min_landmark_km,
        "headline_min_landmarks": HEADLINE_MIN_LANDMARKS,
        "prior_offset_km": PRIOR_OFFSET_KM,
        "false_fix_km": FALSE_FIX_KM,
        "methods": methods,
        "map_check": map_check,
        "windows": windows_out,
        "seconds": round(time.time() - t0, 1),
    }
    atomic_write_text(out / DEMO_JSON, json.dumps(record, indent=1) + "\n")
    click.echo(table)
    click.echo(
        f"wrote {out}/table.md, {out}/{DEMO_JSON} and {len(methods) * len(frames)} annotated PNGs "
        f"in {time.time() - t0:.0f} s"
    )


if __name__ == "__main__":
    main()
