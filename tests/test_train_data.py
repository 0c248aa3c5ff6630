"""Synthetic data loading: cache, split without leakage, refusal of real data, clear errors."""

import json
import shutil

import numpy as np
import pytest
import torch

from crater_core import schema
from crater_synth.config import load_settings
from train import data as tdata
from train.data import build_datasets, check_synthetic_rows, load_rows, split_rows
from train.errors import DatasetError, RealDataLeakError
from train.toydata import write_toy_dataset

torch.set_num_threads(1)
TOY = dict(
    sun_elevations=(15.0, 30.0),
    sun_azimuths=(0.0, 180.0),
    cam_elevations=(90.0, 70.0),
    cam_azimuths=(0.0, 120.0, 240.0),
    rim_px=32.0,
)


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    d = tmp_path_factory.mktemp("toy")
    write_toy_dataset(d, **TOY)
    return d


def _cfg(dataset_dir, tmp_path, *extra):
    """The typed settings train/ takes, for the toy dataset."""
    return load_settings(
        [
            f"train.dataset_dir={dataset_dir}",
            f"data_dir={tmp_path}",
            f"run_dir={tmp_path}/run",
            f"train.cache_dir={tmp_path}/cache",
            "train.num_threads=1",
            "train.progress=false",
            *extra,
        ]
    )


def _copy(toy, tmp_path):
    d = tmp_path / "ds"
    shutil.copytree(toy, d)
    return d


def test_datasets_cache_and_samples(toy, tmp_path, monkeypatch):
    cfg = _cfg(toy, tmp_path)
    data = build_datasets(cfg)
    n_rows = 3 * 24
    assert len(data.train) + len(data.val) == n_rows * 3  # one sample per (row, sigma)
    assert data.info["cache_built"] and data.info["sigmas"] == [1.0, 1.2, 1.4]
    x, y = data.train[0]
    assert x.shape == (1, 150, 150) and x.dtype == torch.float32 and 0 <= float(x.min()) and float(x.max()) <= 1
    assert isinstance(y, int) and set(data.train.labels) == {0, 1, 2}
    # Epoch-dependent noise for training, fixed for validation.
    data.train.set_epoch(1)
    a = data.train.image(0)
    data.train.set_epoch(2)
    assert not np.array_equal(a, data.train.image(0))
    assert np.array_equal(data.val.image(0), data.val.image(0))
    # Second build: no EXR is decoded.
    monkeypatch.setattr(
        tdata, "read_exr_channel_and_header", lambda *a, **k: pytest.fail("EXR decoded despite the cache")
    )
    again = build_datasets(cfg)
    assert not again.info["cache_built"] and again.info["cache"] == data.info["cache"]
    # A different preprocessing configuration is a different cache entry.
    monkeypatch.undo()
    other = build_datasets(_cfg(toy, tmp_path, "train.preprocess.interp_order=3"))
    assert other.info["cache"] != data.info["cache"]


def test_split_holds_out_whole_camera_poses(toy, tmp_path):
    data = build_datasets(_cfg(toy, tmp_path))
    rows = data.train.rows

    def poses(ds):
        return {
            (rows[ri]["cam_elevation"], rows[ri]["cam_azimuth"]) for ri, _ in (ds.cache.samples[j] for j in ds.indices)
        }

    tr, va = poses(data.train), poses(data.val)
    assert tr and va and not (tr & va) and len(tr | va) == 6
    assert data.info["split_by"] == "camera"
    # Seeded: the same seed gives the same split, a different one (typically) another.
    r = load_rows(toy)
    assert (
        split_rows(r, 0.2, "camera", 0, ["shackleton", "de_gerlache", "shoemaker"])[1]
        == split_rows(r, 0.2, "camera", 0, ["shackleton", "de_gerlache", "shoemaker"])[1]
    )
    sun = split_rows(r, 0.3, "sun", 0, ["shackleton", "de_gerlache", "shoemaker"])
    assert sun[2]["split_by"] == "sun"


