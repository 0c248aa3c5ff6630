"""A second stage for the learned detector: each candidate crater re-scored and its rim re-measured on a crop
scaled to the candidate's own radius.

The detector (:mod:`train.crater_detector`) sees about 70 px around a pixel of its level and reads the rim
radius from the same heat-map pixel. On the real windows it puts a candidate near most catalogued craters
at a low heat threshold, but many of those candidates carry a radius off by more than the 25 % a match
allows, and their heat is too weak to keep at a useful precision. The verifier looks at each candidate
alone: a ``CROP_PX`` crop spanning ``CONTEXT_R`` candidate radii each side of its centre, so every crater,
whatever its size, is seen whole with the ground around it, and so the question asked is the same at
every size. It answers whether a crater's rim lies there (a logit) and where: the centre offset and the
log ratio of the true radius to the candidate's.

Trained on rendered frames only (:mod:`crater_synth.navigation.rendered.verifier_train`): the detector's own
candidates on frames it was not trained on, each labelled by the frame's exact craters, and jittered copies
of the labelled rims. numpy + torch + OpenCV + core only.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from crater_core.settings_nav import VerifierTrainSettings
from train.crater_detector import augment_brightness, decimate2
from train.model_files import read_model_file, write_model_file

CROP_PX = 32  # the crop's side, px
CONTEXT_R = 2.0  # the crop spans this many candidate radii each side of the centre
MODEL_FORMAT = "crater-synth-verifier/1"


# ------------------------------------------------------------------------------------------------
# Crops
# ------------------------------------------------------------------------------------------------
def crops(image: np.ndarray, u, v, r, size: int = CROP_PX, context: float = CONTEXT_R) -> np.ndarray:
    """(N, size, size) float32 crops of ``image`` centred on (u, v) (pixel-edge coordinates: pixel j spans
    [j, j + 1)) spanning ``context`` x r each side. Each is sampled bilinearly from the pyramid level
    (2 x 2 area means) at which it spans between ``size`` and 2 ``size`` pixels, so no crop is sampled
    more than 2 x below that level's resolution; the border is mirrored."""
    u, v, r = (np.asarray(x, np.float64).ravel() for x in (u, v, r))
    out = np.zeros((u.size, size, size), np.float32)
    if not u.size:
        return out
    side = 2.0 * context * np.maximum(r, 1e-3)
    level = np.clip(np.floor(np.log2(side / size)), 0, None).astype(int)
    grid = (np.arange(size) + 0.5) / size - 0.5  # -0.5 .. 0.5 of the side
    a = np.asarray(image, np.float32)
    for lv in range(int(level.max()) + 1):
        if lv:
            a = decimate2(a) if min(a.shape) >= 2 else a
        pick = np.nonzero(level == lv)[0]
        if not pick.size:
            continue
        f = 2.0**lv
        # level index coordinate of a frame edge coordinate x: x / f - 0.5
        cx = (u[pick] / f)[:, None, None] + (side[pick] / f)[:, None, None] * grid[None, None, :] - 0.5
        cy = (v[pick] / f)[:, None, None] + (side[pick] / f)[:, None, None] * grid[None, :, None] - 0.5
        mx = np.broadcast_to(cx, (pick.size, size, size)).reshape(-1, size).astype(np.float32)
        my = np.broadcast_to(cy, (pick.size, size, size)).reshape(-1, size).astype(np.float32)
        got = cv2.remap(a, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
        out[pick] = got.reshape(pick.size, size, size)
    return out


def standardise_crops(x: torch.Tensor) -> torch.Tensor:
    """Each crop of (B, 1, c, c) to zero mean and unit standard deviation (a flat crop to zeros)."""
    mean = x.mean((2, 3), keepdim=True)
    std = x.std((2, 3), keepdim=True).clamp(min=1e-6)
    return (x - mean) / std


# ------------------------------------------------------------------------------------------------
# Network
# ------------------------------------------------------------------------------------------------
def _stage(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(2),
    )


class VerifierNet(nn.Module):
    """Crop (B, 1, 32, 32) -> (B, 4): crater logit, centre offset (du, dv) in candidate radii, log(r_true / r)."""

    def __init__(self, width: int = 16):
        super().__init__()
        self.width = width
        self.features = nn.Sequential(_stage(1, width), _stage(width, 2 * width), _stage(2 * width, 4 * width))
        self.head = nn.Sequential(
            nn.Flatten(), nn.Linear(4 * width * 16, 128), nn.ReLU(inplace=True), nn.Dropout(0.2), nn.Linear(128, 4)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))


