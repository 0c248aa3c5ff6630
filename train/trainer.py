"""Training of LunarNet_ex (Adam, stop at the validation target), LunarSVM_ex and the HOG+SVM baseline.

Everything here consumes :class:`train.data.SyntheticData` only: synthetic renders, never real crops.
Artefacts in ``run_dir`` (each written atomically; names from :mod:`train.registry`): ``lunarnet_ex.pt``
(state dict, model config, class names, preprocessing, history, resolved config), ``lunarsvm_ex.joblib``
and ``hog_svm.joblib`` (scikit-learn pipelines, joblib), ``config.yaml`` (resolved) and
``train_summary.json``.
"""

from __future__ import annotations

import io
import json
import os
import pickle
import sys
import time
import warnings
from pathlib import Path

import joblib
import numpy as np
import torch
import yaml
from sklearn.exceptions import ConvergenceWarning
from torch import nn
from tqdm import tqdm

from crater_core.schema import atomic_write_bytes, atomic_write_text, sha256_file
from crater_core.settings import ModelSettings, Settings, SettingsError, TrainSettings, replace
from train.data import SyntheticCropDataset, SyntheticData, seeded_subsample
from train.errors import ModelError, RealDataLeakError, TrainError
from train.metrics import accuracy, class_mean_accuracy
from train.models import LunarNetEx, hog_features, make_linear_svm, multiply_adds, parameter_count
from train.registry import SPECS
from train.runs import new_run_id

NET_FILE, SVM_FILE, HOG_FILE = (SPECS[k].artefact for k in ("lunarnet_ex", "lunarsvm_ex", "hog_svm"))
SUMMARY_FILE, CONFIG_FILE = "train_summary.json", "config.yaml"
SKLEARN_FORMAT = 2  # 1: pickle (.pkl, before joblib); 2: joblib


# ------------------------------------------------------------------------------------------------
# Small utilities
# ------------------------------------------------------------------------------------------------
def json_text(obj) -> str:
    """The project's JSON layout for run artefacts (indented, sorted keys, trailing newline)."""
    return json.dumps(obj, indent=2, sort_keys=True) + "\n"


def configure_torch(train: TrainSettings) -> torch.device:
    """Set torch's thread count (``train.num_threads``, 0 = every core) and return the device of
    ``train.device`` (``auto``: CUDA when there is one); CUDA asked for and absent is a TrainError."""
    n = train.num_threads
    torch.set_num_threads(n if n > 0 else max(1, os.cpu_count() or 1))
    dev = train.device
    if dev == "auto":
        dev = "cuda" if torch.cuda.is_available() else "cpu"
    if dev == "cuda" and not torch.cuda.is_available():
        raise TrainError("train.device=cuda but no CUDA device is available (use train.device=cpu)")
    return torch.device(dev)


def require_synthetic(ds) -> None:
    if not isinstance(ds, SyntheticCropDataset):
        raise RealDataLeakError(f"training accepts only synthetic render datasets, got {type(ds).__name__}")


def _loader(ds, batch_size: int, shuffle: bool, seed: int):
    g = torch.Generator()
    g.manual_seed(int(seed) & 0x7FFFFFFF)
    return torch.utils.data.DataLoader(
        ds, batch_size=batch_size, shuffle=shuffle, generator=g, num_workers=0, drop_last=False
    )


def _batches(X, batch_size: int):
    """(X, y|None) batches from an array or a dataset's deterministic stream."""
    if isinstance(X, SyntheticCropDataset):
        yield from X.iter_arrays(batch_size)
    else:
        for i in range(0, len(X), batch_size):
            yield X[i : i + batch_size], None


@torch.no_grad()
def _apply(fn, X, batch_size: int, device, width: int) -> tuple[np.ndarray, np.ndarray | None]:
    out, labels = [], []
    for xb, yb in _batches(X, batch_size):
        t = torch.from_numpy(np.ascontiguousarray(xb, dtype=np.float32))[:, None].to(device)
        out.append(fn(t).float().cpu().numpy())
        if yb is not None:
            labels.append(yb)
    res = np.concatenate(out) if out else np.zeros((0, width), np.float32)
    return res, (np.concatenate(labels) if labels else None)


