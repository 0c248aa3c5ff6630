"""``crater-synth report RUN_DIR``: one self-contained HTML page summarising a run (docs/report.md).

Writes ``RUN_DIR/report/index.html`` plus its PNGs (relative links only: no external URL, no script),
built in a temporary directory inside RUN_DIR and swapped into place, so a reader never sees half a
report. Sections:

1. contact sheets per crater (:mod:`crater_synth.preview` on the dataset);
2. a real WAC crop beside the synthetic render at the closest geometry/illumination, as display
   originals and after the shared preprocessing (:mod:`train.preprocess`);
3. histograms of the network input, real vs synthetic, per crater;
4. the three classifiers' accuracies and confusion matrices (``metrics.json``, ``confusion_*.png``);
5. the closed-loop history (``loop_history.json``);
6. the Figure 6 experiments (``figure6.png``, ``experiments.csv``);
7. provenance of every data product and of the dataset, and the limits of the test set.

A missing input turns its section into a plain "not run: <what produces it>" note; a corrupt input
is one :class:`ReportError` naming the file. Never imports torch.
"""

from __future__ import annotations

import copy
import csv
import datetime as _dt
import html
import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import click
import numpy as np

from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.errors import UserError

MODELS = ("lunarnet_ex", "lunarsvm_ex", "hog_svm")
MODEL_LABELS = {"lunarnet_ex": "LunarNet_ex", "lunarsvm_ex": "LunarSVM_ex", "hog_svm": "HOG + linear SVM"}
MODEL_COLORS = {"lunarnet_ex": "#2563eb", "lunarsvm_ex": "#16a34a", "hog_svm": "#d97706"}
REAL_COLOR, SYN_COLOR, SENSOR_COLOR = "#d9480f", "#1c7ed6", "#5c7cfa"

REPORT_DIR = "report"
INDEX_FILE = "index.html"
METRICS_FILE = "metrics.json"
LOOP_FILE = "loop_history.json"
EXPERIMENTS_FILE = "experiments.csv"
FIGURE6_FILE = "figure6.png"
RUN_CONFIG_FILE = "config.yaml"          # the resolved config `crater-synth train` saves (train/trainer.py)
SUMMARY_FILE = "train_summary.json"
EXPERIMENT_COLUMNS = ("parameter", "count", "sigma", "model", "real_accuracy", "train_images")
LOOP_ROUND_FIELDS = ("round", "sun_elevation_count", "images", *MODELS, "render_s", "train_s")

# What produces each input, quoted in the "not run" notes: (what, command).
PRODUCERS = {
    "dataset": ("rendering a dataset (then point the report at it with train.dataset_dir=DIR)",
                "crater-synth dataset"),
    "metrics": ("training and evaluation (crater-synth evaluate for saved models)", "crater-synth train run_dir=RUN_DIR"),
    "loop": ("the closed loop (configs/loop)", "crater-synth loop run_dir=RUN_DIR"),
    "experiments": ("the Figure 6 experiments (configs/experiments)", "crater-synth experiments run_dir=RUN_DIR"),
}

SYNTHETIC_CHOICE = (
    "For each crater the synthetic render shown is the manifest row whose camera elevation is closest to 90° "
    "(nadir, like the map-projected mosaic), then the one with the highest sun elevation, then the highest lit "
    "fraction (ties: the first row in manifest order). The LROC WAC south-polar mosaic is a composite of many "
    "orbits under different illumination: it has no single sun direction, so no render can match its lighting "
    "exactly; the highest, best-lit Sun of the sweep is the closest analogue of a mosaic assembled for "
    "illumination. The real crop is the realset's own σ = 1.0 box centred on the crater with no slewing offset "
    "and no rotation.")


class ReportError(UserError):
    """A report input is corrupt (named in the message) or the run directory is unusable."""


