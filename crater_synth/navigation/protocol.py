"""The evaluation protocol shared by real mosaic windows and rendered frames: what counts as a match, a
headline frame and a false fix, and the metrics and summaries every navigation result reports.

A detection matches a truth landmark when its centre is within ``MATCH_CENTRE_D`` D and its diameter
within ``MATCH_DIAMETER`` (one-to-one, nearest first). The prior position is the truth moved by
``PRIOR_OFFSET_KM`` in a seeded random direction. A fix is false when its position error exceeds
``FALSE_FIX_KM``. The headline rows are the frames with >= ``HEADLINE_MIN_LANDMARKS`` landmarks of
D >= ``HEADLINE_MIN_D_KM`` in view.
"""

from __future__ import annotations

import numpy as np

from crater_synth.errors import UserError
from crater_synth.navigation.detectors.classical import Detection
from crater_synth.navigation.fix.solve import FALSE_FIX_KM
from crater_synth.navigation.georef import Georef

__all__ = ["FALSE_FIX_KM"]


MATCH_CENTRE_D = 0.25


MATCH_DIAMETER = 0.25


PRIOR_OFFSET_KM = 5.0


HEADLINE_MIN_D_KM = 15.0


HEADLINE_MIN_LANDMARKS = 3


SIZE_BINS_KM = (10.0, 15.0, 30.0, 60.0, 1e9)
# Size bins of the scores against the LU1319381 catalogue, which lists craters from 8 km.
CATALOGUE_BINS_KM = (8.0, 15.0, 30.0, 60.0, 1e9)


TARGETS = {"fix_rate": 0.9, "median_error_km": 0.8, "false_fix_rate": 0.01, "recall_15km": 0.8, "precision_15km": 0.9}


def truth_in_frame(landmarks, georef: Georef, shape, min_d_km: float = 0.0) -> list[int]:
    """Indices of the landmarks whose centre lies inside a frame of ``shape`` under ``georef``."""
    h, w = shape
    xs = np.array([lm.x_m for lm in landmarks])
    ys = np.array([lm.y_m for lm in landmarks])
    ds = np.array([lm.diameter_km for lm in landmarks])
    u, v = georef.xy_to_uv(xs, ys)
    return list(np.nonzero((u >= 0) & (u < w) & (v >= 0) & (v < h) & (ds >= min_d_km))[0])


def match_detections(dets: list[Detection], landmarks, idx: list[int], georef: Georef) -> dict[int, int]:
    """One-to-one matches detection index -> landmark index (centre within 0.25 D, diameter within 25 %)."""
    if not dets or not idx:
        return {}
    u, v = georef.xy_to_uv(np.array([landmarks[i].x_m for i in idx]), np.array([landmarks[i].y_m for i in idx]))
    r = np.array([landmarks[i].diameter_km for i in idx]) * 500.0 / georef.pixel_m
    du = np.array([d.u for d in dets])[:, None] - u[None, :]
    dv = np.array([d.v for d in dets])[:, None] - v[None, :]
    dr = np.array([d.r for d in dets])[:, None] / r[None, :]
    dist = np.hypot(du, dv) / (2.0 * r[None, :])
    ok = (dist <= MATCH_CENTRE_D) & (np.abs(dr - 1.0) <= MATCH_DIAMETER)
    pairs = sorted(zip(*np.nonzero(ok)), key=lambda p: dist[p])
    out: dict[int, int] = {}
    used: set[int] = set()
    for i, j in pairs:
        if i not in out and j not in used:
            out[int(i)] = int(idx[j])
            used.add(int(j))
    return out


MAX_PRIOR_OFFSET_KM = 100.0


def check_prior_offset_km(offset_km: float) -> None:
    """One error line for a ``--prior-offset-km`` (nav-eval, nav-frames-eval) outside [0, 100] km."""
    if not 0.0 <= offset_km <= MAX_PRIOR_OFFSET_KM:
        raise UserError(f"--prior-offset-km={offset_km:g}: expected 0 to {MAX_PRIOR_OFFSET_KM:g} km")


