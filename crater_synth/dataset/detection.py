"""Detection frames: whole camera frames of procedural crater fields, rendered by the dataset's renderer,
labelled with every crater the field holds (``crater-synth detection-frames --out DIR --frames N``;
docs/procedural.md, "Detection frames"; the run and its folder: :mod:`.detection_run`).

Per frame i (everything drawn from the run's ``seed`` and i, so a frame is the same whatever N is; the
ranges and shares are ``detection.*``, crater_core/settings_detection.py):

1. **Terrain**: field f = i // ``views_per_field``, a crater field of ``procedural.*``
   (:func:`crater_core.procedural.generate`) seeded from the run's seed and f, at :func:`field_spacing`, as
   the worker's terrain patch (:mod:`crater_synth.terrain.procedural_patch`, curved with the Moon) centred
   on (:data:`PATCH_LAT`, :data:`PATCH_LON`).
2. **Conditions** (:func:`draw_conditions`): the Sun ``sun_elevation_deg`` high at an azimuth of the
   field's set (:func:`sun_azimuths`) or any; a nadir view (``nadir_share`` of the views) or one
   ``off_nadir_deg`` off nadir at any azimuth, shared by the frames of a view (:func:`view_rng`); a ground
   sample between the grid spacing and ``gsd_max_factor`` times it (the image is never finer than the
   terrain), lowered if need be so that the frame's footprint stays inside the field.
3. **Render**: one worker job per field through :func:`crater_synth.dataset.dispatch.run_workers`, an
   explicit camera in the patch's ENU frame, as ``nav-frames`` renders (docs/renderer.md, "Worker
   contract"); fast mode's G-buffer at one (centre) sample unless the command sets the samples.
4. **Labels** (:func:`frame_labels`): every crater of ``detectable()`` whose rim-centre point projects into
   the frame and whose projected rim spans at least :data:`MIN_RIM_SPAN_PX` pixels: the rim circle (D/2 at
   the rim's mean grid height, level with the crater's own local horizontal) projected exactly through the
   camera (:func:`crater_core.geometry.project_circles`), its lit and hidden rim fractions read from the
   frame's ``lit`` and ``depth`` channels (:mod:`crater_core.rim_fractions`); they go to the frame's label
   file, columns the row references (:mod:`crater_core.detection_labels`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np

from crater_core import exr, geometry, rim_fractions, schema
from crater_core.detection_labels import label_file_name, with_labels, write_label_file
from crater_core.procedural import ProceduralTerrain, generate
from crater_core.settings import CraterSettings, replace
from crater_core.settings_detection import DetectionSettings
from crater_synth.dataset.plan import CraterJob, camera_worker_item, code_version, hapke_dict
from crater_synth.errors import ConfigError, UserError
from crater_synth.terrain.procedural_patch import grid_centre_m, grid_to_enu, height_at, write_patch

DETECTION_LABEL_VERSION = 1
FOOTPRINT_MARGIN = 1.1  # field half-width / footprint half-extent at least this (relief, curvature)
PATCH_LAT, PATCH_LON = 0.0, 0.0  # where the field lies on the Moon (the Sun is set in its ENU frame)
MIN_RIM_SPAN_PX = 3.0  # a label's projected rim spans at least this many pixels (2a)
RIM_HEIGHT_POINTS = 64  # grid samples on the rim circle averaged for its height
# A rim point is hidden when the rendered depth there is nearer than the point by more than this: a share
# of D (the crest rises and falls about its mean height) plus two ground samples (a pixel's depth is its
# centre's, up to a ground sample away from the rim point in an oblique view).
HIDDEN_MARGIN_D = 0.05
HIDDEN_MARGIN_GSD = 2.0
HIDDEN_RIM_MAX = 0.5  # a label with more of its rim hidden is flagged ``occluded``
CHUNK_PER_WORKER = 2  # fields per worker in a chunk: few, since the next chunk is planned while one renders
# The horizon map of fast mode covers the whole patch (the job's "crater" diameter sets its extent).
FAST_MAP_MARGIN = 1.02
PATCH_DIR = ".jobs/patches"  # under --out, with the worker jobs: the chunks' terrain patches and horizon maps


# A sharded set (``detection-frames launcher=dask``): DIR/shard_NNNNN/, each an ordinary detection-frames folder
# of a contiguous range of whole fields. By default a shard holds at most this many frames, so a folder's
# manifest, its marker's file list and a training's read of it stay bounded however large the set; a task
# renders it in minutes (~6 frames/s a worker at 256 px), so a retried task loses little.
MAX_SHARD_FRAMES = 2048
SHARD_GLOB = "shard_[0-9][0-9][0-9][0-9][0-9]"
SHARDS_KIND = "detection-shards"  # the output-folder kind of a sharded set's parent folder


def shard_name(k: int) -> str:
    return f"shard_{k:05d}"


def shard_folders(out_dir: Path) -> list[Path]:
    """The shard folders of a sharded detection set, in frame order (none: not a sharded set). Each is an
    ordinary detection-frames folder: resume, verify, export and train it as one (``nav-detector-train
    DIR/shard_00000 --also DIR/shard_00001 ...``)."""
    return sorted(p for p in Path(out_dir).glob(SHARD_GLOB) if p.is_dir())


def shard_frames(det: DetectionSettings, n_frames: int, shards: int, cap: bool = True) -> int:
    """Frames a shard holds when ``n_frames`` are split in ``shards``: whole fields, at most
    :data:`MAX_SHARD_FRAMES` (whole fields too, at least one) when ``cap``."""
    v = det.views_per_field
    per = -(-n_frames // shards)  # ceil
    per = -(-per // v) * v  # up to whole fields
    return min(per, max(v, MAX_SHARD_FRAMES // v * v)) if cap else per


def frame_rel_path(index: int) -> str:
    return f"frame_{index:06d}.exr"


def frame_seeds(run_seed: int, index: int) -> tuple[int, np.random.Generator, int]:
    """(terrain seed, conditions generator, render seed) of frame ``index``: independent streams of
    ``SeedSequence([run_seed, index])``."""
    terrain_ss, cond_ss, render_ss = np.random.SeedSequence([int(run_seed), int(index)]).spawn(3)
    return (
        int(terrain_ss.generate_state(1)[0]),
        np.random.default_rng(cond_ss),
        int(render_ss.generate_state(1)[0] & 0x7FFFFFFF),
    )


# A field's set of Sun azimuths is its own stream, apart from every frame's (SeedSequence([seed, field, this])).
AZIMUTH_STREAM = 0x53554E  # "SUN"


def field_azimuths(run_seed: int, field: int, count: int) -> np.ndarray:
    """The ``count`` Sun azimuths (deg) of field ``field``'s frames: evenly spaced from one random offset,
    so that a few horizon maps still cover every direction of light."""
    offset = np.random.default_rng(np.random.SeedSequence([int(run_seed), int(field), AZIMUTH_STREAM])).uniform(0, 360)
    return (offset + 360.0 * np.arange(count) / count) % 360.0


# A field's grid spacing (detection.spacing_m a range) is drawn from its own stream too.
SPACING_STREAM = 0x535043  # "SPC"


def grouping(det: DetectionSettings) -> dict:
    """How frames share a worker's work (docs/procedural.md, "Detection frames"): frame i views field
    i // ``views_per_field`` (one patch, scene and BVH), shares its camera with the ``suns_per_view``
    consecutive frames from i - i % ``suns_per_view`` (one G-buffer), and takes its Sun azimuth from the
    field's ``azimuths_per_field`` azimuths (one horizon map each; 0: every frame draws its own). The Sun's
    elevation is always the frame's own."""
    return {k: getattr(det, k) for k in ("views_per_field", "suns_per_view", "azimuths_per_field")}


