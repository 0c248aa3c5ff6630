"""A tiny procedural stand-in for a rendered dataset (tests, benchmarks, demos without Blender).

Writes tiled EXRs with the renderer's channels (``crater_core.schema.EXR_CHANNELS``), each carrying its
labels in its header as the renderer writes them (``crater_core.render_labels``), and a
``manifest.jsonl`` whose rows pass ``validate_row``. The "craters" are toy height fields (a deep
bowl, a bowl with a satellite crater on its rim, a flat-floored crater with a central peak) on a
seeded rough background, Lambert-shaded for the row's sun direction and rotated by the camera
azimuth. It exercises the data path only; it says nothing about real lunar images.

:func:`write_toy_frames` renders the same three toy craters at poses and suns the dataset does not
contain, as 8-bit frames with a realset labels file: a held-out test set on which a classifier trained
on the toy dataset must beat chance clearly (tests/test_train_e2e.py states the accuracy it must reach).
"""

from __future__ import annotations

import math
import zlib
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image

from crater_core import schema
from crater_core.exr import sealed_header, write_exr
from crater_core.render_labels import header_for_row

DEFAULT_CRATERS = ("shackleton", "de_gerlache", "shoemaker")
# (sun elevation, sun azimuth, camera azimuth) of the held-out frames: none is a pose or sun of the
# default test datasets (camera azimuths 0/90/180/270, sun azimuths 0/120/240).
HELD_OUT_VIEWS = (
    (20.0, 60.0, 45.0),
    (20.0, 180.0, 135.0),
    (20.0, 300.0, 225.0),
    (25.0, 10.0, 315.0),
    (15.0, 90.0, 30.0),
    (30.0, 200.0, 200.0),
    (25.0, 330.0, 110.0),
    (18.0, 150.0, 290.0),
)
TOY_FRAME_SOURCE = "toyframes"


def _height(kind: int, x: np.ndarray, y: np.ndarray, rng_bg: np.ndarray) -> np.ndarray:
    """Toy height field in crater radii (rim at r = 1)."""
    r = np.hypot(x, y)
    rim = 0.15 * np.exp(-(((r - 1.0) / 0.12) ** 2))
    if kind == 0:  # deep simple bowl
        z = np.where(r < 1, -0.6 * (1 - r**2), 0.0) + rim
    elif kind == 1:  # bowl + satellite crater on the rim (breaks the rotational symmetry)
        z = np.where(r < 1, -0.45 * (1 - r**2), 0.0) + rim
        sx, sy = x - 0.9, y - 0.55
        rs = np.hypot(sx, sy) / 0.35
        z = z + np.where(rs < 1, -0.2 * (1 - rs**2), 0.0) + 0.05 * np.exp(-(((rs - 1) / 0.2) ** 2))
    else:  # flat floor + central peak
        z = np.where(r < 1, -0.35 * np.clip((1 - r**2) * 2.0, 0, 1), 0.0) + rim
        z = z + 0.25 * np.exp(-((r / 0.18) ** 2))
    return z + rng_bg