def summarise(rows: list[dict]) -> dict:
    """Metrics of a list of :func:`run_frame` rows (module docstring)."""
    out: dict = {"windows": len(rows)}
    if not rows:
        return out
    out.update(fix_metrics(rows))
    bins = {}
    edges = SIZE_BINS_KM
    for lo, hi in zip(edges[:-1], edges[1:]):
        tp_t = n_t = tp_d = n_d = 0
        for r in rows:
            dt = np.array(r["truth_d_km"])
            sel = (dt >= lo) & (dt < hi)
            n_t += int(sel.sum())
            matched_truth = set(r["matched"].values())
            tp_t += int(sum(1 for i, d in zip(r["truth"], dt) if lo <= d < hi and i in matched_truth))
            dr = 2.0 * np.array(r["det_r_km"])
            seld = (dr >= lo) & (dr < hi)
            n_d += int(seld.sum())
            tp_d += int(sum(1 for k in np.nonzero(seld)[0] if int(k) in r["matched"] or int(k) in r["matched_any"]))
        name = f"{lo:g}-{hi:g}" if hi < 1e8 else f">={lo:g}"
        bins[name] = {
            "recall": round(tp_t / n_t, 4) if n_t else None,
            "precision": round(tp_d / n_d, 4) if n_d else None,
            "n_truth": n_t,
            "n_detections": n_d,
        }
    out["by_size_km"] = bins
    # D >= 15 km pooled.
    tp_t = n_t = tp_d = n_d = 0
    for r in rows:
        dt = np.array(r["truth_d_km"])
        matched_truth = set(r["matched"].values())
        n_t += int((dt >= HEADLINE_MIN_D_KM).sum())
        tp_t += int(sum(1 for i, d in zip(r["truth"], dt) if d >= HEADLINE_MIN_D_KM and i in matched_truth))
        dr = 2.0 * np.array(r["det_r_km"])
        sel = np.nonzero(dr >= HEADLINE_MIN_D_KM)[0]
        n_d += int(sel.size)
        tp_d += int(sum(1 for k in sel if int(k) in r["matched"] or int(k) in r["matched_any"]))
    out["recall_15km"] = round(tp_t / n_t, 4) if n_t else None
    out["precision_15km"] = round(tp_d / n_d, 4) if n_d else None
    if all("catalogue_d_km" in r for r in rows):
        out["against_catalogue"] = catalogue_scores(rows)
    if all("patches_alone" in r for r in rows):
        out["fixed_by_patches"] = sum(r["fix_source"] == "patches" for r in rows)
        out["patches_alone"] = patches_alone(rows)
    return out


def fix_metrics(rows: list[dict]) -> dict:
    """Fix rate, error median and 90th percentile, false fixes and identification of rows (>= 1) with ``fix``,
    ``error_km``, ``identified`` and ``identified_correct``."""
    fixed = [r for r in rows if r["fix"]]
    err = np.array([r["error_km"] for r in fixed])
    ident = sum(r["identified"] for r in fixed)
    return {
        "fix_rate": round(len(fixed) / len(rows), 4),
        "median_error_km": round(float(np.median(err)), 3) if err.size else None,
        "p90_error_km": round(float(np.percentile(err, 90)), 3) if err.size else None,
        "false_fix_rate": round(float((err > FALSE_FIX_KM).sum()) / len(rows), 4),
        "false_fixes": int((err > FALSE_FIX_KM).sum()),
        "identification_accuracy": round(sum(r["identified_correct"] for r in fixed) / ident, 4) if ident else None,
        "identified_per_fix": round(ident / len(fixed), 2) if fixed else None,
    }


def patches_alone(rows: list[dict]) -> dict:
    """Fix metrics of the windows navigated with their terrain patches alone (:func:`with_window_patches`)."""
    out = fix_metrics([r["patches_alone"] for r in rows])
    out["patches_per_window"] = round(float(np.mean([r["patches_alone"]["n_patches"] for r in rows])), 2)
    return out


