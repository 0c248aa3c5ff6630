"""Data integrity of `crater-synth dataset`: nothing lost, nothing stale, nothing mixed.

- Only files crater-synth planned may be removed: a directory that is neither empty nor a dataset is
  refused and left as it was; in a dataset, files no row and no plan names are left alone.
- Every setting that changes a pixel or a label is in a render's identity (derived from the typed
  settings), so changing it renders again; execution-only settings do not.
- Two renders never share one file name (the sweep is refused).
- A lost or edited manifest is rebuilt from the EXR headers and pixel seals, without rendering.
- Refused runs leave no litter; a full disk at start-up names the path; SIGHUP is a clean stop;
  grid sizes are bounded before any list is built; an unquoted path with spaces gets a quoting hint.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from crater_core.settings import AxisSettings, as_plain
from crater_core.sweep import SweepError, grid_from_config
from crater_core.typed_config import SettingsError

from helpers.cli import REPO, cli_command, dataset_workers, exr_files, run_cli, start_dataset, summary

MARKER = ".crater-synth-dataset"


@pytest.fixture(scope="module")
def clean4(tiny_smoke) -> Path:
    """The tiny smoke dataset (4 renders), rendered once per session; tests work on copies."""
    return tiny_smoke


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _rows(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]


def _same_manifest(a: Path, b: Path) -> bool:
    return (a / "manifest.jsonl").read_bytes() == (b / "manifest.jsonl").read_bytes()


def _errors(proc) -> list[str]:
    return [line for line in proc.stderr.splitlines() if line.startswith("error:")]


# ------------------------------------------------------------------------------------------------
# 1. Only files crater-synth wrote, and can prove it wrote, are ever removed
# ------------------------------------------------------------------------------------------------
def test_foreign_directory_is_refused_and_left_as_it_was(tmp_path, tiny_dataset, clean4):
    mine = tmp_path / "mine"
    (mine / "photos").mkdir(parents=True)
    holiday = mine / "photos" / "holiday.exr"
    shutil.copy(exr_files(clean4)[0], holiday)
    before = holiday.read_bytes()
    proc = tiny_dataset(mine, check=False)
    assert proc.returncode == 2, proc.stderr
    assert _errors(proc) == [proc.stderr.splitlines()[-1]]
    assert str(holiday) in _errors(proc)[0] and "not a crater-synth dataset" in _errors(proc)[0]
    assert holiday.read_bytes() == before
    assert sorted(p.relative_to(mine) for p in mine.rglob("*")) == [Path("photos"), Path("photos/holiday.exr")]


def test_files_no_row_and_no_plan_names_are_left_alone(tmp_path, tiny_dataset, clean4):
    out = _copy(clean4, tmp_path / "ds")
    first = exr_files(out)[0]
    unplanned = first.with_name("se09.000_sa000.000_ce90.000_ca000.000.exr")  # a render name, not planned
    holiday = first.with_name("holiday.exr")
    planned_temp = first.with_name(f".{first.name}.k2j3h4.tmp.exr")  # an interrupted write of a planned file
    foreign_temp = first.with_name(".holiday.exr.k2j3h4.tmp.exr")  # looks like one, of a file never planned
    manifest_temp = out / ".manifest.jsonl.abc123.tmp"
    for f in (unplanned, holiday, planned_temp, foreign_temp, manifest_temp):
        shutil.copy(first, f)
    proc = tiny_dataset(out)
    assert summary(proc)["rendered"] == 0
    assert unplanned.exists() and holiday.exists() and foreign_temp.exists()
    assert not planned_temp.exists() and not manifest_temp.exists()
    left = [line for line in proc.stderr.splitlines() if "left 2 file(s) alone" in line]
    assert len(left) == 1 and str(holiday) in left[0], proc.stderr
    assert _same_manifest(out, clean4)


def test_dataset_has_a_marker_and_an_old_dataset_is_adopted(tmp_path, tiny_dataset, clean4):
    assert (clean4 / MARKER).is_file()
    out = _copy(clean4, tmp_path / "old")
    (out / MARKER).unlink()  # a dataset written before markers: its manifest says what it is
    s = summary(tiny_dataset(out))
    assert s["skipped_existing"] == 4 and (out / MARKER).is_file()


# ------------------------------------------------------------------------------------------------
# 2. Stale renders: every input that changes a pixel or a label is in the identity
# ------------------------------------------------------------------------------------------------
STALE = {
    "sweep.fov_deg=60": lambda r: r["fov_deg"] == 60.0,
    "sweep.range_factor=3": lambda r: r["range_m"] == 3 * 21.0e3,
    "sweep.sigma.values=[1.0,2.0]": lambda r: sorted(r["sigma_boxes"]) == ["1.0", "2.0"],
    "render.roi_min_px=40": lambda r: r["width"] >= 40,
    "seed=7": lambda r: True,
    "hapke.w=0.4": lambda r: True,
    "crater.shackleton.source=elsewhere": lambda r: True,  # in the EXR header: a clean run's bytes differ
}


# One changed input in the fast tier; the rest are make test-integration's (each renders the sweep again).
@pytest.mark.parametrize(
    "override", [pytest.param(o, marks=() if o == "seed=7" else pytest.mark.integration) for o in sorted(STALE)]
)
def test_changed_render_input_renders_again(tmp_path, tiny_dataset, clean4, override):
    out = _copy(clean4, tmp_path / "ds")
    s = summary(tiny_dataset(out, override))
    assert (s["rendered"], s["skipped_existing"], s.get("recovered", 0)) == (4, 0, 0), s
    rows = _rows(out)
    assert len(rows) == 4 and all(STALE[override](r) for r in rows)
    assert len({r["render_digest"] for r in rows} | {_rows(clean4)[0]["render_digest"]}) == 2
    ref = tmp_path / "ref"  # byte-identical to a clean run with that setting
    tiny_dataset(ref, override)
    assert _same_manifest(out, ref)


def test_execution_only_settings_keep_the_renders(tmp_path, tiny_dataset, clean4):
    out = _copy(clean4, tmp_path / "ds")
    s = summary(tiny_dataset(out, "render.workers=2", "render.threads=1", "sensor.enabled=false", "train.max_epochs=1"))
    assert (s["rendered"], s["skipped_existing"]) == (0, 4)


def test_grown_grid_keeps_its_renders(tmp_path, tiny_dataset, clean4):
    """The sample positions are not in the identity: a grid grown around the rendered values (the closed
    loop) keeps those renders, whose rows keep the index of the grid that rendered them."""
    out = _copy(clean4, tmp_path / "ds")
    s = summary(tiny_dataset(out, "sweep.sun_elevation.values=[0.8,1.6]"))
    assert (s["rendered"], s["skipped_existing"], s["recovered"]) == (4, 4, 0), s
    old = {r["path"]: r for r in _rows(clean4)}
    assert all(r == old[r["path"]] for r in _rows(out) if r["path"] in old)


def test_identity_holds_every_setting_but_the_listed_ones():
    """Derived, not listed: every leaf of the typed settings is in the identity's payload except the
    keys of IGNORED (each of which exists), so a key added later cannot be forgotten."""
    from crater_synth.config import load_settings
    from crater_synth.dataset.identity import IGNORED, identity_payload, render_identity

    s = load_settings(["crater=shackleton", "sweep=smoke"])
    crater = s.craters[0]

    def leaves(d, prefix=""):
        for k, v in d.items():
            if isinstance(v, dict) and v:
                yield from leaves(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}", v

    plain = dict(leaves(as_plain(s)))
    for key in IGNORED:
        assert any(k == key or k.startswith(key + ".") for k in plain), f"IGNORED lists {key}, not a setting"
    payload = dict(leaves(identity_payload(s, crater, "tid")))
    ignored = lambda k: any(k == i or k.startswith(i + ".") for i in IGNORED)  # noqa: E731
    assert {k: v for k, v in plain.items() if not ignored(k)} == {
        k: v for k, v in payload.items() if not k.startswith(("render_crater.", "terrain_id", "horizon_version"))
    }
    base = render_identity(s, crater, "tid")
    assert render_identity(s, crater, "other") != base
    from crater_core.settings import replace

    assert render_identity(s, replace(crater, lat=crater.lat + 1e-9), "tid") != base
    assert render_identity(replace(s, **{"sweep.fov_deg": 60.0}), crater, "tid") != base
    assert render_identity(replace(s, **{"render.workers": 7}), crater, "tid") == base


# ------------------------------------------------------------------------------------------------
# 3. Two renders, one file
# ------------------------------------------------------------------------------------------------
def test_values_that_share_a_file_name_are_refused():
    cfg = {a: {"count": 2} for a in ("sun_elevation", "sun_azimuth", "cam_elevation", "sigma")}
    with pytest.raises(SweepError, match=r"^sweep\.cam_azimuth\.values=\[0\.0001,0\.0002\]: .*one file name"):
        grid_from_config(cfg | {"cam_azimuth": {"count": 2, "values": [0.0001, 0.0002]}})
    grid_from_config(cfg | {"cam_azimuth": {"count": 2, "values": [0.001, 0.002]}})  # named apart: fine
    proc = run_cli("config", "sweep=smoke", "sweep.cam_azimuth.values=[0.0001,0.0002]")
    assert proc.returncode == 2 and _errors(proc) == [proc.stderr.strip()]
    assert proc.stderr.startswith("error: sweep.cam_azimuth.values=[0.0001,0.0002]: ")


def test_physical_sun_elevations_that_share_a_file_name_are_refused(tmp_path, tiny_dataset):
    """Physical sun elevations are fractions of each crater's highest sun: the names are checked per crater."""
    out = tmp_path / "ds"
    proc = tiny_dataset(out, "sweep.sun_model=physical", "sweep.sun_elevation.values=[0.5,0.5001]", check=False)
    assert proc.returncode == 2 and _errors(proc) == [proc.stderr.splitlines()[-1]], proc.stderr
    assert _errors(proc)[0].startswith("error: sweep.sun_elevation.values=[0.5,0.5001]: two renders of shackleton")
    assert not out.exists()