def field_of(det: DetectionSettings, index: int) -> int:
    return index // det.views_per_field


def view_first(det: DetectionSettings, index: int) -> int:
    """The first frame of frame ``index``'s view (the frame whose camera it takes)."""
    return index - index % det.suns_per_view


def view_rng(det: DetectionSettings, run_seed: int, index: int) -> np.random.Generator | None:
    """The stream the view of frame ``index`` is drawn from: None for the view's first frame (its own
    stream, after its Sun), else that first frame's stream past its two Sun draws."""
    first = view_first(det, index)
    if first == index:
        return None
    rng = frame_seeds(run_seed, first)[1]
    rng.random(2)  # the first frame's Sun elevation and azimuth (draw_conditions)
    return rng


def sun_azimuths(det: DetectionSettings, run_seed: int, field: int) -> np.ndarray | None:
    return field_azimuths(run_seed, field, det.azimuths_per_field) if det.azimuths_per_field else None


def field_spacing(det: DetectionSettings, procedural, run_seed: int, field: int) -> float:
    """Field ``field``'s grid spacing (m/px): ``procedural.spacing_m``, or drawn log-uniform in
    ``detection.spacing_m`` from the field's own stream."""
    if det.spacing_m is None:
        return float(procedural.spacing_m)
    lo, hi = det.spacing_m
    u = np.random.default_rng(np.random.SeedSequence([int(run_seed), int(field), SPACING_STREAM])).random()
    return float(lo * (hi / lo) ** u)


