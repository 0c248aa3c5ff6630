"""A small navigation result in the shapes `make navigate-demo` (crater_synth/navigation/demo.py) and
`crater-synth nav-frames-eval --json` (crater_synth/navigation/rendered/evaluate.py) write, for the report's
navigation section: the JSON files and tiny PNGs, nothing detected or rendered."""

from __future__ import annotations

import json
from pathlib import Path


def _png(path: Path, colour=(40, 80, 120)) -> None:
    from PIL import Image

    Image.new("RGB", (12, 10), colour).save(path)


def _summary(windows, fix_rate, median, p90, ident, recall, precision) -> dict:
    return {
        "windows": windows,
        "fix_rate": fix_rate,
        "median_error_km": median,
        "p90_error_km": p90,
        "false_fix_rate": 0.0,
        "false_fixes": 0,
        "identification_accuracy": ident,
        "identified_per_fix": 7.0,
        "recall_15km": recall,
        "precision_15km": precision,
    }


def make_demo(nav: Path) -> dict:
    """A navigation.json in the shape crater_synth/navigation/demo.py writes (window_entry), with its PNGs."""
    from crater_synth.navigation.demo import DEMO_JSON, window_entry

    nav.mkdir(parents=True, exist_ok=True)
    fixed = {
        "id": "S0_1728_0128",
        "split": "validation",
        "sector": 0,
        "light_azimuth_deg": 30.0,
        "n_detections": 155,
        "truth": list(range(25)),
        "n_headline_landmarks": 16,
        "matched": {i: i for i in range(13)},
        "fix": True,
        "reason": "",
        "error_km": 1.3026,
        "identified": 7,
        "identified_correct": 6,
    }
    lost = {
        "id": "S1_2496_0832",
        "split": "test",
        "sector": 1,
        "light_azimuth_deg": 30.0,
        "n_detections": 116,
        "truth": list(range(21)),
        "n_headline_landmarks": 15,
        "matched": {1: 2},
        "fix": False,
        "reason": "only 4 landmarks agree (need 5)",
    }
    windows = [window_entry("classical", r, f"{r['id']}_classical.png") for r in (fixed, lost)]
    # The appearance search's terrain patches alone on the first window (no crater to match).
    patched = {**fixed, "n_detections": 12, "truth": [], "matched": {}, "error_km": 0.18, "identified": 11}
    patched["identified_correct"] = 11
    windows.append({**window_entry("patches", patched, f"{fixed['id']}_patches.png"), "landmarks_in_view": 16})
    catalogue = _catalogue(fixed)
    for w in windows + catalogue["windows"]:
        _png(nav / w["png"])
    doc = {
        "kind": "crater-synth navigate-demo",
        "schema_version": 1,
        "per_sector": 1,
        "min_landmark_km": 10.0,
        "prior_offset_km": 5.0,
        "false_fix_km": 5.0,
        "methods": {
            "classical": {
                "splits": {
                    "test": {
                        "headline": _summary(1, 0.0, None, None, None, 0.086, 0.031),
                        "all_windows": _summary(1, 0.0, None, None, None, 0.086, 0.031),
                    },
                    "validation": {
                        "headline": _summary(1, 1.0, 1.3026, 1.3026, 0.8571, 0.5217, 0.1939),
                        "all_windows": _summary(1, 1.0, 1.3026, 1.3026, 0.8571, 0.5217, 0.1944),
                    },
                }
            },
            "patches": {
                "splits": {
                    "validation": {
                        "headline": _summary(1, 1.0, 0.18, 0.18, 1.0, None, None),
                        "all_windows": _summary(1, 1.0, 0.18, 0.18, 1.0, None, None),
                    },
                }
            },
        },
        "map_check": {
            "source": "a crater catalogue (test)",
            "criteria": {"centre_within_d": 0.15, "diameter_within": 0.25},
            "n_inside_dem": 3,
            "bins": [
                {"diameter_km": "10-15", "listed": 2, "recall": 0.5, "landmarks": 4, "precision": 0.25},
                {"diameter_km": ">= 50", "listed": 0, "recall": None, "landmarks": 1, "precision": 1.0},
            ],
        },
        "windows": windows,
        "catalogue_detection": catalogue,
    }
    (nav / DEMO_JSON).write_text(json.dumps(doc))
    return doc


