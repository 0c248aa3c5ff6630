"""What ``crater-synth nav-frames-eval`` writes (:mod:`.frames_eval`): the per-frame JSON the report reads
(:func:`frames_record`) and the summary recorded under ``synthetic`` in docs/results/navigation.json
(:func:`record_results`)."""

from __future__ import annotations

import json
from pathlib import Path

from crater_core import exr, schema
from crater_synth.navigation.detectors.classical import DetectorParams
from crater_synth.navigation.fix.solve import FixParams
from crater_synth.navigation.protocol import FALSE_FIX_KM, PRIOR_OFFSET_KM, RESULTS_JSON
from crater_synth.navigation.settings import PNP_INLIER_PX, RESULTS_UNSUFFIXED_PRESET

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
    "attitude_error_deg",  # --method pnp: the angle between the fixed and the true camera attitude
)


def frames_record(
    frames_dir: Path,
    summary: dict,
    rows: list[dict],
    seed: int,
    method: str,
    fparams: FixParams,
    sets=(),
    preset: str | None = None,
    dparams: DetectorParams | None = None,
    inlier_px: float = PNP_INLIER_PX,
) -> dict:
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
        "method": method,
        "seed": seed,
        "settings": list(sets),
        "preset": preset,
        "detector": dparams.as_dict() if dparams is not None else None,
        "fix_settings": fparams.as_dict(),
        "inlier_px": inlier_px,
        "min_landmark_km": fparams.min_landmark_km,
        "min_inliers": fparams.min_inliers,
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


def record_results(frames_dir: Path, rows: list[dict], summary: dict, preset: str, method: str, pre) -> None:
    """Record ``summary`` (a trajectory's, with the preset ``pre`` named ``preset``) under ``synthetic`` in
    docs/results/navigation.json, keyed by trajectory, fix method and preset (and the sensor, terrain patches
    and sequential priors where they were used)."""
    results = json.loads(RESULTS_JSON.read_text(encoding="utf-8")) if RESULTS_JSON.is_file() else {}
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
                "detector": pre.detector,
                "sets": list(pre.sets),
                "scales_from_map": pre.scales_from_map,
                "inlier_px": pre.inlier_px,
                "refine": pre.refine,
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
    schema.atomic_write_text(RESULTS_JSON, json.dumps(results, indent=1) + "\n")
