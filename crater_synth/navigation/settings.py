"""Navigation's settings: the ``nav`` config group composed from ``configs/navigation.yaml`` with the
user's overrides (Hydra, as every other command: ``crater_synth.config``), validated once into
:class:`NavSettings` (docs/navigation/settings.md), and the detector's scale range from the landmark map.

``configs/navigation.yaml`` is composed apart from ``configs/config.yaml`` so that no other command's
composed configuration (nor any run fingerprint) changes. Its groups: ``nav/detector`` (one option per
detector setting, each with its detector's own schema from :mod:`.detectors.registry`), ``nav/fix``,
``nav/lost_in_space``, ``nav/frames`` (rendered frames), ``nav/landmarks`` (the landmark map's commands),
``nav/detector_train`` (the learned detector's training) and ``nav/preset`` (named presets of rendered frames:
``# @package _global_`` files that select a detector and set several groups, like ``experiment=``).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Sequence

import numpy as np
from hydra.core.config_store import ConfigStore

from crater_core.settings_nav import DetectorSettings, DetectorTrainSettings, FramesSettings, LandmarksSettings
from crater_core.typed_config import SettingsError, build
from crater_synth.config import compose_plain, schema_class
from crater_synth.errors import ConfigError
from crater_synth.navigation.detectors import registry
from crater_synth.navigation.fix.lost_in_space import LostInSpaceParams
from crater_synth.navigation.fix.solve import FixParams
from crater_synth.paths import CONFIG_DIR

NAV_CONFIG = "navigation"  # configs/navigation.yaml
# The frame presets' settings recorded without a suffix in the results file (it was the first default).
RESULTS_UNSUFFIXED_PRESET = "synthetic"
DEFAULT_FRAMES_PRESET = "appearance"  # nav-frames-eval, navigate FRAME.exr: the rule on the development frames
# Groups of nav whose schema is one class (nav/detector's is its detector's: the registry's).
NAV_GROUPS = {
    "fix": FixParams,
    "lost_in_space": LostInSpaceParams,
    "frames": FramesSettings,
    "landmarks": LandmarksSettings,
    "detector_train": DetectorTrainSettings,
}


@dataclasses.dataclass(frozen=True)
class NavSettings:
    """The composed ``nav`` group: the detector's settings (its own class), the fix's, lost in space's, the
    rendered frames', the landmark map commands' and the detector training's; ``choices``: the option of
    each group the composition took (``detector``: e.g. ``learned-detect``; ``preset``: the ``nav/preset``
    or None)."""

    detector: Any
    fix: FixParams
    lost_in_space: LostInSpaceParams
    frames: FramesSettings
    landmarks: LandmarksSettings
    detector_train: DetectorTrainSettings
    choices: dict

    @property
    def preset(self) -> str | None:
        return self.choices.get("preset")

    @property
    def appearance(self) -> bool:
        """Whether the landmarks are searched for by appearance (no crater detector runs)."""
        return registry.detector(self.detector.method).candidates is None

    def as_dict(self) -> dict:
        return {
            "detector": self.detector.as_dict(),
            "fix": dataclasses.asdict(self.fix),
            "lost_in_space": dataclasses.asdict(self.lost_in_space),
            "frames": self.frames.as_dict(),
            "landmarks": self.landmarks.as_dict(),
            "detector_train": self.detector_train.as_dict(),
        }


def detector_options() -> list[str]:
    """The options of ``nav/detector`` (``configs/nav/detector/*.yaml``): the detector settings one can name."""
    return sorted(p.stem for p in (CONFIG_DIR / "nav" / "detector").glob("*.yaml"))


def preset_options() -> list[str]:
    """The named presets of rendered frames (``configs/nav/preset/*.yaml``)."""
    return sorted(p.stem for p in (CONFIG_DIR / "nav" / "preset").glob("*.yaml"))


def register_nav_schemas() -> None:
    """Store each nav group's schema in Hydra's ConfigStore: ``<detector>_schema`` under nav/detector for
    every registered detector, ``<group>_schema`` for the others (again whenever the registry changed)."""
    cs = ConfigStore.instance()
    for name, entry in registry.detectors().items():
        cs.store(group="nav/detector", name=f"{name}_schema", node=schema_class(entry.settings))
    for group, cls in NAV_GROUPS.items():
        cs.store(group=f"nav/{group}", name=f"{group}_schema", node=schema_class(cls))


def compose_nav(overrides: Sequence[str] = (), defaults: Sequence[str] = ()) -> NavSettings:
    """The ``nav`` settings of ``configs/navigation.yaml`` with Hydra overrides (``nav/detector=template``,
    ``nav.detector.threshold=0.5``, ``nav/preset=synthetic``), validated once. ``defaults``: overrides a
    command puts first (its own default preset), for the user's to replace: a group the user selects drops
    the command's choice of it. Any bad value or unknown key is one :class:`ConfigError` line naming it."""
    # nav/preset=null: no preset (Hydra takes null for a group option only as a deletion of the default).
    overrides = ["~nav/preset" if o.lstrip("+") == "nav/preset=null" else o for o in overrides]
    chosen = {o.partition("=")[0].lstrip("+~") for o in overrides}
    if "nav/detector" in chosen:  # a detector the user picks replaces the command's default preset too
        chosen.add("nav/preset")
    overrides = [o for o in defaults if o.partition("=")[0].lstrip("+~") not in chosen] + list(overrides)
    bad = [o for o in overrides if not o.lstrip("+~").startswith(("nav.", "nav/"))]
    if bad:
        raise ConfigError(f"{bad[0]}: navigation overrides are nav.<group>.<key>=<value> or nav/<group>=<option>")
    for o in overrides:  # the preset group is optional in the defaults, so Hydra would skip a missing option
        key, _, value = o.lstrip("+~").partition("=")
        if key == "nav/preset" and not o.startswith("~") and value not in preset_options():
            known = ", ".join(preset_options())
            raise ConfigError(f"unknown nav/preset {value!r} (override {o}): choose one of {known}")
    check_preset_detector(overrides)
    register_nav_schemas()
    plain, choices = compose_plain(NAV_CONFIG, overrides, CONFIG_DIR)
    nav = nav_settings(plain["nav"], choices)
    verify_detector_settings(nav.lost_in_space.verify_detector)  # a bad name fails here, before any frame
    return nav


@functools.lru_cache(maxsize=None)
def verify_detector_settings(name: str):
    """The settings of the ``nav/detector`` option ``name`` whose detections join a lost-in-space fix's
    verification (``nav.lost_in_space.verify_detector``), as its file sets them; None for "". One
    :class:`ConfigError` for a name that is no option or an option that finds no craters."""
    if not name:
        return None
    key = "nav.lost_in_space.verify_detector"
    if name not in detector_options():
        raise ConfigError(f"{key}={name!r}: not a nav/detector option (choose one of {', '.join(detector_options())})")
    settings = compose_nav([f"nav/detector={name}"]).detector
    if registry.detector(settings.method).candidates is None:
        raise ConfigError(f"{key}={name!r}: the {settings.method} method finds no craters to verify with")
    return settings


def check_preset_detector(overrides: Sequence[str]) -> None:
    """A preset sets its detector's own keys, so another detector under it cannot compose: say so in one
    line instead of Hydra's key error (``nav/preset=null`` drops the preset)."""
    picked = {o.lstrip("+").partition("=")[0]: o.partition("=")[2] for o in overrides}
    preset = "null" if "~nav/preset" in picked else picked.get("nav/preset", "null")
    detector = picked.get("nav/detector")
    if detector is not None and preset != "null":
        raise ConfigError(
            f"nav/detector={detector}: nav/preset={preset} chooses the detector and its settings; choose a preset "
            f"({', '.join(preset_options())}) or drop it with nav/preset=null"
        )


def nav_settings(plain: dict, choices: dict | None = None) -> NavSettings:
    """:class:`NavSettings` from the resolved ``nav`` mapping (one :class:`ConfigError` naming a bad key)."""
    choices = choices or {}
    try:
        return NavSettings(
            detector=registry.settings_from(plain.get("detector"), "nav.detector"),
            **{group: build(cls, plain.get(group) or {}, f"nav.{group}") for group, cls in NAV_GROUPS.items()},
            choices={
                "detector": choices.get("nav/detector"),
                "lost_in_space": choices.get("nav/lost_in_space"),
                "preset": choices.get("nav/preset"),
            },
        )
    except SettingsError as exc:
        raise ConfigError(str(exc)) from None


def map_scales(dparams: DetectorSettings, fparams: FixParams, gsd_m: float, predicted_r_px) -> DetectorSettings:
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
