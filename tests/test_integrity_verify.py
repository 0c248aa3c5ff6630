"""`verify` checks the labels, not only the bytes; every manifest reader refuses rows that leave the
dataset and names the file and line of an unreadable one; `verify` tells a dataset being written or
interrupted from one with orphan files.

Each test edits a copy of one tiny rendered dataset (4 renders) the way a user or a fault would."""

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from helpers.cli import assert_same_dataset, dataset_workers, exr_files, run_cli, start_dataset

# 16 direct-mode renders at 16 spp on one worker: a run that is still busy when verify looks at it.
SLOW16 = ("render.mode=direct", "render.samples=16", "sweep.sun_azimuth.count=4", "sweep.cam_azimuth.count=4")


@pytest.fixture(scope="module")
def reference(tiny_smoke):
    return tiny_smoke


@pytest.fixture
def ds(reference, tmp_path):
    out = tmp_path / "ds"
    shutil.copytree(reference, out)
    return out


def _lines(ds: Path) -> list[str]:
    return (ds / "manifest.jsonl").read_text().splitlines()


def _write_lines(ds: Path, lines: list[str]) -> None:
    (ds / "manifest.jsonl").write_text("".join(line + "\n" for line in lines))


def _edit_row(ds: Path, i: int, **changes) -> dict:
    lines = _lines(ds)
    row = json.loads(lines[i])
    row.update(changes)
    lines[i] = json.dumps(row, sort_keys=True, separators=(",", ":"))
    _write_lines(ds, lines)
    return row


def _faults(proc: subprocess.CompletedProcess) -> list[str]:
    return [line[len("fault: ") :] for line in proc.stderr.splitlines() if line.startswith("fault: ")]


def _one_error_line(proc: subprocess.CompletedProcess) -> str:
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, proc.stderr[-3000:]
    return errors[0]


# -- labels: the EXR header against the row ----------------------------------------------------------
@pytest.mark.parametrize(
    "field, value",
    [
        ("crater", "de_gerlache"),
        ("sun_elevation", 3.2),
        ("sun_azimuth", 180.0),
        ("cam_elevation", 60.0),
        ("cam_azimuth", 90.0),
        ("range_m", 40000.0),
        ("fov_deg", 60.0),
        ("frame_width", 200),
        ("crop_origin", [20, 24]),
        ("seed", 12345),
        ("terrain_id", "0123456789abcdef"),
    ],
)
def test_verify_fails_on_an_edited_label(ds, field, value):
    row = _edit_row(ds, 1, **{field: value})
    v = run_cli("verify", ds)
    assert v.returncode == 1, v.stdout + v.stderr
    f = ds / row["path"]
    mine = [x for x in _faults(v) if x.startswith(f"{f}: row {field} ")]
    assert mine and "the EXR header says" in mine[0], v.stderr
    assert "sha256" not in v.stderr  # the bytes are fine: only the label is wrong


def test_verify_fails_on_edited_sigma_boxes_and_rim(ds):
    lines = _lines(ds)
    row = json.loads(lines[2])
    row["sigma_boxes"]["1.2"][0] -= 2.0  # a wider box, same centre
    row["sigma_boxes"]["1.2"][2] += 2.0
    row["rim_ellipse"]["a"] *= 1.1
    lines[2] = json.dumps(row, sort_keys=True, separators=(",", ":"))
    _write_lines(ds, lines)
    v = run_cli("verify", ds)
    assert v.returncode == 1
    f = ds / row["path"]
    assert {x.split(" the EXR header")[0] for x in _faults(v)} == {
        f"{f}: row sigma_boxes differs from what",
        f"{f}: row rim_ellipse differs from what",
    }, v.stderr


def test_verify_fails_on_a_centre_that_is_not_the_boxes_centre(ds):
    row = _edit_row(ds, 0, center_px=[20.0, 23.0])
    v = run_cli("verify", ds)
    assert v.returncode == 1
    assert _faults(v) == [f"{ds / row['path']}: center_px [20.0, 23.0] is not the centre of the sigma boxes"]


