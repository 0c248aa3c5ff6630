"""The labels of a render, as its EXR header carries them, checked against its manifest row.

The renderer writes every render parameter into the EXR's header (``blender_gen.worker.header_for``):
the crater, the Sun and camera angles, range, field of view, frame width and crop, the rim ellipse,
the sigma boxes, the seed and the terrain. A manifest row is a second copy of those labels. The sha256
of a row proves that the file is the one rendered, not that the row's labels are the file's: a row
whose crater or Sun angle was edited still hashes right. :func:`label_faults` compares the two copies
(``verify`` for every row; training for every EXR it decodes).

Header floats are stored as 32-bit floats, so a row value and its header value are equal when they
round to the same float32; the JSON-encoded entries (sigma boxes, rim ellipse) are compared to 1e-9.
"""

from __future__ import annotations

import json
import math

import numpy as np

HEADER_PREFIX = "crater_synth:"
# Row field -> (header attribute, how it is stored).
SCALAR_FIELDS: dict[str, tuple[str, str]] = {
    "crater": ("crater", "str"),
    "sun_elevation": ("crater_synth:sun_elevation", "float32"),
    "sun_azimuth": ("crater_synth:sun_azimuth", "float32"),
    "cam_elevation": ("crater_synth:cam_elevation", "float32"),
    "cam_azimuth": ("crater_synth:cam_azimuth", "float32"),
    "range_m": ("crater_synth:range_m", "float32"),
    "fov_deg": ("crater_synth:fov_deg", "float32"),
    "frame_width": ("crater_synth:frame_width", "int"),
    "index": ("crater_synth:index", "int"),
    "seed": ("seed", "int"),
    "terrain_id": ("crater_synth:terrain_id", "str"),
}
# Row field -> header attribute holding it as JSON.
JSON_FIELDS: dict[str, str] = {
    "indices": "crater_synth:indices",
    "sigma_boxes": "sigma_boxes",
    "rim_ellipse": "rim_ellipse",
}
# The crop rendered, [u0, v0, u1, v1] in full-frame pixels: the row's crop_origin, width and height.
CROP_KEY = "crater_synth:crop"
# The full crater description (JSON with its "name"): where an EXR lacks the plain "crater" entry.
CRATER_JSON_KEY = "crater_synth:crater"
# Without these a header proves nothing about the labels that matter for training.
REQUIRED_FIELDS = ("crater", "sun_elevation", "sun_azimuth", "cam_elevation", "cam_azimuth")
JSON_TOLERANCE = 1e-9
CENTRE_TOLERANCE_PX = 1e-6
_INT32 = (-(2**31), 2**31 - 1)


def header_for_row(row: dict) -> dict:
    """The header entries :func:`label_faults` reads, from a row (for writers other than the renderer,
    e.g. ``train.toydata``, so that their EXRs carry their labels the same way)."""
    hdr: dict = {}
    for field, (key, kind) in SCALAR_FIELDS.items():
        v = row[field]
        if kind == "float32":
            hdr[key] = float(v)
        elif kind == "int":
            hdr[key] = int(v) if _INT32[0] <= int(v) <= _INT32[1] else str(int(v))  # EXR ints are 32-bit
        else:
            hdr[key] = str(v)
    for field, key in JSON_FIELDS.items():
        hdr[key] = json.dumps(row[field], sort_keys=True)
    u0, v0 = (int(c) for c in row["crop_origin"])
    hdr[CROP_KEY] = json.dumps([u0, v0, u0 + int(row["width"]), v0 + int(row["height"])])
    return hdr


def _show(v) -> str:
    if isinstance(v, float):
        return f"{v:.7g}"
    return repr(v) if isinstance(v, str) else str(v)


def _same_scalar(kind: str, row_value, header_value) -> bool:
    try:
        if kind == "float32":
            return bool(np.float32(row_value) == np.float32(header_value))
        if kind == "int":
            return int(row_value) == int(header_value)
    except (TypeError, ValueError, OverflowError):
        return False
    return str(row_value) == str(header_value)


def _close(a, b) -> bool:
    """Equal JSON values, numbers to :data:`JSON_TOLERANCE` (relative and absolute)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return math.isclose(a, b, rel_tol=JSON_TOLERANCE, abs_tol=JSON_TOLERANCE)
    return a == b


def centre_faults(row: dict, where: str) -> list[str]:
    """The row's own consistency: every sigma box is centred on ``center_px`` (the projected crater
    centre, ``crater_core.geometry.roi_box``)."""
    cu, cv = (float(c) for c in row["center_px"])
    for box in row["sigma_boxes"].values():
        try:
            u0, v0, u1, v1 = (float(b) for b in box)
        except (TypeError, ValueError):
            return [f"{where}: sigma box {box!r} is not four numbers"]
        if abs((u0 + u1) / 2 - cu) > CENTRE_TOLERANCE_PX or abs((v0 + v1) / 2 - cv) > CENTRE_TOLERANCE_PX:
            return [f"{where}: center_px {row['center_px']} is not the centre of the sigma boxes"]
    return []


def label_faults(row: dict, header: dict, where: str) -> list[str]:
    """Every label of the (validated) ``row`` that its EXR's ``header`` contradicts, one line each
    (``where`` names the file); plus :func:`centre_faults`. An EXR whose header carries no render
    parameters at all is one fault: nothing proves its labels."""
    if not any(str(k).startswith(HEADER_PREFIX) for k in header):
        return [f"{where}: the EXR header carries no render parameters (not written by crater-synth)"]
    faults: list[str] = []
    header = dict(header)
    if "crater" not in header and CRATER_JSON_KEY in header:
        try:
            header["crater"] = json.loads(header[CRATER_JSON_KEY])["name"]
        except (TypeError, ValueError, KeyError):
            pass
    for field, (key, kind) in SCALAR_FIELDS.items():
        if key not in header:
            if field in REQUIRED_FIELDS:
                faults.append(f"{where}: the EXR header has no {key} (cannot check the row's {field})")
            continue
        if not _same_scalar(kind, row[field], header[key]):
            faults.append(f"{where}: row {field} {_show(row[field])} but the EXR header says {_show(header[key])}")
    for field, key in JSON_FIELDS.items():
        if key not in header:
            continue
        try:
            value = json.loads(header[key])
        except (TypeError, ValueError):
            faults.append(f"{where}: the EXR header's {key} is not JSON")
            continue
        if not _close(row[field], value):
            faults.append(f"{where}: row {field} differs from what the EXR header says")
    if CROP_KEY in header:
        try:
            u0, v0, u1, v1 = (int(c) for c in json.loads(header[CROP_KEY]))
        except (TypeError, ValueError):
            faults.append(f"{where}: the EXR header's {CROP_KEY} is not four integers")
        else:
            if list(row["crop_origin"]) != [u0, v0]:
                faults.append(f"{where}: row crop_origin {row['crop_origin']} but the EXR header says {[u0, v0]}")
            if (row["width"], row["height"]) != (u1 - u0, v1 - v0):
                faults.append(
                    f"{where}: row size {row['width']}x{row['height']} but the EXR header's crop is {u1 - u0}x{v1 - v0}"
                )
    return faults + centre_faults(row, where)
