"""Third crater detector: the network of :mod:`train.crater_detector`, trained on rendered frames only.

Training data are the survey frames of :mod:`.detector_frames` (south DEM, rendered by ``nav-frames``,
labelled with the south landmark map's projected rims); no real pixel takes part. The network finds
craters of one octave of rim radius and runs on the frame's image pyramid; the first level searched is
the one whose band starts near ``min_radius_px`` (so a 400 m/px mosaic window is searched from 800 m/px,
the training frames' own ground sample). Its detections go through the same border rule, optional rim
fit and suppression as the other two methods (:func:`crater_synth.navigation.detectors.classical.detect`).

The committed model (``DEFAULT_MODEL``) carries its provenance (survey seed and tracks, training
settings, code commit, synthetic hold-out metrics) inside the file; :mod:`..rendered.detector_train`
(``crater-synth nav-detector-frames``, ``crater-synth nav-detector-train``) makes it again. This module
is inference only.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Tuple

import numpy as np

from crater_core.settings_nav import DetectorSettings
from crater_core.typed_config import need
from crater_synth.errors import UserError
from crater_synth.navigation.detectors.registry import CandidateInput, DetectorEntry
from crater_synth.paths import MODELS_DIR
from train.light_turn import turn_to_light

DEFAULT_MODEL = MODELS_DIR / "crater_detector_south.pt"
VERIFY_SCORES = ("verifier", "geometric")  # LearnedSettings.verify_score


@dataclass(frozen=True)
class LearnedSettings(DetectorSettings):
    """The learned detector's own settings (configs/nav/detector/learned.yaml)."""

    NAME: ClassVar[str] = "learned"

    threshold: float = 0.3  # heat-map peak of a candidate
    model: str = ""  # model file ("": the committed south model)
    # Test-time views: the heat map averaged over this many of the 8 rotations and mirrorings (1: none);
    # each view costs one more network pass.
    tta: int = 1
    # Also search the pyramid of the frame shrunk by sqrt(2) (half-octave steps); twice the network passes.
    half_octaves: bool = False
    # Levels of the frame enlarged 2x, 4x, ... the search may start at (0: none), for rims below the
    # network's band at full resolution (< 6 px, first_level); the first costs 4 x a full-resolution pass.
    upsample_levels: int = 0
    # More model files of the same network (trained on other frames or seeds): their heat and log-radius maps
    # are averaged with ``model``'s, view by view. Models that err differently average their errors down; each
    # costs ``model``'s network passes again.
    ensemble: Tuple[str, ...] = ()
    # The second stage (train.crater_verifier): a model file that re-measures each candidate on a crop
    # scaled to its radius and scores it; "" = none. The heat ``threshold`` then only gathers candidates,
    # and a candidate is kept when the verifier's probability reaches ``verify_threshold`` (its score).
    verifier: str = ""
    verify_threshold: float = 0.5
    verify_refine: bool = True  # take the verifier's re-measured centre and radius (else the detector's)
    # The kept candidate's score, compared with verify_threshold: the verifier's probability ("verifier")
    # or its geometric mean with the heat ("geometric": a strong heat peak outvotes a doubtful crop).
    verify_score: str = "verifier"

    def _check(self) -> None:
        super()._check()
        need(self.tta in (1, 2, 4, 8), "tta", self.tta, "must be 1, 2, 4 or 8")
        need(self.upsample_levels in (0, 1, 2), "upsample_levels", self.upsample_levels, "must be 0, 1 or 2")
        need(0.0 <= self.verify_threshold <= 1.0, "verify_threshold", self.verify_threshold, "must be in [0, 1]")
        need(self.verify_score in VERIFY_SCORES, "verify_score", self.verify_score, f"must be one of {VERIFY_SCORES}")


class DetectorModelFileError(UserError):
    """The learned detector's model file cannot be used."""


def cached_loader(read):
    """A detector's model loader: ``read(Path)`` (a train module's ``load_model``) cached by path (a few
    models at a time), a file that cannot be used one :class:`DetectorModelFileError` naming it."""

    @functools.lru_cache(maxsize=4)
    def load(path: str):
        from train.model_files import DetectorModelError

        try:
            return read(Path(path))
        except DetectorModelError as exc:
            raise DetectorModelFileError(str(exc)) from None

    return load


