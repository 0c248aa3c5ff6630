"""Typed settings (crater_core/settings.py): the one validated form of the configuration."""

import dataclasses
import pickle
import re
from pathlib import Path

import pytest

from crater_core.settings import (
    GROUPS,
    CraterSettings,
    DetailSettings,
    RenderSettings,
    Settings,
    SettingsError,
    SweepSettings,
    build,
    replace,
)
from crater_synth.config import (
    CONFIG_DIR,
    PRESET_GROUPS,
    ConfigError,
    compose,
    compose_settings,
    load_settings,
    resolved,
)


@pytest.fixture(scope="module")
def default():
    return load_settings([])


@pytest.mark.parametrize(
    "option", sorted(f"{p.parent.name}={p.stem}" for p in CONFIG_DIR.glob("*/*.yaml") if p.parent.name != "crater")
)
def test_every_group_option_composes_and_validates(option):
    cfg, s = compose_settings([option])
    assert isinstance(s, Settings)
    assert s.as_dict() == resolved(cfg)  # the typed settings hold exactly the composed values


def test_every_crater_entry_composes():
    names = sorted(p.stem for p in (CONFIG_DIR / "crater").glob("*.yaml") if p.stem != "custom")
    s = load_settings([f"crater=[{','.join(names)}]"])
    assert [c.name for c in s.craters] == names
    assert all(isinstance(c, CraterSettings) and c.source for c in s.craters)


def test_every_yaml_names_its_schema():
    for p in CONFIG_DIR.glob("*/*.yaml"):
        if p.parent.name in PRESET_GROUPS:
            assert p.read_text().startswith("# @package _global_"), p
            continue
        assert f"- {p.parent.name}_schema" in p.read_text(), p
    # configs/nav/ is navigation's own tree (configs/navigation.yaml composes it): its groups are checked below.
    assert set(GROUPS) | PRESET_GROUPS | {"nav"} == {p.name for p in CONFIG_DIR.iterdir() if p.is_dir()}


def test_every_navigation_yaml_names_its_schema():
    """Each option of a nav group names its typed schema (a detector option its detector's), and each
    navigation preset is a global package file, as the experiment presets of configs/config.yaml."""
    files = sorted((CONFIG_DIR / "nav").glob("*/*.yaml"))
    assert files
    for p in files:
        text = p.read_text()
        if p.parent.name == "preset":
            assert text.startswith("# @package _global_"), p
        elif p.parent.name == "detector":
            assert re.search(r"^  - [a-z_]+_schema$", text, re.M), p
        else:
            assert f"- {p.parent.name}_schema" in text, p


def test_experiment_chosen_is_the_chosen_configuration():
    chosen = load_settings(["experiment=chosen"])
    spelled_out = load_settings(["sweep=demo_physical_noon", "train=sim2real"])
    assert chosen.as_dict() == spelled_out.as_dict()
    # later overrides still win over the preset
    assert load_settings(["experiment=chosen", "train.max_epochs=3"]).train.max_epochs == 3
    with pytest.raises(ConfigError, match="unknown experiment 'nope'"):  # a typo is an error, never ignored
        load_settings(["experiment=nope"])


def test_types_and_values(default):
    assert isinstance(default.render, RenderSettings) and default.render.samples == 16
    assert isinstance(default.terrain.detail, DetailSettings) and default.terrain.detail.seed == default.seed
    assert default.sweep.grid.shape == (1, 2, 1, 2)
    assert default.sensor.exposure_white_frac == (0.6, 1.05)  # lists become tuples: frozen all the way down
    with pytest.raises(dataclasses.FrozenInstanceError):
        default.render.samples = 4  # type: ignore[misc]
    assert pickle.loads(pickle.dumps(default)) == default  # travels to Dask workers as it is


def test_plain_mapping_conversion_names_the_key(default):
    plain = default.as_dict()
    assert Settings.from_config(plain) == default
    plain["render"]["samples"] = 0
    with pytest.raises(SettingsError, match=r"^render\.samples=0: must be >= 1$"):
        Settings.from_config(plain)
    plain = default.as_dict()
    plain["crater"]["shackleton"]["lat"] = "south"
    with pytest.raises(SettingsError, match=r"^crater\.shackleton\.lat='south': must be a number$"):
        Settings.from_config(plain)
    plain = default.as_dict()
    del plain["hapke"]["w"]
    with pytest.raises(SettingsError, match=r"^hapke\.w: missing mandatory config value"):
        Settings.from_config(plain)
    plain = default.as_dict()
    plain["sweep"]["sun_elevation"]["count"] = True
    with pytest.raises(SettingsError, match=r"^sweep\.sun_elevation\.count=True: must be an integer$"):
        Settings.from_config(plain)


def test_replace_with_dotted_keys_validates(default):
    s = replace(default, **{"render.workers": 1, "launcher.shard": "1/4"})
    assert s.render.workers == 1 and s.launcher.shard_slice == (1, 4) and s.sweep == default.sweep
    with pytest.raises(SettingsError, match="shard"):
        replace(default, **{"launcher.shard": "4/4"})


def test_duplicate_crater_names_are_refused():
    with pytest.raises(ConfigError, match=r"crater\.custom\.name='shackleton': repeats crater\.shackleton's name"):
        compose(
            [
                "crater=[shackleton,custom]",
                "crater.custom.name=shackleton",
                "crater.custom.lat=-89",
                "crater.custom.lon=0",
                "crater.custom.diameter_km=20",
            ]
        )


def test_a_new_key_is_one_field(monkeypatch):
    """How to add a key (the module docstring): a field with a type; the schema follows."""
    from crater_synth import config

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Render2(RenderSettings):
        shadow_method: str = "horizon"

        def _check(self):
            super()._check()
            if self.shadow_method not in ("horizon", "litmap"):
                raise SettingsError("shadow_method", "must be horizon or litmap", self.shadow_method)

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Settings2(Settings):
        render: Render2

    monkeypatch.setitem(GROUPS, "render", Render2)
    monkeypatch.setattr(config, "Settings", Settings2)
    monkeypatch.setattr(config, "_TWINS", {})
    _, s = config.compose_settings(["render.shadow_method=litmap"])
    assert s.render.shadow_method == "litmap"
    with pytest.raises(ConfigError, match=r"^render\.shadow_method='sky': must be horizon or litmap$"):
        config.compose_settings(["render.shadow_method=sky"])
    with pytest.raises(ConfigError, match=r"^render\.shadow_methd: unknown key \(did you mean render\.shadow_method"):
        config.compose_settings(["render.shadow_methd=litmap"])


def test_build_rejects_non_mappings(default):
    with pytest.raises(SettingsError, match=r"^sweep\.sigma=3: must be a mapping"):
        build(SweepSettings, {**default.sweep.as_dict(), "sigma": 3}, "sweep")


def test_settings_module_imports_only_the_standard_library_and_the_core():
    import ast
    import sys

    import crater_core.settings as mod

    tree = ast.parse(Path(mod.__file__).read_text())
    names = {
        n.module if isinstance(n, ast.ImportFrom) else a.name
        for n in ast.walk(tree)
        if isinstance(n, (ast.Import, ast.ImportFrom))
        for a in getattr(n, "names", [])
    }
    tops = {name.split(".")[0] for name in names if name}
    assert tops <= set(sys.stdlib_module_names) | {"crater_core"}, tops