# ------------------------------------------------------------------------------------------------
# Inputs: each loader returns None when the file is absent and raises ReportError when it is corrupt
# ------------------------------------------------------------------------------------------------
def _is_num(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _num_or_none(x) -> bool:
    return x is None or _is_num(x)


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
    """``metrics.json`` as written by train/evaluate.py, shape-checked."""
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
            if n < 1 or not all(isinstance(r, list) and len(r) == n and all(_is_num(v) for v in r) for r in conf):
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
            if not _is_num(r.get(key)):
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
            row = {"parameter": (rec["parameter"] or "").strip(), "count": int(float(rec["count"])),
                   "sigma": float(rec["sigma"]), "model": (rec["model"] or "").strip(),
                   "real_accuracy": float(acc) if acc else float("nan"),
                   "train_images": int(float(rec["train_images"]))}
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
        from PIL import Image

        with Image.open(path) as im:
            im.verify()
    except ImportError:  # pragma: no cover - Pillow comes with matplotlib
        pass
    except Exception as exc:  # noqa: BLE001 - any decoder complaint means a corrupt file
        raise ReportError(f"{path}: corrupt PNG ({exc})") from None
    return path


def load_run_config(path: Path) -> dict | None:
    """The resolved configuration saved by ``crater-synth train`` (RUN_DIR/config.yaml)."""
    if not path.exists():
        return None
    import yaml

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


# ------------------------------------------------------------------------------------------------
# Configuration: the run's saved config, with the command line's explicit overrides on top
# ------------------------------------------------------------------------------------------------
def _explicit_keys(overrides: Sequence[str]) -> list[str]:
    keys = []
    for o in overrides:
        if "=" not in o or o.startswith("~"):
            continue
        keys.append(o.split("=", 1)[0].lstrip("+").split("@", 1)[0])
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


@dataclass
class RunConfig:
    cfg: dict
    dataset_dir: Path | None
    dataset_dir_source: str
    saved: bool


def effective_config(run_dir: Path, overrides: Sequence[str] = ()) -> RunConfig:
    """The configuration the run used (RUN_DIR/config.yaml when train saved one, else the composed
    defaults), with every key given explicitly on the command line taken from the overrides."""
    from crater_synth.config import REPO_ROOT, compose, resolved

    composed = resolved(compose(list(overrides)))
    saved = load_run_config(run_dir / RUN_CONFIG_FILE)
    explicit = _explicit_keys(overrides)
    if saved is not None:
        cfg = copy.deepcopy(saved)
        for k, v in composed.items():            # sections an older saved config lacks
            cfg.setdefault(k, copy.deepcopy(v))
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


def _config_craters(cfg: Mapping) -> list[dict]:
    out = []
    for key, e in (cfg.get("crater") or {}).items():
        e = e or {}
        out.append({"name": str(e.get("name") or key), "lat": e.get("lat"), "lon": e.get("lon"),
                    "diameter_km": e.get("diameter_km")})
    return out


# ------------------------------------------------------------------------------------------------
# HTML helpers
# ------------------------------------------------------------------------------------------------
def esc(x) -> str:
    return html.escape(str(x), quote=True)


def pct(x, digits: int = 1) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{100.0 * float(x):.{digits}f}&#8239;%"


def acc_cell(x) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return '<td class="num na">–</td>'
    hue = 120.0 * max(0.0, min(1.0, float(x)))
    return f'<td class="num" style="background:hsl({hue:.0f},70%,90%)">{pct(x)}</td>'


def duration(s) -> str:
    if s is None or not math.isfinite(float(s)):
        return "–"
    s = float(s)
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min" if s < 7200 else f"{s / 3600:.2f} h"


def not_run(what: str, producer: str) -> str:
    desc, cmd = PRODUCERS[producer]
    return (f'<div class="notrun"><strong>not run:</strong> {esc(what)}. Produced by {esc(desc)}: '
            f'<code>{esc(cmd)}</code>.</div>')


def note(text: str, kind: str = "info") -> str:
    return f'<div class="note {kind}">{text}</div>'


def figure(src: str, caption: str, alt: str, width: int | None = None) -> str:
    w = f' style="max-width:{width}px"' if width else ""
    return (f'<figure{w}><a href="{esc(src)}"><img src="{esc(src)}" alt="{esc(alt)}"></a>'
            f"<figcaption>{caption}</figcaption></figure>")


def table(header: Sequence[str], rows: Iterable[Sequence[str]], cls: str = "") -> str:
    """``rows`` are pre-rendered cells: a string starting with ``<td`` is used as is, else escaped."""
    h = "".join(f"<th>{esc(c)}</th>" for c in header)
    body = []
    for r in rows:
        cells = "".join(c if str(c).startswith("<td") else f"<td>{esc(c)}</td>" for c in r)
        body.append(f"<tr>{cells}</tr>")
    return f'<div class="tablewrap"><table class="{cls}"><thead><tr>{h}</tr></thead><tbody>{"".join(body)}</tbody></table></div>'


# ------------------------------------------------------------------------------------------------
# Matplotlib helpers (Agg, object API: no global pyplot state)
# ------------------------------------------------------------------------------------------------
_RC = {"font.size": 9, "axes.titlesize": 9, "axes.labelsize": 9, "axes.spines.top": False,
       "axes.spines.right": False, "legend.fontsize": 8, "legend.frameon": False, "figure.dpi": 110}


def _new_figure(w: float, h: float):
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    return Figure(figsize=(w, h), dpi=110)


def _save(fig, path: Path) -> str:
    import matplotlib

    with matplotlib.rc_context(_RC):
        fig.savefig(path, dpi=110, facecolor="white")
    return path.name


def _rc():
    import matplotlib

    matplotlib.use("Agg")
    return matplotlib.rc_context(_RC)


# ------------------------------------------------------------------------------------------------
# The report
# ------------------------------------------------------------------------------------------------
@dataclass
class _Ctx:
    run_dir: Path
    out: Path
    rc: RunConfig
    metrics: dict | None
    rows: list[dict] | None                        # the rows the run trained on (train.select applied)
    all_rows: list[dict] | None                    # every row of the dataset's manifest
    craters: list[str]
    max_tiles: int
    hist_samples: int
    log: object = None
    real: dict = field(default_factory=dict)       # crater -> {"crop", "image"} (canonical σ=1 crop)
    real_error: str | None = None

    def say(self, msg: str) -> None:
        if self.log:
            self.log(msg)


def _dataset_rows(ds: Path | None) -> list[dict] | None:
    from crater_core import schema

    if ds is None or not (ds / schema.MANIFEST_NAME).is_file():
        return None
    return schema.load_manifest(ds)          # strict: a corrupt row is an error naming file:line


def _crater_order(metrics: dict | None, cfg: Mapping, rows: list[dict] | None) -> list[str]:
    names = list((metrics or {}).get("classes") or []) or [c["name"] for c in _config_craters(cfg)]
    for r in rows or ():
        if r["crater"] not in names:
            names.append(r["crater"])
    return names


# ---- 1. contact sheets ---------------------------------------------------------------------------
def section_contact(ctx: _Ctx) -> str:
    from crater_synth.preview import contact_sheet

    if ctx.rows is None:
        where = ctx.rc.dataset_dir or "train.dataset_dir (unset)"
        return not_run(f"no rendered dataset at {where}", "dataset")
    if not ctx.rows:
        if ctx.all_rows:
            return note(f"No row of {esc(ctx.rc.dataset_dir)} matches the run's train.select.", "warn")
        return not_run(f"the manifest of {ctx.rc.dataset_dir} has no rows", "dataset")
    parts, small = [], True
    for crater in ctx.craters:
        crows = [r for r in ctx.rows if r["crater"] == crater]
        if not crows:
            parts.append(note(f"{esc(crater)}: no renders in this dataset.", "warn"))
            continue
        ctx.say(f"contact sheet {crater} ({len(crows)} renders)")
        png = contact_sheet(crows, ctx.rc.dataset_dir, ctx.out / f"contact_{crater}.png",
                            f"{crater}: {len(crows)} renders (sun el/az, cam el/az in deg)\n"
                            f"red: projected rim; blue: sigma boxes", ctx.max_tiles)
        shown = min(ctx.max_tiles, len(crows))
        small = small and shown <= 9
        parts.append(figure(png.name, f"<b>{esc(crater)}</b>: {shown} of {len(crows):,} renders, evenly spread "
                            "over the manifest order (sun-major).", f"contact sheet {crater}"))
    lead = ('<p class="lead">Each tile is tone-mapped on its own (99.5th percentile of lit pixels → white, gamma 2.2; '
            'absolute I/F is in the EXR; <code>crater_synth.preview</code>). Red: the projected rim ellipse; blue dashed: '
            'the σ ROI boxes. Tile titles: sun elevation/azimuth, camera elevation/azimuth (degrees), lit fraction and '
            f'mean I/F. Dataset: <code>{esc(ctx.rc.dataset_dir)}</code>.</p>')
    return lead + (f'<div class="grid3">{"".join(parts)}</div>' if small else "".join(parts))


# ---- 2. real vs synthetic ------------------------------------------------------------------------
def _pick_synthetic(rows: Sequence[dict]) -> dict:
    from crater_core import schema

    return min(rows, key=lambda r: (abs(float(r["cam_elevation"]) - 90.0), -float(r["sun_elevation"]),
                                    -float(r["lit_fraction"]), schema.row_key(r)))


def _box_closest(boxes: Mapping[str, Sequence[float]], sigma: float = 1.0) -> tuple[str, list[float]]:
    key = min(boxes, key=lambda k: abs(float(k) - sigma))
    return key, [float(b) for b in boxes[key]]


def _real_plan(ctx: _Ctx, canonical: bool):
    """Crops (and images) of the real test set of the run's configuration; ``canonical``: one σ = 1.0
    crop per crater, centred, no offset, no rotation. Returns (crops, images) or None with
    ``ctx.real_error`` set when the real product is not installed."""
    from train.errors import RealSetError
    from train.realset import canonical_crater, plan_real_crops

    rs = dict(ctx.rc.cfg.get("realset") or {})
    if canonical:
        rs.update(per_crater=1, sigmas=[1.0], max_offset_frac=0.0, max_rotation_deg=0.0)
    cfg = dict(ctx.rc.cfg)
    cfg["realset"] = rs
    known = {canonical_crater(c) for c in ctx.craters}
    craters = [c for c in _config_craters(ctx.rc.cfg) if canonical_crater(c["name"]) in known]
    if not craters:
        ctx.real_error = "none of the report's craters is in the configuration's crater group"
        return None
    if rs.get("include_embedded", True) and not (rs.get("mosaic") or {}).get("path"):
        from data_manifest.products import ProductError, embedded_path

        try:
            embedded_path(str(rs.get("source_product") or "lroc_wac_south"))
        except ProductError as exc:   # not installed here: a note, not a failure
            ctx.real_error = str(exc)
            return None
    try:
        return plan_real_crops(cfg, craters, [c["name"] for c in craters])
    except RealSetError as exc:
        raise ReportError(f"real test set: {exc}") from None


def _stretch(x: np.ndarray, lo: float = 0.5, hi: float = 99.5) -> np.ndarray:
    a, b = np.percentile(x, [lo, hi])
    return np.clip((x - a) / max(b - a, 1e-9), 0.0, 1.0)


def section_compare(ctx: _Ctx) -> str:
    from crater_synth.preview import _ellipse_points, read_channel, tone_map
    from train.preprocess import PreprocessConfig, SensorModel, preprocess_crop, resample_box
    from train.realset import canonical_crater

    if ctx.rows is None or not ctx.rows:
        return not_run("no rendered dataset to compare with", "dataset")
    plan = _real_plan(ctx, canonical=True)
    if plan is None:
        return note(f"Real crops unavailable: {esc(ctx.real_error)}", "warn")
    crops, images = plan
    pp = PreprocessConfig.from_config(ctx.rc.cfg)
    sensor = SensorModel.from_config(ctx.rc.cfg.get("sensor"))
    parts = [f'<p class="lead">{esc(SYNTHETIC_CHOICE)}</p>',
             f'<p class="lead">Top row: display originals — the real crop as stored (8-bit DN of the WAC mosaic, only '
             f'stretched for display) and the synthetic σ ≈ 1.0 crop (I/F, tone-mapped), each at its native pixel '
             f'count, plus the whole synthetic render with its σ box. Bottom row: the same crops after the one shared '
             f'preprocessing path (<code>train.preprocess.preprocess_crop</code>: resample to {pp.size}×{pp.size}, '
             f'robust normalisation, shadow dead zone, gamma {pp.gamma}) — what the classifiers see; right: with the '
             f'seeded sensor model that training adds to synthetic images (real crops never get it).</p>']
    for crater in ctx.craters:
        crows = [r for r in ctx.rows if r["crater"] == crater]
        real = [c for c in crops if canonical_crater(c.crater) == canonical_crater(crater)]
        real = sorted(real, key=lambda c: (c.kind != "embedded", c.index))
        if not crows or not real:
            missing = "renders" if not crows else "a real crop (not in the configured crater group)"
            parts.append(note(f"{esc(crater)}: no {missing}; nothing to compare.", "warn"))
            continue
        rc, row = real[0], _pick_synthetic(crows)
        ctx.real[crater] = {"crop": rc}
        ctx.say(f"real vs synthetic {crater}")
        img = images[rc.image_path]
        side_r = rc.box[2] - rc.box[0]
        n_r = max(8, int(round(side_r)))
        real_orig = resample_box(img, rc.box, n_r, rc.rotation_deg, True, 1)
        if np.issubdtype(img.dtype, np.integer):
            real_orig = real_orig / float(np.iinfo(img.dtype).max)
        real_pp = preprocess_crop(img, rc.box, pp, rotation_deg=rc.rotation_deg)
        i_f = read_channel(ctx.rc.dataset_dir / row["path"])
        skey, sbox = _box_closest(row["sigma_boxes"], 1.0)
        n_s = max(8, int(round(sbox[2] - sbox[0])))
        syn_orig = tone_map(resample_box(i_f, sbox, n_s, 0.0, True, 1))
        syn_pp = preprocess_crop(i_f, sbox, pp)
        syn_sens = (preprocess_crop(i_f, sbox, pp, sensor=sensor, rng=np.random.default_rng(int(row["seed"])))
                    if sensor.enabled else None)
        with _rc():
            fig = _new_figure(8.8, 6.4)
            axes = fig.subplots(2, 3)
            for ax in axes.ravel():
                ax.set_xticks([])
                ax.set_yticks([])
                for sp in ax.spines.values():
                    sp.set_visible(True)
            axes[0, 0].set_ylabel("display original", fontsize=10, fontweight="bold")
            axes[1, 0].set_ylabel(f"after preprocessing\n({pp.size}×{pp.size} network input)", fontsize=10,
                                  fontweight="bold")
            a = axes[0, 0]
            a.imshow(_stretch(real_orig), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            a.set_title(f"real WAC crop, {n_r}×{n_r} mosaic px\n8-bit DN, 0.5–99.5 % stretch")
            a = axes[0, 1]
            a.imshow(syn_orig, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            a.set_title(f"synthetic σ={skey} crop, {n_s}×{n_s} px\nI/F tone-mapped, gamma 2.2")
            a = axes[0, 2]
            a.imshow(tone_map(i_f), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            u0, v0, u1, v1 = sbox
            a.plot([u0, u1, u1, u0, u0], [v0, v0, v1, v1, v0], "--", color="#50c0ff", lw=0.9)
            pts = _ellipse_points(row["rim_ellipse"])
            a.plot(pts[:, 0], pts[:, 1], "-", color="#ff5050", lw=0.8)
            a.set_xlim(-0.5, i_f.shape[1] - 0.5)
            a.set_ylim(i_f.shape[0] - 0.5, -0.5)
            a.set_title(f"whole synthetic render ({i_f.shape[1]}×{i_f.shape[0]})\nred: rim, blue: σ box")
            for a, im, t in ((axes[1, 0], real_pp, "real"), (axes[1, 1], syn_pp, "synthetic"),
                             (axes[1, 2], syn_sens, "synthetic + sensor model (training)")):
                a.set_title(t)
                if im is None:
                    a.text(0.5, 0.5, "sensor model disabled", ha="center", va="center", transform=a.transAxes)
                    continue
                a.imshow(im, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            fig.suptitle(f"{crater}: real WAC vs closest synthetic render "
                         f"(sun el {row['sun_elevation']:.2f}°, az {row['sun_azimuth']:.0f}°; "
                         f"camera el {row['cam_elevation']:.0f}°, az {row['cam_azimuth']:.0f}°)", fontsize=10.5)
            fig.tight_layout()
            name = _save(fig, ctx.out / f"compare_{crater}.png")
        cap = (f"<b>{esc(crater)}</b>. Real: box {', '.join(f'{b:.1f}' for b in rc.box)} "
               f"(mosaic px), σ = {rc.sigma:.1f}, rotation {rc.rotation_deg:.0f}°, source <code>{esc(rc.source)}</code>. "
               f"Synthetic: <code>{esc(row['path'])}</code>, lit fraction {row['lit_fraction']:.2f}, "
               f"mean I/F {row['mean_if']:.4f}.")
        parts.append(figure(name, cap, f"real vs synthetic {crater}"))
    return "".join(parts)


# ---- 3. histograms -------------------------------------------------------------------------------
def section_histograms(ctx: _Ctx) -> str:
    from crater_synth.preview import read_channel
    from train.preprocess import PreprocessConfig, SensorModel, preprocess_crop
    from train.realset import canonical_crater

    if ctx.rows is None or not ctx.rows:
        return not_run("no rendered dataset to compare with", "dataset")
    plan = _real_plan(ctx, canonical=False)
    if plan is None:
        return note(f"Real crops unavailable: {esc(ctx.real_error)}", "warn")
    crops, images = plan
    pp = PreprocessConfig.from_config(ctx.rc.cfg)
    sensor = SensorModel.from_config(ctx.rc.cfg.get("sensor"))
    bins = np.linspace(0.0, 1.0, 41)
    panels, stats = [], []
    for crater in ctx.craters:
        crows = [r for r in ctx.rows if r["crater"] == crater]
        rcs = [c for c in crops if canonical_crater(c.crater) == canonical_crater(crater)]
        if not crows or not rcs:
            continue
        ctx.say(f"histograms {crater}: {len(rcs)} real crops, {min(len(crows), ctx.hist_samples)} renders")
        real = np.stack([preprocess_crop(images[c.image_path], c.box, pp, rotation_deg=c.rotation_deg) for c in rcs])
        pick = [crows[i] for i in np.unique(np.linspace(0, len(crows) - 1,
                                                       min(ctx.hist_samples, len(crows))).astype(int))]
        syn, sens = [], []
        for row in pick:
            i_f = read_channel(ctx.rc.dataset_dir / row["path"])
            rng = np.random.default_rng(int(row["seed"]))
            for box in row["sigma_boxes"].values():
                syn.append(preprocess_crop(i_f, box, pp))
                if sensor.enabled:
                    sens.append(preprocess_crop(i_f, box, pp, sensor=sensor, rng=rng))
        panels.append((crater, real, np.stack(syn), np.stack(sens) if sens else None, len(rcs), len(pick)))
    if not panels:
        return note("No crater has both renders and real crops.", "warn")
    with _rc():
        n = len(panels)
        cols = min(3, n)
        nrows = int(math.ceil(n / cols))
        fig = _new_figure(3.6 * cols, 2.9 * nrows)
        axes = np.atleast_1d(fig.subplots(nrows, cols, squeeze=False)).ravel()
        for ax in axes[n:]:
            ax.axis("off")
        for ax, (crater, real, syn, sens, nr, ns) in zip(axes, panels):
            hr, _ = np.histogram(real, bins=bins, density=True)
            hs, _ = np.histogram(syn, bins=bins, density=True)
            width = bins[1] - bins[0]
            overlap = float(np.sum(np.minimum(hr, hs)) * width)
            ax.stairs(hr, bins, color=REAL_COLOR, lw=1.6, label=f"real ({nr} crops)")
            ax.stairs(hs, bins, color=SYN_COLOR, lw=1.6, label=f"synthetic ({syn.shape[0]} crops)")
            row_stats = [crater, f"{nr}", f"{float(np.mean(real == 0)):.1%}", f"{real.mean():.3f}",
                         f"{syn.shape[0]}", f"{float(np.mean(syn == 0)):.1%}", f"{syn.mean():.3f}"]
            if sens is not None:
                hz, _ = np.histogram(sens, bins=bins, density=True)
                ax.stairs(hz, bins, color=SENSOR_COLOR, lw=1.1, ls="--", label="synthetic + sensor model")
                row_stats += [f"{float(np.mean(sens == 0)):.1%}", f"{sens.mean():.3f}"]
            else:
                row_stats += ["–", "–"]
            row_stats.append(f"{overlap:.2f}")
            stats.append(row_stats)
            ax.set_yscale("log")
            ax.set_xlim(0, 1)
            ax.set_xlabel("normalised intensity after preprocessing")
            ax.set_ylabel("density (log)")
            ax.set_title(f"{crater}  (overlap real/synthetic {overlap:.2f})")
            ax.legend(loc="upper center")
        fig.tight_layout()
        name = _save(fig, ctx.out / "histograms.png")
    cap = ("Distribution of pixel values of the classifier input (after <code>train.preprocess</code>: 150×150, "
           "robust black/white levels, shadow dead zone, gamma) for every real test crop of the crater (the "
           "configured realset: all σ, slewing offsets and rotations) and for an evenly spread sample of up to "
           f"{ctx.hist_samples} renders per crater at every σ box, without and with the seeded sensor model. "
           "Log density; the spike at 0 is shadow. The normalisation removes absolute brightness, so I/F (synthetic) "
           "and 8-bit DN (real) become comparable: the remaining difference is the shape of the distribution "
           "(shadow fraction, contrast). Overlap = Σ min(p_real, p_synthetic) · bin width (1 = identical).")
    tab = table(["crater", "real crops", "real zero (shadow)", "real mean", "synthetic crops", "synthetic zero",
                 "synthetic mean", "+sensor zero", "+sensor mean", "overlap"], stats)
    return figure(name, cap, "histograms real vs synthetic") + tab


# ---- 4. models -----------------------------------------------------------------------------------
def _plot_confusion(path: Path, conf, classes: Sequence[str], title: str) -> str:
    """Re-plot a confusion matrix from metrics.json with the training stage's own plotter."""
    from train.evaluate import plot_confusion

    plot_confusion(path, conf, classes, title)
    return path.name


def section_models(ctx: _Ctx) -> str:
    m = ctx.metrics
    if m is None:
        return not_run(f"no {ctx.run_dir / METRICS_FILE}", "metrics")
    classes = list(m.get("classes") or [])
    present = [k for k in MODELS if k in m]
    parts = []
    absent = [MODEL_LABELS[k] for k in MODELS if k not in m]
    if absent:
        parts.append(note(f"metrics.json has no entry for {esc(', '.join(absent))}.", "warn"))
    rows = []
    for k in present:
        e = m[k]
        rows.append([f'<td><span class="dot" style="background:{MODEL_COLORS[k]}"></span>{esc(MODEL_LABELS[k])}</td>',
                     acc_cell(e.get("real_accuracy")), acc_cell(e.get("real_accuracy_class_mean")),
                     acc_cell(e.get("val_accuracy"))])
    parts.append("<h3>Overall</h3>" + table(["model", "real accuracy", "real, class-mean", "validation (synthetic)"],
                                            rows, "acc"))
    for key, label in (("per_crater", "crater"), ("per_sigma", "ROI σ"), ("per_source", "real source")):
        cols = []
        for k in present:
            for c in m[k].get(key) or {}:
                if c not in cols:
                    cols.append(c)
        if key == "per_sigma":
            cols.sort(key=lambda s: float(s) if str(s).replace(".", "", 1).isdigit() else 0.0)
        if not cols:
            continue
        trs = [[MODEL_LABELS[k], *[acc_cell((m[k].get(key) or {}).get(c)) for c in cols]] for k in present]
        head = [f"σ = {c}" if key == "per_sigma" else str(c) for c in cols]
        counts = m.get("test_per_crater") if key == "per_crater" else None
        if counts:
            head = [f"{h} (n={counts.get(c, '?')})" for h, c in zip(head, cols)]
        parts.append(f"<h3>Real accuracy per {esc(label)}</h3>" + table(["model", *head], trs, "acc"))
    figs = []
    for k in present:
        src = check_png(ctx.run_dir / f"confusion_{k}.png")
        title = f"{MODEL_LABELS[k]}: real accuracy {pct(m[k].get('real_accuracy'))}"
        if src is not None:
            shutil.copyfile(src, ctx.out / src.name)
            figs.append(figure(src.name, f"{title} — <code>{esc(src.name)}</code> as written by "
                               "<code>crater-synth evaluate</code>. Rows: true crater, columns: predicted; "
                               "counts and row-normalised fractions.", f"confusion {k}", 420))
        elif m[k].get("confusion") is not None:
            cls = classes or [str(i) for i in range(len(m[k]["confusion"]))]
            name = _plot_confusion(ctx.out / f"confusion_{k}.png", m[k]["confusion"], cls,
                                   f"{MODEL_LABELS[k]}: real accuracy {pct(m[k].get('real_accuracy')).replace('&#8239;', ' ')}")
            figs.append(figure(name, f"{title} — re-plotted from <code>metrics.json</code> (no "
                               f"<code>confusion_{k}.png</code> in the run). Rows: true crater, columns: predicted; "
                               "counts and row-normalised fractions.", f"confusion {k}", 420))
        else:
            figs.append(note(f"{esc(MODEL_LABELS[k])}: no confusion matrix in metrics.json and no "
                             f"confusion_{k}.png.", "warn"))
    parts.append('<h3>Confusion matrices (real test crops)</h3><div class="grid3">' + "".join(figs) + "</div>")
    def count(v):
        return f"{int(v):,}" if _is_num(v) else "–"

    facts = [("classes", ", ".join(classes) or "–"), ("training images (synthetic)", count(m.get("train_images"))),
             ("validation images (synthetic)", count(m.get("val_images"))), ("real test images", count(m.get("test_images"))),
             ("real test sources", ", ".join(m.get("test_sources") or []) or "–")]
    if _is_num(m.get("evaluate_seconds")):
        facts.append(("evaluation time", f"{m['evaluate_seconds']:.1f} s"))
    parts.append(table(["", ""], facts, "kv"))
    return "".join(parts)


# ---- 5. closed loop ------------------------------------------------------------------------------
def section_loop(ctx: _Ctx) -> str:
    path = ctx.run_dir / LOOP_FILE
    doc = load_loop_history(path)
    if doc is None:
        return not_run(f"no {path}", "loop")
    rounds = sorted(doc["rounds"], key=lambda r: r["round"])
    thr = doc.get("threshold")
    parts = []
    stop = doc.get("stopped_because")
    summary = [f"{len(rounds)} round(s)"]
    if thr is not None:
        summary.append(f"threshold {pct(thr)} real accuracy")
    if stop:
        summary.append(f"stopped because: <b>{esc(stop)}</b>")
    parts.append(f'<p class="lead">{"; ".join(summary)}.</p>')
    if not rounds:
        return "".join(parts) + note("The loop history has no rounds.", "warn")
    nan = float("nan")
    x = np.array([r["sun_elevation_count"] for r in rounds], dtype=float)
    with _rc():
        fig = _new_figure(10.0, 3.6)
        ax, ax2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.4, 1.0]})
        for k in MODELS:
            y = np.array([nan if r.get(k) is None else 100.0 * r[k] for r in rounds], dtype=float)
            if np.all(np.isnan(y)):
                continue
            ax.plot(x, y, "o-", color=MODEL_COLORS[k], label=MODEL_LABELS[k], lw=1.6, ms=5)
        if thr is not None:
            ax.axhline(100.0 * thr, color="#868e96", ls="--", lw=1, label=f"threshold {100 * thr:.0f} %")
        for r in rounds:
            ax.annotate(f"r{r['round']}", (r["sun_elevation_count"], 0), xytext=(0, 3), textcoords="offset points",
                        ha="center", fontsize=7, color="#868e96")
        ax.set_xticks(sorted(set(x.tolist())))
        ax.set_ylim(0, 102)
        ax.set_xlabel("sun-elevation sample count (round rN)")
        ax.set_ylabel("real accuracy (%)")
        ax.set_title("accuracy on real crops per loop round")
        ax.legend(loc="lower right")
        idx = np.arange(len(rounds))
        rs = np.array([r.get("render_s") or 0.0 for r in rounds], dtype=float) / 60.0
        ts = np.array([r.get("train_s") or 0.0 for r in rounds], dtype=float) / 60.0
        ax2.bar(idx, rs, color="#adb5bd", label="render")
        ax2.bar(idx, ts, bottom=rs, color="#495057", label="train + evaluate")
        for i, r in enumerate(rounds):
            if r.get("images") is not None:
                ax2.annotate(f"{int(r['images']):,} img", (i, rs[i] + ts[i]), xytext=(0, 2),
                             textcoords="offset points", ha="center", fontsize=7)
        ax2.set_xticks(idx, [f"r{r['round']}\n({r['sun_elevation_count']})" for r in rounds])
        ax2.set_ylabel("minutes")
        ax2.set_title("time per round")
        ax2.legend(loc="upper left")
        fig.tight_layout()
        name = _save(fig, ctx.out / "loop.png")
    parts.append(figure(name, "Closed loop (paper Fig. 3): after each round the models are tested on the real crops; "
                        "while the real accuracy is below the threshold, the sun-elevation sample count is raised, only "
                        "the new samples are rendered and the models retrained. Left: real accuracy of each model per "
                        "round against the sun-elevation count; right: wall time of each round (render and "
                        "train/evaluate), labelled with the training-set size.", "loop history"))
    def num(v):
        return f"{int(v):,}" if _is_num(v) else "–"

    trs = [[f"{r['round']}", f"{r['sun_elevation_count']}", num(r.get("images")), num(r.get("renders_new")),
            *[acc_cell(r.get(k)) for k in MODELS],
            duration(r.get("render_s")), duration(r.get("train_s"))] for r in rounds]
    parts.append(table(["round", "sun-el. count", "training images", "new renders", *[MODEL_LABELS[k] for k in MODELS],
                        "render", "train + evaluate"], trs, "acc"))
    return "".join(parts)


# ---- 6. Figure 6 ---------------------------------------------------------------------------------
def _replot_figure6(rows: list[dict], path: Path) -> str:
    params = list(dict.fromkeys(r["parameter"] for r in rows))
    sigmas = sorted({r["sigma"] for r in rows})
    models = [m for m in MODELS if any(r["model"] == m for r in rows)] + \
             sorted({r["model"] for r in rows} - set(MODELS))
    styles = ["-", "--", ":", "-."]
    import matplotlib

    cmap = matplotlib.colormaps["viridis"]
    with _rc():
        fig = _new_figure(3.0 * len(params) + 0.6, 3.2)
        axes = np.atleast_1d(fig.subplots(1, len(params), squeeze=False)).ravel()
        for ax, p in zip(axes, params):
            for si, s in enumerate(sigmas):
                color = cmap(0.15 + 0.7 * si / max(1, len(sigmas) - 1))
                for mi, mdl in enumerate(models):
                    pts = sorted((r["count"], r["real_accuracy"]) for r in rows
                                 if r["parameter"] == p and r["sigma"] == s and r["model"] == mdl)
                    if pts:
                        ax.plot([c for c, _ in pts], [100 * a for _, a in pts], styles[mi % 4], marker="o", ms=3,
                                color=color, label=f"σ={s:.1f} {MODEL_LABELS.get(mdl, mdl)}")
            ax.set_title(p.replace("_", " "))
            ax.set_xticks(sorted({r["count"] for r in rows if r["parameter"] == p}))
            ax.set_xlabel("sample count")
            ax.set_ylim(0, 102)
        axes[0].set_ylabel("real accuracy (%)")
        axes[-1].legend(loc="lower right", fontsize=6)
        fig.tight_layout()
        return _save(fig, path)


def section_figure6(ctx: _Ctx) -> str:
    csv_path, png_path = ctx.run_dir / EXPERIMENTS_FILE, ctx.run_dir / FIGURE6_FILE
    rows = load_experiments(csv_path)
    png = check_png(png_path)
    if rows is None and png is None:
        return not_run(f"no {csv_path} and no {png_path}", "experiments")
    parts = []
    cap = ("Figure 6 of the paper: accuracy on the real crops as a function of each sweep parameter's sample count "
           "(the other parameters at their maximum), one panel per parameter, one curve per ROI σ, for LunarNet_ex "
           "and LunarSVM_ex.")
    if png is not None:
        shutil.copyfile(png, ctx.out / "figure6.png")
        parts.append(figure("figure6.png", cap + " <code>figure6.png</code> as written by the experiments.", "figure 6"))
    elif rows:
        name = _replot_figure6(rows, ctx.out / "figure6_replot.png")
        parts.append(note(f"No {esc(png_path.name)} in the run: re-plotted from {esc(csv_path.name)}.", "warn"))
        parts.append(figure(name, cap + " Re-plotted from <code>experiments.csv</code>; line style = model, "
                            "colour = σ.", "figure 6 (re-plotted)"))
    if rows is None:
        parts.append(not_run(f"no {csv_path} (the table behind the figure)", "experiments"))
        return "".join(parts)
    if not rows:
        parts.append(note(f"{esc(csv_path.name)} has no rows.", "warn"))
        return "".join(parts)
    for p in dict.fromkeys(r["parameter"] for r in rows):
        prow = [r for r in rows if r["parameter"] == p]
        keys = sorted({(r["model"], r["sigma"]) for r in prow},
                      key=lambda k: (MODELS.index(k[0]) if k[0] in MODELS else 9, k[1]))
        counts = sorted({r["count"] for r in prow})
        look = {(r["count"], r["model"], r["sigma"]): r for r in prow}
        trs = []
        for c in counts:
            imgs = {look[(c, mdl, s)]["train_images"] for mdl, s in keys if (c, mdl, s) in look}
            trs.append([str(c), ", ".join(f"{i:,}" for i in sorted(imgs)),
                        *[acc_cell(look[(c, mdl, s)]["real_accuracy"]) if (c, mdl, s) in look else acc_cell(None)
                          for mdl, s in keys]])
        parts.append(f"<h3>{esc(p.replace('_', ' '))}</h3>" +
                     table(["count", "train images", *[f"{MODEL_LABELS.get(mdl, mdl)} σ={s:.1f}" for mdl, s in keys]],
                           trs, "acc"))
    return "".join(parts)


# ---- 7. provenance -------------------------------------------------------------------------------
def _product_rows(cfg: Mapping) -> list[list[str]]:
    from data_manifest import products as P

    out = []
    data_dir = Path(str(cfg.get("data_dir") or "data"))
    for pid, p in P.load_products().items():
        if p["source"] == "embedded":
            pinned = p["sha256"]
            try:
                path = P.embedded_path(pid)
                actual = P.cached_sha256(path)
                status = ("embedded, sha256 verified" if actual == pinned else
                          f"embedded, sha256 MISMATCH ({actual[:12]}…)")
                cls = "ok" if actual == pinned else "bad"
            except P.ProductError as exc:
                path, status, cls = p["package_path"], f"missing: {exc}", "bad"
            where = f"{p['package']} {p['package_version']}: {path}"
        else:
            files = p.get("files") or []
            pinned = ", ".join(f["sha256"] for f in files if f.get("sha256")) or "not pinned"
            base = P.products_dir(data_dir)
            have = [f for f in files if (base / f["name"]).is_file()]
            if not files:
                status, cls = "missing (no file pinned yet)", "na"
            elif len(have) == len(files):
                status, cls = "downloaded (present)", "ok"
            else:
                status, cls = f"missing ({len(have)}/{len(files)} files; crater-synth fetch-data {pid})", "na"
            where = str(base / (p.get("open") or "")) if files else "–"
        out.append([f"<td><code>{esc(pid)}</code><div class='sub'>{esc(p.get('title', ''))}</div></td>",
                    p["source"], f"<td class='path'>{esc(where)}<div class='hash'>sha256 {esc(pinned)}</div></td>",
                    p.get("licence", "–"), f"<td class='st {cls}'>{esc(status)}</td>"])
    return out


def section_provenance(ctx: _Ctx) -> str:
    from crater_core import schema

    parts = [f'<div class="limits"><b>Limits of the test set.</b> {esc(_limits_text(ctx))}</div>']
    parts.append("<h3>Data products</h3>")
    parts.append(table(["product", "source", "file and pinned sha256", "licence", "status"],
                       _product_rows(ctx.rc.cfg), "prov"))
    parts.append("<h3>Dataset</h3>")
    ds = ctx.rc.dataset_dir
    if ctx.all_rows is None:
        parts.append(not_run(f"no rendered dataset at {ds or 'train.dataset_dir (unset)'}", "dataset"))
    else:
        rows = ctx.all_rows
        per = {c: sum(r["crater"] == c for r in rows) for c in dict.fromkeys(r["crater"] for r in rows)}
        axes = {k: sorted({round(float(r[k]), 4) for r in rows})
                for k in ("sun_elevation", "sun_azimuth", "cam_elevation", "cam_azimuth")}
        sigmas = sorted({k for r in rows for k in r["sigma_boxes"]}, key=float)
        facts = [("dataset directory", str(ds)), ("chosen from", ctx.rc.dataset_dir_source),
                 ("manifest", f"{ds / schema.MANIFEST_NAME} (sha256 {schema.sha256_file(ds / schema.MANIFEST_NAME)})"),
                 ("manifest rows", f"{len(rows):,}"),
                 ("rows the run trained on", f"{len(ctx.rows):,} (train.select: a subset of the sweep grid, as in the "
                  "closed loop and the Figure 6 experiments; sections 1–3 show this subset)"
                  if len(ctx.rows) != len(rows) else "all"),
                 ("rows per crater", ", ".join(f"{c}: {n:,}" for c, n in per.items())),
                 ("code_version", ", ".join(sorted({r["code_version"] for r in rows}))),
                 ("renderer", ", ".join(sorted({r["renderer"] for r in rows}))),
                 ("terrain_ids", ", ".join(sorted({r["terrain_id"] for r in rows}))),
                 ("render digests", ", ".join(sorted({r["render_digest"] for r in rows}))),
                 ("schema_version", ", ".join(str(v) for v in sorted({r["schema_version"] for r in rows}))),
                 ("ROI σ boxes", ", ".join(sigmas))]
        for k, v in axes.items():
            shown = ", ".join(f"{x:g}" for x in v[:12]) + (" …" if len(v) > 12 else "")
            facts.append((f"{k.replace('_', ' ')} ({len(v)} values, °)", shown))
        parts.append(table(["", ""], facts, "kv"))
    parts.append("<h3>Run</h3>")
    cfg = ctx.rc.cfg
    facts = [("run directory", str(ctx.run_dir.resolve())),
             ("configuration", f"{ctx.run_dir / RUN_CONFIG_FILE}" if ctx.rc.saved else
              "composed defaults + command-line overrides (the run saved no config.yaml)"),
             ("sweep", str((cfg.get("sweep") or {}).get("name", "–"))), ("seed", str(cfg.get("seed", "–"))),
             ("craters", ", ".join(c["name"] for c in _config_craters(cfg)))]
    summ = load_summary(ctx.run_dir / SUMMARY_FILE)
    if summ is not None:
        info = summ.get("data") or {}
        facts += [("training / validation images", f"{summ.get('train_images', '–')} / {summ.get('val_images', '–')}"),
                  ("validation split", f"by {info.get('split_by', '–')}, {info.get('val_groups') and len(info['val_groups'])} "
                                       f"of {info.get('groups', '–')} groups held out"),
                  ("training σ", ", ".join(str(s) for s in info.get("sigmas") or []) or "–")]
    rs = cfg.get("realset") or {}
    facts += [("real test set", f"{rs.get('source_product', '–')}: {rs.get('per_crater', '–')} crops per crater, "
                                f"σ {rs.get('sigmas', '–')}, offsets ±{rs.get('max_offset_frac', '–')} × side, "
                                f"rotations ±{rs.get('max_rotation_deg', '–')}°, seed {rs.get('seed', '–')}"
                                + (f"; labels file {rs['labels_file']}" if rs.get("labels_file") else ""))]
    parts.append(table(["", ""], facts, "kv"))
    return "".join(parts)


def _limits_text(ctx: _Ctx) -> str:
    from train.realset import LIMITS_NOTE

    rs = ctx.rc.cfg.get("realset") or {}
    m = ctx.metrics or {}
    per = m.get("test_per_crater") or {}
    n = max(per.values()) if per else rs.get("per_crater", 300)
    embedded = rs.get("include_embedded", True)
    run_note = m.get("limits")
    if m and "one real observation per crater" not in str(run_note or "").lower():
        embedded = False                      # the run tested on labels-file frames only
    if not embedded:
        return str(run_note or LIMITS_NOTE)
    text = (f"The embedded real test set is ONE real LROC WAC observation per crater, seen {n} ways (σ, slewing "
            f"offsets and rotations of the same mosaic pixels, {rs.get('source_product', 'lroc_wac_south')}). Crops "
            "of the same crater are strongly correlated: the accuracies measure recognition of that single "
            "observation, not generalisation over real illumination conditions, and per-crater results tend to be "
            "all-or-nothing.")
    if rs.get("labels_file"):
        text += f" Frames from the labels file {rs['labels_file']} are tested as well."
    return text


# ---- page ------------------------------------------------------------------------------------------
SECTIONS = (
    ("contact", "1. Contact sheets", section_contact),
    ("compare", "2. Real vs synthetic", section_compare),
    ("histograms", "3. Input histograms", section_histograms),
    ("models", "4. Classifiers", section_models),
    ("loop", "5. Closed loop", section_loop),
    ("figure6", "6. Figure 6 experiments", section_figure6),
    ("provenance", "7. Provenance & limits", section_provenance),
)

INTROS = {
    "contact": "What the renderer produced: a sample of the synthetic dataset per crater.",
    "compare": "Does a render look like the real image? The real WAC crop beside the closest synthetic render.",
    "histograms": "Do the two domains look alike to the classifier? Pixel statistics of the network input.",
    "models": "Accuracy on the real crops (test) and on the synthetic validation split.",
    "loop": "The closed loop: rounds of rendering more sun elevations until the real accuracy reaches the threshold.",
    "figure6": "Accuracy against the number of samples of each sweep parameter.",
    "provenance": "Where every input came from, and what the test set can and cannot tell.",
}

CSS = """
:root{--fg:#1f2933;--muted:#616e7c;--line:#e4e7eb;--bg:#f5f7fa;--card:#fff;--accent:#2563eb}
*{box-sizing:border-box}
body{margin:0;font:15px/1.55 -apple-system,"Segoe UI",Roboto,"Helvetica Neue",Arial,"Noto Sans",sans-serif;
 color:var(--fg);background:var(--bg)}
header{background:linear-gradient(135deg,#0b1220,#1e293b);color:#f8fafc;padding:28px 0 22px}
.wrap{max-width:1180px;margin:0 auto;padding:0 24px}
header h1{margin:0 0 4px;font-size:26px;font-weight:650;letter-spacing:-.01em}
header .meta{color:#cbd5e1;font-size:13px}
.cards{display:flex;gap:16px;margin:20px 0 6px;flex-wrap:wrap}
.card{flex:1 1 220px;background:rgba(255,255,255,.07);border:1px solid rgba(255,255,255,.14);border-radius:10px;
 padding:14px 18px}
.card .label{font-size:13px;color:#cbd5e1;display:flex;align-items:center;gap:8px}
.card .big{font-size:44px;font-weight:700;line-height:1.1;margin:4px 0 2px;font-variant-numeric:tabular-nums}
.card .small{font-size:12.5px;color:#94a3b8}
.card.na .big{color:#94a3b8}
header .facts{font-size:13px;color:#cbd5e1;margin-top:10px}
nav{position:sticky;top:0;z-index:5;background:rgba(255,255,255,.96);border-bottom:1px solid var(--line);
 backdrop-filter:blur(4px)}
nav .wrap{display:flex;gap:4px;flex-wrap:wrap;padding-top:6px;padding-bottom:6px}
nav a{color:var(--fg);text-decoration:none;font-size:13.5px;padding:5px 10px;border-radius:6px}
nav a:hover{background:#eef2ff;color:var(--accent)}
main{padding:10px 0 40px}
section{background:var(--card);border:1px solid var(--line);border-radius:12px;padding:20px 26px 18px;
 margin:22px 0;box-shadow:0 1px 2px rgba(16,24,40,.04)}
section h2{margin:0 0 2px;font-size:21px;font-weight:650}
section h2 a.anchor{color:#cbd2d9;text-decoration:none;margin-left:8px;font-weight:400}
section h2 a.anchor:hover{color:var(--accent)}
section .intro{color:var(--muted);margin:0 0 14px}
h3{font-size:15.5px;margin:20px 0 8px}
p.lead{max-width:900px}
figure{margin:14px 0 18px}
figure img{max-width:100%;height:auto;border:1px solid var(--line);border-radius:6px;background:#fff;display:block}
figcaption{font-size:13.5px;color:var(--muted);margin-top:6px;max-width:980px}
.grid3{display:grid;grid-template-columns:repeat(auto-fit,minmax(300px,1fr));gap:10px 22px;align-items:start}
.grid3>*{min-width:0}
.tablewrap{overflow-x:auto}
table{border-collapse:collapse;margin:6px 0 10px;font-size:13.5px}
th,td{border-bottom:1px solid var(--line);padding:6px 10px;text-align:left;vertical-align:top}
th{font-weight:600;color:var(--muted);background:#f8fafc}
td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
td.na{color:#9aa5b1}
table.kv td:first-child{color:var(--muted);white-space:nowrap}
table.kv thead{display:none}
td.path{font-family:ui-monospace,SFMono-Regular,Menlo,Consolas,monospace;font-size:11.5px;word-break:break-all;
 min-width:280px;max-width:420px}
table.prov{width:100%}
td.path .hash{color:var(--muted);margin-top:3px}
table.prov td:first-child{min-width:200px}
td.st.ok{color:#166534}td.st.bad{color:#b91c1c;font-weight:600}td.st.na{color:#9a6700}
.sub{color:var(--muted);font-size:12px}
code{font-family:ui-monospace,SFMono-Regular,Menlo,Consolas,monospace;font-size:.9em;background:#f1f5f9;
 padding:1px 4px;border-radius:4px}
.dot{display:inline-block;width:10px;height:10px;border-radius:50%;margin-right:7px;vertical-align:baseline}
.notrun{background:#f8fafc;border:1px dashed #9aa5b1;border-radius:8px;padding:12px 16px;color:#3e4c59}
.note{border-radius:8px;padding:10px 14px;margin:10px 0;font-size:14px}
.note.warn{background:#fff8e6;border:1px solid #f5d27a}
.note.info{background:#eef4ff;border:1px solid #c7d7fe}
.limits{background:#fff4e5;border:1px solid #f0b35b;border-left:6px solid #e8590c;border-radius:8px;
 padding:12px 16px;margin:10px 0;font-size:14.5px;color:#5c3300}
header .limits{margin-top:16px}
header code{background:rgba(255,255,255,.14);color:#f1f5f9}
footer{color:var(--muted);font-size:12.5px;text-align:center;padding:10px 0 30px}
"""


def _header(ctx: _Ctx, generated: str) -> str:
    m = ctx.metrics
    cards = []
    for k in MODELS:
        e = (m or {}).get(k)
        if e is None:
            cards.append(f'<div class="card na"><div class="label"><span class="dot" style="background:'
                         f'{MODEL_COLORS[k]}"></span>{esc(MODEL_LABELS[k])}</div><div class="big">–</div>'
                         f'<div class="small">not evaluated</div></div>')
            continue
        val = e.get("val_accuracy")
        cards.append(f'<div class="card"><div class="label"><span class="dot" style="background:{MODEL_COLORS[k]}">'
                     f'</span>{esc(MODEL_LABELS[k])}</div><div class="big">{pct(e.get("real_accuracy"))}</div>'
                     f'<div class="small">real accuracy · validation (synthetic) {pct(val)}</div></div>')
    facts = []
    if m:
        facts.append(f"{m.get('test_images', '?')} real test crops from {esc(', '.join(m.get('test_sources') or []) or '?')}")
        facts.append(f"{m.get('train_images', '?'):,} synthetic training images" if _is_num(m.get("train_images"))
                     else "training images: ?")
    if ctx.rows is not None:
        facts.append(f"dataset: {len(ctx.rows):,} renders of {len({r['crater'] for r in ctx.rows})} crater(s)")
    facts.append("classes: " + esc(", ".join(ctx.craters)))
    no_metrics = "" if m else (f'<div class="notrun" style="margin-top:14px;color:#e2e8f0;background:transparent">'
                               f'<strong>not run:</strong> no metrics.json — <code>{esc(PRODUCERS["metrics"][1])}</code></div>')
    return (f'<header><div class="wrap"><h1>crater-synth run report — {esc(ctx.run_dir.resolve().name)}</h1>'
            f'<div class="meta">{esc(ctx.run_dir.resolve())} · generated {esc(generated)}</div>'
            f'<div class="cards">{"".join(cards)}</div>{no_metrics}'
            f'<div class="facts">{" · ".join(facts)}</div>'
            f'<div class="limits"><b>Test-set limit.</b> {esc(_limits_text(ctx))}</div></div></header>')


def render_page(ctx: _Ctx) -> str:
    from crater_synth import __version__

    generated = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    body = []
    for sid, title, fn in SECTIONS:
        ctx.say(f"section {title}")
        content = fn(ctx)
        body.append(f'<section id="{sid}"><h2>{esc(title)}<a class="anchor" href="#{sid}" '
                    f'aria-label="link to this section">#</a></h2><p class="intro">{esc(INTROS[sid])}</p>'
                    f"{content}</section>")
    nav = "".join(f'<a href="#{sid}">{esc(title)}</a>' for sid, title, _ in SECTIONS)
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            f"<title>crater-synth report — {esc(ctx.run_dir.resolve().name)}</title><style>{CSS}</style></head><body>"
            f"{_header(ctx, generated)}<nav><div class=\"wrap\">{nav}</div></nav>"
            f"<main><div class=\"wrap\">{''.join(body)}</div></main>"
            f"<footer>crater-synth {esc(__version__)} · <code>crater-synth report</code> · "
            "self-contained: every image is a PNG next to this page</footer></body></html>\n")


# ------------------------------------------------------------------------------------------------
# Atomic publication
# ------------------------------------------------------------------------------------------------
def _rename_exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux renameat2 RENAME_EXCHANGE); False where unsupported."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    at_fdcwd, rename_exchange = -100, 2
    return fn(at_fdcwd, os.fsencode(str(a)), at_fdcwd, os.fsencode(str(b)), rename_exchange) == 0