def predict_logits(model: LunarNetEx, X, batch_size: int = 256, device=torch.device("cpu")) -> np.ndarray:
    """Logits for an (N, H, W) array or a :class:`SyntheticCropDataset` (streamed)."""
    model.eval()
    return _apply(model, X, batch_size, device, model.geometry["nc"])[0]


def fc1_activations(model: LunarNetEx, X, batch_size: int = 256, device=torch.device("cpu")) -> np.ndarray:
    """FC1 (after ReLU3) activations for an array or a dataset (streamed)."""
    model.eval()
    return _apply(model.fc1_features, X, batch_size, device, model.geometry["f1"])[0]


# ------------------------------------------------------------------------------------------------
# LunarNet_ex
# ------------------------------------------------------------------------------------------------
def _train_epoch(model, opt, loss_fn, train_set, bs: int, seed: int, epoch: int, max_epochs: int, device, bar_on: bool):
    """One pass of Adam over the training set: (summed loss, correct, images seen, seconds)."""

    train_set.set_epoch(epoch)
    model.train()
    tot_loss, tot_ok, tot_n = 0.0, 0, 0
    t0 = time.perf_counter()
    # The batch bar on a terminal only: in a log, the epoch summary line is the progress.
    bar = tqdm(
        _loader(train_set, bs, True, seed + epoch),
        desc=f"lunarnet_ex epoch {epoch}/{max_epochs}",
        unit="batch",
        disable=not bar_on,
        leave=False,
    )
    for xb, yb in bar:
        xb, yb = xb.to(device, non_blocking=True), yb.to(device, non_blocking=True)
        opt.zero_grad(set_to_none=True)
        logits = model(xb)
        loss = loss_fn(logits, yb)
        loss.backward()
        opt.step()
        n = int(yb.numel())
        tot_loss += float(loss.item()) * n
        tot_ok += int((logits.argmax(1) == yb).sum().item())
        tot_n += n
        rate = tot_n / max(time.perf_counter() - t0, 1e-9)
        bar.set_postfix(loss=f"{tot_loss / tot_n:.3f}", acc=f"{tot_ok / tot_n:.3f}", img_s=f"{rate:.0f}")
    bar.close()
    return tot_loss, tot_ok, tot_n, time.perf_counter() - t0


def _epoch_record(epoch: int, tot_loss: float, tot_ok: int, tot_n: int, dt: float, yv, pv, t_start: float) -> dict:
    """One epoch's history entry: training loss and accuracy, validation accuracy (class mean and overall)
    of the predictions ``pv`` against ``yv``, throughput and elapsed time."""
    return {
        "epoch": epoch,
        "loss": tot_loss / max(tot_n, 1),
        "train_accuracy": tot_ok / max(tot_n, 1),
        "val_accuracy": class_mean_accuracy(yv, pv),
        "val_accuracy_overall": accuracy(yv, pv),
        "epoch_seconds": dt,
        "images_per_s": tot_n / max(dt, 1e-9),
        "elapsed_s": time.perf_counter() - t_start,
    }


def _training_summary(history, best, target, reached_at, train_time, images_seen, device, model, arch) -> dict:
    """What a LunarNet_ex training did: its history, best epoch, target reached and throughput."""
    return {
        "history": history,
        "best_epoch": best["epoch"],
        "val_accuracy": best["val_accuracy"],
        "target_val_accuracy": target,
        "reached_target": reached_at is not None,
        "time_to_target_s": reached_at,
        "train_seconds": train_time,
        "train_images_per_s": images_seen / max(train_time, 1e-9),
        "device": str(device),
        "parameters": parameter_count(model),
        "multiply_adds": multiply_adds(arch)["total"],
    }


