"""Inference of the learned crater detector (:mod:`train.crater_detector`) on a whole frame: each pyramid level's
output maps (averaged over dihedral views and over an ensemble's models), their peaks, and the craters of every
level in frame pixels (:func:`detect_pyramid`, which the navigation layer calls). Kept apart from the training
module: a detector run needs none of the targets, losses or augmentation.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from train.crater_detector import BAND_LO_PX, CraterNet, pyramid, standardise

HALF_OCTAVE = math.sqrt(2.0)  # the shrink of the half-octave pyramid (detect_pyramid)


# A sun-aligned model (trained on frames turned to their light, train.light_turn) has two views: the level as
# it is and mirrored top to bottom, along the light. A turn or a left-right mirror would move the Sun.
SUN_ALIGNED_VIEWS = 2


@torch.no_grad()
def level_output(model: CraterNet, a: np.ndarray, tta: int = 1, sun_aligned: bool = False) -> np.ndarray:
    """The network's 4 output maps on one level image (standardised here): (4, H, W), heat as probability.
    ``tta`` > 1 averages the heat and log-radius maps over the first ``tta`` of the 8 rotations and
    mirrorings (training draws all 8, so each is an equally valid view); the offsets stay the identity
    view's (they would need turning with the view, and are sub-pixel). ``sun_aligned``: at most
    :data:`SUN_ALIGNED_VIEWS` views, the second mirrored top to bottom."""
    x = torch.from_numpy(standardise(a))[None, None]
    out = model(x)[0]
    heat = torch.sigmoid(out[0])
    logr = out[3].clone()
    tta = min(tta, SUN_ALIGNED_VIEWS) if sun_aligned else tta
    for k in range(1, tta):
        if sun_aligned:
            o = model(x.flip(2))[0].flip(1)
        else:
            turns, flip = k % 4, k >= 4
            xt = torch.rot90(x.flip(3) if flip else x, turns, (2, 3))
            o = torch.rot90(model(xt)[0], -turns, (1, 2))
            o = o.flip(2) if flip else o
        heat += torch.sigmoid(o[0])
        logr += o[3]
    out[0] = heat / tta
    out[3] = logr / tta
    return out.numpy()


def peaks(out: np.ndarray, threshold: float) -> tuple[np.ndarray, ...]:
    """Local maxima (3 x 3) of the heat map above ``threshold``: (u, v, r, score) in level pixels."""
    from scipy.ndimage import maximum_filter

    heat = out[0]
    i, j = np.nonzero((heat >= threshold) & (heat == maximum_filter(heat, size=3, mode="constant")))
    u = j + 0.5 + out[1, i, j]
    v = i + 0.5 + out[2, i, j]
    r = BAND_LO_PX * np.exp(out[3, i, j])
    return u, v, r, heat[i, j]


def ensemble_output(models: list[CraterNet], a: np.ndarray, tta: int = 1, sun_aligned: bool = False) -> np.ndarray:
    """:func:`level_output` of each of ``models`` (the same network, other weights), their heat and log-radius
    maps averaged; the offsets stay the first model's (sub-pixel, as the views' are)."""
    out = level_output(models[0], a, tta, sun_aligned)
    if len(models) > 1:
        rest = [level_output(m, a, tta, sun_aligned) for m in models[1:]]
        out[0] = (out[0] + sum(o[0] for o in rest)) / len(models)
        out[3] = (out[3] + sum(o[3] for o in rest)) / len(models)
    return out


def detect_pyramid(
    model: CraterNet | list[CraterNet],
    image: np.ndarray,
    threshold: float,
    first_level: int = 0,
    tta: int = 1,
    half_octaves=False,
    sun_aligned: bool = False,
):
    """Craters of every pyramid level from ``first_level``: (u, v, r, score, level) in frame pixels.
    ``half_octaves`` also searches the pyramid of the image shrunk by sqrt(2) (its level k sits between
    levels k and k + 1; "level" k + 0.5), so every rim radius lies near a band's middle in one of the two:
    an octave's band edges are where the heat is weakest. ``tta``: :func:`level_output`; a list of models:
    their maps averaged (:func:`ensemble_output`); ``sun_aligned``: models of frames turned to their light, the
    ``image`` turned alike (:func:`level_output`'s views)."""
    models = model if isinstance(model, list) else [model]
    image = np.asarray(image, dtype=np.float32)
    starts = [(0.0, image, 1.0, 1.0)]
    if half_octaves:
        h, w = image.shape
        hh, ww = max(1, round(h / HALF_OCTAVE)), max(1, round(w / HALF_OCTAVE))
        small = F.interpolate(torch.from_numpy(image)[None, None], size=(hh, ww), mode="bilinear", antialias=True)
        starts.append((0.5, small[0, 0].numpy(), w / ww, h / hh))
    found = []
    for half, img, fu, fv in starts:
        for level, a in pyramid(img, first_level):
            u, v, r, s = peaks(ensemble_output(models, a, tta, sun_aligned), threshold)
            f = 2.0**level
            found.append((u * f * fu, v * f * fv, r * f * math.sqrt(fu * fv), s, np.full(u.size, level + half)))
    if not found:
        return tuple(np.zeros(0) for _ in range(5))
    return tuple(np.concatenate(x) for x in zip(*found))
