"""The real test set: 300 crops per crater inside the mosaic, deterministic, labels files, and no
path from the real set into training."""

import ast
import shutil
from pathlib import Path

import numpy as np
import pytest

from crater_core.settings import replace
from crater_synth.config import load_settings
from train.errors import RealSetError
from train.realset import build_real_test_set, load_labels_file, load_mosaic, plan_embedded_crops, plan_real_crops

CLASSES = ["shackleton", "de_gerlache", "shoemaker"]


@pytest.fixture(scope="module")
def cfg():
    return load_settings([])


@pytest.fixture(scope="module")
def craters(cfg):
    return [c.as_dict() for c in cfg.craters]


@pytest.fixture(scope="module")
def mosaic(cfg):
    return load_mosaic(cfg.realset)


def test_300_crops_per_crater_inside_the_mosaic(cfg, craters, mosaic):
    crops = plan_embedded_crops(mosaic.image.shape, mosaic, craters, cfg.realset)
    assert mosaic.image.shape == (3048, 3048) and mosaic.image.dtype == np.uint8
    for c in craters:
        mine = [k for k in crops if k.crater == c["name"]]
        assert len(mine) == 300
        assert {k.sigma for k in mine} == {1.0, 1.2, 1.4}
        assert sorted(np.unique([k.sigma for k in mine], return_counts=True)[1]) == [100, 100, 100]
        d_px = c["diameter_km"] * 1000 / 400.0
        cu, cv = mosaic.latlon_to_uv(c["lat"], c["lon"])
        for k in mine:
            u0, v0, u1, v1 = k.box
            assert u1 - u0 == pytest.approx(k.sigma * d_px) and v1 - v0 == pytest.approx(k.sigma * d_px)
            assert abs(0.5 * (u0 + u1) - cu - k.offset_px[0]) < 1e-6 and abs(k.offset_frac[0]) <= 0.08
            # The rotated sampling square lies inside the mosaic (no padding needed).
            half = 0.5 * (u1 - u0) * (abs(np.cos(np.radians(k.rotation_deg))) + abs(np.sin(np.radians(k.rotation_deg))))
            cx, cy = 0.5 * (u0 + u1), 0.5 * (v0 + v1)
            assert half <= cx <= 3048 - half and half <= cy <= 3048 - half
            assert k.source == "lroc_wac_south"
    rows = [k.as_row() for k in crops]
    assert all(r["role"] == "test" and len(r["box"]) == 4 for r in rows)


def test_crop_plan_is_deterministic_for_the_seed(cfg, craters, mosaic):
    a = [k.as_row() for k in plan_embedded_crops(mosaic.image.shape, mosaic, craters, cfg.realset)]
    b = [k.as_row() for k in plan_embedded_crops(mosaic.image.shape, mosaic, craters, cfg.realset)]
    c = [k.as_row() for k in plan_embedded_crops(mosaic.image.shape, mosaic, craters, replace(cfg.realset, seed=7))]
    assert a == b and a != c


def test_projection_matches_the_shared_geometry(mosaic):
    from crater_core.geometry import south_polar_stereo_forward

    for lat, lon in ((-89.67, 129.78), (-88.5, -87.1), (-88.1, 44.9), (-85.0, 200.0)):
        x, y = south_polar_stereo_forward(lat, lon)
        u, v = mosaic.latlon_to_uv(lat, lon)
        assert u == pytest.approx((x + 609600) / 400) and v == pytest.approx((609600 - y) / 400)


def test_real_test_set_images(cfg, craters):
    small = replace(cfg, **{"realset.per_crater": 6})
    ts = build_real_test_set(small, craters, CLASSES)
    assert ts.images.shape == (18, 150, 150) and ts.images.dtype == np.float32
    assert ts.images.min() >= 0 and ts.images.max() <= 1 and ts.images.max() > 0.5
    assert list(np.bincount(ts.labels)) == [6, 6, 6] and ts.sources == ["lroc_wac_south"]


