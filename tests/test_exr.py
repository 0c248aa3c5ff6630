"""The EXR container (crater_core.exr): stored channel types, lossless round trip, atomicity."""

from __future__ import annotations

import numpy as np
import pytest

from crater_core import exr
from crater_core.schema import EXR_CHANNEL_TYPES, EXR_CHANNELS

oiio = pytest.importorskip("OpenImageIO")

ENCODERS = {"openexr": exr._encode_openexr, "openimageio": exr._encode_oiio}


@pytest.fixture(params=sorted(ENCODERS))
def encoder(request, monkeypatch):
    """Each test runs with both encoders (OpenEXR binding, OpenImageIO fallback)."""
    if request.param == "openexr":
        pytest.importorskip("OpenEXR")
    monkeypatch.setattr(exr, "encoder", lambda: ENCODERS[request.param])
    return request.param


def _channels(seed: int = 0, shape=(70, 90)) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    chans = {c: rng.random(shape).astype(np.float32) for c in EXR_CHANNELS}
    chans["depth"] = (20_000.0 + 30_000.0 * chans["depth"]).astype(np.float32)
    chans["N.X"] = chans["N.X"] * 2.0 - 1.0  # signed components
    chans["IF"][0, :5] = [0.0, 1e-7, 3.3e-5, 0.12345678, 2.5]  # tiny and large radiance factors
    return chans


def test_stored_types_are_the_contract(tmp_path, encoder):
    path = tmp_path / "r.exr"
    exr.write_exr(path, _channels())
    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    inp.close()
    stored = dict(zip(spec.channelnames, (str(t) for t in spec.channelformats)))
    assert stored == EXR_CHANNEL_TYPES
    assert spec.get_string_attribute("compression") == exr.COMPRESSION
    assert (spec.tile_width, spec.tile_height) == (exr.TILE, exr.TILE)


def test_float_channels_are_bit_exact_and_half_channels_are_as_stored(tmp_path, encoder):
    chans = _channels(1)
    path = tmp_path / "r.exr"
    exr.write_exr(path, chans)
    back, _ = exr.read_exr(path)
    expected = exr.as_stored(chans)
    for name in EXR_CHANNELS:
        assert back[name].dtype == np.float32
        np.testing.assert_array_equal(back[name], expected[name], err_msg=name)  # what as_stored says, exactly
        if EXR_CHANNEL_TYPES[name] == "float":
            np.testing.assert_array_equal(back[name], chans[name], err_msg=name)  # lossless
        else:  # half: 11-bit significand, |value| <= 1
            assert np.abs(back[name] - chans[name]).max() <= 2.0**-12, name


def test_read_channels_gives_each_channel_as_read_channel_does(tmp_path, encoder):
    """One decode for several channels (the labels read lit and depth of every frame) gives each exactly
    as a read of its own; a channel the file lacks, or a non-finite one, is one error naming the file."""
    chans = _channels(3)
    path = tmp_path / "r.exr"
    exr.write_exr(path, chans)
    for names in (("lit", "depth"), ("depth", "N.Z", "IF"), ("IF",)):
        got = exr.read_channels(path, names)
        assert list(got) == list(names)
        for name in names:
            assert got[name].shape == (70, 90) and got[name].flags.c_contiguous
            np.testing.assert_array_equal(got[name], exr.read_channel(path, name), err_msg=name)
    with pytest.raises(exr.ExrError, match=r"r\.exr has no channel 'albedo'"):
        exr.read_channels(path, ("lit", "albedo"))
    chans["depth"][3, 4] = np.nan
    exr.write_exr(tmp_path / "nan.exr", chans)
    with pytest.raises(exr.ExrError, match=r"nan\.exr: channel 'depth' holds NaN"):
        exr.read_channels(tmp_path / "nan.exr", ("lit", "depth"))


def test_the_same_channels_give_the_same_bytes(tmp_path, encoder):
    a = exr.write_exr(tmp_path / "a.exr", _channels(2), {"crater_synth:x": 1})
    b = exr.write_exr(tmp_path / "b.exr", _channels(2), {"crater_synth:x": 1})
    assert a == b
    assert not list(tmp_path.glob("*.tmp*"))


def test_wrong_channel_set_names_the_file(tmp_path, encoder):
    chans = _channels()
    del chans["lit"]
    with pytest.raises(exr.ExrError, match=r"r\.exr: EXR channels"):
        exr.write_exr(tmp_path / "r.exr", chans)
    assert not list(tmp_path.iterdir())


def test_both_encoders_write_the_same_image_and_header(tmp_path, monkeypatch):
    pytest.importorskip("OpenEXR")
    header = {"crater_synth:mode": "fast", "crater_synth:index": 7, "crater_synth:sun_elevation": 0.48}
    decoded = {}
    for name, enc in ENCODERS.items():
        monkeypatch.setattr(exr, "encoder", lambda enc=enc: enc)
        exr.write_exr(tmp_path / f"{name}.exr", _channels(3), header)
        decoded[name] = exr.read_exr(tmp_path / f"{name}.exr")
    (a, ha), (b, hb) = decoded["openexr"], decoded["openimageio"]
    for c in EXR_CHANNELS:
        np.testing.assert_array_equal(a[c], b[c], err_msg=c)
    for key in [*header, "compression", "tile_width", "tile_height"]:
        assert ha[key] == hb[key], key


def test_the_default_encoder_is_the_openexr_binding():
    pytest.importorskip("OpenEXR")
    assert exr.encoder() is exr._encode_openexr


def test_the_bench_compares_every_storage_choice_and_the_project_encoder(tmp_path):
    """crater_synth.bench.renderer.exr_codecs on a toy dataset: one row per choice plus the project's
    encoder; the contract's RLE rows of both libraries store the same data (sizes within 1 %)."""
    pytest.importorskip("OpenEXR")  # the project encoder row is then the only "current" one
    from crater_synth.bench.renderer import EXR_CHOICES, exr_codecs
    from train.toydata import write_toy_dataset

    write_toy_dataset(tmp_path, craters=("shackleton",), sun_azimuths=(0.0,), cam_azimuths=(0.0, 90.0))
    rows = exr_codecs(tmp_path, n=2, repeats=1)
    assert [(r["compression"], r["channel_types"]) for r in rows[:-1]] == EXR_CHOICES
    assert [r for r in rows if r["current"]] == [rows[-1]]
    by = {(r["library"], r["compression"], r["channel_types"]): r["mean_bytes"] for r in rows}
    assert by[("OpenImageIO", "none", "float32")] == max(by.values())
    oiio_rle = by[("OpenImageIO", "rle", "contract")]
    assert abs(rows[-1]["mean_bytes"] - oiio_rle) <= 0.01 * oiio_rle
    assert all(r["encode_ms"] > 0 for r in rows)
