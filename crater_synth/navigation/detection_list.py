"""``crater-synth navigate``'s per-detection list: every detection of a frame with its circle, confidence and
the landmark it was identified as, or "unknown" (map windows and rendered frames alike)."""

from __future__ import annotations

import json
from pathlib import Path


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


def write_detections(path: Path, image: Path, records: list[dict]) -> None:
    """The per-detection list of ``navigate`` as JSON (atomic)."""
    from crater_core.schema import atomic_write_text

    atomic_write_text(path, json.dumps({"image": str(image), "detections": records}, indent=1) + "\n")
