"""The report's inputs: every loader returns None when its file is absent and raises
:class:`ReportError` naming the file when it is corrupt; the run's effective configuration."""

from __future__ import annotations

import copy
import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import yaml
from PIL import Image

from crater_core import schema
from crater_synth.config import PRESET_GROUPS, REPO_ROOT, compose, resolved
from crater_synth.errors import UserError
from crater_synth.navigation import DEMO_JSON
from train.registry import MODELS

METRICS_FILE = "metrics.json"
LOOP_FILE = "loop_history.json"
EXPERIMENTS_FILE = "experiments.csv"
FIGURE6_FILE = "figure6.png"
RUN_CONFIG_FILE = "config.yaml"  # the resolved config `crater-synth train` saves (train/trainer.py)
SUMMARY_FILE = "train_summary.json"
EXPERIMENT_COLUMNS = ("parameter", "count", "sigma", "model", "real_accuracy", "train_images")
LOOP_ROUND_FIELDS = ("round", "sun_elevation_count", "images", *MODELS, "render_s", "train_s")


class ReportError(UserError):
    """A report input is corrupt (named in the message) or the run directory is unusable."""


def is_num(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _num_or_none(x) -> bool:
    return x is None or is_num(x)


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ReportError(f"{path}: corrupt input (not UTF-8 text)") from None
    except OSError as exc:
        raise ReportError(f"{path}: cannot read ({exc.strerror})") from None


def _read_json(path: Path):
    text = _read_text(path)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ReportError(f"{path}: corrupt JSON ({exc.msg} at line {exc.lineno}, column {exc.colno})") from None


def load_metrics(path: Path) -> dict | None:
    """``metrics.json`` as written by train/evaluate.py, shape-checked (any number of classes)."""
    if not path.exists():
        return None
    doc = _read_json(path)
    bad = f"{path}: corrupt metrics"
    if not isinstance(doc, dict):
        raise ReportError(f"{bad}: expected a JSON object, got {type(doc).__name__}")
    present = [m for m in MODELS if m in doc]
    if not present:
        raise ReportError(f"{bad}: none of the model entries {list(MODELS)}")
    classes = doc.get("classes")
    if classes is not None and not (isinstance(classes, list) and all(isinstance(c, str) for c in classes)):
        raise ReportError(f"{bad}: 'classes' should be a list of crater names")
    for m in present:
        e = doc[m]
        if not isinstance(e, dict):
            raise ReportError(f"{bad}: {m!r} should be an object")
        if "real_accuracy" not in e or not _num_or_none(e["real_accuracy"]):
            raise ReportError(f"{bad}: {m}.real_accuracy missing or not a number")
        for key in ("val_accuracy", "real_accuracy_class_mean"):
            if not _num_or_none(e.get(key)):
                raise ReportError(f"{bad}: {m}.{key} is not a number")
        for key in ("per_crater", "per_sigma", "per_source"):
            d = e.get(key, {})
            if not isinstance(d, dict) or not all(_num_or_none(v) for v in d.values()):
                raise ReportError(f"{bad}: {m}.{key} should map names to accuracies")
        conf = e.get("confusion")
        if conf is not None:
            n = len(conf) if isinstance(conf, list) else -1
            if n < 1 or not all(isinstance(r, list) and len(r) == n and all(is_num(v) for v in r) for r in conf):
                raise ReportError(f"{bad}: {m}.confusion should be a square matrix of counts")
            if classes is not None and n != len(classes):
                raise ReportError(f"{bad}: {m}.confusion is {n}x{n} but there are {len(classes)} classes")
    return doc


def load_loop_history(path: Path) -> dict | None:
    """``loop_history.json``: {"rounds": [...], "threshold", "stopped_because"}."""
    if not path.exists():
        return None
    doc = _read_json(path)
    bad = f"{path}: corrupt loop history"
    if not isinstance(doc, dict) or not isinstance(doc.get("rounds"), list):
        raise ReportError(f"{bad}: expected an object with a 'rounds' list")
    for i, r in enumerate(doc["rounds"]):
        if not isinstance(r, dict):
            raise ReportError(f"{bad}: rounds[{i}] is not an object")
        for key in ("round", "sun_elevation_count"):
            if not is_num(r.get(key)):
                raise ReportError(f"{bad}: rounds[{i}].{key} missing or not a number")
        for key in LOOP_ROUND_FIELDS[2:]:
            if not _num_or_none(r.get(key)):
                raise ReportError(f"{bad}: rounds[{i}].{key} is not a number")
    if not _num_or_none(doc.get("threshold")):
        raise ReportError(f"{bad}: threshold is not a number")
    if doc.get("stopped_because") is not None and not isinstance(doc["stopped_because"], str):
        raise ReportError(f"{bad}: stopped_because should be text")
    return doc


def load_experiments(path: Path) -> list[dict] | None:
    """``experiments.csv`` rows with typed values (real_accuracy may be empty -> NaN)."""
    if not path.exists():
        return None
    text = _read_text(path)
    reader = csv.DictReader(text.splitlines())
    cols = reader.fieldnames or []
    missing = [c for c in EXPERIMENT_COLUMNS if c not in cols]
    if missing:
        raise ReportError(f"{path}: corrupt experiments table: missing column(s) {missing} (has {cols})")
    out = []
    for lineno, rec in enumerate(reader, 2):
        try:
            acc = (rec["real_accuracy"] or "").strip()
            row = {
                "parameter": (rec["parameter"] or "").strip(),
                "count": int(float(rec["count"])),
                "sigma": float(rec["sigma"]),
                "model": (rec["model"] or "").strip(),
                "real_accuracy": float(acc) if acc else float("nan"),
                "train_images": int(float(rec["train_images"])),
            }
        except (TypeError, ValueError) as exc:
            raise ReportError(f"{path}:{lineno}: corrupt experiments row ({exc})") from None
        if not row["parameter"] or not row["model"]:
            raise ReportError(f"{path}:{lineno}: corrupt experiments row (empty parameter or model)")
        out.append(row)
    return out


def load_summary(path: Path) -> dict | None:
    """``train_summary.json`` (train/trainer.py); only a few facts are shown."""
    if not path.exists():
        return None
    doc = _read_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("data", {}), dict):
        raise ReportError(f"{path}: corrupt training summary (expected a JSON object with a 'data' object)")
    return doc


