"""Training-ready exports (docs/export.md): ``--shape crop|pad`` gives fixed-shape float32 tensors that a
plain ``DataLoader(batch_size=32, num_workers=2)`` batches through both formats of a mixed sweep (three
craters, two Sun and six camera conditions, crops of 42 and 44 px) and of navigation frames, every sample
once; Hugging Face ``datasets`` reads the crops as ``Array2D`` torch tensors equal to the crop cache's
function; and the classifier's training reads a crop export (``train.export_dir``) into exactly the crop
cache's arrays, without decoding an EXR."""

from __future__ import annotations

import glob
import json
import os
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from click.testing import CliRunner
from torch.utils.data import DataLoader

from crater_core import schema
from crater_core.exr import read_channel, sealed_header, write_exr
from crater_core.schema import EXR_CHANNELS
from crater_core.verify_file import navframe_header_for_row
from crater_synth.config import load_settings
from crater_synth.data import ParquetExport, WebDatasetExport, open_export
from crater_synth.dataset import export as ex
from train import data as tdata
from train.data import build_datasets
from train.errors import DatasetError
from train.preprocess import PreprocessConfig, cached_crop
from train.toydata import write_toy_dataset

os.environ.setdefault("HF_HUB_OFFLINE", "1")  # local files only: the test never needs the network
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
torch.set_num_threads(1)

CONDITIONS = dict(sun_elevations=(15.0, 30.0), sun_azimuths=(0.0, 180.0), cam_elevations=(90.0, 70.0))
CONDITIONS |= dict(cam_azimuths=(0.0, 120.0, 240.0))


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    """72 toy renders: shackleton and de Gerlache with 42 px crops, Shoemaker with 44 px ones."""
    d = tmp_path_factory.mktemp("mixed") / "ds"
    other = d.parent / "other"
    rows = write_toy_dataset(d, craters=("shackleton", "de_gerlache"), rim_px=30.0, **CONDITIONS)
    rows += write_toy_dataset(other, craters=("shoemaker",), rim_px=31.0, **CONDITIONS)
    shutil.move(other / "shoemaker", d / "shoemaker")
    schema.write_manifest(d / schema.MANIFEST_NAME, rows)
    assert {r["width"] for r in rows} == {42, 44}
    return d


