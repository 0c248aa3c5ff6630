"""crater_synth.terrain.register and the committed Shackleton layers: registration, artefact repair, products."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crater_core import geometry as g
from crater_synth.terrain import register as R
from crater_synth.terrain.dem import Dem
from data_manifest import products

STEREO_SOUTH = "+proj=stere +lat_0=-90 +lat_ts=-90 +lon_0=0 +k=1 +x_0=0 +y_0=0 +R=1737400 +units=m +no_defs"
PRODUCT_DIR = R.PRODUCT_DIR


def test_layers_are_registered_embedded_products(tmp_path):
    doc = json.loads((PRODUCT_DIR / "registration.json").read_text())
    for pid, px in (("shackleton_lola_200m", 200.0), ("shackleton_lola_40m", 40.0)):
        p = products.get_product(pid)
        assert p["source"] == "embedded" and p["kind"] == "dem" and "Unlicense" in p["licence"]
        path = products.resolve_product(pid, tmp_path)  # sha256-verified
        assert path.parent == PRODUCT_DIR
        dem = Dem(path, product=pid)
        assert dem.pixel_size_m == px and (dem.height, dem.width) == (256, 256)
        out = doc["outputs"][path.name]
        assert out["sha256"] == p["sha256"] and list(dem.transform)[:6] == pytest.approx(out["transform"], abs=1e-3)
    # The registration found by the fit (provenance in the README beside the files).
    reg = doc["registration"]
    assert reg["orientation"] == "identity" and reg["height_frame"] == "pole_tangent_plane"
    assert reg["rms_m"] < 5.0 and reg["diagnostics"]["rms_by_height_frame_m"]["sphere"] > 50.0
    assert max(reg["sigma_jackknife_m"]["x"], reg["sigma_jackknife_m"]["y"]) < 10.0


def test_missing_project_file_names_git(tmp_path, monkeypatch):
    monkeypatch.setattr(products, "PROJECT_ROOT", tmp_path)
    with pytest.raises(products.ProductMissingError, match="git"):
        products.resolve_product("shackleton_lola_200m", tmp_path)


def test_source_crops_decode_and_square_repair():
    c200 = R.read_godot_exr(PRODUCT_DIR / "dem_shackridge_200m_256x256.exr")
    c40 = R.read_godot_exr(PRODUCT_DIR / "dem_shackzoom_40m_256x256.exr")
    assert c200.min() == pytest.approx(-3550.3, abs=0.5) and c200.max() == pytest.approx(1873.4, abs=0.5)
    zoom = R.fit_zoom_origin(c200, c40)
    assert zoom["origin_px"] == pytest.approx([R.ZOOM_ORIGIN_PX] * 2, abs=0.1)
    assert zoom["lowering_m"] == pytest.approx(146.0, abs=3.0) and zoom["lowering_rms_m"] < 6.0
    raw = R.square_edge_steps(c200)["steps_m"]
    fixed = R.square_edge_steps(R.repair_square(c200, c40))
    assert min(abs(v) for v in raw.values()) > 100.0
    assert max(abs(v) for v in fixed["steps_m"].values()) < 2.0 * max(fixed["noise_m"], 0.5)
    # Pixels outside the square are untouched.
    out = R.repair_square(c200, c40)
    mask = np.ones_like(c200, dtype=bool)
    mask[R.SQUARE_START : R.SQUARE_START + R.SQUARE_SIZE, R.SQUARE_START : R.SQUARE_START + R.SQUARE_SIZE] = False
    assert np.array_equal(out[mask], c200[mask])


@pytest.fixture(scope="module")
def synthetic_reference(tmp_path_factory):
    """A smooth 200 m 'truth' around the pole and its 1600 m footprint-mean reference DEM."""
    import rasterio
    from affine import Affine
    from scipy import ndimage

    rng = np.random.default_rng(5)
    n, px = 512, 200.0  # 102.4 km
    truth = ndimage.gaussian_filter(rng.standard_normal((n, n)), 12.0)
    truth *= 1500.0 / truth.std()
    ref = R.block_mean(truth, 8)
    left = top = n / 2 * px
    path = tmp_path_factory.mktemp("reg") / "ref.tif"
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=ref.shape[1],
        height=ref.shape[0],
        count=1,
        dtype="float32",
        crs=STEREO_SOUTH,
        transform=Affine(1600.0, 0, -left, 0, -1600.0, top),
    ) as dst:
        dst.write(ref.astype(np.float32), 1)
    return truth, Dem(path), -left, top


def test_register_recovers_known_placement(synthetic_reference):
    """A crop cut at a known sub-pixel corner, rotated, in the pole's tangent plane and offset by 7 m
    is found again: orientation, corner to a few metres, dz, and the height frame."""
    from scipy import ndimage

    truth, ref, left, top = synthetic_reference
    dr, dc = 131.37, 96.62  # crop corner in truth pixels
    rows = dr + np.arange(160) + 0.5 - 0.5
    cols = dc + np.arange(160) + 0.5 - 0.5
    rg, cg = np.meshgrid(rows, cols, indexing="ij")
    crop = ndimage.map_coordinates(truth, [rg, cg], order=3)
    x0, y0 = left + dc * 200.0, top - dr * 200.0
    xs = x0 + (np.arange(160) + 0.5) * 200.0
    ys = y0 - (np.arange(160) + 0.5) * 200.0
    crop = crop - g.curvature_drop_m(np.hypot(xs[None, :], ys[:, None])) - 7.0
    scrambled = np.rot90(crop.T, -1)  # the inverse of orient(., rot90=1, transpose=True)
    assert np.array_equal(R.orient(scrambled, 1, True), crop)
    reg = R.register_crop(scrambled, 200.0, ref)
    assert (reg.rot90, reg.transpose) == (1, True) and reg.height_frame == "pole_tangent_plane"
    assert reg.x0_m == pytest.approx(x0, abs=2.0) and reg.y0_m == pytest.approx(y0, abs=2.0)  # found: 0.1 m
    assert reg.dz_m == pytest.approx(7.0, abs=0.5) and reg.rms_m < 5.0
    assert reg.sigma_jackknife_m["x"] < 20.0 and reg.misfit_doubling_shift_m["x"] < 400.0


def test_register_refuses_bad_ratio(synthetic_reference):
    _, ref, _, _ = synthetic_reference
    with pytest.raises(R.RegistrationError, match=">= 2 crop pixels"):
        R.register_crop(np.zeros((64, 64)), 1000.0, ref)


@pytest.mark.slow
def test_committed_layers_rebuild_byte_identically():
    """``python -m crater_synth.tools.register_crop --check``: the committed GeoTIFFs are what the fit makes."""
    from crater_synth.tools.register_crop import main

    assert main(["--check"]) == 0
