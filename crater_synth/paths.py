"""Where the project's own files are: the one module that knows.

Packaged data (the embedded DEM layers, the landmark maps, the detector model, the crater catalogues) is
found through :mod:`importlib.resources`, so an installed wheel finds it as an editable checkout does. The
Hydra configuration tree ``configs/`` sits beside the packages in a checkout; a wheel carries a copy as
``crater_synth/configs`` (setup.py's build step). The Blender worker is a module file, started as a script
by ``blender --background``."""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def package_dir(package: str) -> Path:
    """The directory of an importable project package."""
    return Path(str(resources.files(package)))


DATA_MANIFEST = package_dir("data_manifest")
EMBEDDED_DIR = DATA_MANIFEST / "embedded"
LANDMARKS_DIR = DATA_MANIFEST / "landmarks"
MODELS_DIR = DATA_MANIFEST / "models"
CATALOGUES_DIR = DATA_MANIFEST / "catalogues"
SOURCE_ROOT = package_dir("crater_synth").parent  # the directory holding the packages (and configs/ in a checkout)
CONFIG_DIR = SOURCE_ROOT / "configs"
if not CONFIG_DIR.is_dir():  # an installed wheel: the copy inside the package
    CONFIG_DIR = package_dir("crater_synth") / "configs"
BLENDER_WORKER = package_dir("blender_gen") / "worker.py"
