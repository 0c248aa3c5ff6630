"""Progress of long loops that reads well on a terminal and in a log file.

On a terminal (the stream is a TTY) a tqdm bar; otherwise -- output redirected to a file, a pipe, a
batch system's log -- one newline-terminated line at most every ``interval_s`` seconds (default 5,
``CRATER_SYNTH_PROGRESS_INTERVAL`` overrides it), with the count, rate and ETA, and a last line when
the loop ends. Never a carriage return in a log: an error that follows lands on its own line.

A step that cannot be counted (a scikit-learn fit) is a :meth:`Progress.stage`: a start line with an
estimated duration where the caller has one, and an end line with the time taken. :meth:`Progress.write`
prints a message without breaking a bar. Every reading of the time goes through ``clock`` (default
:func:`time.monotonic`), so tests drive the lines with a fake clock and no sleeping.

Standard library only (tqdm is imported for the terminal case only).
"""

from __future__ import annotations

import os
import sys
from time import monotonic
from typing import Callable, TextIO

DEFAULT_INTERVAL_S = 5.0
ENV_INTERVAL = "CRATER_SYNTH_PROGRESS_INTERVAL"
MODES = ("auto", "lines", "off")


def _interval() -> float:
    try:
        return max(0.0, float(os.environ.get(ENV_INTERVAL, DEFAULT_INTERVAL_S)))
    except ValueError:
        return DEFAULT_INTERVAL_S


def plural(unit: str) -> str:
    """``render`` -> ``renders``, ``batch`` -> ``batches``."""
    return unit + ("es" if unit.endswith(("s", "x", "ch", "sh")) else "s")


def duration_text(seconds: float) -> str:
    """``H:MM:SS``."""
    s = int(round(max(0.0, seconds)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def _mode(mode: str, stream: TextIO) -> str:
    """``auto`` resolved: ``bar`` on a TTY, ``lines`` otherwise."""
    if mode not in MODES:
        raise ValueError(f"progress mode {mode!r}: use one of {MODES}")
    if mode == "auto":
        return "bar" if _isatty(stream) else "lines"
    return mode


class Progress:
    """A counter with a display: ``update(n)``, ``close()``; also a context manager.

    ``mode``: ``auto`` (a bar on a TTY, lines otherwise), ``lines`` (always lines: e.g. training with
    ``train.progress=false`` still says where it is), ``off`` (silent). ``leave=False``: the terminal bar
    is erased when it closes (one bar per training epoch). ``clock``: seconds, ``time.monotonic`` by
    default (the lines' rate and ETA; tqdm keeps its own on a terminal)."""

    def __init__(
        self,
        total: int,
        desc: str,
        unit: str,
        mode: str = "auto",
        stream: TextIO | None = None,
        interval_s: float | None = None,
        clock: Callable[[], float] | None = None,
        leave: bool = True,
    ):
        self.total, self.desc, self.unit = int(total), desc, unit
        self.stream = stream if stream is not None else sys.stderr
        self.mode = _mode(mode, self.stream)
        self.interval_s = _interval() if interval_s is None else interval_s
        self.clock = clock if clock is not None else monotonic  # looked up now: tests patch the module's
        self.n = 0
        self.t0 = self._last = self.clock()
        self._closed = False
        self._postfix: dict = {}
        self._bar = None
        if self.mode == "bar":
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=desc, unit=unit, dynamic_ncols=True, file=self.stream, leave=leave)

    def update(self, n: int = 1, **postfix) -> None:
        """``n`` more done; ``postfix`` (e.g. ``loss="0.412"``) is shown after the count, and the last
        one given also on the final line."""
        self.n += n
        if postfix:
            self._postfix = postfix
        if self._bar is not None:
            self._bar.update(n)
            if postfix:
                self._bar.set_postfix(**postfix)
            return
        if self.mode != "lines":
            return
        now = self.clock()
        if now - self._last >= self.interval_s and self.n < self.total:
            self._last = now
            self._line(now, self._postfix)

    def update_to(self, done: int, **postfix) -> None:
        """Set the count to ``done`` (for callbacks that report a running total)."""
        self.update(done - self.n, **postfix)

    def write(self, text: str) -> None:
        """One message line that does not break the bar (nothing with ``mode="off"``)."""
        if self.mode != "off":
            write(text, self.stream)

    @staticmethod
    def stage(
        desc: str,
        eta_s: float | None = None,
        basis: str = "",
        mode: str = "auto",
        stream: TextIO | None = None,
        clock: Callable[[], float] | None = None,
    ) -> "Stage":
        """A step that cannot be counted, as a context manager: a start line (with ``ETA`` when the caller
        has an estimate ``eta_s``, and ``basis``: what the estimate rests on) and an end line with the time
        taken (``failed after`` on an exception)."""
        return Stage(desc, eta_s, basis, mode, stream, clock)

    def _line(self, now: float, postfix: dict, final: bool = False) -> None:
        elapsed = now - self.t0
        rate = self.n / elapsed if elapsed > 0 else 0.0
        pct = f" ({100.0 * self.n / self.total:.0f} %)" if self.total else ""
        units = plural(self.unit)
        text = f"{self.desc}: {self.n}/{self.total} {units}{pct}, {rate:.2f} {units}/s"
        if final:
            text += (
                f", done in {duration_text(elapsed)}"
                if self.n >= self.total
                else f", stopped after {duration_text(elapsed)}"
            )
        else:
            eta = (self.total - self.n) / rate if rate > 0 else float("nan")
            text += f", elapsed {duration_text(elapsed)}, ETA {duration_text(eta) if eta == eta else '?'}"
        if postfix:
            text += ", " + ", ".join(f"{k} {v}" for k, v in postfix.items())
        self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._bar is not None:
            self._bar.close()
        elif self.mode == "lines":
            self._line(self.clock(), self._postfix, final=True)

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Stage:
    """See :meth:`Progress.stage`."""

    def __init__(self, desc, eta_s, basis, mode, stream, clock):
        self.desc, self.eta_s, self.basis = desc, eta_s, basis
        self.stream = stream if stream is not None else sys.stderr
        self.mode = _mode(mode, self.stream)
        self.clock = clock if clock is not None else monotonic
        self.t0 = 0.0

    def __enter__(self) -> "Stage":
        self.t0 = self.clock()
        if self.mode != "off":
            eta = "no estimate" if self.eta_s is None else f"ETA {duration_text(self.eta_s)}"
            basis = f" ({self.basis})" if self.basis else ""
            write(f"{self.desc}: started, {eta}{basis}", self.stream)
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if self.mode != "off":
            how = "done in" if exc_type is None else "failed after"
            write(f"{self.desc}: {how} {duration_text(self.clock() - self.t0)}", self.stream)


def write(text: str, stream: TextIO | None = None) -> None:
    """A message line on ``stream`` (default stderr); on a terminal through tqdm, so that a live bar is
    redrawn below it instead of being broken."""
    stream = stream if stream is not None else sys.stderr
    if _isatty(stream):
        from tqdm import tqdm

        tqdm.write(text, file=stream)
    else:
        stream.write(text + "\n")
        stream.flush()


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False