# ------------------------------------------------------------------------------------------------
# Training
# ------------------------------------------------------------------------------------------------
def dihedral_batch(x: torch.Tensor, off: torch.Tensor, k: int, flip: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Crops (B, 1, c, c) turned by k quarter turns (``torch.rot90`` over the last two axes) and mirrored top
    to bottom, with their centre offsets (B, 2: du, dv) turned alike (as :func:`train.crater_detector.dihedral`)."""
    du, dv = off[:, 0], off[:, 1]
    for _ in range(k):
        x = torch.rot90(x, 1, dims=(-2, -1))
        du, dv = dv, -du
    if flip:
        x = torch.flip(x, dims=(-2,))
        dv = -dv
    return x, torch.stack([du, dv], 1)


def verifier_loss(out: torch.Tensor, label: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, dict]:
    """BCE on the crater logit (label 1 crater, 0 none, -1 neither: no loss) plus smooth-L1 on the offset
    and log radius ratio of the crater crops."""
    known = label >= 0
    cls = F.binary_cross_entropy_with_logits(out[known, 0], label[known].float()) if known.any() else out.sum() * 0
    pos = label == 1
    reg = F.smooth_l1_loss(out[pos, 1:], target[pos], beta=0.1) if pos.any() else out.sum() * 0
    return cls + reg, {"cls": round(float(cls.detach()), 4), "reg": round(float(reg.detach()), 4)}


def train_verifier(
    images: np.ndarray, tops: np.ndarray, label: np.ndarray, target: np.ndarray, s: VerifierTrainSettings, log=None
) -> dict:
    """Train :class:`VerifierNet` on crops (N, c, c; raw brightness), each crop's frame brightness scale
    ``tops`` (N), ``label`` (N: 1, 0, -1) and ``target`` (N, 3: du, dv in candidate radii, log radius ratio),
    with the detector's photometric augmentation and random quarter turns and mirrorings; a one-cycle
    learning rate over ``s.steps`` batches."""
    torch.manual_seed(s.seed)
    gen = torch.Generator().manual_seed(s.seed)
    rng = np.random.default_rng(s.seed)
    model = VerifierNet(s.width)
    opt = torch.optim.AdamW(model.parameters(), lr=s.lr, weight_decay=s.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=s.lr, total_steps=s.steps)
    x_all = torch.from_numpy(np.clip(images / tops[:, None, None], 0.0, None).astype(np.float32))
    lab_all, tgt_all = torch.from_numpy(label.astype(np.int64)), torch.from_numpy(target.astype(np.float32))
    history, t0 = [], time.perf_counter()
    model.train()
    for step in range(1, s.steps + 1):
        pick = torch.from_numpy(rng.integers(0, len(x_all), s.batch))
        x = x_all[pick][:, None]
        tgt = tgt_all[pick]
        x, off = dihedral_batch(x, tgt[:, :2], int(rng.integers(4)), bool(rng.integers(2)))
        x = augment_brightness(x, torch.ones_like(x), s, gen)
        loss, row = verifier_loss(model(x), lab_all[pick], torch.cat([off, tgt[:, 2:]], 1))
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 500 == 0 or step == s.steps:
            history.append({"step": step, "loss": round(float(loss.detach()), 4), **row})
            if log:
                log(f"step {step}/{s.steps}: loss {float(loss.detach()):.3f} cls {row['cls']} reg {row['reg']}")
    model.eval()
    return {"model": model, "history": history, "seconds": round(time.perf_counter() - t0, 1)}


# ------------------------------------------------------------------------------------------------
# Model files and inference
# ------------------------------------------------------------------------------------------------
def save_model(path: Path, model: VerifierNet, meta: dict) -> None:
    write_model_file(path, MODEL_FORMAT, model.state_dict(), meta, width=model.width)


def load_model(path: Path) -> tuple[VerifierNet, dict]:
    """The model and its meta; a missing, corrupt or foreign file raises ``DetectorModelError`` naming it."""
    return read_model_file(path, MODEL_FORMAT, lambda payload: VerifierNet(int(payload["width"])))


@torch.no_grad()
def verify(model: VerifierNet, image: np.ndarray, u, v, r, batch: int = 1024) -> tuple[np.ndarray, ...]:
    """Candidates (u, v, r) of ``image`` re-measured and scored: (u, v, r, probability of a crater)."""
    u, v, r = (np.asarray(x, np.float64).ravel() for x in (u, v, r))
    if not u.size:
        return u, v, r, np.zeros(0)
    x = torch.from_numpy(crops(image, u, v, r))[:, None]
    out = torch.cat([model(standardise_crops(x[i : i + batch])) for i in range(0, len(x), batch)]).numpy()
    p = 1.0 / (1.0 + np.exp(-out[:, 0].astype(np.float64)))
    return u + out[:, 1] * r, v + out[:, 2] * r, r * np.exp(out[:, 3]), p


def jitter(u, v, r, rng: np.random.Generator, centre_r: float = 0.35, ratio: float = 1.6) -> tuple[np.ndarray, ...]:
    """Candidate circles drawn about labelled rims (u, v, r): the centre moved up to ``centre_r`` x r in a random
    direction, the radius scaled log-uniformly within [1 / ``ratio``, ``ratio``]."""
    n = np.size(u)
    ang, dist = rng.uniform(0, 2 * math.pi, n), centre_r * np.sqrt(rng.uniform(0, 1, n))
    scale = np.exp(rng.uniform(-math.log(ratio), math.log(ratio), n))
    return u + dist * r * np.cos(ang), v + dist * r * np.sin(ang), r * scale
