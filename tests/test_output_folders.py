"""The output-folder contract (crater_synth/outfolder.py, docs/architecture.md "Output folders"): every
writer refuses a folder of another kind and files it did not write, naming one; it never deletes or
overwrites a file it cannot prove it wrote; one writer at a time; nav-frames merges its manifest.

Each data-loss case that the writers had before the contract is one test here. The folder names
(markers, lock) are written out as literals: they are the on-disk contract, the same for every version."""

from __future__ import annotations

import fcntl
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crater_synth.config import load_settings
from crater_synth.dataset import export as ex
from crater_synth.errors import DatasetBusyError, UserError
from crater_synth.navigation.rendered.frames import frame_overrides, render_frames

from helpers.cli import REPO, TINY, TINY_NAV
from helpers.export import interrupt_at_sample

LOCK = ".crater-synth.lock"
NAV_MARKER = ".crater-synth-navframes"
EXPORT_MARKER = ".crater-synth-export"
DATASET_MARKER = ".crater-synth-dataset"


# ------------------------------------------------------------------------------------------------
# Helpers
# ------------------------------------------------------------------------------------------------
def nav_settings(data_dir, *overrides):
    return load_settings(frame_overrides([*TINY_NAV, f"data_dir={data_dir}", *overrides]))


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> bytes)."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def rows(folder: Path) -> list[dict]:
    return [json.loads(line) for line in (folder / "manifest.jsonl").read_text().splitlines() if line.strip()]


class Held:
    """An exclusive flock on ``path``, as a live writer holds it."""

    def __init__(self, path: Path):
        path.parent.mkdir(parents=True, exist_ok=True)
        self.fh = open(path, "a+")
        fcntl.flock(self.fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self.fh.write(f"pid {os.getpid()} on test\n")
        self.fh.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.fh.seek(0)
        self.fh.truncate()
        fcntl.flock(self.fh, fcntl.LOCK_UN)
        self.fh.close()


def one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


@pytest.fixture(scope="module")
def nav_frames(tmp_path_factory, nav_data_dir):
    """Frames 0-2 of descent_ridge at tiny settings, rendered once in this process (read-only)."""
    out = tmp_path_factory.mktemp("navfolder") / "frames"
    render_frames(nav_settings(nav_data_dir), out, [0, 1, 2])
    return out


def copy_frames(nav_frames: Path, to: Path) -> Path:
    shutil.copytree(nav_frames, to, ignore=shutil.ignore_patterns(".jobs"))
    return to


def marked_and_unmarked(nav_frames: Path, tmp_path: Path):
    """Two copies of the frames: with their marker, and as written before markers (the marker gone)."""
    for keep_marker in (True, False):
        out = copy_frames(nav_frames, tmp_path / f"frames{keep_marker}")
        if not keep_marker:
            (out / NAV_MARKER).unlink(missing_ok=True)
        yield out


# ------------------------------------------------------------------------------------------------
# nav-frames
# ------------------------------------------------------------------------------------------------
def test_nav_frames_refuses_a_users_frame_and_manifest(tmp_path, nav_data_dir):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "frame_0000.exr").write_bytes(b"my own frame")
    (out / "manifest.jsonl").write_text('{"my": "rows"}\n')
    before = snapshot(out)
    with pytest.raises(UserError) as exc:
        render_frames(nav_settings(nav_data_dir), out, [0])
    assert "did not write" in one_line(exc) and str(out / "frame_0000.exr") in str(exc.value)
    assert snapshot(out) == before  # nothing written: no marker, no lock left behind


def test_nav_frames_refuses_a_render_dataset(tmp_path, nav_data_dir, tiny_smoke):
    """A rendered dataset (marked), and one written before markers (its manifest alone): refused, intact."""
    marked = tmp_path / "marked"
    shutil.copytree(tiny_smoke, marked, ignore=shutil.ignore_patterns(".jobs", ".dataset*.lock"))
    assert (marked / DATASET_MARKER).is_file()
    unmarked = tmp_path / "unmarked"
    shutil.copytree(marked, unmarked)
    (unmarked / DATASET_MARKER).unlink()
    for d in (marked, unmarked):
        before = snapshot(d)
        with pytest.raises(UserError) as exc:
            render_frames(nav_settings(nav_data_dir), d, [0])
        one_line(exc)
        assert snapshot(d) == before


