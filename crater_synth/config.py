"""Compose the Hydra configuration from ``configs/`` with command-line overrides, validated once.

Hydra composes ``configs/config.yaml`` against structured-config schemas derived from the typed
settings of :mod:`crater_core.settings` (``<group>_schema`` in Hydra's ConfigStore; each yaml file
names its schema in its ``defaults``), so composition itself rejects a wrong type or an unknown key.
The result is then converted once into a :class:`~crater_core.settings.Settings`, whose classes check
the ranges. Every failure is one :class:`ConfigError` line naming the key as the user typed it.

Functions below the CLI, ``train/`` included, take the :class:`Settings`; :func:`compose` still returns
the (validated) ``DictConfig`` for the code that reads the raw mapping for its own keys (report, loop,
experiments, validation fingerprints).
"""

from __future__ import annotations

import dataclasses
import difflib
import re
import shlex
import typing
from typing import Any, Dict, List, Mapping, Optional, Sequence

from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from crater_core.errors import ContractError
from crater_core.settings import GROUPS, Settings, SettingsError, as_plain
from crater_core.typed_config import build
from crater_synth.errors import ConfigError
from crater_synth.paths import CONFIG_DIR, SOURCE_ROOT

# Config files in configs/crater/ that are not catalogue entries (the template for any other crater).
NOT_CATALOGUE_ENTRIES = frozenset({"custom"})


def catalogue_names() -> list[str]:
    """Every crater of the catalogue (``configs/crater/<name>.yaml``, except the ``custom`` template), sorted:
    the one list the catalogue check, the validation protocol and the landmark map read."""
    return sorted(p.stem for p in (CONFIG_DIR / "crater").glob("*.yaml") if p.stem not in NOT_CATALOGUE_ENTRIES)


REPO_ROOT = SOURCE_ROOT
# Groups of named presets (``# @package _global_``): each file overrides other groups' options and has no
# schema of its own; every key it sets is validated by the groups it sets.
PRESET_GROUPS = frozenset({"experiment"})
# Groups that configs/config.yaml does not select by default (only the commands that need them read
# them; ``Settings.<group>`` is None otherwise): ``group=option`` selects one (Hydra's ``+group=option``).
OPTIONAL_GROUPS = frozenset({"trajectory", "procedural", "detection"})
ROOT_SCHEMA = "settings_schema"
SCHEMA_SUFFIX = "_schema"

__all__ = [
    "CONFIG_DIR",
    "REPO_ROOT",
    "ConfigError",
    "as_settings",
    "compose",
    "compose_settings",
    "craters",
    "load_settings",
    "one_line_config_error",
    "resolved",
    "settings_from",
    "sweep_error",
]


# ------------------------------------------------------------------------------------------------
# Schemas: mutable twins of the frozen settings classes, registered in Hydra's ConfigStore
# ------------------------------------------------------------------------------------------------
_TWINS: dict[type, type] = {}


