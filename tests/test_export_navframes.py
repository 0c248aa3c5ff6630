"""`crater-synth export` of navigation frames (record kind ``navframe``): two real tiny frames of
``descent_ridge`` round-trip through Hugging Face `datasets` (Parquet) and `webdataset` with bit-identical
images and every label, the landmarks as a list of structs; the kind is detected from the manifest, a
mismatched ``--kind`` is one error line, and an interrupted export leaves no half-written shard."""

from __future__ import annotations

import glob
import io
import json
import os
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from crater_core.exr import read_exr, stored_dtype
from crater_synth.dataset import export as ex
from crater_synth.outfolder import LOCK_NAME, MARKERS

from helpers.cli import run_nav_frames
from helpers.export import interrupt_at_sample

BOOKKEEPING = (MARKERS["export"], LOCK_NAME)  # the export folder's marker and lock (crater_synth.outfolder)

os.environ.setdefault("HF_HUB_OFFLINE", "1")  # local files only: the test never needs the network
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")

ALL = ["IF", "depth", "N.X", "N.Y", "N.Z", "lit"]
LANDMARK_FIELDS = (
    "id",
    "name",
    "diameter_km",
    "lat",
    "lon",
    "centre_px",
    "depth_m",
    "ellipse",
    "rim_inside",
    "lit_rim_fraction",
    "occluded_rim_fraction",
)


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Two real frames (64 px, fast mode, one sample) of descent_ridge, as in tests/test_navframes.py."""
    tmp = tmp_path_factory.mktemp("navexport")
    out = tmp / "frames"
    proc = run_nav_frames(tmp / "data", out, "0,1")
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out


def load_manifest(frames) -> list[dict]:
    """The nav-frames manifest's rows (JSON Lines; not a render manifest, so not crater_core.schema's reader)."""
    return [json.loads(line) for line in (frames / "manifest.jsonl").read_text().splitlines() if line.strip()]


def _rows(frames) -> dict[str, dict]:
    return {r["rel_path"]: r for r in load_manifest(frames)}


def _expected(frames, row):
    chans, _ = read_exr(frames / row["rel_path"])
    return {c: chans[c].astype(stored_dtype(c)) for c in ALL}


def _npy(b: bytes) -> np.ndarray:
    return np.load(io.BytesIO(b), allow_pickle=False)


def _landmarks(row) -> list[dict]:
    """The manifest's landmark labels with every typed field (a missing lit-rim fraction is null)."""
    return [{k: lm.get(k) for k in LANDMARK_FIELDS} for lm in row["landmarks"]]


def _check_labels(rec: dict, row: dict) -> None:
    assert rec["trajectory"] == "descent_ridge" and rec["frame_index"] == row["index"]
    assert rec["sha256"] == row["sha256"] and rec["rel_path"] == row["rel_path"]
    assert rec["camera_position_m"] == row["camera_enu"]["position_m"]
    assert rec["camera_rotation"] == row["camera_enu"]["rotation"]
    assert rec["camera_position_mc_m"] == row["pose"]["position_mc_m"]
    assert (rec["sun_elevation_deg"], rec["sun_azimuth_deg"]) == (
        row["sun_enu"]["elevation_deg"],
        row["sun_enu"]["azimuth_deg"],
    )
    assert (rec["frame_origin_lat"], rec["frame_origin_lon"]) == (
        row["frame_origin"]["lat"],
        row["frame_origin"]["lon"],
    )
    assert rec["ground_sample_m"] == row["ground_sample_m"]
    assert rec["footprint_half_width_m"] == row["footprint_half_width_m"]
    assert (rec["width_px"], rec["fov_deg"], rec["altitude_m"]) == (
        row["pose"]["width_px"],
        row["pose"]["fov_deg"],
        row["pose"]["altitude_m"],
    )
    assert rec["landmarks"] == _landmarks(row)  # exactly, ellipses and nullable lit-rim fractions included
    assert rec["landmark_map_sha256"] == row["landmark_map"]["sha256"] and rec["label_version"] == 3


def test_kind_is_detected_from_the_manifest(frames):
    rows = load_manifest(frames)
    assert len(rows) == 2 and all(len(r["landmarks"]) > 5 for r in rows)  # a real test: frames with landmarks
    assert ex.detect_kind(frames) == "navframe"


