"""Runs that are legal but almost surely a mistake: a `warning:` line, and the run goes on."""

from helpers.cli import TINY, exr_files, run_cli, summary


def test_sun_below_the_horizon_warns_before_and_after_rendering(tmp_path, tiny_data_dir):
    out = tmp_path / "ds"
    proc = run_cli("dataset", *TINY, f"data_dir={tiny_data_dir}", f"out_dir={out}", "sweep.sun_elevation.values=[-5]")
    assert proc.returncode == 0, proc.stderr
    warnings = [line for line in proc.stderr.splitlines() if line.startswith("warning: ")]
    assert warnings[0] == (
        "warning: sweep.sun_elevation values [-5.0] put the Sun below the local horizon at the "
        "crater: those renders will be (almost) all black"
    )
    assert warnings[1].startswith("warning: 4 of 4 new renders are entirely in shadow (lit_fraction 0, all black)")
    assert summary(proc)["rendered"] == 4 and len(exr_files(out)) == 4


def test_sun_at_the_horizon_is_not_below_it():
    from crater_core.settings import SweepSettings

    sweep = SweepSettings.from_config(
        {
            "name": "x",
            "sun_elevation": {"count": 1, "values": [0.0, 0.16]},
            **{a: {"count": 1} for a in ("sun_azimuth", "cam_elevation", "cam_azimuth", "sigma")},
            "fov_deg": 90.0,
            "range_factor": 1.5,
        },
        "sweep",
    )
    assert sweep.warnings() == [
        "sweep.sun_elevation values [0.0] put the Sun at or below the local horizon at the "
        "crater: those renders will be (almost) all black"
    ]
    ok = SweepSettings.from_config({**sweep.as_dict(), "sun_elevation": {"count": 2, "values": None}}, "sweep")
    assert ok.warnings() == []
