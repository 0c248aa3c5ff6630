"""Training of the learned detector's second stage (:mod:`train.crater_verifier`) on rendered frames only
(``crater-synth nav-verifier-train``).

The examples are the crops the verifier will be asked about: the detector's own candidates, at a heat
threshold below any operating point, on a detection set's frames (procedural crater fields, exact labels)
that the detector was not trained on, plus jittered copies of the labelled rims (so the radius and centre
corrections are learned over their whole range, not only the detector's typical errors) and random
circles. Each is labelled against the frame's exact rims (:func:`candidate_targets`). The held-out fields of
the set are not read.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import click
import numpy as np

from crater_core.settings_nav import VerifierTrainSettings
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import compose_group
from crater_synth.navigation.detectors.learned import DEFAULT_MODEL, LearnedSettings
from crater_synth.navigation.detectors.learned import load_model as load_detector
from crater_synth.navigation.rendered.detector_train import (
    HOLDOUT_FIELD_SHARE,
    code_commit,
    detection_set_records,
    score_synthetic,
)
from crater_synth.navigation.rendered.training_rows import label_circles

# A candidate within POS_CENTRE_R label radii of a visible rim's centre, its radius within a factor POS_RATIO,
# is that crater (the target: its offset and radius ratio); one within the looser NEAR_* bounds of any rim
# (or matched to a hidden one) is trained as neither; the rest are not craters.
POS_CENTRE_R, POS_RATIO = 0.4, 1.8
NEAR_CENTRE_R, NEAR_RATIO = 0.7, 2.4
MIN_LABEL_R_PX = 4.0  # rims smaller than this are not jittered into examples (below the detector's band)
JITTER_PER_FRAME = 64
RANDOM_PER_FRAME = 32
NEGATIVES_PER_CRATER = 2


def candidate_targets(uc, vc, rc, u, v, r, hidden) -> tuple[np.ndarray, np.ndarray]:
    """(label, target) of candidate circles (uc, vc, rc) against a frame's rims (u, v, r, hidden): label 1
    (a crater; target du, dv in candidate radii and log(r_true / r_candidate) of the nearest qualifying rim),
    0 (none) or -1 (near a rim, or a hidden rim's: trained as neither)."""
    uc, vc, rc = (np.asarray(x, np.float64) for x in (uc, vc, rc))
    label = np.zeros(uc.size, np.int64)
    target = np.zeros((uc.size, 3), np.float32)
    if not uc.size or not np.size(u):
        return label, target
    dist = np.hypot(uc[:, None] - u[None, :], vc[:, None] - v[None, :]) / r[None, :]
    logq = np.abs(np.log(rc[:, None] / r[None, :]))
    near = (dist <= NEAR_CENTRE_R) & (logq <= math.log(NEAR_RATIO))
    pos = (dist <= POS_CENTRE_R) & (logq <= math.log(POS_RATIO))
    cost = np.where(pos, dist + logq, np.inf)
    best = np.argmin(cost, 1)
    has = np.isfinite(cost[np.arange(uc.size), best])
    label[near.any(1)] = -1
    ok = has & ~hidden[best]
    label[ok] = 1
    j = best[ok]
    target[ok] = np.stack([(u[j] - uc[ok]) / rc[ok], (v[j] - vc[ok]) / rc[ok], np.log(r[j] / rc[ok])], 1)
    return label, target


def frame_examples(image, row, detector, heat: float, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """One frame's examples: (crops, label, target) of the detector's candidates at ``heat``, jittered rims
    and random circles."""
    from train.crater_detector_inference import detect_pyramid
    from train.crater_verifier import crops, jitter

    u, v, r, _, hidden = label_circles(row, image.shape)
    cu, cv, cr, _, _ = detect_pyramid(detector, image, heat)
    big = np.nonzero((r >= MIN_LABEL_R_PX) & ~hidden & (r <= 0.5 * max(image.shape)))[0]
    pick = rng.choice(big, min(JITTER_PER_FRAME, big.size), replace=False) if big.size else big
    ju, jv, jr = jitter(u[pick], v[pick], r[pick], rng)
    h, w = image.shape
    ru, rv = rng.uniform(0, w, RANDOM_PER_FRAME), rng.uniform(0, h, RANDOM_PER_FRAME)
    rr = np.exp(rng.uniform(math.log(MIN_LABEL_R_PX), math.log(0.25 * min(h, w)), RANDOM_PER_FRAME))
    au, av, ar = (np.concatenate(x) for x in ((cu, ju, ru), (cv, jv, rv), (cr, jr, rr)))
    label, target = candidate_targets(au, av, ar, u, v, r, hidden)
    # Every crater example, and at most NEGATIVES_PER_CRATER x as many others (a dense field gives the
    # detector hundreds of weak candidates a frame); "neither" carries no loss and is not kept.
    pos, neg = np.nonzero(label == 1)[0], np.nonzero(label == 0)[0]
    neg = rng.choice(neg, min(neg.size, NEGATIVES_PER_CRATER * pos.size + RANDOM_PER_FRAME), replace=False)
    keep = np.sort(np.concatenate([pos, neg]))
    return crops(image, au[keep], av[keep], ar[keep]), label[keep], target[keep]


def build_examples(folder: Path, detector_path: Path, frames: int, heat: float, seed: int, log=None) -> dict:
    """Examples from the first ``frames`` training frames of a detection set (its held-out fields unread)."""
    from train.crater_detector import brightness_top

    detector, det_meta = load_detector(str(detector_path))
    records, _, what = detection_set_records(
        folder, HOLDOUT_FIELD_SHARE, max_frames=frames, frames_key="nav.verifier_train.frames"
    )
    rng = np.random.default_rng(seed)
    xs, tops, labels, targets = [], [], [], []
    for k, (image, row) in enumerate(records):
        x, lab, tgt = frame_examples(image, row, detector, heat, rng)
        xs.append(x)
        tops.append(np.full(len(x), brightness_top(image), np.float32))
        labels.append(lab)
        targets.append(tgt)
        if log and (k + 1) % 500 == 0:
            log(f"{k + 1}/{len(records)} frames, {sum(len(a) for a in xs)} examples")
    label = np.concatenate(labels)
    return {
        "images": np.concatenate(xs),
        "tops": np.concatenate(tops),
        "label": label,
        "target": np.concatenate(targets),
        "what": what
        | {
            "frames_dir": str(folder),
            "frames": len(records),
            "detector": str(detector_path),
            "detector_trained_on": det_meta.get("trained_on", "unknown"),
            "candidate_heat": heat,
            "examples": {
                "crater": int((label == 1).sum()),
                "none": int((label == 0).sum()),
                "neither": int((label == -1).sum()),
            },
            "code_commit": code_commit(),
        },
    }


HOLDOUT_SCORED = 256  # held-out frames scored with and without the verifier (a few minutes on 2 cores)


def train_verifier_from_set(folder: Path, out: Path, settings, log=None) -> dict:
    """Train the verifier on a detection set's examples (:func:`build_examples`), score the detector with and
    without it on the set's first ``HOLDOUT_SCORED`` held-out frames (every rim from the detector's band up,
    at the examples' heat), and save it to ``out`` with its provenance; returns the summary it carries."""
    import torch

    from train.crater_detector import BAND_LO_PX
    from train.crater_verifier import save_model, train_verifier

    if settings.threads:
        torch.set_num_threads(settings.threads)
    detector = Path(settings.detector) if settings.detector else DEFAULT_MODEL
    ex = build_examples(folder, detector, settings.frames, settings.heat, settings.seed, log)
    result = train_verifier(ex["images"], ex["tops"], ex["label"], ex["target"], settings, log)
    summary = {
        "trained_on": "procedural detection frames only (crater-synth detection-frames); no real pixel, no DEM",
        "set": ex["what"],
        "settings": settings.as_dict(),
        "history": result["history"],
        "train_seconds": result["seconds"],
    }
    # Scoring runs the detector with the verifier's file: a file beside ``out``, removed at the end, so
    # ``out`` appears only complete, with its scores.
    scratch = Path(out).with_name(Path(out).name + ".scoring")
    save_model(scratch, result["model"], summary)
    _, hold, _ = detection_set_records(folder, HOLDOUT_FIELD_SHARE, training=False)
    hold = hold[:HOLDOUT_SCORED]
    base = {"min_radius_px": 4.5, "refine": False, "model": str(detector), "threshold": settings.heat}
    scores = {}
    try:
        for name, extra in (("detector", {}), ("with_verifier", {"verifier": str(scratch)})):
            params = LearnedSettings(**base, **extra)  # type: ignore[arg-type]
            scores[name] = score_synthetic(hold, params, min_d_km=0.0, min_r_px=BAND_LO_PX)
    finally:
        scratch.unlink(missing_ok=True)
    summary["holdout"] = scores | {"note": f"the set's first {len(hold)} held-out frames, at heat {settings.heat}"}
    save_model(out, result["model"], summary)
    return summary


@click.command("nav-verifier-train")
@click.argument("frames_dir", type=click.Path(path_type=Path))
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Verifier model file.")
@OVERRIDES
@user_errors
def nav_verifier_train_command(frames_dir, out, overrides):
    """Train the learned detector's second stage on a detection set's frames; score it on held-out frames.

    FRAMES_DIR is a detection set (crater-synth detection-frames). The examples are the detector's own
    candidates on its first nav.verifier_train.frames training frames (their heat at least
    nav.verifier_train.heat), jittered labelled rims and random circles, each labelled by the frame's exact
    rims; the last 10 % of its fields are held out and scored with and without the verifier. Run the detector
    with it: `nav.detector.verifier=OUT nav.detector.verify_threshold=P` (docs/navigation/detectors.md).
    Settings are Hydra overrides of nav.verifier_train (docs/navigation/settings.md). Example:
    `crater-synth nav-verifier-train SET --out verifier.pt nav.verifier_train.steps=500`
    """
    settings = compose_group("nav/verifier_train", VerifierTrainSettings, overrides)
    if settings.detector:
        load_detector(settings.detector)  # a bad file: one line, before any frame is read
    summary = train_verifier_from_set(frames_dir, out, settings, log=lambda m: click.echo(m, err=True))
    click.echo(json.dumps(summary.get("holdout", {}), indent=1))
