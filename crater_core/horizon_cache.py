"""The on-disk cache of horizon maps, shared by the worker processes of a sweep.

One ``.npy`` per (terrain, sun azimuth, map levels), keyed by everything that decides its values
(:func:`cache_key`); the first process to claim an azimuth's lock file computes it
(:func:`crater_core.horizon.horizon_maps`) while the others compute other azimuths, then every
process reads the result. A torn file is recomputed; a lock of a dead process is taken over.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import time

import numpy as np

from crater_core.horizon import HORIZON_VERSION, MIN_OCCLUDER_DISTANCE_SPACINGS, PLANES, WINDOW_RATIO, horizon_maps


def cache_key(terrain_digest: str, azimuth_deg: float, halves, px: int) -> str:
    payload = json.dumps(
        {
            "v": HORIZON_VERSION,
            "terrain": terrain_digest,
            "azimuth": round(float(azimuth_deg), 9),
            "halves": [round(float(h), 6) for h in halves],
            "px": int(px),
            "window_ratio": WINDOW_RATIO,
            "min_occluder": MIN_OCCLUDER_DISTANCE_SPACINGS,
        },
        sort_keys=True,
    )
    return hashlib.sha256(payload.encode()).hexdigest()[:24]


def file_digest(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def load_cached(path: str, shape: tuple) -> np.ndarray | None:
    """The cached maps, or None when missing or unreadable (a torn file is recomputed)."""
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError):
        return None
    return arr if arr.shape == tuple(shape) and arr.dtype == np.float32 else None


def save_atomic(path: str, maps: np.ndarray) -> None:
    directory = os.path.dirname(path)
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".horizon-", suffix=".npy.tmp", dir=directory)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.save(fh, maps)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _claim(lock_path: str) -> bool:
    """Create ``lock_path`` exclusively (holding our pid); a lock of a dead process is taken over."""
    for _ in range(2):
        try:
            fd = os.open(lock_path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                with open(lock_path) as fh:
                    pid = int(fh.read().strip() or 0)
                if pid > 0:
                    os.kill(pid, 0)
                    return False  # alive: it is computing this map
            except ProcessLookupError:
                pass  # its owner died: remove the lock and try again
            except (OSError, ValueError):
                return False
            try:
                os.unlink(lock_path)
            except OSError:
                return False
            continue
        with os.fdopen(fd, "w") as fh:
            fh.write(str(os.getpid()))
        return True
    return False


def ensure_maps(
    terrain_factory,
    terrain_digest: str,
    azimuths,
    halves,
    px: int,
    cache_dir: str,
    log=None,
    poll_s: float = 0.2,
    timeout_s: float = 3600.0,
) -> dict[float, np.ndarray]:
    """{azimuth: maps} for every azimuth, computed once and shared through ``cache_dir``.

    Several workers may call this at once: each azimuth is computed by the process that first claims
    its lock file, the others compute other azimuths meanwhile and then read the result (a lock whose
    process died is taken over). ``terrain_factory()`` builds the :class:`Terrain` only if needed."""
    shape = (len(halves), len(PLANES), int(px), int(px))
    todo = sorted(set(float(a) for a in azimuths))
    out: dict[float, np.ndarray] = {}
    terrain = None
    deadline = time.monotonic() + timeout_s
    while todo:
        waiting = []
        for az in todo:
            path = os.path.join(cache_dir, cache_key(terrain_digest, az, halves, px) + ".npy")
            maps = load_cached(path, shape) if os.path.exists(path) else None
            if maps is None:
                os.makedirs(cache_dir, exist_ok=True)
                lock = path + ".lock"
                if not _claim(lock):
                    waiting.append(az)
                    continue
                try:
                    maps = load_cached(path, shape) if os.path.exists(path) else None  # finished meanwhile
                    if maps is None:
                        t0 = time.perf_counter()
                        if terrain is None:
                            terrain = terrain_factory()
                        maps = horizon_maps(terrain, az, halves, px)
                        save_atomic(path, maps)
                        if log:
                            log(f"horizon map azimuth {az:g} deg: {time.perf_counter() - t0:.2f} s")
                finally:
                    try:
                        os.unlink(lock)
                    except OSError:
                        pass
            out[az] = maps
        todo = waiting
        if todo:
            if time.monotonic() > deadline:
                raise TimeoutError(f"horizon maps {todo} still locked in {cache_dir} after {timeout_s:.0f} s")
            time.sleep(poll_s)
    return out