def _schema_type(tp: Any) -> Any:
    """The annotation OmegaConf validates against: tuples become lists, settings classes their twins."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Union:
        inner = [a for a in args if a is not type(None)]
        if len(inner) != 1 or typing.get_origin(inner[0]) is dict:
            # An optional mapping stays untyped for OmegaConf: its None node cannot take
            # OmegaConf.update(..., {...}) (the loop and Figure 6 set train.select so); the settings
            # conversion checks its keys and values all the same.
            return Any
        return Optional[_schema_type(inner[0])]
    if origin in (tuple, list):
        return List[_schema_type(args[0]) if args else Any]
    if origin is dict:
        return Dict[str, _schema_type(args[1])]
    if dataclasses.is_dataclass(tp):
        return schema_class(tp)
    return tp


def schema_class(cls: type) -> type:
    """A mutable dataclass with the fields, types and defaults of the frozen settings class ``cls``.

    OmegaConf turns a frozen dataclass into a read-only node, into which Hydra cannot merge the yaml
    values: the schema is this twin, generated, so the settings classes stay the one definition."""
    if cls not in _TWINS:
        hints = typing.get_type_hints(cls)
        specs = []
        for f in dataclasses.fields(cls):
            tp = _schema_type(hints[f.name])
            if f.default is not dataclasses.MISSING:
                value = f.default
                default = (
                    dataclasses.field(default_factory=lambda v=value: list(v))
                    if isinstance(value, tuple)
                    else dataclasses.field(default=value)
                )
            elif f.default_factory is not dataclasses.MISSING or typing.get_origin(tp) is dict:
                default = (
                    dataclasses.field(default_factory=dict)
                    if typing.get_origin(tp) is dict
                    else dataclasses.field(default_factory=lambda c=f.default_factory: _plain_default(c()))
                )
            else:
                default = dataclasses.field(default=MISSING)
            specs.append((f.name, tp, default))
        _TWINS[cls] = dataclasses.make_dataclass(cls.__name__, specs, kw_only=True)
    return _TWINS[cls]


def _plain_default(value):
    return as_plain(value)


_REGISTERED: list = []


def register_schemas() -> None:
    """Store ``settings_schema`` (the root) and ``<group>_schema`` for every group of configs/ in Hydra's
    (process-wide) ConfigStore; again only when the settings classes changed (tests extend them)."""
    key = (Settings, tuple(GROUPS.items()))
    if _REGISTERED == [key]:
        return
    _REGISTERED[:] = [key]
    cs = ConfigStore.instance()
    cs.store(name=ROOT_SCHEMA, node=schema_class(Settings))
    for group, cls in GROUPS.items():
        cs.store(group=group, name=f"{group}{SCHEMA_SUFFIX}", node=schema_class(cls))


# ------------------------------------------------------------------------------------------------
# Composition
# ------------------------------------------------------------------------------------------------
def compose_settings(overrides: Sequence[str] = (), config_name: str = "config") -> tuple[DictConfig, Settings]:
    """Compose ``configs/<config_name>.yaml`` with Hydra overrides (``key=value``, ``group=option``) and
    validate it: ``(DictConfig, Settings)``. Any bad value or unknown key is a :class:`ConfigError`."""
    check_keys(overrides)
    refuse_sweeps(overrides)
    overrides = [f"+{o}" if o.partition("=")[0] in OPTIONAL_GROUPS else o for o in overrides]
    register_schemas()
    cfg = hydra_config(config_name, overrides)
    return cfg, settings_from(cfg)


def hydra_config(
    config_name: str | None, overrides: Sequence[str], config_dir=CONFIG_DIR, with_hydra: bool = False
) -> DictConfig:
    """Hydra's composition of ``<config_dir>/<config_name>.yaml`` with ``overrides`` (``with_hydra``: its
    ``hydra`` node too), the one place Hydra is initialised: a bad value or an unknown key is one
    :class:`ConfigError` line (its callers refuse an override with no key or several values first)."""
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
            return hydra_compose(config_name=config_name, overrides=list(overrides), return_hydra_config=with_hydra)
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(one_line_config_error(exc, overrides)) from None
    finally:
        GlobalHydra.instance().clear()


def check_keys(overrides: Sequence[str]) -> None:
    """One :class:`ConfigError` line for an override with nothing before its ``=`` (``=5``), which Hydra
    itself fails on with a bare ValueError."""
    for o in overrides:
        key, eq, _ = o.lstrip("+~").partition("=")
        if eq and not key.strip():
            raise ConfigError(f"override {o!r} names no key: write key=value (e.g. render.samples=4)")


def compose_plain(config_name: str | None, overrides: Sequence[str], config_dir=CONFIG_DIR) -> tuple[dict, dict]:
    """The resolved composition of ``<config_dir>/<config_name>.yaml`` (None: only the groups the overrides
    add with ``+group=option``) and the option each group took; the schemas must be in the ConfigStore
    already. Any bad value or unknown key is one :class:`ConfigError` line naming it."""
    check_keys(overrides)
    refuse_sweeps(overrides)
    cfg = hydra_config(config_name, overrides, config_dir, with_hydra=True)
    choices = dict(cfg.hydra.runtime.choices)
    OmegaConf.set_struct(cfg, False)
    cfg.pop("hydra")
    return resolved(cfg), choices


def compose_group(group: str, cls: type, overrides: Sequence[str] = (), option: str = "default"):
    """The settings ``cls`` of one config group (``configs/<group>/<option>.yaml``, e.g. ``nav/landmarks``)
    with the overrides a command takes, all of them keys of that group (``nav.landmarks.workers=4``):
    a command with one group of settings refuses any other key. Errors: one :class:`ConfigError` line."""

    refuse_sweeps(overrides)
    prefix = group.replace("/", ".")
    bad = [o for o in overrides if not o.lstrip("+~").startswith(prefix + ".")]
    if bad:
        raise ConfigError(f"{bad[0]}: this command's settings are {prefix}.<key>=<value>")
    ConfigStore.instance().store(group=group, name=f"{group.rsplit('/', 1)[-1]}{SCHEMA_SUFFIX}", node=schema_class(cls))
    plain, _ = compose_plain(None, [f"+{group}={option}", *overrides])
    for part in group.split("/"):
        plain = plain[part]
    try:
        return build(cls, plain, prefix)
    except SettingsError as exc:
        raise ConfigError(str(exc)) from None


def compose(overrides: Sequence[str] = (), config_name: str = "config") -> DictConfig:
    """The validated, composed configuration as a ``DictConfig`` (see :func:`compose_settings`)."""
    return compose_settings(overrides, config_name)[0]


def load_settings(overrides: Sequence[str] = ()) -> Settings:
    """The typed settings of ``configs/config.yaml`` with these overrides (what every command runs on)."""
    return compose_settings(overrides)[1]


def settings_from(cfg: DictConfig | Mapping) -> Settings:
    """Convert a composed (or plain, resolved) configuration once into :class:`Settings`."""
    plain = resolved(cfg) if isinstance(cfg, DictConfig) else cfg
    try:
        return Settings.from_config(plain)
    except (SettingsError, ContractError) as exc:
        raise ConfigError(str(exc)) from None


def as_settings(cfg: Settings | DictConfig | Mapping) -> Settings:
    """``cfg`` itself when it is already :class:`Settings`, else its conversion (the boundary of the
    functions that still accept the raw mapping from callers that have not moved to settings)."""
    return cfg if isinstance(cfg, Settings) else settings_from(cfg)


def resolved(cfg: DictConfig) -> dict:
    """Plain-dict copy with all interpolations resolved; ``???`` values are kept (the settings
    conversion names them); an interpolation that cannot be resolved is a :class:`ConfigError`."""
    try:
        return OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)  # type: ignore[return-value]
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None)
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConfigError(
            f"{key}: cannot resolve the value ({first})" if key else f"cannot resolve a config value: {first}"
        ) from None


def craters(cfg: Settings | DictConfig | Mapping) -> list[dict]:
    """The selected crater entries as plain dicts (name, lat, lon, diameter_km, source), in order."""
    return [c.as_dict() for c in as_settings(cfg).craters]


# ------------------------------------------------------------------------------------------------
# Hydra/OmegaConf errors as one line naming the key as the user typed it
# ------------------------------------------------------------------------------------------------
_EXPECTED = {
    "Integer": "must be an integer",
    "Float": "must be a number",
    "Boolean": "must be true or false",
    "String": "must be a string",
}


def one_line_config_error(exc: BaseException | str, overrides: Sequence[str] = ()) -> str:
    """Hydra's (often multi-line) composition error as one line."""
    msg = str(exc)
    m = re.search(r"Could not find '([^']+)/([^'/]+)'", msg)
    if m:
        group, option = m.groups()
        avail = re.search(r"Available options in '[^']*':[ \t]*\n((?:[ \t]+\S[^\n]*\n?)+)", msg)
        choices = ", ".join(_user_options(group, avail.group(1).split() if avail else None))
        return f"unknown {group} {option!r} (override {group}={option}): choose one of {choices}"
    m = re.search(r"Could not load '([^']+)/([^'/]+)'", msg)  # the same mistake inside crater=[a,b,...]
    if m and (CONFIG_DIR / m.group(1)).is_dir():
        group, option = m.groups()
        return f"unknown {group} {option!r} (in {group}=[...]): choose from {', '.join(_user_options(group, None))}"
    cause = exc.__cause__ if isinstance(exc, BaseException) else None
    full_key = getattr(cause, "full_key", None) or getattr(exc, "full_key", None)
    if full_key:
        why = str(cause or exc).splitlines()[0]
        if re.match(r"Key '[^']+' not in '", why) or "Could not override" in msg or "Could not append" in msg:
            return f"{full_key}: unknown key{_suggest(full_key)}"
        conv = re.match(r"Value '(.*)' of type '[^']+' could not be converted to (\w+)", why) or re.match(
            r"Value '(.*)' is not a valid (bool)", why
        )
        if conv:
            kind = "Boolean" if conv.group(2) == "bool" else conv.group(2)
            why = _EXPECTED.get(kind, f"must be of type {kind}")
        if re.match(r"field '[^']+' is not Optional", why) or "is not Optional" in why:
            why = "must not be null"
        if "is not a ListConfig, list or tuple" in why:
            why = "must be a list, e.g. [a,b]"
        typed = _override_for(full_key, overrides)
        element = re.search(r"\[(\d+)\]$", full_key)
        if typed and element and conv:
            return f"{typed}: element {element.group(1)} ({conv.group(1)!r}) {why}"
        if typed:
            return f"{typed}: {why}"
        value = f"={conv.group(1)}" if conv else ""
        return f"{full_key}{value}: {why} (in configs/)"
    hint = _quoting_hint(msg, overrides)
    if hint:
        return hint
    return " ".join(msg.split("\nConfig search path:")[0].split())


