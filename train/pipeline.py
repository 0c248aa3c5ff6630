"""`crater-synth train` / `evaluate` as functions (the closed loop and `make bench` call these too).

Both take the configuration as the typed, already validated :class:`crater_core.settings.Settings`
(``crater_synth.config.load_settings`` / ``settings_from``); nothing in ``train/`` checks it again.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from crater_core.files import check_dir_path
from crater_core.settings import Settings
from train.runs import StagedRun


def train_and_evaluate(settings: Settings, progress: bool | None = None) -> dict:
    """Train LunarNet_ex, LunarSVM_ex and HOG+SVM on the synthetic manifest at ``train.dataset_dir``
    and evaluate them on the real test set into ``run_dir``. Returns metrics.json's content.

    Cheap checks come first (the class count, ``train.cache_dir``, the manifest), then the real test
    set (a broken realset fails before hours of training); the checksums/paths of its image files are
    handed to the training loader, which refuses them. The models and metrics are written into a
    staging directory and published into ``run_dir`` together (:class:`train.runs.StagedRun`): an
    interrupted or refused run leaves ``run_dir`` as it was (and none where there was none)."""
    from train.data import (
        build_datasets,
        cache_dir_of,
        class_names_of,
        crop_export_index,
        require_classes,
        require_manifest,
    )
    from train.evaluate import craters_for, evaluate_run
    from train.realset import build_real_test_set
    from train.trainer import configure_torch, train_all

    progress = settings.train.progress if progress is None else progress
    class_names = require_classes(class_names_of(settings))
    check_dir_path(cache_dir_of(settings.train), "train.cache_dir")
    with StagedRun(settings.run_dir) as stage:  # creates and checks run_dir before minutes of caching
        configure_torch(settings.train)
        if settings.train.export_dir:  # the rows and crops come from an export (docs/export.md)
            crop_export_index(settings.train.export_dir)
        else:
            require_manifest(settings.train.dataset_dir)
        test = build_real_test_set(settings, craters_for(settings, class_names), class_names)
        real_paths = sorted({c.image_path for c in test.crops})
        data = build_datasets(
            settings, forbidden_sha256=test.image_sha256s(), forbidden_paths=real_paths, progress=progress
        )
        train_all(settings, data, stage, progress)
        return evaluate_run(settings, stage, progress, test=test)


def evaluate_saved(
    settings: Settings, progress: bool | None = None, kept: Callable[[Path], None] | None = None
) -> dict:
    """Evaluate the models saved in ``run_dir``; the metrics files are published together (staged).
    With ``kept`` the metrics files this replaces are kept in ``run_dir/previous/<UTC time>/``
    (:func:`train.runs.keep_previous`) and ``kept`` is called with that folder (not when none existed)."""
    from train.evaluate import evaluate_run

    progress = settings.train.progress if progress is None else progress
    run_dir = Path(settings.run_dir)
    staged = StagedRun(run_dir, keep_previous=kept is not None)
    with staged as stage:
        metrics = evaluate_run(settings, run_dir, progress, out_dir=stage)
    if kept is not None and staged.kept is not None:
        kept(staged.kept)
    return metrics
