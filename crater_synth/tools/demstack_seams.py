"""Seam metrics and figures of the DEM stack on a crater's near field (docs/dem_stack.md).

``python -m crater_synth.tools.demstack_seams [OVERRIDES...] [--png PREFIX]`` samples the configured
stack and the base DEM alone (no detail) on the crater's near grid, prints one JSON line of seam
metrics per crater, and with ``--png`` writes ``PREFIX_hillshade.png`` and ``PREFIX_profile.png``.
Example: ``python -m crater_synth.tools.demstack_seams crater=shackleton --png /tmp/demstack``.
"""

from __future__ import annotations

import argparse
import io
import json
import sys

import numpy as np

from crater_core.errors import ContractError
from crater_core.schema import atomic_write_bytes
from crater_synth.config import compose, craters
from crater_synth.errors import UserError
from crater_synth.terrain.grid import sphere_points
from crater_synth.terrain.patch import open_stack, terrain_settings

BAND_LIMITS = (0.01, 0.99)  # fine weight strictly between these: the blend band
PURE = 1e-3  # fine weight <= PURE: base only; >= 1 - PURE: fine layers only


def _regions(w: np.ndarray) -> dict[str, np.ndarray]:
    return {"base": w <= PURE, "band": (w > BAND_LIMITS[0]) & (w < BAND_LIMITS[1]), "fine": w >= 1.0 - PURE}


def _region_stats(h: np.ndarray, mask: np.ndarray) -> dict:
    """p99 / max of adjacent-vertex steps and second differences with all vertices inside ``mask``."""
    steps = np.concatenate(
        [np.abs(np.diff(h, axis=1))[mask[:, 1:] & mask[:, :-1]], np.abs(np.diff(h, axis=0))[mask[1:] & mask[:-1]]]
    )
    curv = np.concatenate(
        [
            np.abs(np.diff(h, 2, axis=1))[mask[:, 2:] & mask[:, 1:-1] & mask[:, :-2]],
            np.abs(np.diff(h, 2, axis=0))[mask[2:] & mask[1:-1] & mask[:-2]],
        ]
    )
    if steps.size == 0 or curv.size == 0:
        return {"vertices": int(mask.sum())}
    return {
        "vertices": int(mask.sum()),
        "step_p99_m": round(float(np.percentile(steps, 99)), 2),
        "step_max_m": round(float(steps.max()), 2),
        "second_diff_p99_m": round(float(np.percentile(curv, 99)), 2),
        "second_diff_max_m": round(float(curv.max()), 2),
    }


def seam_metrics(crater: dict, cfg) -> tuple[dict, dict]:
    """(metrics, arrays for figures) for one crater's near field under the configured stack."""
    s = terrain_settings(cfg)
    stack, _ = open_stack(s)
    lat, lon = float(crater["lat"]), float(crater["lon"])
    hw = s["near_radius_factor"] * float(crater["diameter_km"]) * 1000.0
    nv = s["near_vertices"]
    spacing = 2.0 * hw / (nv - 1)
    coords = np.linspace(-hw, hw, nv)
    ee, nn = np.meshgrid(coords, coords)
    _, plat, plon = sphere_points(ee, nn, lat, lon)
    blended = stack.sample(plat, plon, spacing_m=spacing)
    base = stack.base.sample(plat, plon, spacing_m=spacing)
    h, hb, w = blended.heights, base.heights, blended.fine_weight
    regions = _regions(w)
    band = regions["band"]
    metrics = {
        "crater": crater["name"],
        "stack": [layer["product"] for layer in stack.stack_info()],
        "near_spacing_m": round(spacing, 2),
        **{name: _region_stats(h, mask) for name, mask in regions.items()},
    }
    if band.any():
        # What the band blends: the finest-layer-weighted heights minus the base, and whether the
        # blended surface ever leaves the envelope of the two.
        fine_only = np.where(w > 0, (h - (1.0 - w) * hb) / np.where(w > 0, w, 1.0), hb)
        d = (fine_only - hb)[band]
        lo, hi = np.minimum(fine_only, hb)[band], np.maximum(fine_only, hb)[band]
        metrics["band_fine_minus_base_m"] = {
            "mean": round(float(d.mean()), 2),
            "rms": round(float(np.sqrt(np.mean(d**2))), 2),
            "max_abs": round(float(np.abs(d).max()), 1),
        }
        metrics["band_envelope_excursion_m"] = float(np.max(np.maximum(lo - h[band], h[band] - hi)))
    r = np.hypot(ee, nn)
    radius = 0.5 * float(crater["diameter_km"]) * 1000.0
    in_crater = r <= 1.1 * radius
    on_rim = np.abs(r - radius) <= 0.75 * spacing
    metrics["crater_fine_weight_min"] = round(float(w[in_crater].min()), 4)  # within 1.1 R
    metrics["crater_fine_weight_mean"] = round(float(w[in_crater].mean()), 4)
    metrics["rim_circle_fine_weight_min"] = round(float(w[on_rim].min()), 4)
    return metrics, {"h": h, "hb": hb, "w": w, "coords": coords, "spacing": spacing}