def test_verify_fails_on_an_exr_without_render_parameters(ds):
    """An EXR that carries no render parameters cannot prove its labels: a fault, even with a matching hash."""
    import numpy as np

    from crater_core import exr, schema

    lines = _lines(ds)
    row = json.loads(lines[0])
    f = ds / row["path"]
    chans, _ = exr.read_exr(f)
    sha = exr.write_exr(f, {k: np.asarray(v) for k, v in chans.items()})
    lines[0] = schema.dumps_row(row | {"sha256": sha})
    _write_lines(ds, lines)
    v = run_cli("verify", ds)
    assert v.returncode == 1
    assert _faults(v) == [f"{f}: the EXR header carries no render parameters (not written by crater-synth)"]


def test_verify_ok_on_an_untouched_dataset_checks_every_header(ds):
    v = run_cli("verify", ds)
    assert v.returncode == 0, v.stderr
    assert "verify OK: 4 rows" in v.stdout


# -- an empty manifest ---------------------------------------------------------------------------------
def test_verify_fails_on_an_empty_manifest_with_files_beside_it(ds):
    _write_lines(ds, [])
    v = run_cli("verify", ds)
    assert v.returncode == 1, v.stdout
    assert _faults(v) == [f"{ds / 'manifest.jsonl'} lists no rows, but 4 EXR files lie beside it"]


def test_verify_ok_on_an_empty_manifest_alone(tmp_path):
    d = tmp_path / "empty"
    d.mkdir()
    (d / "manifest.jsonl").write_text("")
    v = run_cli("verify", d)
    assert v.returncode == 0 and "verify OK: 0 rows" in v.stdout, v.stdout + v.stderr


# -- rows whose path leaves the dataset -----------------------------------------------------------------
@pytest.mark.parametrize("how", ["dotdot", "absolute"])
def test_verify_refuses_a_path_that_leaves_the_dataset(ds, how):
    """The row is a faithful copy of another with a path outside the dataset: refused, never hashed."""
    lines = _lines(ds)
    row = json.loads(lines[0])
    outside = ds.parent / "outside.exr"
    shutil.copy(ds / row["path"], outside)
    row["path"] = "../outside.exr" if how == "dotdot" else str(outside)
    lines[0] = json.dumps(row, sort_keys=True, separators=(",", ":"))
    _write_lines(ds, lines)
    v = run_cli("verify", ds)
    assert v.returncode == 1
    faults = _faults(v)
    assert faults[0].startswith(f"{ds / 'manifest.jsonl'}:1: unreadable row (")
    assert f"path {row['path']!r} leaves the dataset directory" in faults[0], faults


def test_verify_refuses_a_symlink_that_leaves_the_dataset(ds):
    row = json.loads(_lines(ds)[0])
    f = ds / row["path"]
    outside = ds.parent / "outside.exr"
    shutil.move(f, outside)
    f.symlink_to(outside)
    v = run_cli("verify", ds)
    assert v.returncode == 1
    assert _faults(v) == [f"{f}: leaves the dataset directory (a link to {outside.resolve()})"], v.stderr


# -- unreadable manifest lines: one line naming the file and line, in every reader ------------------------
BAD_LINES = {"null": b"null", "number": b"42", "list": b"[1, 2]", "not-utf8": b'{"crater": "sh\xffckleton"}'}


def _put_bad_line(ds: Path, what: str, lineno: int = 3) -> None:
    raw = (ds / "manifest.jsonl").read_bytes().splitlines()
    raw[lineno - 1] = BAD_LINES[what]
    (ds / "manifest.jsonl").write_bytes(b"\n".join(raw) + b"\n")


@pytest.mark.parametrize("what", sorted(BAD_LINES))
def test_verify_names_an_unreadable_line(ds, what):
    _put_bad_line(ds, what)
    v = run_cli("verify", ds)
    assert v.returncode == 1 and "Traceback" not in v.stderr, v.stderr[-3000:]
    faults = _faults(v)
    assert faults[0].startswith(f"{ds / 'manifest.jsonl'}:3: unreadable row ("), faults


