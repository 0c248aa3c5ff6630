"""A standard detector beside the learned one: torchvision's FCOS (:mod:`train.fcos_detector`), trained from
scratch on the same rendered frames (``crater-synth nav-detector-train ... nav.detector_train.arch=fcos``).

It searches the frame at the pyramid level the learned detector would start at for ``min_radius_px``
(:func:`.learned.first_level`: a 1024 px mosaic window at 400 m/px is searched at 800 m/px, the survey
frames' ground sample) and its boxes are read back as circles (centre, mean half side). No FCOS model is
committed: ``nav.detector.model`` names one. Its detections go through the same border rule, optional
rim fit and suppression as every detector (:func:`crater_synth.navigation.detectors.classical.detect`).
This module is inference only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from crater_core.settings_nav import DetectorSettings
from crater_synth.errors import UserError
from crater_synth.navigation.detectors.learned import cached_loader, first_level, within_radii
from crater_synth.navigation.detectors.registry import CandidateInput, DetectorEntry


@dataclass(frozen=True)
class FcosSettings(DetectorSettings):
    """The FCOS detector's own settings (configs/nav/detector/fcos.yaml)."""

    NAME: ClassVar[str] = "fcos"

    threshold: float = 0.3  # FCOS's score (class probability x centre-ness, square-rooted) of a candidate
    model: str = ""  # model file (required: no FCOS model is committed)


def _read_fcos(path: Path):
    from train.fcos_detector import load_model as read

    return read(path)


load_fcos_model = cached_loader(_read_fcos)


def fcos_model_path(params: FcosSettings) -> Path:
    """The model file the settings name; none named is one error line saying how to make one."""
    if not params.model:
        raise UserError(
            "nav/detector=fcos needs a model: train one with `crater-synth nav-detector-train FRAMES_DIR "
            "nav.detector_train.arch=fcos --out fcos.pt` and pass nav.detector.model=fcos.pt"
        )
    return Path(params.model)


def fcos_candidates(frame: CandidateInput, params: FcosSettings):
    """FCOS's craters in ``frame.image``: (u, v, r, score) in frame pixels, radii within the detector's
    [min_radius_px, max_radius_px]."""
    from train.fcos_detector import detect_fcos

    model, _meta = load_fcos_model(str(fcos_model_path(params)))
    u, v, r, s = detect_fcos(model, frame.image, params.threshold, first_level(params.min_radius_px))
    return within_radii(params, u, v, r, s)


# Like the learned detector: no Fourier spectrum, no light direction.
DETECTOR = DetectorEntry(
    "fcos",
    FcosSettings,
    fcos_candidates,
    "torchvision's FCOS with a small ResNet, trained from scratch on rendered frames only "
    "(crater_synth.navigation.detectors.fcos, train.fcos_detector)",
    spectrum=False,
    model_file=fcos_model_path,
    load_model=load_fcos_model,
)