def catalogue_split(row: dict, lo_km: float = HEADLINE_MIN_D_KM, hi_km: float = 1e9) -> dict[str, list[int]]:
    """One row's split against the crater catalogue (:func:`.windows.evaluate.catalogue_fields`) for
    diameters in [``lo_km``, ``hi_km``) (default: D >= 15 km): ``found`` and ``missed``, positions in the
    row's catalogue craters in view (``catalogue_d_km``) of that size that a detection matches or none does;
    ``true`` and ``false``, indices of the detections of that size that match a map landmark (any size) or a
    catalogued crater (any size), or neither (the map's truth misses most catalogued craters, and a
    detection of a crater the catalogue lacks is no false one)."""
    dt = np.array(row["catalogue_d_km"], dtype=float)
    found = {int(k) for k in row["catalogue_found"]}
    big = np.nonzero((dt >= lo_km) & (dt < hi_km))[0]
    dd = 2.0 * np.array(row["det_r_km"], dtype=float)
    sel = np.nonzero((dd >= lo_km) & (dd < hi_km))[0]
    true = {int(k) for k in row["matched"]} | set(row["matched_any"]) | set(row["matched_catalogue"])
    return {
        "found": [int(k) for k in big if int(k) in found],
        "missed": [int(k) for k in big if int(k) not in found],
        "true": [int(k) for k in sel if int(k) in true],
        "false": [int(k) for k in sel if int(k) not in true],
    }


def _catalogue_pooled(splits: list[dict]) -> tuple[float | None, float | None, int, int]:
    tp_t = sum(len(s["found"]) for s in splits)
    n_t = tp_t + sum(len(s["missed"]) for s in splits)
    tp_d = sum(len(s["true"]) for s in splits)
    n_d = tp_d + sum(len(s["false"]) for s in splits)
    return (round(tp_t / n_t, 4) if n_t else None, round(tp_d / n_d, 4) if n_d else None, n_t, n_d)


def catalogue_scores(rows: list[dict]) -> dict:
    """Pooled over ``rows``: recall of the catalogue's craters in view and precision of the detections, by
    :func:`catalogue_split`, for D >= 15 km and by size (``CATALOGUE_BINS_KM``)."""
    recall, precision, n_t, n_d = _catalogue_pooled([catalogue_split(r) for r in rows])
    out: dict = {
        "recall_15km": recall,
        "precision_15km": precision,
        "n_catalogue_15km": n_t,
        "n_detections_15km": n_d,
    }
    bins = {}
    for lo, hi in zip(CATALOGUE_BINS_KM[:-1], CATALOGUE_BINS_KM[1:]):
        recall, precision, n_t, n_d = _catalogue_pooled([catalogue_split(r, lo, hi) for r in rows])
        name = f"{lo:g}-{hi:g}" if hi < 1e8 else f">={lo:g}"
        bins[name] = {"recall": recall, "precision": precision, "n_catalogue": n_t, "n_detections": n_d}
    out["by_size_km"] = bins
    return out


def rendered_summary(rows: list[dict]) -> dict:
    """:func:`summarise` plus the median horizontal part of the fixes' errors."""
    out = summarise(rows)
    h = [r["error_horizontal_km"] for r in rows if r["fix"]]
    if rows:
        out["median_horizontal_error_km"] = round(float(np.median(h)), 3) if h else None
    return out


def fix_counts(frames: int, errors_km) -> dict:
    """Frames, fixes, fix rate and false fixes (error > FALSE_FIX_KM) of a run whose fixes have these errors."""
    err = np.asarray(errors_km, dtype=float)
    return {
        "frames": frames,
        "fixes": int(err.size),
        "fix_rate": round(err.size / frames, 4) if frames else None,
        "false_fixes": int((err > FALSE_FIX_KM).sum()),
    }


def lost_in_space_summary(out: list[dict]) -> dict:
    """Fix rate, false fixes, horizontal error and identification accuracy of lost-in-space rows."""
    fixed = [r for r in out if r["fix"]]
    err = np.array([r["error_km"] for r in fixed])
    ident = sum(r["identified"] for r in fixed)
    return fix_counts(len(out), err) | {
        "median_horizontal_error_km": round(float(np.median(err)), 3) if err.size else None,
        "p90_horizontal_error_km": round(float(np.percentile(err, 90)), 3) if err.size else None,
        "identification_accuracy": round(sum(r["identified_correct"] for r in fixed) / ident, 4) if ident else None,
    }
