"""Georeferenced real frames (train/realframes.py): the embedded WAC mosaic reprojected with
rasterio.warp into a local orthographic lunar CRS at 300 m/px, ingested as a frame, gives the
mosaic's crops (same ground footprints within 1 px, same accuracy of a fixed classifier within 0.01);
bad frames give one clear error."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from crater_core.settings import FrameSettings, replace
from crater_synth.config import ConfigError, compose, load_settings, resolved
from train.errors import RealSetError
from train.preprocess import PreprocessConfig, box_axes
from train.realframes import open_frame, plan_frames, reference_to_frame
from train.realset import PolarGrid, build_real_test_set, load_mosaic, plan_embedded_crops

CLASSES = ["shackleton", "de_gerlache", "shoemaker"]
ORTHO = "+proj=ortho +lat_0=-88.8 +lon_0=60 +x_0=0 +y_0=0 +R=1737400 +units=m +no_defs"
PER = 100  # crops per crater: 300 in all, so 0.01 of accuracy is 3 crops


@pytest.fixture(scope="module")
def cfg():
    return replace(load_settings([]), **{"realset.per_crater": PER})


@pytest.fixture(scope="module")
def craters(cfg):
    return [c.as_dict() for c in cfg.craters if c.name in CLASSES]


def _with_frames(rs, *entries, **changes):
    """``realset`` settings whose ``frames`` are these entries (FrameSettings fields)."""
    return replace(rs, frames=tuple(FrameSettings(**e) for e in entries), **changes)


def _write(path, array, crs, transform, **extra):
    import rasterio

    profile = dict(driver="GTiff", width=array.shape[1], height=array.shape[0], count=1, dtype=array.dtype.name)
    if crs is not None:
        profile.update(crs=crs, transform=transform)
    profile.update(extra)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # NotGeoreferencedWarning for the deliberately bare file
        with rasterio.open(path, "w", **profile) as ds:
            ds.write(array, 1)
    return path


def _reprojected(mosaic, path, pixel_m=300.0, half_m=(62_000.0, 100_000.0), center=(-15_000.0, -17_500.0), crs=ORTHO):
    """The mosaic warped (bilinear) into ``crs`` at ``pixel_m``, a window of half-size ``half_m``."""
    from rasterio.crs import CRS
    from rasterio.transform import from_origin
    from rasterio.warp import Resampling, reproject

    g = mosaic.grid
    src_t = from_origin(-g.extent_m, g.extent_m, g.pixel_m, g.pixel_m)
    w, h = int(2 * half_m[0] / pixel_m), int(2 * half_m[1] / pixel_m)
    dst_t = from_origin(center[0] - half_m[0], center[1] + half_m[1], pixel_m, pixel_m)
    dst = np.zeros((h, w), dtype=np.float32)
    reproject(
        mosaic.image.astype(np.float32),
        dst,
        src_transform=src_t,
        src_crs=CRS.from_proj4(g.proj4),
        dst_transform=dst_t,
        dst_crs=CRS.from_proj4(crs),
        resampling=Resampling.bilinear,
    )
    return _write(path, dst, crs, dst_t)


@pytest.fixture(scope="module")
def frame_tif(cfg, tmp_path_factory):
    mosaic = load_mosaic(cfg.realset)
    return _reprojected(mosaic, tmp_path_factory.mktemp("frames") / "wac_ortho_300m.tif")


def _frame_cfg(cfg, **entry):
    return replace(cfg, realset=_with_frames(cfg.realset, entry, include_embedded=False))


def _features(images: np.ndarray) -> np.ndarray:
    """A fixed, rotation-invariant description of each crop: mean and spread in 16 rings."""
    n, s, _ = images.shape
    c = np.arange(s) + 0.5 - s / 2
    ring = np.minimum((np.hypot(c[None, :], c[:, None]) / (s / 2) * 16).astype(int), 16).ravel()
    flat = images.reshape(n, -1)
    counts = np.bincount(ring, minlength=17)[:16]
    mean = np.stack([np.bincount(ring, w, minlength=17)[:16] for w in flat]) / counts
    sq = np.stack([np.bincount(ring, w * w, minlength=17)[:16] for w in flat]) / counts
    return np.hstack([mean, np.sqrt(np.maximum(sq - mean**2, 0))])


def test_reprojected_mosaic_frame_matches_the_mosaic(cfg, craters, frame_tif):
    rs = cfg.realset
    mosaic = load_mosaic(rs)
    grid = mosaic.grid
    ref = plan_embedded_crops(mosaic.image.shape, mosaic, craters, rs)
    crops, images = plan_frames(_with_frames(rs, {"path": str(frame_tif), "frame_id": "ortho300"}), craters)
    assert len(crops) == len(ref) == 3 * PER
    frame = open_frame(frame_tif, "ortho300")
    assert frame.image.shape == (666, 413)

    # Same ground footprints: each frame crop's sampling corners, carried back to mosaic pixels, lie
    # within 1 px of the mosaic crop's rotated box corners.
    from rasterio.crs import CRS
    from rasterio.warp import transform as warp_transform

    st = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]).T
    worst = 0.0
    for f, m in zip(crops, ref):
        assert (f.crater, f.index, f.sigma, f.rotation_deg) == (m.crater, m.index, m.sigma, m.rotation_deg)
        assert f.kind == "frame" and f.frame_id == "ortho300" and f.source == "ortho300"
        fc = np.array([(f.box[0] + f.box[2]) / 2, (f.box[1] + f.box[3]) / 2])[:, None] + np.reshape(f.axes, (2, 2)) @ st
        x, y = frame.uv_to_xy(fc[0], fc[1])
        px, py = warp_transform(frame.crs, CRS.from_proj4(grid.proj4), list(x), list(y))
        back_u, back_v = (np.array(px) + grid.extent_m) / grid.pixel_m, (grid.extent_m - np.array(py)) / grid.pixel_m
        cu, cv = (m.box[0] + m.box[2]) / 2, (m.box[1] + m.box[3]) / 2
        mc = np.array([cu, cv])[:, None] + box_axes(m.box[2] - m.box[0], m.box[3] - m.box[1], m.rotation_deg) @ st
        worst = max(worst, float(np.max(np.hypot(back_u - mc[0], back_v - mc[1]))))
    assert worst < 1.0, worst
    # The pixels the report shows (no photometry) agree too: same ground, resampled from another grid.
    from train.realcrops import crop_pixels

    for f, m in list(zip(crops, ref))[::50]:
        a, b = crop_pixels(images[str(frame_tif)], f, 48), crop_pixels(mosaic.image, m, 48)  # both in DN
        assert float(np.mean(np.abs(a - b))) / 255.0 < 0.03
    # The frame crops are 4/3 larger in frame pixels (400 m mosaic px -> 300 m frame px).
    side_f = np.hypot(*np.reshape(crops[0].axes, (2, 2))[:, 0])
    assert side_f == pytest.approx((ref[0].box[2] - ref[0].box[0]) * 400 / 300, rel=0.01)

    # The same accuracy of a fixed classifier (nearest ring-profile centroid, centroids from the
    # mosaic crops of another seed) on both crop sets.
    pp = PreprocessConfig(size=64, support="disc")
    mos_set = build_real_test_set(cfg, craters, CLASSES, pp)
    frm_set = build_real_test_set(_frame_cfg(cfg, path=str(frame_tif), frame_id="ortho300"), craters, CLASSES, pp)
    assert [c.kind for c in frm_set.crops] == ["frame"] * 3 * PER
    train_cfg = replace(cfg, **{"realset.seed": 99, "realset.per_crater": 30})
    tr = build_real_test_set(train_cfg, craters, CLASSES, pp)
    ftr = _features(tr.images)
    cent = np.stack([ftr[tr.labels == k].mean(0) for k in range(3)])

    def predict(images):
        return np.argmin(((_features(images)[:, None, :] - cent[None]) ** 2).sum(-1), axis=1)

    acc_m = float(np.mean(predict(mos_set.images) == mos_set.labels))
    acc_f = float(np.mean(predict(frm_set.images) == frm_set.labels))
    print(f"frame vs mosaic: worst corner {worst:.3f} mosaic px, accuracy {acc_f:.3f} vs {acc_m:.3f}")
    assert 0.4 < acc_m < 1.0  # the classifier is informative but not perfect, so the test can fail
    assert abs(acc_f - acc_m) <= 0.01, (acc_m, acc_f)
    assert float(np.mean(np.abs(frm_set.images - mos_set.images))) < 0.05
    rows = frm_set.rows()
    assert all(r["frame_id"] == "ortho300" and len(r["box"]) == 4 and len(r["axes"]) == 4 for r in rows)


def test_frames_config_group_composes():
    c = resolved(compose(["realset=frames"]))
    rs = c["realset"]
    assert rs["include_embedded"] is False
    assert [f["frame_id"] for f in rs["frames"]] == ["M101457600MC", "M139810920MC", "TC1W2B0_01_00582S883E2719"]
    over = resolved(compose(["realset=frames", "realset.frames=[{path: /x.tif, frame_id: x, craters: [shoemaker]}]"]))
    assert over["realset"]["frames"] == [
        {"path": "/x.tif", "frame_id": "x", "source": None, "band": 1, "craters": ["shoemaker"]}
    ]
    with pytest.raises(ConfigError, match=r"realset\.frames\[0\]\.band=0: must be >= 1"):
        compose(["realset.frames=[{path: /x.tif, band: 0}]"])
    # Offline the frames are not fetched: one clear error naming the product and fetch-data.
    with pytest.raises(RealSetError, match="fetch-data lroc_m101457600mc"):
        plan_frames(
            load_settings(["realset=frames"]).realset, [dict(e) for e in c["crater"].values()], "/nonexistent-data-dir"
        )


def test_no_georeference(cfg, craters, tmp_path):
    p = _write(tmp_path / "bare.tif", np.ones((64, 64), np.uint8), None, None)
    with pytest.raises(RealSetError, match="has no georeference.*cam2map"):
        plan_frames(_with_frames(cfg.realset, {"path": str(p)}), craters)


def test_crater_outside_the_frame(cfg, craters, tmp_path):
    mosaic = load_mosaic(cfg.realset)
    # A window around Shackleton only; Shoemaker's centre is ~58 km away.
    p = _reprojected(mosaic, tmp_path / "small.tif", half_m=(20_000.0, 20_000.0), center=(9_400.0, -32_900.0))
    rs = _with_frames(cfg.realset, {"path": str(p), "craters": ("Shoemaker",)})
    with pytest.raises(RealSetError, match=r"crater shoemaker .* lies outside the frame"):
        plan_frames(rs, craters)


@pytest.mark.parametrize(
    "crs, body",
    [
        ("EPSG:4326", "Earth"),
        ("+proj=stere +lat_0=-90 +lon_0=0 +R=3396190 +units=m +no_defs", "Mars"),
    ],
)
def test_frame_of_another_body(cfg, craters, tmp_path, crs, body):
    from rasterio.transform import from_origin

    p = _write(tmp_path / "other.tif", np.ones((64, 64), np.uint8), crs, from_origin(0, 0, 1, 1))
    with pytest.raises(RealSetError, match=r"not the Moon") as exc:
        plan_frames(_with_frames(cfg.realset, {"path": str(p)}), craters)
    assert body in str(exc.value)


def test_truncated_frame(cfg, craters, frame_tif, tmp_path):
    data = frame_tif.read_bytes()
    p = tmp_path / "truncated.tif"
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(RealSetError, match="truncated or corrupt"):
        plan_frames(_with_frames(cfg.realset, {"path": str(p)}), craters)


def test_reference_grid_is_the_mosaic_grid(cfg):
    grid = PolarGrid.from_settings(cfg.realset)
    mosaic = load_mosaic(cfg.realset)
    assert mosaic.grid == grid
    # A frame that IS the mosaic grid maps reference pixels onto themselves.
    from rasterio.crs import CRS
    from rasterio.transform import from_origin

    from train.realframes import Frame

    f = Frame("m", "m", mosaic.path, mosaic.image, CRS.from_proj4(grid.proj4), from_origin(-609600, 609600, 400, 400))
    u, v = reference_to_frame(grid, f, [1542.7, 10.0], [1539.5, 3000.0])
    assert np.allclose(u, [1542.7, 10.0], atol=1e-6) and np.allclose(v, [1539.5, 3000.0], atol=1e-6)


def test_crops_leaving_the_frame_are_skipped_and_named(cfg, craters, tmp_path):
    """A frame that holds Shackleton with little margin: the crops whose sigma box (with its offset and
    roll) crosses the frame's edge are left out, one line each naming the frame, crop and crater; the
    others are planned and the evaluation's test set is built from them."""
    mosaic = load_mosaic(cfg.realset)
    p = _reprojected(mosaic, tmp_path / "tight.tif", half_m=(14_000.0, 14_000.0), center=(9_400.0, -32_900.0))
    entry = {"path": str(p), "frame_id": "tight", "craters": ("shackleton",)}
    skipped: list[str] = []
    crops, _ = plan_frames(_with_frames(cfg.realset, entry), craters, skipped=skipped)
    assert crops and skipped, (len(crops), len(skipped))
    assert len(crops) + len(skipped) == PER
    for line in skipped:
        assert re.fullmatch(
            r"real frame 'tight' \(tight\.tif, \d+x\d+\): crop \d+ of shackleton \(sigma=[\d.]+, roll=-?[\d.]+\) "
            r"spans pixels \[.*\], outside the frame: skipped",
            line,
        ), line
    kept = {c.index for c in crops}
    assert not kept & {int(re.search(r"crop (\d+) of", line).group(1)) for line in skipped}
    # Without a list to collect them, each is a warning rather than lost.
    with warnings.catch_warnings(record=True) as held:
        warnings.simplefilter("always")
        plan_frames(_with_frames(cfg.realset, entry), craters)
    assert [str(w.message) for w in held] == skipped
    # The evaluation's test set carries the lines (metrics.json: test_skipped_crops, test_skipped).
    test = build_real_test_set(_frame_cfg(cfg, **entry), craters, CLASSES)
    assert len(test.labels) == len(crops) and test.skipped == skipped
