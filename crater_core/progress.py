"""Progress of long loops that reads well on a terminal and in a log file.

On a terminal (the stream is a TTY) a tqdm bar; otherwise -- output redirected to a file, a pipe, a
batch system's log -- one newline-terminated line at most every ``interval_s`` seconds (default 5,
``CRATER_SYNTH_PROGRESS_INTERVAL`` overrides it), with the count, rate and ETA, and a last line when
the loop ends. Never a carriage return in a log: an error that follows lands on its own line.

Standard library only (tqdm is imported for the terminal case only).
"""

from __future__ import annotations

import os
import sys
import time
from typing import TextIO

DEFAULT_INTERVAL_S = 5.0
ENV_INTERVAL = "CRATER_SYNTH_PROGRESS_INTERVAL"
MODES = ("auto", "lines", "off")


def _interval() -> float:
    try:
        return max(0.0, float(os.environ.get(ENV_INTERVAL, DEFAULT_INTERVAL_S)))
    except ValueError:
        return DEFAULT_INTERVAL_S


def duration_text(seconds: float) -> str:
    """``H:MM:SS``."""
    s = int(round(max(0.0, seconds)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


class Progress:
    """A counter with a display: ``update(n)``, ``close()``; also a context manager.

    ``mode``: ``auto`` (a bar on a TTY, lines otherwise), ``lines`` (always lines: e.g. training with
    ``train.progress=false`` still says where it is), ``off`` (silent)."""

    def __init__(
        self,
        total: int,
        desc: str,
        unit: str,
        mode: str = "auto",
        stream: TextIO | None = None,
        interval_s: float | None = None,
    ):
        if mode not in MODES:
            raise ValueError(f"progress mode {mode!r}: use one of {MODES}")
        self.total, self.desc, self.unit = int(total), desc, unit
        self.stream = stream if stream is not None else sys.stderr
        self.interval_s = _interval() if interval_s is None else interval_s
        self.n = 0
        self.t0 = self._last = time.monotonic()
        self._closed = False
        self._bar = None
        self.mode = mode
        if mode == "auto" and _isatty(self.stream):
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=desc, unit=unit, dynamic_ncols=True, file=self.stream)
        elif mode == "auto":
            self.mode = "lines"

    def update(self, n: int = 1, **postfix) -> None:
        self.n += n
        if self._bar is not None:
            self._bar.update(n)
            if postfix:
                self._bar.set_postfix(**postfix)
            return
        now = time.monotonic()
        if self.mode == "lines" and now - self._last >= self.interval_s and self.n < self.total:
            self._last = now
            self._line(now, postfix)

    def _line(self, now: float, postfix: dict, final: bool = False) -> None:
        elapsed = now - self.t0
        rate = self.n / elapsed if elapsed > 0 else 0.0
        pct = f" ({100.0 * self.n / self.total:.0f} %)" if self.total else ""
        text = f"{self.desc}: {self.n}/{self.total} {self.unit}s{pct}, {rate:.2f} {self.unit}s/s"
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
            self._line(time.monotonic(), {}, final=True)

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False
