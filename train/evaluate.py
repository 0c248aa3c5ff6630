"""Evaluation of the saved classifiers on the real test set (docs/classifiers.md, docs/realset.md).

Writes into ``run_dir`` (atomically): ``metrics.json`` (accuracy overall / per crater / per sigma /
per source and the confusion matrix of each model), ``confusion_<model>.png``, ``realset.jsonl``
(every real crop: source product, pixel box, sigma, offset, rotation, and each model's prediction).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from crater_core.schema import atomic_write_text
from train.errors import ModelError
from train.metrics import accuracy, class_mean_accuracy, confusion
from train.plots import plot_confusion
from train.realset import LIMITS_NOTE, RealTestSet, build_real_test_set, canonical_crater
from train.registry import MODELS
from train.trainer import (
    HOG_FILE,
    SUMMARY_FILE,
    SVM_FILE,
    configure_torch,
    fc1_activations,
    json_text,
    load_lunarnet,
    load_sklearn,
    predict_logits,
)

METRICS_FILE, REALSET_FILE = "metrics.json", "realset.jsonl"


def model_metrics(y_true: np.ndarray, y_pred: np.ndarray, test: RealTestSet, val_accuracy: float | None) -> dict:
    """One model's entry of metrics.json: accuracy overall, class-mean, per crater/sigma/source, confusion."""
    names = test.class_names
    sig = np.array([c.sigma for c in test.crops])
    src = np.array([c.source for c in test.crops])

    def subset(mask: np.ndarray) -> float:
        return accuracy(y_true[mask], y_pred[mask])

    return {
        "real_accuracy": accuracy(y_true, y_pred),
        "real_accuracy_class_mean": class_mean_accuracy(y_true, y_pred),
        "val_accuracy": None if val_accuracy is None else float(val_accuracy),
        "per_crater": {n: subset(y_true == i) for i, n in enumerate(names) if np.any(y_true == i)},
        "per_sigma": {f"{s:.1f}": subset(np.isclose(sig, s)) for s in sorted(set(sig.tolist()))},
        "per_source": {s: subset(src == s) for s in sorted(set(src.tolist()))},
        "confusion": confusion(y_true, y_pred, len(names)),
    }


def _craters_for(cfg: Mapping, class_names: Sequence[str]) -> list[dict]:
    by = {}
    for key, e in (cfg.get("crater") or {}).items():
        e = e or {}
        by[canonical_crater(e.get("name") or key)] = {
            "name": str(e.get("name") or key),
            "lat": e.get("lat"),
            "lon": e.get("lon"),
            "diameter_km": e.get("diameter_km"),
        }
    out = []
    for n in class_names:
        c = by.get(canonical_crater(n))
        if c is None:
            raise ModelError(
                f"the saved models know crater {n!r}, which is not in the configuration's crater "
                f"group (select it with crater=[...])"
            )
        out.append(c)
    return out


def evaluate_run(cfg: Mapping, run_dir: str | Path, progress: bool = True, test: RealTestSet | None = None) -> dict:
    """Evaluate the saved models (``train.registry``) of ``run_dir`` on the real test set; write the metrics files."""
    run_dir = Path(run_dir)
    device = configure_torch(cfg["train"])
    t0 = time.perf_counter()
    net, ck = load_lunarnet(run_dir, device)
    svm = load_sklearn(run_dir / SVM_FILE)
    hog = load_sklearn(run_dir / HOG_FILE)
    class_names = list(ck["class_names"])
    for other, f in ((svm, SVM_FILE), (hog, HOG_FILE)):
        if list(other["class_names"]) != class_names:
            raise ModelError(
                f"{run_dir / f} was trained on classes {other['class_names']}, LunarNet_ex on {class_names}: retrain"
            )
    summary = {}
    if (run_dir / SUMMARY_FILE).is_file():
        summary = json.loads((run_dir / SUMMARY_FILE).read_text())
    if test is None:  # with the preprocessing the network was trained with
        from train.preprocess import PreprocessConfig

        pp = PreprocessConfig(**ck["preprocess"]) if ck.get("preprocess") else None
        test = build_real_test_set(cfg, _craters_for(cfg, class_names), class_names, pp)
    ebs = int(cfg["train"].get("eval_batch_size", 256))
    from train.models import hog_features

    preds = {  # one entry per model of train.registry
        "lunarnet_ex": predict_logits(net, test.images, ebs, device).argmax(1),
        "lunarsvm_ex": svm["model"].predict(fc1_activations(net, test.images, ebs, device)),
        "hog_svm": hog["model"].predict(hog_features(test.images, hog.get("hog") or cfg["train"].get("hog", {}))),
    }
    vals = {
        "lunarnet_ex": ck.get("val_accuracy"),
        "lunarsvm_ex": svm.get("val_accuracy"),
        "hog_svm": hog.get("val_accuracy"),
    }
    if set(preds) != set(MODELS) or set(vals) != set(MODELS):
        raise AssertionError(f"evaluate_run predicts {sorted(preds)}, train.registry lists {list(MODELS)}")
    metrics: dict = {}
    for name in MODELS:
        metrics[name] = model_metrics(test.labels, np.asarray(preds[name], dtype=np.int64), test, vals[name])
        plot_confusion(
            run_dir / f"confusion_{name}.png",
            metrics[name]["confusion"],
            class_names,
            f"{name}: real accuracy {metrics[name]['real_accuracy']:.1%}",
        )
    metrics.update(
        {
            "classes": class_names,
            "train_images": int(summary.get("train_images", 0)),
            "val_images": int(summary.get("val_images", 0)),
            "test_images": int(len(test.labels)),
            "test_sources": test.sources,
            "test_per_crater": {n: int(np.sum(test.labels == i)) for i, n in enumerate(class_names)},
            "limits": LIMITS_NOTE
            if any(c.kind == "embedded" for c in test.crops)
            else "Real test frames from the labels file only; see realset.jsonl for their sources.",
            "evaluate_seconds": time.perf_counter() - t0,
        }
    )
    rows = []
    for i, c in enumerate(test.crops):
        r = c.as_row()
        r.update({f"pred_{m}": class_names[int(preds[m][i])] for m in MODELS})
        rows.append(json.dumps(r, sort_keys=True))
    atomic_write_text(run_dir / REALSET_FILE, "\n".join(rows) + "\n")
    atomic_write_text(run_dir / METRICS_FILE, json_text(_jsonable(metrics)))
    return metrics


def _jsonable(obj):
    """NaN -> None so metrics.json is strict JSON."""
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    return obj
