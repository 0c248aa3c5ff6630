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
import time
import warnings
from pathlib import Path

import joblib
import numpy as np
import torch
import yaml
from sklearn.base import clone
from sklearn.exceptions import ConvergenceWarning
from torch import nn

from crater_core.progress import Progress
from crater_core.progress import write as progress_write
from crater_core.schema import atomic_write_bytes, atomic_write_text, sha256_file
from crater_core.settings import ModelSettings, Settings, SettingsError, TrainSettings, replace
from train.data import SyntheticCropDataset, SyntheticData, seeded_subsample
from train.errors import ModelError, RealDataLeakError, TrainError
from train.metrics import accuracy, class_mean_accuracy
from train.models import LunarNetEx, hog_features, make_linear_svm, multiply_adds, parameter_count
from train.registry import SPECS
from train.runs import CONFIG_FILE, SUMMARY_FILE, new_run_id

NET_FILE, SVM_FILE, HOG_FILE = (SPECS[k].artefact for k in ("lunarnet_ex", "lunarsvm_ex", "hog_svm"))
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
def _apply(fn, X, batch_size: int, device, width: int, bar: Progress | None = None):
    """(outputs, labels or None) of ``fn`` over the batches of ``X``, counted on ``bar`` (images)."""
    out, labels = [], []
    for xb, yb in _batches(X, batch_size):
        t = torch.from_numpy(np.ascontiguousarray(xb, dtype=np.float32))[:, None].to(device)
        out.append(fn(t).float().cpu().numpy())
        if yb is not None:
            labels.append(yb)
        if bar is not None:
            bar.update(len(xb))
    res = np.concatenate(out) if out else np.zeros((0, width), np.float32)
    return res, (np.concatenate(labels) if labels else None)


def predict_logits(model: LunarNetEx, X, batch_size: int = 256, device=torch.device("cpu")) -> np.ndarray:
    """Logits for an (N, H, W) array or a :class:`SyntheticCropDataset` (streamed)."""
    model.eval()
    return _apply(model, X, batch_size, device, model.geometry["nc"])[0]


def fc1_activations(
    model: LunarNetEx, X, batch_size: int = 256, device=torch.device("cpu"), bar: Progress | None = None
) -> np.ndarray:
    """FC1 (after ReLU3) activations for an array or a dataset (streamed), counted on ``bar``."""
    model.eval()
    return _apply(model.fc1_features, X, batch_size, device, model.geometry["f1"], bar)[0]


