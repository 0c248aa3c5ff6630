"""``crater-synth navigate``'s outputs, for map windows and rendered frames alike: the per-detection list
(every detection with its circle, confidence and the landmark it was identified as, or "unknown") and the
drawing of the annotated PNG (detections red dashed, identified landmarks yellow with their names)."""

from __future__ import annotations

import io
import json
from pathlib import Path

from crater_core.schema import atomic_write_text
from crater_synth.navigation.fix.patches import PATCH_SOURCE
from crater_synth.navigation.fix.refine import RefineParams


def detection_records(dets, identified: dict[int, int], landmarks, truth: dict[int, int] | None = None) -> list[dict]:
    """Per detection: its circle (px), confidence and the landmark it was identified as (``identified``:
    detection index -> landmark index) or "unknown"; with ``truth`` (rendered frames: detection index ->
    the labelled landmark it matches), that landmark too, or None."""
    out = []
    for i, d in enumerate(dets):
        li = identified.get(i)
        rec = d.as_dict() | {
            "landmark": "unknown" if li is None else landmarks[li].id,
            "name": None if li is None else (landmarks[li].name or None),
        }
        if truth is not None:
            rec["truth_landmark"] = None if i not in truth else landmarks[truth[i]].id
        out.append(rec)
    return out


def detections_text(image: Path, records: list[dict]) -> str:
    """The per-detection list of ``navigate`` as JSON text."""
    return json.dumps({"image": str(image), "detections": records}, indent=1) + "\n"


def write_detections(path: Path, image: Path, records: list[dict]) -> None:
    """The per-detection list of ``navigate`` as JSON (atomic)."""
    atomic_write_text(path, detections_text(image, records))


def draw_detections(ax, dets, identified, landmarks) -> None:
    """Every detection (``u``, ``v``, ``r`` px) as a red dashed circle; those of ``identified`` ((detection
    index, landmark index) pairs) yellow, with the landmark's name (or id); an identified terrain patch
    (:mod:`.patches`) as a cyan square, its window."""
    from matplotlib.patches import Circle, Rectangle

    for d in dets:
        ax.add_patch(Circle((d.u, d.v), d.r, fill=False, ec="#ff4040", lw=0.6, ls="--"))
    for di, li in identified:
        lm, d = landmarks[li], dets[di]
        if lm.source == PATCH_SOURCE:
            half = 2.0 * RefineParams().window_diameters * d.r  # r is half the patch's "diameter"
            ax.add_patch(Rectangle((d.u - half, d.v - half), 2 * half, 2 * half, fill=False, ec="#30c0ff", lw=1.0))
            continue
        ax.add_patch(Circle((d.u, d.v), d.r, fill=False, ec="#ffd000", lw=1.2))
        ax.text(d.u, d.v, lm.name or lm.id, color="#ffd000", fontsize=7, ha="center", va="center")


def png_of(fig, ax, width: int, height: int, title: str) -> bytes:
    """The figure (one image of ``width`` x ``height`` px on ``ax``) with ``title``, as PNG bytes; closed."""
    import matplotlib.pyplot as plt

    ax.set_title(title, fontsize=9)
    ax.set_xlim(0, width)
    ax.set_ylim(height, 0)
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return buf.getvalue()
