"""Damaged or foreign inputs end in ONE `error:` line naming the file (and the line, for a manifest row),
exit status 2, and write nothing -- never a Python traceback: a manifest line that is not UTF-8 or not a
JSON object, a render dataset's manifest given to the nav-frames commands, a corrupt model checkpoint, an
override with no key.

Tiny inputs built in tmp_path; in-process (click's CliRunner); nothing is rendered."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from crater_core import exr, schema
from crater_core.render_labels import header_for_row


def _invoke(args):
    from crater_synth.cli import main

    res = CliRunner().invoke(main, [str(a) for a in args])
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert res.exit_code == 2, (res.stdout, res.stderr)
    (line,) = res.stderr.splitlines()  # the error line is the only one
    assert line.startswith("error: ")
    return line


def _tree(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*"))


def _render_row(path: str = "shackleton/x.exr", sha256: str = "0" * 64) -> dict:
    """A manifest row as `crater-synth dataset` writes it (every schema.REQUIRED_FIELDS field)."""
    row = {
        "schema_version": schema.SCHEMA_VERSION,
        "crater": "shackleton",
        "index": 0,
        "indices": [0, 0, 0, 0],
        "sun_elevation": 5.0,
        "sun_azimuth": 0.0,
        "cam_elevation": 90.0,
        "cam_azimuth": 0.0,
        "range_m": 1000.0,
        "fov_deg": 10.0,
        "width": 8,
        "height": 8,
        "frame_width": 8,
        "crop_origin": [0, 0],
        "center_px": [4.0, 4.0],
        "rim_ellipse": {},
        "sigma_boxes": {},
        "lit_fraction": 0.5,
        "mean_if": 0.1,
        "path": path,
        "sha256": sha256,
        "seed": 0,
        "code_version": "test",
        "renderer": "test",
        "terrain_id": "test",
        "render_digest": "test",
    }
    assert schema.validate_row(row) is row
    return row


# --- crater-synth export -------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["parquet", "webdataset"])
def test_export_refuses_a_manifest_line_that_is_not_utf8_before_writing_any_shard(tmp_path, fmt):
    ds = tmp_path / "ds"
    (ds / "shackleton").mkdir(parents=True)
    row = _render_row()
    # The row's labels in the header, as the renderer writes them: export checks them.
    row["sha256"] = exr.write_exr(
        ds / "shackleton/x.exr", {c: np.zeros((8, 8), np.float32) for c in schema.EXR_CHANNELS}, header_for_row(row)
    )
    good = json.dumps(row).encode()
    (ds / "manifest.jsonl").write_bytes(good + b"\n" + b"\xff\xfe not text\n")
    before = _tree(ds)
    out = tmp_path / "out"
    line = _invoke(["export", ds, "--format", fmt, "--out", out, "--shard-rows", "1"])
    assert line == f"error: {ds / 'manifest.jsonl'}:2: unreadable row (not UTF-8 text: byte 0xff at column 1)"
    assert not out.exists() and _tree(ds) == before  # no shard from the good row above it
    # The same dataset with the bad line gone exports.
    (ds / "manifest.jsonl").write_bytes(good + b"\n")
    from crater_synth.cli import main

    res = CliRunner().invoke(main, ["export", str(ds), "--format", fmt, "--out", str(out)])
    assert res.exit_code == 0, res.output


# --- the nav-frames commands on a damaged or foreign manifest ------------------------------------
def _frames_dir(tmp_path: Path, manifest: bytes) -> Path:
    d = tmp_path / "frames"
    d.mkdir()
    (d / "manifest.jsonl").write_bytes(manifest)
    (d / "frame_0000.exr").write_bytes(b"not read: the manifest is refused first")
    return d


NAVFRAME_COMMANDS = {
    "nav-frames-eval": lambda d, tmp: ["nav-frames-eval", d, "--json", tmp / "t.json"],
    "navigate": lambda d, tmp: ["navigate", d / "frame_0000.exr", "--out", tmp / "x.png"],
    "nav-frames-relabel": lambda d, tmp: ["nav-frames-relabel", d],
    "nav-frames-lis": lambda d, tmp: ["nav-frames-lis", d, "--json", tmp / "l.json"],
}
BAD_LINES = {
    "null": (b"null\n", "line 1: JSON but not a row (a JSON object)"),
    "number": (b"42\n", "line 1: JSON but not a row (a JSON object)"),
    "not-utf8": (b"\n\xff\xfe\n", "line 2: not UTF-8 text (byte 0xff)"),
    "not-json": (b'{"index": 0\n', "line 1: not a JSON row"),
    "render-dataset": (
        (json.dumps(_render_row()) + "\n").encode(),
        "line 1: a render dataset's row (`crater-synth dataset`) without the nav-frames field(s) "
        "['trajectory', 'rel_path', 'frame_origin', 'pose', 'landmarks']: not a `crater-synth nav-frames` manifest",
    ),
}


@pytest.mark.parametrize("command", NAVFRAME_COMMANDS, ids=NAVFRAME_COMMANDS.keys())
@pytest.mark.parametrize("manifest, message", BAD_LINES.values(), ids=BAD_LINES.keys())
def test_navframe_commands_refuse_a_bad_manifest_line_naming_it(tmp_path, command, manifest, message):
    d = _frames_dir(tmp_path, manifest)
    before = {p: p.read_bytes() for p in d.iterdir()}
    line = _invoke(NAVFRAME_COMMANDS[command](d, tmp_path))
    assert line == f"error: {d / 'manifest.jsonl'} {message}"
    assert {p: p.read_bytes() for p in d.iterdir()} == before  # relabel rewrote nothing
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames"]  # no result file


# --- crater-synth evaluate with a damaged checkpoint ---------------------------------------------
class _Payload:
    """A pickle that touches a file when unpickled: what loading an untrusted checkpoint must never run."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


