"""`crater-synth train` and `crater-synth evaluate`: the CLI glue over :mod:`train.pipeline` (heavy
imports stay inside the commands; ``train/`` itself never imports this layer)."""

from __future__ import annotations

import click

from crater_synth.cli_common import OVERRIDES, user_errors, warn
from crater_synth.config import load_settings
from crater_synth.evaluation.run_folder import run_writer
from train.pipeline import evaluate_saved, train_and_evaluate
from train.registry import MODELS
from train.runs import EVALUATE_FILES, TRAIN_FILES


def _settings(overrides):
    return load_settings(overrides)


def _report(metrics: dict, run_dir) -> None:
    for line in metrics.get("test_skipped", []):
        warn(line)
    for m in MODELS:
        r = metrics[m]
        val = "n/a" if r.get("val_accuracy") is None else f"{r['val_accuracy']:.3f}"
        click.echo(f"{m:12s} real accuracy {r['real_accuracy']:.3f}  (validation {val})")
    skipped = metrics.get("test_skipped_crops", 0)
    click.echo(
        f"train images {metrics['train_images']}, real test images {metrics['test_images']} "
        f"from {metrics['test_sources']}" + (f", {skipped} crops skipped (they leave their frame)" if skipped else "")
    )
    click.echo(f"note: {metrics['limits']}")
    click.echo(f"wrote {run_dir}/metrics.json")


@click.command("train")
@OVERRIDES
@user_errors
def train_command(overrides):
    """Train the classifiers (LunarNet_ex, LunarSVM_ex, HOG+SVM) on the manifest at train.dataset_dir;
    evaluate them on the real crops.

    e.g. ``crater-synth train sweep=demo train.max_epochs=10 run_dir=outputs/demo``
    """
    settings = _settings(overrides)
    with run_writer(settings.run_dir, TRAIN_FILES):  # locked; a user's file of a run's name refused
        metrics = train_and_evaluate(settings)
    _report(metrics, settings.run_dir)


@click.command("evaluate")
@OVERRIDES
@user_errors
def evaluate_command(overrides):
    """Evaluate the models saved in run_dir on the real test set (metrics.json, confusion PNGs).

    The metrics files it replaces are kept in run_dir/previous/<UTC time they were written>/.
    """
    settings = _settings(overrides)
    kept: list = []
    with run_writer(settings.run_dir, EVALUATE_FILES):
        metrics = evaluate_saved(settings, kept=kept.append)
    _report(metrics, settings.run_dir)
    for folder in kept:
        click.echo(f"kept the previous metrics files in {folder}/")
