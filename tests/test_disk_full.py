"""A full disk mid-run: one `error:` line that says the disk is full (ENOSPC) and names the
file, no temp file left behind, and one rerun after freeing space completes the dataset.

Needs a small filesystem to fill: a tmpfs mounted for the test (root, or a user namespace allowed to
mount); skipped where neither is possible. On main this run hangs: OpenImageIO/OpenEXR never return
from write_image on a full disk (crater_core/exr.py now encodes in memory and writes the bytes itself).
"""

import errno
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from helpers.cli import REPO, TINY, cli_command, exr_files, run_cli, summary

SLOW16 = ("render.mode=direct", "render.samples=16", "sweep.sun_azimuth.count=4", "sweep.cam_azimuth.count=4")
N16 = 16


@pytest.fixture
def small_disk(tmp_path):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64m", "tmpfs", str(mnt)], capture_output=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.decode(errors='replace').strip()}")
    yield mnt
    subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def _fill(directory: Path) -> Path:
    """Write a file until the filesystem is full."""
    filler = directory / "filler.bin"
    block = b"\0" * (1 << 16)
    with open(filler, "wb", buffering=0) as fh:
        while True:
            try:
                fh.write(block)
            except OSError as exc:
                assert exc.errno == errno.ENOSPC
                break
    return filler


def test_full_disk_mid_run_says_so(small_disk, tiny_data_dir):
    out = small_disk / "ds"
    proc = subprocess.Popen(
        [*cli_command(), "dataset", *TINY, f"data_dir={tiny_data_dir}", f"out_dir={out}", *SLOW16],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 180
        while not exr_files(out) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert exr_files(out), proc.stderr.read() if proc.poll() is not None else "no EXR in time"
        filler = _fill(small_disk)
        stdout, stderr = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 2, stderr[-3000:]
    last = stderr.splitlines()[-1]
    assert last.startswith("error: disk full (ENOSPC): cannot write "), stderr[-3000:]
    written = last.split("cannot write ", 1)[1].split(" (")[0]
    assert written.startswith(str(out)), last
    assert [line for line in stderr.splitlines() if line.startswith("error:")] == [last]
    assert not [p for p in out.rglob(".*") if ".tmp" in p.name], "temp files of the failed writes are left"
    filler.unlink()
    s = summary(run_cli("dataset", *TINY, f"data_dir={tiny_data_dir}", f"out_dir={out}", *SLOW16))
    assert s["manifest_rows"] == N16 and s["rendered"] < N16
    v = run_cli("verify", out)
    assert v.returncode == 0 and "0 orphan files" in v.stdout, v.stdout + v.stderr