def _catalogue(window: dict) -> dict:
    """navigation.json's catalogue_detection (crater_synth/navigation/demo.py, demo_catalogue) on one validation
    window: rows in score_window's shape, their counts by catalogue_entry."""
    from crater_synth.navigation.demo import catalogue_entry
    from crater_synth.navigation.protocol import catalogue_scores

    base = {k: window[k] for k in ("id", "split", "sector")} | {"matched": {}, "matched_any": []}
    rows = {
        # 4 catalogued craters of D >= 15 km (and one of 12 km), 3 found; 5 detections of D >= 15 km, 2 false.
        "learned-detect": {
            **base,
            "catalogue_d_km": [20.0, 18.0, 12.0, 30.0, 16.0],
            "catalogue_found": [0, 1, 3],
            "det_r_km": [10.0, 9.0, 15.0, 8.0, 8.5, 4.0],
            "matched_catalogue": [0, 1, 2],
        },
        # nothing found: 1 missed, 1 false.
        "template": {
            **base,
            "catalogue_d_km": [40.0],
            "catalogue_found": [],
            "det_r_km": [9.0],
            "matched_catalogue": [],
        },
    }
    return {
        "source": "a crater catalogue (test)",
        "pole": "south",
        "split": "validation",
        "min_d_km": 15.0,
        "match": {"centre_within_d": 0.25, "diameter_within": 0.25},
        "methods": {m: catalogue_scores([r]) for m, r in rows.items()},
        "windows": [catalogue_entry(m, r, f"{r['id']}_{m}_catalogue.png") for m, r in rows.items()],
    }


def _frame(i, alt, fix_err, perfect_err, reason="2 landmarks identified (need 5)") -> dict:
    def fix(err):
        return (
            {"fix": True, "reason": "", "error_km": err, "identified": 9}
            if err is not None
            else {
                "fix": False,
                "reason": reason,
                "error_km": None,
                "identified": None,
            }
        )

    return {
        "index": i,
        "altitude_km": alt,
        "ground_sample_m": alt * 2.25,
        "landmarks_in_view": 20 - 5 * i,
        "landmarks_in_view_min_d": 12 - 3 * i,
        "headline_landmarks": 6 - 2 * i,
        "n_detections": 140 - 10 * i,
        "matched": 5 - i,
        **fix(fix_err),
        "perfect": {"n_detections": 20 - 5 * i, **fix(perfect_err)},
    }


def make_frames(nav: Path, name: str = "frames_eval.json") -> dict:
    """A nav-frames-eval result in the shape crater_synth/navigation/rendered/record.py's frames_record writes."""
    nav.mkdir(parents=True, exist_ok=True)
    empty = _summary(3, 0.0, None, None, None, 0.2, 0.05)
    doc = {
        "kind": "crater-synth nav-frames-eval",
        "schema_version": 1,
        "trajectory": "descent_ridge",
        "method": "position",
        "preset": "appearance",
        "settings": [],
        "min_landmark_km": 10.0,
        "min_inliers": 5,
        "false_fix_km": 5.0,
        "render": {"mode": "fast", "samples": 1, "width_px": 512, "fov_deg": 60.0},
        "summary": {
            "all": {**empty, "fix_rate": 0.3333, "median_error_km": 0.412},
            "headline": empty,
            "perfect": {"all": {**empty, "fix_rate": 0.6667}, "headline": empty},
            "unrefined": {"all": {**empty, "fix_rate": 0.3333, "median_error_km": 0.93}, "headline": empty},
        },
        "frames": [
            _frame(0, 150.0, 0.412, 1.02e-5),  # both fix
            _frame(1, 138.2, None, 6.3e-6, "only 3 landmarks agree on one position"),  # perfect detections only
            _frame(2, 126.4, None, None, "no putative landmark pairs"),  # neither
        ],
    }
    (nav / name).write_text(json.dumps(doc))
    return doc
