"""``python -m crater_synth.tools.detector_choice``: choose a learned detector model and its detection threshold
on the south validation windows, by detection F1 against the LU1319381 catalogue for D >= 15 km (the issue's
whole-frame measure), and write the runs and the choice as JSON.

Every (model, threshold) pair runs the ``learned-detect`` option of ``nav-eval`` (the detection operating
point: no light, no rim fit) on the same south validation windows (``--every N`` of them), the committed
model among the candidates so the table holds the baseline measured in the same run. A model given as
``fcos:PATH`` (torchvision's FCOS, ``nav.detector_train.arch=fcos``) runs the ``fcos`` option instead, with
the same operating point and the same table. The chosen pair is the
highest F1; ties go to the higher precision. The north windows are a test: this tool never reads them; run
``nav-eval --pole north`` once with the choice, after it is committed.

    python -m crater_synth.tools.detector_choice --model A.pt --model fcos:B.pt --thresholds 0.2,0.3,0.4 \\
        --every 2 --out docs/results/detector_choice_south.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shlex
import sys
import time
from pathlib import Path

from crater_core.schema import atomic_write_text
from crater_synth.navigation.detectors.learned import DEFAULT_MODEL
from crater_synth.navigation.windows.evaluate import (
    PRIOR_OFFSET_KM,
    catalogue_craters,
    evaluate_split,
    nav_eval_map,
    nav_eval_request,
)
from crater_synth.paths import SOURCE_ROOT

PROG = "python -m crater_synth.tools.detector_choice"
POLE, SPLIT = "south", "validation"  # choices are made here only (docs/navigation/protocol.md)
DETECTOR_PREFIXES = {"fcos": "fcos"}  # --model PREFIX:PATH -> the nav/detector option that runs it


def model_option(model: str) -> tuple[str, str]:
    """(nav/detector option, model file or "committed") of a ``--model`` value: ``fcos:PATH`` runs the fcos
    option; anything else is a learned-detect model (a path may itself hold a colon)."""
    prefix, sep, rest = model.partition(":")
    if sep and prefix in DETECTOR_PREFIXES:
        return DETECTOR_PREFIXES[prefix], rest
    return "learned-detect", model


def f1(precision: float | None, recall: float | None) -> float | None:
    if not precision or not recall:
        return None if precision is None or recall is None else 0.0
    return round(2.0 * precision * recall / (precision + recall), 4)


def detector_overrides(model: str, threshold: float, variant: tuple[str, ...] = ()) -> list[str]:
    """The nav-eval overrides that run ``model`` at ``threshold`` with the ``variant``'s own overrides."""
    option, path = model_option(model)
    overrides = [f"nav/detector={option}", f"nav.detector.threshold={threshold}", *variant]
    if path != "committed":
        overrides.append(f"nav.detector.model={path}")
    return overrides


def run_pair(model: str, threshold: float, landmarks, listed, every: int, variant: tuple[str, ...] = ()) -> dict:
    """``model``'s detector option (:func:`model_option`) at ``threshold``, with the ``variant`` overrides
    (inference settings such as ``nav.detector.tta=4``), on the south validation windows: its detection
    scores (against the catalogue, D >= 15 km, and the map's size bins) and fix metrics."""
    option, _ = model_option(model)
    settings, _, _ = nav_eval_request(
        every, PRIOR_OFFSET_KM, False, False, detector_overrides(model, threshold, variant)
    )
    nav = settings[option]
    t0 = time.perf_counter()
    summary, _ = evaluate_split(SPLIT, landmarks, nav.detector, nav.fix, every=every, pole=POLE, listed=listed)
    cat = summary["all_windows"].get("against_catalogue", {})
    return {
        "model": model,
        "model_sha256": model_sha256(model),
        "method": option,
        "threshold": threshold,
        "variant": list(variant),
        "variant_sha256": variant_sha256(variant),
        "catalogue_15km": cat | {"f1": f1(cat.get("precision_15km"), cat.get("recall_15km"))},
        "map_by_size_km": summary["all_windows"].get("by_size_km"),
        "fix_rate": summary["all_windows"].get("fix_rate"),
        "false_fixes": summary["all_windows"].get("false_fixes"),
        "windows": summary["all_windows"]["windows"],
        "seconds": round(time.perf_counter() - t0, 1),
    }