def train_lunarnet(
    data: SyntheticData,
    settings: Settings,
    run_dir: str | Path | None = None,
    progress: bool = True,
    run_id: str | None = None,
) -> tuple[LunarNetEx, dict]:
    """Adam on cross-entropy until the class-balanced validation accuracy reaches
    ``train.target_val_accuracy`` or ``train.max_epochs``. The best-validation weights are kept and,
    with ``run_dir``, checkpointed atomically after every epoch that improves them (each checkpoint
    carrying ``run_id``: :mod:`train.runs`).

    Returns (model, history) where history holds per-epoch loss/accuracy/throughput and timings."""
    require_synthetic(data.train)
    require_synthetic(data.val)
    ts = settings.train
    arch = model_for(settings.model, data.class_names)
    device = configure_torch(ts)
    seed = ts.seed
    torch.manual_seed(seed)
    model = LunarNetEx(arch).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=ts.lr, weight_decay=ts.weight_decay)
    loss_fn = nn.CrossEntropyLoss()  # = the Softmax layer + log-loss
    target = ts.target_val_accuracy
    max_epochs = ts.max_epochs
    bs, ebs = ts.batch_size, ts.eval_batch_size
    yv = data.val.labels
    history: list[dict] = []
    best = {"val_accuracy": -1.0, "state": None, "epoch": 0}
    t_start = time.perf_counter()
    train_time = 0.0
    images_seen = 0
    reached_at = None
    bar_on = progress and sys.stderr.isatty()
    for epoch in range(1, max_epochs + 1):
        tot_loss, tot_ok, tot_n, dt = _train_epoch(
            model, opt, loss_fn, data.train, bs, seed, epoch, max_epochs, device, bar_on
        )
        train_time += dt
        images_seen += tot_n
        pv = predict_logits(model, data.val, ebs, device).argmax(1)
        rec = _epoch_record(epoch, tot_loss, tot_ok, tot_n, dt, yv, pv, t_start)
        val_acc = rec["val_accuracy"]
        history.append(rec)
        if progress:
            tqdm.write(
                f"lunarnet_ex epoch {epoch}: loss {rec['loss']:.4f} train acc {rec['train_accuracy']:.3f} "
                f"val acc (class mean) {val_acc:.3f} [{rec['images_per_s']:.0f} img/s]"
            )
        if val_acc > best["val_accuracy"]:
            best = {
                "val_accuracy": val_acc,
                "epoch": epoch,
                "state": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
            }
            if run_dir is not None:
                save_lunarnet(
                    run_dir, best["state"], arch, data.class_names, settings, history, best["epoch"], val_acc, run_id
                )
        if val_acc >= target:
            reached_at = rec["elapsed_s"]
            break
    model.load_state_dict(best["state"])
    summary = _training_summary(history, best, target, reached_at, train_time, images_seen, device, model, arch)
    if run_dir is not None:  # final save carries the complete history
        save_lunarnet(
            run_dir,
            best["state"],
            arch,
            data.class_names,
            settings,
            history,
            best["epoch"],
            best["val_accuracy"],
            run_id,
        )
    return model, summary


def model_for(model: ModelSettings, class_names) -> ModelSettings:
    """The ``model`` settings with ``num_classes`` set to the number of classes trained."""
    n = len(class_names)
    return model if model.num_classes == n else replace(model, num_classes=n)


def save_lunarnet(
    run_dir, state, model: ModelSettings, class_names, settings: Settings, history, epoch, val_acc, run_id=None
) -> Path:
    """The checkpoint: weights, the model's layer sizes, classes, preprocessing, history and the whole
    configuration (plain mappings, as the run's config.yaml), written atomically."""
    from train.preprocess import PreprocessConfig

    buf = io.BytesIO()
    torch.save(
        {
            "format": 1,
            "state_dict": state,
            "model": model.as_dict(),
            "class_names": list(class_names),
            "preprocess": PreprocessConfig.from_settings(settings.train.preprocess, settings.model.input_size).__dict__,
            "epoch": epoch,
            "val_accuracy": val_acc,
            "history": history,
            "config": settings.as_dict(),
            "run_id": run_id,
        },
        buf,
    )
    path = Path(run_dir) / NET_FILE
    atomic_write_bytes(path, buf.getvalue())
    return path


