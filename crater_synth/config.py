"""Compose the Hydra configuration from ``configs/`` with command-line overrides."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Sequence

from omegaconf import DictConfig, OmegaConf

from crater_synth.errors import UserError

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
REPO_ROOT = CONFIG_DIR.parent


class ConfigError(UserError):
    """A configuration value is missing or makes no sense."""


def compose(overrides: Sequence[str] = (), config_name: str = "config") -> DictConfig:
    """Compose ``configs/<config_name>.yaml`` with Hydra overrides (``key=value``, ``group=option``).

    Raises :class:`ConfigError` with Hydra's message for an unknown group option or a bad override.
    """
    from hydra import compose as hydra_compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            cfg = hydra_compose(config_name=config_name, overrides=list(overrides))
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(one_line_config_error(str(exc))) from None
    finally:
        GlobalHydra.instance().clear()
    return cfg


def one_line_config_error(msg: str) -> str:
    """Hydra's multi-line composition error as one line (an unknown group option names the choices)."""
    m = re.search(r"Could not find '([^']+)/([^'/]+)'", msg)
    if m:
        group, option = m.groups()
        avail = re.search(r"Available options in '[^']*':[ \t]*\n((?:[ \t]+\S[^\n]*\n?)+)", msg)
        choices = ", ".join(avail.group(1).split()) if avail else "see configs/" + group
        return f"unknown {group} {option!r} (override {group}={option}): choose one of {choices}"
    # The same mistake inside a list selection (crater=[a,b,...]): Hydra names no choices then.
    m = re.search(r"Could not load '([^']+)/([^'/]+)'", msg)
    if m and (CONFIG_DIR / m.group(1)).is_dir():
        group, option = m.groups()
        choices = ", ".join(sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml")))
        return f"unknown {group} {option!r} (in {group}=[...]): choose from {choices}"
    return " ".join(msg.split("\nConfig search path:")[0].split())


def resolved(cfg: DictConfig) -> dict:
    """Plain-dict copy with all interpolations resolved; a missing mandatory value (``???``) is a
    :class:`ConfigError` naming the key."""
    from omegaconf.errors import MissingMandatoryValue, InterpolationResolutionError

    try:
        return OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)  # type: ignore[return-value]
    except MissingMandatoryValue as exc:
        raise ConfigError(f"missing mandatory config value: {exc.full_key} (give it as an override)") from None
    except InterpolationResolutionError as exc:
        raise ConfigError(f"cannot resolve config value: {exc}") from None


def craters(cfg: DictConfig) -> list[dict]:
    """The crater entries selected in ``cfg.crater``, validated, in configuration order."""
    out = []
    for key, entry in resolved(cfg)["crater"].items():
        try:
            lat, lon, diam = float(entry["lat"]), float(entry["lon"]), float(entry["diameter_km"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"crater {key!r}: needs numeric lat, lon, diameter_km ({exc})") from None
        if not -90.0 <= lat <= 90.0:
            raise ConfigError(f"crater {key!r}: lat={lat} outside [-90, 90]")
        if not -360.0 <= lon <= 360.0:
            raise ConfigError(f"crater {key!r}: lon={lon} outside [-360, 360]")
        if not 0.0 < diam < 2000.0:
            raise ConfigError(f"crater {key!r}: diameter_km={diam} must be in (0, 2000)")
        out.append({"name": str(entry.get("name") or key), "lat": lat, "lon": lon, "diameter_km": diam,
                    "source": str(entry.get("source", ""))})
    if not out:
        raise ConfigError("no crater selected (crater=...)")
    return out
