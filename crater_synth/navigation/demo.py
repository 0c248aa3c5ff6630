"""``make navigate-demo``: a small end-to-end navigation run on the embedded data.

A few real south-mosaic windows of each split (fixed, spread over the sectors), the three detection methods
and the appearance search with their frozen settings, and the appearance search's terrain patches alone
(``patches``: no crater), the committed landmark map: per window and method an annotated PNG
(detections, identified landmarks, error arrow) and one table of the metrics over these windows, written
to ``OUT/table.md`` and printed, and the same per window and per method/split in ``OUT/navigation.json``
(:data:`DEMO_JSON`, read by ``crater-synth report`` from ``RUN_DIR/navigation/``). On the validation
windows alone, :data:`CATALOGUE_METHODS` are also scored against the crater catalogue LU1319381 at
D >= 15 km (the evaluation's ``against_catalogue`` rule, :func:`.protocol.catalogue_split`): a PNG per
window and method (catalogued craters found green, missed red, false detections orange) and the counts
under ``catalogue_detection``. Nothing heavy is built (no landmark map, no rendering). The numbers are a
smoke view of a handful of windows; the evaluation is ``crater-synth nav-eval``
(docs/navigation/commands.md).

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
from crater_synth.navigation.map.check import LU_SOURCE, catalogue_check, catalogue_craters
from crater_synth.navigation.map.landmarks import DATA_DIR, DEM_PRODUCTS, load_default_map
from crater_synth.navigation.protocol import (
    FALSE_FIX_KM,
    HEADLINE_MIN_D_KM,
    HEADLINE_MIN_LANDMARKS,
    MATCH_CENTRE_D,
    MATCH_DIAMETER,
    PRIOR_OFFSET_KM,
    catalogue_scores,
    catalogue_split,
    summarise,
)
from crater_synth.navigation.settings import compose_nav
from crater_synth.navigation.windows.evaluate import (
    navigate_window,
    prior_georef,
    results_markdown,
    score_window,
    window_patches_alone,
)
from crater_synth.navigation.windows.mosaic import windows
from crater_synth.navigation.windows.navigate import annotate, annotate_catalogue, catalogue_circles
from crater_synth.terrain.stack import open_dem_entry

DEMO_WINDOWS_PER_SECTOR = 1
# The per-window fields of navigation.json (crater_synth.navigation.windows.evaluate.run_frame's scalars).
WINDOW_FIELDS = ("id", "split", "sector", "light_azimuth_deg", "n_detections", "fix", "reason", "error_km")
# The detector settings scored against the crater catalogue: the learned network at its detection operating
# point and the template detector (docs/navigation/detectors.md).
CATALOGUE_METHODS = ("learned-detect", "template")
# Development data only: the south validation windows (the test windows are not looked at crater by crater).
CATALOGUE_POLE, CATALOGUE_SPLIT = "south", "validation"


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


def catalogue_entry(method: str, row: dict, png_name: str) -> dict:
    """One window of ``navigation.json``'s ``catalogue_detection``: the counts of the window's
    :func:`.protocol.catalogue_split` (a :func:`.evaluate.score_window` row with the catalogue), its recall
    and precision (:func:`.protocol.catalogue_scores` of the window alone) and the PNG's name."""
    split, scores = catalogue_split(row), catalogue_scores([row])
    return {
        "method": method,
        **{k: row[k] for k in ("id", "split", "sector")},
        **{k: len(split[k]) for k in ("found", "missed", "false")},
        "detections_15km": scores["n_detections_15km"],
        "recall": scores["recall_15km"],
        "precision": scores["precision_15km"],
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
    catalogue = ("catalogue", "catalogue_d_km", "catalogue_found", "matched_catalogue")  # no crater to score
    out = {k: v for k, v in row.items() if k not in (*keys, *catalogue, "fix_source", "patches_alone")}
    out.update(truth=[], truth_d_km=[], det_r_km=[], matched={}, matched_any=[], n_detections=scores["n_detections"])
    out.update(fix=scores["fix"], reason=scores["reason"], **{k: scores[k] for k in keys if k in scores})
    return out


def _demo_crater_methods(frames, landmarks, listed, out: Path, windows_out: list) -> tuple[dict, dict, dict]:
    """Every crater method on every window, each annotated into ``out`` and listed in ``windows_out``:
    (summary per method, the appearance search's row of each window, (row, detections) by (method, window
    id) of the validation windows)."""
    methods = {}
    appearance_rows = {}  # the appearance search's row of each window: the patches' rows start from it
    kept = {}
    for method in ("classical", "template", "learned", "appearance"):
        nav = compose_nav([f"nav/detector={method}"])
        dparams, fparams = nav.detector, nav.fix
        splits: dict = {}
        for f in frames:
            dets, theta, fix, prior = navigate_window(f, landmarks, dparams, fparams)
            # The catalogue scores the validation windows alone (CATALOGUE_SPLIT).
            row = score_window(f, landmarks, fparams, dets, theta, fix, listed if f.split == CATALOGUE_SPLIT else None)
            if method == "appearance":
                appearance_rows[f.id] = row
            if f.split == CATALOGUE_SPLIT:
                kept[method, f.id] = (row, dets)
            splits.setdefault(f.split, []).append(row)
            png = out / f"{f.id}_{method}.png"
            atomic_write_bytes(png, annotate(f.image, dets, landmarks, fix, prior, f.georef))
            err = f"{row['error_km']:.2f} km" if row["fix"] else f"no fix ({row['reason']})"
            click.echo(f"{method:9s} {f.split:10s} {f.id}: {row['n_detections']} detections, {err} -> {png}")
            windows_out.append(window_entry(method, row, png.name))
        methods[method] = _splits_summary(splits, summarise, HEADLINE_MIN_LANDMARKS)
    return methods, appearance_rows, kept


def _catalogue_window(f, method: str, landmarks, listed, kept: dict) -> tuple[dict, list]:
    """(row, detections) of ``method`` on window ``f`` with the catalogue: from ``kept`` when the crater
    methods ran it, else detected here."""
    if (method, f.id) in kept:
        return kept[method, f.id]
    nav = compose_nav([f"nav/detector={method}"])
    dets, theta, fix, _ = navigate_window(f, landmarks, nav.detector, nav.fix)
    return score_window(f, landmarks, nav.fix, dets, theta, fix, listed), dets


def demo_catalogue(frames, landmarks, listed, out: Path, kept: dict | None = None) -> dict:
    """:data:`CATALOGUE_METHODS` on the :data:`CATALOGUE_SPLIT` windows of ``frames`` against the crater
    catalogue ``listed`` (``map.check.catalogue_craters``) at D >= 15 km: a PNG per window and method in
    ``out`` and ``navigation.json``'s ``catalogue_detection`` (per window :func:`catalogue_entry`, per method
    :func:`.protocol.catalogue_scores` pooled). ``kept``: rows already scored (:func:`_demo_crater_methods`)."""
    entries, pooled = [], {}
    chosen = [f for f in frames if f.split == CATALOGUE_SPLIT and f.georef.pole == CATALOGUE_POLE]
    for method in CATALOGUE_METHODS:
        rows = []
        for f in chosen:
            row, dets = _catalogue_window(f, method, landmarks, listed, kept or {})
            entry = catalogue_entry(method, row, f"{f.id}_{method}_catalogue.png")
            title = f"{f.id} {method} against LU1319381, D >= {HEADLINE_MIN_D_KM:g} km: " + ", ".join(
                f"{k} {'-' if entry[k] is None else format(entry[k], '.2f')}" for k in ("recall", "precision")
            )
            atomic_write_bytes(
                out / entry["png"], annotate_catalogue(f.image, catalogue_circles(row, dets, listed, f.georef), title)
            )
            counts = ", ".join(f"{k} {entry[k]}" for k in ("found", "missed", "false"))
            click.echo(f"{method:14s} {f.id}: catalogue D >= {HEADLINE_MIN_D_KM:g} km {counts} -> {out / entry['png']}")
            rows.append(row)
            entries.append(entry)
        pooled[method] = catalogue_scores(rows)
    return {
        "source": LU_SOURCE,
        "pole": CATALOGUE_POLE,
        "split": CATALOGUE_SPLIT,
        "min_d_km": HEADLINE_MIN_D_KM,
        "match": {"centre_within_d": MATCH_CENTRE_D, "diameter_within": MATCH_DIAMETER},
        "methods": pooled,
        "windows": entries,
    }


def catalogue_markdown(cat: dict) -> str:
    """The catalogue counts of :func:`demo_catalogue` as a Markdown table (per window, then pooled)."""

    def f(x):
        return "-" if x is None else f"{x:.3f}"

    lines = [
        f"Detections against {cat['source']}, D >= {cat['min_d_km']:g} km ({cat['pole']} {cat['split']} windows):",
        "",
        "| method | window | found | missed | false | recall | precision |",
        "|---|---|---|---|---|---|---|",
    ]
    for w in cat["windows"]:
        counts = " | ".join(str(w[k]) for k in ("found", "missed", "false"))
        lines.append(f"| {w['method']} | {w['id']} | {counts} | {f(w['recall'])} | {f(w['precision'])} |")
    for m, s in cat["methods"].items():
        lines.append(f"| {m} | all | | | | {f(s['recall_15km'])} | {f(s['precision_15km'])} |")
    return "\n".join(lines) + "\n"


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
    listed = catalogue_craters("south")
    frames = demo_frames(per_sector)
    windows_out = []
    methods, appearance_rows, kept = _demo_crater_methods(frames, landmarks, listed, out, windows_out)
    methods["patches"] = _demo_patches_alone(frames, appearance_rows, out, windows_out)
    catalogue = demo_catalogue(frames, landmarks, listed, out, kept)
    map_check = _demo_map_check(landmarks)
    table = results_markdown({"methods": methods}) + "\n" + catalogue_markdown(catalogue)
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
        "catalogue_detection": catalogue,
        "seconds": round(time.time() - t0, 1),
    }
    atomic_write_text(out / DEMO_JSON, json.dumps(record, indent=1) + "\n")
    click.echo(table)
    click.echo(
        f"wrote {out}/table.md, {out}/{DEMO_JSON} and {len(windows_out) + len(catalogue['windows'])} annotated PNGs "
        f"in {time.time() - t0:.0f} s"
    )


if __name__ == "__main__":
    main()
