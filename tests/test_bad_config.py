"""Bad input ends `crater-synth dataset` with exit status 2 and ONE `error:` line, before any render
(no EXR, no Blender worker, no Dask cluster)."""

import re
import shutil

import pytest
from click.testing import CliRunner

from helpers.cli import TINY, exr_files, run_cli

HUGE = (
    "sweep.sun_elevation.values=null",
    "sweep.sun_elevation.count=100",
    "sweep.sun_azimuth.count=300",
    "sweep.cam_elevation.count=20",
    "sweep.cam_azimuth.count=15",
)  # 9e6 renders (under the 1e7 bound of a sweep), ~5.9 TB at the 600 kB default each

CASES = {
    "unknown-crater": (
        ["crater=atlantis"],  # the choices list every configs/crater/ entry (docs/catalogue.md)
        "unknown crater 'atlantis' (override crater=atlantis): choose one of aepinus, amundsen, bi_sheng, bosch, "
        "cabeus, cai_lun, custom, de_forest, de_gerlache,",
    ),
    "crater-in-the-other-hemisphere": (
        ["crater=peary"],  # a north-polar catalogue crater with the default (south-polar) DEM
        "crater peary (lat 88.63) is in the northern hemisphere but DEM lola_ldem256_south is south-polar: "
        "use dem=lola_ldem256_north",
    ),
    "crater-outside-dem": (
        ["crater=custom", "crater.custom.lat=0", "crater.custom.lon=0", "crater.custom.diameter_km=20"],
        "crater custom at (lat 0, lon 0) lies outside DEM lola_ldem256_south",
    ),
    "custom-crater-without-lat": (["crater=custom"], "crater.custom.lat: missing mandatory config value"),
    "sun-elevation-95": (["sweep.sun_elevation.values=[95]"], "invalid sweep.sun_elevation values [95.0]"),
    "sun-elevation--90": (["sweep.sun_elevation.values=[-90]"], "invalid sweep.sun_elevation values [-90.0]"),
    "sigma-0": (["sweep.sigma.values=[0]"], "invalid sweep.sigma values [0.0]: ROI ratio must be > 0"),
    "sigma-negative": (["sweep.sigma.values=[-0.5]"], "invalid sweep.sigma values [-0.5]"),
    "sigma-leaves-frame": (["sweep.sigma.values=[3]"], "ROI box of sigma=3.0 leaves the 90.0 deg frame"),
    "fov-180": (["sweep.fov_deg=180"], "invalid sweep.fov_deg=180.0: field of view must lie in (0, 180)"),
    "fov-270": (["sweep.fov_deg=270"], "invalid sweep.fov_deg=270.0"),
    "cam-elevation-0": (["sweep.cam_elevation.values=[0]"], "invalid sweep.cam_elevation values [0.0]"),
    "samples-0": (["render.samples=0"], "render.samples=0: must be >= 1"),
    "samples-not-a-number": (["render.samples=many"], "render.samples=many: must be an integer"),
    "mode-foo": (["render.mode=foo"], "render.mode='foo': must be 'fast' or 'direct'"),
    "threads-negative": (["render.threads=-1"], "render.threads=-1: must be >= 0"),
    "shadow-map-0": (["render.shadow_map_px=0"], "render.shadow_map_px=0: must lie in [1, 4096]"),
    "hapke-w": (["hapke.w=-1"], "Hapke parameter(s) out of physical range: w=-1.0"),
    "bad-shard": (["launcher.shard=2/2"], "launcher.shard='2/2': need 0 <= i < n"),
    "unknown-key": (["render.sample=4"], "render.sample: unknown key (did you mean render.samples?)"),
    # The largest crops (render.roi_min_px at its bound): petabytes, more than any test machine has free.
    "too-little-disk": ([*HUGE, "render.roi_min_px=4096"], "9000000 renders need ~"),
    "too-big-sweep": (
        [*HUGE, "sweep.cam_azimuth.count=1000"],
        "sweep of 100 x 300 x 20 x 1000 = 600,000,000 renders per crater: at most 10,000,000",
    ),
}


def _check_one_error(proc, expected: str, out):
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert expected in lines[0]
    assert proc.stdout == ""
    assert not exr_files(out)
    assert not (out / ".jobs").exists()  # no Blender worker was started


@pytest.mark.parametrize("overrides,expected", CASES.values(), ids=CASES.keys())
def test_bad_value_is_one_error_line(tmp_path, tiny_data_dir, overrides, expected):
    out = tmp_path / "ds"
    proc = run_cli("dataset", *TINY, f"data_dir={tiny_data_dir}", f"out_dir={out}", *overrides)
    _check_one_error(proc, expected, out)


@pytest.mark.parametrize("case", ["crater-outside-dem", "samples-0", "sigma-leaves-frame", "too-little-disk"])
def test_dask_launcher_checks_before_starting_a_cluster(tmp_path, tiny_data_dir, case):
    overrides, expected = CASES[case]
    out = tmp_path / "ds"
    proc = run_cli(
        "dataset", *TINY, f"data_dir={tiny_data_dir}", f"out_dir={out}", "launcher=dask", *overrides, timeout=60
    )
    _check_one_error(proc, expected, out)
    assert "dask sweep" not in proc.stderr  # no progress bar: the cluster never started


@pytest.mark.parametrize("where", ["under-a-file", "proc"])
def test_unwritable_output_directory(tmp_path, tiny_data_dir, where):
    # Tests run as root, so a chmod'ed directory would not stop them: use a path under a regular file,
    # and one in /proc (no directory can be made there, even by root).
    (tmp_path / "a-file").write_text("x")
    target = tmp_path / "a-file" / "ds" if where == "under-a-file" else "/proc/crater-synth-test/ds"
    proc = run_cli("dataset", *TINY, f"data_dir={tiny_data_dir}", f"out_dir={target}")
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"error: out_dir={target}: cannot create the directory: "), lines
    assert (tmp_path / "a-file").read_text() == "x"


def test_free_disk_estimate_uses_measured_render_size(tmp_path, tiny_data_dir, tiny_dataset, monkeypatch):
    """Resuming a dataset: the estimate uses the measured compression of its EXRs at the sweep's crop size
    (~29 kB here, not a fixed figure). The free space is faked in-process (a real full disk cannot be made
    here)."""
    from crater_synth.dataset.launcher import dataset_command

    out = tmp_path / "ds"
    tiny_dataset(out)  # 4 renders of the smoke sweep
    sizes = [p.stat().st_size for p in exr_files(out)]
    mean = sum(sizes) // len(sizes)
    real_usage = shutil.disk_usage
    free = int(4 * mean)  # 4 renders left, each ~mean bytes: need 4 x mean x 1.1 > free

    def fake_usage(path):
        return real_usage(path)._replace(free=free)

    monkeypatch.setattr(shutil, "disk_usage", fake_usage)
    result = CliRunner().invoke(
        dataset_command, [*TINY, f"data_dir={tiny_data_dir}", f"out_dir={out}", "sweep.cam_elevation.count=2"]
    )  # 8 renders, 4 of them new
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    found = re.fullmatch(
        rf"error: not enough free disk in {re.escape(str(out))}: 4 renders need ~([0-9.]+) kB "
        rf"\(~([0-9.]+) kB each, \+10 %\), {re.escape(_kb(free))} free",
        lines[0] if len(lines) == 1 else "",
    )
    assert found, lines
    each = float(found.group(2)) * 1e3
    assert abs(each - mean) < 0.05 * mean, (each, mean)  # the measured size, within 5 %
    assert len(exr_files(out)) == 4


def _kb(n):
    return f"{n / 1e3:.2f} kB"