def test_real_rows_and_real_files_are_refused(toy, tmp_path):
    rows = load_rows(toy)
    real_like = {
        "crater": "shackleton",
        "source": "lroc_wac_south",
        "image_path": "wac_south.jpg",
        "box": [0, 0, 10, 10],
        "sigma": 1.0,
        "role": "test",
    }
    with pytest.raises(RealDataLeakError, match="real images are only ever test data"):
        check_synthetic_rows([rows[0], real_like], toy)
    with pytest.raises(RealDataLeakError, match="not a render-manifest row"):
        check_synthetic_rows([{k: v for k, v in rows[0].items() if k != "sun_elevation"}], toy)
    with pytest.raises(RealDataLeakError, match="sha256 of a real test image"):
        check_synthetic_rows(rows, toy, forbidden_sha256={rows[5]["sha256"]})
    with pytest.raises(RealDataLeakError, match="points at a real test image"):
        check_synthetic_rows(rows, toy, forbidden_paths=[toy / rows[3]["path"]])
    # The configured mosaic's checksum is refused even when the caller forgets to pass it.
    d = _copy(toy, tmp_path)
    r = load_rows(d)
    r[0]["sha256"] = load_settings([]).realset.mosaic.sha256
    schema.write_manifest(d / schema.MANIFEST_NAME, r)
    with pytest.raises(RealDataLeakError):
        build_datasets(_cfg(d, tmp_path))
    # And the trainer accepts nothing but synthetic datasets.
    from train.trainer import require_synthetic

    with pytest.raises(RealDataLeakError):
        require_synthetic(torch.utils.data.TensorDataset(torch.zeros(2, 1, 150, 150), torch.zeros(2)))


def test_missing_exr_names_the_file(toy, tmp_path):
    d = _copy(toy, tmp_path)
    victim = load_rows(d)[7]["path"]
    (d / victim).unlink()
    with pytest.raises(DatasetError, match=f"{victim}.*does not exist"):
        build_datasets(_cfg(d, tmp_path))


def test_corrupt_exr_names_the_file(toy, tmp_path):
    d = _copy(toy, tmp_path)
    victim = load_rows(d)[4]["path"]
    (d / victim).write_bytes(b"not an exr at all" * 10)
    with pytest.raises(DatasetError, match=f"{victim}.*sha256"):
        build_datasets(_cfg(d, tmp_path))
    # Without checksum verification the decoder itself reports the corrupt file.
    with pytest.raises(DatasetError, match=f"{victim}"):
        build_datasets(_cfg(d, tmp_path, "train.verify_sha256=false"))


def test_empty_class_is_a_clear_error(toy, tmp_path):
    d = _copy(toy, tmp_path)
    rows = [r for r in load_rows(d) if r["crater"] != "de_gerlache"]
    schema.write_manifest(d / schema.MANIFEST_NAME, rows)
    with pytest.raises(DatasetError, match=r"empty class.*de_gerlache"):
        build_datasets(_cfg(d, tmp_path))


def test_missing_manifest_and_unsplittable_dataset(tmp_path):
    with pytest.raises(DatasetError, match="no manifest.jsonl"):
        build_datasets(_cfg(tmp_path / "nothing", tmp_path))
    d = tmp_path / "one"
    write_toy_dataset(
        d, sun_elevations=(20.0,), sun_azimuths=(0.0,), cam_elevations=(90.0,), cam_azimuths=(0.0,), rim_px=16.0
    )
    with pytest.raises(DatasetError, match="single camera pose and a single sun direction"):
        build_datasets(_cfg(d, tmp_path))


def test_cache_index_records_its_key(toy, tmp_path):
    data = build_datasets(_cfg(toy, tmp_path))
    meta = json.loads((tdata.Path(data.info["cache"]) / "index.json").read_text())
    assert meta["key"].startswith("crops-" + schema.manifest_digest(load_rows(toy)))