def choose(runs: list[dict]) -> dict:
    scored = [r for r in runs if r["catalogue_15km"]["f1"] is not None]
    best = max(scored, key=lambda r: (r["catalogue_15km"]["f1"], r["catalogue_15km"]["precision_15km"] or 0.0))
    return {
        "model": best["model"],
        "threshold": best["threshold"],
        "variant": best.get("variant", []),
        "variant_sha256": best.get("variant_sha256", {}),
        "catalogue_15km": best["catalogue_15km"],
        "model_sha256": best["model_sha256"],
    }


def command_line(argv, prog: str = PROG) -> str:
    """A tool's command line as run (``argv``: the arguments, None for the process's own), shell-quoted."""
    return shlex.join([*prog.split(), *(sys.argv[1:] if argv is None else argv)])


def score_line(label: str, cat: dict, f1_key: str, seconds: float) -> str:
    """One progress line: a run's F1, precision and recall against the catalogue at D >= 15 km."""
    return f"{label}: F1 {cat[f1_key]} P {cat['precision_15km']} R {cat['recall_15km']} ({seconds} s)"


def model_sha256(model: str) -> str:
    """sha256 of a ``--model`` value's file (the committed model's for "committed"): what a test run checks
    it is given the model that was chosen."""
    _, path = model_option(model)
    return file_sha256(DEFAULT_MODEL if path == "committed" else path)


def file_sha256(path) -> str:
    """sha256 of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# Variant overrides naming model files (one, or a [list]): hashed like --model.
VARIANT_FILE_KEYS = ("nav.detector.verifier", "nav.detector.ensemble")


def variant_sha256(variant) -> dict:
    """sha256 of each model file a variant's overrides name (the verifier, the ensemble's models), keyed by
    the file as given."""
    out = {}
    for o in variant:
        key, _, value = o.partition("=")
        if key not in VARIANT_FILE_KEYS:
            continue
        for name in value.strip("[]").split(","):
            if name.strip():
                out[name.strip()] = file_sha256(name.strip())
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--model", action="append", default=[], help="a candidate model file, fcos:PATH for an FCOS one (repeatable)"
    )
    p.add_argument("--thresholds", default="0.2,0.3,0.4", help="heat thresholds, comma-separated")
    p.add_argument("--every", type=int, default=2, help="every Nth south validation window")
    p.add_argument(
        "--variant",
        action="append",
        default=None,
        help="space-separated nav.detector overrides run as one more candidate of every model and threshold, "
        "e.g. 'nav.detector.tta=4' (repeatable; '' is the option as it is; default: '' alone)",
    )
    p.add_argument("--out", type=Path, default=None, help="JSON of the runs and the choice")
    args = p.parse_args(argv)
    thresholds = [float(t) for t in args.thresholds.split(",")]
    landmarks, _ = nav_eval_map(POLE, None)
    listed = catalogue_craters(POLE)  # LU1319381, as nav-eval scores against it
    variants = [tuple(v.split()) for v in (args.variant or [""])]
    runs = []
    for model in ["committed", *args.model]:
        for variant in variants:
            for t in thresholds:
                r = run_pair(model, t, landmarks, listed, args.every, variant)
                label = " ".join([model, *variant, f"t={t}"])
                print(score_line(label, r["catalogue_15km"], "f1", r["seconds"]), flush=True)
                runs.append(r)
    doc = {
        "command": command_line(argv),
        "split": f"{POLE} {SPLIT}, every {args.every}th window",
        "committed_model": str(DEFAULT_MODEL.relative_to(SOURCE_ROOT)),  # where it lies in a checkout
        "rule": "highest detection F1 against the LU1319381 catalogue, D >= 15 km (ties: higher precision)",
        "runs": runs,
        "chosen": choose(runs),
        # Each model's own best threshold by the same rule: what `python -m crater_synth.tools.detector_test`
        # runs on the north test windows, once, after this file is committed.
        "chosen_per_model": [choose([r for r in runs if r["model"] == m]) for m in ["committed", *args.model]],
    }
    print(json.dumps(doc["chosen"]))
    if args.out:
        atomic_write_text(args.out, json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
