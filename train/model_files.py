"""The detectors' model files (``crater-synth nav-detector-train``; read by every trained detector): the
weights, the provenance and settings as plain JSON, the architecture fields, a format tag and a sha256 of
the weights, written atomically; on loading, the tag and the checksum are checked and a file that cannot be
used is one error naming it. torch and core only."""

from __future__ import annotations

import hashlib
import io
import json
from collections import OrderedDict
from pathlib import Path

import torch
from torch import nn

from crater_core.schema import atomic_write_bytes


class DetectorModelError(ValueError):
    """A detector model file that cannot be used (missing, corrupt, wrong format)."""


def write_model_file(path: Path, fmt: str, state_dict: dict, meta: dict, **fields) -> None:
    """Write weights (``state_dict``), ``meta`` (provenance, settings; plain JSON types) and the architecture
    ``fields`` atomically under the format tag ``fmt``, with a sha256 of the weights (every detector's file)."""
    meta = json.loads(json.dumps(meta, default=str))  # plain JSON types only: the file loads with weights_only
    buf = io.BytesIO()
    torch.save(standard_layout(state_dict), buf)
    weights = buf.getvalue()
    payload = {
        "format": fmt,
        **fields,
        "meta": meta,
        "weights_sha256": hashlib.sha256(weights).hexdigest(),
        "weights": weights,
    }
    out = io.BytesIO()
    torch.save(payload, out)
    atomic_write_bytes(Path(path), out.getvalue())


def standard_layout(state_dict: dict) -> OrderedDict:
    """``state_dict`` with every tensor in the standard (NCHW) layout, its version metadata kept: the same
    weights give the same bytes and checksum whatever layout the model ran in (channels last stores other
    strides, even where a size-1 dimension leaves both layouts contiguous)."""
    out = OrderedDict((k, v.clone(memory_format=torch.contiguous_format)) for k, v in state_dict.items())
    metadata = getattr(state_dict, "_metadata", None)
    if metadata is not None:
        out._metadata = metadata  # type: ignore[attr-defined]
    return out


def read_model_file(path: Path, fmt: str, build) -> tuple[nn.Module, dict]:
    """The model (``build(payload)`` with the file's weights loaded, in eval mode) and its meta from a
    :func:`write_model_file` file of format ``fmt``; a missing, corrupt or foreign file raises
    :class:`DetectorModelError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise DetectorModelError(f"detector model {path}: no such file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(payload, dict) or payload.get("format") != fmt:
            raise DetectorModelError(f"detector model {path}: not a {fmt} file")
        weights = payload["weights"]
        if hashlib.sha256(weights).hexdigest() != payload["weights_sha256"]:
            raise DetectorModelError(f"detector model {path}: weights checksum mismatch (corrupt file)")
        model = build(payload)
        model.load_state_dict(torch.load(io.BytesIO(weights), map_location="cpu", weights_only=True))
    except DetectorModelError:
        raise
    except Exception as exc:  # torch raises many types on a damaged file
        raise DetectorModelError(f"detector model {path}: cannot be read ({type(exc).__name__})") from None
    model.eval()
    return model, dict(payload["meta"])
