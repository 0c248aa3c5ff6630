"""Settings of ``crater-synth nav-frames-eval`` (:mod:`.frames_eval`): its presets and the detector's
scale range from the landmark map (docs/navigation/rendered.md, where the "synthetic" preset was
chosen on rendered frames)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from crater_synth.errors import UserError
from crater_synth.navigation.detectors.classical import DetectorParams
from crater_synth.navigation.fix.appearance import AppearanceParams
from crater_synth.navigation.fix.solve import FixParams

PNP_INLIER_PX = 3.0  # the first runs' reprojection tolerance of the pinhole fix (px): the "real-window" preset's


@dataclasses.dataclass(frozen=True)
class FramesPreset:
    """The settings of ``nav-frames-eval``: a detector of :data:`.detect.PRESETS` and ``--set``-style
    overrides of it and of :class:`.fix.FixParams`, whether the detector searches only the landmark
    map's radii (:func:`map_scales`), and the fix's reprojection inlier tolerance (px)."""

    detector: str
    sets: tuple = ()
    scales_from_map: bool = False
    inlier_px: float = PNP_INLIER_PX
    refine: bool = False  # known-attitude fixes refined by appearance (:mod:`.refine`)
    appearance: AppearanceParams | None = None  # no detector: the appearance search (:mod:`.appearance`)


# "real-window": the real-window settings unchanged (the classical preset, every scale, 5 agreeing
# landmarks, 3 px), the first runs on rendered frames. "synthetic": chosen on the rendered frames of
# descent_ridge and polar_orbit_arc (render.samples=4, fast, 512 px; development data, no real window
# used) by the rule of the real windows: no false fix, then the most fixes, then the lowest median
# error (docs/navigation/rendered.md, the grid): the classical detector at threshold 0.3 on the map's
# radii only, 3 agreeing landmarks with the ambiguity test, 5 px inliers (the 6-DOF fix takes at least 4:
# three points determine a pinhole pose exactly).
FRAMES_PRESETS = {
    "real-window": FramesPreset("classical"),
    "synthetic": FramesPreset(
        "classical",
        ("detect.threshold=0.3", "fix.min_inliers=3"),
        scales_from_map=True,
        inlier_px=5.0,
        refine=True,
    ),
}
# "learned": the learned detector with its frozen real-window preset (chosen on the south windows, not on
# these frames) and the "synthetic" preset's fix settings; nothing was chosen on the rendered trajectories.
FRAMES_PRESETS["learned"] = FramesPreset(
    "learned", ("fix.min_inliers=3",), scales_from_map=True, inlier_px=5.0, refine=True
)
# "appearance": no crater detector; the map's landmarks searched for by their predicted appearance
# (:mod:`.appearance`, settings chosen on descent_ridge and polar_orbit_arc), then the synthetic preset's
# identification, fix and refinement.
FRAMES_PRESETS["appearance"] = FramesPreset(
    "appearance",
    ("fix.min_inliers=3",),
    inlier_px=5.0,
    refine=True,
    appearance=AppearanceParams(),
)
# The default: the rule above on the development trajectories (no false fix, most fixes, lowest median)
# ranks "appearance" first (21 of 28 fixes, median 0.04 km; "synthetic" 7, 0.07 km).
DEFAULT_FRAMES_PRESET = "appearance"
# The results file keys the "synthetic" preset without a suffix (it was the first default).
RESULTS_UNSUFFIXED_PRESET = "synthetic"


def frames_params(name: str, sets=()) -> tuple[DetectorParams, FixParams, FramesPreset]:
    """(detector settings, fix settings, preset) of the ``nav-frames-eval`` preset ``name`` with the
    ``--set`` overrides ``sets`` applied after the preset's own. Every preset serves both fixes: the
    6-DOF fix never takes fewer than 4 landmarks and refuses an ambiguous pose or one that contradicts its
    prior (:func:`.fix.ransac_pnp`)."""

    if name not in FRAMES_PRESETS:
        raise UserError(f"nav-frames-eval preset {name!r}: expected one of {sorted(FRAMES_PRESETS)}")
    pre = FRAMES_PRESETS[name]
    # The appearance search runs no crater detector: its detector settings are the defaults, unused.
    dparams, fparams = params_with(tuple(pre.sets) + tuple(sets), "classical" if pre.appearance else pre.detector)
    return dparams, fparams, pre


def map_scales(dparams: DetectorParams, fparams: FixParams, gsd_m: float, predicted_r_px) -> DetectorParams:
    """Detector settings searching only the crater radii the landmark map can use in this frame, as a
    lander knowing its altitude (hence its ground sample) and its coarse position would: from the
    smallest landmark's radius (``min_landmark_km`` / 2 at ``gsd_m``) to the largest radius of the
    landmarks the prior predicts in the frame (``predicted_r_px``), each widened by the identification's
    ``radius_ratio`` (a detection outside it could never pair with a landmark). Without a predicted
    landmark the range is the smallest landmark's alone."""
    lo = fparams.min_landmark_km * 500.0 / gsd_m / fparams.radius_ratio
    big = float(np.max(predicted_r_px)) if len(predicted_r_px) else fparams.min_landmark_km * 500.0 / gsd_m
    hi = max(big * fparams.radius_ratio, lo * dparams.scale_ratio**2)
    return dataclasses.replace(dparams, min_radius_px=lo, max_radius_px=hi)


# --------------------------------------------------------------------------------------------
# nav-eval
# --------------------------------------------------------------------------------------------
def params_with(overrides: tuple[str, ...], method: str = "classical") -> tuple[DetectorParams, FixParams]:
    """Detector settings of ``method`` (:data:`crater_synth.navigation.detectors.classical.PRESETS`) and fix settings,
    with ``key=value`` overrides (``detect.threshold=0.8``, ``fix.min_inliers=4``)."""
    from crater_synth.navigation.detectors.classical import preset

    base = preset(method)
    groups = {"detect": dataclasses.asdict(base), "fix": dataclasses.asdict(FixParams())}
    for o in overrides:
        key, sep, value = o.partition("=")
        group, _, name = key.partition(".")
        if not sep or group not in groups or name not in groups[group]:
            raise UserError(f"--set {o}: expected detect.<name>=<value> or fix.<name>=<value> with a known name")
        old = groups[group][name]
        try:
            parsed = json.loads(value) if not isinstance(old, str) or value.startswith('"') else value
            groups[group][name] = type(old)(parsed) if not isinstance(old, tuple) else tuple(parsed)
        except (ValueError, TypeError):
            raise UserError(f"--set {o}: {value!r} is not a {type(old).__name__}") from None
    return DetectorParams(**groups["detect"]), FixParams(**groups["fix"])