# ------------------------------------------------------------------------------------------------
# 7. Recover instead of re-render
# ------------------------------------------------------------------------------------------------
def test_lost_manifest_is_rebuilt_from_the_files(tmp_path, tiny_dataset, clean4):
    out = _copy(clean4, tmp_path / "ds")
    (out / "manifest.jsonl").unlink()
    proc = tiny_dataset(out)
    s = summary(proc)
    assert (s["rendered"], s["recovered"], s["manifest_rows"]) == (0, 4, 4), s
    assert "recovered 4 manifest row(s)" in proc.stderr
    assert _same_manifest(out, clean4)
    v = run_cli("verify", out)
    assert v.returncode == 0, v.stderr


@pytest.mark.parametrize("where", ["pixels", "header-text"])
def test_a_file_that_cannot_be_proved_is_rendered_again(tmp_path, tiny_dataset, clean4, where):
    out = _copy(clean4, tmp_path / "ds")
    (out / "manifest.jsonl").unlink()
    victim = exr_files(out)[1]
    data = bytearray(victim.read_bytes())
    if where == "pixels":  # the header still reads, the seal does not match
        data[-200] ^= 0x40
    else:  # a byte of an attribute recovery does not read: the file no longer encodes to its bytes
        data[data.find(b"radiance factor") + 3] ^= 0x20
    victim.write_bytes(bytes(data))
    s = summary(tiny_dataset(out))
    assert (s["rendered"], s["recovered"]) == (1, 3), s
    assert _same_manifest(out, clean4)
    assert victim.read_bytes() == (clean4 / victim.relative_to(out)).read_bytes()


