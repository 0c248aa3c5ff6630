"""``crater-synth preview DIR``: PNG contact sheets of a dataset, one per crater."""

from __future__ import annotations

import io
from pathlib import Path

import click
import numpy as np

from crater_core import schema
from crater_core.exr import read_channel as read
from crater_core.files import ensure_writable_dir
from crater_core.schema import atomic_write_bytes
from crater_synth.cli_common import user_errors
from crater_synth.errors import UserError


def read_channel(path: Path, name: str = "IF") -> np.ndarray:
    """One named channel of an EXR as a 2-D float32 array (``crater_core.exr``)."""
    return read(path, name)


def tone_map(radiance_factor: np.ndarray) -> np.ndarray:
    """Display mapping for I/F: scale so the 99.5th percentile of lit pixels is white, then sRGB-like
    gamma. Shadows stay black; each tile is scaled on its own (absolute I/F is in the EXR)."""
    lit = radiance_factor[radiance_factor > 0]
    white = float(np.percentile(lit, 99.5)) if lit.size else 1.0
    return np.clip(radiance_factor / max(white, 1e-6), 0.0, 1.0) ** (1.0 / 2.2)


def ellipse_points(e: dict, n: int = 180) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * np.pi, n)
    ca, sa = np.cos(e["angle_rad"]), np.sin(e["angle_rad"])
    x, y = e["a"] * np.cos(t), e["b"] * np.sin(t)
    return np.stack([e["cu"] + ca * x - sa * y, e["cv"] + sa * x + ca * y], axis=-1)


def contact_sheet(rows: list[dict], dataset_dir: Path, out_png: Path, title: str, max_tiles: int = 36) -> Path:
    """Write a contact sheet of up to ``max_tiles`` renders (evenly spread over ``rows``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pick = [rows[i] for i in np.unique(np.linspace(0, len(rows) - 1, min(max_tiles, len(rows))).astype(int))]
    cols = int(np.ceil(np.sqrt(len(pick))))
    nrows = int(np.ceil(len(pick) / cols))
    fig, axes = plt.subplots(nrows, cols, figsize=(2.4 * cols, 2.6 * nrows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, row in zip(axes.ravel(), pick, strict=False):
        img = tone_map(read_channel(schema.row_file(dataset_dir, row)))
        ax.imshow(img, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        pts = ellipse_points(row["rim_ellipse"])
        ax.plot(pts[:, 0], pts[:, 1], "-", color="#ff5050", lw=0.8)
        for u0, v0, u1, v1 in row["sigma_boxes"].values():
            ax.plot([u0, u1, u1, u0, u0], [v0, v0, v1, v1, v0], "--", color="#50c0ff", lw=0.5)
        ax.set_title(
            f"sun {row['sun_elevation']:.2f}/{row['sun_azimuth']:.0f}  cam {row['cam_elevation']:.0f}/"
            f"{row['cam_azimuth']:.0f}\nlit {row['lit_fraction']:.2f}  I/F {row['mean_if']:.4f}",
            fontsize=6,
        )
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=110)
    finally:
        plt.close(fig)
    atomic_write_bytes(out_png, buf.getvalue())  # temp file, fsync, rename; 0666 less the umask
    return out_png


def preview_dataset(dataset_dir: str | Path, out_dir: str | Path | None = None, max_tiles: int = 36) -> list[Path]:
    """One contact sheet PNG per crater of the dataset, in ``out_dir`` (default DATASET_DIR/preview)."""
    d = Path(dataset_dir)
    rows = schema.load_manifest(d) if (d / schema.MANIFEST_NAME).exists() else []
    if not rows:
        raise UserError(f"{d}: no rendered rows to preview")
    out = Path(out_dir) if out_dir else d / "preview"
    ensure_writable_dir(out, "--out" if out_dir else None)
    sheets = []
    for crater in sorted({r["crater"] for r in rows}):
        crater_rows = [r for r in rows if r["crater"] == crater]
        sheets.append(
            contact_sheet(
                crater_rows,
                d,
                out / f"contact_{crater}.png",
                f"{crater}: {len(crater_rows)} renders (sun el/az, cam el/az in deg)\n"
                f"red: projected rim; blue: sigma boxes",
                max_tiles,
            )
        )
    return sheets


@click.command("preview")
@click.argument("dataset_dir", type=click.Path(file_okay=False))
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    default=None,
    help="Where to write the PNGs (default DATASET_DIR/preview).",
)
@click.option("--max-tiles", default=36, show_default=True, type=click.IntRange(min=1), help="Renders per sheet.")
@user_errors
def preview_command(dataset_dir, out_dir, max_tiles):
    """Write a PNG contact sheet per crater: tone-mapped renders labelled with their parameters, with the
    projected rim ellipse and the sigma boxes drawn.

    Example: `crater-synth preview data/synth/smoke --max-tiles 16`
    """
    for sheet in preview_dataset(dataset_dir, out_dir, max_tiles):
        click.echo(str(sheet))
