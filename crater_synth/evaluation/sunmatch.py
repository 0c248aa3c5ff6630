"""``crater-synth sunmatch``: does the renderer reproduce the real images, and under which Sun?

For every selected crater, a nadir view is rendered under a dense grid of physically possible suns
(``sweep.sun_model=physical``: 36 azimuths x 10 fractions of the highest elevation the Sun reaches
there, by default). The real LROC WAC mosaic is resampled into each render's own pixel grid through the
render's ``depth`` channel (every pixel back-projected to its ground point, then to the polar
stereographic map: an exact orthorectification, no hand alignment), and the two are compared by the
overlap of their **lit areas** (the preprocessing's shadow floor, ``train.preprocess.normalize``, is the
one shadow definition for both domains):

- ``best``: the sun whose render matches the real crop best, and that overlap (lit-area IoU). A high
  value says terrain, shadows and the renderer reproduce the real image once the Sun is right;
- ``per azimuth step``: how much the lit area of a render changes when the Sun's azimuth moves by
  10-90 degrees (median IoU between renders that far apart, same elevation fraction). It is the angular
  scale on which a training sweep has to sample the Sun's azimuth (docs/fidelity.md);
- ``on the 60-degree grid``: the best overlap among the suns a 6-azimuth sweep contains;
- ``composite``: the overlap of a mosaic-like composite of 2 and 3 suns (the union of their lit areas,
  chosen greedily from the best single sun). A real crop taken under one sun gains little from a second
  one; a crop assembled from frames under different suns gains a lot.

Writes ``sunmatch.json``, ``sunmatch.md`` and ``sunmatch.png`` (real | best render, per crater) into
``--out``. It looks at real images, so it is a diagnostic: settings are still chosen only by the
validation craters' classification accuracy (docs/validation.md); test craters are listed, marked.
"""

from __future__ import annotations

import csv
import io
import json
import time
from collections import defaultdict
from pathlib import Path
from typing import Mapping, Sequence

import click
import numpy as np
from PIL import Image, ImageDraw

from crater_core import geometry
from crater_core.exr import read_channel
from crater_core.schema import atomic_write_bytes, atomic_write_text, load_manifest, row_file
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import compose, craters, load_settings, resolved
from crater_synth.dataset import build_dataset
from crater_synth.errors import ConfigError

AZIMUTH_STEPS_DEG = (10, 20, 30, 40, 60, 90)
COARSE_AZIMUTH_STEP_DEG = 60  # the demo sweeps' 6 sun azimuths
COMPOSITE_SUNS = (2, 3)  # composites of this many suns: does one real crop need several frames?


def sunmatch_overrides(names: Sequence[str], azimuths: int, fractions: int) -> list[str]:
    """The sweep of the diagnostic: nadir camera with north up (camera azimuth 180: image up is away
    from the camera), physical suns on a dense grid."""
    if azimuths < 4 or 360 % azimuths:
        raise ConfigError(f"--azimuths {azimuths}: needs a divisor of 360 that is at least 4")
    if fractions < 1:
        raise ConfigError(f"--fractions {fractions}: needs at least 1")
    return [
        f"crater=[{','.join(names)}]",
        "sweep.name=sunmatch",
        "sweep.sun_model=physical",
        f"sweep.sun_elevation.count={fractions}",
        "sweep.sun_elevation.values=null",
        f"sweep.sun_azimuth.count={azimuths}",
        "sweep.sun_azimuth.values=null",
        "sweep.cam_elevation.count=1",
        "sweep.cam_elevation.values=[90.0]",
        "sweep.cam_azimuth.count=1",
        "sweep.cam_azimuth.values=[180.0]",
    ]


def ground_latlon(row: dict, depth: np.ndarray, crater: dict) -> tuple[np.ndarray, np.ndarray]:
    """Latitude and longitude (degrees) of the ground point under every pixel of a render's crop."""
    pose = geometry.look_at_camera(row["cam_elevation"], row["cam_azimuth"], row["range_m"], row["fov_deg"])
    h, w = depth.shape
    u0, v0 = row["crop_origin"]
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    enu = geometry.back_project_pixels(np.stack([uu + u0, vv + v0], axis=-1), depth, pose, row["frame_width"])
    lat, lon, _ = geometry.mc_to_latlon(geometry.enu_to_mc(enu.reshape(-1, 3), crater["lat"], crater["lon"]))
    return np.asarray(lat).reshape(h, w), np.asarray(lon).reshape(h, w)


