"""Training of the learned crater detector (:mod:`.learned`): its frames, labels, training and scores.

``crater-synth nav-detector-frames`` renders the survey of :mod:`.detector_frames` (south DEM only);
:func:`train_from_sources`, run by ``crater-synth nav-detector-train`` (:mod:`..train_cmd`), trains
:class:`train.crater_detector.CraterNet` (or, with ``nav.detector_train.arch=fcos``, torchvision's FCOS of
:mod:`train.fcos_detector`) on every track but the last ``HOLDOUT_TRACKS`` (a detection set: every field but
the last 10 %), scores it on those against their exact labels (:func:`score_synthetic`) and writes the model
with its provenance (docs/navigation/detectors.md).
"""

from __future__ import annotations

import functools
import json
import subprocess
from pathlib import Path

import click
import numpy as np

from crater_core import exr
from crater_core.detection_labels import with_labels
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.dataset.detection import SHARDS_KIND, scan_manifest, shard_folders
from crater_synth.dataset.detection_run import KIND as DETECTION_KIND
from crater_synth.errors import UserError
from crater_synth.navigation.detectors import fcos, registry
from crater_synth.navigation.detectors.classical import detect
from crater_synth.navigation.detectors.learned import LearnedSettings
from crater_synth.navigation.rendered.evaluate import match_pixels
from crater_synth.navigation.rendered.labels import frame_rows
from crater_synth.navigation.rendered.sunlight import rendered_light
from crater_synth.navigation.rendered.survey import render_survey, track_dirs
from crater_synth.navigation.rendered.training_rows import (
    ChainedSamples,
    StreamedFrames,
    label_circles,
    labels_in_frame,
    off_nadir_deg,
    record_frame,
    slim_row,
    streamed_row,
    training_levels,
)
from crater_synth.outfolder import MARKERS, marker_kind
from crater_synth.paths import SOURCE_ROOT

DEFAULT_FRAMES = Path("data") / "detector_frames" / "south"
HOLDOUT_TRACKS = 10  # the survey's last tracks: synthetic hold-out, never trained on
HOLDOUT_FIELD_SHARE = 0.1  # a detection set's last fields: synthetic hold-out, never trained on


# ------------------------------------------------------------------------------------------------
# Training data and synthetic scoring
# ------------------------------------------------------------------------------------------------
def frame_records(root: Path, tracks: slice) -> list[tuple[np.ndarray, dict]]:
    """(I/F image, manifest row) of every frame of the survey tracks ``tracks`` under ``root``."""
    dirs = track_dirs(root)
    if not dirs:
        raise UserError(f"{root}: no rendered survey track (run `crater-synth nav-detector-frames --out {root}`)")
    out = []
    for d in dirs[tracks]:
        for row in frame_rows(d):
            out.append((exr.read_channel(d / row["rel_path"], "IF"), row))
    return out


def detection_set_records(
    folder: Path,
    holdout_share: float,
    max_frames: int = 0,
    max_off_nadir: float = 90.0,
    training: bool = True,
    frames_key: str = "nav.detector_train.frames",
    stream: bool = False,
) -> tuple[list, list, dict]:
    """(training records, held-out records, what they are) of a detection set (or a sharded one: its shard
    folders together): (I/F image, row) of every frame, the frames of the last ``holdout_share`` of its
    fields held out (a field's frames share craters). Each manifest is streamed twice (fields, then rows):
    held-out rows keep their labels for scoring, training rows their circles only (:func:`slim_row`), so a
    large set's labels need not fit in memory. ``max_frames`` > 0: only the first that many training frames
    (by shard, then frame index), the hold-out unchanged, so models trained on parts of one set are scored
    on the same fields. ``max_off_nadir`` < 90: only training frames viewed at most that many degrees off
    nadir (before ``max_frames`` counts them), the hold-out unchanged. ``training=False``: the held-out
    frames only (scoring a model: a large set's training images need not be read). ``frames_key``: the
    setting that asked for ``max_frames``, named when the set has fewer. ``stream``: no image is read and no
    label kept; each record is (None, :func:`streamed_row`), read when used (:class:`StreamedFrames`,
    :func:`record_frame`)."""
    folders = shard_folders(folder) if marker_kind(folder) == SHARDS_KIND else [folder]
    fields_in = [
        {f for _, _, f in scan_manifest(d, keep=lambda row: row["terrain"]["field"])[0].values()} for d in folders
    ]
    fields = sorted(set().union(*fields_in))
    if not fields:
        raise UserError(f"{folder}: no detection frame (run `crater-synth detection-frames --out {folder}`)")
    n_hold = max(1, int(round(holdout_share * len(fields)))) if len(fields) > 1 else 0
    held = set(fields[len(fields) - n_hold :])
    train, hold = [], []
    for d in folders:
        found, _ = scan_manifest(d, keep=functools.partial(_set_row, d, held, training, stream))
        for i in sorted(found):
            row = found[i][2]
            if row is None:
                continue
            is_held = row["terrain"]["field"] in held
            if not is_held and (0 < max_frames <= len(train) or off_nadir_deg(row) > max_off_nadir):
                continue
            image = None if stream else exr.read_channel(d / row["rel_path"], "IF")
            (hold if is_held else train).append((image, row))
    within = f" within {max_off_nadir:g} degrees of nadir" if max_off_nadir < 90.0 else ""
    if training and len(train) < max(max_frames, 1):
        asked = f"{frames_key}={max_frames}" if max_frames else "training needs frames"
        raise UserError(
            f"{folder}: {asked}, but the set has {len(train)} training frames{within} outside its held-out fields"
        )
    train_fields = len({row["terrain"]["field"] for _, row in train})
    what = {"train_fields": train_fields, "holdout_fields": sorted(held), "recipe": _recipe(folders[0])}
    limits = ({"frames_limit": max_frames} if max_frames else {}) | (
        {"max_off_nadir_deg": max_off_nadir} if max_off_nadir < 90.0 else {}
    )
    return train, hold, what | limits


