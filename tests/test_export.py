"""`crater-synth export`: a smoke sweep round-trips through Hugging Face `datasets` (Parquet) and
`webdataset` (tar shards) with lossless images and every manifest label; an interrupted export
leaves complete shards only, and a rerun completes it."""

from __future__ import annotations

import glob
import io
import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from crater_core.exr import read_exr, stored_dtype
from crater_core.schema import load_manifest
from crater_synth.dataset import export as ex
from crater_synth.outfolder import LOCK_NAME, MARKERS

from helpers.export import interrupt_at_sample

BOOKKEEPING = (MARKERS["export"], LOCK_NAME)  # the export folder's marker and lock (crater_synth.outfolder)

os.environ.setdefault("HF_HUB_OFFLINE", "1")  # local files only: the test never needs the network
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")

ALL = ["IF", "depth", "N.X", "N.Y", "N.Z", "lit"]


@pytest.fixture(scope="module")
def dataset(tiny_smoke):
    return tiny_smoke  # sweep=smoke, one crater: 4 renders; the directory is named "smoke"


def _expected(dataset, row):
    chans, _ = read_exr(dataset / row["path"])
    return {c: chans[c].astype(stored_dtype(c)) for c in ALL}


def _npy(b: bytes) -> np.ndarray:
    return np.load(io.BytesIO(b), allow_pickle=False)


def test_parquet_round_trip_through_hugging_face_datasets(dataset, tmp_path):
    import datasets

    out = tmp_path / "pq"
    index = ex.export_dataset(dataset, out, "parquet", channels=ALL, shard_rows=3, row_group_rows=2)
    assert index["rows"] == 4 and [s["file"] for s in index["shards"]] == [
        "data-00000-of-00002.parquet",
        "data-00001-of-00002.parquet",
    ]
    files = sorted(glob.glob(str(out / "*.parquet")))
    ds = datasets.load_dataset("parquet", data_files=files, split="train", cache_dir=str(tmp_path / "hf"))
    rows = {r["path"]: r for r in load_manifest(dataset)}
    assert len(ds) == 4
    for rec in ds:
        row = rows[rec["path"]]
        want = _expected(dataset, row)
        for c in ALL:
            got = _npy(rec[f"{ex.column_name(c)}_npy"])
            assert got.dtype == want[c].dtype and np.array_equal(got, want[c]), c  # lossless, bit for bit
        assert _npy(rec["if_npy"]).dtype == np.float32 and _npy(rec["lit_npy"]).dtype == np.float16
        assert json.loads(rec["labels_json"]) == row  # every manifest label, verbatim
        assert rec["crater"] == row["crater"] and rec["sha256"] == row["sha256"]
        for k in ("sun_elevation", "sun_azimuth", "cam_elevation", "cam_azimuth", "range_m", "fov_deg"):
            assert rec[k] == row[k]
        assert rec["rim_ellipse"] == row["rim_ellipse"]
        assert {str(b["sigma"]): b["box"] for b in rec["sigma_boxes"]} == row["sigma_boxes"]


def test_webdataset_round_trip(dataset, tmp_path):
    import webdataset as wds

    out = tmp_path / "wds"
    index = ex.export_dataset(dataset, out, "webdataset", shard_rows=3)
    assert index["channels"] == {"IF": {"column": "if.npy"}}
    urls = [str(out / s["file"]) for s in index["shards"]]
    rows = {r["path"]: r for r in load_manifest(dataset)}
    seen = 0
    for sample in wds.WebDataset(urls, shardshuffle=False).decode():
        meta = sample["json"]
        row = rows[meta["path"]]
        assert meta["manifest_row"] == row and meta["key"] == sample["__key__"]
        assert meta["rim_ellipse"] == row["rim_ellipse"] and meta["sha256"] == row["sha256"]
        want = _expected(dataset, row)["IF"]
        assert sample["if.npy"].dtype == np.float32 and np.array_equal(sample["if.npy"], want)
        seen += 1
    assert seen == 4


@pytest.mark.parametrize("fmt", ex.FORMATS)
def test_interrupted_export_leaves_no_half_written_shard(dataset, tmp_path, monkeypatch, fmt):
    out = tmp_path / fmt
    interrupt_at_sample(monkeypatch, "render", 4)  # the second shard's second sample
    with pytest.raises(KeyboardInterrupt):
        ex.export_dataset(dataset, out, fmt, shard_rows=2, row_group_rows=1)
    names = sorted(p.name for p in out.iterdir() if p.name not in BOOKKEEPING)
    first = ex.EXPORT_WRITERS[fmt].shard_name(0, 2)
    assert names == [first]  # the complete first shard only: no second shard, no temporary, no index
    if fmt == "parquet":
        import pyarrow.parquet as pq

        assert pq.read_table(out / first).num_rows == 2
    else:
        import tarfile

        with tarfile.open(out / first) as tf:
            assert len(tf.getnames()) == 4  # 2 samples x (if.npy, json)
    monkeypatch.undo()
    index = ex.export_dataset(dataset, out, fmt, shard_rows=2)  # a rerun completes it
    assert index["rows"] == 4 and (out / ex.INDEX_FILE).is_file()
    with pytest.raises(ex.ExportError, match="already holds a complete export"):
        ex.export_dataset(dataset, out, fmt, shard_rows=2)


def test_bad_inputs_are_one_error_and_write_nothing(dataset, tmp_path):
    runner = CliRunner()
    from crater_synth.cli import main

    res = runner.invoke(main, ["export", str(dataset), "--format", "parquet", "--channels", "IF,albedo"])
    assert res.exit_code == 2 and res.stderr.startswith("error: export channels ['albedo']")
    assert not (dataset.parent / "smoke-parquet").exists()
    (tmp_path / "empty").mkdir()
    with pytest.raises(ex.ExportError, match="no manifest.jsonl"):
        ex.export_dataset(tmp_path / "empty", tmp_path / "o", "webdataset")
    assert not (tmp_path / "o").exists()
    with pytest.raises(ex.ExportError, match="outside the dataset"):
        ex.export_dataset(dataset, dataset / "export", "parquet")

    # A damaged EXR: the checksum check stops the export; no shard, no temporary is left.
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(dataset, bad)
    row = load_manifest(bad)[1]
    (bad / row["path"]).write_bytes(b"not an exr")
    with pytest.raises(ex.ExportError, match="sha256"):
        ex.export_dataset(bad, tmp_path / "bad-out", "parquet", shard_rows=10)
    assert not (tmp_path / "bad-out").exists()  # created by the failed run, removed by it


def test_cli_prints_the_index(dataset, tmp_path):
    from crater_synth.cli import main

    res = CliRunner().invoke(main, ["export", str(dataset), "--format", "webdataset", "--out", str(tmp_path / "w")])
    assert res.exit_code == 0, res.output
    line = json.loads(res.stdout.strip().splitlines()[-1])
    assert line["rows"] == 4 and line["shards"] == 1 and line["format"] == "webdataset"


def test_each_format_names_and_recognises_only_its_own_shards():
    # _prepare_out clears an interrupted export by these names: a format must not claim another's files.
    for fmt, writer in ex.EXPORT_WRITERS.items():
        names = [writer.shard_name(i, 3) for i in range(3)]
        assert len(set(names)) == 3 and all(writer.is_shard_file(n) for n in names), fmt
        for other in ex.EXPORT_WRITERS.values():
            if other is not writer:
                assert not any(other.is_shard_file(n) for n in names), (fmt, other.name)
