"""The one EXR reader/writer of the project (renderer output, training input, verify, preview, tests).

Dataset EXRs (the render contract, docs/manifest.md): tiled 64x64, lossless RLE, exactly the channels
of :data:`crater_core.schema.EXR_CHANNELS` stored as :data:`crater_core.schema.EXR_CHANNEL_TYPES`
(float32 I/F and depth, half normals and lit fraction; every reader gets float32), the render
parameters as header attributes.
Writes are atomic (temp file in the same directory, fsync, then ``os.replace``; 0666 less the umask),
a full disk is an :class:`ExrError` saying so (ENOSPC, naming the file), and files are byte-reproducible
(no time stamp). Blender's multilayer scratch output (one part per render pass) is read by
:func:`read_multilayer`.

Files are encoded by the OpenEXR library's Python binding (:func:`encoder`; OpenImageIO where it is
missing) and read by OpenImageIO. Both are imported inside the functions, so importing ``crater_core``
needs only numpy and the standard library; every failure is an :class:`ExrError` naming the file.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import IO

import numpy as np

from crater_core.errors import ContractError
from crater_core.files import (
    SCRATCH_PREFIXES,
    disk_full_message,
    free_bytes,
    is_disk_full,
    scratch_file,
    size_text,
    umask,
)
from crater_core.schema import EXR_CHANNEL_TYPES, EXR_CHANNELS

CHANNELS = EXR_CHANNELS
TILE = 64
# Lossless run-length coding: float32 render noise does not compress, so zip saves only ~10 % more
# bytes than RLE and costs twice the CPU (measured on real renders, docs/renderer.md "EXR size").
COMPRESSION = "rle"
_NUMPY_TYPE = {"float": np.float32, "half": np.float16}


class ExrError(ContractError):
    """An EXR is missing, unreadable, corrupt or does not hold what the contract says."""


def _header_value(v):
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, (int, float, str)):
        return v
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    return json.dumps(v, sort_keys=True)


def stored_type(channel: str) -> str:
    """The pixel type ("float" or "half") a channel is stored as; channels outside the contract: float."""
    return EXR_CHANNEL_TYPES.get(channel, "float")


def stored_dtype(channel: str) -> type:
    """The numpy dtype of a channel's stored pixel type (np.float32 or np.float16)."""
    return _NUMPY_TYPE[stored_type(channel)]


