"""The detectors of navigation, in one place: name -> (settings class, candidates function, description).

Each module of this package that is a detector declares one module-level ``DETECTOR``
(:class:`DetectorEntry`); :func:`detectors` discovers them, so adding a detector is writing one module
here and its settings in ``configs/nav/detector/<name>.yaml`` (docs/navigation/settings.md). ``nav-eval``'s
choices, its method descriptions, ``detect()``'s dispatch and the navigation benchmark read this registry.

A candidates function takes ``(frame, params)``: ``frame`` a :class:`CandidateInput` (the normalised
image, its padded spectrum, the radii searched and the light direction), and returns the candidate
craters as four arrays (u, v, r, score) in frame pixels; the border rule, the rim fit and the suppression
are :func:`.classical.detect`'s, shared by every detector.
"""

from __future__ import annotations

import functools
import importlib
import pkgutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from crater_core.typed_config import SettingsError
from crater_synth.errors import UserError
from crater_synth.navigation import detectors as package

ENTRY_NAME = "DETECTOR"  # the module-level name a detector module declares its entry under
# Earlier results files name the classical detector "filter": read as "classical".
LEGACY_NAMES = {"filter": "classical"}


@dataclass(frozen=True)
class CandidateInput:
    """What a candidates function may read of a frame: ``image`` (zero mean, unit deviation), ``spectrum``
    (:func:`.scalespace.spectrum` of it: (spec, shape); None for a detector that declares
    ``spectrum=False``), ``radii`` (px, :func:`.classical.scale_radii`) and ``light`` (travel azimuth, rad;
    NaN when the detector needs none and no rim fit follows)."""

    image: Any
    spectrum: Any
    radii: Any
    light: float


@dataclass(frozen=True)
class DetectorEntry:
    """One detector: ``name`` (``nav/detector=<name>``; its settings' ``method``), ``settings`` (its frozen
    settings class), ``candidates`` (None: not an image detector; it searches the map's landmarks under a
    prior, so ``detect()`` refuses it), a one-line ``description``, whether it needs the frame's Fourier
    spectrum and a light direction (``spectrum``), and for a trained detector its model file and loader."""

    name: str
    settings: type
    candidates: Callable | None
    description: str
    spectrum: bool = True
    # A trained detector's model: the file its settings name (``model_file(params)``) and its cached loader
    # (``load_model(path_str)``; a bad file raises one error line); None for a detector with no model.
    model_file: Callable | None = None
    load_model: Callable | None = None


@functools.lru_cache(maxsize=1)
def detectors() -> dict[str, DetectorEntry]:
    """Every detector declared by a module of this package, by name (discovered once; tests clear the cache
    with ``detectors.cache_clear()`` after adding a module)."""
    found: dict[str, DetectorEntry] = {}
    for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda i: i.name):
        module = importlib.import_module(f"{package.__name__}.{info.name}")
        entry = getattr(module, ENTRY_NAME, None)
        if isinstance(entry, DetectorEntry):
            if entry.name in found:
                raise RuntimeError(f"detector {entry.name!r} declared twice ({module.__name__})")
            found[entry.name] = entry
    return found


def detector(name: str) -> DetectorEntry:
    """The registry entry of detector ``name``; an unknown name is one error line listing the known ones."""
    known = detectors()
    if name not in known:
        raise UserError(f"detector {name!r}: expected one of {', '.join(sorted(known))}")
    return known[name]


def settings_from(mapping, path: str = "nav.detector"):
    """The settings of the detector a (resolved) mapping names in its ``method``, validated by its class."""
    mapping = dict(mapping or {})
    method = mapping["method"] = LEGACY_NAMES.get(mapping.get("method"), mapping.get("method"))
    if method not in detectors():
        raise SettingsError(f"{path}.method", f"must be one of {', '.join(sorted(detectors()))}", method)
    return detector(method).settings.from_config(mapping, path)


def model_files(params) -> list[Path]:
    """The model files a detector's settings name (its model, then its ensemble's; none for a detector with
    no model), which a command's outputs must never replace."""
    entry = detector(params.method)
    if not entry.model_file:
        return []
    return [Path(entry.model_file(params)), *(Path(p) for p in getattr(params, "ensemble", ()))]


def preload_model(params) -> None:
    """Load the detector's models once, before any frame: a bad model file is one error line up front."""
    entry = detector(params.method)
    if entry.load_model:
        for path in model_files(params):
            entry.load_model(str(path))
