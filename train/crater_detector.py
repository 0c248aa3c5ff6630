"""A learned crater detector: a small fully convolutional network run on an image pyramid.

Scale is handled by the pyramid, not by the network: the network finds craters whose rim radius lies in
one octave, [``BAND_LO_PX``, ``BAND_HI_PX``) pixels, and it is run on the frame decimated by 1, 2, 4, ...
(area means), so each level covers the next octave of crater sizes with the same weights. The network
therefore needs a receptive field of a few band radii only (about 70 px), it is small (144 k weights at
width 16), and every training frame teaches every size at once.

Output, per level pixel (CenterNet-style, Zhou et al. 2019, "Objects as Points"): a centre heat map
(logit), the sub-pixel offset of the centre from the pixel centre, and log(r / ``BAND_LO_PX``). Targets: a
Gaussian of sigma ``HEAT_SIGMA_R`` x r about each crater of the band, 1 at the pixel holding its centre;
craters just outside the band (``IGNORE_LO_PX``, ``IGNORE_HI_PX``) are neither positive nor negative
(their disc carries no loss), so the octave edges are not learned as hard boundaries. The heat map is
trained with the penalty-reduced focal loss of CenterNet, the offset and the radius with L1 at the
centre pixels.

Inputs are standardised per level image (zero mean, unit variance), so exposure and the units (I/F of a
render, DN of a mosaic) do not matter. numpy + torch + core only: the navigation layer gives the frames
and labels; inference on a frame is :mod:`train.crater_detector_inference`.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from crater_core.settings_nav import AugmentRanges, DetectorTrainSettings
from train.detector_fit import fit
from train.model_files import read_model_file, write_model_file
from train.prefetch import prefetched

BAND_LO_PX = 6.0  # rim radius band of one pyramid level, px
BAND_HI_PX = 12.0
IGNORE_LO_PX = 4.5  # craters between these and the band carry no loss at that level
IGNORE_HI_PX = 16.0
HEAT_SIGMA_R = 0.25  # heat-map Gaussian sigma, fraction of the rim radius
MIN_LEVEL_PX = 24  # a pyramid level smaller than this is not searched
GAUSS_REACH_SIGMA = 7.0  # exp(-49 / 2) = 2e-11: past it a heat target is 0 (1 - heat == 1 in float32)
MODEL_FORMAT = "crater-synth-detector/1"


def _block(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class CraterNet(nn.Module):
    """Encoder (1, 1/2, 1/4 resolution, dilated at 1/4) and a two-step decoder with skips back to full
    resolution; 4 outputs per pixel: heat logit, centre offset (du, dv), log(r / ``BAND_LO_PX``)."""

    def __init__(self, width: int = 16):
        super().__init__()
        w = width
        self.enc0 = nn.Sequential(_block(1, w), _block(w, w))
        self.enc1 = nn.Sequential(_block(w, 2 * w, stride=2), _block(2 * w, 2 * w))
        self.enc2 = nn.Sequential(
            _block(2 * w, 4 * w, stride=2), _block(4 * w, 4 * w, dilation=2), _block(4 * w, 4 * w, dilation=4)
        )
        self.dec1 = _block(6 * w, 2 * w)
        self.dec0 = _block(3 * w, w)
        self.head = nn.Conv2d(w, 4, 1)
        with torch.no_grad():  # start from a low heat everywhere (CenterNet's prior of ~0.01)
            self.head.bias.copy_(torch.tensor([-4.6, 0.0, 0.0, 0.0]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f0 = self.enc0(x)
        f1 = self.enc1(f0)
        f2 = self.enc2(f1)
        d1 = self.dec1(torch.cat([F.interpolate(f2, size=f1.shape[-2:], mode="bilinear", align_corners=False), f1], 1))
        d0 = self.dec0(torch.cat([F.interpolate(d1, size=f0.shape[-2:], mode="bilinear", align_corners=False), f0], 1))
        return self.head(d0)


# ------------------------------------------------------------------------------------------------
# Pyramid and targets
# ------------------------------------------------------------------------------------------------
def decimate2(a: np.ndarray) -> np.ndarray:
    """Area mean over 2 x 2 blocks (an odd last row or column is dropped)."""
    h, w = (a.shape[0] // 2) * 2, (a.shape[1] // 2) * 2
    a = a[:h, :w]
    return 0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2])


def pyramid(image: np.ndarray, first_level: int = 0, min_px: int = MIN_LEVEL_PX) -> list[tuple[int, np.ndarray]]:
    """(level, image decimated by 2**level) from ``first_level`` while the smaller side is >= ``min_px``. A
    negative ``first_level`` starts with the image enlarged 2**-level times (bilinear; pixel corners kept, so
    a level's coordinates times 2**level are the frame's): rims below the network's band at full
    resolution lie inside it there."""
    a = np.asarray(image, dtype=np.float32)
    out = [(level, enlarge(a, 2**-level)) for level in range(min(first_level, 0), 0)]
    level = 0
    while min(a.shape) >= min_px:
        if level >= first_level:
            out.append((level, a))
        a = decimate2(a)
        level += 1
    return out


def enlarge(a: np.ndarray, factor: int) -> np.ndarray:
    """``a`` enlarged ``factor`` times, bilinear with pixel corners kept (``align_corners=False``)."""
    t = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))[None, None]
    return F.interpolate(t, scale_factor=float(factor), mode="bilinear", align_corners=False)[0, 0].numpy()


def level_shapes(shape, first_level: int = 0, min_px: int = MIN_LEVEL_PX) -> list[tuple[int, int]]:
    """The shapes of :func:`pyramid`'s levels of an image of ``shape``, without the image: a training set
    read from disk counts and plans its samples before reading a frame."""
    h, w = (int(n) for n in shape)
    out, level = [(h << -k, w << -k) for k in range(min(first_level, 0), 0)], 0  # pyramid's enlarged levels
    while min(h, w) >= min_px:
        if level >= first_level:
            out.append((h, w))
        h, w, level = h // 2, w // 2, level + 1
    return out


def level_count(shape, first_level: int = 0, min_px: int = MIN_LEVEL_PX) -> int:
    """How many levels :func:`pyramid` gives an image of ``shape`` (:func:`level_shapes`)."""
    return len(level_shapes(shape, first_level, min_px))


def standardise(a: np.ndarray) -> np.ndarray:
    """Zero mean, unit standard deviation (a constant image becomes zeros)."""
    a = np.asarray(a, dtype=np.float32)
    s = float(a.std())
    return (a - float(a.mean())) / (s if s > 0 else 1.0)


def level_targets(shape, u, v, r, hidden=None, window=None) -> dict[str, np.ndarray]:
    """Training targets of one level image of ``shape`` for craters at level pixels (u, v) of rim radius
    r (arrays; continuous coordinates, origin at the top-left pixel corner): heat (H, W), loss weight
    (H, W; 0 on the discs of craters just outside the band, and on the whole disc of ``hidden`` craters,
    a boolean per crater: rims the image does not show, neither positive nor negative), and at the centre
    pixels the offset and log-radius targets with their mask.

    ``window`` = (i0, j0, hw, ww): the targets of that window of the level only (rows i0 .. i0 + hw - 1,
    columns j0 .. j0 + ww - 1; it may reach past the image), the same values as the whole level's there.
    Each crater touches only the pixels near it (its disc; its Gaussian out to ``GAUSS_REACH_SIGMA``
    sigmas, beyond which the heat is below float32's resolution of 1 - heat, so the loss is unchanged)."""
    h, w = shape
    i0, j0, hw, ww = (0, 0, h, w) if window is None else window
    heat = np.zeros((hw, ww), np.float32)
    weight = np.ones((hw, ww), np.float32)
    offset = np.zeros((2, hw, ww), np.float32)
    logr = np.zeros((hw, ww), np.float32)
    centre = np.zeros((hw, ww), bool)
    u, v, r = (np.asarray(x, dtype=np.float64).ravel() for x in (u, v, r))
    hidden = np.zeros(u.size, bool) if hidden is None else np.asarray(hidden, bool).ravel()
    band = (r >= BAND_LO_PX) & (r < BAND_HI_PX) & ~hidden
    near = ((r >= IGNORE_LO_PX) & (r < BAND_LO_PX)) | ((r >= BAND_HI_PX) & (r < IGNORE_HI_PX))

    def box(k: int, reach: float):
        """Window slices and pixel-centre coordinates within ``reach`` of crater k (None: none there)."""
        a0, a1 = max(0, int(math.floor(v[k] - reach)) - i0), min(hw, int(math.ceil(v[k] + reach)) + 1 - i0)
        b0, b1 = max(0, int(math.floor(u[k] - reach)) - j0), min(ww, int(math.ceil(u[k] + reach)) + 1 - j0)
        if a0 >= a1 or b0 >= b1:
            return None
        jj, ii = np.meshgrid(np.arange(b0, b1) + j0 + 0.5, np.arange(a0, a1) + i0 + 0.5)
        return (slice(a0, a1), slice(b0, b1)), (jj - u[k]) ** 2 + (ii - v[k]) ** 2

    for k in np.nonzero(near & ~hidden)[0]:
        if (b := box(k, 0.5 * r[k])) is not None:
            weight[b[0]][b[1] <= (0.5 * r[k]) ** 2] = 0.0
    for k in np.nonzero(hidden & (r >= IGNORE_LO_PX) & (r < IGNORE_HI_PX))[0]:
        if (b := box(k, r[k])) is not None:
            weight[b[0]][b[1] <= r[k] ** 2] = 0.0
    for k in np.nonzero(band)[0]:
        ci, cj = int(math.floor(v[k])), int(math.floor(u[k]))
        if not (0 <= ci < h and 0 <= cj < w):
            continue
        s = HEAT_SIGMA_R * r[k]
        if (b := box(k, GAUSS_REACH_SIGMA * s)) is not None:
            g = np.exp(-b[1] / (2.0 * s * s)).astype(np.float32)
            np.maximum(heat[b[0]], g, out=heat[b[0]])
        ci, cj = ci - i0, cj - j0
        if 0 <= ci < hw and 0 <= cj < ww:
            heat[ci, cj] = 1.0
            weight[ci, cj] = 1.0
            centre[ci, cj] = True
            offset[:, ci, cj] = (u[k] - (cj + j0 + 0.5), v[k] - (ci + i0 + 0.5))
            logr[ci, cj] = math.log(r[k] / BAND_LO_PX)
    # A weight of 0 never hides a band crater's Gaussian.
    weight[heat > 0.05] = 1.0
    return {"heat": heat, "weight": weight, "offset": offset, "logr": logr, "centre": centre}


def detector_loss(out: torch.Tensor, heat, weight, offset, logr, centre) -> tuple[torch.Tensor, dict]:
    """CenterNet's penalty-reduced focal loss on the heat map plus L1 on offset and log-radius at the
    centre pixels, each normalised by the number of centres in the batch."""
    p = torch.sigmoid(out[:, 0]).clamp(1e-4, 1 - 1e-4)
    pos = centre.float()
    n = pos.sum().clamp(min=1.0)
    pos_loss = -(torch.log(p) * (1 - p) ** 2 * pos).sum()
    neg_loss = -(torch.log(1 - p) * p**2 * (1 - heat) ** 4 * (1 - pos) * weight).sum()
    heat_loss = (pos_loss + neg_loss) / n
    off_loss = (torch.abs(out[:, 1:3] - offset).sum(1) * pos).sum() / n
    r_loss = (torch.abs(out[:, 3] - logr) * pos).sum() / n
    total = heat_loss + off_loss + 2.0 * r_loss
    return total, {
        "heat": float(heat_loss.detach()),
        "offset": float(off_loss.detach()),
        "logr": float(r_loss.detach()),
    }


# ------------------------------------------------------------------------------------------------
# Training
# ------------------------------------------------------------------------------------------------
@dataclass
class LevelSample:
    """One pyramid level of one training frame: its image and its craters in level pixels."""

    image: np.ndarray  # float32, not standardised (augmentation acts on the physical values)
    u: np.ndarray
    v: np.ndarray
    r: np.ndarray
    hidden: np.ndarray  # bool per crater: no loss on its disc (:func:`level_targets`)


def level_samples(image: np.ndarray, u, v, r, hidden=None) -> list[LevelSample]:
    """Every pyramid level of a training frame with its craters (native-pixel u, v, r scaled by level)."""
    u, v, r = (np.asarray(x, dtype=np.float64) for x in (u, v, r))
    hidden = np.zeros(u.size, bool) if hidden is None else np.asarray(hidden, bool)
    return [LevelSample(a, u / 2**k, v / 2**k, r / 2**k, hidden) for k, a in pyramid(image)]


# Channels of a stacked sample: the brightness (0-1, before augmentation), then the targets of
# :func:`level_targets` (heat, loss weight, offset u, offset v, log-radius, centre mask), then the mask of
# real (not padded) pixels.
_IMG, _HEAT, _WEIGHT, _DU, _DV, _LOGR, _CENTRE, _VALID = range(8)


def stack_sample(sample: LevelSample, crop_px: int) -> np.ndarray:
    """(8, H, W) float32 of one whole level (:func:`crop_stack` from its corner), padded with zeros (no loss)
    to at least ``crop_px`` a side."""
    h, w = np.shape(sample.image)
    return crop_stack(sample, brightness_top(sample.image), 0, 0, max(h, crop_px), max(w, crop_px))


CROP_REACH_PX = 24.0  # farthest a crater outside a crop can set its targets: a 16 px disc, a 21 px Gaussian


def crop_stack(sample: LevelSample, top: float, i0: int, j0: int, hw: int, ww: int) -> np.ndarray:
    """(8, hw, ww) float32: the window at (i0, j0) of one level, its brightness over ``top`` (the level's
    99.5th percentile), the targets of :func:`level_targets` computed for the window alone, and the
    valid-pixel mask; past the level's edge, zeros (no loss). Training draws crops this way instead of
    holding every level's full stack in memory (~3 MB a 256 px frame), which would cap a training set at a
    few thousand frames."""
    a = np.clip(np.asarray(sample.image, np.float32), 0.0, None)
    h, w = a.shape
    u, v, r = sample.u, sample.v, sample.r
    near = (
        (u > j0 - CROP_REACH_PX)
        & (u < j0 + ww + CROP_REACH_PX)
        & (v > i0 - CROP_REACH_PX)
        & (v < i0 + hw + CROP_REACH_PX)
    )
    t = level_targets(a.shape, u[near], v[near], r[near], sample.hidden[near], window=(i0, j0, hw, ww))
    out = np.zeros((8, hw, ww), np.float32)
    hh, wv = max(0, min(hw, h - i0)), max(0, min(ww, w - j0))
    win = a[i0 : i0 + hh, j0 : j0 + wv]
    inside = np.isfinite(win)  # a frame turned to its light (train.light_turn) is NaN outside itself
    out[_IMG, :hh, :wv] = np.where(inside, win, 0.0) / top
    out[_HEAT, :hh, :wv] = t["heat"][:hh, :wv]
    out[_WEIGHT, :hh, :wv] = t["weight"][:hh, :wv]
    out[_DU : _DV + 1, :hh, :wv] = t["offset"][:, :hh, :wv]
    out[_LOGR, :hh, :wv] = t["logr"][:hh, :wv]
    out[_CENTRE, :hh, :wv] = t["centre"][:hh, :wv]
    out[_VALID, :hh, :wv] = inside
    return out


def brightness_top(image: np.ndarray) -> float:
    """The level's brightness scale: its 99.5th percentile of the pixels inside the frame (1 for a black
    level)."""
    a = np.clip(np.asarray(image, np.float32), 0.0, None)
    inside = a[np.isfinite(a)]
    return (float(np.percentile(inside, 99.5)) if inside.size else 0.0) or 1.0


def dihedral(t: torch.Tensor, k: int, flip: bool) -> torch.Tensor:
    """A stacked sample (8, H, W) rotated by k x 90 degrees counter-clockwise (``torch.rot90``, as
    ``np.rot90``) and then mirrored top to bottom, the offset vectors turned with it. A nadir frame so
    transformed is the same terrain under a Sun rotated or mirrored alike: still physical."""
    for _ in range(k):  # a quarter turn moves (u, v) to (v, W - u): the offset (du, dv) becomes (dv, -du)
        t = torch.rot90(t, 1, dims=(-2, -1))
        du, dv = t[_DU].clone(), t[_DV].clone()
        t[_DU], t[_DV] = dv, -du
    if flip:  # (u, v) -> (u, H - v)
        t = torch.flip(t, dims=(-2,))
        t[_DV] = -t[_DV]
    return t


def _blur(x: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Each image of (B, 1, H, W) blurred by its own Gaussian sigma (px; 0 leaves it unchanged)."""
    half = 3
    k = torch.arange(-half, half + 1, device=x.device, dtype=x.dtype)
    g = torch.exp(-0.5 * (k[None, :] / sigma.clamp(min=1e-3)[:, None]) ** 2)
    g = g / g.sum(1, keepdim=True)
    b = x.shape[0]
    y = F.conv2d(F.pad(x.transpose(0, 1), (half, half, 0, 0), mode="replicate"), g[:, None, None, :], groups=b)
    y = F.conv2d(F.pad(y, (0, 0, half, half), mode="replicate"), g[:, None, :, None], groups=b)
    return y.transpose(0, 1)


def augment(t: torch.Tensor, s: DetectorTrainSettings, gen: torch.Generator) -> torch.Tensor:
    """The network input of a batch of stacked crops (B, 8, c, c): :func:`augment_brightness`."""
    return augment_brightness(t[:, _IMG : _IMG + 1], t[:, _VALID : _VALID + 1], s, gen)


def augment_brightness(
    brightness: torch.Tensor, valid: torch.Tensor, s: AugmentRanges, gen: torch.Generator
) -> torch.Tensor:
    """Photometric augmentation of a batch of brightness crops (B, 1, c, c; 0-1) with their valid-pixel
    masks (gamma, shadow floor, blur), standardisation over the valid pixels, noise; 0 off the valid pixels."""
    b = brightness.shape[0]

    def uniform(lo_hi):
        lo, hi = lo_hi
        return lo + (hi - lo) * torch.rand(b, 1, 1, 1, generator=gen, device=brightness.device)

    n = valid.sum((2, 3), keepdim=True).clamp(min=1.0)
    x = brightness.clamp(min=0.0) ** uniform(s.gamma)
    x = x + uniform(s.shadow_lift) * (x * valid).sum((2, 3), keepdim=True) / n
    sigma = uniform(s.blur_sigma_px).flatten()
    x = torch.where((sigma > 0.2)[:, None, None, None], _blur(x, sigma), x)
    mean = (x * valid).sum((2, 3), keepdim=True) / n
    std = (((x - mean) ** 2 * valid).sum((2, 3), keepdim=True) / n).sqrt().clamp(min=1e-6)
    x = (x - mean) / std
    x = x + uniform(s.noise) * torch.randn(x.shape, generator=gen, device=brightness.device)
    return x * valid


def sample_shape(samples: Sequence[LevelSample], i: int) -> tuple[int, int]:
    """The level image shape of sample ``i``: a sequence read from disk when drawn (``shape``) tells it
    without reading the frame, so crops can be planned ahead of their reads."""
    shape = getattr(samples, "shape", None)
    return tuple(shape(i)) if shape is not None else np.shape(samples[i].image)  # type: ignore[return-value]


def plan_batch(samples: Sequence[LevelSample], s: DetectorTrainSettings, rng, p=None) -> list[tuple]:
    """The draws of one batch, (sample, row, column, quarter turns, mirrored) per crop: random level
    samples (probabilities ``p``; None: uniformly), a random ``crop_px`` window of each, a random dihedral
    view (``s.sun_aligned``: no quarter turn, which would move the Sun; the mirror along the light only).
    Only the plan uses ``rng``, so plans drawn ahead (:func:`crop_batches`) are the same draws."""
    c = s.crop_px
    picks = rng.integers(0, len(samples), s.batch) if p is None else rng.choice(len(samples), s.batch, p=p)
    plan = []
    for i in picks:
        h, w = (max(n, c) for n in sample_shape(samples, int(i)))
        i0, j0 = int(rng.integers(0, h - c + 1)), int(rng.integers(0, w - c + 1))
        turns = 0 if s.sun_aligned else int(rng.integers(4))
        plan.append((int(i), i0, j0, turns, bool(rng.integers(2))))
    return plan


class PlannedCrops:
    """Builds the crops of a batch plan (:func:`plan_batch`): each a :func:`crop_stack` turned by
    :func:`dihedral`. ``tops``: each sample's brightness scale, None to take it from each drawn sample (samples
    read from disk when drawn: the same values, computed per draw). A module-level class, so the loader's
    spawned worker processes can unpickle it."""

    def __init__(self, samples: Sequence[LevelSample], tops: list[float] | None, crop_px: int):
        self.samples, self.tops, self.crop_px = samples, tops, crop_px

    def __call__(self, plan: list[tuple]) -> torch.Tensor:
        crops = []
        for i, i0, j0, turns, flip in plan:
            x = self.samples[i]
            top = self.tops[i] if self.tops is not None else brightness_top(x.image)
            t = torch.from_numpy(crop_stack(x, top, i0, j0, self.crop_px, self.crop_px))
            crops.append(dihedral(t, turns, flip))
        return torch.stack(crops)


def crop_batches(samples, tops, s: DetectorTrainSettings, rng, p, device: str = "cpu") -> Iterator[torch.Tensor]:
    """The ``s.steps`` training batches, in order: built in this process (``s.loader_workers`` 0) or by
    that many worker processes from plans drawn here (:func:`train.prefetch.prefetched`), so frames read
    from disk are read while the network trains. The same batches either way."""
    build = PlannedCrops(samples, tops, s.crop_px)
    return prefetched(
        lambda: plan_batch(samples, s, rng, p), build, s.steps, s.loader_workers, pin_memory=device != "cpu"
    )


def train_detector(
    samples: Sequence[LevelSample], settings: DetectorTrainSettings, log=None, device: str = "cpu", source=None
) -> dict:
    """Train :class:`CraterNet` on level samples (:func:`train.detector_fit.fit`): a list held in memory, or
    any sequence that builds each sample when drawn (frames read from disk: memory flat in the number of
    frames). Each drawn crop's targets are computed for the crop alone (:func:`crop_stack`), so memory holds
    the level images and their craters, not full target stacks; augmentation is a tensor operation on
    ``device``. ``source`` (an index per sample) with ``settings.source_shares`` sets each source's share of
    the draws."""
    # a list is held in memory: its brightness scales once; a sequence read from disk when drawn: per draw
    tops = [brightness_top(x.image) for x in samples] if isinstance(samples, list) else None

    batches: Iterator[torch.Tensor] | None = None

    def step_loss(model, rng, p, gen):
        nonlocal batches
        if batches is None:  # fit's seeded generator and draw probabilities exist from its first step
            batches = crop_batches(samples, tops, settings, rng, p, device)
        t = next(batches).to(device)
        out = model(augment(t, settings, gen))
        w = t[:, _WEIGHT] * t[:, _VALID]
        return detector_loss(out, t[:, _HEAT], w, t[:, _DU : _DV + 1], t[:, _LOGR], t[:, _CENTRE] > 0.5)

    layout = settings.channels_last
    if not settings.init:
        return fit(lambda: CraterNet(settings.width), samples, settings, step_loss, log, device, source, layout)
    # Fine-tuning: the init model's weights (and so its width) are the start; the schedule is this run's.
    init_model, init_meta = load_model(Path(settings.init))
    result = fit(lambda: init_model, samples, settings, step_loss, log, device, source, layout)
    result["init"] = {
        "model": settings.init,
        "file_sha256": hashlib.sha256(Path(settings.init).read_bytes()).hexdigest(),
        "width": init_model.head.in_channels,
        "trained_on": init_meta.get("trained_on", "unknown"),
    }
    return result


# ------------------------------------------------------------------------------------------------
# Model files (the format: train.model_files)
# ------------------------------------------------------------------------------------------------
def save_model(path: Path, model: CraterNet, meta: dict) -> None:
    """Write the weights and ``meta`` (provenance, settings) atomically, with a sha256 of the weights."""
    write_model_file(path, MODEL_FORMAT, model.state_dict(), meta, width=model.head.in_channels)


def load_model(path: Path) -> tuple[CraterNet, dict]:
    """The model and its meta from a :func:`save_model` file; a missing, corrupt or foreign file raises
    :class:`DetectorModelError` naming it. The model runs channels last (NHWC): oneDNN's convolutions take
    ~0.7 of the time on the CPU (a 1024 x 1024 level: 0.58 s against 0.79), the outputs within ~1e-6 of the
    standard layout's."""
    model, meta = read_model_file(path, MODEL_FORMAT, lambda payload: CraterNet(int(payload["width"])))
    return model.to(memory_format=torch.channels_last), meta


def settings_dict(s: DetectorTrainSettings) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(s).items()}
