"""The appearance search in the detector registry: not an image detector (no candidates function), it
searches for the map's landmarks by their predicted appearance under a position prior
(:mod:`crater_synth.navigation.fix.appearance`, :mod:`crater_synth.navigation.windows.appearance`); its
settings are :class:`crater_core.settings_nav.AppearanceSettings` (configs/nav/detector/appearance.yaml)."""

from __future__ import annotations

from crater_core.settings_nav import AppearanceSettings
from crater_synth.navigation.detectors.registry import DetectorEntry

DETECTOR = DetectorEntry(
    "appearance",
    AppearanceSettings,
    None,
    "no detector: each map landmark predicted from the DEM (Hapke, horizon shadows) and searched for by NCC "
    "under the prior (crater_synth.navigation.fix.appearance)",
    spectrum=False,
)
