"""Plots of the training stage (matplotlib Agg only: no torch, so the report can use them too)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Sequence

import numpy as np

from crater_core.schema import atomic_write_bytes


def plot_confusion(path: str | Path, conf: Sequence[Sequence[int]], class_names: Sequence[str], title: str) -> None:
    """Confusion matrix PNG (matplotlib Agg), written atomically. Sized for any number of classes:
    cells carry count and row fraction up to 8 classes, the count alone up to 24, colour only beyond."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    m = np.asarray(conf, dtype=float)
    n = len(class_names)
    if m.shape != (n, n):
        raise ValueError(f"confusion matrix of shape {m.shape} for {n} classes")
    rowsum = m.sum(axis=1, keepdims=True)
    frac = np.divide(m, rowsum, out=np.zeros_like(m), where=rowsum > 0)
    side = max(4.6, 1.6 + 0.42 * n)
    fig = Figure(figsize=(side, side - 0.6), dpi=120)
    ax = fig.add_subplot(111)
    im = ax.imshow(frac, vmin=0, vmax=1, cmap="Blues")
    tick_size = 9 if n <= 8 else max(5, 9 - (n - 8) // 4)
    ax.set_xticks(range(n), class_names, rotation=30 if n <= 8 else 60, ha="right", fontsize=tick_size)
    ax.set_yticks(range(n), class_names, fontsize=tick_size)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(title, fontsize=9)
    if n <= 24:
        for i in range(n):
            for j in range(n):
                text = f"{int(m[i, j])}\n{frac[i, j]:.0%}" if n <= 8 else f"{int(m[i, j])}"
                ax.text(
                    j,
                    i,
                    text,
                    ha="center",
                    va="center",
                    fontsize=8 if n <= 8 else 6,
                    color="white" if frac[i, j] > 0.5 else "black",
                )
    fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    atomic_write_bytes(path, buf.getvalue())
