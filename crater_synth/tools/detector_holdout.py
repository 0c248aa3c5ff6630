"""``python -m crater_synth.tools.detector_holdout``: score detector models on a detection set's held-out
fields, by the frame's off-nadir angle, and write the table as JSON.

The synthetic side of the oblique-view lever: a model trained on nadir frames only and one trained on
every view are scored on the same held-out fields (the last 10 % of the set's fields, never trained on by
either), frame by frame against their exact labels. Recall counts labelled rims that span at least
``--min-span-px`` (10 px: a rim radius of 5 px), precision the detections of that size; occluded rims and
rims lit on less than 5 % of their length are neither (the training's rule). Each model runs at the
hold-out's scoring settings (no rim fit) and ``--threshold``. Recall is also split by the label's
degradation (0 fresh .. 1 ghost, :class:`crater_core.procedural.Crater`; ``by_degradation``, in all and in
each off-nadir bin): which rims a model misses, the fresh or the worn. ``--verifier V.pt`` runs every
learned model
once more with that second stage (``nav.detector.verifier``; its candidates at ``--threshold``, kept at
``--verify-threshold`` of ``--verify-score``). Nothing real is read.

    python -m crater_synth.tools.detector_holdout SET --model A.pt --model fcos:B.pt --threshold 0.15 \\
        --out holdout.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from crater_core.schema import atomic_write_text
from crater_synth.errors import UserError
from crater_synth.navigation.detectors import registry
from crater_synth.navigation.detectors.learned import VERIFY_SCORES
from crater_synth.navigation.rendered.detector_train import (
    HOLDOUT_FIELD_SHARE,
    architecture,
    detection_set_records,
    frame_matches,
)
from crater_synth.navigation.rendered.training_rows import off_nadir_deg
from crater_synth.tools.detector_choice import command_line, f1, model_option, model_sha256

PROG = "python -m crater_synth.tools.detector_holdout"
DEFAULT_BINS = (0.0, 1.0, 15.0, 30.0, 46.0)  # nadir; 1-15; 15-30; 30-45 degrees off nadir (the oblique band)
# Degradation quarters; detectable() labels stop at 0.9, so the last bin holds 0.75-0.9.
DEGRADATION_BINS = (0.0, 0.25, 0.5, 0.75, 1.0)


def off_nadir_bin(angle: float, edges) -> str | None:
    for lo, hi in zip(edges[:-1], edges[1:]):
        if lo <= angle < hi:
            return f"{lo:g}-{hi:g}"
    return None


def degradation_bin(value: float, edges=DEGRADATION_BINS) -> int:
    """The index of the degradation bin holding ``value`` (the last bin closed)."""
    return int(np.clip(np.searchsorted(edges, value, side="right") - 1, 0, len(edges) - 2))


def score_model(records, params, min_r: float, edges, degradation_edges=DEGRADATION_BINS) -> dict:
    """Recall and precision of one model over ``records``, in all and by off-nadir bin, each with its recall
    by degradation bin (``by_degradation``: labels and recall per bin)."""
    n_deg = len(degradation_edges) - 1
    sums: dict[str, np.ndarray] = {}
    by_deg: dict[str, np.ndarray] = {}  # key -> (bins, 2): labels counted, found
    for image, row in records:
        labels, counted, found, tp, n_det = frame_matches(image, row, params, 0.0, min_r, skip_hidden=True)
        # a label without a degradation (a set whose labels lack the field) is in no degradation bin
        bins = np.array(
            [degradation_bin(lb["degradation"], degradation_edges) if "degradation" in lb else -1 for lb in labels], int
        )
        known = bins >= 0
        per_bin = np.stack(
            [np.bincount(bins[counted & known], minlength=n_deg), np.bincount(bins[found & known], minlength=n_deg)], 1
        )
        for key in ("all", off_nadir_bin(off_nadir_deg(row), edges)):
            if key is not None:
                sums[key] = sums.get(key, np.zeros(5, int)) + np.r_[found.sum(), counted.sum(), tp, n_det, 1]
                by_deg[key] = by_deg.get(key, np.zeros((n_deg, 2), int)) + per_bin
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
            "by_degradation": {
                f"{lo:g}-{hi:g}": {"labels": int(n), "recall": round(k / n, 4) if n else None}
                for lo, hi, (n, k) in zip(degradation_edges[:-1], degradation_edges[1:], by_deg[key])
            },
        }
    return out


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
    ap.add_argument("--out", type=Path, required=True, help="JSON of the table")
    args = ap.parse_args(argv)
    try:
        _, hold, what = detection_set_records(args.folder, HOLDOUT_FIELD_SHARE, training=False)
        hold = hold[:: max(1, args.every)]
        for path in [*(model_option(m)[1] for m in args.model), *args.verifier]:
            if not Path(path).is_file():
                raise UserError(f"{path}: no such model file")
        runs = []
        for model in args.model:
            option, path = model_option(model)
            plain = architecture("fcos" if option == "fcos" else "centernet")[2](path)
            plain = dataclasses.replace(plain, threshold=args.threshold)
            stages = [("", plain)] + [
                (
                    v,
                    dataclasses.replace(
                        plain, verifier=v, verify_threshold=args.verify_threshold, verify_score=args.verify_score
                    ),
                )
                for v in (args.verifier if option != "fcos" else [])
            ]
            model_sha = model_sha256(model)
            for verifier, params in stages:
                t0 = time.perf_counter()
                scores = score_model(hold, params, 0.5 * args.min_span_px, DEFAULT_BINS)
                seconds = round(time.perf_counter() - t0, 1)
                second = {"verifier": verifier, "verifier_sha256": model_sha256(verifier)} if verifier else {}
                runs.append({"model": model, "model_sha256": model_sha} | second | {"seconds": seconds} | scores)
                print(f"{model} {verifier}: {json.dumps(scores['all'])}", flush=True)
            registry.detector(plain.method).load_model.cache_clear()
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    result = {
        "command": command_line(argv, PROG),
        "set": {"folder": str(args.folder), "holdout_fields": what["holdout_fields"], "recipe": what["recipe"]},
        "threshold": args.threshold,
        "verify": {"threshold": args.verify_threshold, "score": args.verify_score} if args.verifier else None,
        "min_span_px": args.min_span_px,
        "off_nadir_bins_deg": list(DEFAULT_BINS),
        "degradation_bins": list(DEGRADATION_BINS),
        "runs": runs,
    }
    atomic_write_text(args.out, json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
