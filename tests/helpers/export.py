"""Helpers for the export tests."""

from __future__ import annotations

from crater_synth.dataset import export as ex


def interrupt_at_sample(monkeypatch, kind: str, n: int) -> None:
    """Make ``kind``'s export raise KeyboardInterrupt (a Ctrl-C) while reading its ``n``-th sample."""
    real = ex.RECORD_KINDS[kind]
    calls = {"n": 0}

    def dying(d, row, channels):
        calls["n"] += 1
        if calls["n"] == n:
            raise KeyboardInterrupt
        return real.arrays(d, row, channels)

    monkeypatch.setitem(ex.RECORD_KINDS, kind, ex.RecordKind(**{**real.__dict__, "arrays": dying}))
