"""The ``crater-synth detection-frames`` command and its launchers: ``launcher=local`` renders one folder on
this machine (:mod:`crater_synth.dataset.detection_run`); ``launcher=dask`` renders a folder of shard
folders on a Dask cluster (:mod:`crater_synth.dataset.detection_dask`, imported only for it: Dask is the
``dask`` extra).
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import load_settings
from crater_synth.dataset.detection import detection_overrides
from crater_synth.dataset.detection_run import render_detection_frames
from crater_synth.errors import UserError


@click.command("detection-frames")
@OVERRIDES
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Output directory.")
@click.option("--frames", "n_frames", type=int, default=4, show_default=True, help="Frames to render.")
@click.option("--start", type=int, default=0, show_default=True, help="Index of the first frame.")
@user_errors
def detection_frames_command(overrides, out, n_frames, start):
    """Render labelled detection frames of procedural crater fields (EXR, label file + manifest), resumably.

    Each frame draws its field (procedural.*, default procedural=detection), Sun and view (detection.*, default
    detection=default: conditions and grouping) from the run seed and its index. Example:
    `crater-synth detection-frames --out data/detection --frames 8 seed=1 detection.width_px=512`.
    With `launcher=dask`, a folder of shard folders (OUT/shard_NNNNN/, one Dask task each):
    `crater-synth detection-frames --out /shared/det --frames 1000000 launcher=dask launcher.address=tcp://head:8786`
    """
    if start < 0:
        raise UserError(f"--start {start}: must be >= 0")
    settings = load_settings(detection_overrides(overrides))
    if settings.launcher.name == "dask":
        from crater_synth.dataset.detection_dask import run_detection_dask  # needs the dask extra

        click.echo(json.dumps(run_detection_dask(settings, out, n_frames, start)))
        return
    click.echo(json.dumps(render_detection_frames(settings, out, n_frames, start)))