@pytest.fixture(scope="module")
def navframes(tmp_path_factory):
    """Five fake 64 px navigation frames (a nav-frames directory: frame EXRs and their manifest)."""
    d = tmp_path_factory.mktemp("nav") / "frames"
    rng = np.random.default_rng(3)
    rows = []
    for i in range(5):
        rel = f"frame_{i:04d}.exr"
        chans = {c: np.full((64, 64), 0.5, np.float32) for c in EXR_CHANNELS}
        chans["IF"] = rng.random((64, 64), dtype=np.float32) * 0.1
        lm = {"id": 7, "name": "x", "diameter_km": 5.0, "ellipse": {"cu": 30.0, "cv": 31.0, "a": 9, "b": 8}}
        pose = {"index": i, "position_mc_m": [0.0, 0.0, 1746400.0 + i], "rotation_mc": np.eye(3).tolist()}
        pose |= {"fov_deg": 30.0, "width_px": 64, "altitude_m": 9000.0 + i, "heading_deg": 0.0}
        pose |= {"subcam_lat": 90.0, "subcam_lon": 0.0, "target_lat": 90.0, "target_lon": 0.0, "to_sun_mc": [1, 0, 0]}
        row = {"trajectory": "t", "index": i, "rel_path": rel, "landmarks": [lm], "pose": pose}
        row |= {"frame_origin": {"lat": 90.0, "lon": 0.0}, "mode": "fast", "terrain_id": "fake"}
        row |= {"lit_fraction": 0.5, "mean_if": float(chans["IF"].mean())}
        # The labels in the header and a seal, as `crater-synth nav-frames` writes them: export checks both.
        row["sha256"] = write_exr(d / rel, chans, sealed_header(chans, navframe_header_for_row(row)))
        rows.append(row)
    (d / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return d


def _pp() -> PreprocessConfig:
    s = load_settings()
    return PreprocessConfig.from_settings(s.train.preprocess, s.model.input_size)


def _epoch(ds, **kw) -> list:
    """Every batch of one pass of a plain DataLoader (default collate) with two workers."""
    return list(DataLoader(ds, batch_size=32, num_workers=2, **kw))


@pytest.mark.parametrize("fmt", ex.FORMATS)
def test_crop_export_batches_through_a_plain_dataloader(mixed, tmp_path, fmt):
    out = tmp_path / fmt
    index = ex.export_dataset(mixed, out, fmt, shape="crop", shard_rows=40, row_group_rows=16)
    assert index["rows"] == 72 * 3 and len(index["shards"]) == 6  # one sample per (row, sigma)
    assert index["shape"]["mode"] == "crop" and index["shape"]["sigmas"] == [1.0, 1.2, 1.4]
    assert index["shape"]["size"] == 150 and index["shape"]["shape"] == [150, 150]
    ds = open_export(out)
    assert isinstance(ds, ParquetExport if fmt == "parquet" else WebDatasetExport) and len(ds) == 216
    if fmt == "webdataset":  # the choice travels with every sample (Parquet: the schema metadata, below)
        assert next(ds.records()).labels["export"] == index["shape"]
    keys, sigmas = [], []
    for images, labels in _epoch(ds):
        assert images.dtype == torch.float32 and images.shape[1:] == (1, 150, 150) and len(images) <= 32
        assert labels["sun_elevation"].dtype == torch.float64 and isinstance(labels["crater"], list)
        assert set(labels["rim_ellipse"]) == {"cu", "cv", "a", "b", "angle_rad"}
        keys += labels["key"]
        sigmas += labels["sigma"].tolist()
    assert sorted(keys) == sorted(set(keys)) and len(keys) == 216  # every sample once, with two workers
    assert sorted(set(sigmas)) == [1.0, 1.2, 1.4]
    # The crop is the crop cache's own: the sigma box of the EXR's IF through train.preprocess.cached_crop.
    rows = {r["path"]: r for r in schema.load_manifest(mixed)}
    for images, labels in _epoch(ds):
        for img, path, sigma in zip(images[:3], labels["path"], labels["sigma"].tolist()):
            row = rows[path]
            box = row["sigma_boxes"][f"{sigma:.1f}"]
            want = cached_crop(read_channel(mixed / row["path"], "IF"), box, _pp())
            assert torch.equal(img[0], torch.from_numpy(want))
        break


@pytest.mark.parametrize("fmt", ex.FORMATS)
def test_pad_export_batches_with_its_mask(mixed, tmp_path, fmt):
    out = tmp_path / fmt
    index = ex.export_dataset(mixed, out, fmt, shape="pad", channels=["IF", "lit"], shard_rows=20)
    assert index["shape"] | {"shape": None} == {
        "mode": "pad",
        "shape": None,
        "dtype": "float32",
        "pad_value": 0.0,
        "anchor": "top-left",
        "mask": "valid",
        "original_shape": ["orig_height", "orig_width"],
    }
    assert index["shape"]["shape"] == [44, 44]
    rows = {r["path"]: r for r in schema.load_manifest(mixed)}
    seen = []
    for images, labels in _epoch(open_export(out)):
        assert images.shape[1:] == (2, 44, 44) and labels["valid"].dtype == torch.bool
        for img, valid, h, w, path in zip(
            images, labels["valid"], labels["orig_height"], labels["orig_width"], labels["path"]
        ):
            want = read_channel(mixed / path, "IF")
            assert (int(h), int(w)) == want.shape == (rows[path]["height"], rows[path]["width"])
            assert torch.equal(img[0, :h, :w], torch.from_numpy(want))  # top-left anchored, values as stored
            assert int(valid.sum()) == h * w and bool(valid[:h, :w].all()) and float(img[:, ~valid].abs().sum()) == 0
            seen.append(path)
    assert sorted(seen) == sorted(rows)


@pytest.mark.parametrize("fmt", ex.FORMATS)
@pytest.mark.parametrize("shape", ["pad", "native"])
def test_navigation_frames_batch_through_a_plain_dataloader(navframes, tmp_path, fmt, shape):
    out = tmp_path / f"{fmt}-{shape}"
    index = ex.export_dataset(navframes, out, fmt, shape=shape, channels=["IF", "lit"], shard_rows=2)
    assert index["record_kind"] == "navframe" and index["shape"]["mode"] == shape
    batches = _epoch(open_export(out, channels=["IF"]))
    keys = [k for _, labels in batches for k in labels["key"]]
    assert sorted(keys) == [f"t_frame_{i:04d}" for i in range(5)]
    for images, labels in batches:
        assert images.shape[1:] == (1, 64, 64)
        assert labels["altitude_m"].dtype == torch.float64 and labels["frame_index"].dtype == torch.int64
        for img, rel in zip(images, labels["rel_path"]):
            assert torch.equal(img[0], torch.from_numpy(read_channel(navframes / rel, "IF")))
    rec = open_export(out).records().__next__() if fmt == "webdataset" else open_export(out).record(0)
    assert rec.labels["landmarks"][0]["name"] == "x" and rec.row["trajectory"] == "t"  # the list labels, kept
    with pytest.raises(ex.ExportError, match="--shape crop needs sigma boxes"):
        ex.export_dataset(navframes, tmp_path / "crop", fmt, shape="crop")


def test_hugging_face_reads_fixed_shape_exports_as_torch_tensors(mixed, tmp_path):
    import datasets

    out = tmp_path / "pq"
    index = ex.export_dataset(mixed, out, "parquet", shape="crop", sigmas=[1.2], size=64, shard_rows=50)
    assert index["rows"] == 72 and index["shape"]["sigmas"] == [1.2] and index["shape"]["shape"] == [64, 64]
    files = sorted(glob.glob(str(out / "*.parquet")))
    meta = pq.read_schema(files[0]).metadata
    assert json.loads(meta[b"crater_synth"]) == index["shape"]  # the choice, in every shard's schema too
    hf = datasets.load_dataset("parquet", data_files=files, split="train", cache_dir=str(tmp_path / "hf"))
    assert hf.features["if"] == datasets.Array2D((64, 64), "float32")
    assert hf.features["sigma"] == datasets.Value("float64")
    # The metadata spells every other column as datasets itself would.
    assert json.loads(meta[b"huggingface"])["info"]["features"] == json.loads(json.dumps(hf.features.to_dict()))
    torch_ds = hf.with_format("torch")
    ours = ParquetExport(out)
    batch = torch_ds[0:10]["if"]
    assert isinstance(batch, torch.Tensor) and batch.shape == (10, 64, 64) and batch.dtype == torch.float32
    for i in range(10):
        image, labels = ours[i]
        assert torch_ds[i]["key"] == labels["key"] and torch.equal(batch[i], image[0])
    row = json.loads(torch_ds[3]["labels_json"])
    pp = PreprocessConfig.from_settings(load_settings().train.preprocess, 64)
    want = cached_crop(read_channel(mixed / row["path"], "IF"), row["sigma_boxes"]["1.2"], pp)
    assert torch.equal(batch[3], torch.from_numpy(want))
    # A padded export: its mask is an Array2D of uint8 as well.
    ex.export_dataset(mixed, tmp_path / "pad", "parquet", shape="pad")
    pad = datasets.load_dataset(
        "parquet", data_files=sorted(glob.glob(str(tmp_path / "pad" / "*.parquet"))), cache_dir=str(tmp_path / "hf2")
    )["train"].with_format("torch")
    assert pad.features["valid"] == datasets.Array2D((44, 44), "uint8") and pad[0]["if"].shape == (44, 44)


def test_native_exports_keep_their_bytes_and_still_load(mixed, tmp_path):
    out = tmp_path / "pq"
    index = ex.export_dataset(mixed, out, "parquet", shard_rows=100)
    assert index["shape"] == {"mode": "native"} and index["channels"] == {"IF": {"column": "if_npy"}}
    assert pq.read_schema(out / index["shards"][0]["file"]).metadata is None  # the schema exports always had
    image, labels = ParquetExport(out)[71]
    assert image.shape == (1, 44, 44) and labels["crater"] == "shoemaker"  # its own shape; a batch needs crop/pad


def test_cli_crop_defaults_come_from_the_composed_settings(mixed, tmp_path):
    from crater_synth.cli import main

    runner = CliRunner()
    out = tmp_path / "a"
    args = ["export", str(mixed), "--format", "webdataset", "--shape", "crop", "--out", str(out)]
    res = runner.invoke(main, args + ["model.input_size=96", "train.sigmas=[1.4]"])
    assert res.exit_code == 0, res.output
    index = json.loads((out / "export.json").read_text())
    assert index["shape"]["size"] == 96 and index["shape"]["sigmas"] == [1.4] and index["rows"] == 72
    res = runner.invoke(main, args + ["--overwrite", "--sigma", "1.0,1.2", "--size", "32"])
    assert res.exit_code == 0, res.output
    index = json.loads((out / "export.json").read_text())
    assert index["shape"]["size"] == 32 and index["shape"]["sigmas"] == [1.0, 1.2] and index["rows"] == 144
    res = runner.invoke(main, args + ["--overwrite", "--sigma", "1.1"])
    assert res.exit_code == 2 and "no sigma box for sigma=1.1" in res.stderr
    res = runner.invoke(
        main, ["export", str(mixed), "--format", "parquet", "--out", str(tmp_path / "b"), "--size", "9"]
    )
    assert res.exit_code == 2 and "go with --shape crop" in res.stderr and not (tmp_path / "b").exists()


def _train_cfg(tmp_path, *extra):
    return load_settings(
        [
            f"data_dir={tmp_path}",
            f"run_dir={tmp_path}/run",
            f"train.cache_dir={tmp_path}/cache",
            "train.cache_dtype=float32",
            "train.num_threads=1",
            "train.progress=false",
            *extra,
        ]
    )


@pytest.mark.parametrize("fmt", ex.FORMATS)
def test_training_reads_a_crop_export_into_the_crop_cache_arrays(mixed, tmp_path, monkeypatch, fmt):
    out = tmp_path / "export"
    ex.export_dataset(mixed, out, fmt, shape="crop", shard_rows=64)
    from_exrs = build_datasets(_train_cfg(tmp_path, f"train.dataset_dir={mixed}"))
    monkeypatch.setattr(tdata, "read_exr_channel_and_header", lambda *a, **k: pytest.fail("EXR decoded"))
    from_export = build_datasets(_train_cfg(tmp_path, f"train.export_dir={out}"))
    assert from_export.info["cache"] != from_exrs.info["cache"] and from_export.info["cache_built"]
    a, b = from_exrs.train, from_export.train
    assert a.rows == b.rows and a.cache.samples == b.cache.samples and list(a.indices) == list(b.indices)
    assert np.array_equal(np.asarray(a.cache.images), np.asarray(b.cache.images))  # the same crops, bit for bit
    assert from_exrs.info["sigmas"] == from_export.info["sigmas"] == [1.0, 1.2, 1.4]
    for i in (0, len(a) - 1):
        assert torch.equal(a[i][0], b[i][0]) and a[i][1] == b[i][1]
    monkeypatch.undo()
    # An export that is not the training's crop: one error naming it.
    ex.export_dataset(mixed, tmp_path / "small", fmt, shape="crop", size=64)
    with pytest.raises(DatasetError, match="was cropped with"):
        build_datasets(_train_cfg(tmp_path, f"train.export_dir={tmp_path / 'small'}"))
    ex.export_dataset(mixed, tmp_path / "native", fmt)
    with pytest.raises(DatasetError, match="training reads a `crater-synth export --shape crop`"):
        build_datasets(_train_cfg(tmp_path, f"train.export_dir={tmp_path / 'native'}"))


@pytest.mark.integration  # two trainings end to end (~20 s)
def test_crater_synth_train_from_an_export_gives_the_same_metrics(tmp_path):
    from crater_synth.cli import main
    from train.toydata import write_toy_frames

    toy, frames = tmp_path / "toy", write_toy_frames(tmp_path / "frames")
    write_toy_dataset(toy, sun_azimuths=(0.0, 120.0, 240.0), cam_azimuths=(0.0, 90.0, 180.0, 270.0), rim_px=40.0)
    runner = CliRunner()
    res = runner.invoke(
        main,
        [
            "export",
            str(toy),
            "--format",
            "webdataset",
            "--shape",
            "crop",
            "--out",
            str(tmp_path / "crops"),
            "model.input_size=64",
        ],
    )
    assert res.exit_code == 0, res.output
    common = [f"data_dir={tmp_path}", "train.num_threads=1", "train.progress=false", "realset.per_crater=15"]
    common += [f"realset.labels_file={frames}", "model.input_size=64", "train.batch_size=16", "train.lr=3e-3"]
    common += ["train.max_epochs=4", "train.hog.max_train_images=200"]
    metrics = {}
    for name, source in (("exrs", f"train.dataset_dir={toy}"), ("export", f"train.export_dir={tmp_path / 'crops'}")):
        args = ["train", *common, source, f"run_dir={tmp_path}/run-{name}", f"train.cache_dir={tmp_path}/cache-{name}"]
        res = runner.invoke(main, args, catch_exceptions=False)
        assert res.exit_code == 0, res.output
        m = json.loads((tmp_path / f"run-{name}" / "metrics.json").read_text())
        metrics[name] = {
            k: (m[k]["val_accuracy"], m[k]["per_source"]) for k in ("lunarnet_ex", "lunarsvm_ex", "hog_svm")
        }
    assert metrics["export"] == metrics["exrs"]  # the same crops, so the same seeded training and scores