@pytest.mark.parametrize(
    "edit",
    [
        {"crater": "haworth"},  # a flipped label: the row's key is no planned render's, its file is
        {"sun_azimuth": 90.0},
        {"lit_fraction": 0.5},
        {"sigma_boxes": {"1.0": [0, 0, 1, 1]}},
        {"path": "shackleton/elsewhere.exr"},
        {"path": "../../etc/hostname"},  # never followed: the row is dropped and rebuilt from the file
    ],
    ids=lambda e: f"{next(iter(e))}={next(iter(e.values()))}",
)
def test_edited_rows_are_repaired_from_the_files(tmp_path, tiny_dataset, clean4, edit):
    out = _copy(clean4, tmp_path / "ds")
    rows = _rows(out)
    rows[2] |= edit
    (out / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    s = summary(tiny_dataset(out))
    assert s["rendered"] == 0, s
    assert _same_manifest(out, clean4)


# ------------------------------------------------------------------------------------------------
# 8b. Sweep sizes are bounded before any list is built
# ------------------------------------------------------------------------------------------------
def test_axis_count_and_grid_size_are_bounded():
    with pytest.raises(SettingsError, match=r"count=1000000000: must lie in \[1, 3600\]"):
        AxisSettings.from_config({"count": 10**9}, "sweep.cam_azimuth")
    cfg = {a: {"count": 3000} for a in ("sun_azimuth", "cam_azimuth")}
    with pytest.raises(SweepError, match=r"^sweep of 2 x 3000 x 2 x 3000 = 36,000,000 renders per crater: at most"):
        grid_from_config(cfg | {a: {"count": 2} for a in ("sun_elevation", "cam_elevation", "sigma")})


def _limit_memory():
    resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))  # a blow-up fails here, not on the machine


