"""Evaluation of the saved classifiers on the real test set (docs/classifiers.md, docs/realset.md).

Writes into ``run_dir`` (atomically): ``metrics.json`` (accuracy overall / per crater / per sigma /
per source and the confusion matrix of each model), ``confusion_<model>.png``, ``realset.jsonl``
(every real crop: source product, pixel box, sigma, offset, rotation, and each model's prediction).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from crater_core.progress import Progress
from crater_core.schema import atomic_write_text
from crater_core.settings import HogSettings, Settings, SettingsError
from train.errors import ModelError
from train.metrics import accuracy, class_mean_accuracy, confusion
from train.plots import plot_confusion
from train.realset import LIMITS_NOTE, RealTestSet, build_real_test_set, canonical_crater
from train.registry import MODELS
from train.runs import METRICS_FILE, REALSET_FILE, SUMMARY_FILE, check_one_run, confusion_file
from train.trainer import (
    HOG_FILE,
    NET_FILE,
    SVM_FILE,
    configure_torch,
    fc1_activations,
    json_text,
    load_lunarnet,
    load_sklearn,
    predict_logits,
)


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


def craters_for(settings: Settings, class_names: Sequence[str]) -> list[dict]:
    """The configured crater entry (name, lat, lon, diameter_km) of each class, in class order."""
    by = {}
    for e in settings.craters:
        by[canonical_crater(e.name)] = {"name": e.name, "lat": e.lat, "lon": e.lon, "diameter_km": e.diameter_km}
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


def _svm_scores(model, X: np.ndarray) -> np.ndarray:
    """(N, classes) decision values of a scikit-learn linear classifier; ``model.predict`` is
    ``classes_[argmax]`` of them (a binary one's single column d becomes [-d, d])."""
    d = np.asarray(model.decision_function(X), dtype=np.float64)
    return np.stack([-d, d], axis=1) if d.ndim == 1 else d


def roll_averaged_predictions(
    net,
    svm_model,
    hog_model,
    hog_settings: HogSettings,
    images: np.ndarray,
    rolls: int,
    batch_size: int,
    device,
    progress: bool = False,
) -> dict[str, np.ndarray]:
    """Each model's predicted class (index into the class names) for every real crop.

    The camera's roll about its boresight is unknown in a real image, so with ``rolls`` > 1 each
    model's scores (LunarNet_ex: softmax probabilities; the SVMs: decision values) are averaged over
    the crop turned by ``360 / rolls`` degree steps before the arg-max (test-time averaging over roll;
    disc-support crops only, which any turn keeps inside the box). ``rolls == 1`` is the plain
    prediction of each model. ``progress``: the turns done, with rate and ETA, on stderr."""
    from train.models import hog_features
    from train.preprocess import rotate_crop

    if int(rolls) == 1:
        return {
            "lunarnet_ex": predict_logits(net, images, batch_size, device).argmax(1),
            "lunarsvm_ex": svm_model.predict(fc1_activations(net, images, batch_size, device)),
            "hog_svm": hog_model.predict(hog_features(images, hog_settings)),
        }
    scores: dict[str, np.ndarray | float] = dict.fromkeys(MODELS, 0.0)
    bar = Progress(
        int(rolls), f"evaluate: {len(images)} real crops, roll averaging", "turn", "auto" if progress else "off"
    )
    for k in range(int(rolls)):
        x = images if k == 0 else rotate_crop(images, 360.0 * k / rolls)
        logits = predict_logits(net, x, batch_size, device).astype(np.float64)
        p = np.exp(logits - logits.max(axis=1, keepdims=True))
        fc1 = fc1_activations(net, x, batch_size, device)
        scores["lunarnet_ex"] = scores["lunarnet_ex"] + p / p.sum(axis=1, keepdims=True)
        scores["lunarsvm_ex"] = scores["lunarsvm_ex"] + _svm_scores(svm_model, fc1)
        scores["hog_svm"] = scores["hog_svm"] + _svm_scores(hog_model, hog_features(x, hog_settings))
        bar.update()
    bar.close()
    return {
        "lunarnet_ex": np.asarray(scores["lunarnet_ex"]).argmax(axis=1),
        "lunarsvm_ex": np.asarray(svm_model.classes_)[np.asarray(scores["lunarsvm_ex"]).argmax(axis=1)],
        "hog_svm": np.asarray(hog_model.classes_)[np.asarray(scores["hog_svm"]).argmax(axis=1)],
    }


def _load_run(run_dir: Path, device):
    """The three saved models of ``run_dir``, checked to be of one training run and one class list:
    (net, its checkpoint, svm doc, hog doc, the run's summary (or {}), run id, class names)."""

    net, ck = load_lunarnet(run_dir, device)
    svm = load_sklearn(run_dir / SVM_FILE)
    hog = load_sklearn(run_dir / HOG_FILE)
    summary = None
    if (run_dir / SUMMARY_FILE).is_file():
        try:
            summary = json.loads((run_dir / SUMMARY_FILE).read_text())
        except (ValueError, OSError) as exc:
            raise ModelError(f"cannot read {run_dir / SUMMARY_FILE}: {exc}") from None
    run_id = check_one_run(
        run_dir,
        {NET_FILE: ck.get("run_id"), SVM_FILE: svm.get("run_id"), HOG_FILE: hog.get("run_id")},
        summary if isinstance(summary, dict) else None,
    )
    summary = summary if isinstance(summary, dict) else {}
    class_names = list(ck["class_names"])
    for other, f in ((svm, SVM_FILE), (hog, HOG_FILE)):
        if list(other["class_names"]) != class_names:
            raise ModelError(
                f"{run_dir / f} was trained on classes {other['class_names']}, LunarNet_ex on {class_names}: retrain"
            )
    return net, ck, svm, hog, summary, run_id, class_names


def _check_roll_averaging(rolls: int, ck: dict, run_dir: Path) -> None:
    """Roll averaging (``train.tta_rotations`` > 1) needs models trained on disc-support crops."""
    if rolls > 1 and (ck.get("preprocess") or {}).get("support", "square") != "disc":
        raise ModelError(
            f"train.tta_rotations={rolls}: the models in {run_dir} were trained on square crops; roll averaging "
            "needs disc-support crops (train.preprocess.support=disc), which any turn keeps inside the box"
        )


def _metrics_and_confusions(out_dir: Path, test: RealTestSet, preds: dict, vals: dict, class_names: list) -> dict:
    """Each model's metrics on the test set, with its confusion matrix plotted into ``out_dir``."""
    metrics: dict = {}
    for name in MODELS:
        metrics[name] = model_metrics(test.labels, np.asarray(preds[name], dtype=np.int64), test, vals[name])
        plot_confusion(
            out_dir / confusion_file(name),
            metrics[name]["confusion"],
            class_names,
            f"{name}: real accuracy {metrics[name]['real_accuracy']:.1%}",
        )
    return metrics


def _write_realset(path: Path, test: RealTestSet, preds: dict, class_names: list) -> None:
    """One JSON line per test crop: its source and every model's prediction."""
    rows = []
    for i, c in enumerate(test.crops):
        r = c.as_row()
        r.update({f"pred_{m}": class_names[int(preds[m][i])] for m in MODELS})
        rows.append(json.dumps(r, sort_keys=True))
    atomic_write_text(path, "\n".join(rows) + "\n")


def evaluate_run(
    settings: Settings,
    run_dir: str | Path,
    progress: bool = True,
    test: RealTestSet | None = None,
    out_dir: str | Path | None = None,
) -> dict:
    """Evaluate the saved models (``train.registry``) of ``run_dir`` on the real test set; write the metrics
    files into ``out_dir`` (default ``run_dir``; the pipeline passes a staging directory, :mod:`train.runs`).
    The models and the summary must be of one training run (:func:`train.runs.check_one_run`)."""
    run_dir = Path(run_dir)
    out_dir = run_dir if out_dir is None else Path(out_dir)
    device = configure_torch(settings.train)
    t0 = time.perf_counter()
    net, ck, svm, hog, summary, run_id, class_names = _load_run(run_dir, device)
    if test is None:  # with the preprocessing the network was trained with
        from train.preprocess import PreprocessConfig

        pp = PreprocessConfig(**ck["preprocess"]) if ck.get("preprocess") else None
        test = build_real_test_set(settings, craters_for(settings, class_names), class_names, pp)
    ebs = settings.train.eval_batch_size
    rolls = settings.train.tta_rotations
    _check_roll_averaging(rolls, ck, run_dir)
    preds = roll_averaged_predictions(
        net,
        svm["model"],
        hog["model"],
        _saved_hog(hog, run_dir / HOG_FILE, settings),
        test.images,
        rolls,
        ebs,
        device,
        progress,
    )
    vals = {
        "lunarnet_ex": ck.get("val_accuracy"),
        "lunarsvm_ex": svm.get("val_accuracy"),
        "hog_svm": hog.get("val_accuracy"),
    }
    if set(preds) != set(MODELS) or set(vals) != set(MODELS):
        raise AssertionError(f"evaluate_run predicts {sorted(preds)}, train.registry lists {list(MODELS)}")
    metrics = _metrics_and_confusions(out_dir, test, preds, vals, class_names)
    metrics.update(
        {
            "classes": class_names,
            "train_images": int(summary.get("train_images", 0)),
            "val_images": int(summary.get("val_images", 0)),
            "test_images": int(len(test.labels)),
            "test_skipped_crops": len(test.skipped),
            "test_skipped": list(test.skipped),
            "test_sources": test.sources,
            "test_per_crater": {n: int(np.sum(test.labels == i)) for i, n in enumerate(class_names)},
            "limits": LIMITS_NOTE
            if any(c.kind == "embedded" for c in test.crops)
            else "Real test frames only (labels file, georeferenced frames); see realset.jsonl for their sources.",
            "tta_rotations": rolls,
            "evaluate_seconds": time.perf_counter() - t0,
            "run_id": run_id,
        }
    )
    _write_realset(out_dir / REALSET_FILE, test, preds, class_names)
    atomic_write_text(out_dir / METRICS_FILE, json_text(_jsonable(metrics)))
    return metrics


def _saved_hog(doc: dict, path: Path, settings: Settings) -> HogSettings:
    """The HOG parameters the saved HOG+SVM was trained with (recorded in its file; the configured
    ``train.hog`` for a file that records none)."""
    if not doc.get("hog"):
        return settings.train.hog
    try:
        return HogSettings.from_config(doc["hog"], "hog")
    except SettingsError as exc:
        raise ModelError(f"cannot load {path}: its recorded {exc}") from None


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