def footprint_extent(off_nadir_deg: float, azimuth_deg: float, fov_deg: float) -> np.ndarray:
    """(|e|, |n|) half-extents of the ground footprint (corner rays on a flat ground) per metre of range."""
    cam = geometry.look_at_camera(90.0 - off_nadir_deg, azimuth_deg, 1.0, fov_deg)
    t = math.tan(math.radians(fov_deg) / 2.0)
    corners = np.array([[sx * t, sy * t, -1.0] for sx in (-1, 1) for sy in (-1, 1)]) @ cam.rotation.T
    ground = cam.position + corners * (-cam.position[2] / corners[:, 2])[:, None]
    return np.abs(ground[:, :2]).max(axis=0)


def check_field_fits(procedural, det: DetectionSettings) -> None:
    """One error, before anything is written, when the fields of ``procedural`` cannot hold a frame's
    footprint at the grid's own ground sample in the most oblique view at its worst azimuth."""
    off = det.off_nadir_deg[1] if det.nadir_share < 1.0 else 0.0
    worst = max(float(footprint_extent(off, az, det.fov_deg).max()) for az in range(0, 360, 5))
    focal = 0.5 * det.width_px / math.tan(math.radians(det.fov_deg) / 2.0)
    need_px = 2.0 * worst * FOOTPRINT_MARGIN * focal + 1.0
    if procedural.size_px < need_px:
        raise UserError(
            f"procedural.size_px={procedural.size_px}: a {det.width_px} px frame {off:g} deg off "
            f"nadir at the grid's ground sample needs a field of at least {math.ceil(need_px)} px: raise it"
        )


def draw_conditions(
    rng: np.random.Generator,
    terrain: ProceduralTerrain,
    det: DetectionSettings,
    azimuths: np.ndarray | None = None,
    view_rng: np.random.Generator | None = None,
) -> dict:
    """Sun, view and ground sample of one frame over ``terrain`` (module docstring, step 2): the camera in
    the patch frame, looking at a target whose footprint stays inside the field. The Sun comes from
    ``rng``; its azimuth is the one of ``azimuths`` (a field's set, :func:`field_azimuths`) that the same
    uniform draw falls on, when given. The view comes from ``view_rng`` (the view's first frame's stream,
    :func:`view_rng`) when given, else from ``rng``. Ranges and shares: ``det``."""
    s, width_px, fov_deg = terrain.spacing_m, det.width_px, det.fov_deg
    sun_el = float(rng.uniform(*det.sun_elevation_deg))
    sun_az = float(rng.uniform(0.0, 360.0))
    if azimuths is not None and len(azimuths):
        sun_az = float(azimuths[min(int(sun_az / 360.0 * len(azimuths)), len(azimuths) - 1)])
    rng = rng if view_rng is None else view_rng
    off = 0.0 if rng.random() < det.nadir_share else float(rng.uniform(*det.off_nadir_deg))
    view_az = float(rng.uniform(0.0, 360.0))
    gsd = s * float(np.exp(rng.uniform(0.0, math.log(det.gsd_max_factor))))
    focal = 0.5 * width_px / math.tan(math.radians(fov_deg) / 2.0)
    extent = footprint_extent(off, view_az, fov_deg) * FOOTPRINT_MARGIN
    half = grid_centre_m(terrain)
    fit = half / float(extent.max()) / focal  # the largest ground sample whose footprint fits the field
    if fit < s:
        raise UserError(
            f"procedural field of {terrain.height.shape[0]} px at {s:g} m/px is too small for a {width_px} px "
            f"frame at its spacing {off:.1f} deg off nadir: raise procedural.size_px"
        )
    gsd = min(gsd, fit)
    range_m = gsd * focal
    slack = np.maximum(half - extent * range_m, 0.0)
    te, tn = rng.uniform(-slack, slack)
    tx, ty = te + half, tn + half
    target, _ = grid_to_enu(terrain, tx, ty, height_at(terrain, tx, ty), PATCH_LAT, PATCH_LON)
    cam = geometry.look_at_camera(90.0 - off, view_az, range_m, fov_deg, target=target)
    return {
        "camera": cam,
        "width_px": int(width_px),
        "sun_elevation_deg": sun_el,
        "sun_azimuth_deg": sun_az,
        "off_nadir_deg": off,
        "view_azimuth_deg": view_az,
        "ground_sample_m": gsd,
        "range_m": range_m,
        "target_grid_m": [float(tx), float(ty)],
        "target_enu_m": [float(v) for v in target],
    }