@pytest.mark.parametrize("kind", ["garbage", "truncated-zip", "pickled-code"])
def test_evaluate_refuses_a_damaged_checkpoint_in_one_line_and_runs_no_code_from_it(tmp_path, kind):
    import torch

    from train.trainer import NET_FILE

    run = tmp_path / "run"
    run.mkdir()
    marker = tmp_path / "code-ran"
    net = run / NET_FILE
    if kind == "garbage":
        net.write_bytes(b"not a torch file")
    elif kind == "truncated-zip":
        net.write_bytes(b"PK\x03\x04" + bytes(40))
    else:
        torch.save({"format": 1, "model": _Payload(marker)}, net)
    line = _invoke(["evaluate", f"run_dir={run}"])
    assert line.startswith(f"error: cannot load {net}: not a LunarNet_ex checkpoint (")
    assert not marker.exists()
    assert _tree(run) == [NET_FILE]  # no metrics, no confusion matrices


def test_a_saved_checkpoint_loads_with_weights_only(tmp_path):
    """The checkpoint `crater-synth train` writes holds plain data only: weights_only loading accepts it."""
    from crater_synth.config import load_settings
    from train.metrics import accuracy, class_mean_accuracy
    from train.trainer import LunarNetEx, load_lunarnet, save_lunarnet

    settings = load_settings([])
    model = LunarNetEx(settings.model)
    yv, pv = np.array([0, 1, 1]), np.array([0, 1, 0])
    # The history values as training records them (the metrics' own return types).
    history = [{"epoch": 1, "val_accuracy": class_mean_accuracy(yv, pv), "val_accuracy_overall": accuracy(yv, pv)}]
    save_lunarnet(tmp_path, model.state_dict(), settings.model, ["a", "b"], settings, history, 1, 0.75, run_id="r")
    loaded, ck = load_lunarnet(tmp_path)
    assert ck["run_id"] == "r" and ck["history"] == history
    for k, v in model.state_dict().items():
        assert torch_equal(loaded.state_dict()[k], v), k


def torch_equal(a, b) -> bool:
    import torch

    return bool(torch.equal(a, b))


# --- crater-synth config -------------------------------------------------------------------------
@pytest.mark.parametrize("override", ["=5", "+=5", " =x"])
def test_an_override_with_no_key_is_one_line(override):
    assert _invoke(["config", override]) == (
        f"error: override {override!r} names no key: write key=value (e.g. render.samples=4)"
    )
