"""The nav config group: every option composes, a bad override is one line naming its key, and a detector
is one module plus one YAML file (a toy detector added the way a newcomer would)."""

from __future__ import annotations

import re
import textwrap

import numpy as np
import pytest

from crater_core.settings_nav import DetectorTrainSettings, LandmarksSettings
from crater_synth.config import compose_group
from crater_synth.errors import ConfigError
from crater_synth.navigation.detectors import registry
from crater_synth.navigation.settings import compose_nav, detector_options, preset_options


@pytest.mark.parametrize("option", detector_options())
def test_every_detector_option_composes(option):
    nav = compose_nav([f"nav/detector={option}"])
    assert nav.detector.method in registry.detectors() and nav.choices["detector"] == option


@pytest.mark.parametrize("preset", preset_options())
def test_every_preset_composes(preset):
    nav = compose_nav([f"nav/preset={preset}"])
    assert nav.preset == preset and nav.fix.min_inliers >= 3


@pytest.mark.parametrize(
    "override, message",
    [
        ("nav.detector.thresold=0.3", "nav.detector.thresold: unknown key"),
        ("nav.detector.threshold=abc", "nav.detector.threshold=abc: must be a number"),
        ("nav.fix.min_inliers=x", "nav.fix.min_inliers=x: must be an integer"),
        ("nav.detector.light_scope=moon", "nav.detector.light_scope='moon': must be one of"),
        ("nav/detector=cnn", "unknown nav/detector 'cnn'"),
        ("nav/preset=template", "unknown nav/preset 'template' (override nav/preset=template): choose one of"),
        ("detect.threshold=0.3", "detect.threshold=0.3: navigation overrides are nav."),
    ],
)
def test_bad_override_is_one_line_naming_the_key(override, message):
    with pytest.raises(ConfigError) as err:
        compose_nav([override])
    assert message in str(err.value) and "\n" not in str(err.value)


def test_old_results_name_filter_reads_as_classical():
    assert registry.settings_from({"method": "filter", "threshold": 0.4}).method == "classical"


TOY_MODULE = """
from dataclasses import dataclass
from typing import ClassVar
import numpy as np
from crater_core.settings_nav import DetectorSettings
from crater_synth.navigation.detectors.registry import DetectorEntry

@dataclass(frozen=True)
class ToySettings(DetectorSettings):
    NAME: ClassVar[str] = "toy"
    radius_px: float = 12.0

def toy_candidates(frame, params):  # one crater at the frame's centre
    h, w = frame.image.shape
    return np.array([w / 2]), np.array([h / 2]), np.array([params.radius_px]), np.array([1.0])

DETECTOR = DetectorEntry("toy", ToySettings, toy_candidates, "a toy: one crater at the centre", spectrum=False)
"""


@pytest.fixture
def toy_detector(tmp_path, monkeypatch):
    """A toy detector added as a newcomer would: one module in detectors/ and one YAML in nav/detector/
    (here a module in a directory added to the package's path and a YAML in a copy of configs/)."""
    import shutil

    from crater_synth.navigation import detectors as package
    from crater_synth.navigation import settings as nav_settings

    mods = tmp_path / "mods"
    mods.mkdir()
    (mods / "toy.py").write_text(textwrap.dedent(TOY_MODULE))
    monkeypatch.setattr(package, "__path__", [*package.__path__, str(mods)])
    configs = tmp_path / "configs"
    shutil.copytree(nav_settings.CONFIG_DIR, configs)
    (configs / "nav" / "detector" / "toy.yaml").write_text(
        "defaults:\n  - toy_schema\n  - _self_\n\nmethod: toy\nradius_px: 20.0\nrefine: false\n"
    )
    monkeypatch.setattr(nav_settings, "CONFIG_DIR", configs)
    registry.detectors.cache_clear()
    yield
    registry.detectors.cache_clear()