def _fraction(v: float):
    """A rim fraction as the row keeps it: 4 decimals, None for NaN (less than half the rim in the frame)."""
    return None if np.isnan(v) else round(float(v), 4)


def frame_labels(terrain: ProceduralTerrain, cam: geometry.CameraPose, width_px: int, lit=None, depth=None) -> list:
    """Labels of the detectable craters in view (module docstring, step 4); with the frame's ``lit`` and
    ``depth`` channels, each rim's lit fraction and hidden fraction (None where less than half the rim is
    in the frame). Every label carries ``source: "procedural"``."""
    craters = terrain.detectable()
    if not craters:
        return []
    x = np.array([c.x_m for c in craters])
    y = np.array([c.y_m for c in craters])
    radius = 0.5 * np.array([c.diameter_m for c in craters])
    theta = np.arange(RIM_HEIGHT_POINTS) * 2.0 * np.pi / RIM_HEIGHT_POINTS
    rim_x = x[:, None] + radius[:, None] * np.cos(theta)
    rim_y = y[:, None] + radius[:, None] * np.sin(theta)
    rim_z = height_at(terrain, rim_x, rim_y).mean(axis=1)
    centres, normals = grid_to_enu(terrain, x, y, rim_z, PATCH_LAT, PATCH_LON)
    uv, dist = geometry.project_points(centres, cam, width_px)
    w = width_px
    inside = (dist > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < w)
    to_cam = cam.position - centres
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    emission = np.degrees(np.arccos(np.clip(np.sum(to_cam * normals, axis=1), -1.0, 1.0)))
    gsd = dist / cam.focal_px(w)
    ks = np.nonzero(inside)[0]
    ellipses = np.stack(geometry.project_circles(centres[ks], normals[ks], radius[ks], cam, w), axis=1)
    keep = 2.0 * ellipses[:, 2] >= MIN_RIM_SPAN_PX
    ks, ellipses = ks[keep], ellipses[keep]
    lit_f = hidden = None
    if lit is not None:
        lit_f = rim_fractions.lit_rim_fractions(lit, geometry.ellipse_points(ellipses, rim_fractions.RIM_POINTS))
    if depth is not None:
        rim_uv, rim_depth = geometry.project_points(
            rim_fractions.rim_circles(centres[ks], normals[ks], radius[ks]), cam, w
        )
        margins = HIDDEN_MARGIN_D * 2.0 * radius[ks] + HIDDEN_MARGIN_GSD * gsd[ks]
        hidden = rim_fractions.hidden_rim_fractions(depth, rim_uv, rim_depth, margins)
    out = []
    for j, (k, e) in enumerate(zip(ks, ellipses)):
        c = craters[k]
        cu, cv, a = e[0], e[1], e[2]
        label = {
            "id": c.order,
            "source": "procedural",
            "ellipse": {key: round(float(v), 4) for key, v in zip(("cu", "cv", "a", "b", "angle_rad"), e)},
            "centre_px": [round(float(uv[k, 0]), 3), round(float(uv[k, 1]), 3)],
            "x_m": round(c.x_m, 3),
            "y_m": round(c.y_m, 3),
            "diameter_m": round(c.diameter_m, 3),
            "rim_diameter_m": round(c.rim_diameter_m, 3),
            "depth_m": round(c.depth_m, 3),
            "rim_height_m": round(c.rim_height_m, 3),
            "degradation": round(c.degradation, 4),
            "class": c.morph_class,
            "is_secondary": c.is_secondary,
            "visible_rim_fraction": round(c.visible_rim_fraction, 4),
            "emission_deg": round(float(emission[k]), 3),
            "rim_inside": bool(cu - a >= 0 and cv - a >= 0 and cu + a <= w and cv + a <= w),
        }
        if lit_f is not None:
            label["lit_rim_fraction"] = _fraction(lit_f[j])
        if hidden is not None:
            label["occluded_rim_fraction"] = _fraction(hidden[j])
            label["occluded"] = bool(hidden[j] > HIDDEN_RIM_MAX)  # NaN (rim mostly outside): False
        out.append(label)
    return out


