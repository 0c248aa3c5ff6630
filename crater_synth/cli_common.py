"""Pieces shared by every subcommand: trailing overrides, one-line errors, warnings, signals.

:func:`user_errors` wraps each command so that
- bad input (:class:`UserError`, :class:`ContractError`) and environment errors (``OSError``: a full
  disk, a permission) end it with ONE ``error: ...`` line on stderr and exit status 2;
- SIGTERM, SIGINT and SIGHUP (the terminal closed) unwind it like an error (its ``finally`` blocks stop
  the Blender workers and remove scratch files), then print one ``error: interrupted ...`` line and
  exit 143 / 130 / 129;
- warnings that libraries raise through Python's :mod:`warnings` (e.g. rasterio's) are held back and
  printed as ``warning:`` lines when the command succeeds; when it fails, the error line is the only
  one (a library warning about the very input that failed would only bury it).
"""

from __future__ import annotations

import functools
import signal
import sys
import threading
import warnings

import click

from crater_core.errors import ContractError
from crater_core.files import os_error_text
from crater_synth.config import sweep_error
from crater_synth.errors import STOP_SIGNALS, Interrupted, UserError

_EXIT_BAD_INPUT = 2


def _one_run(ctx: click.Context, _param, overrides: tuple[str, ...]) -> tuple[str, ...]:
    """Refuse Hydra's multirun (``key=a,b``, ``range(...)``, ...) while parsing, naming this command in
    the shell loop that runs one value after another (composition refuses it too, for callers from Python)."""
    names, c = [], ctx
    while c.parent is not None:  # the root's name is however the program was started; the project's is fixed
        names.append(c.info_name)
        c = c.parent
    error = sweep_error(overrides, " ".join(["crater-synth", *reversed(names)]))
    if error:
        _fail(error)
    return overrides


OVERRIDES = click.argument("overrides", nargs=-1, metavar="[OVERRIDES]...", callback=_one_run)


def warn(message: str) -> None:
    """One ``warning: ...`` line on stderr: a legal run that is almost surely a mistake."""
    click.echo(f"warning: {message}", err=True)


def _raise_interrupted(signum, _frame):
    name = signal.Signals(signum).name
    raise Interrupted(signum, f"interrupted by {name}: stopped; rerun the same command to resume")


class StopSignals:
    """SIGTERM/SIGINT/SIGHUP raise :class:`Interrupted` in the main thread while a command runs."""

    def __enter__(self):
        self.old = {}
        if threading.current_thread() is threading.main_thread():
            for s in STOP_SIGNALS:
                self.old[s] = signal.signal(s, _raise_interrupted)
        return self

    def __exit__(self, *exc):
        for s, h in self.old.items():
            signal.signal(s, h)


def _fail(message: str, code: int = _EXIT_BAD_INPUT):
    click.echo(f"error: {' '.join(str(message).split())}", err=True)
    sys.exit(code)


def user_errors(fn):
    """Turn bad-input errors into one ``error: ...`` line on stderr and exit status 2 (see module doc)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with warnings.catch_warnings(record=True) as held:  # the filters in force decide what is recorded
            try:
                with StopSignals():
                    result = fn(*args, **kwargs)
            except Interrupted as exc:
                _fail(str(exc), 128 + exc.signum)
            except KeyboardInterrupt:
                _fail("interrupted by SIGINT: stopped; rerun the same command to resume", 130)
            except (UserError, ContractError) as exc:
                _fail(str(exc))
            except OSError as exc:
                _fail(os_error_text(exc))
        for w in held:
            category = w.category.__name__
            warn(f"{category}: {w.message}" if category not in ("UserWarning", "Warning") else str(w.message))
        return result

    return wrapper
