"""``python -m crater_synth.tools.detector_holdout``: score detector models on a detection set's held-out
fields, by the frame's off-nadir angle, and write the table as JSON.

The synthetic side of the oblique-view lever: a model trained on nadir frames only and one trained on every
view are scored on the same held-out fields (the last 10 % of the set's fields, never trained on by either;
``--held-out-share 1`` scores every field of a folder that holds only a set's held-out fields, rendered alone
with ``detection-frames --start``), frame by frame against their exact labels. Recall counts labelled rims
that span at least ``--min-span-px`` (10 px: a rim radius of 5 px), precision the detections of that size;
occluded rims and rims lit on less than 5 % of their length are neither (the training's rule). Each model runs
at the hold-out's scoring settings (no rim fit) and ``--threshold``. Recall is also split by four properties
of the counted labels (``recall_by``, in all and in each off-nadir bin; :data:`LABEL_SPLITS`): the degradation
(0 fresh .. 1 ghost, :class:`crater_core.procedural.Crater`), the rim's semi-major axis in pixels, its axis
ratio b/a (foreshortening) and its lit-rim fraction: which rims a model misses. ``--ground-view on|both``
searches each frame at least ``--ground-view-from`` degrees off nadir on the ground, as lost in space on
rendered frames does (:mod:`crater_synth.navigation.rendered.ground_view`; both: each model as the frame is
and so). ``--verifier V.pt`` runs every learned model once more with that second stage
(``nav.detector.verifier``; its candidates at ``--threshold``, kept at ``--verify-threshold`` of
``--verify-score``). Nothing real is read.

    python -m crater_synth.tools.detector_holdout SET --model A.pt --model fcos:B.pt --threshold 0.15 \\
        --out holdout.json
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from crater_core.schema import atomic_write_text
from crater_core.typed_config import SettingsError
from crater_synth.errors import UserError
from crater_synth.navigation.detectors import registry
from crater_synth.navigation.detectors.learned import VERIFY_SCORES
from crater_synth.navigation.rendered.detector_train import (
    HOLDOUT_FIELD_SHARE,
    architecture,
    detect_in_frame,
    detection_set_records,
    frame_matches,
)
from crater_synth.navigation.rendered.ground_view import detect_on_ground
from crater_synth.navigation.rendered.training_rows import off_nadir_deg
from crater_synth.tools.detector_choice import command_line, f1, model_option, model_sha256

PROG = "python -m crater_synth.tools.detector_holdout"
DEFAULT_BINS = (0.0, 1.0, 15.0, 30.0, 46.0)  # nadir; 1-15; 15-30; 30-45 degrees off nadir (the oblique band)
# The ground view serves frames at least this far off nadir (degrees). Chosen on the highland set's
# validation fields (docs/history.md): it gains F1 at 30-45 degrees and loses it nearer nadir, where the
# resampling and the fill of the east-north grid cost more precision than the foreshortening costs recall.
GROUND_VIEW_FROM_DEG = 30.0
# Label properties recall is split by: name -> (the label's value, bin edges; the last bin closed, values
# beyond the edges in the end bins). A label without the property (a set whose labels lack the field) is
# in none of its bins.
LABEL_SPLITS = {
    "degradation": (lambda lb: lb.get("degradation"), (0.0, 0.25, 0.5, 0.75, 1.0)),  # detectable() stops at 0.9
    "rim_radius_px": (lambda lb: lb["ellipse"]["a"], (5.0, 8.0, 12.0, 20.0, 40.0, np.inf)),
    "axis_ratio": (lambda lb: lb["ellipse"]["b"] / lb["ellipse"]["a"], (0.0, 0.7, 0.85, 0.95, 1.0)),
    "lit_rim": (lambda lb: lb.get("lit_rim_fraction"), (0.0, 0.25, 0.5, 0.75, 1.0)),
}


def off_nadir_bin(angle: float, edges) -> str | None:
    for lo, hi in zip(edges[:-1], edges[1:]):
        if lo <= angle < hi:
            return f"{lo:g}-{hi:g}"
    return None


def value_bin(value, edges) -> int:
    """The index of the bin of ``edges`` holding ``value`` (the last bin closed, values beyond the edges
    in the end bins); -1 for a missing value."""
    if value is None or not np.isfinite(value):
        return -1
    return int(np.clip(np.searchsorted(edges, value, side="right") - 1, 0, len(edges) - 2))


def _bin_name(lo: float, hi: float) -> str:
    return f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">={lo:g}"


def detector_settings(pairs: list[str]) -> dict:
    """``--set KEY=VALUE`` pairs as detector settings, each value read as YAML (``1``, ``3.0``, ``true``)."""
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise UserError(f"--set {pair!r}: not KEY=VALUE")
        out[key] = yaml.safe_load(value)
    return out


def finder(ground_view_from_deg: float | None):
    """What finds a frame's craters for :func:`frame_matches`: the detector on the frame as it is
    (:func:`detect_in_frame`), or, from ``ground_view_from_deg`` off nadir, on the frame's ground view
    (:func:`crater_synth.navigation.rendered.ground_view.detect_on_ground`, the view's range)."""
    if ground_view_from_deg is None:
        return detect_in_frame

    def find(image, row, params):
        if off_nadir_deg(row) < ground_view_from_deg:
            return detect_in_frame(image, row, params)
        return detect_on_ground(image, row, float(row["view"]["range_m"]), params, what=row["rel_path"])

    return find


def score_model(
    records, params, min_r: float, edges, splits=LABEL_SPLITS, ground_view_from_deg: float | None = None
) -> dict:
    """Recall and precision of one model over ``records``, in all and by off-nadir bin, each with its recall
    by the bins of each label property of ``splits`` (``recall_by``: labels and recall per bin);
    ``ground_view_from_deg``: frames that far off nadir searched on the ground (:func:`finder`)."""
    sums: dict[str, np.ndarray] = {}
    by: dict[tuple[str, str], np.ndarray] = {}  # (off-nadir key, property) -> (bins, 2): labels counted, found
    find = finder(ground_view_from_deg)
    for image, row in records:
        labels, counted, found, tp, n_det = frame_matches(image, row, params, 0.0, min_r, skip_hidden=True, find=find)
        per_split = {}
        for name, (value, split_edges) in splits.items():
            n_bins = len(split_edges) - 1
            bins = np.array([value_bin(value(lb), split_edges) for lb in labels], int)
            known = bins >= 0
            per_split[name] = np.stack(
                [
                    np.bincount(bins[counted & known], minlength=n_bins),
                    np.bincount(bins[found & known], minlength=n_bins),
                ],
                1,
            )
        for key in ("all", off_nadir_bin(off_nadir_deg(row), edges)):
            if key is None:
                continue
            sums[key] = sums.get(key, np.zeros(5, int)) + np.r_[found.sum(), counted.sum(), tp, n_det, 1]
            for name, counts in per_split.items():
                by[key, name] = by.get((key, name), 0) + counts
    out = {}
    for key, (n_found, n_lab, tp, n_det, frames) in sums.items():
        recall = round(n_found / n_lab, 4) if n_lab else None
        precision = round(tp / n_det, 4) if n_det else None
        out[key] = {
            "frames": int(frames),
            "recall": recall,
            "precision": precision,
            "f1": f1(precision, recall),
            "labels": int(n_lab),
            "recall_by": {
                name: {
                    _bin_name(lo, hi): {"labels": int(n), "recall": round(k / n, 4) if n else None}
                    for lo, hi, (n, k) in zip(split_edges[:-1], split_edges[1:], by[key, name])
                }
                for name, (_, split_edges) in splits.items()
            },
        }
    return out


def model_runs(model: str, args, settings: dict, hold: list, views) -> list[dict]:
    """One model's runs: as it is and with each ``--verifier``, each with and without the ground view as
    ``views`` asks, scored on ``hold``."""
    option, path = model_option(model)
    plain = architecture("fcos" if option == "fcos" else "centernet")[2](path)
    try:
        plain = dataclasses.replace(plain, threshold=args.threshold, **settings)
    except (TypeError, SettingsError) as e:  # a key the detector has not, or a value it refuses
        raise UserError(f"--set {' '.join(args.settings)}: {e}") from None
    verify = {"verify_threshold": args.verify_threshold, "verify_score": args.verify_score}
    verifiers = args.verifier if option != "fcos" else []
    stages = [("", plain)] + [(v, dataclasses.replace(plain, verifier=v, **verify)) for v in verifiers]
    model_sha = model_sha256(model)
    runs = []
    for (verifier, params), ground_from in itertools.product(stages, views):
        t0 = time.perf_counter()
        scores = score_model(hold, params, 0.5 * args.min_span_px, DEFAULT_BINS, ground_view_from_deg=ground_from)
        seconds = round(time.perf_counter() - t0, 1)
        second = {"verifier": verifier, "verifier_sha256": model_sha256(verifier)} if verifier else {}
        first = {"model": model, "model_sha256": model_sha, "ground_view_from_deg": ground_from}
        runs.append(first | second | {"seconds": seconds} | scores)
        print(f"{model} {verifier} ground view from {ground_from}: {json.dumps(scores['all'])}", flush=True)
    registry.detector(plain.method).load_model.cache_clear()
    return runs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path, help="a detection set (crater-synth detection-frames)")
    ap.add_argument("--model", action="append", required=True, help="a model file; fcos:PATH for FCOS (repeatable)")
    ap.add_argument("--threshold", type=float, default=0.15, help="detection threshold of every model")
    ap.add_argument("--min-span-px", type=float, default=10.0, help="rims spanning at least this many pixels")
    ap.add_argument("--every", type=int, default=1, help="every Nth held-out frame")
    ap.add_argument("--verifier", action="append", default=[], help="a second-stage model file (repeatable)")
    ap.add_argument("--verify-threshold", type=float, default=0.5, help="the verifier score a candidate needs")
    ap.add_argument("--verify-score", choices=VERIFY_SCORES, default="verifier", help="the verifier's score rule")
    ap.add_argument(
        "--ground-view",
        choices=("off", "on", "both"),
        default="off",
        help="search oblique frames on the ground (crater_synth.navigation.rendered.ground_view): on, off or both",
    )
    ap.add_argument(
        "--ground-view-from",
        type=float,
        default=GROUND_VIEW_FROM_DEG,
        help="the ground view serves frames at least this many degrees off nadir",
    )
    ap.add_argument(
        "--set",
        dest="settings",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a detector setting for every model (nav.detector's keys, e.g. upsample_levels=1); repeatable",
    )
    ap.add_argument(
        "--held-out-share",
        type=float,
        default=HOLDOUT_FIELD_SHARE,
        help="the share of the set's last fields scored (1: every field, a hold-out rendered alone with --start)",
    )
    ap.add_argument("--out", type=Path, required=True, help="JSON of the table")
    args = ap.parse_args(argv)
    if not 0.0 < args.held_out_share <= 1.0:
        ap.error(f"--held-out-share {args.held_out_share:g}: must lie in (0, 1]")
    views = {"off": (None,), "on": (args.ground_view_from,), "both": (None, args.ground_view_from)}[args.ground_view]
    try:
        settings = detector_settings(args.settings)
        _, hold, what = detection_set_records(args.folder, args.held_out_share, training=False)
        hold = hold[:: max(1, args.every)]
        for path in [*(model_option(m)[1] for m in args.model), *args.verifier]:
            if not Path(path).is_file():
                raise UserError(f"{path}: no such model file")
        runs = [run for model in args.model for run in model_runs(model, args, settings, hold, views)]
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    result = {
        "command": command_line(argv, PROG),
        "set": {"folder": str(args.folder), "holdout_fields": what["holdout_fields"], "recipe": what["recipe"]},
        "threshold": args.threshold,
        "settings": settings,
        "verify": {"threshold": args.verify_threshold, "score": args.verify_score} if args.verifier else None,
        "min_span_px": args.min_span_px,
        "off_nadir_bins_deg": list(DEFAULT_BINS),
        "recall_by_bins": {
            name: [_bin_name(lo, hi) for lo, hi in zip(e[:-1], e[1:])] for name, (_, e) in LABEL_SPLITS.items()
        },
        "runs": runs,
    }
    atomic_write_text(args.out, json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