def as_stored(channels: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``channels`` as float32, each rounded to the precision it is stored with (half channels through
    float16): statistics taken from the result (lit_fraction, mean I/F) are those of the file."""
    return {
        name: np.asarray(a, dtype=stored_dtype(name)).astype(np.float32, copy=False) for name, a in channels.items()
    }


def _encode_openexr(scratch: str, arrays: dict[str, np.ndarray], header: dict, tile: int) -> None:
    """Encode with the OpenEXR library's own Python binding: each array is handed over in its stored
    type (float32 / float16), so nothing is converted pixel by pixel inside the library."""
    import OpenEXR

    tiles = OpenEXR.TileDescription()
    tiles.xSize = tiles.ySize = int(tile)
    hdr = {"compression": OpenEXR.RLE_COMPRESSION, "type": OpenEXR.tiledimage, "tiles": tiles}
    hdr.update((str(k), _header_value(v)) for k, v in header.items())
    try:
        with OpenEXR.File(hdr, dict(arrays)) as exr_file:  # (File takes the dict over: pass a copy)
            exr_file.write(scratch)
    except (RuntimeError, TypeError, ValueError) as exc:
        raise ExrError(f"cannot encode {scratch}: {exc}") from None


def _encode_oiio(
    scratch: str, arrays: dict[str, np.ndarray], header: dict, tile: int, compression: str = COMPRESSION
) -> None:
    """Encode with OpenImageIO (where the OpenEXR binding is not installed, e.g. Blender's own Python),
    each channel stored in its array's type (float16: half, else float); the pixels go in as float32
    and OpenImageIO rounds them to half to nearest even, exactly as :func:`as_stored` does."""
    import OpenImageIO as oiio

    names = tuple(arrays)
    h, w = arrays[names[0]].shape
    spec = oiio.ImageSpec(w, h, len(names), "float")
    spec.channelformats = tuple(oiio.TypeDesc("half" if a.dtype == np.float16 else "float") for a in arrays.values())
    spec.channelnames = names
    spec.tile_width = spec.tile_height = int(tile)
    spec.attribute("compression", compression)
    spec.attribute("DateTime", "")  # an empty value stops OpenImageIO stamping the time: same input, same bytes
    for key, val in header.items():
        spec.attribute(str(key), _header_value(val))
    out = oiio.ImageOutput.create("openexr")
    if out is None or not out.open(scratch, spec):
        raise ExrError(f"cannot open {scratch} for writing: {oiio.geterror()}")
    ok = out.write_image(np.stack([a.astype(np.float32) for a in arrays.values()], axis=-1))
    ok = out.close() and ok
    if not ok:
        raise ExrError(f"cannot encode {scratch}: {out.geterror() or oiio.geterror()}")


def encoder():
    """The EXR encoder in use: the OpenEXR binding (a project dependency: 2-3x faster here, it takes
    half channels as float16 arrays) or, where it is missing or too old to have its ``File`` API
    (OpenEXR < 3.3, e.g. a Blender binary's system Python), OpenImageIO. Both write the same
    channels, types, tiling, compression and header; their bytes differ, so one installation always
    uses the same one (byte-reproducible datasets)."""
    try:
        import OpenEXR
    except ImportError:
        return _encode_oiio
    return _encode_openexr if hasattr(OpenEXR, "File") else _encode_oiio


def encode_exr(
    channels: dict[str, np.ndarray],
    header: dict | None = None,
    channel_names: tuple[str, ...] = CHANNELS,
    tile: int = TILE,
    what: str = "EXR",
) -> bytes:
    """The bytes :func:`write_exr` writes for ``channels`` and ``header`` (``what`` names the file in
    errors). Same input, same bytes: a file can be checked by encoding its decoded content again."""
    if set(channels) != set(channel_names):
        raise ExrError(f"{what}: EXR channels {sorted(channels)} != {sorted(channel_names)}")
    h, w = np.asarray(channels[channel_names[0]]).shape
    arrays: dict[str, np.ndarray] = {
        c: np.ascontiguousarray(np.asarray(channels[c], dtype=np.float32).reshape(h, w), dtype=stored_dtype(c))
        for c in channel_names
    }
    # OpenEXR deadlocks (never returns) when the disk fills during a write, so the file is encoded
    # into a scratch file in memory (/dev/shm) first, checked to have room, and its bytes are then
    # written by Python, where a full disk is a plain OSError (ENOSPC) naming the path.
    scratch = scratch_file(SCRATCH_PREFIXES[1])
    try:
        room = free_bytes(scratch)
        raw = sum(a.nbytes for a in arrays.values())
        if room < 2 * raw + (1 << 20):  # RLE never inflates tiles much beyond raw size
            raise ExrError(
                f"disk full (ENOSPC): no room to encode {what} in {os.path.dirname(scratch)} ({size_text(room)} free)"
            )
        try:
            encoder()(scratch, arrays, header or {}, tile)
        except ExrError as exc:
            raise ExrError(f"{what}: {exc}") from None
        with open(scratch, "rb") as fh:
            return fh.read()
    finally:
        try:
            os.unlink(scratch)
        except OSError:
            pass


def write_exr(
    path: str | os.PathLike,
    channels: dict[str, np.ndarray],
    header: dict | None = None,
    channel_names: tuple[str, ...] = CHANNELS,
    tile: int = TILE,
) -> str:
    """Write ``channels`` (name -> (h, w) array; exactly ``channel_names``) atomically as one tiled,
    RLE-compressed EXR, each channel stored as :func:`stored_type`; returns the file's sha256."""
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    blob = encode_exr(channels, header, channel_names, tile, what=str(path))
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".tmp.exr", dir=directory)
    try:
        os.fchmod(fd, 0o666 & ~umask())  # mkstemp makes 0600: datasets are shared like any file
        with os.fdopen(fd, "wb") as fh:
            fh.write(blob)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        if is_disk_full(exc):
            raise ExrError(disk_full_message(path, exc)) from None
        raise
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return hashlib.sha256(blob).hexdigest()


class _LibraryStderr:
    """Holds what C/C++ code writes to file descriptor 2 while a file is read (OpenEXR prints one line
    per corrupt tile of a truncated file before OpenImageIO reports the error: 17 lines for a 4x4-tile
    render). The output is kept in an unnamed temp file; a read that succeeds passes it on to stderr
    unchanged, a failed one drops it (its :class:`ExrError` is the one line the user sees). The
    redirection is process-wide: readers run in the main thread or in worker processes."""

    def __enter__(self) -> "_LibraryStderr":
        self.failed = True
        self._sink: "IO[bytes] | None" = None
        try:
            sys.stderr.flush()
        except (AttributeError, ValueError, OSError):
            pass
        try:
            self._sink = tempfile.TemporaryFile()
            self._saved = os.dup(2)
            os.dup2(self._sink.fileno(), 2)
        except OSError:  # no fd 2, or no room for a temp file: read without the redirection
            self._sink = None
        return self

    def __exit__(self, exc_type, *_) -> None:
        if self._sink is None:
            return
        os.dup2(self._saved, 2)
        os.close(self._saved)
        try:
            if exc_type is None and not self.failed:
                self._sink.seek(0)
                text = self._sink.read()
                while text:
                    text = text[os.write(2, text) :]
        except OSError:
            pass
        finally:
            self._sink.close()


def _open(path: str | os.PathLike):
    import OpenImageIO as oiio

    if not Path(path).is_file():
        raise ExrError(f"EXR {path} does not exist")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ExrError(f"cannot open EXR {path}: {_first_line(oiio.geterror()) or 'unreadable file'}")
    return inp


def _first_line(text: str) -> str:
    """Library errors can span lines (one per bad tile): the message keeps its first line."""
    return (text or "").strip().split("\n", 1)[0]


def _header(spec) -> dict:
    header = {a.name: a.value for a in spec.extra_attribs}
    header["tile_width"], header["tile_height"] = spec.tile_width, spec.tile_height
    return header


def read_exr(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict]:
    """(channels by name as float32 (h, w), {header attribute: value}) of a single-part EXR."""
    with _LibraryStderr() as quiet:
        out = _read_exr(path)
        quiet.failed = False
    return out


def _read_exr(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict]:
    inp = _open(path)
    try:
        spec = inp.spec()
        px = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if px is None:
            raise ExrError(f"cannot decode EXR {path}: {_first_line(inp.geterror()) or 'corrupt file'}")
        px = np.asarray(px, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
        chans = {name: px[..., i] for i, name in enumerate(spec.channelnames)}
        header = _header(spec)
    finally:
        inp.close()
    return chans, header


def read_channel(path: str | os.PathLike, channel: str = "IF") -> np.ndarray:
    """One channel looked up by name (OpenImageIO may reorder channels), float32 (h, w), all finite."""
    return read_channel_and_header(path, channel)[0]


def read_channel_and_header(path: str | os.PathLike, channel: str = "IF") -> tuple[np.ndarray, dict]:
    """:func:`read_channel` and the file's header attributes (the render parameters), from one open."""
    with _LibraryStderr() as quiet:
        data, header = _read_channels(path, (channel,))
        quiet.failed = False
    return data[channel], header


def read_channels(path: str | os.PathLike, channels) -> dict[str, np.ndarray]:
    """Several channels by name, each as :func:`read_channel` gives it, from one decode of the file (the
    contiguous range of channels that holds them): cheaper than one :func:`read_channel` per channel."""
    if not channels:
        return {}
    with _LibraryStderr() as quiet:
        data, _ = _read_channels(path, tuple(channels))
        quiet.failed = False
    return data


def _read_channels(path: str | os.PathLike, channels: tuple[str, ...]) -> tuple[dict[str, np.ndarray], dict]:
    inp = _open(path)
    try:
        spec = inp.spec()
        names = list(spec.channelnames)
        for channel in channels:
            if channel not in names:
                raise ExrError(f"EXR {path} has no channel {channel!r} (channels: {names})")
        index = [names.index(c) for c in channels]
        first, last = min(index), max(index)
        data = inp.read_image(0, 0, first, last + 1, "float")
        if data is None:
            raise ExrError(f"cannot decode EXR {path}: {_first_line(inp.geterror()) or 'corrupt file'}")
        header = _header(spec)
    finally:
        inp.close()
    data = np.asarray(data, dtype=np.float32).reshape(spec.height, spec.width, last + 1 - first)
    out = {}
    for channel, c in zip(channels, index):
        plane = np.ascontiguousarray(data[..., c - first])
        if not np.all(np.isfinite(plane)):
            raise ExrError(f"EXR {path}: channel {channel!r} holds NaN/inf values")
        out[channel] = plane
    return out, header


def exr_info(path: str | os.PathLike, decode: bool = True) -> dict:
    """The facts ``verify`` checks: channels, size, tiling, header attributes and (``decode``: every
    pixel decoded) finiteness; ``finite`` is None without ``decode``."""
    with _LibraryStderr() as quiet:
        info = _exr_info(path, decode)
        quiet.failed = False
    return info


def _exr_info(path: str | os.PathLike, decode: bool) -> dict:
    inp = _open(path)
    try:
        spec = inp.spec()
        finite = None
        if decode:
            pixels = inp.read_image("float")
            if pixels is None:
                raise ExrError(f"{path}: cannot decode pixels ({_first_line(inp.geterror())})")
            finite = bool(np.isfinite(np.asarray(pixels)).all())
        return {
            "channels": tuple(spec.channelnames),
            "width": spec.width,
            "height": spec.height,
            "tiled": spec.tile_width > 0,
            "finite": finite,
            "header": _header(spec),
        }
    finally:
        inp.close()


def read_multilayer(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """{pass name: (h, w) or (h, w, c) float32} from a Blender multilayer EXR (one part per pass,
    channels named ``<ViewLayer>.<Pass>.<chan>``), channels ordered R G B A / X Y Z."""
    inp = _open(path)
    out = {}
    try:
        sub = 0
        while inp.seek_subimage(sub, 0):
            spec = inp.spec()
            px = inp.read_image(sub, 0, 0, spec.nchannels, "float")
            if px is None:
                raise ExrError(f"cannot decode render output {path} part {sub}: {inp.geterror()}")
            names = list(spec.channelnames)
            groups: dict[str, list[int]] = {}
            for i, ch in enumerate(names):
                parts = ch.split(".")
                key = ".".join(parts[1:-1]) if len(parts) >= 3 else parts[0]
                groups.setdefault(key, []).append(i)
            px = np.asarray(px, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
            for key, idx in groups.items():
                chans = [names[i].rsplit(".", 1)[-1] for i in idx]
                order = sorted(
                    range(len(chans)), key=lambda k: "RGBAXYZUVW".find(chans[k][0]) if len(chans[k]) == 1 else 99
                )
                arr = px[..., [idx[k] for k in order]]
                out[key] = arr[..., 0] if arr.shape[-1] == 1 else arr
            sub += 1
    finally:
        inp.close()
    return out


def read_header(path: str | os.PathLike) -> dict:
    """{header attribute: value} of an EXR, without decoding its pixels (the library's own error output
    kept quiet like every other reader here)."""
    with _LibraryStderr() as quiet:
        inp = _open(path)
        try:
            header = _header(inp.spec())
        finally:
            inp.close()
        quiet.failed = False
    return header


SEAL_ATTR = "crater_synth:seal"
SEALED_ATTR = "crater_synth:sealed"


def _as_read(value):
    """A header value as it reads back from the file (floats are stored as float32 attributes)."""
    v = _header_value(value)
    return float(np.float32(v)) if isinstance(v, float) else v


def as_read(header: dict) -> dict:
    """``header`` as its attributes read back from a written file (what :func:`check_seal` returns)."""
    return {k: _as_read(v) for k, v in header.items()}


def _seal(channels: dict[str, np.ndarray], sealed: dict) -> str:
    h = hashlib.sha256(json.dumps(sealed, sort_keys=True).encode("utf-8"))
    for c in CHANNELS:
        a: np.ndarray = np.ascontiguousarray(np.asarray(channels[c], dtype=np.float32), dtype=stored_dtype(c))
        h.update(c.encode() + b"\0" + str(a.shape).encode() + b"\0")
        h.update(a.tobytes())
    return h.hexdigest()


def sealed_header(channels: dict[str, np.ndarray], header: dict) -> dict:
    """``header`` plus a seal: the sha256 of every attribute (as it reads back) and of the pixels as
    stored. The renderer writes it into each EXR, so that the file alone proves its content
    (:func:`check_seal`) when the manifest that held its sha256 is lost."""
    sealed = as_read(header)
    sealed[SEALED_ATTR] = json.dumps(sorted(sealed) + [SEALED_ATTR])
    return {**header, SEALED_ATTR: sealed[SEALED_ATTR], SEAL_ATTR: _seal(channels, sealed)}


def check_seal(path: str | os.PathLike) -> dict | None:
    """The sealed header attributes of an EXR if the file is exactly what its writer sealed -- the
    decoded pixels and the attributes give the seal, and encoding them again gives the file's bytes
    (so no byte outside them changed either) -- else None. Raises :class:`ExrError` for an unreadable file."""
    channels, header = read_exr(path)
    sealed = sealed_attrs(channels, header)
    if sealed is None:
        return None
    if encode_exr(channels, {**sealed, SEAL_ATTR: header[SEAL_ATTR]}, what=str(path)) != Path(path).read_bytes():
        return None
    return sealed


def sealed_attrs(channels: dict[str, np.ndarray], header: dict) -> dict | None:
    """The sealed attributes of a decoded EXR (``channels``, ``header`` as :func:`read_exr` gives them)
    when its pixels and those attributes give the seal its header carries, else None (no seal, or any
    sealed pixel or attribute changed). Unlike :func:`check_seal` nothing is encoded again, so the
    answer does not depend on the encoder installed here."""
    try:
        keys = json.loads(header[SEALED_ATTR])
        sealed = {k: header[k] for k in keys}
        seal = header[SEAL_ATTR]
        ok = _seal(channels, sealed) == seal
    except (KeyError, TypeError, ValueError):
        return None
    return sealed if ok else None