def check_png(path: Path) -> Path | None:
    """``path`` if it is a readable PNG, None if absent; ReportError if corrupt."""
    if not path.exists():
        return None
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
    except OSError as exc:
        raise ReportError(f"{path}: cannot read ({exc.strerror})") from None
    if head != b"\x89PNG\r\n\x1a\n":
        raise ReportError(f"{path}: corrupt PNG (bad signature)")
    try:
        with Image.open(path) as im:
            im.verify()
    except Exception as exc:  # noqa: BLE001 - any decoder complaint means a corrupt file
        raise ReportError(f"{path}: corrupt PNG ({exc})") from None
    return path


def load_run_config(path: Path) -> dict | None:
    """The resolved configuration saved by ``crater-synth train`` (RUN_DIR/config.yaml)."""
    if not path.exists():
        return None

    try:
        doc = yaml.safe_load(_read_text(path))
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        what = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ReportError(f"{path}: corrupt YAML ({what}{where})") from None
    if not isinstance(doc, dict):
        raise ReportError(f"{path}: corrupt run config (expected a mapping)")
    return doc


def dataset_rows(ds: Path | None) -> list[dict] | None:
    """Every row of the dataset's manifest (strict: a corrupt row is an error naming file:line)."""
    if ds is None or not (ds / schema.MANIFEST_NAME).is_file():
        return None
    return schema.load_manifest(ds)


# ------------------------------------------------------------------------------------------------
# Configuration: the run's saved config, with the command line's explicit overrides on top
# ------------------------------------------------------------------------------------------------
def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+").split("@", 1)[0]


# Where a run lives: the report is given the run directory itself, so a preset's paths are not its choice.
_PATH_KEYS = frozenset({"run_dir", "out_dir", "data_dir"})


