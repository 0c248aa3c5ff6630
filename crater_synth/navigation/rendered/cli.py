"""``crater-synth nav-frames-eval DIR``: the metrics of :mod:`.frames_eval` on a ``nav-frames`` directory,
printed per frame, written as JSON for the report and, with ``--write-results``, recorded in
docs/results/navigation.json."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import click

from crater_core import schema
from crater_synth.cli_common import user_errors
from crater_synth.errors import UserError
from crater_synth.navigation.fix.patches import PatchParams
from crater_synth.navigation.fix.sequence import SequenceParams
from crater_synth.navigation.map.dem_error import DemErrorParams
from crater_synth.navigation.protocol import PRIOR_OFFSET_KM, check_prior_offset_km
from crater_synth.navigation.rendered.evaluate import evaluate_dir
from crater_synth.navigation.rendered.record import FRAMES_EVAL_JSON, frames_record, record_results
from crater_synth.navigation.settings import DEFAULT_FRAMES_PRESET, FRAMES_PRESETS, frames_params


@click.command("nav-frames-eval")
@click.argument("frames_dir", type=click.Path(path_type=Path))
@click.option(
    "--write-results", is_flag=True, help="Record the summary under 'synthetic' in docs/results/navigation.json."
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
    "--set", "sets", multiple=True, help="detect.<name>=<value> or fix.<name>=<value> (as in nav-eval); not recorded."
)
@click.option(
    "--preset",
    type=click.Choice(sorted(FRAMES_PRESETS)),
    default=DEFAULT_FRAMES_PRESET,
    show_default=True,
    help="appearance: landmarks found by their predicted appearance (no detector); synthetic: the classical "
    "detector's settings chosen on rendered frames; learned: the learned detector; real-window: the real "
    "windows' settings unchanged.",
)
@click.option(
    "--method",
    type=click.Choice(["position", "pnp"]),
    default="position",
    show_default=True,
    help="position: camera centre with the known attitude; pnp: full pose (ransac_pnp).",
)
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
    help="How far the position prior is from the true camera (seeded direction); the gate is fix.prior_sigma_km.",
)
@click.option(
    "--sensor",
    default=None,
    help="Sensor config (configs/sensor/, e.g. nav_camera) applied to each frame before navigating it.",
)
@click.option(
    "--patches/--no-patches",
    default=None,
    help="appearance preset: a frame its craters do not fix is navigated with terrain patches (4 x 4 grid); "
    "on by default for that preset, --no-patches: craters only.",
)
@click.option(
    "--refine-pose/--no-refine-pose",
    default=None,
    help="--method pnp with a preset that refines: the 6-DOF fix refined by appearance, attitude and position "
    "(the default there; --no-refine-pose: as RANSAC gives it).",
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
    "--dem-error-km",
    type=float,
    default=5.0,
    show_default=True,
    help="Central wavelength of that error (km).",
)
@click.option(
    "--terrain-workers",
    type=click.IntRange(1, 16),
    default=1,
    show_default=True,
    help="Processes preparing each frame's new landmark and patch windows (the same results, sooner cold).",
)
@user_errors
def nav_frames_eval_command(
    frames_dir,
    json_path,
    write_results,
    seed,
    sets,
    preset,
    method,
    attitude_error_deg,
    prior_offset_km,
    sensor,
    patches,
    refine_pose,
    attitude_sigma_deg,
    sequential,
    dem_error_m,
    dem_error_km,
    terrain_workers,
):
    """Navigation metrics (detection, identification, fix) on rendered frames with exact truth, and the
    perfect-detection check (each label's own ellipse as a detection: the same identification and fix).

    Example: `crater-synth nav-frames-eval data/navframes/descent_ridge`
    """
    if sets and write_results:
        raise UserError("--write-results records a preset's settings only; drop --set")
    dparams, fparams, pre = frames_params(preset, sets)
    camera = None
    if sensor is not None:
        from crater_synth.config import load_settings
        from train.preprocess import SensorModel

        camera = SensorModel.from_settings(load_settings([f"sensor={sensor}"]).sensor)
    if not 0.0 <= attitude_error_deg <= 10.0:
        raise UserError(f"--attitude-error-deg {attitude_error_deg:g}: expected 0 to 10 degrees")
    check_prior_offset_km(prior_offset_km)
    if write_results and (attitude_error_deg or prior_offset_km != PRIOR_OFFSET_KM):
        raise UserError("--write-results records the standard prior and attitude only")
    args = (pre.scales_from_map, pre.inlier_px, pre.refine, pre.appearance, camera, attitude_error_deg, prior_offset_km)
    if patches and pre.appearance is None:
        raise UserError(f"--patches needs the appearance search (--preset appearance), not --preset {preset}")
    patches = pre.appearance is not None if patches is None else patches  # the appearance preset's default
    refines_pnp = method == "pnp" and bool(pre.refine or pre.appearance)
    if refine_pose and not refines_pnp:
        raise UserError(f"--refine-pose refines a 6-DOF fix (--method pnp) of a preset that refines, not {preset}")
    refine_pose = refines_pnp if refine_pose is None else refine_pose
    if not 0.0 <= attitude_sigma_deg <= 10.0 or (attitude_sigma_deg and not refine_pose):
        raise UserError(f"--attitude-sigma-deg {attitude_sigma_deg:g}: 0 to 10 degrees, with a refined 6-DOF fix")
    pparams, sparams = (PatchParams() if patches else None), (SequenceParams() if sequential else None)
    try:
        eparams = DemErrorParams(dem_error_m, dem_error_km) if dem_error_m else None
    except ValueError as exc:
        raise UserError(f"--dem-error-m/--dem-error-km: {exc}") from None
    if write_results and eparams is not None:
        raise UserError("--write-results records the lander's DEM as it is; drop --dem-error-m")
    if eparams is not None and pre.appearance is None and not pre.refine:
        raise UserError(f"--dem-error-m: the {preset} preset does not use the lander's DEM")
    summary, rows = evaluate_dir(
        frames_dir,
        dparams,
        fparams,
        seed,
        method,
        *args,
        patches=pparams,
        sequence=sparams,
        dem_error=eparams,
        terrain_workers=terrain_workers,
        refine_pnp=refine_pose,
        attitude_sigma_deg=attitude_sigma_deg,
    )
    summary.update(
        sensor=sensor,
        attitude_error_deg=attitude_error_deg,
        prior_offset_km=prior_offset_km,
        refine_pose=refine_pose,
        attitude_sigma_deg=attitude_sigma_deg,
        patches=dataclasses.asdict(pparams) if pparams else None,
        sequence=dataclasses.asdict(sparams) if sparams else None,
        dem_error=dataclasses.asdict(eparams) if eparams else None,
    )
    for r in rows:
        click.echo(
            f"frame {r['index']:3d} alt {r['altitude_km']:6.1f} km gsd {r['ground_sample_m']:6.1f} m "
            f"det {r['n_detections']:3d} truth {len(r['truth']):3d} matched {len(r['matched']):3d} "
            f"fix {r['fix']!s:5} "
            + (f"err {r['error_km']:.3f} km" if r["fix"] else r["reason"])
            + (" (terrain patches)" if r.get("fix_source") == "patches" else "")
            + (f" prior {r['prior_sigma_km']:g} km" if sequential else "")
            + "; perfect detections: "
            + (f"err {r['perfect']['error_km'] * 1000:.3f} m" if r["perfect"]["fix"] else r["perfect"]["reason"]),
            err=True,
        )
    json_path = json_path or Path(frames_dir) / FRAMES_EVAL_JSON
    used = None if pre.appearance else dparams  # the appearance search runs no crater detector
    record = frames_record(frames_dir, summary, rows, seed, method, fparams, sets, preset, used, pre.inlier_px)
    schema.atomic_write_text(json_path, json.dumps(record, indent=1) + "\n")
    click.echo(f"wrote {json_path}", err=True)
    if write_results:
        record_results(frames_dir, rows, summary, preset, method, pre)
    click.echo(json.dumps(summary))