# Hydra's override grammar errors: a value with spaces (split by the shell) or special characters.
_GRAMMAR_ERRORS = ("missing EQUAL", "mismatched input", "token recognition error", "extraneous input", "no viable")


def _quoting_hint(msg: str, overrides: Sequence[str]) -> str | None:
    """One line for an override Hydra cannot parse, with the quoting that fixes it: a path with
    spaces left unquoted in the shell arrives as two arguments (``out_dir=/my`` and ``data``); one with
    spaces or ``()[]{},'"`` inside one argument needs quotes for Hydra itself."""
    if not any(e in msg for e in _GRAMMAR_ERRORS):
        return None
    overrides = list(overrides)
    m = re.search(r"Error parsing override '([^']*)'\s+missing EQUAL", msg)
    if m and m.group(1) in overrides:
        i = overrides.index(m.group(1))
        if i > 0 and "=" in overrides[i - 1]:
            joined = f"{overrides[i - 1]} {m.group(1)}"
            return (
                f"override {m.group(1)!r} is not key=value: if it is the rest of the value before it (a path "
                f'with spaces), quote the whole override, e.g. "{joined}"'
            )
        return f"override {m.group(1)!r} is not key=value (e.g. out_dir=/data/x)"

    parser = OverridesParser.create()
    for o in overrides:
        try:
            parser.parse_override(o)
        except Exception as exc:  # noqa: BLE001 - any grammar error of this one override
            key, _, value = o.partition("=")
            why = " ".join(str(exc).split("See https://")[0].split())
            return (
                f"{o}: Hydra cannot parse the value ({why}): quote a value holding spaces or ()[]{{}},'\" "
                f"for Hydra, e.g. \"{key}='{value}'\""
            )
    return None


