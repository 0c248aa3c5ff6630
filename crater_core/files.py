"""Filesystem facts every layer needs to report clearly: writable directories, a full disk, scratch files.

Standard library only. Errors are :class:`PathError` (a :class:`~crater_core.errors.ContractError`), so
the CLI prints them as one ``error:`` line naming the configuration key or the path.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import tempfile
from pathlib import Path

from crater_core.errors import ContractError

# errno values that mean "the disk (or the user's quota) is full".
DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
# Per-process scratch files (Cycles output, EXR encoding) are named <prefix><pid>_<random>.exr, so
# that those of dead processes can be found and removed (crater_core.files.remove_stale_scratch).
SCRATCH_PREFIXES = ("crater_synth_render_", "crater_synth_exr_")
_SCRATCH_RE = re.compile(r"^(?:%s)(\d+)_" % "|".join(map(re.escape, SCRATCH_PREFIXES)))


class PathError(ContractError):
    """A directory cannot be created or written, or the disk is full."""


def umask() -> int:
    """The process umask (read without changing it for good)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _obstacle(path: Path) -> str:
    """Why ``path`` cannot be a directory: the first existing ancestor that is not one."""
    for parent in [path, *path.parents]:
        if parent.exists() or parent.is_symlink():
            if not parent.is_dir():
                return (
                    f"{parent} is a regular file, not a directory"
                    if parent.is_file()
                    else f"{parent} is not a directory"
                )
            return ""
    return ""


def check_dir_path(path: str | os.PathLike, key: str | None = None) -> Path:
    """Refuse, without creating anything, a ``path`` that cannot become a directory because it, or
    one of its ancestors, is a file: the :class:`PathError` names ``key`` as :func:`ensure_writable_dir`
    does. For checks up front, before work whose output would go there."""
    p = Path(path)
    why = _obstacle(p)
    if why:
        raise PathError(f"{f'{key}={path}' if key else str(path)}: cannot create the directory: {why}")
    return p


def ensure_writable_dir(path: str | os.PathLike, key: str | None = None) -> Path:
    """Create ``path`` (and its parents) if needed and check that files can be created in it.

    ``key`` is the configuration key the path came from (``out_dir``, ``data_dir``, ``run_dir``...):
    the :class:`PathError` names it as the user typed it, e.g.
    ``data_dir=/x/file/data: cannot create the directory: /x/file is a regular file, not a directory``."""
    p = check_dir_path(path, key)
    label = f"{key}={path}" if key else str(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=p)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise PathError(
            f"{label}: {'not a writable directory' if p.is_dir() else 'cannot create the directory'}: "
            f"{os_error_text(exc)}"
        ) from None
    return p


def free_bytes(path: str | os.PathLike) -> int:
    """Free bytes (for an unprivileged user) on the filesystem holding ``path`` or its nearest ancestor."""
    p = Path(path)
    for candidate in [p, *p.parents]:
        if candidate.exists():
            return shutil.disk_usage(candidate).free
    return 0


def size_text(n: float) -> str:
    """Bytes as ``1.23 MB`` (decimal units)."""
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.2f} {unit}"
    return f"{int(n)} B"


def is_disk_full(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS


def disk_full_message(path: str | os.PathLike, exc: OSError | None = None) -> str:
    """``disk full (ENOSPC): cannot write <path> (<free> free in <dir>)``."""
    code = errno.errorcode.get(exc.errno, "ENOSPC") if exc is not None and exc.errno else "ENOSPC"
    where = Path(path).parent
    return f"disk full ({code}): cannot write {path} ({size_text(free_bytes(where))} free in {where})"


def os_error_text(exc: OSError) -> str:
    """One line for an OSError: the disk-full message, or ``<strerror>: <filename>``."""
    name = exc.filename if exc.filename is not None else None
    if is_disk_full(exc) and name is not None:
        return disk_full_message(name, exc)
    text = exc.strerror or str(exc)
    return f"{text}: {name}" if name is not None else text


def scratch_dir() -> str:
    """Where per-process scratch files go: /dev/shm (memory) when writable, else the temp directory."""
    if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK):
        return "/dev/shm"
    return tempfile.gettempdir()


def scratch_file(prefix: str, suffix: str = ".exr", directory: str | None = None) -> str:
    """A new empty scratch file ``<prefix><pid>_<random><suffix>`` (prefix from :data:`SCRATCH_PREFIXES`)."""
    fd, path = tempfile.mkstemp(prefix=f"{prefix}{os.getpid()}_", suffix=suffix, dir=directory or scratch_dir())
    os.close(fd)
    return path


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # alive, another user's
    return True


def remove_stale_scratch(pids: "set[int] | None" = None, directory: str | None = None) -> list[str]:
    """Delete scratch files of processes that no longer run (or, with ``pids``, of exactly those
    processes once they have ended: a host cleaning up after the workers it stopped). Returns the paths
    removed."""
    directory = directory or scratch_dir()
    removed: list[str] = []
    try:
        names = os.listdir(directory)
    except OSError:
        return removed
    for name in names:
        m = _SCRATCH_RE.match(name)
        if not m:
            continue
        pid = int(m.group(1))
        if (pids is not None and pid not in pids) or _alive(pid):
            continue
        try:
            os.unlink(os.path.join(directory, name))
            removed.append(os.path.join(directory, name))
        except OSError:
            pass
    return removed