def _read_centernet(path: Path):
    from train.crater_detector import load_model as read

    return read(path)


load_model = cached_loader(_read_centernet)


def _read_verifier(path: Path):
    from train.crater_verifier import load_model as read

    return read(path)


load_verifier = cached_loader(_read_verifier)


def model_path(params) -> Path:
    """The model file a detector setting names ("" = the committed default)."""
    return Path(params.model) if params.model else DEFAULT_MODEL


def first_level(min_radius_px: float, upsample_levels: int = 0) -> int:
    """The first pyramid level searched: its band's lower edge (6 x 2**level px) near 4/3 x the
    smallest radius wanted, so that radius is found at a level where it lies inside the band; no lower
    than ``-upsample_levels`` (a negative level: the frame enlarged, :func:`train.crater_detector.pyramid`)."""
    from train.crater_detector import BAND_LO_PX

    return max(-upsample_levels, int(round(math.log2(max(min_radius_px, 1e-6) / (0.75 * BAND_LO_PX)))))


def learned_candidates(frame: CandidateInput, params: LearnedSettings):
    """The network's craters in ``frame.image``: (u, v, r, score) in frame pixels, radii within the
    detector's [min_radius_px, max_radius_px]."""
    from train.crater_detector_inference import detect_pyramid

    loaded = [load_model(str(path)) for path in (model_path(params), *params.ensemble)]
    aligned = {sun_aligned(meta) for _, meta in loaded}
    if len(aligned) > 1:
        raise DetectorModelFileError(
            f"{model_path(params)} and nav.detector.ensemble={list(params.ensemble)}: "
            "either every model is sun-aligned (nav.detector_train.sun_aligned) or none is"
        )
    image, turned = frame.image, None
    if True in aligned:  # the frame turned to its light, as the model's training frames were
        if not math.isfinite(frame.light):
            raise UserError(f"{model_path(params)} is sun-aligned: it needs the frame's light direction, none given")
        turned = turn_to_light(frame.image, frame.light)
        image = np.where(np.isfinite(turned.image), turned.image, np.nanmedian(turned.image)).astype(np.float32)
    u, v, r, s, _level = detect_pyramid(
        [model for model, _ in loaded],
        image,
        params.threshold,
        first_level(params.min_radius_px, params.upsample_levels),
        params.tta,
        params.half_octaves,
        sun_aligned=turned is not None,
    )
    if turned is not None:
        u, v = turned.back(u, v)
        h, w = np.shape(frame.image)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        u, v, r, s = u[inside], v[inside], r[inside], s[inside]
    if params.verifier:
        from train.crater_verifier import verify

        verifier, _ = load_verifier(params.verifier)
        uv, vv, rv, p = verify(verifier, frame.image, u, v, r)
        s = p if params.verify_score == "verifier" else np.sqrt(p * s)
        if params.verify_refine:
            u, v, r = uv, vv, rv
        keep = s >= params.verify_threshold
        u, v, r, s = u[keep], v[keep], r[keep], s[keep]
    return within_radii(params, u, v, r, s)


def sun_aligned(meta: dict) -> bool:
    """Whether a model file's network was trained on frames turned to their light
    (``nav.detector_train.sun_aligned``, :mod:`train.light_turn`)."""
    return bool((meta.get("settings") or {}).get("sun_aligned", False))


def model_sun_aligned(params) -> bool:
    """Whether the learned detector's model file (``params.model``) is sun-aligned (:func:`sun_aligned`)."""
    return sun_aligned(load_model(str(model_path(params)))[1])


def within_radii(params, u, v, r, s):
    """The candidates (u, v, r, score arrays) whose radius lies in the detector's [min_radius_px,
    max_radius_px]."""
    keep = (r >= params.min_radius_px) & (r <= params.max_radius_px)
    return u[keep], v[keep], r[keep], s[keep]


# The network needs no Fourier spectrum; a light direction only when its model is sun-aligned.
DETECTOR = DetectorEntry(
    "learned",
    LearnedSettings,
    learned_candidates,
    "fully convolutional network on an image pyramid, trained on rendered frames only "
    "(crater_synth.navigation.detectors.learned, train.crater_detector)",
    spectrum=False,
    model_file=model_path,
    load_model=load_model,
)