def test_nav_frames_refuses_another_trajectorys_frames(tmp_path, nav_data_dir, nav_frames):
    """Marked for descent_ridge; and the same frames without their marker (written before markers)."""
    for out in marked_and_unmarked(nav_frames, tmp_path):
        before = snapshot(out)
        with pytest.raises(UserError) as exc:
            render_frames(nav_settings(nav_data_dir, "trajectory.name=other_track"), out, [0])
        one_line(exc)
        assert snapshot(out) == before


def test_nav_frames_merges_the_manifest(tmp_path, nav_data_dir, nav_frames):
    """--frames 3 after 0-2: the manifest lists 0-3, the rows of 0-2 byte for byte as they were; the
    same run again changes nothing but the marker's bookkeeping."""
    out = copy_frames(nav_frames, tmp_path / "frames")
    old = (out / "manifest.jsonl").read_text().splitlines()
    summary = render_frames(nav_settings(nav_data_dir), out, [3])
    new = (out / "manifest.jsonl").read_text().splitlines()
    assert [json.loads(r)["index"] for r in new] == [0, 1, 2, 3] and new[:3] == old
    assert summary["frames"] == 1 and summary["manifest_frames"] == 4
    files = snapshot(out)
    again = render_frames(nav_settings(nav_data_dir), out, [3])
    assert again["reused"] == 1 and {k: v for k, v in snapshot(out).items() if k != LOCK} == {
        k: v for k, v in files.items() if k != LOCK
    }


def test_nav_frames_adopts_its_own_frames_written_before_markers(tmp_path, nav_data_dir, nav_frames):
    out = copy_frames(nav_frames, tmp_path / "frames")
    (out / NAV_MARKER).unlink(missing_ok=True)
    (out / LOCK).unlink(missing_ok=True)
    before = rows(out)
    summary = render_frames(nav_settings(nav_data_dir), out, [0, 1, 2])
    assert summary["reused"] == 3 and rows(out) == before
    assert sorted(json.loads((out / NAV_MARKER).read_text())["files"]) == [
        "frame_0000.exr",
        "frame_0001.exr",
        "frame_0002.exr",
        "manifest.jsonl",
    ]


def test_nav_frames_refuses_while_another_writer_holds_the_folder(tmp_path, nav_data_dir, nav_frames):
    out = copy_frames(nav_frames, tmp_path / "frames")
    before = snapshot(out)
    with Held(out / LOCK):
        with pytest.raises(DatasetBusyError) as exc:
            render_frames(nav_settings(nav_data_dir), out, [3])
        assert "being written by another crater-synth process (pid" in one_line(exc)
    assert {k: v for k, v in snapshot(out).items() if k != LOCK} == {k: v for k, v in before.items() if k != LOCK}


