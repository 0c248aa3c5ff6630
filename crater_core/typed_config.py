"""Frozen dataclasses from plain mappings: the converter behind :mod:`crater_core.settings`.

:func:`build` checks a (resolved) mapping against a dataclass's annotations -- unknown keys, missing
values (absent, or Hydra's ``???``), wrong types -- then constructs it, so that the class's own
``_check`` validates the ranges; every failure is one :class:`SettingsError` naming the full dotted key
as the user types it. Standard library only.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import types
import typing
from typing import Any, Mapping

from crater_core.errors import ContractError


class SettingsError(ContractError):
    """A configuration value has the wrong type, lies out of range, is missing or unknown.

    ``key`` is the dotted path (relative while a class validates itself, made absolute by the
    converter); the message reads ``<key>=<value>: <why>`` or ``<key>: <why>``."""

    _NO_VALUE = object()

    def __init__(self, key: str, why: str, value: Any = _NO_VALUE):
        self.key, self.why, self.value = key, why, value
        shown = "" if value is self._NO_VALUE else f"={_show(value)}"
        super().__init__(f"{key}{shown}: {why}")

    def under(self, path: str) -> "SettingsError":
        """The same error with ``path`` prefixed to its key."""
        return SettingsError(_join(path, self.key), self.why, self.value)


def _show(value: Any) -> str:
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, tuple):
        return repr(list(value))
    return str(value)


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path and key else (path or key)


def need(ok: bool, key: str, value: Any, why: str) -> None:
    if not ok:
        raise SettingsError(key, why, value)


# A name that becomes a file or folder name (a crater's terrain and renders, a sweep's out_dir, a trajectory's
# frames): letters, digits, "_" and "-", starting with a letter or digit. No "/", no "..", no dot-file, so
# nothing it names can land outside the folder it is meant for.
PLAIN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")


def need_plain_name(key: str, value: str) -> None:
    need(
        isinstance(value, str) and PLAIN_NAME.fullmatch(value) is not None,
        key,
        value,
        "must be a plain name (letters, digits, '_' and '-', at most 64, it names files and folders)",
    )


class Group:
    """Shared behaviour of the settings classes: conversion from a mapping, back to a plain dict."""

    @classmethod
    def from_config(cls, mapping: Mapping | None, path: str = ""):
        """Build and validate from a plain (resolved) mapping; errors name ``path.<key>``."""
        return build(cls, mapping or {}, path)

    def as_dict(self) -> dict:
        """Plain nested dict (tuples as lists): the resolved-mapping form older code takes."""
        return as_plain(self)

    def __post_init__(self):
        self._check()

    def _check(self) -> None:  # overridden by groups with ranges to check
        pass


def build(cls: type, data: Mapping, path: str = ""):
    """An instance of the dataclass ``cls`` from the plain mapping ``data`` (keys under ``path``).

    Unknown keys, missing values (absent, or Hydra's ``???``), wrong types and out-of-range values
    raise :class:`SettingsError` naming the full key. A :class:`ContractError` raised by a class's own
    validation (e.g. :class:`crater_core.sweep.SweepError`) passes through unchanged."""
    if not isinstance(data, Mapping):
        raise SettingsError(path, f"must be a mapping of {_type_name(cls)} keys", data)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = [k for k in data if k not in fields]
    if unknown:
        key = str(unknown[0])
        close = difflib.get_close_matches(key, list(fields), n=1)
        hint = f" (did you mean {_join(path, close[0])}?)" if close else f"; known: {', '.join(fields)}"
        raise SettingsError(_join(path, key), f"unknown key{hint}")
    kwargs = {}
    for name, f in fields.items():
        key = _join(path, name)
        if name not in data or data[name] == "???":
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise SettingsError(key, "missing mandatory config value (give it as an override)")
            continue
        kwargs[name] = _convert(data[name], hints[name], key)
    try:
        return cls(**kwargs)
    except SettingsError as exc:
        raise exc.under(path) from None
    except ContractError:
        raise
    except (TypeError, ValueError) as exc:  # e.g. HapkeParams' own range check
        raise SettingsError(path, str(exc)) from None


def _type_name(tp) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(value: Any, tp: Any, key: str) -> Any:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any:
        return value
    if origin is typing.Union or origin is types.UnionType:  # Optional[X] and X | None
        if value is None and type(None) in args:
            return None
        (inner,) = [a for a in args if a is not type(None)]
        return _convert(value, inner, key)
    if value is None:
        raise SettingsError(key, "must not be null", value)
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return build(tp, value, key)
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise SettingsError(key, "must be a list", value)
        inner = args[0] if args else Any
        return tuple(_convert(v, inner, f"{key}[{i}]") for i, v in enumerate(value))
    if origin in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise SettingsError(key, "must be a mapping", value)
        inner = args[1] if len(args) == 2 else Any
        return {str(k): _convert(v, inner, _join(key, str(k))) for k, v in value.items()}
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false"):
            return value.lower() == "true"
        raise SettingsError(key, "must be true or false", value)
    if tp is int:
        if isinstance(value, bool):
            raise SettingsError(key, "must be an integer", value)
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str):
            try:
                return int(value.strip())
            except ValueError:
                pass
        raise SettingsError(key, "must be an integer", value)
    if tp is float:
        if isinstance(value, bool):
            raise SettingsError(key, "must be a number", value)
        try:
            num = float(value)
        except (TypeError, ValueError):
            raise SettingsError(key, "must be a number", value) from None
        if not math.isfinite(num):
            raise SettingsError(key, "must be finite", value)
        return num
    if tp is str:
        if isinstance(value, (str, int, float)) and not isinstance(value, bool):
            return str(value)
        raise SettingsError(key, "must be a string", value)
    raise TypeError(f"settings field {key}: unsupported annotation {tp!r}")


def as_plain(obj: Any) -> Any:
    """Settings object -> plain nested dicts/lists (the inverse of :func:`build`)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: as_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [as_plain(v) for v in obj]
    if isinstance(obj, Mapping):
        return {k: as_plain(v) for k, v in obj.items()}
    return obj


def replace(obj, **changes):
    """``dataclasses.replace`` with dotted keys: ``replace(s, **{"render.workers": 1})``."""
    direct: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for key, value in changes.items():
        head, _, rest = key.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            direct[head] = value
    for head, sub in nested.items():
        direct[head] = replace(getattr(obj, head), **sub)
    return dataclasses.replace(obj, **direct)
