"""`crater-synth train` / `evaluate` as functions (the closed loop and `make bench` call these too)."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping


def train_and_evaluate(cfg: Mapping, progress: bool | None = None) -> dict:
    """Train LunarNet_ex, LunarSVM_ex and HOG+SVM on the synthetic manifest at ``train.dataset_dir``
    and evaluate them on the real test set into ``run_dir``. Returns metrics.json's content.

    The real test set is built first (a broken realset fails before hours of training) and the
    checksums/paths of its image files are handed to the training loader, which refuses them."""
    from crater_core.files import ensure_writable_dir
    from train.data import build_datasets, class_names_from_config, require_manifest
    from train.evaluate import _craters_for, evaluate_run
    from train.realset import build_real_test_set
    from train.trainer import configure_torch, train_all

    progress = bool(cfg["train"].get("progress", True)) if progress is None else progress
    ensure_writable_dir(str(cfg["run_dir"]), "run_dir")  # before minutes of crop caching, not after
    configure_torch(cfg["train"])
    class_names = class_names_from_config(cfg)
    require_manifest(str(cfg["train"]["dataset_dir"]))
    test = build_real_test_set(cfg, _craters_for(cfg, class_names), class_names)
    real_paths = sorted({c.image_path for c in test.crops})
    data = build_datasets(cfg, forbidden_sha256=test.image_sha256s(), forbidden_paths=real_paths, progress=progress)
    run_dir = Path(str(cfg["run_dir"]))
    train_all(cfg, data, run_dir, progress)
    return evaluate_run(cfg, run_dir, progress, test=test)


def evaluate_saved(cfg: Mapping, progress: bool | None = None) -> dict:
    from train.evaluate import evaluate_run

    progress = bool(cfg["train"].get("progress", True)) if progress is None else progress
    return evaluate_run(cfg, Path(str(cfg["run_dir"])), progress)
