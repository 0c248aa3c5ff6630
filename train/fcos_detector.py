"""A standard detector for comparison with :mod:`train.crater_detector`: torchvision's FCOS (Tian et al. 2019,
"FCOS: Fully Convolutional One-Stage Object Detection"), trained from scratch on the same rendered frames.

Everything but the backbone is torchvision's: the FPN (P3-P5 from the backbone, P6-P7 by
``LastLevelP6P7``), the FCOS head, its focal, GIoU and centre-ness losses, its target assignment and its
post-processing (NMS: :mod:`train.tv_ops`). The backbone is a ResNet of torchvision's ``BasicBlock`` with
one block per stage and stage widths ``width`` x (1, 2, 4, 8) instead of ResNet-18's 64 x (1, 2, 4, 8), so
that a model file stays small (no ImageNet weights: a grey rendered frame is nothing like a photograph,
and nothing is downloaded). A crater (u, v, r px) is the box (u - r, v - r, u + r, v + r); a box (x1,
y1, x2, y2) is read back as its centre and r = the mean half side.

Input: one grey channel standardised per image (zero mean, unit deviation), as the CenterNet's, so the
model's own normalisation is the identity, and no image is resized (the pyramid level a frame is
searched at sets the scale, as for the CenterNet). Training reuses the CenterNet's level samples, its
photometric augmentation (:func:`train.crater_detector.augment_brightness`) and its 8 dihedral transforms.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from crater_core.settings_nav import DetectorTrainSettings
from train.crater_detector import LevelSample, augment_brightness, decimate2, standardise
from train.detector_fit import fit
from train.model_files import read_model_file, write_model_file
from train.tv_ops import import_torchvision

MODEL_FORMAT = "crater-synth-fcos-detector/1"
MIN_TARGET_R_PX = 3.0  # a smaller rim (at its level) is no target: its box holds at most one P3 location
DETECTIONS_PER_IMAGE = 400  # torchvision's default 100 is fewer than a 1024 px window's craters
FPN_CHANNELS_PER_WIDTH = 4  # FPN and head channels = 4 x width (FCOS's GroupNorm needs a multiple of 16)


def _stage(tv, cin: int, cout: int) -> nn.Sequential:
    """One ResNet stage: a stride-2 ``BasicBlock`` with its 1 x 1 projection shortcut."""
    down = nn.Sequential(tv.models.resnet.conv1x1(cin, cout, 2), nn.BatchNorm2d(cout))
    return nn.Sequential(tv.models.resnet.BasicBlock(cin, cout, stride=2, downsample=down))


def build_fcos(width: int = 16) -> nn.Module:
    """torchvision's FCOS, 2 classes (background, crater), on a from-scratch ResNet of one ``BasicBlock``
    per stage (widths ``width`` x 1, 2, 4, 8; strides 4 ... 32), its own image transform leaving images
    unresized and unnormalised (they come standardised)."""
    tv = import_torchvision()
    from torchvision.models.detection import FCOS
    from torchvision.models.detection.backbone_utils import BackboneWithFPN
    from torchvision.models.detection.transform import GeneralizedRCNNTransform
    from torchvision.ops.feature_pyramid_network import LastLevelP6P7

    class KeepSize(GeneralizedRCNNTransform):
        """No resize: a frame is searched at the pyramid level its crater sizes ask for (the min_size and
        max_size of torchvision's transform would scale every frame to 800 px)."""

        def resize(self, image, target=None):
            return image, target

    w = width
    body = nn.Sequential()
    body.add_module("stem", nn.Sequential(nn.Conv2d(1, w, 3, 2, 1, bias=False), nn.BatchNorm2d(w), nn.ReLU(True)))
    body.add_module("layer1", _stage(tv, w, w))  # stride 4
    body.add_module("layer2", _stage(tv, w, 2 * w))  # 8: P3
    body.add_module("layer3", _stage(tv, 2 * w, 4 * w))  # 16: P4
    body.add_module("layer4", _stage(tv, 4 * w, 8 * w))  # 32: P5
    c = FPN_CHANNELS_PER_WIDTH * w
    backbone = BackboneWithFPN(
        body,
        {"layer2": "p3", "layer3": "p4", "layer4": "p5"},
        [2 * w, 4 * w, 8 * w],
        c,
        extra_blocks=LastLevelP6P7(c, c),
    )
    model = FCOS(backbone, num_classes=2, image_mean=[0.0], image_std=[1.0], detections_per_img=DETECTIONS_PER_IMAGE)
    model.transform = KeepSize(0, 0, [0.0], [1.0])
    return model


def weight_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


# ------------------------------------------------------------------------------------------------
# Training
# ------------------------------------------------------------------------------------------------
def _prepared(sample: LevelSample, crop_px: int) -> tuple[torch.Tensor, np.ndarray]:
    """(2, H, W) brightness scaled to its 99.5th percentile and the valid-pixel mask, zero-padded to at
    least ``crop_px`` a side; and the sample's target circles (n, 3): u, v, r. Hidden craters are left
    out: torchvision's FCOS has no ignore regions, so their discs are background like any unlabelled
    pixel (a hidden rim is in shadow all round or occluded, so the image shows no rim there either)."""
    a = np.clip(np.asarray(sample.image, np.float32), 0.0, None)
    top = float(np.percentile(a, 99.5)) or 1.0
    h, w = a.shape
    out = np.zeros((2, max(h, crop_px), max(w, crop_px)), np.float32)
    out[0, :h, :w] = a / top
    out[1, :h, :w] = 1.0
    keep = ~np.asarray(sample.hidden, bool) & (np.asarray(sample.r) >= MIN_TARGET_R_PX)
    circles = np.stack([np.asarray(x, np.float64)[keep] for x in (sample.u, sample.v, sample.r)], axis=1)
    return torch.from_numpy(out), circles.reshape(-1, 3)


def dihedral_circles(uvr: np.ndarray, size: int, k: int, flip: bool) -> np.ndarray:
    """Circle centres of a ``size`` square crop moved as :func:`train.crater_detector.dihedral` moves its
    pixels: k quarter turns ((u, v) -> (v, size - u) each), then a top-bottom mirror ((u, v) -> (u, size - v))."""
    u, v, r = uvr[:, 0].copy(), uvr[:, 1].copy(), uvr[:, 2]
    for _ in range(k):
        u, v = v, size - u
    if flip:
        v = size - v
    return np.stack([u, v, r], axis=1)


def circle_boxes(uvr: np.ndarray) -> torch.Tensor:
    """(n, 4) float32 boxes (u - r, v - r, u + r, v + r)."""
    u, v, r = uvr[:, 0], uvr[:, 1], uvr[:, 2]
    return torch.from_numpy(np.stack([u - r, v - r, u + r, v + r], axis=1).astype(np.float32)).reshape(-1, 4)


def _batch(prepared, s: DetectorTrainSettings, rng: np.random.Generator, p) -> tuple[torch.Tensor, list[dict]]:
    """A batch of random ``crop_px`` crops (B, 2, c, c: brightness, valid mask), each turned and mirrored
    at random, with their targets: the circles whose centre lies in the crop (a rim cut by the crop edge
    keeps its whole box)."""
    c = s.crop_px
    stacks, targets = [], []
    picks = rng.integers(0, len(prepared), s.batch) if p is None else rng.choice(len(prepared), s.batch, p=p)
    for i in picks:
        img, uvr = prepared[int(i)]
        h, w = img.shape[-2:]
        i0, j0 = int(rng.integers(0, h - c + 1)), int(rng.integers(0, w - c + 1))
        k, flip = int(rng.integers(4)), bool(rng.integers(2))
        crop = torch.rot90(img[:, i0 : i0 + c, j0 : j0 + c], k, dims=(-2, -1))
        stacks.append(torch.flip(crop, dims=(-2,)) if flip else crop)
        local = uvr - np.array([j0, i0, 0.0])
        inside = (local[:, 0] >= 0) & (local[:, 0] < c) & (local[:, 1] >= 0) & (local[:, 1] < c)
        boxes = circle_boxes(dihedral_circles(local[inside], c, k, flip))
        targets.append({"boxes": boxes, "labels": torch.ones(len(boxes), dtype=torch.int64)})
    return torch.stack(stacks), targets


def train_fcos(
    samples: list[LevelSample], settings: DetectorTrainSettings, log=None, device: str = "cpu", source=None
) -> dict:
    """Train :func:`build_fcos` on level samples with the detectors' loop (:func:`train.detector_fit.fit`:
    torchvision's references/detection shape, the model's loss dict summed); returns what ``fit`` does."""
    prepared = [_prepared(x, settings.crop_px) for x in samples]

    def step_loss(model, rng, p, gen):
        t, targets = _batch(prepared, settings, rng, p)
        t = t.to(device)
        x = augment_brightness(t[:, :1], t[:, 1:], settings, gen)
        parts = model(list(x), [{k: v.to(device) for k, v in tg.items()} for tg in targets])
        return sum(parts.values()), {k: float(v.detach()) for k, v in parts.items()}

    return fit(lambda: build_fcos(settings.width), samples, settings, step_loss, log, device, source)


# ------------------------------------------------------------------------------------------------
# Model files and inference
# ------------------------------------------------------------------------------------------------
def _width(model: nn.Module) -> int:
    return int(model.backbone.body.stem[0].out_channels)


def save_model(path, model: nn.Module, meta: dict) -> None:
    """Write the weights and ``meta`` atomically, with a sha256 of the weights (format ``MODEL_FORMAT``)."""
    write_model_file(path, MODEL_FORMAT, model.state_dict(), meta, width=_width(model))


def load_model(path) -> tuple[nn.Module, dict]:
    """The model and its meta from a :func:`save_model` file; a missing, corrupt or foreign file raises
    :class:`train.model_files.DetectorModelError` naming it."""
    return read_model_file(path, MODEL_FORMAT, lambda payload: build_fcos(int(payload["width"])))


@torch.no_grad()
def detect_fcos(model: nn.Module, image: np.ndarray, threshold: float, level: int = 0):
    """Craters in ``image`` searched at its pyramid level ``level`` (decimated 2**level times):
    (u, v, r, score) in frame pixels, score >= ``threshold``."""
    a = np.asarray(image, np.float32)
    for _ in range(level):
        a = decimate2(a)
    model.score_thresh = float(threshold)
    out = model([torch.from_numpy(standardise(a))[None]])[0]
    b = out["boxes"].double().numpy() * 2.0**level
    s = out["scores"].double().numpy()
    u, v = 0.5 * (b[:, 0] + b[:, 2]), 0.5 * (b[:, 1] + b[:, 3])
    r = 0.25 * ((b[:, 2] - b[:, 0]) + (b[:, 3] - b[:, 1]))
    return u, v, r, s