@pytest.mark.parametrize("what", sorted(BAD_LINES))
def test_preview_names_an_unreadable_line(ds, what, tmp_path):
    _put_bad_line(ds, what)
    p = run_cli("preview", ds, "--out", tmp_path / "png")
    assert p.returncode == 2
    assert _one_error_line(p).startswith(f"error: {ds / 'manifest.jsonl'}:3: unreadable row ("), p.stderr


@pytest.mark.parametrize("what", ["null", "not-utf8"])
def test_dataset_repairs_an_unreadable_line(ds, reference, tiny_dataset, what):
    """The line is dropped like any corrupt line; the render it hid is done again; same bytes as a clean run."""
    _put_bad_line(ds, what)
    proc = tiny_dataset(ds)
    assert "Traceback" not in proc.stderr
    assert json.loads(proc.stdout.splitlines()[-1])["manifest_rows"] == 4
    assert_same_dataset(reference, ds)
    assert run_cli("verify", ds).returncode == 0


def test_dataset_drops_a_row_that_leaves_the_dataset(ds, reference, tiny_dataset):
    """A row pointing at a faithful copy outside the dataset is never read: it is dropped, and the render's
    own file inside the dataset, proved by its sealed header, gives its row back (nothing is rendered)."""
    row = json.loads(_lines(ds)[0])
    shutil.copy(ds / row["path"], ds.parent / "outside.exr")
    _edit_row(ds, 0, path="../outside.exr")
    proc = tiny_dataset(ds)
    summary = json.loads(proc.stdout.splitlines()[-1])
    assert (summary["rendered"], summary["recovered"]) == (0, 1), summary
    assert_same_dataset(reference, ds)


def test_dataset_renders_again_a_file_linked_out_of_the_dataset(ds, reference, tiny_dataset):
    """The resume check does not take a link to a faithful copy outside the dataset as a done render."""
    row = json.loads(_lines(ds)[1])
    f = ds / row["path"]
    outside = ds.parent / "outside.exr"
    shutil.move(f, outside)
    f.symlink_to(outside)
    proc = tiny_dataset(ds)
    assert json.loads(proc.stdout.splitlines()[-1])["rendered"] == 1
    assert not f.is_symlink()
    assert_same_dataset(reference, ds)


def test_verify_no_decode_still_checks_the_labels(ds):
    row = _edit_row(ds, 3, cam_azimuth=45.0)
    v = run_cli("verify", "--no-decode", ds)
    assert v.returncode == 1
    assert _faults(v) == [f"{ds / row['path']}: row cam_azimuth 45 but the EXR header says 180"], v.stderr


def test_preview_refuses_a_path_that_leaves_the_dataset(ds, tmp_path):
    _edit_row(ds, 0, path="/etc/hostname")
    p = run_cli("preview", ds, "--out", tmp_path / "png")
    assert p.returncode == 2
    line = _one_error_line(p)
    assert line.startswith(f"error: {ds / 'manifest.jsonl'}:1: unreadable row (") and "leaves the dataset" in line


# -- a dataset being written, and one whose writer was killed ---------------------------------------------
def _wait_for(cond, what: str, proc: subprocess.Popen, timeout: float = 180):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        if proc.poll() is not None:
            pytest.fail(f"sweep ended (exit {proc.returncode}) before {what}: {proc.stderr.read()[-2000:]}")
        time.sleep(0.02)
    pytest.fail(f"timed out waiting for {what}")


def _kill(proc: subprocess.Popen, out: Path) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    for pid in dataset_workers(out):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def _part_rows(out: Path) -> int:
    return sum(p.read_text().count("\n") for p in (out / "manifest.parts").glob("*.jsonl"))


