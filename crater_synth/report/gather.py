"""Data gathering for the report: one function per section, each returning a plain dict for its template
(``templates/<section>.html.j2``) and drawing its figures (:mod:`crater_synth.report.figures`) into the
report's temporary directory. No HTML here: the templates own the markup.

Any number of craters (classes) is supported: every per-crater item is a list, never three columns.

Length: one gatherer per report section (nine) plus the real-crop planning and synthetic-render
choice they share; a module per section would import those shared helpers back from here.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from crater_core import schema
from crater_core.exr import read_channel
from crater_core.schema import load_manifest
from crater_core.settings import ModelSettings, PreprocessSettings, RealsetSettings, SensorSettings, SettingsError
from crater_synth.config import compose_settings, resolved
from crater_synth.dataset.preview import contact_sheet, ellipse_points, tone_map
from crater_synth.report import figures
from crater_synth.report.context import PRODUCERS, SYNTHETIC_CHOICE, Ctx, not_run
from crater_synth.report.inputs import (
    EXPERIMENTS_FILE,
    FIGURE6_FILE,
    LOOP_FILE,
    METRICS_FILE,
    NAV_FRAMES_GLOB,
    ReportError,
    check_png,
    config_craters,
    is_num,
    load_experiments,
    load_loop_history,
    load_nav_demo,
    load_nav_frames,
    nav_paths,
)
from crater_synth.report.provenance import limits_text, provenance
from data_manifest.products import ProductError, embedded_path
from train.errors import RealSetError
from train.realcrops import crop_pixels
from train.registry import MODELS, REGISTRY, SPECS


def crater_order(metrics: dict | None, cfg: Mapping, rows: list[dict] | None) -> list[str]:
    """The classes of metrics.json, else the configured craters, then any other crater of the dataset."""
    names = list((metrics or {}).get("classes") or []) or [c["name"] for c in config_craters(cfg)]
    for r in rows or ():
        if r["crater"] not in names:
            names.append(r["crater"])
    return names


# ---- 1. contact sheets ---------------------------------------------------------------------------
def contact(ctx: Ctx) -> dict:
    ds = ctx.rc.dataset_dir
    if ctx.rows is None:
        return {"not_run": not_run(f"no rendered dataset at {ds or 'train.dataset_dir (unset)'}", "dataset")}
    if not ctx.rows:
        if ctx.all_rows:
            return {"warning": f"No row of {ds} matches the run's train.select."}
        return {"not_run": not_run(f"the manifest of {ds} has no rows", "dataset")}
    items, small = [], True
    for crater in ctx.craters:
        crows = [r for r in ctx.rows if r["crater"] == crater]
        if not crows:
            items.append({"crater": crater, "missing": True})
            continue
        ctx.say(f"contact sheet {crater} ({len(crows)} renders)")
        png = contact_sheet(
            crows,
            ds,
            ctx.out / f"contact_{crater}.png",
            f"{crater}: {len(crows)} renders (sun el/az, cam el/az in deg)\nred: projected rim; blue: sigma boxes",
            ctx.max_tiles,
        )
        shown = min(ctx.max_tiles, len(crows))
        small = small and shown <= 9
        items.append({"crater": crater, "src": png.name, "shown": shown, "total": len(crows)})
    return {"dataset_dir": str(ds), "items": items, "grid": small}


# ---- 2. real vs synthetic ------------------------------------------------------------------------
def pick_synthetic(rows: Sequence[dict]) -> dict:
    """Closest to nadir, then the highest sun, then the highest lit fraction, then manifest order."""
    return min(
        rows,
        key=lambda r: (
            abs(float(r["cam_elevation"]) - 90.0),
            -float(r["sun_elevation"]),
            -float(r["lit_fraction"]),
            schema.row_key(r),
        ),
    )


def _box_closest(boxes: Mapping[str, Sequence[float]], sigma: float = 1.0) -> tuple[str, list[float]]:
    key = min(boxes, key=lambda k: abs(float(k) - sigma))
    return key, [float(b) for b in boxes[key]]


def _typed(cls: type, mapping, key: str):
    """One group of the run's (saved or composed) configuration as its validated settings class; a value
    the settings refuse is a :class:`ReportError` naming the key."""
    try:
        return cls.from_config(mapping, key)
    except SettingsError as exc:
        raise ReportError(f"the run's configuration: {exc}") from None


def _preprocess_and_sensor(cfg: Mapping):
    """The run's crop preprocessing (``train.preprocess`` at ``model.input_size``) and sensor model."""
    from train.preprocess import PreprocessConfig, SensorModel

    pre = _typed(PreprocessSettings, (cfg.get("train") or {}).get("preprocess"), "train.preprocess")
    size = _typed(ModelSettings, cfg.get("model"), "model").input_size
    sensor = _typed(SensorSettings, cfg.get("sensor"), "sensor")
    return PreprocessConfig.from_settings(pre, size), SensorModel.from_settings(sensor)