def load_lunarnet(run_dir: str | Path, device=torch.device("cpu")) -> tuple[LunarNetEx, dict]:
    path = Path(run_dir) / NET_FILE
    if not path.is_file():
        raise ModelError(f"no trained LunarNet_ex at {path}: run `crater-synth train` first (or set run_dir)")
    try:
        ck = torch.load(path, map_location=device, weights_only=True)  # a user-supplied file: no pickled code
        model = LunarNetEx(ModelSettings.from_config(ck["model"], "model")).to(device)
        model.load_state_dict(ck["state_dict"])
    except (RuntimeError, KeyError, TypeError, SettingsError, pickle.UnpicklingError, EOFError) as exc:
        # torch's messages on a damaged file run to paragraphs: its first sentence names the fault.
        why = str(exc).strip().split("\n")[0].split(". ")[0].rstrip(".")
        raise ModelError(f"cannot load {path}: not a LunarNet_ex checkpoint ({type(exc).__name__}: {why})") from None
    model.eval()
    return model, ck


# ------------------------------------------------------------------------------------------------
# LunarSVM_ex and HOG + SVM
# ------------------------------------------------------------------------------------------------
def train_svms(model: LunarNetEx, data: SyntheticData, settings: Settings, progress: bool = True) -> dict:
    """Fit LunarSVM_ex (FC1 activations) and the HOG+SVM baseline on the synthetic training images
    (deterministic: no augmentation, epoch-0 sensor noise); report class-balanced validation accuracies."""
    require_synthetic(data.train)
    require_synthetic(data.val)
    ts = settings.train
    seed = ts.seed
    device = next(model.parameters()).device
    ebs = ts.eval_batch_size
    yt, yv = data.train.labels, data.val.labels
    out = {}
    t0 = time.perf_counter()
    svm = make_linear_svm(ts.svm, seed)
    conv = _fit_quiet(svm, fc1_activations(model, data.train, ebs, device), yt)
    pv = svm.predict(fc1_activations(model, data.val, ebs, device))
    out["lunarsvm_ex"] = {
        "model": svm,
        "val_accuracy": class_mean_accuracy(yv, pv),
        "train_images": int(len(yt)),
        "converged": conv,
        "seconds": time.perf_counter() - t0,
    }
    t0 = time.perf_counter()
    hog_s = ts.hog
    sel = seeded_subsample(len(data.train), hog_s.max_train_images, seed, 0x406)
    Ht = np.concatenate([hog_features(xb, hog_s) for xb, _ in data.train.iter_arrays(ebs, sel)])
    hog_svm = make_linear_svm(hog_s, seed)
    conv = _fit_quiet(hog_svm, Ht, yt[sel])
    del Ht
    # Validation HOG is predicted batch by batch: at paper scale (40,500 validation crops, 7,056
    # features each) the whole matrix would be 2.3 GB of RAM.
    pv = np.concatenate(
        [hog_svm.predict(hog_features(xb, hog_s)) for xb, _ in data.val.iter_arrays(ebs)] or [np.zeros(0, np.int64)]
    )
    out["hog_svm"] = {
        "model": hog_svm,
        "val_accuracy": class_mean_accuracy(yv, pv),
        "train_images": int(len(sel)),
        "converged": conv,
        "seconds": time.perf_counter() - t0,
    }
    if progress:
        tqdm.write(
            f"lunarsvm_ex val acc (class mean) {out['lunarsvm_ex']['val_accuracy']:.3f}; "
            f"hog_svm val acc {out['hog_svm']['val_accuracy']:.3f}"
        )
    return out


