"""``crater-synth nav-detector-train``: the detector's training command, above both kinds of training data.

It sits above :mod:`.rendered` and :mod:`.windows`, which never import each other: rendered frames (the survey
and the procedural detection sets, :mod:`.rendered.detector_train`) train every synthetic-only model, and
``--real-windows`` adds the real mosaic windows (:mod:`.windows.training`) for the reference trained on real
images (docs/navigation/detectors.md).
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from crater_core.settings_nav import DetectorTrainSettings
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import compose_group
from crater_synth.errors import UserError
from crater_synth.navigation.detectors import learned
from crater_synth.navigation.detectors.learned import DEFAULT_MODEL
from crater_synth.navigation.rendered.detector_train import frames_source, train_from_sources
from crater_synth.navigation.windows.training import real_window_records


def real_source() -> tuple[list, list, dict, dict]:
    """(training records, no held-out records, what they are, scoring) of the real south mosaic windows of
    :mod:`crater_synth.navigation.windows.training`: the reference trained on real images. Nothing is held
    out: its threshold is chosen on the south validation windows (``python -m
    crater_synth.tools.detector_choice``), which share no pixel with these."""
    records, what = real_window_records()
    return records, [], what, {}


@click.command("nav-detector-train")
@click.argument("frames_dir", type=click.Path(path_type=Path), required=False)
@click.option(
    "--also",
    "more_dirs",
    multiple=True,
    type=click.Path(path_type=Path),
    help="Another frames folder, trained on together with FRAMES_DIR (repeatable).",
)
@click.option(
    "--real-windows",
    is_flag=True,
    help="Also train on the real south mosaic windows of the spent test sectors, catalogue-labelled (the "
    "reference trained on real images; never a synthetic-only model).",
)
@click.option("--out", type=click.Path(path_type=Path), default=None, help=f"Model file (default: {DEFAULT_MODEL}).")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True, help="Training device.")
@OVERRIDES
@user_errors
def nav_detector_train_command(frames_dir, more_dirs, real_windows, out, device, overrides):
    """Train the learned crater detector on rendered frames; score it on the held-out frames.

    FRAMES_DIR (and each --also folder) is a survey (crater-synth nav-detector-frames: the last 10 tracks held
    out) or a detection set (crater-synth detection-frames: the last 10 % of its fields held out). Several
    folders are trained on together (`nav.detector_train.source_shares=[0.5,0.5]`: each one's share of the
    drawn crops, FRAMES_DIR first, the real windows last) and each is scored on its own hold-out.
    --real-windows (with or without FRAMES_DIR) adds the real south windows with the LU1319381 catalogue as
    labels: the reference the synthetic-only detector is compared with (docs/navigation/detectors.md); --out
    is then required.

    Settings are Hydra overrides of nav.detector_train (docs/navigation/settings.md), e.g.
    `nav.detector_train.steps=500`, `nav.detector_train.checkpoints=[500,1000]` (also save the weights after
    these steps), `nav.detector_train.threads=4` (0: every core), `nav.detector_train.arch=fcos` (torchvision's
    FCOS instead of the learned detector's network; --out required), `nav.detector_train.init=MODEL.pt`
    (fine-tune that model), `nav.detector_train.frames=1000` (only the first 1,000 training frames of each
    detection set, its hold-out unchanged: the data curve), `nav.detector_train.max_off_nadir_deg=5` (only
    detection frames viewed within 5 degrees of nadir: the oblique-view ablation). Example:
    `crater-synth nav-detector-train data/detector_frames/south --out model.pt nav.detector_train.steps=500`
    """
    import torch

    key, eq, _ = str(frames_dir).partition("=")
    if frames_dir is not None and eq and "/" not in key and not frames_dir.exists():
        # With --real-windows alone, click reads the first override as FRAMES_DIR (an optional argument
        # before the variadic overrides): a missing path of the form key=value is that override.
        overrides, frames_dir = (str(frames_dir), *overrides), None
    settings = compose_group("nav/detector_train", DetectorTrainSettings, overrides)
    if device == "cuda" and not torch.cuda.is_available():
        raise UserError("--device cuda: no CUDA device is available (use --device cpu)")
    if frames_dir is None and more_dirs:
        raise UserError("nav-detector-train: --also needs FRAMES_DIR")
    if frames_dir is None and not real_windows:
        raise UserError("nav-detector-train: give FRAMES_DIR, --real-windows, or both")
    frames_dirs = () if frames_dir is None else (frames_dir, *more_dirs)
    if len(set(frames_dirs)) < len(frames_dirs):
        raise UserError(f"nav-detector-train: a frames folder is given twice ({', '.join(map(str, frames_dirs))})")
    n_sources = len(frames_dirs) + int(real_windows)
    if settings.source_shares and len(settings.source_shares) != n_sources:
        raise UserError(
            f"nav.detector_train.source_shares={list(settings.source_shares)}: one share per training source "
            f"({n_sources} given)"
        )
    if settings.arch != "centernet" and out is None:
        raise UserError(f"nav.detector_train.arch={settings.arch} needs --out (the default is the learned model)")
    if real_windows and out is None:
        raise UserError("--real-windows needs --out (the default is the committed synthetic-only model)")
    if settings.init:
        if not Path(settings.init).is_file():
            raise UserError(f"nav.detector_train.init={settings.init}: no such model file")
        learned.load_model(settings.init)  # a corrupt or foreign file: one line, before any frame is read
    sources = [frames_source(d, settings.frames, settings.max_off_nadir_deg, settings.stream) for d in frames_dirs] + (
        [real_source()] if real_windows else []
    )
    summary = train_from_sources(
        sources, out or DEFAULT_MODEL, settings, log=lambda m: click.echo(m, err=True), device=device
    )
    click.echo(json.dumps(summary, indent=1))