def _real_plan(ctx: Ctx, canonical: bool):
    """Crops (and images) of the real test set of the run's configuration; ``canonical``: one sigma = 1.0
    crop per crater, centred, no offset, no rotation. Returns (crops, images), or None with
    ``ctx.real_error`` set when the real product is not installed."""
    from train.realset import canonical_crater, plan_real_crops

    rs = dict(ctx.rc.cfg.get("realset") or {})
    if canonical:
        rs.update(per_crater=1, sigmas=[1.0], max_offset_frac=0.0, max_rotation_deg=0.0)
    known = {canonical_crater(c) for c in ctx.craters}
    craters = [c for c in config_craters(ctx.rc.cfg) if canonical_crater(c["name"]) in known]
    if not craters:
        ctx.real_error = "none of the report's craters is in the configuration's crater group"
        return None
    if rs.get("include_embedded", True) and not (rs.get("mosaic") or {}).get("path"):
        try:
            embedded_path(str(rs.get("source_product") or "lroc_wac_south"))
        except ProductError as exc:  # not installed here: a note, not a failure
            ctx.real_error = str(exc)
            return None
    try:
        return plan_real_crops(
            _typed(RealsetSettings, rs, "realset"), craters, [c["name"] for c in craters], ctx.rc.cfg.get("data_dir")
        )
    except RealSetError as exc:
        raise ReportError(f"real test set: {exc}") from None


def compare(ctx: Ctx) -> dict:
    from train.preprocess import preprocess_crop, resample_box
    from train.realset import canonical_crater

    if not ctx.rows:
        return {"not_run": not_run("no rendered dataset to compare with", "dataset")}
    plan = _real_plan(ctx, canonical=True)
    if plan is None:
        return {"unavailable": ctx.real_error}
    crops, images = plan
    pp, sensor = _preprocess_and_sensor(ctx.rc.cfg)
    items = []
    for crater in ctx.craters:
        crows = [r for r in ctx.rows if r["crater"] == crater]
        real = sorted(
            (c for c in crops if canonical_crater(c.crater) == canonical_crater(crater)),
            key=lambda c: (c.kind != "embedded", c.index),
        )
        if not crows or not real:
            items.append(
                {
                    "crater": crater,
                    "missing": "renders" if not crows else "a real crop (not in the configured crater group)",
                }
            )
            continue
        rc, row = real[0], pick_synthetic(crows)
        ctx.real[crater] = {"crop": rc}
        ctx.say(f"real vs synthetic {crater}")
        img = images[rc.image_path]
        n_r = max(8, int(round(rc.box[2] - rc.box[0])))
        real_orig = crop_pixels(img, rc, n_r)
        if np.issubdtype(img.dtype, np.integer):
            real_orig = real_orig / float(np.iinfo(img.dtype).max)
        i_f = read_channel(ctx.rc.dataset_dir / row["path"])
        skey, sbox = _box_closest(row["sigma_boxes"], 1.0)
        n_s = max(8, int(round(sbox[2] - sbox[0])))
        syn_sensor = (
            preprocess_crop(i_f, sbox, pp, sensor=sensor, rng=np.random.default_rng(int(row["seed"])))
            if sensor.enabled
            else None
        )
        name = figures.compare_panel(
            ctx.out / f"compare_{crater}.png",
            crater,
            row,
            real_orig,
            tone_map(resample_box(i_f, sbox, n_s, 0.0, True, 1)),
            i_f,
            skey,
            sbox,
            ellipse_points(row["rim_ellipse"]),
            preprocess_crop(img, rc.box, pp, rotation_deg=rc.rotation_deg, axes=rc.axes),
            preprocess_crop(i_f, sbox, pp),
            syn_sensor,
            pp.size,
        )
        items.append(
            {
                "crater": crater,
                "src": name,
                "box": list(rc.box),
                "sigma": rc.sigma,
                "rotation_deg": rc.rotation_deg,
                "source": rc.source,
                "path": row["path"],
                "lit_fraction": row["lit_fraction"],
                "mean_if": row["mean_if"],
            }
        )
    return {"choice": SYNTHETIC_CHOICE, "size": pp.size, "gamma": pp.gamma, "items": items}


