"""One Cycles render of the current scene, returned as numpy passes.

bpy offers no direct access to render-result pixels, so each render is written (uncompressed,
multi-part multilayer EXR, float32) to a per-process scratch file (in /dev/shm when available) and
read back with ``crater_core.exr.read_multilayer``. Costs ~1-3 ms for a 210^2 crop.
"""

from __future__ import annotations

import os
import tempfile
import time

import bpy
import numpy as np

from crater_core.exr import read_multilayer

_SCRATCH = None


_PREFIX = "crater_synth_render_"


def _remove_stale(directory: str) -> None:
    """Delete scratch files of worker processes that no longer exist (e.g. killed with -9)."""
    for name in os.listdir(directory):
        if not (name.startswith(_PREFIX) and name.endswith(".exr")):
            continue
        try:
            pid = int(name[len(_PREFIX):].split("_", 1)[0])
        except ValueError:
            continue
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            try:
                os.unlink(os.path.join(directory, name))
            except OSError:
                pass
        except OSError:
            pass  # alive but not ours (EPERM)


def scratch_path() -> str:
    """Per-process scratch file for Cycles' output (a G-buffer or direct render of one crop: a few MB)."""
    global _SCRATCH
    if _SCRATCH is None:
        use_shm = os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK)
        directory = "/dev/shm" if use_shm else tempfile.gettempdir()
        _remove_stale(directory)
        fd, _SCRATCH = tempfile.mkstemp(prefix=f"{_PREFIX}{os.getpid()}_", suffix=".exr", dir=directory)
        os.close(fd)
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
    return read_multilayer(path), t_render
