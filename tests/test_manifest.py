"""The render manifest: append-only parts, tolerant reads, atomic sorted merges."""

import json

import pytest

from crater_core import schema


def make_row(crater="shackleton", index=0, se=0.16, sa=0.0, ce=90.0, ca=0.0, **kw):
    row = {
        "schema_version": schema.SCHEMA_VERSION,
        "crater": crater,
        "index": index,
        "indices": [0, 0, 0, index],
        "sun_elevation": se,
        "sun_azimuth": sa,
        "cam_elevation": ce,
        "cam_azimuth": ca,
        "range_m": 31500.0,
        "fov_deg": 90.0,
        "width": 212,
        "height": 212,
        "frame_width": 450,
        "crop_origin": [119, 119],
        "center_px": [106.0, 106.0],
        "rim_ellipse": {"cu": 106.0, "cv": 106.0, "a": 75.0, "b": 75.0, "angle_rad": 0.0},
        "sigma_boxes": {"1.0": [31.0, 31.0, 181.0, 181.0]},
        "lit_fraction": 0.5,
        "mean_if": 0.01,
        "path": schema.render_rel_path(crater, se, sa, ce, ca),
        "sha256": "0" * 64,
        "seed": 1,
        "code_version": "test",
        "renderer": "fast",
        "terrain_id": "t",
        "render_digest": "d",
    }
    row.update(kw)
    return row


def test_validate_rejects_missing_and_mistyped_fields():
    row = make_row()
    del row["sha256"]
    with pytest.raises(schema.ManifestError, match="sha256"):
        schema.validate_row(row)
    with pytest.raises(schema.ManifestError, match="mean_if"):
        schema.validate_row(make_row(mean_if="bright"))


def test_truncated_last_line_is_skipped_but_strict_read_names_it(tmp_path):
    part = tmp_path / "p.jsonl"
    schema.append_row(part, make_row(index=0, ca=0.0))
    schema.append_row(part, make_row(index=1, ca=24.0))
    with open(part, "a") as fh:  # a writer killed mid-line
        fh.write(json.dumps(make_row(index=2, ca=48.0))[:40])
    assert [r["index"] for r in schema.iter_rows(part)] == [0, 1]
    with pytest.raises(schema.ManifestError, match=r"p.jsonl:3"):
        list(schema.iter_rows(part, strict=True))


def test_merge_is_sorted_deduplicated_and_byte_stable(tmp_path):
    parts = tmp_path / schema.PARTS_DIR
    schema.append_row(parts / "b.jsonl", make_row("shoemaker", 0))
    schema.append_row(parts / "a.jsonl", make_row("shackleton", 1, ca=24.0))
    schema.append_row(parts / "a.jsonl", make_row("shackleton", 0))
    schema.append_row(parts / "b.jsonl", make_row("shackleton", 0, mean_if=0.02))  # later duplicate wins
    assert schema.merge_parts(tmp_path) == 3
    first = (tmp_path / schema.MANIFEST_NAME).read_bytes()
    rows = schema.load_manifest(tmp_path)
    assert [(r["crater"], r["cam_azimuth"]) for r in rows] == [
        ("shackleton", 0.0),
        ("shackleton", 24.0),
        ("shoemaker", 0.0),
    ]
    assert rows[0]["mean_if"] == 0.02
    assert not list(parts.glob("*.jsonl"))
    schema.write_manifest(tmp_path / "again.jsonl", reversed(rows))
    assert (tmp_path / "again.jsonl").read_bytes() == first


def test_atomic_write_leaves_old_file_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "m.jsonl"
    schema.atomic_write_text(target, "old\n")

    def disk_full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(schema.os, "fsync", disk_full)
    with pytest.raises(OSError, match="No space"):
        schema.atomic_write_text(target, "new\n")
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["m.jsonl"]