def sweep_error(overrides: Sequence[str], command: str = "crater-synth <command>") -> str | None:
    """One line for the first override that asks for several values (``key=a,b``, ``range(...)``,
    ``choice(...)``, ``glob(...)``, ...), i.e. Hydra's multirun, or None. A command runs one configuration,
    so several values are several runs: the line spells out the shell loop over ``command`` with the
    other overrides as typed. A list (``key=[a,b]``) or a quoted value holding a comma is one value."""
    parser = OverridesParser.create()
    overrides = list(overrides)
    for i, o in enumerate(overrides):
        try:
            parsed = parser.parse_override(o)
        except Exception:  # noqa: BLE001 - a grammar error is composition's to report, with its quoting hint
            continue
        if not parsed.is_sweep_override():
            continue
        try:  # choice and range sweeps can be listed; glob needs the group's options, interval is continuous
            values = " ".join(shlex.quote(v) for v in parsed.sweep_string_iterator())
        except HydraException:
            values = "VALUE1 VALUE2"
        run = [*map(shlex.quote, overrides[:i]), f"{o.partition('=')[0]}=$v", *map(shlex.quote, overrides[i + 1 :])]
        return (
            f"{o}: several values mean several runs, and a command runs one configuration: "
            f"run one per value, e.g. for v in {values}; do {command} {' '.join(run)}; done "
            f"(a list is key=[a,b]; a value holding a comma is quoted: \"key='a,b'\")"
        )
    return None


def refuse_sweeps(overrides: Sequence[str], command: str = "crater-synth <command>") -> None:
    """Raise :class:`ConfigError` with :func:`sweep_error`'s line when an override asks for several runs."""
    error = sweep_error(overrides, command)
    if error:
        raise ConfigError(error)


def _user_options(group: str, listed: list[str] | None) -> list[str]:
    """A group's selectable options (the schemas Hydra also lists are not options)."""
    names = listed if listed is not None else [p.stem for p in (CONFIG_DIR / group).glob("*.yaml")]
    return sorted(n for n in names if not n.endswith(SCHEMA_SUFFIX))


def _override_for(full_key: str, overrides: Sequence[str]) -> str | None:
    """The override (as typed) that sets ``full_key`` or the list holding it."""
    base = re.sub(r"\[\d+\]$", "", full_key)
    for o in reversed(list(overrides)):
        key = o.split("=", 1)[0].lstrip("+~")
        if key == base or key == full_key:
            return o.lstrip("+~")
    return None


def _suggest(full_key: str) -> str:
    """`` (did you mean <key>?)`` for a misspelt key, from the settings classes' fields."""
    parts = full_key.split(".")
    cls: Any = Settings
    i = 0
    while i < len(parts) - 1:
        tp = typing.get_type_hints(cls).get(parts[i]) if dataclasses.is_dataclass(cls) else None
        if tp is None:
            return ""
        if typing.get_origin(tp) is typing.Union:
            tp = next(a for a in typing.get_args(tp) if a is not type(None))
        if typing.get_origin(tp) is dict:  # crater.<entry>.<key>: the next part names an entry
            tp, i = typing.get_args(tp)[1], i + 1
        cls, i = tp, i + 1
    if not dataclasses.is_dataclass(cls):
        return ""
    close = difflib.get_close_matches(parts[-1], [f.name for f in dataclasses.fields(cls)], n=1)
    return f" (did you mean {'.'.join(parts[:-1] + [close[0]])}?)" if close else ""