def worker_item(index: int, cond: dict, seed: int, header: dict) -> dict:
    """One worker ``renders`` entry with an explicit camera (docs/renderer.md, "Worker contract")."""
    return camera_worker_item(
        index=index,
        camera=cond["camera"],
        sun=(cond["sun_elevation_deg"], cond["sun_azimuth_deg"]),
        view=(90.0 - cond["off_nadir_deg"], cond["view_azimuth_deg"]),
        range_m=cond["range_m"],
        fov_deg=cond["camera"].fov_deg,
        width_px=cond["width_px"],
        rel_path=frame_rel_path(index),
        seed=seed,
        header=header,
    )


def plan_field(settings, field: int, indices: list[int], patch_dir: Path) -> dict:
    """Field ``field``'s terrain (generated from the terrain stream of ``frame_seeds(seed, field)``, at
    :func:`field_spacing`, its patch written under ``patch_dir``) and the conditions of its frames
    ``indices`` (each from its own stream, the view and Sun azimuth shared as :func:`grouping` says):
    {"job": one worker job for them all, "frames": index -> {terrain, cond, field, terrain_seed, ...}}."""
    det = settings.detection
    terrain_seed = frame_seeds(settings.seed, field)[0]
    spacing = field_spacing(det, settings.procedural, settings.seed, field)
    psettings = replace(settings.procedural, seed=terrain_seed, spacing_m=spacing)
    try:
        terrain = generate(psettings)
    except ValueError as exc:
        raise ConfigError(f"procedural: {str(exc).splitlines()[0]}") from None
    npz = patch_dir / f"field_{field:06d}.npz"
    write_patch(terrain, PATCH_LAT, PATCH_LON, npz)
    terrain_id = schema.content_key([psettings.as_dict(), PATCH_LAT, PATCH_LON])
    half = grid_centre_m(terrain)
    map_d_km = half * FAST_MAP_MARGIN / settings.render.shadow_map_extent_factor / 1000.0
    crater = CraterSettings(name=f"detection-{field:06d}", lat=PATCH_LAT, lon=PATCH_LON, diameter_km=map_d_km)
    job = CraterJob(crater=crater, npz=npz, meta={"terrain_id": terrain_id})
    frames = {}
    azimuths = sun_azimuths(det, settings.seed, field)
    for index in indices:
        _, rng, seed = frame_seeds(settings.seed, index)
        cond = draw_conditions(rng, terrain, det, azimuths, view_rng(det, settings.seed, index))
        header = {
            "detection_frame": index,
            "terrain_id": terrain_id,
            "procedural": json.dumps(psettings.as_dict(), sort_keys=True),
            "code_version": code_version(),
            "renderer": settings.render.mode,
            "samples": int(settings.render.samples),
            "hapke": json.dumps(hapke_dict(settings.hapke), sort_keys=True),
            "seed": seed,
            "detection": json.dumps(det.as_dict(), sort_keys=True),
        }
        item = worker_item(index, cond, seed, header)
        job.plans.append({"params": SimpleNamespace(index=index, indices=(0, 0, 0, index)), "item": item})
        frames[index] = {
            "terrain": terrain,
            "cond": cond,
            "field": field,
            "terrain_seed": terrain_seed,
            "terrain_id": terrain_id,
            "view_first": view_first(det, index),
            "grouping": grouping(det),
        }
    return {"job": job, "frames": frames}