def _explicit_keys(overrides: Sequence[str], composed: Mapping) -> list[str]:
    """The keys the command line sets: each ``key=value`` and ``group=option``, and for a preset
    (``experiment=NAME``) the top-level keys whose value it changes, paths aside (``experiment=demo``
    counts as the ``sweep=... train=... loop...`` it stands for)."""
    keys = [_key(o) for o in overrides if "=" in o and not o.startswith("~") and _key(o) not in PRESET_GROUPS]
    presets = [o for o in overrides if "=" in o and _key(o) in PRESET_GROUPS]
    if presets:
        without = resolved(compose([o for o in overrides if o not in presets]))
        keys += [k for k, v in composed.items() if k not in _PATH_KEYS and without.get(k) != v and k not in keys]
    return keys


def _get_path(d: Mapping, dotted: str):
    cur = d
    for part in dotted.split("."):
        if not isinstance(cur, Mapping) or part not in cur:
            raise KeyError(dotted)
        cur = cur[part]
    return cur


def _set_path(d: dict, dotted: str, value) -> None:
    parts = dotted.split(".")
    for part in parts[:-1]:
        if not isinstance(d.get(part), dict):
            d[part] = {}
        d = d[part]
    d[parts[-1]] = copy.deepcopy(value)


# Mappings that are a run's own choice, not a group of keys: never completed from the composed defaults.
_CHOICES = ("crater", "train.select", "ablation.train", "ablation.levers")


def _fill_missing(cfg: dict, composed: Mapping, path: str = "") -> None:
    """Complete ``cfg`` in place with every key it lacks, group by group, from ``composed``: a saved
    configuration from before a key existed (or a partial one) still converts to its settings."""
    for key, value in composed.items():
        full = f"{path}.{key}" if path else str(key)
        if key not in cfg:
            cfg[key] = copy.deepcopy(value)
        elif isinstance(cfg[key], dict) and isinstance(value, Mapping) and full not in _CHOICES:
            _fill_missing(cfg[key], value, full)


@dataclass
class RunConfig:
    cfg: dict
    dataset_dir: Path | None
    dataset_dir_source: str
    saved: bool


def effective_config(run_dir: Path, overrides: Sequence[str] = ()) -> RunConfig:
    """The configuration the run used (RUN_DIR/config.yaml when train saved one, else the composed
    defaults), with every key given explicitly on the command line taken from the overrides."""
    composed = resolved(compose(list(overrides)))
    saved = load_run_config(run_dir / RUN_CONFIG_FILE)
    explicit = _explicit_keys(overrides, composed)
    if saved is not None:
        cfg = copy.deepcopy(saved)
        _fill_missing(cfg, composed)  # sections and keys an older saved config lacks
        for key in explicit:
            try:
                _set_path(cfg, key, _get_path(composed, key))
            except KeyError:
                pass
    else:
        cfg = composed
    if any(k in ("train", "train.dataset_dir") for k in explicit):
        source = "command-line override train.dataset_dir"
    elif saved is not None and (saved.get("train") or {}).get("dataset_dir"):
        source = f"{run_dir / RUN_CONFIG_FILE} (the configuration the run was trained with)"
    else:
        source = "configuration default (train.dataset_dir)"
    raw = (cfg.get("train") or {}).get("dataset_dir")
    ds = None
    if raw:
        ds = Path(str(raw))
        if not ds.is_absolute() and not ds.exists() and (REPO_ROOT / ds).exists():
            ds = REPO_ROOT / ds
    return RunConfig(cfg, ds, source, saved is not None)


def config_craters(cfg: Mapping) -> list[dict]:
    """The crater entries of the configuration's crater group, in configuration order."""
    out = []
    for key, e in (cfg.get("crater") or {}).items():
        e = e or {}
        out.append(
            {
                "name": str(e.get("name") or key),
                "lat": e.get("lat"),
                "lon": e.get("lon"),
                "diameter_km": e.get("diameter_km"),
            }
        )
    return out


# ------------------------------------------------------------------------------------------------
# Navigation (docs/navigation/overview.md): RUN_DIR/navigation/ holds what `make navigate-demo` and
# `crater-synth nav-frames-eval --json` write
# ------------------------------------------------------------------------------------------------
NAVIGATION_DIR = "navigation"
NAV_FRAMES_GLOB = "frames_eval*.json"  # one per rendered trajectory (FRAMES_EVAL_JSON, or frames_eval_NAME.json)
NAV_SUMMARY_KEYS = (
    "fix_rate",
    "median_error_km",
    "p90_error_km",
    "false_fix_rate",
    "identification_accuracy",
    "recall_15km",
    "precision_15km",
)


