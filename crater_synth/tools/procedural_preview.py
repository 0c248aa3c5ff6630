"""``python -m crater_synth.tools.procedural_preview --out DIR [procedural.<key>=<value> ...]``: one
procedural crater field (crater_core/procedural.py, docs/procedural.md) as a look.

Writes into DIR: ``hillshade.png`` (the height grid lit from -x, 30 deg up; image rows are grid rows, y
down), ``overlay.png``
(the same with each crater's rim: green the detectable labels, red the ghosts and overprinted ones)
and ``craters.json`` (the settings, a summary and every crater placed). ``--patch-at LAT LON`` also
writes ``terrain.npz``: the grid as the Blender worker's terrain patch (docs/terrain.md's contract,
near field only), centred on (LAT, LON) and curved with the Moon as the DEM patches are.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from crater_core.procedural import ProceduralTerrain, generate
from crater_core.schema import atomic_write_bytes, atomic_write_text
from crater_core.settings_procedural import ProceduralSettings
from crater_synth.config import ConfigError, compose_group
from crater_synth.terrain.procedural_patch import write_patch

# The PNGs keep the grid's rows: row i (y = i * spacing) is image row i, so +y (north in the renderer
# patch) points down the image. The light comes from -x (the image's left), 30 deg up.
SUN_AZIMUTH_DEG = 270.0  # clockwise from +y (north)
SUN_ELEVATION_DEG = 30.0


def hillshade(height: np.ndarray, spacing_m: float) -> np.ndarray:
    """Lambertian shading in [0, 1] of ``height`` (rows along +y, columns along +x) under the preview's sun."""
    gy, gx = np.gradient(height, spacing_m)
    az, el = math.radians(SUN_AZIMUTH_DEG), math.radians(SUN_ELEVATION_DEG)
    sun = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])  # (x, y, z)
    shade = (-gx * sun[0] - gy * sun[1] + sun[2]) / np.sqrt(1.0 + gx * gx + gy * gy)
    return np.clip(shade, 0.0, 1.0)


def _png(image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise OSError("PNG encoding failed")
    return buf.tobytes()


def summary(terrain: ProceduralTerrain) -> dict:
    """Counts by class, secondaries, ghosts and detectable labels; the height range."""
    craters = terrain.craters
    return {
        "craters": len(craters),
        "by_class": dict(Counter(c.morph_class for c in craters)),
        "secondaries": sum(c.is_secondary for c in craters),
        "ghosts": sum(c.degradation >= 1.0 for c in craters),
        "detectable": len(terrain.detectable()),
        "height_range_m": [float(terrain.height.min()), float(terrain.height.max())],
    }


def write_preview(terrain: ProceduralTerrain, settings: ProceduralSettings, out: Path) -> dict:
    """The three files of the preview into ``out``; returns the summary."""
    grey = (hillshade(terrain.height, terrain.spacing_m) * 255.0).astype(np.uint8)
    atomic_write_bytes(out / "hillshade.png", _png(grey))
    overlay = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    keep = {c.order for c in terrain.detectable()}
    for c in terrain.craters:
        centre = (round(c.x_m / terrain.spacing_m), round(c.y_m / terrain.spacing_m))
        radius = max(1, round(0.5 * c.diameter_m / terrain.spacing_m))
        cv2.circle(overlay, centre, radius, (0, 200, 0) if c.order in keep else (0, 0, 200), 1, cv2.LINE_AA)
    atomic_write_bytes(out / "overlay.png", _png(overlay))
    doc = {
        "settings": settings.as_dict(),
        "summary": summary(terrain),
        "craters": [
            {k: round(v, 3) if isinstance(v, float) else v for k, v in c.as_dict().items()} for c in terrain.craters
        ],
    }
    atomic_write_text(out / "craters.json", json.dumps(doc, separators=(",", ":")) + "\n")
    return doc["summary"]


def main(argv: list[str] | None = None) -> int:
    """``python -m crater_synth.tools.procedural_preview --out DIR [procedural.<key>=<value> ...]``."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="folder to write the preview into")
    ap.add_argument("--option", default="default", help="configs/procedural/<option>.yaml")
    ap.add_argument("--patch-at", nargs=2, type=float, metavar=("LAT", "LON"), help="also write terrain.npz there")
    ap.add_argument("overrides", nargs="*", help="procedural.<key>=<value>")
    args = ap.parse_args(argv)
    try:
        settings = compose_group("procedural", ProceduralSettings, args.overrides, option=args.option)
        terrain = generate(settings)
        print(json.dumps(write_preview(terrain, settings, args.out)))
        if args.patch_at:
            write_patch(terrain, args.patch_at[0], args.patch_at[1], args.out / "terrain.npz")
        return 0
    except (ConfigError, ValueError, OSError) as exc:
        print(f"error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
