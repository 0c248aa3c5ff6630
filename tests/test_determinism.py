"""Same config + seed -> byte-identical manifests and EXRs: across runs, shard counts, thread counts."""

import json

import numpy as np
import pytest

from helpers.cli import EIGHT, assert_same_dataset, exr_files, summary


@pytest.fixture(scope="module")
def reference(tiny_eight):
    """One single-process run of the 8-render sweep (render.workers=1, render.threads=0)."""
    return tiny_eight


def test_two_runs_are_byte_identical(tmp_path, tiny_dataset, reference):
    tiny_dataset(tmp_path / "again", *EIGHT)
    assert_same_dataset(reference, tmp_path / "again")


@pytest.mark.integration
@pytest.mark.parametrize("n", [2, 3])
def test_shards_merge_to_the_single_run(tmp_path, tiny_dataset, reference, n):
    rendered = 0
    for i in range(n):
        rendered += summary(tiny_dataset(tmp_path / "sharded", *EIGHT, f"launcher.shard={i}/{n}"))["rendered"]
    assert rendered == 8
    assert not list((tmp_path / "sharded" / "manifest.parts").glob("*.jsonl"))  # every part merged
    assert_same_dataset(reference, tmp_path / "sharded")


def _pixels_and_header(path):
    from crater_core.exr import read_exr

    chans, header = read_exr(str(path))
    render = json.loads(header.pop("crater_synth:render"))
    return chans, header, render


@pytest.mark.integration
def test_thread_count_changes_no_pixel(tmp_path, tiny_dataset, reference):
    """Cycles with a fixed seed gives the same pixels with 1 thread as with all cores, and the
    execution-only ``render.threads`` stays out of the EXR header, so the files are byte-identical."""
    tiny_dataset(tmp_path / "t1", *EIGHT, "render.threads=1")
    for a, b in zip(exr_files(tmp_path / "t1"), exr_files(reference), strict=True):
        ca, ha, ra = _pixels_and_header(a)
        cb, hb, rb = _pixels_and_header(b)
        for name in ca:
            np.testing.assert_array_equal(ca[name], cb[name], err_msg=f"{a.name} {name}")
        assert ha == hb
        assert "threads" not in ra and "threads" not in rb
        assert ra == rb
        assert a.read_bytes() == b.read_bytes()


@pytest.mark.integration
def test_worker_count_gives_byte_identical_files(tmp_path, tiny_dataset, reference):
    tiny_dataset(tmp_path / "w2", *EIGHT, "render.workers=2")
    assert_same_dataset(reference, tmp_path / "w2")
