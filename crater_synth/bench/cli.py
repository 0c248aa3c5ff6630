"""``crater-synth bench`` / ``make bench``: the performance goals, measured (never asserted in tests).

Parts (``--part``, default all, in this order):
- ``distributed``: renders/s of the Dask path vs one process (crater_synth.bench.distributed.bench_distributed);
- ``train``: LunarNet_ex training images/s and time to the validation target on the demo sweep
  (crater_synth.bench.train.run_train_bench; skipped with a note if that dataset is not rendered yet);
- ``renderer``: crater_synth.bench.renderer: (a) a whole paper crater (22,500 renders), (b) sweep=demo,
  (c) a 60-sun x 24-camera grid, (d) direct mode with the ROI crop on a sample of (a)'s items (and
  fast-vs-direct per pixel on them), (e) the naive whole-frame baseline, and peak RSS, in one run
  (~10-20 min on 2 cores);
- ``navigation``: detection + identification + fix frames/s on a 1024 x 1024 real mosaic window
  (crater_synth.bench.navigation.bench_navigation);
- ``export``: ``crater-synth export`` time and peak RSS on a generated dataset of ``--export-renders``
  EXRs, extrapolated to the 67,500-render sweep (crater_synth.bench.export);
- ``navframes``: navigation-frame renders/s along a trajectory, then their navigation time per frame,
  appearance search against the classical detector (crater_synth.bench.navframes);
- ``detector``: training cost of the learned crater detector, s per step, fixed s and peak RSS, on the
  survey or ``--detector-frames``, on ``--detector-device``, with ``--detector-train`` settings
  (crater_synth.bench.detector; skipped with a note if its frames are not rendered yet);
- ``detector-layout``: the detector network's training step and 1024² level in the standard layout, channels last
  and with the bfloat16 forward pass, in one run (crater_synth.bench.detector_layout);
- ``detection-frames``: detection-frame renders/s at 256² and 512², the default grouping against one frame per field
  (crater_synth.bench.detection);
- ``detect``: ``crater-synth detect`` on synthetic frames: seconds per 1024 x 1024 and 2592 x 1944 frame, peak
  RSS, and a folder in one process against one process per image (crater_synth.bench.detect);
- ``opencv``: the solvers OpenCV does for the project (PnP minimal solve and RANSAC fix, NCC, crop warps)
  against the hand-written code they replaced, before/after ms, ratio and agreement (crater_synth.bench.opencv).

The last two lines are exactly ``paper_crater_renders_per_s=A demo_renders_per_s=B grid_renders_per_s=C
direct_roi_renders_per_s=D`` and ``renders_per_s=X naive_renders_per_s=Y ratio=Z``.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import click

from crater_synth.bench.detect import bench_detect
from crater_synth.bench.detection import bench_detection
from crater_synth.bench.detection import summary_line as detection_summary_line
from crater_synth.bench.detector import bench_detector_training
from crater_synth.bench.export import bench_export, summary_line
from crater_synth.bench.navframes import bench_navframes
from crater_synth.bench.navigation import bench_navigation
from crater_synth.bench.opencv import bench_opencv
from crater_synth.bench.renderer import bench_renderer, summary_lines
from crater_synth.bench.train import run_train_bench
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import compose, load_settings
from crater_synth.navigation.rendered.detector_train import DEFAULT_FRAMES

PARTS = (
    "renderer",
    "train",
    "distributed",
    "navigation",
    "export",
    "navframes",
    "detector",
    "detector-layout",
    "detect",
    "opencv",
    "detection-frames",
)


@click.command("bench")
@click.option(
    "--part",
    type=click.Choice(["all", *PARTS]),
    default="all",
    show_default=True,
)
@click.option(
    "--keep",
    type=click.Path(file_okay=False),
    default=None,
    help="Keep the benchmark datasets in this directory (default: a temp dir, removed).",
)
@click.option(
    "--export-renders",
    type=click.IntRange(min=4),
    default=1000,
    show_default=True,
    help="Size of the generated dataset the export part measures.",
)
@click.option(
    "--navframes-frames",
    type=click.IntRange(min=1),
    default=4,
    show_default=True,
    help="navframes part: how many of the trajectory's first frames to render (each path).",
)
@click.option(
    "--detector-frames",
    type=click.Path(file_okay=False, path_type=Path),
    default=DEFAULT_FRAMES,
    show_default=True,
    help="detector part: the frames folder to train on (a rendered survey or a detection set).",
)
@click.option(
    "--detector-device",
    type=click.Choice(["cpu", "cuda"]),
    default="cpu",
    show_default=True,
    help="detector part: the training device.",
)
@click.option(
    "--detector-train",
    "detector_train",
    multiple=True,
    metavar="nav.detector_train.KEY=VALUE",
    help="detector part: a training setting (repeatable), e.g. nav.detector_train.loader_workers=4.",
)
@OVERRIDES
@user_errors
def bench_command(
    part, keep, export_renders, navframes_frames, detector_frames, detector_device, detector_train, overrides
):
    """Measure the performance goals: renderer vs baselines, training, distributed sweep, navigation, export.

    Overrides apply to every part, e.g. ``crater-synth bench render.workers=2``. The last line is
    ``renders_per_s=X naive_renders_per_s=Y ratio=Z`` (after the renderer's rates line).
    """
    overrides = list(overrides)
    for setting in detector_train:
        if not setting.startswith("nav.detector_train.") or "=" not in setting:
            raise click.BadParameter(f"{setting!r}: not nav.detector_train.KEY=VALUE", param_hint="--detector-train")
    load_settings(overrides)  # a typo stops here in one line, not after the parts that ignore it have run
    work = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="crater-synth-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        if part in ("all", "distributed"):
            from crater_synth.bench.distributed import bench_distributed  # Dask: the dask extra, this part's alone

            cfg = compose(["sweep=smoke", "crater=shackleton", "launcher=dask", *overrides])
            click.echo("distributed " + json.dumps(bench_distributed(cfg, work / "distributed")))
        if part in ("all", "train"):
            settings = load_settings(["sweep=demo", "train.progress=false", *overrides])
            dataset = Path(settings.train.dataset_dir) / "manifest.jsonl"
            if dataset.is_file():
                click.echo("train " + json.dumps(run_train_bench(settings)))
            else:
                click.echo(
                    f"train skipped: no rendered dataset at {dataset.parent} (make demo, or "
                    f"make dataset OVERRIDES=sweep=demo, renders it)"
                )
        if part in ("all", "navigation"):
            click.echo("navigation " + json.dumps(bench_navigation()))
        if part in ("all", "export"):
            r = bench_export(work / "export", export_renders)
            click.echo("export " + json.dumps(r))
            click.echo(summary_line(r))
        if part in ("all", "navframes"):
            click.echo("navframes " + json.dumps(bench_navframes(overrides, work, navframes_frames)))
        if part in ("all", "detector"):
            if detector_frames.is_dir():
                from train.crater_detector import DetectorTrainSettings

                full = DetectorTrainSettings().steps
                r = bench_detector_training(
                    detector_frames, work / "detector", full, detector_device, tuple(detector_train)
                )
                click.echo("detector " + json.dumps(r))
            else:
                click.echo(
                    f"detector skipped: no frames at {detector_frames} (crater-synth nav-detector-frames, "
                    "or make nav-detector, renders the survey there)"
                )
        if part in ("all", "detector-layout"):
            from crater_synth.bench.detector_layout import bench_detector_layout  # torch: this part's alone

            click.echo("detector-layout " + json.dumps(bench_detector_layout()))
        if part in ("all", "detect"):
            click.echo("detect " + json.dumps(bench_detect(work / "detect")))
        if part in ("all", "opencv"):
            click.echo("opencv " + json.dumps(bench_opencv()))
        if part in ("all", "detection-frames"):
            r = bench_detection(overrides, work / "detection_frames")
            click.echo("detection-frames " + json.dumps(r))
            click.echo(detection_summary_line(r))
        if part in ("all", "renderer"):
            r = bench_renderer(overrides, work / "renderer")
            click.echo("renderer " + json.dumps(r))
            for line in summary_lines(r):
                click.echo(line)
    finally:
        if not keep:
            shutil.rmtree(work, ignore_errors=True)