# ------------------------------------------------------------------------------------------------
# LunarNet_ex
# ------------------------------------------------------------------------------------------------
def _train_epoch(model, opt, loss_fn, train_set, bs: int, seed: int, epoch: int, max_epochs: int, device, mode: str):
    """One pass of Adam over the training set: (summed loss, correct, images seen, seconds). Its batches
    are counted on a :class:`Progress` of ``mode`` (a bar erased at the epoch's end on a terminal)."""

    train_set.set_epoch(epoch)
    model.train()
    tot_loss, tot_ok, tot_n = 0.0, 0, 0
    t0 = time.perf_counter()
    loader = _loader(train_set, bs, True, seed + epoch)
    bar = Progress(len(loader), f"lunarnet_ex epoch {epoch}/{max_epochs}", "batch", mode, leave=False)
    for xb, yb in loader:
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
        bar.update(loss=f"{tot_loss / tot_n:.3f}", acc=f"{tot_ok / tot_n:.3f}", img_s=f"{rate:.0f}")
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
    mode = "auto" if progress else "off"
    for epoch in range(1, max_epochs + 1):
        tot_loss, tot_ok, tot_n, dt = _train_epoch(
            model, opt, loss_fn, data.train, bs, seed, epoch, max_epochs, device, mode
        )
        train_time += dt
        images_seen += tot_n
        pv = predict_logits(model, data.val, ebs, device).argmax(1)
        rec = _epoch_record(epoch, tot_loss, tot_ok, tot_n, dt, yv, pv, t_start)
        val_acc = rec["val_accuracy"]
        history.append(rec)
        if progress:
            progress_write(
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
    (deterministic: no augmentation, epoch-0 sensor noise); report class-balanced validation accuracies.

    ``progress``: the features are counted per crop (rate, ETA) and each fit, which scikit-learn cannot
    report from inside, is a stage with an estimated duration (:func:`fit_svm`)."""
    require_synthetic(data.train)
    require_synthetic(data.val)
    ts = settings.train
    seed = ts.seed
    device = next(model.parameters()).device
    ebs = ts.eval_batch_size
    yt, yv = data.train.labels, data.val.labels
    mode = "auto" if progress else "off"
    out = {}
    t0 = time.perf_counter()
    svm = make_linear_svm(ts.svm, seed)
    with Progress(len(data.train), "lunarsvm_ex: FC1 features of the training crops", "crop", mode) as bar:
        Ft = fc1_activations(model, data.train, ebs, device, bar)
    conv = fit_svm(svm, Ft, yt, "lunarsvm_ex", mode)
    del Ft
    with Progress(len(data.val), "lunarsvm_ex: validation", "crop", mode) as bar:
        pv = svm.predict(fc1_activations(model, data.val, ebs, device, bar))
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
    Ht = hog_batches(data.train.iter_arrays(ebs, sel), len(sel), hog_s, "hog_svm: HOG of the training crops", mode)
    hog_svm = make_linear_svm(hog_s, seed)
    conv = fit_svm(hog_svm, Ht, yt[sel], "hog_svm", mode)
    del Ht
    # Validation HOG is predicted batch by batch: at paper scale (40,500 validation crops, 7,056
    # features each) the whole matrix would be 2.3 GB of RAM.
    pv = hog_batches(data.val.iter_arrays(ebs), len(data.val), hog_s, "hog_svm: validation", mode, hog_svm.predict)
    out["hog_svm"] = {
        "model": hog_svm,
        "val_accuracy": class_mean_accuracy(yv, pv),
        "train_images": int(len(sel)),
        "converged": conv,
        "seconds": time.perf_counter() - t0,
    }
    if progress:
        progress_write(
            f"lunarsvm_ex val acc (class mean) {out['lunarsvm_ex']['val_accuracy']:.3f}; "
            f"hog_svm val acc {out['hog_svm']['val_accuracy']:.3f}"
        )
    return out


def hog_batches(batches, n: int, hog_s, desc: str, mode: str, then=None) -> np.ndarray:
    """HOG features of ``n`` crops arriving as ``(X, y)`` batches, counted per crop on a :class:`Progress`;
    with ``then`` (e.g. a fitted model's ``predict``) its result per batch instead of the features."""
    out = []
    with Progress(n, desc, "crop", mode) as bar:
        for xb, _ in batches:
            h = hog_features(xb, hog_s)
            out.append(h if then is None else then(h))
            bar.update(len(xb))
    if out:
        return np.concatenate(out)
    return np.zeros((0, 0), np.float32) if then is None else np.zeros(0, np.int64)


# The estimate of an SVM fit: a fit of the same pipeline on a seeded subset this large (at most a tenth
# of the rows), scaled by the row count. None below PROBE_MIN_ROWS: there the fit takes no time to speak of.
PROBE_MAX_ROWS, PROBE_MIN_ROWS = 2000, 20


def fit_svm(svm, X: np.ndarray, y: np.ndarray, name: str, mode: str) -> bool:
    """:func:`_fit_quiet` as a :meth:`Progress.stage`: a start line with an ETA and an end line with the time
    taken. The ETA is the time of a fit on a seeded subset of the rows, scaled linearly by the row count; SGD's
    epoch count to converge differs between the subset and the whole set, so it is a guide to the order of
    magnitude, not a promise (and costs at most a tenth of the fit it estimates; none with ``mode="off"``)."""
    eta, basis = None, ""
    m = min(PROBE_MAX_ROWS, len(X) // 10)
    if mode != "off" and m >= PROBE_MIN_ROWS:
        rows = np.sort(np.random.default_rng(0x5F17).choice(len(X), size=m, replace=False))
        if len(np.unique(y[rows])) > 1:  # a one-class subset cannot be fitted
            t = time.perf_counter()
            _fit_quiet(clone(svm), X[rows], y[rows])
            probe_s = time.perf_counter() - t
            eta = probe_s * len(X) / m
            basis = f"a fit on {m} of them took {probe_s:.2f} s"
    desc = f"{name}: SVM fit on {len(X)} crops x {X.shape[1] if X.ndim == 2 else 0} features"
    with Progress.stage(desc, eta, basis, mode):
        return _fit_quiet(svm, X, y)


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