@pytest.mark.integration
def test_two_nav_frames_runs_at_once_lose_no_frame(tmp_path, nav_data_dir):
    """Two processes started together on one folder: one refuses (busy), or both finish one after the
    other; either way the manifest lists every frame a successful run rendered."""
    out = tmp_path / "frames"
    cmd = [sys.executable, "-m", "crater_synth.cli", "nav-frames", *TINY_NAV, f"data_dir={nav_data_dir}", "--out"]
    procs = [
        subprocess.Popen([*cmd, str(out), "--frames", f], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        for f in ("0,1", "2,3")
    ]
    results = [(p.wait(timeout=300), p.stderr.read().decode()) for p in procs]
    done = set()
    for (rc, err), frames in zip(results, ({0, 1}, {2, 3})):
        assert rc == 0 or (rc == 2 and "being written by another crater-synth process" in err), err[-2000:]
        if rc == 0:
            done |= frames
    assert done and {r["index"] for r in rows(out)} == done


def test_detector_survey_refuses_foreign_files_and_another_seeds_survey(tmp_path):
    """nav-detector-frames' folder: a stray file, or another seed's survey, is refused before any track is
    rendered; a finished track (its manifest) is kept and the folder marked as this seed's survey."""
    from crater_synth.navigation.rendered.survey import render_survey

    out = tmp_path / "survey"
    (out / "track_000").mkdir(parents=True)
    (out / "track_000" / "manifest.jsonl").write_text("{}\n")
    (out / "notes.txt").write_text("mine")
    before = snapshot(out)
    with pytest.raises(UserError) as exc:
        render_survey(out, 1, seed=3, progress=False)
    assert "notes.txt" in one_line(exc) and snapshot(out) == before
    (out / "notes.txt").unlink()
    assert render_survey(out, 1, seed=3, progress=False)["already_there"] == 1
    assert json.loads((out / ".crater-synth-navdetector-survey").read_text())["subject"] == "seed=3"
    with pytest.raises(UserError, match="seed=3"):
        render_survey(out, 1, seed=4, progress=False)


def test_report_replaces_only_a_report_it_wrote(tmp_path):
    """`report` publishes RUN_DIR/report whole (the old one removed): a report folder holding a file the
    report did not write is refused, the file kept; its own report (marked, or written before markers)
    is replaced."""
    from click.testing import CliRunner

    from crater_synth.cli import main

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("seed: 0\n")
    args = ["report", str(run), f"train.dataset_dir={tmp_path}/none", "--hist-samples", "2", "-q"]
    assert CliRunner().invoke(main, args).exit_code == 0
    assert (run / "report" / ".crater-synth-report").is_file()
    (run / "report" / ".crater-synth-report").unlink()  # a report written before markers
    assert CliRunner().invoke(main, args).exit_code == 0
    (run / "report" / "my_notes.txt").write_text("mine")
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 2 and "my_notes.txt" in res.output
    assert (run / "report" / "my_notes.txt").read_text() == "mine"


# ------------------------------------------------------------------------------------------------
# dataset
# ------------------------------------------------------------------------------------------------
def test_dataset_refuses_a_nav_frames_folder(tmp_path, tiny_data_dir, nav_frames):
    """Marked, and written before markers (a manifest of nav-frame rows): refused, the manifest intact."""
    from crater_synth.dataset.build import build_dataset

    for out in marked_and_unmarked(nav_frames, tmp_path):
        before = snapshot(out)
        settings = load_settings([*TINY, f"data_dir={tiny_data_dir}", f"out_dir={out}"])
        with pytest.raises(UserError) as exc:
            build_dataset(settings, progress=False, warn=None)
        assert "not a dataset" in one_line(exc) or "navigation frames" in str(exc.value)
        assert snapshot(out) == before


# ------------------------------------------------------------------------------------------------
# export
# ------------------------------------------------------------------------------------------------
def test_export_never_deletes_shard_looking_files_it_did_not_write(tmp_path, tiny_smoke):
    out = tmp_path / "out"
    out.mkdir()
    for name in ("data-00000-of-00001.parquet", "shard-000000.tar"):
        (out / name).write_bytes(b"the user's own " + name.encode())
    before = snapshot(out)
    for fmt in ex.FORMATS:
        with pytest.raises(UserError) as exc:
            ex.export_dataset(tiny_smoke, out, fmt)
        assert "did not write" in one_line(exc)
        assert snapshot(out) == before


def test_export_written_before_markers_is_replaced_only_where_its_index_proves_it(tmp_path, tiny_smoke):
    out = tmp_path / "out"
    ex.export_dataset(tiny_smoke, out, "parquet", shard_rows=2)
    (out / EXPORT_MARKER).unlink()
    (out / LOCK).unlink()
    stray = out / "data-00005-of-00009.parquet"  # shard-looking, recorded by no index
    stray.write_bytes(b"mine")
    with pytest.raises(UserError, match="data-00005-of-00009.parquet"):
        ex.export_dataset(tiny_smoke, out, "parquet", overwrite=True)
    stray.unlink()
    index = ex.export_dataset(tiny_smoke, out, "webdataset", overwrite=True)  # proved by export.json: replaced
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == ["export.json", "shard-000000.tar"]
    assert index["format"] == "webdataset"


def test_two_exports_into_one_folder_at_once(tmp_path, tiny_smoke, monkeypatch):
    """A second export (WebDataset) starts while the first (Parquet) writes its shards: it is refused,
    and the first ends as a clean Parquet export, no tar shard among its files."""
    real = ex.RECORD_KINDS["render"]
    out, second = tmp_path / "out", []

    def arrays_then_second_export(d, row, channels):
        if not second:
            second.append(None)  # once: the second export reads through this function too
            try:
                second[0] = ex.export_dataset(tiny_smoke, out, "webdataset", overwrite=True)
            except DatasetBusyError as exc:
                second[0] = exc
        return real.arrays(d, row, channels)

    monkeypatch.setitem(
        ex.RECORD_KINDS, "render", ex.RecordKind(**{**real.__dict__, "arrays": arrays_then_second_export})
    )
    index = ex.export_dataset(tiny_smoke, out, "parquet")
    assert isinstance(second[0], DatasetBusyError) and "being written" in str(second[0])
    assert index["format"] == "parquet"
    assert sorted(p.name for p in out.iterdir() if p.name[0] != ".") == ["data-00000-of-00001.parquet", "export.json"]


def test_export_refuses_a_dataset_being_written(tmp_path, tiny_smoke):
    """A live `dataset` run holds its lock before its first part row: the export would take half the rows."""
    ds = tmp_path / "ds"
    shutil.copytree(tiny_smoke, ds, ignore=shutil.ignore_patterns(".jobs"))
    with Held(ds / ".dataset.lock"):
        with pytest.raises(DatasetBusyError) as exc:
            ex.export_dataset(ds, tmp_path / "out", "parquet")
        assert "being written" in one_line(exc)
    assert not (tmp_path / "out").exists()


def test_export_refuses_frames_being_written(tmp_path, nav_frames):
    frames = copy_frames(nav_frames, tmp_path / "frames")
    with Held(frames / LOCK):
        with pytest.raises(DatasetBusyError):
            ex.export_dataset(frames, tmp_path / "out", "parquet")
    assert not (tmp_path / "out").exists()


def test_every_writer_refuses_another_kinds_folder(tmp_path, tiny_smoke, nav_data_dir):
    """An export folder is no nav-frames folder; a nav-frames folder is no export folder."""
    exp = tmp_path / "exp"
    ex.export_dataset(tiny_smoke, exp, "parquet")
    before = snapshot(exp)
    with pytest.raises(UserError) as exc:
        render_frames(nav_settings(nav_data_dir), exp, [0])
    assert "give another folder" in one_line(exc) and snapshot(exp) == before
    nav = tmp_path / "nav"
    nav.mkdir()
    (nav / NAV_MARKER).write_text(json.dumps({"kind": "navframes", "files": [], "subject": "descent_ridge"}))
    with pytest.raises(UserError, match="give another folder"):
        ex.export_dataset(tiny_smoke, nav, "parquet")
    assert sorted(p.name for p in nav.iterdir()) == [NAV_MARKER]


# ------------------------------------------------------------------------------------------------
# Property tests: random sequences of interrupts, edits, deletions, foreign files, concurrent writers
# ------------------------------------------------------------------------------------------------
FOREIGN = ("frame_0001.exr", "frame_0003.exr", "manifest.jsonl", "notes.txt", "sub/frame_0000.exr")


def _nav_step(op: str, rng: random.Random, out: Path, data_dir, user: dict, edited: set, monkeypatch) -> None:
    """One step on a nav-frames folder; the user's files are recorded in ``user`` (path -> bytes), the
    names of the writer's files the user damaged in ``edited``."""
    frames = sorted(rng.sample(range(4), rng.randint(1, 3)))
    if op == "add_foreign":
        name = rng.choice(FOREIGN)
        if not (out / name).exists():
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            (out / name).write_bytes(f"user {name}".encode())
            user[name] = (out / name).read_bytes()
    elif op == "remove_foreign" and user:
        name = rng.choice(sorted(user))
        (out / name).unlink()
        del user[name]
    elif op in ("edit", "delete"):
        ours = [p for p in sorted(out.glob("frame_*.exr")) + [out / "manifest.jsonl"] if p.is_file()]
        ours = [p for p in ours if p.name not in user]
        if ours:
            p = rng.choice(ours)
            if op == "delete":
                p.unlink()
            else:
                raw = bytearray(p.read_bytes())
                raw[rng.randrange(len(raw))] ^= 0xFF
                p.write_bytes(bytes(raw))
                edited.add(p.name)
    elif op == "busy":
        with Held(out / LOCK):
            with pytest.raises(DatasetBusyError):
                render_frames(nav_settings(data_dir), out, frames)
    elif op == "interrupt":
        import crater_synth.navigation.rendered.frames as fr

        def stop(*_a, **_k):
            raise KeyboardInterrupt

        monkeypatch.setattr(fr, "run_workers", stop)
        try:
            render_frames(nav_settings(data_dir), out, frames)
        except (KeyboardInterrupt, UserError):
            pass
        finally:
            monkeypatch.undo()
    else:  # run
        try:
            render_frames(nav_settings(data_dir), out, frames)
        except UserError as exc:
            assert "\n" not in str(exc) and (user or "did not write" in str(exc)), exc


def _until_clean(run, out: Path, edited: set) -> None:
    """``run()``; a refusal may only name a file of the writer's that the user damaged (it can no longer
    prove it wrote it): the user removes it and runs again."""
    for _ in range(len(edited) + 1):
        try:
            return run()
        except UserError as exc:
            named = [n for n in edited if str(out / n) in str(exc)]
            assert named, exc
            (out / named[0]).unlink()
            edited.discard(named[0])
    run()


def _check_user_files(out: Path, user: dict) -> None:
    for name, data in user.items():
        assert (out / name).read_bytes() == data, name  # never lost, never changed


def _frames_result(out: Path) -> tuple[list[dict], dict[str, bytes]]:
    """The manifest less render times, and the frames' bytes."""
    manifest = [{k: v for k, v in r.items() if k != "render_seconds"} for r in rows(out)]
    return manifest, {p.name: p.read_bytes() for p in sorted(out.glob("frame_*.exr"))}


STEP = st.integers(0, 2**32 - 1)  # each step's own random choices (which frames, which file, which byte)
PROPERTY = dict(deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
NAV_OPS = ("run", "interrupt", "edit", "delete", "add_foreign", "remove_foreign", "busy")


@pytest.mark.integration
@settings(max_examples=8, **PROPERTY)
@given(sequence=st.lists(st.tuples(st.sampled_from(NAV_OPS), STEP), min_size=1, max_size=6))
def test_any_nav_frames_sequence_ends_refused_or_clean(sequence, tmp_path, nav_data_dir, nav_frames, monkeypatch):
    """Runs, interrupted runs, edits, deletions, foreign files and a concurrent writer on one folder: no
    user file is ever lost or changed; once the user has moved their files away (and the damaged files
    the refusals name), a full run gives the clean result, byte for byte."""
    clean = _frames_result(nav_frames)
    out, user, edited = Path(tempfile.mkdtemp(dir=tmp_path)) / "frames", {}, set()
    for op, step in sequence:
        _nav_step(op, random.Random(step), out, nav_data_dir, user, edited, monkeypatch)
        if out.exists():
            _check_user_files(out, user)
    for name in list(user):
        (out / name).unlink()
    _until_clean(lambda: render_frames(nav_settings(nav_data_dir), out, [0, 1, 2]), out, edited)
    manifest, files = _frames_result(out)
    assert [r for r in manifest if r["index"] < 3] == clean[0]
    assert {k: v for k, v in files.items() if k in clean[1]} == clean[1]


def _export_result(out: Path) -> tuple[dict, dict[str, bytes]]:
    index = json.loads((out / "export.json").read_text())
    index.pop("seconds")
    return index, {
        p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.name[0] != "." and p.name != "export.json"
    }


EXPORT_OPS = ("run", "interrupt", "edit", "delete", "add_foreign", "remove_foreign", "busy")
EXPORT_FOREIGN = ("data-00000-of-00002.parquet", "shard-000001.tar", ".data-00001-of-00002.parquet.1.tmp", "x.txt")


@pytest.fixture(scope="module")
def clean_export(tiny_smoke, tmp_path_factory):
    return _export_result_of(tiny_smoke, tmp_path_factory.mktemp("clean") / "out")


@settings(max_examples=30, **PROPERTY)
@given(sequence=st.lists(st.tuples(st.sampled_from(EXPORT_OPS), STEP), min_size=1, max_size=8))
def test_any_export_sequence_ends_refused_or_clean(sequence, tmp_path, tiny_smoke, clean_export, monkeypatch):
    """The same for exports: runs of either format, interrupted runs, edits, deletions, shard-looking
    foreign files and a concurrent writer; the user's files survive every step, and a final overwrite
    gives the clean export byte for byte."""
    out, user, edited = Path(tempfile.mkdtemp(dir=tmp_path)) / "out", {}, set()
    for op, step in sequence:
        _export_step(op, random.Random(step), out, tiny_smoke, user, edited, monkeypatch)
        if out.exists():
            _check_user_files(out, user)
    for name in list(user):
        (out / name).unlink()
    _until_clean(lambda: ex.export_dataset(tiny_smoke, out, "parquet", shard_rows=2, overwrite=True), out, edited)
    assert _export_result(out) == clean_export


def _export_step(op: str, rng: random.Random, out: Path, dataset, user: dict, edited: set, monkeypatch) -> None:
    fmt = rng.choice(ex.FORMATS)
    if op in ("run", "interrupt", "busy"):
        try:
            if op == "interrupt":
                interrupt_at_sample(monkeypatch, "render", 3)
            if op == "busy":
                with Held(out / LOCK), pytest.raises(DatasetBusyError):
                    ex.export_dataset(dataset, out, fmt, shard_rows=2, overwrite=True)
            else:
                ex.export_dataset(dataset, out, fmt, shard_rows=2, overwrite=rng.random() < 0.7)
        except (KeyboardInterrupt, UserError) as exc:
            assert "\n" not in str(exc)
        finally:
            monkeypatch.undo()
    elif op == "add_foreign":
        name = rng.choice(EXPORT_FOREIGN)
        if not (out / name).exists():
            out.mkdir(parents=True, exist_ok=True)
            (out / name).write_bytes(f"user {name}".encode())
            user[name] = (out / name).read_bytes()
    elif op == "remove_foreign" and user:
        name = rng.choice(sorted(user))
        (out / name).unlink()
        del user[name]
    elif op in ("edit", "delete") and out.is_dir():
        ours = [p for p in sorted(out.iterdir()) if p.is_file() and p.name not in user and p.name[0] != "."]
        if ours:
            p = rng.choice(ours)
            if op == "delete":
                p.unlink()
            else:
                p.write_bytes(p.read_bytes()[:-1] + b"!")
                edited.add(p.name)


def _export_result_of(dataset, out):
    ex.export_dataset(dataset, out, "parquet", shard_rows=2)
    return _export_result(out)


def test_the_markers_own_temp_file_is_bookkeeping_not_a_foreign_file(tmp_path):
    """A second writer caught between the first one's marker temp file and its rename is refused as busy,
    never for a 'file crater-synth did not write' (the marker's and verify's record's temp files)."""
    from crater_synth.outfolder import OutFolder

    first = OutFolder(tmp_path / "f", "navframes", subject="t").claim()
    for name in ("..crater-synth-navframes.abc123.tmp", "..verified.json.x1y2.tmp"):
        (tmp_path / "f" / name).write_text("{}")
    second = OutFolder(tmp_path / "f", "navframes", subject="t")
    second.check()
    assert second.unlisted() == []
    (tmp_path / "f" / ".notes.abc.tmp").write_text("mine")  # a temp file of nothing listed: not bookkeeping
    assert second.unlisted() == [".notes.abc.tmp"]
    first.release()