def _check_summary(s, where: str, bad: str) -> None:
    if not isinstance(s, dict) or not is_num(s.get("windows")):
        raise ReportError(f"{bad}: {where} should be a summary object with a 'windows' count")
    for key in NAV_SUMMARY_KEYS:
        if not _num_or_none(s.get(key)):
            raise ReportError(f"{bad}: {where}.{key} is not a number")


def _check_fix(f: dict, where: str, bad: str) -> None:
    if not isinstance(f.get("fix"), bool):
        raise ReportError(f"{bad}: {where}.fix missing or not true/false")
    if f["fix"] and not is_num(f.get("error_km")):
        raise ReportError(f"{bad}: {where} has a fix but no error_km")
    if not f["fix"] and not isinstance(f.get("reason"), str):
        raise ReportError(f"{bad}: {where} has no fix and no reason")


def load_nav_demo(path: Path) -> dict | None:
    """``navigation.json`` of ``make navigate-demo`` (crater_synth/navigation/demo.py), shape-checked;
    every annotated PNG it names must sit next to it and be a PNG."""
    if not path.exists():
        return None
    doc = _read_json(path)
    bad = f"{path}: corrupt navigation demo result"
    if (
        not isinstance(doc, dict)
        or not isinstance(doc.get("windows"), list)
        or not isinstance(doc.get("methods"), dict)
    ):
        raise ReportError(f"{bad}: expected an object with a 'windows' list and a 'methods' object")
    for key in ("per_sector", "min_landmark_km", "prior_offset_km", "false_fix_km"):
        if not _num_or_none(doc.get(key)):
            raise ReportError(f"{bad}: {key} is not a number")
    for m, res in doc["methods"].items():
        splits = res.get("splits") if isinstance(res, dict) else None
        if not isinstance(splits, dict):
            raise ReportError(f"{bad}: methods.{m} should have a 'splits' object")
        for s, r in splits.items():
            for part in ("headline", "all_windows"):
                _check_summary((r or {}).get(part) if isinstance(r, dict) else None, f"methods.{m}.{s}.{part}", bad)
    check = doc.get("map_check")  # optional: demos written before the catalogue check have none
    if check is not None:
        bins = check.get("bins") if isinstance(check, dict) else None
        if not isinstance(bins, list) or not all(
            isinstance(b, dict)
            and isinstance(b.get("diameter_km"), str)
            and all(is_num(b.get(k)) for k in ("listed", "landmarks"))
            and all(_num_or_none(b.get(k)) for k in ("recall", "precision"))
            for b in bins
        ):
            raise ReportError(f"{bad}: map_check should hold 'bins' (diameter_km, listed, recall, landmarks, ...)")
    for i, w in enumerate(doc["windows"]):
        where = f"windows[{i}]"
        if not isinstance(w, dict):
            raise ReportError(f"{bad}: {where} is not an object")
        for key in ("id", "method", "split", "png"):
            if not isinstance(w.get(key), str) or not w[key]:
                raise ReportError(f"{bad}: {where}.{key} missing or not text")
        for key in ("n_detections", "landmarks_in_view", "matched", "identified"):
            if not is_num(w.get(key)):
                raise ReportError(f"{bad}: {where}.{key} missing or not a number")
        _check_fix(w, where, bad)
        _check_png_next_to(path, w["png"], where, bad)
    if "catalogue_detection" in doc:  # optional: demos written before the catalogue scoring have none
        _check_catalogue(path, doc["catalogue_detection"], bad)
    return doc


def _check_png_next_to(path: Path, name: str, where: str, bad: str) -> None:
    """``name`` (``where``.png of the JSON file ``path``) is a file name of a PNG next to ``path``."""
    if Path(name).name != name:
        raise ReportError(f"{bad}: {where}.png should be a file name next to it, not {name!r}")
    if check_png(path.parent / name) is None:
        raise ReportError(f"{bad}: {where}.png names {path.parent / name}, which does not exist")


CATALOGUE_COUNTS = ("found", "missed", "false", "detections_15km")