def test_verify_during_a_running_dataset_says_in_progress(tmp_path, tiny_data_dir):
    out = tmp_path / "ds"
    proc = start_dataset(out, tiny_data_dir, *SLOW16, "render.workers=1")
    try:
        _wait_for(lambda: _part_rows(out) >= 1 and len(exr_files(out)) >= 1, "the first row", proc)
        # held still (it keeps its lock) so that it cannot finish before verify looks, however slow verify starts
        os.kill(proc.pid, signal.SIGSTOP)
        try:
            v = run_cli("verify", out)
            assert proc.poll() is None, "the run ended before verify looked at it"
        finally:
            os.kill(proc.pid, signal.SIGCONT)
    finally:
        _kill(proc, out)
    assert "Traceback" not in v.stderr and "orphan" not in v.stderr, v.stderr
    text = v.stdout + v.stderr
    assert "dataset in progress" in text and f"pid {proc.pid}" in text, text
    assert "never merged" not in text
    assert v.returncode != 0  # not verified: it is still being written


def test_verify_after_sigkill_says_rerun_to_resume(tmp_path, tiny_data_dir, tiny_dataset):
    out = tmp_path / "ds"
    proc = start_dataset(out, tiny_data_dir, *SLOW16, "render.workers=1")
    try:
        _wait_for(lambda: _part_rows(out) >= 2, "two rows", proc)
    finally:
        _kill(proc, out)
    assert not (out / "manifest.jsonl").exists()
    v = run_cli("verify", out)
    line = _one_error_line(v)
    assert "never merged" not in line and "orphan" not in v.stderr
    assert "interrupted" in line and "re-run `crater-synth dataset` with the same settings to resume" in line, line
    assert v.returncode == 2


def test_verify_after_sigkill_of_a_resumed_run_names_the_unmerged_rows(ds, tmp_path, tiny_data_dir):
    """A merged manifest plus the part file of a killed writer: the unmerged rows are not orphans."""
    rows = [json.loads(x) for x in _lines(ds)]
    _write_lines(ds, [json.dumps(r, sort_keys=True, separators=(",", ":")) for r in rows[:2]])
    from crater_synth.dataset.manifest import writer_tag

    host = writer_tag().rsplit("-", 1)[0]
    part = ds / "manifest.parts" / f"all-{host}-999999.jsonl"
    part.parent.mkdir(exist_ok=True)
    part.write_text("".join(json.dumps(r, sort_keys=True, separators=(",", ":")) + "\n" for r in rows[2:]))
    v = run_cli("verify", ds)
    assert v.returncode == 1 and "orphan:" not in v.stderr, v.stderr
    assert _faults(v) == [
        f"{part}: 2 rows of an interrupted run (pid 999999, no longer running) were never merged: "
        "re-run `crater-synth dataset` with the same settings to resume"
    ]


# -- a truncated EXR: one line, not a screenful of library output ------------------------------------------
@pytest.fixture(scope="module")
def truncated_toy(tmp_path_factory):
    """A toy dataset of 210 px renders (4x4 tiles of 64 px), its first EXR cut in half."""
    from train.toydata import write_toy_dataset

    d = tmp_path_factory.mktemp("truncated")
    rows = write_toy_dataset(d, craters=("shackleton",), sun_elevations=(20.0,), sun_azimuths=(0.0,), rim_px=150.0)
    victim = d / rows[0]["path"]
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) // 2])
    return d, victim


def test_a_truncated_exr_is_one_line_in_every_reader(truncated_toy):
    """OpenEXR prints a line per unreadable tile on fd 2 (16 here); the readers keep it out of the terminal."""
    import sys

    d, victim = truncated_toy
    code = (
        "import sys\n"
        "from crater_core import exr\n"
        "for read in (exr.read_exr, exr.read_channel, exr.exr_info):\n"
        "    try:\n"
        "        read(sys.argv[1])\n"
        "    except exr.ExrError as e:\n"
        "        print(e)\n"
    )
    p = subprocess.run([sys.executable, "-c", code, victim], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stderr == ""
    lines = p.stdout.splitlines()
    assert len(lines) == 3 and all(str(victim) in line for line in lines), p.stdout


def test_preview_of_a_truncated_exr_prints_one_line(truncated_toy, tmp_path):
    d, victim = truncated_toy
    p = run_cli("preview", d, "--out", tmp_path / "png")
    assert p.returncode == 2
    assert p.stderr.splitlines() == [_one_error_line(p)] and str(victim) in p.stderr, p.stderr