def test_tampered_mosaic_is_refused(cfg, mosaic, tmp_path):
    bad = tmp_path / "wac_south.jpg"
    shutil.copy(mosaic.path, bad)
    with open(bad, "r+b") as fh:
        fh.seek(5000)
        fh.write(b"\x00\x01\x02")
    with pytest.raises(RealSetError, match="sha256"):
        load_mosaic(replace(cfg.realset, **{"mosaic.path": str(bad)}))


def _png(path, arr):
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(arr.shape[1], arr.shape[0], 1, oiio.UINT8))
    out.write_image(arr)
    out.close()


def test_labels_file_plugs_in_user_frames(cfg, craters, mosaic, tmp_path):
    _png(tmp_path / "frame.png", np.ascontiguousarray(mosaic.image[1400:1700, 1400:1700]))
    (tmp_path / "labels.csv").write_text(
        "image_path,crater,center_u,center_v,diameter_px,source\n"
        "frame.png,Shackleton,142.7,139.5,52.5,lroc_nac\n"
        "frame.png,de Gerlache,9.9,117.7,81.25,selene_tc\n"
    )
    crops = load_labels_file(tmp_path / "labels.csv", CLASSES, [1.0, 1.2])
    assert [(c.crater, c.source, c.sigma) for c in crops] == [
        ("shackleton", "lroc_nac", 1.0),
        ("shackleton", "lroc_nac", 1.2),
        ("de_gerlache", "selene_tc", 1.0),
        ("de_gerlache", "selene_tc", 1.2),
    ]
    rs = replace(cfg.realset, include_embedded=False, labels_file=str(tmp_path / "labels.csv"))
    # de Gerlache sits at the frame's edge: its box leaves the image by more than 25 % -> clear error.
    with pytest.raises(RealSetError, match="leaves"):
        plan_real_crops(rs, craters, CLASSES)
    (tmp_path / "labels.csv").write_text(
        "image_path,crater,box_u0,box_v0,box_u1,box_v1,source\nframe.png,shoemaker,10,10,110,110,selene_hdtv\n"
    )
    ts = build_real_test_set(replace(cfg, realset=rs), craters, CLASSES)
    assert ts.sources == ["selene_hdtv"] and len(ts.labels) == 3 and set(ts.labels) == {2}


@pytest.mark.parametrize(
    "csv, match",
    [
        (
            "image_path,crater,center_u,center_v,diameter_px,source\nframe.png,Faustini,10,10,5,x\n",
            "unknown crater 'Faustini'",
        ),
        ("image_path,crater,source\nframe.png,shackleton,x\n", "needs columns"),
        ("image_path,crater,center_u,center_v,diameter_px,source\nnope.png,shackleton,10,10,5,x\n", "does not exist"),
        ("image_path,crater,center_u,center_v,diameter_px,source\nframe.png,shackleton,10,ten,5,x\n", "bad number"),
    ],
)
def test_bad_labels_files(tmp_path, csv, match):
    _png(tmp_path / "frame.png", np.zeros((20, 20), np.uint8))
    (tmp_path / "labels.csv").write_text(csv)
    with pytest.raises(RealSetError, match=match):
        load_labels_file(tmp_path / "labels.csv", CLASSES, [1.0])


def _train_imports(module_file: Path) -> set[str]:
    tree = ast.parse(module_file.read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
    return out


def test_realset_has_no_path_to_the_training_loader():
    """Transitive import graph of train.realset inside the package: no train.data / train.trainer."""
    root = Path(__file__).resolve().parent.parent
    seen, todo = set(), ["train.realset"]
    while todo:
        mod = todo.pop()
        if mod in seen:
            continue
        seen.add(mod)
        f = root / (mod.replace(".", "/") + ".py")
        if f.is_file():
            todo += [m for m in _train_imports(f) if m.startswith("train")]
    assert "train.data" not in seen and "train.trainer" not in seen and "train.pipeline" not in seen
    assert not any(
        m.startswith(("bpy", "blender_gen")) for f in (root / "train").glob("*.py") for m in _train_imports(f)
    )