def test_parquet_round_trip_through_hugging_face_datasets(frames, tmp_path):
    import datasets

    out = tmp_path / "pq"
    index = ex.export_dataset(frames, out, "parquet", channels=ALL, shard_rows=1)
    assert index["record_kind"] == "navframe" and index["rows"] == 2 and len(index["shards"]) == 2
    files = sorted(glob.glob(str(out / "*.parquet")))
    ds = datasets.load_dataset("parquet", data_files=files, split="train", cache_dir=str(tmp_path / "hf"))
    rows = _rows(frames)
    assert len(ds) == 2 and ds[0]["key"] == "descent_ridge_frame_0000" and ds[1]["frame_index"] == 1
    import pyarrow as pa

    lm_type = ds.data.schema.field("landmarks").type  # typed, not JSON text
    assert lm_type.value_type.field("ellipse").type.field("a").type == pa.float64()
    assert lm_type.value_type.field("lit_rim_fraction").nullable
    for rec in ds:
        row = rows[rec["rel_path"]]
        want = _expected(frames, row)
        for c in ALL:
            got = _npy(rec[f"{ex.column_name(c)}_npy"])
            assert got.dtype == want[c].dtype and np.array_equal(got, want[c]), c  # lossless, bit for bit
        assert json.loads(rec["labels_json"]) == row  # the whole manifest row, verbatim
        _check_labels(rec, row)


def test_webdataset_round_trip(frames, tmp_path):
    import webdataset as wds

    out = tmp_path / "wds"
    index = ex.export_dataset(frames, out, "webdataset", channels=["IF", "lit"], kind="navframe")
    urls = [str(out / s["file"]) for s in index["shards"]]
    rows = _rows(frames)
    seen = []
    for sample in wds.WebDataset(urls, shardshuffle=False).decode():
        meta = sample["json"]
        row = rows[meta["rel_path"]]
        assert meta["manifest_row"] == row and meta["key"] == sample["__key__"] and meta["record_kind"] == "navframe"
        _check_labels(meta, row)
        want = _expected(frames, row)
        assert sample["if.npy"].dtype == np.float32 and np.array_equal(sample["if.npy"], want["IF"])
        assert sample["lit.npy"].dtype == np.float16 and np.array_equal(sample["lit.npy"], want["lit"])
        seen.append(meta["frame_index"])
    assert seen == [0, 1]  # the manifest's (frame) order


@pytest.mark.parametrize("fmt", ex.FORMATS)
def test_interrupted_export_leaves_no_half_written_shard(frames, tmp_path, monkeypatch, fmt):
    out = tmp_path / fmt
    interrupt_at_sample(monkeypatch, "navframe", 2)  # the second shard's only sample
    with pytest.raises(KeyboardInterrupt):
        ex.export_dataset(frames, out, fmt, shard_rows=1)
    first = ex.EXPORT_WRITERS[fmt].shard_name(0, 2)
    assert sorted(p.name for p in out.iterdir() if p.name not in BOOKKEEPING) == [
        first
    ]  # no second shard, no temporary, no index
    monkeypatch.undo()
    index = ex.export_dataset(frames, out, fmt, shard_rows=1)  # a rerun completes it
    assert index["rows"] == 2 and (out / ex.INDEX_FILE).is_file()


def test_kind_mismatch_and_bad_frames_are_one_error(frames, tmp_path):
    from crater_synth.cli import main

    runner = CliRunner()
    res = runner.invoke(main, ["export", str(frames), "--format", "parquet", "--kind", "render"])
    assert res.exit_code == 2 and len(res.stderr.strip().splitlines()) == 1, res.output
    assert res.stderr.startswith("error: dataset ") and "holds navframe records, not render" in res.stderr
    assert not (frames.parent / "frames-parquet").exists()
    res = runner.invoke(main, ["export", str(frames), "--format", "webdataset", "--out", str(tmp_path / "w")])
    assert res.exit_code == 0, res.output
    line = json.loads(res.stdout.strip().splitlines()[-1])
    assert line["record_kind"] == "navframe" and line["rows"] == 2

    # A manifest of neither kind.
    odd = tmp_path / "odd"
    odd.mkdir()
    (odd / "manifest.jsonl").write_text(json.dumps({"index": 0, "sha256": "0"}) + "\n")
    with pytest.raises(ex.ExportError, match="neither a render manifest"):
        ex.export_dataset(odd, tmp_path / "odd-out", "parquet")
    assert not (tmp_path / "odd-out").exists()

    # A damaged frame: the checksum check stops the export; no shard, no temporary is left.
    bad = tmp_path / "bad"
    shutil.copytree(frames, bad, ignore=shutil.ignore_patterns(".*"))
    (bad / load_manifest(bad)[1]["rel_path"]).write_bytes(b"not an exr")
    with pytest.raises(ex.ExportError, match="sha256"):
        ex.export_dataset(bad, tmp_path / "bad-out", "parquet", shard_rows=10)
    assert not (tmp_path / "bad-out").exists()  # created by the failed run, removed by it