# ---- 3. histograms -------------------------------------------------------------------------------
def histograms(ctx: Ctx) -> dict:
    from train.preprocess import preprocess_crop
    from train.realset import canonical_crater

    if not ctx.rows:
        return {"not_run": not_run("no rendered dataset to compare with", "dataset")}
    plan = _real_plan(ctx, canonical=False)
    if plan is None:
        return {"unavailable": ctx.real_error}
    crops, images = plan
    pp, sensor = _preprocess_and_sensor(ctx.rc.cfg)
    bins = np.linspace(0.0, 1.0, 41)
    width = bins[1] - bins[0]
    panels = []
    for crater in ctx.craters:
        crows = [r for r in ctx.rows if r["crater"] == crater]
        rcs = [c for c in crops if canonical_crater(c.crater) == canonical_crater(crater)]
        if not crows or not rcs:
            continue
        ctx.say(f"histograms {crater}: {len(rcs)} real crops, {min(len(crows), ctx.hist_samples)} renders")
        real = np.stack(
            [preprocess_crop(images[c.image_path], c.box, pp, rotation_deg=c.rotation_deg, axes=c.axes) for c in rcs]
        )
        pick = [
            crows[i] for i in np.unique(np.linspace(0, len(crows) - 1, min(ctx.hist_samples, len(crows))).astype(int))
        ]
        syn, sens = [], []
        for row in pick:
            i_f = read_channel(ctx.rc.dataset_dir / row["path"])
            rng = np.random.default_rng(int(row["seed"]))
            for box in row["sigma_boxes"].values():
                syn.append(preprocess_crop(i_f, box, pp))
                if sensor.enabled:
                    sens.append(preprocess_crop(i_f, box, pp, sensor=sensor, rng=rng))
        syn_a, sens_a = np.stack(syn), (np.stack(sens) if sens else None)
        hr, _ = np.histogram(real, bins=bins, density=True)
        hs, _ = np.histogram(syn_a, bins=bins, density=True)
        panels.append(
            {
                "crater": crater,
                "real_crops": len(rcs),
                "syn_crops": syn_a.shape[0],
                "renders": len(pick),
                "real_density": hr,
                "syn_density": hs,
                "sensor_density": None if sens_a is None else np.histogram(sens_a, bins=bins, density=True)[0],
                "overlap": float(np.sum(np.minimum(hr, hs)) * width),
                "real_zero": float(np.mean(real == 0)),
                "real_mean": float(real.mean()),
                "syn_zero": float(np.mean(syn_a == 0)),
                "syn_mean": float(syn_a.mean()),
                "sensor_zero": None if sens_a is None else float(np.mean(sens_a == 0)),
                "sensor_mean": None if sens_a is None else float(sens_a.mean()),
            }
        )
    if not panels:
        return {"warning": "No crater has both renders and real crops."}
    name = figures.histograms(ctx.out / "histograms.png", panels, bins)
    return {"src": name, "hist_samples": ctx.hist_samples, "panels": panels}


# ---- 4. models -----------------------------------------------------------------------------------
def _sigma_order(s) -> float:
    try:
        return float(s)
    except ValueError:
        return 0.0


