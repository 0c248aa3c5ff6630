"""One verification for every record kind (crater_core.verify_file): `verify` reads render datasets and
nav-frames folders, checks each row against its EXR header and the pixel seal; train, export,
nav-frames-eval and navigate run the same check (or trust a recorded pass), so none of them takes a
dataset `verify` would refuse."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from crater_core import exr, schema
from crater_core.verify_file import RECORD_NAME, trusted_paths
from crater_synth.config import load_settings
from crater_synth.dataset import export as ex
from crater_synth.dataset.verify import verify_command, verify_dataset
from crater_synth.navigation.navigate import navigate_command
from crater_synth.navigation.rendered.cli import nav_frames_eval_command
from train.data import build_datasets
from train.errors import DatasetError
from train.toydata import write_toy_dataset

from helpers.cli import run_nav_frames

torch.set_num_threads(1)
TOY = dict(sun_elevations=(15.0, 30.0), sun_azimuths=(0.0, 180.0), cam_elevations=(90.0, 70.0), rim_px=32.0)


def _rows(d: Path) -> list[dict]:
    return [json.loads(line) for line in (d / schema.MANIFEST_NAME).read_text().splitlines() if line.strip()]


def _write_rows(d: Path, rows: list[dict]) -> None:
    (d / schema.MANIFEST_NAME).write_text("".join(json.dumps(r) + "\n" for r in rows))


# ------------------------------------------------------------------------------------------------
# Render datasets
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    d = tmp_path_factory.mktemp("toy") / "ds"
    write_toy_dataset(d, **TOY)
    return d


def _train_settings(d: Path, tmp_path: Path):
    return load_settings(
        [
            f"train.dataset_dir={d}",
            f"data_dir={tmp_path}",
            f"run_dir={tmp_path}/run",
            f"train.cache_dir={tmp_path}/cache",
            "train.num_threads=1",
            "train.progress=false",
        ]
    )


def test_toy_dataset_verifies_with_its_seals(toy):
    report = verify_dataset(toy, jobs=1)
    assert report["ok"] and report["kind"] == "render", report["faults"]


def test_train_refuses_deleted_exrs_behind_cached_crops(toy, tmp_path):
    d = tmp_path / "ds"
    shutil.copytree(toy, d)
    cfg = _train_settings(d, tmp_path)
    assert build_datasets(cfg).info["cache_built"]
    for f in d.glob("*/*.exr"):
        f.unlink()
    with pytest.raises(DatasetError, match=r"\.exr does not exist"):
        build_datasets(cfg)  # the crops are cached, but their files are gone


def test_train_refuses_unmerged_manifest_parts(toy, tmp_path):
    d = tmp_path / "ds"
    shutil.copytree(toy, d)
    cfg = _train_settings(d, tmp_path)
    (d / schema.PARTS_DIR).mkdir()
    (d / schema.PARTS_DIR / f"{schema.MANIFEST_NAME}-host-12345.jsonl").write_text(json.dumps(_rows(d)[0]) + "\n")
    with pytest.raises(DatasetError, match=r"1 unmerged manifest part\(s\) in manifest.parts/") as info:
        build_datasets(cfg)
    assert "\n" not in str(info.value)


@pytest.fixture
def smoke(tiny_smoke, tmp_path):
    """A copy of the shared tiny rendered dataset (real renderer headers and seals) to damage."""
    d = tmp_path / "smoke"
    shutil.copytree(tiny_smoke, d)
    return d


def test_edited_crater_is_refused_by_verify_and_export(smoke, tmp_path):
    rows = _rows(smoke)
    was = rows[1]["crater"]
    rows[1]["crater"] = "shoemaker" if was != "shoemaker" else "shackleton"
    _write_rows(smoke, rows)
    f = smoke / rows[1]["path"]
    report = verify_dataset(smoke, jobs=1)
    assert f"{f}: row crater {rows[1]['crater']!r} but the EXR header says {was!r}" in report["faults"]
    with pytest.raises(ex.ExportError, match=rf"{f}: row crater .* but the EXR header says {was!r}"):
        ex.export_dataset(smoke, tmp_path / "out", "parquet")


def test_export_refuses_a_symlink_out_of_the_dataset(smoke, tmp_path):
    rel = _rows(smoke)[0]["path"]
    outside = tmp_path / "elsewhere.exr"
    shutil.move(smoke / rel, outside)
    (smoke / rel).symlink_to(outside)
    with pytest.raises(ex.ExportError, match=rf"{smoke / rel}: leaves the dataset directory"):
        ex.export_dataset(smoke, tmp_path / "out", "webdataset")


def _rewrite_pixels(path: Path) -> str:
    """Rewrite 25 I/F pixels, keeping every attribute the renderer wrote (seal included); the new sha256."""
    channels, header = exr.read_exr(path)
    keys = json.loads(header[exr.SEALED_ATTR]) + [exr.SEAL_ATTR]
    channels["IF"][:5, :5] += 0.01
    return exr.write_exr(path, channels, {k: header[k] for k in keys})


def test_rewritten_pixels_with_a_matching_sha256_break_the_seal(smoke):
    rows = _rows(smoke)
    f = smoke / rows[2]["path"]
    rows[2]["sha256"] = _rewrite_pixels(f)
    _write_rows(smoke, rows)
    report = verify_dataset(smoke, jobs=1)
    assert report["faults"] == [f"{f}: pixel seal broken (its pixels or header are not those its renderer wrote)"]
    assert not report["ok"] and not (smoke / RECORD_NAME).exists()
    assert verify_dataset(smoke, decode=False, jobs=1)["ok"]  # --no-decode: sha256 and header alone


def test_a_recorded_pass_covers_only_unchanged_files(smoke):
    report = verify_dataset(smoke, jobs=1)
    assert report["ok"] and report["recorded"] == str(smoke / RECORD_NAME)
    rels = {r["path"] for r in _rows(smoke)}
    assert trusted_paths(smoke, "render", decode=True) == rels
    changed = sorted(rels)[0]
    shutil.copy(smoke / changed, smoke / "x.tmp")
    (smoke / "x.tmp").replace(smoke / changed)  # same bytes, another file: checked again
    assert trusted_paths(smoke, "render") == rels - {changed}
    _write_rows(smoke, _rows(smoke)[:-1])  # another manifest: nothing is trusted
    assert trusted_paths(smoke, "render") == set()


# ------------------------------------------------------------------------------------------------
# Navigation frames
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rendered_frames(tmp_path_factory):
    """Two real frames (64 px, fast mode) of descent_ridge, as in tests/test_export_navframes.py."""
    tmp = tmp_path_factory.mktemp("navverify")
    proc = run_nav_frames(tmp / "data", tmp / "frames", "0,1")
    assert proc.returncode == 0, proc.stderr[-2000:]
    return tmp / "frames"


@pytest.fixture
def frames(rendered_frames, tmp_path):
    d = tmp_path / "frames"
    shutil.copytree(rendered_frames, d)
    return d


def _invoke(command, *args):
    return CliRunner().invoke(command, [str(a) for a in args], catch_exceptions=False)


def test_verify_reads_a_nav_frames_folder_and_records_the_pass(frames):
    v = _invoke(verify_command, frames)
    assert v.exit_code == 0, v.output
    assert "verify OK: 2 frames {'descent_ridge': 2}" in v.output
    record = json.loads((frames / RECORD_NAME).read_text())
    assert record["kind"] == "navframe" and sorted(record["files"]) == ["frame_0000.exr", "frame_0001.exr"]


def test_a_truth_pose_moved_3_km_is_refused_everywhere(frames, tmp_path):
    rows = _rows(frames)
    rows[0]["pose"]["position_mc_m"] = (np.asarray(rows[0]["pose"]["position_mc_m"]) + [3000.0, 0, 0]).tolist()
    _write_rows(frames, rows)
    fault = (
        f"{frames / 'frame_0000.exr'}: row pose.position_mc_m (off by 3000) differs from what the EXR header records"
    )
    assert fault in verify_dataset(frames, jobs=1)["faults"]
    nav = _invoke(navigate_command, frames / "frame_0000.exr", "--out", tmp_path / "nav.png")
    assert nav.exit_code != 0 and fault in nav.output
    ev = _invoke(nav_frames_eval_command, frames, "--json", tmp_path / "eval.json")
    assert ev.exit_code != 0 and fault in ev.output
    assert not (tmp_path / "eval.json").exists()


def test_a_flipped_byte_in_a_frame_is_refused(frames, tmp_path):
    f = frames / "frame_0001.exr"
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0x01
    f.write_bytes(bytes(data))
    assert verify_dataset(frames, decode=False, jobs=1)["faults"] == [f"{f}: sha256 mismatch (corrupt or changed)"]
    ev = _invoke(nav_frames_eval_command, frames, "--json", tmp_path / "eval.json")
    assert ev.exit_code != 0 and f"{f}: sha256 mismatch" in ev.output


def test_a_recorded_pass_is_not_trusted_for_a_changed_frame(frames, tmp_path):
    assert verify_dataset(frames, jobs=1)["ok"]
    f = frames / "frame_0000.exr"
    rows = _rows(frames)
    rows[0]["sha256"] = _rewrite_pixels(f)  # the manifest changes too: the record no longer holds
    _write_rows(frames, rows)
    assert verify_dataset(frames, jobs=1)["faults"] == [
        f"{f}: pixel seal broken (its pixels or header are not those its renderer wrote)"
    ]


def test_a_verified_nav_frames_folder_can_still_be_resumed(frames, rendered_frames):
    """verify's record is bookkeeping of the folder, not a user's file: nav-frames resumes past it."""
    assert _invoke(verify_command, frames).exit_code == 0 and (frames / RECORD_NAME).is_file()
    proc = run_nav_frames(rendered_frames.parent / "data", frames, "1")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert [r["index"] for r in _rows(frames)] == [0, 1]


def test_orphan_lines_say_what_the_writer_does(smoke):
    """An EXR no row names is left alone by `dataset` (docs/manifest.md); an interrupted write's temp file is
    removed by the next run. verify's lines say so."""
    exr = next(p for p in sorted(smoke.rglob("*.exr")) if not p.name.startswith("."))
    crater_dir = exr.parent
    shutil.copy2(exr, crater_dir / "extra.exr")
    (crater_dir / ".x.exr.123.tmp.exr").write_bytes(b"partial")
    v = _invoke(verify_command, smoke)
    lines = [line for line in v.output.splitlines() if line.startswith("orphan: ")]
    assert any("extra.exr" in line and "leaves it alone" in line for line in lines), lines
    assert any(".tmp.exr" in line and "the next run that writes this folder removes it" in line for line in lines)
    assert not any("removes it)" in line and "extra.exr" in line for line in lines)