def _set_row(folder: Path, held: set, training: bool, stream: bool, row: dict) -> dict | None:
    """What :func:`detection_set_records` keeps of a row: a held-out one with its labels, a training one
    slimmed (None when not training); streamed, either one's :func:`streamed_row`."""
    is_held = row["terrain"]["field"] in held
    if not (is_held or training):
        return None
    if stream:
        return streamed_row(row, folder)
    return with_labels(folder, row) if is_held else slim_row(row, folder)


def _recipe(folder: Path) -> str | None:
    try:
        return json.loads((folder / MARKERS[DETECTION_KIND]).read_text(encoding="utf-8")).get("subject")
    except (OSError, ValueError):
        return None


def detect_in_frame(image, row: dict, params) -> list:
    """The detector's craters in a rendered frame as it is, under the renderer's light
    (:func:`.sunlight.rendered_light`: a sun-aligned model turns the frame to it), the way
    :func:`frame_matches` finds them unless told otherwise."""
    return detect(image, params, light_dir=rendered_light(row), what=row["rel_path"])[0]


def frame_matches(
    image,
    row: dict,
    params,
    min_d_km: float = 15.0,
    min_r_px: float = 0.0,
    skip_hidden: bool = False,
    find=detect_in_frame,
):
    """(the frame's labels, which of them count, which of those were found, detections matched, detections)
    of one rendered frame against its exact labels (the rendered frames' matching,
    :func:`crater_synth.navigation.rendered.evaluate.match_pixels`): labels and detections of D >=
    ``min_d_km`` and a rim radius >= ``min_r_px`` count. ``skip_hidden``: a label that training treats as
    neither (:func:`label_circles`), and a detection matched to one, count nowhere.
    ``find(image, row, params)``: the detections (default :func:`detect_in_frame`; on the ground for oblique
    frames: :func:`crater_synth.tools.detector_holdout.finder`)."""
    labels = labels_in_frame(row, image.shape)
    km_per_px = float(row["ground_sample_m"]) / 1000.0
    dets = find(image, row, params)
    matched = match_pixels(dets, labels)  # detection index -> label index
    r_min = max(min_r_px, 0.5 * min_d_km / km_per_px)
    hidden = label_circles({"labels": labels}, image.shape)[4] if skip_hidden else np.zeros(len(labels), bool)
    big_t = np.array([lb["ellipse"]["a"] >= r_min and not hide for lb, hide in zip(labels, hidden)], bool)
    big_d = [d.r >= r_min and not (i in matched and hidden[matched[i]]) for i, d in enumerate(dets)]
    found = np.zeros(len(labels), bool)
    found[list(matched.values())] = True
    return labels, big_t, found & big_t, sum(1 for i in matched if big_d[i]), sum(big_d)


def frame_counts(image, row: dict, params, min_d_km: float = 15.0, min_r_px: float = 0.0, skip_hidden: bool = False):
    """(labels found, labels, detections matched, detections) of one rendered frame: :func:`frame_matches`
    counted."""
    _, counted, found, tp, n_det = frame_matches(image, row, params, min_d_km, min_r_px, skip_hidden)
    return int(found.sum()), int(counted.sum()), tp, n_det