def write_figures(prefix: str, name: str, a: dict) -> list[str]:
    """Hillshades (base, stack, difference with weight contours) and a W-E profile through the centre."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LightSource

    c, sp = a["coords"] / 1e3, a["spacing"]
    ext = [c[0], c[-1], c[0], c[-1]]
    ls = LightSource(azdeg=315, altdeg=20)
    fig, ax = plt.subplots(1, 3, figsize=(21, 7))
    for axis, h, title in ((ax[0], a["hb"], "base DEM only (dem.stack=[])"), (ax[1], a["h"], "DEM stack")):
        axis.imshow(ls.hillshade(h, vert_exag=1, dx=sp, dy=sp), cmap="gray", origin="lower", extent=ext)
        axis.set_title(f"{name}: {title}")
    im = ax[2].imshow(a["h"] - a["hb"], cmap="RdBu_r", vmin=-300, vmax=300, origin="lower", extent=ext)
    fig.colorbar(im, ax=ax[2], label="stack - base (m)")
    ax[2].set_title("difference; blend band: fine weight 0.01 (red) to 0.99 (green)")
    for axis in ax:
        axis.contour(c, c, a["w"], levels=list(BAND_LIMITS), colors=["r", "g"], linewidths=0.6)
        axis.set_xlabel("east (km)")
        axis.set_ylabel("north (km)")
    fig.tight_layout()
    out = []
    for suffix, figure in (("hillshade", fig), ("profile", _profile_figure(plt, a, name))):
        buf = io.BytesIO()
        figure.savefig(buf, format="png", dpi=80)
        plt.close(figure)
        path = f"{prefix}_{suffix}.png"
        atomic_write_bytes(path, buf.getvalue())
        out.append(path)
    return out


def _profile_figure(plt, a: dict, name: str):
    i0 = len(a["coords"]) // 2
    c, sp = a["coords"] / 1e3, a["spacing"]
    fig, ax = plt.subplots(3, 1, figsize=(12, 10), sharex=True)
    ax[0].plot(c, a["hb"][i0], label="base DEM only")
    ax[0].plot(c, a["h"][i0], label="stack")
    ax[0].set_ylabel("height (m)")
    ax[0].legend()
    ax[0].set_title(f"{name}: west-east profile through the centre")
    for h, label in ((a["hb"][i0], "base"), (a["h"][i0], "stack")):
        ax[1].plot(c, np.degrees(np.arctan(np.gradient(h, sp))), label=label)
    ax[1].set_ylabel("slope (deg)")
    ax[1].legend()
    ax[2].plot(c, a["w"][i0], "k")
    ax[2].set_ylabel("fine weight")
    ax[2].set_xlabel("east (km)")
    fig.tight_layout()
    return fig


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("overrides", nargs="*")
    ap.add_argument("--png", default=None, help="write PREFIX_hillshade.png and PREFIX_profile.png")
    args = ap.parse_args(argv)
    try:
        cfg = compose(list(args.overrides))
        for crater in craters(cfg):
            metrics, arrays = seam_metrics(crater, cfg)
            if args.png:
                metrics["figures"] = write_figures(f"{args.png}_{crater['name']}", crater["name"], arrays)
            print(json.dumps(metrics))
    except (UserError, ContractError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