def render_toy(
    kind: int,
    size: int,
    rim_px: float,
    sun_elevation: float,
    sun_azimuth: float,
    cam_elevation: float,
    cam_azimuth: float,
    terrain_seed: int,
) -> dict[str, np.ndarray]:
    """All EXR channels of one toy render (I/F up to ~0.3, unclamped float)."""
    c = size / 2.0
    v, u = np.mgrid[0:size, 0:size].astype(np.float64) + 0.5
    # Image -> ground (crater radii): rotate by the camera azimuth, foreshorten by the elevation.
    du, dv = (u - c) / (rim_px / 2.0), (v - c) / (rim_px / 2.0)
    t = math.radians(cam_azimuth)
    fs = max(math.sin(math.radians(cam_elevation)), 0.3)
    gx = math.cos(t) * du - math.sin(t) * dv / fs
    gy = -(math.sin(t) * du + math.cos(t) * dv / fs)
    rng = np.random.default_rng(terrain_seed)
    # Seeded fixed roughness of this crater's terrain, sampled at the ground coordinates.
    k = rng.normal(size=(6, 4))
    bg = sum(0.02 * a * np.sin(b * 4 * gx + cc * 4 * gy + d) for a, b, cc, d in k)
    z = _height(kind, gx, gy, bg)
    dzdy, dzdx = np.gradient(z, 2.0 / rim_px)
    n = np.stack([-dzdx, -dzdy, np.ones_like(z)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    el, az = math.radians(sun_elevation), math.radians(sun_azimuth - cam_azimuth)
    s = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
    mu0 = np.clip(n @ s, 0.0, None)
    lit = (mu0 > 0).astype(np.float32)
    i_f = (0.12 * mu0 / max(math.sin(el), 0.2)).astype(np.float32)
    return {
        "IF": i_f,
        "depth": (1000.0 - 50.0 * z).astype(np.float32),
        "N.X": n[..., 0].astype(np.float32),
        "N.Y": n[..., 1].astype(np.float32),
        "N.Z": n[..., 2].astype(np.float32),
        "lit": lit,
    }


def write_toy_dataset(
    out_dir: str | Path,
    craters: Sequence[str] = DEFAULT_CRATERS,
    sun_elevations: Sequence[float] = (15.0, 30.0),
    sun_azimuths: Sequence[float] = (0.0, 120.0, 240.0),
    cam_elevations: Sequence[float] = (90.0,),
    cam_azimuths: Sequence[float] = (0.0, 90.0, 180.0, 270.0),
    rim_px: float = 48.0,
    sigmas: Sequence[float] = (1.0, 1.2, 1.4),
    seed: int = 0,
) -> list[dict]:
    """Write EXRs + ``manifest.jsonl`` into ``out_dir``; returns the rows."""
    out_dir = Path(out_dir)
    size = int(math.ceil(max(sigmas) * rim_px))
    c = size / 2.0
    half = {s: s * rim_px / 2 for s in sigmas}
    boxes = {f"{s:.1f}": [c - half[s], c - half[s], c + half[s], c + half[s]] for s in sigmas}
    rows = []
    shape = (len(sun_elevations), len(sun_azimuths), len(cam_elevations), len(cam_azimuths))
    for ci, crater in enumerate(craters):
        tseed = zlib.crc32(f"{seed}:{crater}".encode())
        for flat, idx in enumerate(np.ndindex(*shape)):
            se, sa = sun_elevations[idx[0]], sun_azimuths[idx[1]]
            ce, ca = cam_elevations[idx[2]], cam_azimuths[idx[3]]
            ch = render_toy(ci % 3, size, rim_px, se, sa, ce, ca, tseed)
            rel = f"{crater}/{flat:05d}.exr"
            row = {
                "schema_version": schema.SCHEMA_VERSION,
                "crater": crater,
                "index": flat,
                "indices": list(idx),
                "sun_elevation": float(se),
                "sun_azimuth": float(sa),
                "cam_elevation": float(ce),
                "cam_azimuth": float(ca),
                "range_m": 1000.0,
                "fov_deg": 90.0,
                "width": size,
                "height": size,
                "frame_width": size,
                "crop_origin": [0, 0],
                "center_px": [c, c],
                "rim_ellipse": {"cu": c, "cv": c, "a": rim_px / 2, "b": rim_px / 2, "angle_rad": 0.0},
                "sigma_boxes": boxes,
                "lit_fraction": float(ch["lit"].mean()),
                "mean_if": float(ch["IF"].mean()),
                "path": rel,
                "sha256": "",
                "seed": int(tseed),
                "code_version": "toydata",
                "renderer": "toydata",
                "terrain_id": f"toy-{crater}",
                "render_digest": "toydata",
            }
            # The labels go into the header as the renderer writes them, sealed with the pixels, so verify and
            # training can check them.
            row["sha256"] = write_exr(out_dir / rel, ch, sealed_header(ch, header_for_row(row)))
            rows.append(schema.validate_row(row))
    schema.write_manifest(out_dir / schema.MANIFEST_NAME, rows)
    return rows


def write_toy_frames(
    out_dir: str | Path,
    craters: Sequence[str] = DEFAULT_CRATERS,
    views: Sequence[tuple[float, float, float]] = HELD_OUT_VIEWS,
    rim_px: float = 40.0,
    size: int = 96,
    seed: int = 0,
) -> Path:
    """Held-out toy frames (8-bit PNG, nadir camera) and their realset labels file; returns the CSV path.

    Same toy craters and terrain seeds as :func:`write_toy_dataset` (same ``seed``), new views: use it as
    ``realset.labels_file`` to test a model trained on the toy dataset (``source`` = ``toyframes``)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    lines = ["image_path,crater,center_u,center_v,diameter_px,source"]
    for ci, crater in enumerate(craters):
        tseed = zlib.crc32(f"{seed}:{crater}".encode())
        for k, (sun_el, sun_az, cam_az) in enumerate(views):
            i_f = render_toy(ci % 3, size, rim_px, sun_el, sun_az, 90.0, cam_az, tseed)["IF"]
            name = f"{crater}_{k:02d}.png"
            dn = np.clip(np.round(i_f / 0.3 * 255.0), 0, 255).astype(np.uint8)  # 8-bit DN like a real frame
            Image.fromarray(dn).save(out_dir / name)
            lines.append(f"{name},{crater},{size / 2},{size / 2},{rim_px},{TOY_FRAME_SOURCE}")
    labels = out_dir / "labels.csv"
    schema.atomic_write_text(labels, "\n".join(lines) + "\n")
    return labels
