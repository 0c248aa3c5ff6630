"""What ``crater-synth nav-frames-eval`` writes (:mod:`.evaluate`): the per-frame JSON the report reads
(:func:`frames_record`) and the summary recorded under ``synthetic`` in docs/results/navigation.json
(:func:`record_results`)."""

from __future__ import annotations

import json
from pathlib import Path

from crater_core import exr, schema
from crater_synth.navigation.protocol import FALSE_FIX_KM, PRIOR_OFFSET_KM
from crater_synth.navigation.settings import RESULTS_UNSUFFIXED_PRESET

FRAMES_EVAL_JSON = "frames_eval.json"
FRAME_FIELDS = (
    "fix",
    "reason",
    "error_km",
    "error_horizontal_km",
    "unrefined",
    "identified",
    "identified_correct",
    "rms_px",
    "putative_pairs",
    "enough_landmarks",
    "fix_source",  # "craters" or "patches" (--patches), None without a fix
    "patches",  # what the terrain patches gave, when they were searched
    "prior_sigma_km",  # the prior's uncertainty (--sequential: carried from the last fix)
    "sigma_horizontal_km",  # the fix's own 1-sigma horizontal uncertainty
    "fix_position",  # the fixed camera centre: planetocentric lat, lon (deg), altitude above the sphere (m)
    "attitude_error_deg",  # nav.frames.solver=pnp: the angle between the fixed and the true camera attitude
)


def frames_record(frames_dir: Path, summary: dict, rows: list[dict], seed: int, nav, overrides=()) -> dict:
    """The machine-readable result of ``nav-frames-eval`` (``--json``; read by ``crater-synth report``):
    per frame the altitude, ground sample, landmarks in view (all labels; and >= the fix's minimum size),
    detections, matched labels and the fix (or the reason for none) of the detector and of the
    perfect-detection check."""
    frames = []
    for r in rows:
        p = r["perfect"]
        frames.append(
            {
                "index": r["index"],
                "altitude_km": r["altitude_km"],
                "ground_sample_m": r["ground_sample_m"],
                "landmarks_in_view": r["landmarks_in_view"],
                "landmarks_in_view_min_d": len(r["truth"]),
                "headline_landmarks": r["n_headline_landmarks"],
                "n_detections": r["n_detections"],
                "matched": len(r["matched"]),
                **{k: r.get(k) for k in FRAME_FIELDS},
                "perfect": {"n_detections": p["n_detections"], **{k: p.get(k) for k in FRAME_FIELDS}},
            }
        )
    return {
        "kind": "crater-synth nav-frames-eval",
        "schema_version": 1,
        "frames_dir": str(Path(frames_dir).resolve()),
        "trajectory": rows[0]["id"].split("/")[0],
        "method": nav.frames.solver,
        "seed": seed,
        "settings": list(overrides),
        "preset": nav.preset,
        "detector": None if nav.appearance else nav.detector.as_dict(),  # the appearance search runs none
        "fix_settings": nav.fix.as_dict(),
        "inlier_px": nav.frames.inlier_px,
        "min_landmark_km": nav.fix.min_landmark_km,
        "min_inliers": nav.fix.min_inliers,
        "false_fix_km": FALSE_FIX_KM,
        "render": _render_info(frames_dir),
        "summary": summary,
        "frames": frames,
    }


def _render_info(frames_dir: Path) -> dict:
    """Render settings of the first frame, from its EXR header (mode, samples, G-buffer samples in fast
    mode, frame size)."""
    rows = [json.loads(line) for line in (Path(frames_dir) / schema.MANIFEST_NAME).read_text().splitlines() if line]
    header = exr.read_header(Path(frames_dir) / rows[0]["rel_path"])
    render = json.loads(header.get("crater_synth:render") or "{}")
    return {
        "mode": header.get("crater_synth:mode"),
        "samples": header.get("samples"),
        "gbuffer_samples": render.get("gbuffer_samples") or None,
        "width_px": rows[0]["pose"]["width_px"],
        "fov_deg": rows[0]["pose"]["fov_deg"],
    }


def record_results(path: Path, frames_dir: Path, rows: list[dict], summary: dict, nav) -> None:
    """Record ``summary`` (a trajectory's, with the settings ``nav`` of a ``nav/preset``) under ``synthetic``
    in the results file ``path`` (e.g. docs/results/navigation.json; its other entries kept), keyed by
    trajectory, fix solver and preset (and the sensor, terrain patches and sequential priors where used)."""
    preset, method = nav.preset, nav.frames.solver
    results = json.loads(Path(path).read_text(encoding="utf-8")) if Path(path).is_file() else {}
    info = _render_info(frames_dir)
    key = f"{rows[0]['id'].split('/')[0]}/{method}" + ("" if preset == RESULTS_UNSUFFIXED_PRESET else f"/{preset}")
    key += f"/sensor={summary['sensor']}" if summary.get("sensor") else ""
    key += "/patches" if summary.get("patches") else ""
    key += "/sequential" if summary.get("sequence") else ""
    results.setdefault("synthetic", {})[key] = {
        "command": f"crater-synth nav-frames trajectory={rows[0]['id'].split('/')[0]} "
        f"render.mode={info['mode']} render.samples={info['samples']}"
        + (f" render.gbuffer_samples={info['gbuffer_samples']}" if info["gbuffer_samples"] else "")
        + f" trajectory.width_px={info['width_px']}",
        "render": info,
        "protocol": {
            "prior_offset_km": PRIOR_OFFSET_KM,
            "prior_attitude": "exact",
            "light_direction": "given (attitude + ephemeris)",
            "preset": preset,
            "preset_settings": {
                "detector": nav.detector.method,
                "scales_from_map": nav.frames.scales_from_map,
                "inlier_px": nav.frames.inlier_px,
                "refine": nav.frames.refine,
            },
            "method": method,
            "patches": summary.get("patches"),  # terrain patches where the craters give no fix (None: off)
            "sequence": summary.get("sequence"),  # priors carried from the last fix (None: every frame alone)
            "error": "3-D camera centre distance",
        },
        "frames": [
            {
                k: r.get(k)
                for k in ("index", "altitude_km", "ground_sample_m", "n_detections", "fix", "error_km", "reason")
                + (("fix_source",) if summary.get("patches") else ())
            }
            for r in rows
        ],
        **summary,
    }
    schema.atomic_write_text(Path(path), json.dumps(results, indent=1) + "\n")