@pytest.mark.integration
def test_cache_built_by_worker_processes_equals_the_serial_build(toy, tmp_path, monkeypatch):
    """Large caches are built by a process pool (chunks of rows, each writing its slice of the
    memmap): the same array, and a bad file still ends the build with an error naming it."""
    from train.preprocess import PreprocessConfig

    rows = load_rows(toy)
    monkeypatch.setattr(tdata, "CACHE_ROWS_PER_CHUNK", 10)  # 72 rows: 8 chunks, so the pool is used
    serial = tdata.build_cache(rows, toy, [1.0, 1.4], PreprocessConfig(), tmp_path / "c1", workers=1)
    pooled = tdata.build_cache(rows, toy, [1.0, 1.4], PreprocessConfig(), tmp_path / "c2", workers=2)
    assert pooled.built and pooled.samples == serial.samples
    np.testing.assert_array_equal(np.asarray(pooled.images), np.asarray(serial.images))

    d = _copy(toy, tmp_path)
    victim = rows[50]["path"]
    (d / victim).write_bytes(b"not an exr at all" * 10)
    with pytest.raises(DatasetError, match=f"{victim}.*sha256"):
        tdata.build_cache(rows, d, [1.0], PreprocessConfig(), tmp_path / "c3", workers=2)
    assert not [p for p in (tmp_path / "c3").iterdir() if p.is_dir()], "a half-built cache was left behind"


def test_subsets_of_a_dataset_share_its_cache(toy, tmp_path, monkeypatch):
    """A grid subset at one sigma (a Figure 6 point, a loop round) picks samples from the whole
    dataset's cache: no EXR is decoded again, and each picked crop is the one the full build made."""
    full = build_datasets(_cfg(toy, tmp_path))
    monkeypatch.setattr(tdata, "read_exr_channel_and_header", lambda *a, **k: pytest.fail("EXR decoded for a subset"))
    sub = build_datasets(
        _cfg(toy, tmp_path, "train.sigmas=[1.2]", "+train.select={sun_azimuth:[0.0],cam_elevation:[90.0]}")
    )
    assert not sub.info["cache_built"] and sub.info["cache"] == full.info["cache"]
    assert sub.info["sigmas"] == [1.2]
    picked = [sub.train.sample_info(i) for i in range(len(sub.train))] + [
        sub.val.sample_info(i) for i in range(len(sub.val))
    ]
    assert len(picked) == 3 * 2 * 3  # 3 craters x 2 sun elevations x 3 camera azimuths, one sigma
    assert {p["sigma"] for p in picked} == {1.2}
    rows = {r["path"]: r for r in load_rows(toy)}
    assert {rows[p["path"]]["sun_azimuth"] for p in picked} == {0.0}
    assert {rows[p["path"]]["cam_elevation"] for p in picked} == {90.0}
    # Same cached array, so the same crop as in the full build.
    j = int(sub.train.indices[0])
    assert np.array_equal(np.asarray(sub.train.cache.images[j]), np.asarray(full.train.cache.images[j]))


def test_budget_cut_keeps_a_seeded_subsample(toy, tmp_path):
    full = build_datasets(_cfg(toy, tmp_path))
    cut = _cfg(toy, tmp_path, "train.max_train_images=50", "train.max_val_images=20")
    a, b = build_datasets(cut), build_datasets(cut)
    assert (len(a.train), len(a.val)) == (50, 20) and a.info["train_images"] == 50
    assert np.array_equal(a.train.indices, b.train.indices)  # same seed, same subsample
    assert set(a.train.indices) <= set(full.train.indices) and set(a.val.indices) <= set(full.val.indices)
    other = build_datasets(_cfg(toy, tmp_path, "train.max_train_images=50", "seed=1"))
    assert not np.array_equal(a.train.indices, other.train.indices)