def _fit_quiet(model, X, y) -> bool:
    """Fit, turning scikit-learn's ConvergenceWarning into a returned flag (recorded in the summary)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ConvergenceWarning)
        model.fit(X, y)
    return not any(issubclass(w.category, ConvergenceWarning) for w in caught)


def save_sklearn(path: str | Path, model, class_names, meta: dict) -> None:
    """A fitted scikit-learn model with its class names and metadata, as one joblib file (atomic)."""
    buf = io.BytesIO()
    joblib.dump({"format": SKLEARN_FORMAT, "model": model, "class_names": list(class_names), **meta}, buf)
    atomic_write_bytes(path, buf.getvalue())


def load_sklearn(path: str | Path) -> dict:
    """What :func:`save_sklearn` wrote; ModelError naming the file if it is missing, corrupt or stale."""
    path = Path(path)
    if not path.is_file():
        if path.with_suffix(".pkl").is_file():
            raise ModelError(
                f"{path.with_suffix('.pkl')} was saved by an older crater-synth (pickle); "
                f"retrain with `crater-synth train` to write {path.name}"
            )
        raise ModelError(f"no trained model at {path}: run `crater-synth train` first (or set run_dir)")
    try:
        doc = joblib.load(path)
    except (
        pickle.UnpicklingError,
        EOFError,
        AttributeError,
        ImportError,
        KeyError,
        IndexError,
        ValueError,
        TypeError,
        OSError,
    ) as exc:
        raise ModelError(f"cannot load {path}: {exc or type(exc).__name__}") from None
    if not (
        isinstance(doc, dict)
        and doc.get("format") == SKLEARN_FORMAT
        and "model" in doc
        and isinstance(doc.get("class_names"), list)
    ):
        raise ModelError(f"cannot load {path}: not a crater-synth scikit-learn model file (format {SKLEARN_FORMAT})")
    return doc


# ------------------------------------------------------------------------------------------------
# All three
# ------------------------------------------------------------------------------------------------
def train_all(
    settings: Settings, data: SyntheticData, run_dir: str | Path, progress: bool = True, run_id: str | None = None
) -> dict:
    """Train the three classifiers on ``data`` and save them (plus config and summary) in ``run_dir``.

    Every model file and the summary carry ``run_id`` (default: a new one), the summary also each
    model's sha256 (``artefacts``), so that a directory mixing two runs is refused (:mod:`train.runs`;
    ``crater-synth train`` trains into a staging directory and publishes the run whole)."""
    run_id = run_id or new_run_id()
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(run_dir / CONFIG_FILE, yaml.safe_dump(settings.as_dict(), sort_keys=False))
    model, net = train_lunarnet(data, settings, run_dir, progress, run_id)
    svms = train_svms(model, data, settings, progress)
    save_sklearn(
        run_dir / SVM_FILE,
        svms["lunarsvm_ex"]["model"],
        data.class_names,
        {"kind": "lunarsvm_ex", "val_accuracy": svms["lunarsvm_ex"]["val_accuracy"], "run_id": run_id},
    )
    save_sklearn(
        run_dir / HOG_FILE,
        svms["hog_svm"]["model"],
        data.class_names,
        {
            "kind": "hog_svm",
            "val_accuracy": svms["hog_svm"]["val_accuracy"],
            "hog": settings.train.hog.as_dict(),
            "run_id": run_id,
        },
    )
    summary = {
        "run_id": run_id,
        "artefacts": {name: sha256_file(run_dir / name) for name in (NET_FILE, SVM_FILE, HOG_FILE)},
        "class_names": data.class_names,
        "data": data.info,
        "train_images": int(len(data.train)),
        "val_images": int(len(data.val)),
        "lunarnet_ex": {k: v for k, v in net.items()},
        "lunarsvm_ex": {k: v for k, v in svms["lunarsvm_ex"].items() if k != "model"},
        "hog_svm": {k: v for k, v in svms["hog_svm"].items() if k != "model"},
    }
    atomic_write_text(run_dir / SUMMARY_FILE, json_text(summary))
    return summary