def real_in_render_frame(mosaic, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """The real map-projected mosaic sampled (bilinear) at the given ground points."""
    from scipy.ndimage import map_coordinates

    u, v = mosaic.latlon_to_uv(lat, lon)  # corner origin; map_coordinates indexes pixel centres
    return map_coordinates(mosaic.image.astype(np.float32), [v - 0.5, u - 0.5], order=1, mode="nearest")


def lit_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of boolean lit masks: ``a`` (n, P) against ``b`` (P,) or (n, P) row by row."""
    a = a.astype(np.float32)
    b = np.broadcast_to(b, a.shape).astype(np.float32)
    inter = (a * b).sum(-1)
    union = a.sum(-1) + b.sum(-1) - inter
    return np.where(union > 0, inter / np.maximum(union, 1.0), 1.0)


def greedy_composite(lit: np.ndarray, target: np.ndarray, first: int, suns: int) -> tuple[list[int], list[float]]:
    """A composite of ``suns`` renders that explains ``target`` (P,) best, built greedily: from render
    ``first``, each step adds the render of ``lit`` (n, P) whose lit area raises the IoU of the union
    most. Returns the chosen indices and the IoU after each step (the first is ``first``'s own)."""
    chosen, union = [first], lit[first].copy()
    ious = [float(lit_iou(union[None], target)[0])]
    for _ in range(suns - 1):
        iou = lit_iou(lit | union, target)
        nxt = int(np.argmax(iou))
        chosen.append(nxt)
        union |= lit[nxt]
        ious.append(float(iou[nxt]))
    return chosen, ious


def match_crater(rows: list[dict], dataset_dir: Path, crater: dict, mosaic, pp) -> dict:
    """Lit-area overlap of every render of one crater with its real crop (see the module docstring)."""
    from train.preprocess import normalize

    rows = sorted(rows, key=lambda r: (r["sun_azimuth"], r["sun_elevation_param"]))
    depth = read_channel(row_file(dataset_dir, rows[0]), "depth")
    valid = np.isfinite(depth) & (depth > 0)
    lat, lon = ground_latlon(rows[0], np.where(valid, depth, rows[0]["range_m"]), crater)
    real = real_in_render_frame(mosaic, lat, lon)
    real_norm = normalize(real, pp)
    real_lit = (real_norm > 0) & valid
    radiance = [read_channel(row_file(dataset_dir, r)) for r in rows]  # I/F, each EXR read once
    renders = [normalize(x, pp) for x in radiance]
    lit = np.stack([(y > 0) & valid for y in renders]).reshape(len(rows), -1)
    iou = lit_iou(lit, real_lit.ravel())
    best = int(np.argmax(iou))
    key = {(round(r["sun_azimuth"]) % 360, r["sun_elevation_param"]): i for i, r in enumerate(rows)}
    steps = {}
    for step in AZIMUTH_STEPS_DEG:
        pairs = [(i, key[(az + step) % 360, f]) for (az, f), i in key.items() if ((az + step) % 360, f) in key]
        if pairs:
            i, j = np.array(pairs).T
            steps[step] = float(np.median(lit_iou(lit[i], lit[j])))
    coarse = [i for i, r in enumerate(rows) if round(r["sun_azimuth"]) % COARSE_AZIMUTH_STEP_DEG == 0]
    chosen, composite_iou = greedy_composite(lit, real_lit.ravel(), best, max(COMPOSITE_SUNS))
    r = rows[best]
    return {
        "renders": len(rows),
        "real_lit_fraction": float(real_lit[valid].mean()),
        "best_iou": float(iou[best]),
        "best_sun": {
            "azimuth_deg": float(r["sun_azimuth"]),
            "elevation_deg": float(r["sun_elevation"]),
            "fraction_of_max": float(r["sun_elevation_param"]),
        },
        "median_iou": float(np.median(iou)),
        "best_iou_on_coarse_grid": float(iou[coarse].max()) if coarse else None,
        "iou_by_azimuth_step": steps,
        "composite": [
            {
                "suns": n,
                "iou": composite_iou[n - 1],
                "azimuths_deg": [float(rows[i]["sun_azimuth"]) for i in chosen[:n]],
                "elevations_deg": [float(rows[i]["sun_elevation"]) for i in chosen[:n]],
            }
            for n in COMPOSITE_SUNS
        ],
        "_images": (real_norm, renders[best]),
        "_frames": {
            "real": real,
            "best": radiance[best],
            "grid60": radiance[coarse[int(np.argmax(iou[coarse]))]] if coarse else None,
            "rim": rows[0]["rim_ellipse"],
        },
    }


def _sheet(results: dict, path: Path) -> None:
    """Real | best render, one row per crater, labelled."""
    tiles = []
    for name, res in results.items():
        real, best = res.pop("_images")
        pair = np.hstack([real, np.ones((real.shape[0], 4), np.float32), best])
        tiles.append((name, pair))
    width = max(t.shape[1] for _, t in tiles)
    rows = [np.pad(t, ((0, 6), (0, width - t.shape[1]))) for _, t in tiles]
    img = Image.fromarray((np.clip(np.vstack(rows), 0.0, 1.0) * 255).astype(np.uint8)).convert("RGB")
    draw = ImageDraw.Draw(img)
    y = 0
    for (name, tile), row in zip(tiles, rows):
        draw.text((4, y + 2), f"{name}: real", fill=(255, 80, 80))
        draw.text((tile.shape[1] // 2 + 6, y + 2), "best render", fill=(255, 80, 80))
        y += row.shape[0]
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    atomic_write_bytes(path, buf.getvalue())


FRAME_ROLLS_DEG = tuple(range(0, 360, 30))  # on the 30-degree lattice of the demo grid's training crops
OFF_LATTICE_DEG = 15.0


def write_frames(results: dict, out: Path, groups: Mapping[str, Sequence[str]] | None = None) -> Path:
    """Paired test frames for ``crater-synth evaluate realset.labels_file=OUT/labels.csv``: per crater
    the real crop orthorectified into the nadir render's frame (``real``), the best-matching render
    (``best``) and the best render on the 60-degree sun grid (``grid60``), each rolled by the 12
    multiples of 30 degrees and by those plus 15 degrees (``*_roll15``). Renders are saved linear (the
    99.5th percentile of the lit pixels at DN 220), which the affine-invariant normalisation undoes.
    ``groups`` (label -> craters) also writes ``labels_<label>.csv`` with only that group's craters, the
    classes of the models trained on it (``crater-synth validate``)."""
    out.mkdir(parents=True, exist_ok=True)
    lines = []
    for name, res in results.items():
        fr = res.pop("_frames")
        rim = fr.pop("rim")
        for kind, img in fr.items():
            if img is None:
                continue
            if kind != "real":
                lit = img[img > 0]
                img = img / (np.percentile(lit, 99.5) if lit.size else 1.0) * 220.0
            path = out / f"{name}_{kind}.png"
            buf = io.BytesIO()
            Image.fromarray(np.clip(np.rint(img), 0, 255).astype(np.uint8)).save(buf, format="PNG")
            atomic_write_bytes(path, buf.getvalue())
            for extra, tag in ((0.0, ""), (OFF_LATTICE_DEG, "_roll15")):
                for roll in FRAME_ROLLS_DEG:
                    lines.append([path.name, name, rim["cu"], rim["cv"], 2.0 * rim["a"], kind + tag, roll + extra])
    header = ["image_path", "crater", "center_u", "center_v", "diameter_px", "source", "rotation_deg"]
    for label, keep in [("", None)] + [(f"_{k}", set(v)) for k, v in (groups or {}).items()]:
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(header)
        writer.writerows(line for line in lines if keep is None or line[1] in keep)
        atomic_write_text(out / f"labels{label}.csv", buf.getvalue())
    return out / "labels.csv"


def table_markdown(results: dict, roles: dict) -> str:
    steps = list(AZIMUTH_STEPS_DEG)
    head = (
        "| crater | role | best sun: azimuth / elevation (fraction of max) | lit IoU at best sun | "
        f"best on the {COARSE_AZIMUTH_STEP_DEG} deg grid | median over suns | "
        + " | ".join(f"IoU {s} deg apart" for s in steps)
        + " | "
        + " | ".join(f"{n}-sun composite (sun azimuths)" for n in COMPOSITE_SUNS)
        + " |\n|"
        + "---|" * (6 + len(steps) + len(COMPOSITE_SUNS))
        + "\n"
    )
    lines = []
    for name, r in results.items():
        s = r["best_sun"]
        by = r["iou_by_azimuth_step"]
        lines.append(
            f"| {name} | {roles.get(name, '-')} | {s['azimuth_deg']:.0f} / {s['elevation_deg']:.2f} deg "
            f"({s['fraction_of_max']:.1f}) | {r['best_iou']:.2f} | {r['best_iou_on_coarse_grid']:.2f} | "
            f"{r['median_iou']:.2f} | "
            + " | ".join(f"{by[k]:.2f}" if k in by else "-" for k in steps)
            + " | "
            + " | ".join(f"{c['iou']:.2f} ({', '.join(f'{a:.0f}' for a in c['azimuths_deg'])})" for c in r["composite"])
            + " |"
        )
    return head + "\n".join(lines) + "\n"


def run_sunmatch(
    overrides: Sequence[str],
    names: Sequence[str] | None,
    azimuths: int,
    fractions: int,
    out: Path,
    frames: bool = False,
) -> dict:
    """Render the dense nadir sun grid, compare with the real crops, write the results into ``out``."""
    from train.preprocess import PreprocessConfig
    from train.realset import load_mosaic

    base = resolved(compose(list(overrides)))
    vcfg = base.get("validate") or {}
    roles = {c: "validation" for g in (vcfg.get("groups") or []) for c in g}
    roles.update({c: "test" for c in (vcfg.get("test") or [])})
    names = list(names) if names else list(roles)
    settings = load_settings(list(overrides) + sunmatch_overrides(names, azimuths, fractions))
    mosaic = load_mosaic(settings.realset)  # checksum first: a bad product stops before rendering
    for c in craters(settings):  # and a crater of the other hemisphere than the mosaic
        mosaic.check_crater(c)
    t0 = time.perf_counter()
    build_dataset(settings, progress=settings.train.progress)
    dataset_dir = Path(settings.out_dir)
    by_crater = defaultdict(list)
    for row in load_manifest(dataset_dir):
        by_crater[row["crater"]].append(row)
    pp = PreprocessConfig.from_settings(settings.train.preprocess, settings.model.input_size)
    results = {}
    for c in craters(settings):
        if not by_crater.get(c["name"]):
            raise ConfigError(f"sunmatch: no render of {c['name']} in {dataset_dir} (every sun below the horizon?)")
        results[c["name"]] = match_crater(by_crater[c["name"]], dataset_dir, c, mosaic, pp)
    out.mkdir(parents=True, exist_ok=True)
    _sheet(results, out / "sunmatch.png")
    group_craters = {f"validation{i + 1}": list(g) for i, g in enumerate(vcfg.get("groups") or [])}
    if vcfg.get("test"):
        group_craters["test"] = list(vcfg["test"])
    labels = write_frames(results, out / "frames", group_craters) if frames else None
    payload = {
        "command": "crater-synth sunmatch " + " ".join(overrides),
        "azimuths": azimuths,
        "fractions": fractions,
        "seconds": round(time.perf_counter() - t0, 1),
        "roles": roles,
        "frames_labels": None if labels is None else str(labels),
        "craters": {k: {kk: vv for kk, vv in v.items() if not kk.startswith("_")} for k, v in results.items()},
    }
    atomic_write_text(out / "sunmatch.json", json.dumps(payload, indent=1) + "\n")
    atomic_write_text(
        out / "sunmatch.md",
        "# Real WAC crops against nadir renders under a dense grid of physical suns\n\n"
        f"`{payload['command']}` ({azimuths} azimuths x {fractions} elevation fractions per crater; "
        "sunmatch.png: real | best render). Lit-area IoU; test craters are reported, never used to choose.\n\n"
        + table_markdown(results, roles),
    )
    return payload


@click.command("sunmatch")
@OVERRIDES
@click.option("--craters", "names", default="", help="comma-separated craters (default: validation + test)")
@click.option("--azimuths", default=36, show_default=True, type=int, help="sun azimuths (divisor of 360)")
@click.option("--fractions", default=10, show_default=True, type=int, help="sun elevation fractions of the maximum")
@click.option("--out", default="outputs/sunmatch", show_default=True, type=click.Path(path_type=Path))
@click.option("--frames", is_flag=True, help="also write OUT/frames/: paired real/render frames and a labels.csv")
@user_errors
def sunmatch_command(overrides, names, azimuths, fractions, out, frames):
    """Does the renderer reproduce the real images, and under which Sun? (docs/fidelity.md)

    Example: crater-synth sunmatch sweep=demo_physical --craters kocher,kuhn
    """
    res = run_sunmatch(overrides, [n for n in names.split(",") if n], azimuths, fractions, out, frames)
    for name, r in res["craters"].items():
        s = r["best_sun"]
        click.echo(
            f"{name} ({res['roles'].get(name, '-')}): lit IoU {r['best_iou']:.2f} at sun "
            f"{s['azimuth_deg']:.0f}/{s['elevation_deg']:.2f} deg; {r['best_iou_on_coarse_grid']:.2f} on the "
            f"{COARSE_AZIMUTH_STEP_DEG} deg grid"
        )
    click.echo(f"table: {out / 'sunmatch.md'}")
    if res["frames_labels"]:
        click.echo(
            f"frames: {res['frames_labels']} (evaluate with realset.labels_file=THAT realset.include_embedded=false)"
        )