def models(ctx: Ctx) -> dict:
    m = ctx.metrics
    if m is None:
        return {"not_run": not_run(f"no {ctx.run_dir / METRICS_FILE}", "metrics")}
    classes = list(m.get("classes") or [])
    present = [s for s in REGISTRY if s.key in m]
    overall = [
        {
            "spec": s,
            "real": m[s.key].get("real_accuracy"),
            "class_mean": m[s.key].get("real_accuracy_class_mean"),
            "val": m[s.key].get("val_accuracy"),
        }
        for s in present
    ]
    # Breakdowns: one row per crater / sigma / source, one column per model (scales to any class count).
    breakdowns = []
    for key, what in (("per_crater", "crater"), ("per_sigma", "ROI σ"), ("per_source", "real source")):
        names: list[str] = []
        for s in present:
            names += [n for n in (m[s.key].get(key) or {}) if n not in names]
        if key == "per_sigma":
            names.sort(key=_sigma_order)
        if key == "per_crater":  # class order
            names.sort(key=lambda n: classes.index(n) if n in classes else len(classes))
        if not names:
            continue
        counts = m.get("test_per_crater") if key == "per_crater" else None
        rows = [
            {
                "name": f"σ = {n}" if key == "per_sigma" else n,
                "n": (counts or {}).get(n, "?") if counts else None,
                "accs": [(m[s.key].get(key) or {}).get(n) for s in present],
            }
            for n in names
        ]
        breakdowns.append({"what": what, "rows": rows, "counted": bool(counts)})
    confusions = []
    for s in present:
        src = check_png(ctx.run_dir / f"confusion_{s.key}.png")
        item = {"spec": s, "real": m[s.key].get("real_accuracy")}
        if src is not None:
            shutil.copyfile(src, ctx.out / src.name)
            item.update(src=src.name, replot=False)
        elif m[s.key].get("confusion") is not None:
            conf = m[s.key]["confusion"]
            acc = m[s.key].get("real_accuracy")
            title = f"{s.label}: real accuracy " + ("–" if not is_num(acc) else f"{100 * acc:.1f} %")
            item.update(
                src=figures.confusion(
                    ctx.out / f"confusion_{s.key}.png", conf, classes or [str(i) for i in range(len(conf))], title
                ),
                replot=True,
            )
        confusions.append(item)

    def count(v):
        return f"{int(v):,}" if is_num(v) else "–"

    facts = [
        ("classes", ", ".join(classes) or "–"),
        ("training images (synthetic)", count(m.get("train_images"))),
        ("validation images (synthetic)", count(m.get("val_images"))),
        ("real test images", count(m.get("test_images"))),
        ("real test sources", ", ".join(m.get("test_sources") or []) or "–"),
    ]
    if is_num(m.get("evaluate_seconds")):
        facts.append(("evaluation time", f"{m['evaluate_seconds']:.1f} s"))
    return {
        "absent": [s.label for s in REGISTRY if s.key not in m],
        "present": present,
        "overall": overall,
        "breakdowns": breakdowns,
        "confusions": confusions,
        "facts": facts,
    }


# ---- 5. closed loop ------------------------------------------------------------------------------
def loop(ctx: Ctx) -> dict:
    path = ctx.run_dir / LOOP_FILE
    doc = load_loop_history(path)
    if doc is None:
        return {"not_run": not_run(f"no {path}", "loop")}
    rounds = sorted(doc["rounds"], key=lambda r: r["round"])
    out = {
        "rounds": rounds,
        "threshold": doc.get("threshold"),
        "stopped_because": doc.get("stopped_because"),
        "models": [SPECS[k] for k in MODELS],
    }
    if rounds:
        out["src"] = figures.loop_history(ctx.out / "loop.png", rounds, doc.get("threshold"))
    return out


# ---- 6. Figure 6 ---------------------------------------------------------------------------------
def figure6(ctx: Ctx) -> dict:
    csv_path, png_path = ctx.run_dir / EXPERIMENTS_FILE, ctx.run_dir / FIGURE6_FILE
    rows = load_experiments(csv_path)
    png = check_png(png_path)
    if rows is None and png is None:
        return {"not_run": not_run(f"no {csv_path} and no {png_path}", "experiments")}
    out: dict = {"csv_name": csv_path.name, "png_name": png_path.name}
    known = [m for m in MODELS if any(r["model"] == m for r in rows or ())]
    models_ = known + sorted({r["model"] for r in rows or ()} - set(MODELS))
    if png is not None:
        shutil.copyfile(png, ctx.out / FIGURE6_FILE)
        out["figure"] = {"src": FIGURE6_FILE, "replot": False}
    elif rows:
        out["figure"] = {"src": figures.figure6(ctx.out / "figure6_replot.png", rows, models_), "replot": True}
    if rows is None:
        out["csv_missing"] = not_run(f"no {csv_path} (the table behind the figure)", "experiments")
        return out
    out["empty"] = not rows
    tables = []
    for p in dict.fromkeys(r["parameter"] for r in rows):
        prow = [r for r in rows if r["parameter"] == p]
        keys = sorted({(r["model"], r["sigma"]) for r in prow}, key=lambda k: (models_.index(k[0]), k[1]))
        look = {(r["count"], r["model"], r["sigma"]): r for r in prow}
        lines = []
        for c in sorted({r["count"] for r in prow}):
            imgs = sorted({look[(c, mdl, s)]["train_images"] for mdl, s in keys if (c, mdl, s) in look})
            lines.append(
                {
                    "count": c,
                    "images": imgs,
                    "accs": [look[(c, mdl, s)]["real_accuracy"] if (c, mdl, s) in look else None for mdl, s in keys],
                }
            )
        tables.append({"parameter": p, "columns": [(mdl, s) for mdl, s in keys], "lines": lines})
    out["tables"] = tables
    return out


