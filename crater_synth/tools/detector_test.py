"""``python -m crater_synth.tools.detector_test``: run detector models on the north test windows, once, at the
thresholds a committed choice file froze on the south validation windows, and write their detection scores.

The choice file is written by ``python -m crater_synth.tools.detector_choice`` (its ``chosen_per_model``: each
model's best threshold on the south validation windows). This tool refuses a choice file that git does not
hold unchanged (the choice must be committed before the test), and a model file whose sha256 is not the one
the choice recorded (the model tested is the model chosen). Nothing here chooses anything: every model runs
at its frozen threshold on every north window, and the scores are written as they come.

Scores per model, pooled over the windows: precision, recall and F1 against the LU1319381 catalogue for
D >= 15 km and by size (8-15, 15-30, 30-60, >= 60 km), against the map by size, and the fix metrics.
``--reference NAME`` names the model trained on real images; every other model's F1 is then also given as
a ratio to the reference's (the sim-to-real gap).

    python -m crater_synth.tools.detector_test --choice docs/results/detector_choice_south_real.json \\
        --reference real.pt --out docs/results/detector_test_north.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from pathlib import Path

from crater_core.schema import atomic_write_text
from crater_synth.errors import UserError
from crater_synth.navigation.windows.evaluate import (
    PRIOR_OFFSET_KM,
    catalogue_craters,
    evaluate_split,
    nav_eval_map,
    nav_eval_request,
)
from crater_synth.paths import SOURCE_ROOT
from crater_synth.tools.detector_choice import (
    command_line,
    detector_overrides,
    f1,
    model_option,
    model_sha256,
    score_line,
)

PROG = "python -m crater_synth.tools.detector_test"
POLE, SPLIT = "north", "test"  # the held-out pole: run once per frozen model (docs/navigation/protocol.md)


def committed_unchanged(path: Path) -> bool:
    """True when git tracks ``path`` and it equals its committed version (no staged or unstaged change)."""
    path = Path(path).resolve()
    try:
        subprocess.run(
            ["git", "-C", str(SOURCE_ROOT), "ls-files", "--error-unmatch", str(path)], capture_output=True, check=True
        )
        return (
            subprocess.run(["git", "-C", str(SOURCE_ROOT), "diff", "--quiet", "HEAD", "--", str(path)]).returncode == 0
        )
    except (OSError, subprocess.CalledProcessError):
        return False


def frozen_choices(choice_file: Path, models: list[str]) -> list[dict]:
    """The ``chosen_per_model`` entries of a committed choice file (those of ``models`` only, when given),
    each model file checked against the sha256 the choice recorded."""
    if not committed_unchanged(choice_file):
        raise UserError(f"{choice_file}: not committed as it is; commit the choice before the test")
    try:
        chosen = json.loads(Path(choice_file).read_text(encoding="utf-8"))["chosen_per_model"]
    except (OSError, ValueError, KeyError):
        raise UserError(f"{choice_file}: not a detector_choice file with chosen_per_model") from None
    if models:
        missing = sorted(set(models) - {c["model"] for c in chosen})
        if missing:
            raise UserError(f"{choice_file}: no choice for {', '.join(missing)}")
        chosen = [c for c in chosen if c["model"] in models]
    for c in chosen:
        # the model, and each model file its variant names (the verifier; a plain path reads as itself)
        for name, want in ({c["model"]: c["model_sha256"]} | c.get("variant_sha256", {})).items():
            try:
                got = model_sha256(name)
            except OSError:
                raise UserError(f"model {name}: cannot be read") from None
            if got != want:
                raise UserError(f"model {name}: not the file chosen in {choice_file} (sha256 differs)")
    return chosen


def with_f1(scores: dict) -> dict:
    """Catalogue scores with F1 added, for D >= 15 km and each size bin."""
    out = dict(scores) | {"f1_15km": f1(scores.get("precision_15km"), scores.get("recall_15km"))}
    out["by_size_km"] = {
        k: v | {"f1": f1(v["precision"], v["recall"])} for k, v in scores.get("by_size_km", {}).items()
    }
    return out


def run_model(choice: dict, landmarks, listed) -> dict:
    option, _ = model_option(choice["model"])
    overrides = detector_overrides(choice["model"], choice["threshold"], tuple(choice.get("variant", ())))
    settings, _, _ = nav_eval_request(1, PRIOR_OFFSET_KM, False, False, overrides)
    nav = settings[option]
    t0 = time.perf_counter()
    summary, _ = evaluate_split(SPLIT, landmarks, nav.detector, nav.fix, pole=POLE, listed=listed)
    every = summary["all_windows"]
    return {
        "model": choice["model"],
        "model_sha256": choice["model_sha256"],
        "method": option,
        "threshold": choice["threshold"],
        "variant": choice.get("variant", []),
        "variant_sha256": choice.get("variant_sha256", {}),
        "south_validation_catalogue_15km": choice["catalogue_15km"],
        "catalogue": with_f1(every.get("against_catalogue", {})),
        "map_by_size_km": every.get("by_size_km"),
        "fix_rate": every.get("fix_rate"),
        "false_fixes": every.get("false_fixes"),
        "headline_fix_rate": summary["headline"].get("fix_rate"),
        "windows": every["windows"],
        "seconds": round(time.perf_counter() - t0, 1),
    }


def ratios(runs: list[dict], reference: str) -> dict:
    """Each model's F1 over the reference's, for D >= 15 km and by size (None where either is undefined)."""
    ref = next(r for r in runs if r["model"] == reference)["catalogue"]

    def ratio(a, b):
        return round(a / b, 4) if a is not None and b else None

    return {
        r["model"]: {
            "f1_15km": ratio(r["catalogue"]["f1_15km"], ref["f1_15km"]),
            "by_size_km": {
                k: ratio(v["f1"], ref["by_size_km"][k]["f1"]) for k, v in r["catalogue"]["by_size_km"].items()
            },
        }
        for r in runs
        if r["model"] != reference
    }


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--choice", type=Path, required=True, help="a committed detector_choice JSON file")
    p.add_argument("--model", action="append", default=[], help="only this model of the choice file (repeatable)")
    p.add_argument("--reference", default=None, help="the model trained on real images: F1 ratios against it")
    p.add_argument("--out", type=Path, required=True, help="JSON of the test runs")
    args = p.parse_args(argv)
    try:
        chosen = frozen_choices(args.choice, args.model)
        if args.reference is not None and args.reference not in {c["model"] for c in chosen}:
            raise UserError(f"--reference {args.reference}: not among the models tested")
    except UserError as exc:
        p.exit(2, f"{PROG}: {exc}\n")
    landmarks, _ = nav_eval_map(POLE, None)
    listed = catalogue_craters(POLE)
    runs = []
    for c in chosen:
        r = run_model(c, landmarks, listed)
        print(score_line(f"{r['model']} t={r['threshold']}", r["catalogue"], "f1_15km", r["seconds"]), flush=True)
        runs.append(r)
    doc = {
        "command": command_line(argv, PROG),
        "split": f"{POLE} {SPLIT}, every window",
        "choice_file": str(args.choice),
        "rule": "each model at the threshold its choice file froze on the south validation windows; run once",
        "runs": runs,
    }
    if args.reference is not None:
        doc["reference"] = args.reference
        doc["f1_ratio_to_reference"] = ratios(runs, args.reference)
    atomic_write_text(args.out, json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