def test_huge_count_is_one_line_at_once():
    t0 = time.monotonic()
    proc = subprocess.run(
        [*cli_command(), "config", "sweep.cam_azimuth.count=1000000000"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
        preexec_fn=_limit_memory,
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.strip() == "error: sweep.cam_azimuth.count=1000000000: must lie in [1, 3600]"
    assert time.monotonic() - t0 < 60


# ------------------------------------------------------------------------------------------------
# 9. Litter and unclear lines
# ------------------------------------------------------------------------------------------------
def test_refused_run_leaves_no_litter(tmp_path, tiny_dataset):
    out = tmp_path / "new" / "ds"
    proc = tiny_dataset(out, "sweep.sigma.values=[1.0,9.0]", check=False)  # the ROI leaves the frame
    assert proc.returncode == 2 and "ROI box" in proc.stderr, proc.stderr
    assert not (tmp_path / "new").exists(), sorted(p.name for p in (tmp_path / "new").rglob("*"))


def test_refused_run_in_an_empty_directory_leaves_it_empty(tmp_path, tiny_dataset):
    out = tmp_path / "empty"
    out.mkdir()
    proc = tiny_dataset(out, "sweep.sigma.values=[1.0,9.0]", check=False)
    assert proc.returncode == 2
    assert list(out.iterdir()) == []


@pytest.fixture
def full_disk(tmp_path):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.decode(errors='replace').strip()}")
    try:
        with open(mnt / "filler.bin", "wb", buffering=0) as fh:
            while True:
                fh.write(b"\0" * 4096)
    except OSError:
        pass
    yield mnt
    subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_full_disk_at_start_up_names_the_path(full_disk, tiny_dataset):
    out = full_disk / "ds"
    proc = tiny_dataset(out, check=False)
    assert proc.returncode == 2, proc.stderr
    assert _errors(proc) == [proc.stderr.splitlines()[-1]]
    assert "disk full (ENOSPC)" in _errors(proc)[0] and str(out) in _errors(proc)[0], proc.stderr
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler.bin"]  # and no litter


# 16 direct-mode renders at 16 spp on 2 workers: time to hang up mid-run.
SLOW16 = (
    "render.mode=direct",
    "render.samples=16",
    "sweep.sun_azimuth.count=4",
    "sweep.cam_azimuth.count=4",
    "render.workers=2",
)


@pytest.mark.integration
def test_sighup_is_a_clean_resumable_stop(tmp_path, tiny_data_dir, tiny_dataset):
    out = tmp_path / "ds"
    proc = start_dataset(out, tiny_data_dir, *SLOW16)
    try:
        deadline = time.monotonic() + 180
        while not (exr_files(out) and len(dataset_workers(out)) == 2) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.stderr.read()[-2000:]
            time.sleep(0.02)
        os.killpg(proc.pid, signal.SIGHUP)  # the terminal closed: the whole process group gets it
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 128 + signal.SIGHUP, stderr[-3000:]
    assert stderr.splitlines()[-1] == "error: interrupted by SIGHUP: stopped; rerun the same command to resume"
    assert not dataset_workers(out)
    v = run_cli("verify", out)
    assert v.returncode == 0 and "0 orphan files" in v.stdout, v.stdout + v.stderr
    s = summary(tiny_dataset(out, *SLOW16))
    assert s["rendered"] + s["skipped_existing"] == 16 and s["manifest_rows"] == 16


def test_unquoted_path_with_spaces_says_how_to_quote():
    proc = run_cli("config", "out_dir=/tmp/my", "data")  # the shell split `out_dir=/tmp/my data`
    assert proc.returncode == 2
    assert proc.stderr.strip() == (
        "error: override 'data' is not key=value: if it is the rest of the value before it (a path with "
        'spaces), quote the whole override, e.g. "out_dir=/tmp/my data"'
    )
    proc = run_cli("config", "out_dir=/tmp/my (1)")
    assert proc.returncode == 2 and len(proc.stderr.splitlines()) == 1
    assert proc.stderr.startswith("error: out_dir=/tmp/my (1): Hydra cannot parse the value")
    assert "\"out_dir='/tmp/my (1)'\"" in proc.stderr