# ---- 7. fidelity (docs/fidelity.md) -------------------------------------------------------------------------
ABLATION_FILE = "ablation.json"


def ablation_path(run_dir, cfg: Mapping):
    """RUN_DIR/ablation.json when present, else the configured ``ablation.out_dir``'s."""
    local = run_dir / ABLATION_FILE
    if local.is_file():
        return local
    out = (cfg.get("ablation") or {}).get("out_dir")
    return Path(str(out)) / ABLATION_FILE if out else local


def load_ablation(path) -> dict | None:
    """The ablation results, checked: None when absent; ReportError naming the file when malformed."""
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        variants = doc["variants"]
        for v in variants:
            v["summary"]["validation_mean"], v["summary"]["test_mean"], v["summary"]["groups"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ReportError(f"{path}: not a crater-synth ablation result ({type(exc).__name__}: {exc})") from None
    return doc


def fidelity(ctx: Ctx) -> dict:
    """The ablation table, and for every crater of the ablation a real crop beside the synthetic images
    of the chosen configuration (one render; the composite and sensor model training applies)."""
    path = ablation_path(ctx.run_dir, ctx.rc.cfg)
    doc = load_ablation(path)
    if doc is None:
        return {"not_run": not_run(f"no {path}", "ablation")}
    table = []
    for v in doc["variants"]:
        s = v["summary"]
        groups = [
            {"label": label, "role": g["role"], "per_crater": g["models"].get("lunarnet_ex", {}).get("per_crater", {})}
            for label, g in s["groups"].items()
        ]
        table.append(
            {
                "variant": v["variant"],
                "why": v.get("why", ""),
                "overrides": v.get("overrides", []),
                "val": {m: s["validation_mean"].get(m) for m in MODELS},
                "test": {m: s["test_mean"].get(m) for m in MODELS},
                "holdout": {m: (s.get("holdout_mean") or {}).get(m) for m in MODELS},
                "groups": groups,
                "renders": sorted(set((v.get("renders") or {}).values())),
            }
        )
    out = {
        "path": str(path),
        "budget": doc.get("budget", []),
        "overrides": doc.get("overrides"),
        "table": table,
        "models": [SPECS[k] for k in MODELS],
        "holdout": any(v is not None for row in table for v in row["holdout"].values()),
    }
    if doc.get("overrides") is None:
        out["no_images"] = "this ablation.json predates the recorded overrides: re-run crater-synth ablate"
        return out
    out["items"] = _fidelity_images(ctx, doc)
    return out


def _fidelity_images(ctx: Ctx, doc: dict) -> list[dict]:
    from train.preprocess import PreprocessConfig, SensorModel, mosaic_composite, preprocess_crop
    from train.realset import load_mosaic

    base = doc["variants"][0]
    craters = [
        c for g in base["summary"]["groups"].values() for c in g["models"].get("lunarnet_ex", {}).get("per_crater", {})
    ]
    composed, settings = compose_settings(list(doc["overrides"]) + [f"crater=[{','.join(craters)}]"])
    cfg = resolved(composed)
    if not base.get("render_key"):  # (crater_synth.evaluation.ablation is not imported: it reaches the training stack)
        return [{"crater": c, "missing": "the ablation result names no render_key"} for c in craters]
    ds = Path(str(cfg["data_dir"])) / "synth" / f"ablate-{base['render_key']}"
    if not (ds / "manifest.jsonl").is_file():
        return [{"crater": c, "missing": f"no renders at {ds}"} for c in craters]
    rows = load_manifest(ds)
    pp = PreprocessConfig.from_settings(settings.train.preprocess, settings.model.input_size)
    sensor = SensorModel.from_settings(settings.sensor)
    try:
        mosaic = load_mosaic(settings.realset)
    except Exception as exc:  # the real product is optional for the report
        return [{"crater": c, "missing": f"real mosaic unavailable ({exc})"} for c in craters]
    items = []
    for name in craters:
        c = cfg["crater"][name]
        crows = [r for r in rows if r["crater"] == name]
        if not crows:
            items.append({"crater": name, "missing": f"no renders of {name} in {ds}"})
            continue
        cu, cv = mosaic.latlon_to_uv(c["lat"], c["lon"])
        side = float(c["diameter_km"]) * 1000.0 / float(mosaic.pixel_m)
        real = preprocess_crop(mosaic.image, (cu - side / 2, cv - side / 2, cu + side / 2, cv + side / 2), pp)
        row = pick_synthetic(crows)
        pose = [
            r for r in crows if (r["cam_elevation"], r["cam_azimuth"]) == (row["cam_elevation"], row["cam_azimuth"])
        ]
        rng = np.random.default_rng(int(row["seed"]))
        _, box = _box_closest(row["sigma_boxes"], 1.0)
        frames = [
            read_channel(ds / r["path"])
            for r in [row]
            + [pose[i] for i in rng.permutation(len(pose)) if pose[i] is not row][
                : max(0, int(sensor.mosaic_frames) - 1)
            ]
        ]
        single = preprocess_crop(frames[0], box, pp)
        composite = mosaic_composite(frames, rng, sensor.mosaic_blend, sensor.mosaic_patches)
        trained = preprocess_crop(
            composite,
            box,
            pp,
            sensor=sensor if sensor.enabled else None,
            rng=rng,
            box_side_m=float(c["diameter_km"]) * 1000.0,
        )
        ctx.say(f"fidelity real vs synthetic {name}")
        src = figures.fidelity_panel(ctx.out / f"fidelity_{name}.png", name, real, single, trained, len(frames), row)
        items.append({"crater": name, "src": src, "path": row["path"], "frames": len(frames)})
    return items


# ---- 8. navigation (docs/navigation/overview.md) ---------------------------------------------------------
NAV_SPLIT_ORDER = {"validation": 0, "test": 1}


def navigation(ctx: Ctx) -> dict:
    """The navigate-demo metrics table and its annotated real windows (copied in), and per rendered
    trajectory the per-frame fix error of the detector and of the perfect-detection check."""
    demo_path, frame_paths = nav_paths(ctx.run_dir)
    demo = load_nav_demo(demo_path)
    if demo is None and not frame_paths:
        return {"not_run": not_run(f"no {demo_path} and no {demo_path.parent}/{NAV_FRAMES_GLOB}", "navigation")}
    out: dict = {"demo_path": str(demo_path)}
    if demo is None:
        out["demo_missing"] = not_run(f"no {demo_path}", "navigation")
    else:
        rows = []
        for method, res in demo["methods"].items():
            for split in sorted(res["splits"], key=lambda s: (NAV_SPLIT_ORDER.get(s, 2), s)):
                r = res["splits"][split]
                rows.append({"method": method, "split": split, "which": "≥ 3 landmarks D ≥ 15 km", "s": r["headline"]})
                rows.append({"method": method, "split": split, "which": "all windows", "s": r["all_windows"]})
        windows: dict[str, dict] = {}
        for w in demo["windows"]:
            item = windows.setdefault(
                w["id"], {"id": w["id"], "split": w["split"], "sector": w.get("sector"), "by": []}
            )
            src = f"nav_{w['png']}"
            shutil.copyfile(demo_path.parent / w["png"], ctx.out / src)
            item["by"].append({**w, "src": src})
        gallery = sorted(windows.values(), key=lambda it: (NAV_SPLIT_ORDER.get(it["split"], 2), it["id"]))
        out.update(
            table=rows,
            gallery=gallery,
            methods=list(demo["methods"]),
            per_sector=demo.get("per_sector"),
            min_landmark_km=demo.get("min_landmark_km"),
            prior_offset_km=demo.get("prior_offset_km"),
            false_fix_km=demo.get("false_fix_km"),
            n_windows=len(windows),
            map_check=demo.get("map_check"),
            catalogue=_nav_catalogue(ctx, demo_path, demo.get("catalogue_detection")),
        )
    trajectories = []
    for k, path in enumerate(frame_paths):
        doc = load_nav_frames(path)
        ctx.say(f"navigation error plot {path.name}")
        frames = sorted(doc["frames"], key=lambda f: f["index"])
        src = figures.nav_trajectory(
            ctx.out / f"nav_trajectory_{k}.png",
            doc["trajectory"],
            frames,
            float(doc.get("false_fix_km") or 5.0),
            doc.get("min_inliers"),
        )
        trajectories.append(
            {
                "path": str(path),
                "name": doc["trajectory"],
                "method": doc.get("method", "position"),
                "preset": doc.get("preset"),
                "render": doc.get("render") or {},
                "settings": doc.get("settings") or [],
                "summary": doc["summary"],
                "frames": frames,
                "src": src,
                "fixes": sum(f["fix"] for f in frames),
                "patch_fixes": sum(bool(f["fix"]) and f.get("fix_source") == "patches" for f in frames),
                "perfect_fixes": sum(f["perfect"]["fix"] for f in frames),
            }
        )
    out["trajectories"] = trajectories
    if not trajectories:
        out["frames_missing"] = not_run(f"no {demo_path.parent}/{NAV_FRAMES_GLOB}", "navframes")
    return out


def _nav_catalogue(ctx: Ctx, demo_path: Path, cat: dict | None) -> dict | None:
    """The demo's detections against the crater catalogue (``catalogue_detection``, None for a demo from
    before it): the PNGs copied in, grouped by window (method order as written), the per-window counts
    and the pooled scores per method."""
    if cat is None:
        return None
    by_window: dict[str, dict] = {}
    for w in cat["windows"]:
        src = f"nav_{w['png']}"
        shutil.copyfile(demo_path.parent / w["png"], ctx.out / src)
        by_window.setdefault(w["id"], {"id": w["id"], "sector": w.get("sector"), "by": []})["by"].append(
            {**w, "src": src}
        )
    return {**cat, "gallery": list(by_window.values())}


# ---- header --------------------------------------------------------------------------------------
def header(ctx: Ctx) -> dict:
    m = ctx.metrics
    cards = [{"spec": s, "entry": (m or {}).get(s.key)} for s in REGISTRY]
    facts = []
    if m:
        sources = ", ".join(m.get("test_sources") or []) or "?"
        facts.append(f"{m.get('test_images', '?')} real test crops from {sources}")
        facts.append(
            f"{m.get('train_images', '?'):,} synthetic training images"
            if is_num(m.get("train_images"))
            else "training images: ?"
        )
    if ctx.rows is not None:
        facts.append(f"dataset: {len(ctx.rows):,} renders of {len({r['crater'] for r in ctx.rows})} crater(s)")
    facts.append("classes: " + ", ".join(ctx.craters))
    return {
        "name": ctx.run_dir.resolve().name,
        "path": str(ctx.run_dir.resolve()),
        "cards": cards,
        "facts": facts,
        "metrics_cmd": None if m else PRODUCERS["metrics"][1],
        "limits": limits_text(ctx),
    }


# (id, title, gatherer, one-line intro), in page order
SECTIONS = (
    (
        "contact",
        "1. Contact sheets",
        contact,
        "What the renderer produced: a sample of the synthetic dataset per crater.",
    ),
    (
        "compare",
        "2. Real vs synthetic",
        compare,
        "Does a render look like the real image? The real WAC crop beside the closest synthetic render.",
    ),
    (
        "histograms",
        "3. Input histograms",
        histograms,
        "Do the two domains look alike to the classifier? Pixel statistics of the network input.",
    ),
    ("models", "4. Classifiers", models, "Accuracy on the real crops (test) and on the synthetic validation split."),
    (
        "loop",
        "5. Closed loop",
        loop,
        "The closed loop: rounds of rendering more sun elevations until the real accuracy reaches the threshold.",
    ),
    ("figure6", "6. Figure 6 experiments", figure6, "Accuracy against the number of samples of each sweep parameter."),
    (
        "fidelity",
        "7. Fidelity ablation",
        fidelity,
        "Which sim-to-real levers moved the real accuracy (validation craters choose, the test craters are reported).",
    ),
    (
        "navigation",
        "8. Crater navigation",
        navigation,
        "Position fixes from crater landmarks: annotated real windows and the fix error along a rendered trajectory.",
    ),
    (
        "provenance",
        "9. Provenance & limits",
        provenance,
        "Where every input came from, and what the test set can and cannot tell.",
    ),
)
