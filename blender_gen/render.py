"""One Cycles render of the current scene, returned as numpy passes.

bpy offers no direct access to render-result pixels, so each render is written (uncompressed,
multi-part multilayer EXR, float32) to a per-process scratch file (in /dev/shm when available;
``crater_core.files`` names it and removes those of dead processes) and
read back with ``crater_core.exr.read_multilayer``. Costs ~1-3 ms for a 210^2 crop.
"""

from __future__ import annotations

import os
import time

import bpy
import numpy as np

from blender_gen import compat
from crater_core.exr import read_multilayer
from crater_core.files import SCRATCH_PREFIXES, remove_stale_scratch, scratch_file

_SCRATCH = None


def scratch_path() -> str:
    """Per-process scratch file for Cycles' output (a G-buffer or direct render of one crop: a few MB),
    named after the pid so that a host or a later worker can remove those of dead processes (kill -9)."""
    global _SCRATCH
    if _SCRATCH is None:
        remove_stale_scratch()
        _SCRATCH = scratch_file(SCRATCH_PREFIXES[0])
    return _SCRATCH


def cleanup() -> None:
    global _SCRATCH
    if _SCRATCH is not None:
        try:
            os.unlink(_SCRATCH)
        except OSError:
            pass
        _SCRATCH = None


def render_passes(scene) -> tuple[dict[str, np.ndarray], float]:
    """Render the scene's current camera/border; returns (passes, seconds spent in Cycles)."""
    path = scratch_path()
    scene.render.filepath = path
    scene.render.use_file_extension = False
    t0 = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    t_render = time.perf_counter() - t0
    return compat.canonical_passes(read_multilayer(path)), t_render