def frame_row(frame: dict, res: dict, out_dir: Path) -> dict:
    """The manifest row of one rendered frame: the worker's ``res``, the frame's terrain, Sun and camera,
    and its labels (lit and hidden rim fractions read from the frame's EXR), written to the frame's label
    file (``frame_NNNNNN.labels.npz``) before the row names it."""
    cond, terrain = frame["cond"], frame["terrain"]
    channels = exr.read_channels(out_dir / res["rel_path"], ("lit", "depth"))
    cam = cond["camera"]
    labels = frame_labels(terrain, cam, cond["width_px"], channels["lit"], channels["depth"])
    label_rel = label_file_name(res["rel_path"])
    return {
        "schema_version": schema.SCHEMA_VERSION,
        "label_version": DETECTION_LABEL_VERSION,
        "index": int(res["index"]),
        "rel_path": res["rel_path"],
        "sha256": res["sha256"],
        "mode": res["mode"],
        "render_seconds": res["seconds"],
        "terrain": {
            "field": frame["field"],
            "seed": frame["terrain_seed"],
            "terrain_id": frame["terrain_id"],
            "size_px": int(terrain.height.shape[0]),
            "spacing_m": terrain.spacing_m,
            "patch_lat": PATCH_LAT,
            "patch_lon": PATCH_LON,
            "frame": "ENU on the 1737.4 km sphere at the patch centre; grid (x, y) = (column, row) x spacing",
        },
        "camera_enu": {
            "position_m": [float(v) for v in cam.position],
            "rotation": cam.rotation.tolist(),
            "fov_deg": cam.fov_deg,
            "width_px": cond["width_px"],
        },
        "view": {k: cond[k] for k in ("off_nadir_deg", "view_azimuth_deg", "range_m", "target_grid_m")}
        | {"first_frame": frame["view_first"]},
        "sun_enu": {"elevation_deg": cond["sun_elevation_deg"], "azimuth_deg": cond["sun_azimuth_deg"]},
        "ground_sample_m": cond["ground_sample_m"],
        "grouping": frame["grouping"],
        "lit_fraction": res["lit_fraction"],
        "mean_if": res["mean_if"],
        # a reference to the labels' own file (crater_core.detection_labels): ~6 x smaller than inline JSON
        "labels": write_label_file(out_dir / label_rel, labels, label_rel),
    }


def detection_overrides(overrides) -> list[str]:
    """The command's defaults ahead of the user's overrides: ``procedural=detection`` and
    ``detection=default`` unless an option of the group is named, and fast mode's one-sample G-buffer unless
    the samples are set."""
    overrides = list(overrides)
    keys = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    first = [] if "procedural" in keys else ["procedural=detection"]
    first += [] if "detection" in keys else ["detection=default"]
    if not keys & {"render.samples", "render.gbuffer_samples"}:
        first.append("render.gbuffer_samples=1")
    return first + overrides


def scan_manifest(out_dir: Path, keep: Callable[[dict], Any] = lambda row: row) -> tuple[dict[int, tuple], bool]:
    """(frame index -> (byte offset, byte length, ``keep(row)``) of its line, compact) of the detection
    manifest in ``out_dir`` (none yet: ``({}, True)``), streamed line by line. A run appends each chunk's
    rows and compacts the file when it ends (:mod:`.detection_run`), so a hard-killed run's file is read as
    what it means: a torn last line (no newline after it: the chunk being appended) is dropped, and an
    index repeated keeps its last row. ``compact``: the file is as a finished run leaves it (indices
    strictly increasing, every line whole, none blank). Any other line that is no detection row is one
    error naming it."""
    path = Path(out_dir) / schema.MANIFEST_NAME
    if not path.is_file():
        return {}, True
    found: dict[int, tuple] = {}
    compact, last, offset = True, -1, 0
    with open(path, "rb") as fh:
        for n, line in enumerate(fh, 1):
            start, offset = offset, offset + len(line)
            if not line.strip():
                compact = False
                continue
            try:
                row = json.loads(line)
                index = int(row["index"])
                row["labels"]
            except (ValueError, TypeError, KeyError):
                if not line.endswith(b"\n"):  # the torn tail of a killed append
                    return found, False
                raise UserError(f"{path} line {n}: not a detection-frames row (another command's --out?)") from None
            compact = compact and index > last and line.endswith(b"\n")
            found[index], last = (start, len(line), keep(row)), index
    return found, compact


def read_manifest(out_dir: Path) -> tuple[dict[int, dict], bool]:
    """(frame index -> row with its labels inline, compact) of the detection manifest in ``out_dir``
    (:func:`scan_manifest`; each label file read, :func:`crater_core.detection_labels.with_labels`). A large
    set's readers stream the rows instead (:func:`scan_manifest`) and read the labels they need."""
    found, compact = scan_manifest(out_dir, keep=lambda row: with_labels(out_dir, row))
    return {i: v[2] for i, v in found.items()}, compact


def manifest_rows(out_dir: Path) -> dict[int, dict]:
    """Frame index -> row of the detection manifest in ``out_dir`` (:func:`read_manifest`)."""
    return read_manifest(out_dir)[0]