def _publish(tmp: Path, final: Path) -> None:
    if not final.exists():
        os.rename(tmp, final)
        return
    if _rename_exchange(tmp, final):
        shutil.rmtree(tmp, ignore_errors=True)          # tmp now holds the previous report
        return
    old = final.with_name(f".{final.name}.old-{os.getpid()}")
    os.rename(final, old)
    os.rename(tmp, final)
    shutil.rmtree(old, ignore_errors=True)


def build_report(run_dir: str | Path, overrides: Sequence[str] = (), max_tiles: int = 36, hist_samples: int = 48,
                 log=None) -> Path:
    """Write ``RUN_DIR/report/index.html`` (+ PNGs) and return its path."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ReportError(f"run directory {run_dir} does not exist (`{PRODUCERS['metrics'][1]}` writes it)")
    if max_tiles < 1 or hist_samples < 1:
        raise ReportError("--max-tiles and --hist-samples must be >= 1")
    run_outputs = (METRICS_FILE, LOOP_FILE, EXPERIMENTS_FILE, SUMMARY_FILE, RUN_CONFIG_FILE)
    if not any((run_dir / name).exists() for name in (*run_outputs, FIGURE6_FILE)) \
            and not any(run_dir.glob("confusion_*.png")):  # nothing of a run here: e.g. a typo in RUN_DIR
        raise ReportError(f"run directory {run_dir} holds no run to report (none of {', '.join(run_outputs)}): "
                          f"run `{PRODUCERS['metrics'][1]}` first, or give the run_dir it wrote")
    rc = effective_config(run_dir, overrides)
    metrics = load_metrics(run_dir / METRICS_FILE)
    # Validate every optional input up front: a corrupt one fails before any work.
    load_loop_history(run_dir / LOOP_FILE)
    load_experiments(run_dir / EXPERIMENTS_FILE)
    check_png(run_dir / FIGURE6_FILE)
    load_summary(run_dir / SUMMARY_FILE)
    for m in MODELS:
        check_png(run_dir / f"confusion_{m}.png")
    all_rows = _dataset_rows(rc.dataset_dir)
    rows = all_rows
    selection = (rc.cfg.get("train") or {}).get("select")
    if all_rows is not None and selection:
        from crater_core.sweep import rows_in_selection

        rows = rows_in_selection(all_rows, dict(selection))
    tmp = Path(tempfile.mkdtemp(prefix=".report.tmp-", dir=run_dir))
    try:
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o777 & ~mask)
        ctx = _Ctx(run_dir=run_dir, out=tmp, rc=rc, metrics=metrics, rows=rows, all_rows=all_rows,
                   craters=_crater_order(metrics, rc.cfg, rows), max_tiles=max_tiles, hist_samples=hist_samples,
                   log=log)
        page = render_page(ctx)
        for f in tmp.iterdir():               # mkstemp-written PNGs (preview) are 0600
            os.chmod(f, 0o666 & ~mask)
        with open(tmp / INDEX_FILE, "w", encoding="utf-8") as fh:
            fh.write(page)
            fh.flush()
            os.fsync(fh.fileno())
        final = run_dir / REPORT_DIR
        _publish(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final / INDEX_FILE


@click.command("report")
@click.argument("run_dir", type=click.Path(file_okay=False))
@OVERRIDES
@click.option("--max-tiles", default=36, show_default=True, help="Renders per contact sheet.")
@click.option("--hist-samples", default=48, show_default=True,
              help="Renders per crater sampled for the input histograms.")
@click.option("--quiet", "-q", is_flag=True, help="Only print the page's path.")
@user_errors
def report_command(run_dir, overrides, max_tiles, hist_samples, quiet):
    """Write RUN_DIR/report/index.html: contact sheets, real vs synthetic, input histograms, accuracies and
    confusion matrices, closed-loop history, Figure 6, provenance and test-set limits.

    The dataset is the run's train.dataset_dir (from RUN_DIR/config.yaml when train saved it), or
    give train.dataset_dir=DIR. Absent inputs become "not run" notes; a corrupt one is an error.
    """
    log = None if quiet else (lambda msg: click.echo(f"report: {msg}", err=True))
    click.echo(str(build_report(run_dir, overrides, max_tiles, hist_samples, log)))
