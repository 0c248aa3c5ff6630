"""A detection frame's label file (crater_core.detection_labels): exact round trip, deterministic bytes, one
fault per bad file, and resumption that renders a frame again when its label file changed."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crater_core import detection_labels as L
from crater_core import schema
from crater_core.verify_file import row_files
from crater_synth.config import load_settings
from crater_synth.dataset import detection as D
from crater_synth.dataset import detection_run as R
from crater_synth.navigation.rendered import training_rows
from crater_synth.outfolder import OutFolder


def _label(i: int, lit=0.5, hidden=0.0) -> dict:
    return {
        "id": i,
        "source": "procedural",
        "ellipse": {"cu": 10.25 + i, "cv": 3.0, "a": 4.1234, "b": 3.9, "angle_rad": -0.9799},
        "centre_px": [10.251 + i, 3.001],
        "x_m": 68094.678,
        "y_m": -1.5,
        "diameter_m": 641.932,
        "rim_diameter_m": 962.899,
        "depth_m": 29.441,
        "rim_height_m": -0.544,
        "degradation": 0.8238,
        "class": "complex" if i % 2 else "simple",
        "is_secondary": bool(i % 3 == 0),
        "visible_rim_fraction": 0.7812,
        "emission_deg": 20.334,
        "rim_inside": True,
        "lit_rim_fraction": lit,
        "occluded_rim_fraction": hidden,
        "occluded": False,
    }


LABELS = [_label(0), _label(1, lit=None, hidden=None), _label(2, lit=0.0)]


def test_labels_round_trip_exactly_through_the_file_and_the_same_labels_are_the_same_bytes():
    data = L.encode(LABELS)
    assert L.from_columns(L.decode(data, "x")) == LABELS  # None fractions come back None, floats bit for bit
    assert L.encode(LABELS) == data  # fixed zip times: the row's sha256 is the labels'
    assert L.encode(LABELS[:2]) != data
    assert L.from_columns(L.decode(L.encode([]), "empty")) == []
    cols = L.to_columns(LABELS)
    assert cols["ellipse"].shape == (3, 5) and cols["centre_px"].shape == (3, 2) and cols["id"].dtype == np.int64
    assert np.isnan(cols["lit_rim_fraction"][1]) and cols["class"].tolist() == ["simple", "complex", "simple"]


def test_a_field_some_labels_lack_is_refused_and_one_none_lack_is_left_out():
    with pytest.raises(ValueError, match="lit_rim_fraction"):
        L.to_columns([LABELS[0], {k: v for k, v in LABELS[1].items() if k != "lit_rim_fraction"}])
    without = [{k: v for k, v in lb.items() if k != "occluded"} for lb in LABELS]
    assert "occluded" not in L.to_columns(without) and L.from_columns(L.to_columns(without)) == without


def _written(tmp_path, labels=LABELS):
    rel = "frame_000007.labels.npz"
    ref = L.write_label_file(tmp_path / rel, labels, rel)
    return {"index": 7, "rel_path": "frame_000007.exr", "labels": ref}


def test_a_row_reads_its_labels_from_its_file_or_inline(tmp_path):
    row = _written(tmp_path)
    assert row["labels"] == {
        "file": "frame_000007.labels.npz",
        "sha256": schema.sha256_file(tmp_path / "frame_000007.labels.npz"),
        "count": 3,
        "format": L.LABEL_FILE_FORMAT,
    }
    assert L.read_labels(tmp_path, row) == LABELS and L.label_count(row) == 3
    some = L.read_label_columns(tmp_path, row, ["ellipse", "occluded"])  # only the columns asked for
    assert sorted(some) == ["ellipse", "occluded"] and np.array_equal(some["ellipse"], L.to_columns(LABELS)["ellipse"])
    assert L.with_labels(tmp_path, row) == row | {"labels": LABELS} and row["labels"]["count"] == 3  # a copy
    assert L.label_rel_paths(row) == ["frame_000007.labels.npz"]
    assert row_files("detection", row) == ["frame_000007.exr", "frame_000007.labels.npz"]
    inline = {"index": 1, "rel_path": "frame_000001.exr", "labels": LABELS}
    assert L.read_labels(tmp_path, inline) == LABELS and L.label_count(inline) == 3 and L.label_rel_paths(inline) == []
    assert L.label_file_faults(tmp_path, inline) == [] and L.label_file_faults(tmp_path, row) == []
    assert L.label_file_name("sub/frame_000003.exr") == "sub/frame_000003.labels.npz"


@pytest.mark.parametrize(
    "spoil, says",
    [
        (lambda p, row: p.unlink(), "missing or unreadable"),
        (lambda p, row: p.write_bytes(L.encode(LABELS[:1])), "sha256 differs"),
        (lambda p, row: p.write_bytes(b"not a zip"), "not a detection label file"),
        (lambda p, row: row["labels"].update(count=5), "3 labels, the row says 5"),
        (lambda p, row: row["labels"].update(file="../elsewhere.npz"), "label file"),
    ],
)
def test_each_bad_label_file_is_one_fault_naming_it(tmp_path, spoil, says):
    (tmp_path / "set").mkdir()
    row = _written(tmp_path / "set")
    spoil(tmp_path / "set" / "frame_000007.labels.npz", row)
    faults = L.label_file_faults(tmp_path / "set", row, sha="sha256" in says)  # unhashed: the later checks
    assert len(faults) == 1 and says in faults[0] and ("frame_000007" in faults[0] or "elsewhere" in faults[0])
    if "sha256" not in says:  # a reader that does not hash still refuses it, with one error naming the file
        with pytest.raises(L.LabelFileError):
            L.read_label_columns(tmp_path / "set", row)


def test_a_rerun_renders_again_a_frame_whose_label_file_changed(tmp_path):
    """Resumption keeps a frame only when its EXR and its label file are both unchanged since written."""
    out = tmp_path / "set"
    settings = load_settings(D.detection_overrides(["detection.width_px=96"]))
    folder = OutFolder(out, R.KIND, subject=f"recipe {R.recipe_key(settings)}").claim()
    rows = {}
    for i in range(4):
        rel = D.frame_rel_path(i)
        (out / rel).write_bytes(b"frame %d" % i)
        name = L.label_file_name(rel)
        rows[i] = {"index": i, "rel_path": rel, "labels": L.write_label_file(out / name, LABELS[: i + 1], name)}
    folder.record([*(n for i in rows for n in R.frame_files(i)), "manifest.jsonl"])
    folder.seal([n for i in rows for n in R.frame_files(i)])
    (out / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows.values()))
    folder.seal(["manifest.jsonl"])
    (out / L.label_file_name(D.frame_rel_path(1))).unlink()
    L.write_label_file(out / L.label_file_name(D.frame_rel_path(2)), LABELS, "rewritten")
    kept, done = R.kept_rows(folder, range(0, 3))
    folder.release()
    assert done == {0} and sorted(kept) == [0, 3] and kept[0]["labels"] == 1


def test_training_reads_the_same_rim_circles_from_a_label_file_as_from_inline_labels(tmp_path):
    """slim_row of a row referencing its label file (columns, no dict per crater) equals slim_row of the same
    labels inline: centres, radii, diameters and the hidden flags (dark rim, unknown lit fraction: lit)."""
    labels = [*LABELS, _label(3, lit=0.01), dict(_label(4), occluded=True)]
    rel = "frame_000007.labels.npz"
    base = {"index": 7, "rel_path": "frame_000007.exr", "ground_sample_m": 60.0, "terrain": {"field": 0}}
    with_file = base | {"labels": L.write_label_file(tmp_path / rel, labels, rel)}
    from_file = training_rows.slim_row(with_file, tmp_path)["circles"]
    inline = training_rows.slim_row(base | {"labels": labels})["circles"]
    assert all(np.array_equal(a, b) for a, b in zip(from_file, inline))
    assert from_file[4].tolist() == [False, False, True, True, True]
    with pytest.raises(ValueError, match="folder"):
        training_rows.slim_row(with_file)