def test_toy_detector_is_one_module_and_one_yaml(toy_detector):
    from crater_synth.navigation.detectors.classical import detect

    assert "toy" in registry.detectors() and "toy" in detector_options()
    nav = compose_nav(["nav/detector=toy", "nav.detector.radius_px=16"])
    assert type(nav.detector).__name__ == "ToySettings" and nav.detector.radius_px == 16.0
    image = np.random.default_rng(0).normal(size=(128, 128))
    dets, _ = detect(image, nav.detector)
    assert [(d.u, d.v, d.r) for d in dets] == [(64.0, 64.0, 16.0)]
    with pytest.raises(ConfigError, match="nav.detector.radius_pix: unknown key"):
        compose_nav(["nav/detector=toy", "nav.detector.radius_pix=3"])


@pytest.mark.parametrize(
    "group, cls, overrides, field, value",
    [
        ("nav/landmarks", LandmarksSettings, ["nav.landmarks.workers=4"], "workers", 4),
        ("nav/landmarks", LandmarksSettings, ["nav.landmarks.dem_product=shackleton_lola_200m"], "dem_product",
         "shackleton_lola_200m"),
        ("nav/detector_train", DetectorTrainSettings, ["nav.detector_train.checkpoints=[500,1000]"], "checkpoints",
         (500, 1000)),
        ("nav/detector_train", DetectorTrainSettings, ["nav.detector_train.noise=[0,0]"], "noise", (0.0, 0.0)),
    ],
)  # fmt: skip
def test_command_groups_compose_with_overrides_and_default_to_their_schemas(group, cls, overrides, field, value):
    """The landmark map's and the detector training's settings: the YAML holds the schema's defaults (no
    result changes with the move to the config), an override changes its one field."""
    assert compose_group(group, cls) == cls()
    assert getattr(compose_group(group, cls, overrides), field) == value
    nav = compose_nav(["nav/preset=synthetic", *overrides])
    assert getattr(getattr(nav, group.split("/")[1]), field) == value


@pytest.mark.parametrize(
    "group, cls, override, message",
    [
        ("nav/landmarks", LandmarksSettings, "nav.landmarks.iau_check=maybe", "nav.landmarks.iau_check=maybe: must be"),
        ("nav/landmarks", LandmarksSettings, "nav.landmarks.iau_recall_target=2", "iau_recall_target=2.0: must be in"),
        (
            "nav/detector_train",
            DetectorTrainSettings,
            "nav.detector_train.stesp=5",
            "nav.detector_train.stesp: unknown",
        ),
        ("nav/detector_train", DetectorTrainSettings, "nav.detector_train.gamma=[2,1]", "gamma=[2.0, 1.0]: must be a"),
        ("nav/detector_train", DetectorTrainSettings, "nav/detector=template", "this command's settings are nav.det"),
    ],
)
def test_command_group_bad_override_is_one_line_naming_the_key(group, cls, override, message):
    with pytest.raises(ConfigError) as err:
        compose_group(group, cls, [override])
    assert message in str(err.value) and "\n" not in str(err.value)


def test_a_detector_under_a_preset_is_one_line_and_null_drops_the_preset():
    """A preset sets its detector's own keys: another detector under it is refused in one line naming both
    (not Hydra's key error); a detector picked alone replaces a command's default preset."""
    with pytest.raises(ConfigError, match=r"^nav/detector=template: nav/preset=appearance chooses the detector"):
        compose_nav(["nav/preset=appearance", "nav/detector=template"])
    alone = compose_nav(["nav/detector=template"], defaults=["nav/preset=appearance"])
    assert (alone.detector.method, alone.preset) == ("template", None)
    dropped = compose_nav(["nav/preset=null", "nav/detector=template"], defaults=["nav/preset=appearance"])
    assert (dropped.detector.method, dropped.preset) == ("template", None)
    kept = compose_nav([], defaults=["nav/preset=appearance"])
    assert (kept.detector.method, kept.preset) == ("appearance", "appearance")


def test_the_detectors_page_lists_every_registered_detector_and_option():
    """docs/navigation/detectors.md's table has one row per option of nav/detector, and names every detector
    of the registry: a detector added as one module and one YAML shows up as a missing row here."""
    from crater_synth.paths import SOURCE_ROOT

    page = (SOURCE_ROOT / "docs" / "navigation" / "detectors.md").read_text(encoding="utf-8")
    rows = set(re.findall(r"^\| `([a-z-]+)` \|", page, re.M))
    assert rows == set(detector_options())
    assert set(registry.detectors()) <= rows
