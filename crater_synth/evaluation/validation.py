"""The real validation protocol (docs/validation.md): choose settings on other craters, report the test.

Only one real observation per crater exists offline (a crop of the LROC WAC south-polar mosaic), so
a setting chosen while watching the paper's three craters would be tuned to the test set. The protocol:

- **Validation groups** (``validate.groups``): disjoint groups (triples by default) of catalogue craters,
  none of them one of the test craters. For each group, a classifier is trained on renders of those
  craters only and tested on their real WAC crops. Their mean accuracy (``validation mean``) is the
  ONLY real-image number any setting (renderer, detail, sensor model, preprocessing, model, training)
  may be chosen by.
- **Held-out groups** (``validate.holdout``; ``validate=holdout`` names the rest of the catalogue):
  more catalogue craters, disjoint from both, trained and evaluated the same way once the settings are
  chosen. Their mean (``held-out mean``) says whether what was chosen on the validation craters carries
  over to craters nobody looked at; like the test, it is reported, never used to choose.
- **Test group** (``validate.test``): the paper's three craters, trained and evaluated the same way,
  reported next to the validation numbers and never used to choose.

Every group is rendered into the same dataset directory (``out_dir``; renders are shared and
resumed), trained with each seed of ``validate.seeds`` (the spread across seeds is the noise floor a
lever must beat) and evaluated with the project's own ``train.pipeline.train_and_evaluate``. Results
land in ``validate.out_dir``: ``validation.json`` (every number), ``validation.csv`` (one row per
group, seed, model and crater) and ``validation.md`` (the table). A rerun skips finished
(group, seed) runs whose configuration is unchanged.
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import click
import numpy as np

from crater_core.geometry import hemisphere
from crater_core.schema import atomic_write_json, atomic_write_text, content_key
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import ConfigError, catalogue_names, compose, compose_settings, craters, resolved
from crater_synth.dataset import build_dataset
from train.pipeline import evaluate_saved, train_and_evaluate
from train.registry import MODELS

RESULTS_FILE, CSV_FILE, TABLE_FILE = "validation.json", "validation.csv", "validation.md"
REPORTED_MODELS = MODELS  # every classifier of train.registry
# Each group role and the summary key of its mean accuracy.
MEAN_KEYS = {"validation": "validation_mean", "holdout": "holdout_mean", "test": "test_mean"}
# Overrides the protocol sets itself for each run: a user override of these would be silently lost.
_OWNED_KEYS = ("crater", "run_dir", "train.seed")


@dataclass(frozen=True)
class Group:
    """One set of craters trained and tested together."""

    role: str  # "validation" | "holdout" | "test"
    index: int
    craters: tuple[str, ...]

    @property
    def label(self) -> str:
        prefix = "test" if self.role == "test" else f"{self.role}{self.index}"
        return f"{prefix}-" + "+".join(self.craters)

    def crater_override(self) -> str:
        return "crater=[" + ",".join(self.craters) + "]"


def plan_groups(vcfg: dict, known_craters: Sequence[str]) -> list[Group]:
    """Validation groups, held-out groups, then the test group, checked: at least two validation groups;
    every group of at least two distinct catalogue craters; validation and held-out groups pairwise
    disjoint and none sharing a crater with the test group."""
    groups_cfg = vcfg.get("groups") or []
    test = tuple(str(c) for c in (vcfg.get("test") or []))
    known = set(known_craters)
    if len(groups_cfg) < 2:
        raise ConfigError(f"validate.groups needs at least two validation groups, got {len(groups_cfg)}")
    groups = []
    seen: dict[str, str] = {}
    for key, role in (("groups", "validation"), ("holdout", "holdout")):
        for i, g in enumerate(vcfg.get(key) or []):
            where = f"validate.{key}[{i}]"
            names = tuple(str(c) for c in g)
            if len(names) < 2 or len(set(names)) != len(names):
                raise ConfigError(f"{where}={list(names)}: needs at least two distinct craters")
            for n in names:
                if n not in known:
                    raise ConfigError(f"{where}: unknown crater {n!r} (not in configs/crater/)")
                if n in test:
                    raise ConfigError(
                        f"{where}: {n!r} is a test crater; validation and held-out craters must be "
                        f"disjoint from validate.test={list(test)}"
                    )
                if n in seen:
                    raise ConfigError(f"{where}: {n!r} is already in {seen[n]}; groups must be disjoint")
                seen[n] = where
            groups.append(Group(role, i + 1, names))
    if test:
        if len(test) < 2:
            raise ConfigError(f"validate.test={list(test)}: needs at least two craters")
        for n in test:
            if n not in known:
                raise ConfigError(f"validate.test: unknown crater {n!r} (not in configs/crater/)")
        groups.append(Group("test", 0, test))
    return groups


def group_overrides(overrides: Sequence[str], group: Group, north_overrides: Sequence[str]) -> list[str]:
    """The overrides a group is run with: the user's, and for a group of north-polar craters
    ``validate.north_overrides`` (its DEM and real mosaic) in place of any user override of the same
    keys. A group mixing the hemispheres is refused: one DEM and one mosaic serve a run."""
    sides = {hemisphere(c["lat"]) for c in craters(compose([group.crater_override()]))}
    if len(sides) > 1:
        raise ConfigError(f"{group.label}: mixes north- and south-polar craters; a group needs one hemisphere")
    if sides != {"north"}:
        return list(overrides)
    if not north_overrides:
        raise ConfigError(
            f"{group.label}: north-polar craters need validate.north_overrides (their DEM and real mosaic, e.g. "
            "validate.north_overrides=['dem=lola_ldem256_north','realset=wac_north'])"
        )
    owned = {o.lstrip("+~").split("=", 1)[0].split(".")[0] for o in north_overrides}
    kept = [o for o in overrides if o.lstrip("+~").split("=", 1)[0].split(".")[0] not in owned]
    return kept + list(north_overrides)


# Settings added after fingerprints were published (docs/results/experiments.csv): at these values they
# train exactly as before the key existed, so they are left out and published runs stay resumable.
NEUTRAL_LATER_KEYS = {
    ("train", "augment_rotation"): "right_angles",
    ("train", "augment_offset_frac"): 0.0,
    ("train", "tta_rotations"): 1,
    ("train", "preprocess", "support"): "square",
    ("realset", "frames"): [],  # georeferenced real frames: none unless asked for
    ("render", "blender"): None,  # null: the bpy module, as every run before the setting existed
    ("realset", "mosaic", "pole"): None,  # read from the product's CRS unless set
    ("procedural",): None,  # the procedural terrain group: unset for every DEM-rendered run
    ("detection",): None,  # detection frames' group: unset for every sweep run
}


# Settings that change how finished models are evaluated on the real crops, not how they are trained:
# a run that differs from a finished one only in these is re-evaluated, not retrained.
EVALUATION_ONLY_KEYS = (("train", "tta_rotations"),)  # each also in NEUTRAL_LATER_KEYS (see _same_training)
_ANY = object()  # run_fingerprint: drop the key whatever its value
# Groups renamed after fingerprints were published: hashed under their old name, so published runs keep
# their fingerprints (the Figure 6 counts were the ``experiments`` group).
RENAMED_GROUPS = {"figure6": "experiments"}


def run_fingerprint(cfg_resolved: dict, training_only: bool = False) -> str:
    """What decides a run's result: everything but paths, progress and the validate group itself.
    ``training_only``: what decides its trained models (the evaluation-only keys left out too)."""
    skip = {"run_dir", "validate", "ablation", "data_dir", "out_dir", "trajectory"}  # trajectory: nav frames only
    payload = {RENAMED_GROUPS.get(k, k): v for k, v in cfg_resolved.items() if k not in skip}
    payload["train"] = {
        k: v
        for k, v in payload.get("train", {}).items()
        if k not in ("progress", "dataset_dir", "export_dir", "cache_dir", "cache_workers", "num_threads", "device")
    }
    payload = json.loads(json.dumps(payload, default=str))  # a deep copy to prune
    drop = dict(NEUTRAL_LATER_KEYS)
    for path in EVALUATION_ONLY_KEYS if training_only else ():
        drop[path] = _ANY
    for path, neutral in drop.items():
        parent = payload
        for key in path[:-1]:
            parent = parent.get(key) if isinstance(parent, dict) else None
        if isinstance(parent, dict) and path[-1] in parent and (neutral is _ANY or parent[path[-1]] == neutral):
            del parent[path[-1]]
    return content_key(payload)


def evaluation_only(overrides: Sequence[str]) -> bool:
    """True when every override sets an evaluation-only key (``EVALUATION_ONLY_KEYS``): such a variant
    of a finished protocol run needs no training, only a new evaluation of the same models."""
    keys = [tuple(o.lstrip("+~").split("=", 1)[0].split(".")) for o in overrides]
    return bool(keys) and all(k in EVALUATION_ONLY_KEYS for k in keys)


def _check_overrides(overrides: Sequence[str]) -> None:
    for o in overrides:
        key = o.lstrip("+~").split("=", 1)[0]
        if key in _OWNED_KEYS:
            raise ConfigError(
                f"override {o!r}: the validation protocol sets {key} itself "
                f"(choose craters with validate.groups / validate.test, seeds with validate.seeds)"
            )


def run_validation(overrides: Sequence[str], progress: bool = True) -> dict:
    """Render, train and evaluate every (group, seed); returns the results dict (also written)."""
    overrides = list(overrides)
    _check_overrides(overrides)
    base = resolved(compose(overrides))
    progress = progress and bool(base["train"].get("progress", True))  # train.progress=false: quiet logs
    vcfg = base["validate"]
    seeds = [int(s) for s in (vcfg.get("seeds") or [0])]
    groups = plan_groups(vcfg, catalogue_names())
    roles = set(vcfg.get("roles") or MEAN_KEYS)
    north = [str(o) for o in (vcfg.get("north_overrides") or [])]
    out = Path(str(vcfg["out_dir"]))
    out.mkdir(parents=True, exist_ok=True)
    results_path = out / RESULTS_FILE
    previous = json.loads(results_path.read_text()) if results_path.is_file() else {}
    done = {(r["group"], r["seed"]): r for r in previous.get("runs", [])}
    runs = []
    for g in groups:
        if g.role not in roles:
            continue
        rendered = False
        g_ovr = group_overrides(overrides, g, north)
        for seed in seeds:
            run_dir = out / g.label / f"seed{seed}"
            ovr = g_ovr + [g.crater_override(), f"run_dir={run_dir}", f"train.seed={seed}"]
            cfg, settings = compose_settings(ovr)
            cfg_r = resolved(cfg)
            fp = run_fingerprint(cfg_r)
            old = done.get((g.label, seed))
            if old is not None and old.get("fingerprint") == fp:
                runs.append(old)
                continue
            tfp = run_fingerprint(cfg_r, training_only=True)
            if old is not None and _same_training(old, tfp) and _has_models(run_dir):
                if progress:
                    click.echo(f"validate: {g.label} seed {seed}: same training, evaluating again", err=True)
                t1 = time.perf_counter()
                metrics = evaluate_saved(settings, progress=progress)
                run = _run_record(g, seed, fp, tfp, metrics, old["renders"], old["render_s"], old["train_s"], run_dir)
                run["evaluate_only_s"] = round(time.perf_counter() - t1, 1)
            else:
                if not rendered:
                    if progress:
                        click.echo(f"validate: rendering {g.label} ({', '.join(g.craters)})", err=True)
                    t0 = time.perf_counter()
                    render = build_dataset(settings, progress=progress)
                    render_s = time.perf_counter() - t0
                    rendered = True
                t1 = time.perf_counter()
                metrics = train_and_evaluate(settings, progress=progress)
                run = _run_record(
                    g, seed, fp, tfp, metrics, int(render["renders_total"]), render_s, time.perf_counter() - t1, run_dir
                )
                render_s = 0.0
            runs.append(run)
            done[(g.label, seed)] = run
            _write(out, runs, base, groups, seeds)
    return _write(out, runs, base, groups, seeds)


def _same_training(old: dict, tfp: str) -> bool:
    """Were ``old``'s models trained exactly as the configuration with training fingerprint ``tfp``
    would train them? A record written before ``training_fingerprint`` existed has only its
    ``fingerprint``, which left every evaluation-only key out at its neutral value (each is also in
    ``NEUTRAL_LATER_KEYS``), so that fingerprint is its training fingerprint."""
    return old.get("training_fingerprint", old.get("fingerprint")) == tfp


def _has_models(run_dir: Path) -> bool:
    from train.trainer import HOG_FILE, NET_FILE, SVM_FILE

    return all((run_dir / f).is_file() for f in (NET_FILE, SVM_FILE, HOG_FILE))


def _run_record(
    g: Group, seed: int, fp: str, tfp: str, metrics: dict, renders: int, render_s: float, train_s: float, run_dir: Path
) -> dict:
    """One (group, seed) entry of validation.json."""
    return {
        "group": g.label,
        "role": g.role,
        "craters": list(g.craters),
        "seed": seed,
        "fingerprint": fp,
        "training_fingerprint": tfp,
        "train_images": int(metrics["train_images"]),
        "renders": int(renders),
        "render_s": round(render_s, 1),
        "train_s": round(train_s, 1),
        "models": {
            m: {
                "real_accuracy": float(metrics[m]["real_accuracy"]),
                "val_accuracy": metrics[m].get("val_accuracy"),
                "per_crater": {k: float(v) for k, v in metrics[m]["per_crater"].items()},
                "confusion": metrics[m]["confusion"],
            }
            for m in REPORTED_MODELS
        },
        "run_dir": str(run_dir),
    }


def summarise(runs: list[dict], groups: list[Group], seeds: list[int]) -> dict:
    """Per group and model: mean accuracy over seeds (and its spread), per crater; then the
    validation mean (mean over validation groups), the held-out mean and the test mean."""
    out: dict = {"groups": {}, "validation_mean": {}, "holdout_mean": {}, "test_mean": {}}
    for g in groups:
        rs = [r for r in runs if r["group"] == g.label]
        if not rs:
            continue
        entry = {"role": g.role, "craters": list(g.craters), "seeds": [r["seed"] for r in rs], "models": {}}
        for m in REPORTED_MODELS:
            accs = [r["models"][m]["real_accuracy"] for r in rs]
            per = {c: float(np.mean([r["models"][m]["per_crater"][c] for r in rs])) for c in g.craters}
            entry["models"][m] = {
                "mean": float(np.mean(accs)),
                "std_over_seeds": float(np.std(accs)),
                "per_crater": per,
                "min_crater": float(min(per.values())),
            }
        out["groups"][g.label] = entry
    for m in REPORTED_MODELS:
        for role, key in MEAN_KEYS.items():
            accs = [e["models"][m]["mean"] for e in out["groups"].values() if e["role"] == role]
            out[key][m] = float(np.mean(accs)) if accs else None
    return out


def table_markdown(summary: dict) -> str:
    """The validation table: one line per group and model, per-crater accuracies, means."""
    lines = ["| group | model | accuracy (mean over seeds ± sd) | per crater |", "|---|---|---|---|"]
    for label, e in summary["groups"].items():
        for m in REPORTED_MODELS:
            d = e["models"][m]
            per = ", ".join(f"{c} {v:.3f}" for c, v in d["per_crater"].items())
            lines.append(f"| {label} | {m} | {d['mean']:.3f} ± {d['std_over_seeds']:.3f} | {per} |")
    lines.append("")
    for m in REPORTED_MODELS:
        lines.append(f"- {m}: " + means_line(summary, m))
    return "\n".join(lines) + "\n"


def format_mean(x: float | None) -> str:
    """An accuracy mean as the tables print it (``n/a`` for a role without results)."""
    return "n/a" if x is None else f"{x:.3f}"


def means_line(summary: dict, model: str) -> str:
    """The means of one model as a line: validation, held-out and test, each only when its groups ran
    (``n/a`` when none did)."""
    names = {"validation": "validation mean", "holdout": "held-out mean", "test": "test mean"}
    parts = [
        f"{names[role]} {format_mean(summary[key][model])}"
        for role, key in MEAN_KEYS.items()
        if summary.get(key, {}).get(model) is not None
    ]
    return ", ".join(parts) or "n/a"


def _write(out: Path, runs: list[dict], base: dict, groups: list[Group], seeds: list[int]) -> dict:
    summary = summarise(runs, groups, seeds)
    res = {
        "protocol": "docs/validation.md",
        "sweep": base["sweep"].get("name"),
        "seeds": seeds,
        "groups": [{"label": g.label, "role": g.role, "craters": list(g.craters)} for g in groups],
        "runs": runs,
        "summary": summary,
    }
    atomic_write_json(out / RESULTS_FILE, res)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["group", "role", "seed", "model", "crater", "accuracy", "group_accuracy", "train_images"])
    for r in runs:
        for m in REPORTED_MODELS:
            for c, a in r["models"][m]["per_crater"].items():
                w.writerow(
                    [
                        r["group"],
                        r["role"],
                        r["seed"],
                        m,
                        c,
                        f"{a:.4f}",
                        f"{r['models'][m]['real_accuracy']:.4f}",
                        r["train_images"],
                    ]
                )
    atomic_write_text(out / CSV_FILE, buf.getvalue())
    head = (
        f"# Validation protocol results ({res['sweep']}, seeds {seeds})\n\n"
        "Settings are chosen by the validation mean only; the held-out and test groups are reported, "
        "never used to choose.\n\n"
    )
    atomic_write_text(out / TABLE_FILE, head + table_markdown(summary))
    return res


@click.command("validate")
@OVERRIDES
@user_errors
def validate_command(overrides):
    """Real validation protocol: train and test on validation crater groups, then the test craters.

    Writes validation.json/.csv/.md under validate.out_dir (docs/validation.md). Example:
    crater-synth validate sweep=demo validate.seeds=[0,1]
    """
    res = run_validation(overrides)
    for m in REPORTED_MODELS:
        click.echo(f"{m}: " + means_line(res["summary"], m))
    click.echo(f"table: {Path(str(resolved(compose(list(overrides)))['validate']['out_dir'])) / TABLE_FILE}")
