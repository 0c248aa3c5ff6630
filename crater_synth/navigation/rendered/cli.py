"""``crater-synth nav-frames-eval DIR``: the metrics of :mod:`.evaluate` on a ``nav-frames`` directory,
printed per frame, written as JSON for the report and, with ``--results PATH``, recorded in a results file
(the committed one: ``--results docs/results/navigation.json``)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import click

from crater_core import schema
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import load_settings
from crater_synth.errors import UserError
from crater_synth.navigation.fix.patches import PatchParams
from crater_synth.navigation.fix.sequence import SequenceParams
from crater_synth.navigation.map.dem_error import DemErrorParams
from crater_synth.navigation.protocol import PRIOR_OFFSET_KM, check_prior_offset_km
from crater_synth.navigation.rendered.evaluate import DirOptions, FrameRun, evaluate_dir, frame_run
from crater_synth.navigation.rendered.record import FRAMES_EVAL_JSON, frames_record, record_results
from crater_synth.navigation.settings import DEFAULT_FRAMES_PRESET, compose_nav


@click.command("nav-frames-eval")
@click.argument("frames_dir", type=click.Path(path_type=Path))
@click.option(
    "--results",
    "results_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Record the summary under 'synthetic' in this results file, its other entries kept (the committed "
    "record: docs/results/navigation.json); a preset's settings only.",
)
@click.option(
    "--json",
    "json_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Per-frame results (detector and perfect-detection check) as JSON [FRAMES_DIR/frames_eval.json]; "
    "crater-synth report reads RUN_DIR/navigation/frames_eval*.json.",
)
@click.option("--seed", default=0, show_default=True, help="Seed of the prior offsets.")
@click.option(
    "--attitude-error-deg",
    type=float,
    default=0.0,
    show_default=True,
    help="The lander's attitude error: the pipeline uses the true attitude turned by this angle (seeded axis).",
)
@click.option(
    "--prior-offset-km",
    type=float,
    default=PRIOR_OFFSET_KM,
    show_default=True,
    help="How far the position prior is from the true camera (seeded direction); the gate is nav.fix.prior_sigma_km.",
)
@click.option(
    "--sensor",
    default=None,
    help="Sensor config (configs/sensor/, e.g. nav_camera) applied to each frame before navigating it.",
)
@click.option(
    "--patches/--no-patches",
    default=None,
    help="nav/preset=appearance: a frame its craters do not fix is navigated with terrain patches (4 x 4 grid); "
    "on by default for that preset, --no-patches: craters only.",
)
@click.option(
    "--refine-pose/--no-refine-pose",
    default=None,
    help="nav.frames.solver=pnp with a preset that refines: the 6-DOF fix refined by appearance, attitude and "
    "position (the default there; --no-refine-pose: as RANSAC gives it).",
)
@click.option(
    "--attitude-sigma-deg",
    type=float,
    default=0.0,
    show_default=True,
    help="With --refine-pose: the believed attitude's 1-sigma (deg); the refined 6-DOF pose is weighted towards "
    "it (0: no attitude prior).",
)
@click.option(
    "--sequential",
    is_flag=True,
    help="Each frame's position prior from its trajectory's last fix, carried by the motion plus a 1 % drift.",
)
@click.option(
    "--dem-error-m",
    type=float,
    default=0.0,
    show_default=True,
    help="The lander's DEM carries a smooth seeded height error of this RMS (m; the frames stay as rendered).",
)
@click.option(
    "--dem-error-km", type=float, default=5.0, show_default=True, help="Central wavelength of that error (km)."
)
@click.option(
    "--terrain-workers",
    type=click.IntRange(1, 16),
    default=1,
    show_default=True,
    help="Processes preparing each frame's new landmark and patch windows (the same results, sooner cold).",
)
@OVERRIDES
@user_errors
def nav_frames_eval_command(frames_dir, json_path, results_path, seed, overrides, **options):
    """Navigation metrics (detection, identification, fix) on rendered frames with exact truth, and the
    perfect-detection check (each label's own ellipse as a detection: the same identification and fix).
    Settings are Hydra overrides (docs/navigation/settings.md): `nav/preset=synthetic` (default: appearance),
    `nav.frames.solver=pnp`, `nav.fix.min_inliers=4`, `nav.detector.threshold=0.4`.

    Example: `crater-synth nav-frames-eval data/navframes/descent_ridge nav/preset=synthetic`
    """
    nav = compose_nav(overrides, defaults=[f"nav/preset={DEFAULT_FRAMES_PRESET}"])
    run, dir_options = frames_eval_options(nav, results_path is not None, overrides, seed, **options)
    summary, rows = evaluate_dir(frames_dir, run, dir_options, progress=True)
    summary.update(frames_eval_summary_fields(options, run, dir_options))
    for r in rows:
        click.echo(frame_line(r, options["sequential"]), err=True)
    json_path = json_path or Path(frames_dir) / FRAMES_EVAL_JSON
    record = frames_record(frames_dir, summary, rows, seed, nav, overrides)
    schema.atomic_write_text(json_path, json.dumps(record, indent=1) + "\n")
    click.echo(f"wrote {json_path}", err=True)
    if results_path is not None:
        record_results(results_path, frames_dir, rows, summary, nav)
        click.echo(f"wrote {results_path}", err=True)
    click.echo(json.dumps(summary))


def frames_eval_options(nav, recording: bool, overrides, seed: int, **o) -> tuple[FrameRun, DirOptions]:
    """The settings and options of :func:`.evaluate.evaluate_dir` from ``nav`` and the command's options,
    each checked (one error line naming the option)."""
    preset = nav.preset or nav.choices["detector"]
    if recording and any(not ov.startswith("nav/preset=") for ov in overrides):
        raise UserError("--results records a preset's settings only; drop the other overrides")
    if not 0.0 <= o["attitude_error_deg"] <= 10.0:
        raise UserError(f"--attitude-error-deg {o['attitude_error_deg']:g}: expected 0 to 10 degrees")
    check_prior_offset_km(o["prior_offset_km"])
    if recording and (o["attitude_error_deg"] or o["prior_offset_km"] != PRIOR_OFFSET_KM):
        raise UserError("--results records the standard prior and attitude only")
    if o["patches"] and not nav.appearance:
        raise UserError(f"--patches needs the appearance search (nav/preset=appearance), not {preset}")
    patches = nav.appearance if o["patches"] is None else o["patches"]  # the appearance preset's default
    solver = nav.frames.solver
    refines_pnp = solver == "pnp" and bool(nav.frames.refine or nav.appearance)
    if o["refine_pose"] and not refines_pnp:
        raise UserError(
            f"--refine-pose refines a 6-DOF fix (nav.frames.solver=pnp) of a preset that refines, not {preset}"
        )
    refine_pose = refines_pnp if o["refine_pose"] is None else o["refine_pose"]
    sigma = o["attitude_sigma_deg"]
    if not 0.0 <= sigma <= 10.0 or (sigma and not refine_pose):
        raise UserError(f"--attitude-sigma-deg {sigma:g}: 0 to 10 degrees, with a refined 6-DOF fix")
    try:
        eparams = DemErrorParams(o["dem_error_m"], o["dem_error_km"]) if o["dem_error_m"] else None
    except ValueError as exc:
        raise UserError(f"--dem-error-m/--dem-error-km: {exc}") from None
    if recording and eparams is not None:
        raise UserError("--results records the lander's DEM as it is; drop --dem-error-m")
    if eparams is not None and not nav.appearance and not nav.frames.refine:
        raise UserError(f"--dem-error-m: the {preset} preset does not use the lander's DEM")
    camera = None
    if o["sensor"] is not None:
        from train.preprocess import SensorModel

        camera = SensorModel.from_settings(load_settings([f"sensor={o['sensor']}"]).sensor)
    run = frame_run(
        nav,
        seed=seed,
        attitude_error_deg=o["attitude_error_deg"],
        prior_offset_km=o["prior_offset_km"],
        refine_pnp=refine_pose,
        attitude_sigma_deg=sigma,
    )
    dir_options = DirOptions(
        sensor=camera,
        terrain_workers=o["terrain_workers"],
        patches=PatchParams() if patches else None,
        sequence=SequenceParams() if o["sequential"] else None,
        dem_error=eparams,
    )
    return run, dir_options


def frames_eval_summary_fields(options: dict, run: FrameRun, dir_options: DirOptions) -> dict:
    """What the summary records of the run's options."""
    return dict(
        sensor=options["sensor"],
        attitude_error_deg=run.attitude_error_deg,
        prior_offset_km=run.prior_offset_km,
        refine_pose=run.refine_pnp,
        attitude_sigma_deg=run.attitude_sigma_deg,
        patches=dataclasses.asdict(dir_options.patches) if dir_options.patches else None,
        sequence=dataclasses.asdict(dir_options.sequence) if dir_options.sequence else None,
        dem_error=dataclasses.asdict(dir_options.dem_error) if dir_options.dem_error else None,
    )


def frame_line(r: dict, sequential: bool) -> str:
    """One frame's line on stderr."""
    return (
        f"frame {r['index']:3d} alt {r['altitude_km']:6.1f} km gsd {r['ground_sample_m']:6.1f} m "
        f"det {r['n_detections']:3d} truth {len(r['truth']):3d} matched {len(r['matched']):3d} "
        f"fix {r['fix']!s:5} "
        + (f"err {r['error_km']:.3f} km" if r["fix"] else r["reason"])
        + (" (terrain patches)" if r.get("fix_source") == "patches" else "")
        + (f" prior {r['prior_sigma_km']:g} km" if sequential else "")
        + "; perfect detections: "
        + (f"err {r['perfect']['error_km'] * 1000:.3f} m" if r["perfect"]["fix"] else r["perfect"]["reason"])
    )