def score_synthetic(records, params, min_d_km: float = 15.0, min_r_px: float = 0.0) -> dict:
    """Detection recall and precision over ``records`` (:func:`frame_counts`, every label counted)."""
    counts = [frame_counts(*record_frame(rec), params, min_d_km, min_r_px) for rec in records]
    tp_t, n_t, tp_d, n_d = np.sum(counts, 0)
    return {
        "frames": len(records),
        "recall": round(tp_t / n_t, 4) if n_t else None,
        "precision": round(tp_d / n_d, 4) if n_d else None,
        "n_labels": int(n_t),
        "n_detections": int(n_d),
        "min_diameter_km": min_d_km,
        "min_radius_px": min_r_px,
    }


def code_commit() -> str:
    """The source tree's git commit, with ``-dirty`` when tracked files differ from it ("unknown" outside a
    checkout): a model's provenance. A model trained from uncommitted code must not claim a commit."""
    try:
        return subprocess.run(
            ["git", "-C", str(SOURCE_ROOT), "describe", "--always", "--dirty", "--abbrev=40", "--match=-"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def survey_source(frames_dir: Path, holdout: int = HOLDOUT_TRACKS) -> tuple[list, list, dict, dict]:
    """(training records, held-out records, what they are, scoring) of a survey: every track but the last
    ``holdout`` trained on, those scored at D >= 15 km."""
    dirs = track_dirs(frames_dir)
    if len(dirs) <= holdout:
        raise UserError(f"{frames_dir}: {len(dirs)} rendered tracks, need more than the {holdout} held out")
    what = {
        "kind": "survey",
        "trained_on": "rendered survey frames only (crater-synth nav-detector-frames); no real pixel",
        "frames_dir": str(frames_dir),
        "train_tracks": [d.name for d in dirs[: len(dirs) - holdout]],
        "holdout_tracks": [d.name for d in dirs[len(dirs) - holdout :]],
    }
    train_records = frame_records(frames_dir, slice(0, len(dirs) - holdout))
    holdout_records = frame_records(frames_dir, slice(len(dirs) - holdout, None))
    return train_records, holdout_records, what, {}


def detection_source(
    folder: Path,
    holdout_share: float = HOLDOUT_FIELD_SHARE,
    max_frames: int = 0,
    max_off_nadir: float = 90.0,
    stream: bool = False,
) -> tuple[list, list, dict, dict]:
    """(training records, held-out records, what they are, scoring) of a detection set (procedural crater
    fields only): the last ``holdout_share`` of its fields held out and scored over every rim of the
    network's band and up (a 38 km field holds few craters of D >= 15 km); ``max_frames`` and
    ``max_off_nadir`` and ``stream``: as :func:`detection_set_records`."""
    from train.crater_detector import BAND_LO_PX

    train_records, holdout_records, what = detection_set_records(
        folder, holdout_share, max_frames, max_off_nadir, stream=stream
    )
    what = {
        "kind": "procedural",
        "trained_on": "procedural detection frames only (crater-synth detection-frames); no real pixel, no DEM",
        "frames_dir": str(folder),
    } | what
    return train_records, holdout_records, what, {"min_d_km": 0.0, "min_r_px": BAND_LO_PX}


SOURCE_NAMES = {
    "survey": "rendered survey frames",
    "procedural": "procedural detection frames",
    "real": "real mosaic windows",
}


def frames_source(
    frames_dir: Path, max_frames: int = 0, max_off_nadir: float = 90.0, stream: bool = False
) -> tuple[list, list, dict, dict]:
    """:func:`detection_source` or :func:`survey_source`, by the folder's marker; ``max_frames``
    (``nav.detector_train.frames``) and ``stream`` (``nav.detector_train.stream``) apply to a detection set
    only, ``max_off_nadir`` (``nav.detector_train.max_off_nadir_deg``) keeps every survey frame (nadir)."""
    if marker_kind(frames_dir) in (DETECTION_KIND, SHARDS_KIND):
        return detection_source(frames_dir, max_frames=max_frames, max_off_nadir=max_off_nadir, stream=stream)
    if max_frames:
        raise UserError(f"{frames_dir}: nav.detector_train.frames applies to detection sets, not to survey frames")
    return survey_source(frames_dir)


def train_from_survey(
    frames_dir: Path, out: Path, settings, holdout: int = HOLDOUT_TRACKS, log=None, device: str = "cpu"
) -> dict:
    """Train the detector on the survey's tracks but the last ``holdout``, score it on those, and save it
    to ``out`` with its provenance; returns the summary written into the model."""
    return train_from_sources([survey_source(frames_dir, holdout)], out, settings, log, device)


def train_from_detection(
    folder: Path, out: Path, settings, holdout_share: float = HOLDOUT_FIELD_SHARE, log=None, device: str = "cpu"
) -> dict:
    """Train the detector on a detection set's frames (procedural crater fields only), holding out the last
    ``holdout_share`` of its fields, score it on those, and save it to ``out`` with its provenance."""
    return train_from_sources([detection_source(folder, holdout_share)], out, settings, log, device)


def architecture(arch: str):
    """(train, save, scoring settings of a model file) of ``arch`` (``nav.detector_train.arch``): the
    CenterNet of :mod:`train.crater_detector` scored as the learned detector, or torchvision's FCOS of
    :mod:`train.fcos_detector` scored as the fcos detector; both scored alike (:func:`score_synthetic`, from
    4.5 px radii, no rim fit)."""
    if arch == "fcos":
        from train.fcos_detector import save_model, train_fcos

        return train_fcos, save_model, lambda path: fcos.FcosSettings(**_SCORING, model=path)
    from train.crater_detector import save_model, train_detector

    return train_detector, save_model, lambda path: LearnedSettings(**_SCORING, model=path)


_SCORING = {"min_radius_px": 4.5, "refine": False}  # the synthetic hold-out's detector settings


def train_from_sources(sources: list, out: Path, settings, log=None, device: str = "cpu") -> dict:
    """Train on the training records of every source (``*_source``'s tuples; their draw shares are
    ``settings.source_shares``), score the model on each source's held-out records, and save it to ``out``
    with its provenance; returns the summary written into the model. One source: its description and
    score at the top level; several: a list of them under ``sources``."""
    from train.crater_detector import settings_dict

    commit = code_commit()  # the code the training runs: the tree may change during a long run
    train, save_model, scoring_params = architecture(settings.arch)
    parts, source = [], []
    for k, (train_records, _, _, _) in enumerate(sources):
        levels: list | StreamedFrames
        if any(image is None for image, _ in train_records):  # streamed (detection_set_records(stream=True))
            levels = StreamedFrames([row for _, row in train_records], settings.sun_aligned)
        else:
            levels = []
            for image, row in train_records:
                levels.extend(training_levels(image, row, label_circles(row, image.shape), settings.sun_aligned))
        parts.append(levels)
        source.extend([k] * len(levels))
    samples = [x for p in parts for x in p] if all(isinstance(p, list) for p in parts) else ChainedSamples(parts)
    result = train(samples, settings, log=log, device=device, source=np.asarray(source, int))
    run = {
        "train_frames": sum(len(s[0]) for s in sources),
        "level_samples": len(samples),
        "settings": settings_dict(settings),
        "seconds": round(result["seconds"], 1),
        "device": device,
        "history": result["history"],
        "code_commit": commit,
    }
    if "init" in result:
        run["init"] = result["init"]
    if len(sources) == 1:
        meta = sources[0][2] | run
    else:
        kinds = [s[2]["kind"] for s in sources]
        meta = {
            "trained_on": " + ".join(SOURCE_NAMES[k] for k in kinds)
            + ("; real pixels (a reference)" if "real" in kinds else "; no real pixel"),
            "sources": [s[2] | {"train_frames": len(s[0])} for s in sources],
        } | run
    if settings.init:
        meta["trained_on"] += "; fine-tuned from a model trained on " + run["init"]["trained_on"]
    tmp = Path(str(out) + ".scoring.pt")
    save_model(tmp, result["model"], meta)
    params = scoring_params(str(tmp))
    try:
        scores = [score_synthetic(s[1], params, **s[3]) for s in sources]
    finally:
        tmp.unlink(missing_ok=True)
        registry.detector(params.method).load_model.cache_clear()  # the scoring file is gone
    if len(sources) == 1:
        meta["holdout"] = scores[0]
    else:
        for entry, score in zip(meta["sources"], scores):
            entry["holdout"] = score
    model = result["model"]
    final = {k: v.clone() for k, v in model.state_dict().items()}
    for step, state in sorted(result["checkpoints"].items()):
        model.load_state_dict(state)
        save_model(Path(out).with_name(f"{Path(out).stem}.step{step}.pt"), model, dict(meta, steps_done=step))
    model.load_state_dict(final)
    save_model(Path(out), result["model"], meta)
    return {k: v for k, v in meta.items() if k != "history"}


# ------------------------------------------------------------------------------------------------
# Commands
# ------------------------------------------------------------------------------------------------
@click.command("nav-detector-frames")
@OVERRIDES
@click.option(
    "--tracks", default=70, show_default=True, help="Survey tracks (4 frames each); the last 10 are held out."
)
@click.option("--seed", default=0, show_default=True, help="Seed of the track draw.")
@click.option("--out", type=click.Path(path_type=Path), default=None, help=f"Directory (default: {DEFAULT_FRAMES}).")
@user_errors
def nav_detector_frames_command(overrides, tracks, seed, out):
    """Render the learned detector's training frames: nadir survey tracks over the south map.

    Resumable (a finished track is skipped). Example: `crater-synth nav-detector-frames render.samples=4`
    """
    summary = render_survey(out or DEFAULT_FRAMES, tracks, seed, tuple(overrides))
    click.echo(json.dumps(summary))
