"""Proving a rendered file: is it the render planned now, and what is its manifest row?

Every EXR the renderer writes carries, in its header, the manifest row it was planned for
(``manifest_row``: every field but the worker's stats and the file's sha256), the worker's stats
(``crater_synth:stats``: lit_fraction, mean_if) and a seal (``crater_synth:seal``: the sha256 of every
attribute, that row and those stats among them, and of the pixels; :func:`crater_core.exr.sealed_header`).

:func:`prove` gives the row a clean run would record for a file, or None:

- the header's row must equal the row planned now (same identity, angles, crop, labels, seed ...);
- when the dataset's row for that render equals the rebuilt row, its sha256 -- recorded when the file
  was rendered -- proves the bytes (no decoding);
- otherwise (no row: a deleted manifest, a run killed between writing a file and recording it; or an
  edited row) the pixels are decoded and, with the attributes, must give the seal, and encoding them
  again must give the file's bytes (:func:`crater_core.exr.check_seal`): no byte of it changed.

A file that cannot be proved is rendered again; nothing is deleted here.
"""

from __future__ import annotations

import json
from pathlib import Path

from crater_core import exr, schema
from crater_synth.dataset.manifest import RESULT_FIELDS

ROW_HEADER = "manifest_row"
STATS_HEADER = "crater_synth:stats"
# Row fields a resumed dataset keeps from the file rather than the plan: the version that rendered it
# (a new crater-synth version does not re-render a dataset whose identity is unchanged) and the
# render's place in the grid that rendered it (a grown grid -- the closed loop -- keeps its renders).
KEPT_FROM_FILE = ("code_version", "index", "indices")


def _same_plan(row: dict, planned: dict) -> bool:
    keys = set(planned) | set(row)
    return all(row.get(k) == planned.get(k) for k in keys if k not in KEPT_FROM_FILE and k not in RESULT_FIELDS)


def prove(path: Path, planned: dict, row: dict | None) -> dict | None:
    """The manifest row of the file ``path`` for the planned render ``planned`` (its row less
    :data:`~crater_synth.dataset.manifest.RESULT_FIELDS`), or None when the file cannot be proved to be
    that render. ``row``: the dataset's row for that render, if any."""
    try:
        header = exr.read_header(path)
        file_row = json.loads(header[ROW_HEADER])
        stats = json.loads(header[STATS_HEADER])
        if not isinstance(file_row, dict) or not isinstance(stats, dict) or not _same_plan(file_row, planned):
            return None
        rebuilt = {
            **file_row,
            "lit_fraction": float(stats["lit_fraction"]),
            "mean_if": float(stats["mean_if"]),
            "sha256": schema.sha256_file(path),
        }
        if row is not None and schema.dumps_row(row) == schema.dumps_row(rebuilt):
            return rebuilt  # the row's sha256, recorded at render time, proves the bytes
        sealed = exr.check_seal(path)  # decodes the pixels, encodes them again
        if (
            sealed is None
            or sealed.get(ROW_HEADER) != header[ROW_HEADER]
            or sealed.get(STATS_HEADER) != header[STATS_HEADER]
        ):
            return None
        return schema.validate_row(rebuilt)
    except (exr.ExrError, OSError, KeyError, TypeError, ValueError, schema.ManifestError):
        return None  # unreadable, truncated, written before the seal, or not a render of this project