def _check_catalogue(path: Path, cat, bad: str) -> None:
    """navigation.json's ``catalogue_detection`` (crater_synth/navigation/demo.py, ``demo_catalogue``): the
    catalogue, its windows' split, the pooled scores per method and per window the counts and PNG."""
    where = "catalogue_detection"
    if (
        not isinstance(cat, dict)
        or not isinstance(cat.get("windows"), list)
        or not isinstance(cat.get("methods"), dict)
    ):
        raise ReportError(f"{bad}: {where} should be an object with a 'windows' list and a 'methods' object")
    if not all(isinstance(cat.get(k), str) and cat[k] for k in ("source", "pole", "split")) or not is_num(
        cat.get("min_d_km")
    ):
        raise ReportError(f"{bad}: {where} should name its source, pole and split (text) and min_d_km (a number)")
    for m, s in cat["methods"].items():
        if not isinstance(s, dict) or not all(is_num(s.get(k)) for k in ("n_catalogue_15km", "n_detections_15km")):
            raise ReportError(f"{bad}: {where}.methods.{m} should hold n_catalogue_15km and n_detections_15km")
        if not all(_num_or_none(s.get(k)) for k in ("recall_15km", "precision_15km")):
            raise ReportError(f"{bad}: {where}.methods.{m} recall_15km or precision_15km is not a number")
    for i, w in enumerate(cat["windows"]):
        at = f"{where}.windows[{i}]"
        if not isinstance(w, dict) or not all(isinstance(w.get(k), str) and w[k] for k in ("id", "method", "png")):
            raise ReportError(f"{bad}: {at} should be an object with an id, a method and a png (text)")
        if w.get("split") != cat["split"]:
            raise ReportError(f"{bad}: {at}.split is {w.get('split')!r}, not the catalogue windows' {cat['split']!r}")
        if not all(is_num(w.get(k)) for k in CATALOGUE_COUNTS) or not all(
            _num_or_none(w.get(k)) for k in ("recall", "precision")
        ):
            raise ReportError(f"{bad}: {at} should hold the numbers {', '.join(CATALOGUE_COUNTS)}, recall, precision")
        _check_png_next_to(path, w["png"], at, bad)


def load_nav_frames(path: Path) -> dict | None:
    """A trajectory's ``nav-frames-eval --json`` result (crater_synth/navigation/rendered/evaluate.py),
    shape-checked: per frame the altitude, landmarks in view, detections, matches and the fixes of the
    detector and of the perfect-detection check."""
    if not path.exists():
        return None
    doc = _read_json(path)
    bad = f"{path}: corrupt nav-frames-eval result"
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list) or not doc["frames"]:
        raise ReportError(f"{bad}: expected an object with a non-empty 'frames' list")
    if not isinstance(doc.get("trajectory"), str):
        raise ReportError(f"{bad}: 'trajectory' missing or not text")
    for key in ("false_fix_km", "min_inliers", "min_landmark_km"):
        if not _num_or_none(doc.get(key)):
            raise ReportError(f"{bad}: {key} is not a number")
    summary = doc.get("summary")
    if not isinstance(summary, dict) or not isinstance(summary.get("perfect"), dict):
        raise ReportError(f"{bad}: 'summary' should hold the detector's and the perfect-detection summaries")
    for part in ("all", "headline"):
        _check_summary(summary.get(part), f"summary.{part}", bad)
        _check_summary(summary["perfect"].get(part), f"summary.perfect.{part}", bad)
    for i, f in enumerate(doc["frames"]):
        where = f"frames[{i}]"
        if not isinstance(f, dict) or not isinstance(f.get("perfect"), dict):
            raise ReportError(f"{bad}: {where} should be an object with a 'perfect' object")
        for key in ("index", "altitude_km", "ground_sample_m", "landmarks_in_view", "n_detections", "matched"):
            if not is_num(f.get(key)):
                raise ReportError(f"{bad}: {where}.{key} missing or not a number")
        _check_fix(f, where, bad)
        _check_fix(f["perfect"], f"{where}.perfect", bad)
    return doc


def nav_paths(run_dir: Path) -> tuple[Path, list[Path]]:
    """(the navigate-demo result, the trajectories' nav-frames-eval results) of ``RUN_DIR/navigation/``."""
    nav = run_dir / NAVIGATION_DIR
    return nav / DEMO_JSON, sorted(nav.glob(NAV_FRAMES_GLOB)) if nav.is_dir() else []
