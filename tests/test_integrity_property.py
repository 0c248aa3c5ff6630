"""Property: whatever happens to a dataset -- interrupts (kill -9, Ctrl-C, SIGTERM, SIGHUP while it
renders), corrupt or truncated files, corrupt manifest lines, deleted files, rows or manifest, edited
rows, and files of the user's put beside the renders -- one `crater-synth dataset` re-run followed by
`crater-synth verify` ends with a manifest (and EXRs) byte-identical to a clean run, and every file
the user put there is still there, unchanged.

The clean smoke dataset (4 tiny renders) is rendered once; each example works on a copy. The default
run tries a fixed set of examples (derandomised); the long variant (``-m slow``) tries many more.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import pytest

from helpers.cli import assert_same_dataset, exr_files, run_cli, start_dataset

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

pytestmark = pytest.mark.integration  # end-to-end: make test-integration

# Files of the user's: names a render could have, temp-file look-alikes, other directories.
USER_FILES = (
    "notes.txt",
    "photos/holiday.exr",
    "shackleton/holiday.exr",
    "shackleton/se09.000_sa000.000_ce90.000_ca000.000.exr",
    "shackleton/.holiday.exr.abc123.tmp.exr",
)
EDITS = (
    ("crater", "haworth"),
    ("sun_azimuth", 90.0),
    ("cam_elevation", 80.0),
    ("lit_fraction", 0.5),
    ("mean_if", 0.0),
    ("sigma_boxes", {"1.0": [0, 0, 1, 1]}),
    ("seed", 1),
    ("render_digest", "0"),
    ("path", "shackleton/elsewhere.exr"),
    ("path", "../outside.exr"),
)
# Manifest damage `dataset` repairs. (Lines that are JSON but no object, and non-UTF-8 bytes, are the
# manifest readers' to report: add b"null\n" and b"\xff\xfe\n" here once they do.)
MANIFEST_DAMAGE = (
    b'{"crater": "shackleton", "index"\n',  # a line cut by a killed writer
    b"not json at all\n",
    b'{"crater": 1}\n',  # an object that is not a row
    b"null\n",  # JSON that is not an object
    b"42\n",
    b"\xff\xfe\n",  # bytes that are not UTF-8
)
STOPS = (signal.SIGKILL, signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

actions = st.one_of(
    st.tuples(st.just("interrupt"), st.sampled_from(STOPS), st.floats(0.0, 2.5)),
    st.tuples(st.just("flip_exr_byte"), st.integers(0, 3), st.integers(0, 1 << 20)),
    st.tuples(st.just("truncate_exr"), st.integers(0, 3), st.floats(0.0, 0.99)),
    st.tuples(st.just("damage_manifest"), st.sampled_from(MANIFEST_DAMAGE), st.booleans()),
    st.tuples(st.just("delete_exr"), st.integers(0, 3)),
    st.tuples(st.just("delete_manifest")),
    st.tuples(st.just("delete_row"), st.integers(0, 3)),
    st.tuples(st.just("edit_row"), st.integers(0, 3), st.sampled_from(EDITS)),
    st.tuples(st.just("user_file"), st.sampled_from(USER_FILES)),
)


@pytest.fixture(scope="module")
def clean(tiny_smoke) -> Path:
    return tiny_smoke


def _apply(action: tuple, out: Path, data_dir: Path, user: dict[Path, bytes]) -> None:
    kind, *args = action
    manifest = out / "manifest.jsonl"
    exrs = exr_files(out)
    if kind == "interrupt":
        signum, delay = args
        proc = start_dataset(out, data_dir)
        try:
            proc.wait(timeout=delay)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signum)  # the whole group, like a terminal (SIGKILL: like a crash)
        try:
            proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        if signum == signal.SIGKILL:
            time.sleep(0.2)  # its workers notice the host is gone within a second; the next run copes anyway
    elif kind in ("flip_exr_byte", "truncate_exr", "delete_exr") and exrs:
        f = exrs[args[0] % len(exrs)]
        if f in user:
            return
        data = bytearray(f.read_bytes())
        if kind == "flip_exr_byte":
            data[args[1] % len(data)] ^= 0x5A
            f.write_bytes(bytes(data))
        elif kind == "truncate_exr":
            f.write_bytes(bytes(data[: int(len(data) * args[1])]))
        else:
            f.unlink()
    elif kind == "damage_manifest" and manifest.exists():
        line, at_end = args
        text = manifest.read_bytes()
        manifest.write_bytes(text + line if at_end else line + text)
    elif kind == "delete_manifest":
        manifest.unlink(missing_ok=True)
    elif kind in ("delete_row", "edit_row") and manifest.exists():
        lines = manifest.read_text().splitlines(keepends=True)
        if not lines:
            return
        i = args[0] % len(lines)
        if kind == "delete_row":
            del lines[i]
        else:
            try:
                row = json.loads(lines[i])
            except ValueError:
                return
            field, value = args[1]
            row[field] = value
            lines[i] = json.dumps(row) + "\n"
        manifest.write_text("".join(lines))
    elif kind == "user_file":
        f = out / args[0]
        if f.exists():
            return
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(b"the user's own file: " + args[0].encode())
        user[f] = f.read_bytes()


def _check(sequence: list[tuple], clean: Path, data_dir: Path) -> None:
    with tempfile.TemporaryDirectory(prefix="crater-property-") as tmp:
        out = Path(tmp) / "ds"
        shutil.copytree(clean, out)
        user: dict[Path, bytes] = {}
        for action in sequence:
            _apply(action, out, data_dir, user)
        from helpers.cli import TINY

        proc = run_cli("dataset", *TINY, f"data_dir={data_dir}", f"out_dir={out}")
        assert proc.returncode == 0, f"{sequence}: {proc.stderr[-3000:]}"
        v = run_cli("verify", out)
        assert v.returncode == 0, f"{sequence}: {v.stdout}{v.stderr[-3000:]}"
        for f, data in user.items():
            assert f.is_file() and f.read_bytes() == data, f"{sequence}: the user's {f} was changed or removed"
        for f in user:  # out of the way for the byte comparison with the clean run
            f.unlink()
        assert_same_dataset(clean, out)


COMMON = dict(deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])


@settings(max_examples=6, derandomize=True, **COMMON)
@given(sequence=st.lists(actions, min_size=1, max_size=4))
# Lines that crashed every reader before (JSON that is not an object, bytes that are not UTF-8), always run.
@example(sequence=[("damage_manifest", b"null\n", False), ("damage_manifest", b"\xff\xfe\n", True)])
def test_any_damage_is_repaired_to_a_clean_dataset(sequence, clean, tiny_data_dir):
    _check(sequence, clean, tiny_data_dir)


@pytest.mark.slow
@settings(max_examples=60, **COMMON)
@given(sequence=st.lists(actions, min_size=1, max_size=8))
def test_any_damage_is_repaired_to_a_clean_dataset_long(sequence, clean, tiny_data_dir):
    _check(sequence, clean, tiny_data_dir)
