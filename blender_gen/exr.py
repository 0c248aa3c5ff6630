"""Dataset EXR writer/reader: tiled 64x64, float32, lossless zip, the contract's channels
(``data_manifest.schema.EXR_CHANNELS``, repeated here because blender_gen imports no project
package) and the render parameters as header attributes. Writes are atomic (temp file in the same
directory, then ``os.replace``).
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile

import numpy as np
import OpenImageIO as oiio

CHANNELS = ("IF", "depth", "N.X", "N.Y", "N.Z", "lit")  # == data_manifest.schema.EXR_CHANNELS
TILE = 64
COMPRESSION = "zip"
HEADER_PREFIX = ""  # header keys are written as given (str, int or float values)


def _header_value(v):
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, (int, float, str)):
        return v
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating,)):
        return float(v)
    return json.dumps(v, sort_keys=True)


def write_exr(path: str, channels: dict[str, np.ndarray], header: dict) -> str:
    """Write ``channels`` (name -> (h, w) array; exactly :data:`CHANNELS`) atomically; returns sha256."""
    if set(channels) != set(CHANNELS):
        raise ValueError(f"EXR channels {sorted(channels)} != {sorted(CHANNELS)}")
    h, w = np.asarray(channels[CHANNELS[0]]).shape
    data = np.stack([np.asarray(channels[c], dtype=np.float32).reshape(h, w) for c in CHANNELS], axis=-1)
    spec = oiio.ImageSpec(w, h, len(CHANNELS), "float")
    spec.channelnames = CHANNELS
    spec.tile_width = spec.tile_height = TILE
    spec.attribute("compression", COMPRESSION)
    spec.attribute("DateTime", "")  # an empty value stops OpenImageIO stamping the time: same input, same bytes
    for key, val in header.items():
        spec.attribute(HEADER_PREFIX + str(key), _header_value(val))

    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".tmp.exr", dir=directory)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create("openexr")
        if out is None or not out.open(tmp, spec):
            raise OSError(f"cannot open {tmp} for writing: {oiio.geterror()}")
        ok = out.write_image(data)
        ok = out.close() and ok
        if not ok:
            raise OSError(f"cannot write {tmp}: {out.geterror() or oiio.geterror()}")
        with open(tmp, "rb") as fh:
            digest = hashlib.sha256(fh.read()).hexdigest()
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return digest


def read_exr(path: str) -> tuple[dict[str, np.ndarray], dict]:
    """(channels by name, {header attribute: value}) of an EXR; for tests and tools."""
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise OSError(f"cannot open {path}: {oiio.geterror()}")
    try:
        spec = inp.spec()
        px = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, "float"), dtype=np.float32)
        px = px.reshape(spec.height, spec.width, spec.nchannels)
        chans = {name: px[..., i] for i, name in enumerate(spec.channelnames)}
        header = {a.name: a.value for a in spec.extra_attribs}
        header["tile_width"], header["tile_height"] = spec.tile_width, spec.tile_height
    finally:
        inp.close()
    return chans, header
