"""crater-synth sunmatch: orthorectifying the real mosaic into a render's frame, the lit-area overlap,
and the command end to end on a tiny sun grid."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crater_core import geometry
from crater_synth.errors import ConfigError
from crater_synth.evaluation import sunmatch
from train.realset import Mosaic

from helpers.cli import TINY, run_cli

LAT, LON = -85.0, 40.0


def _nadir_row(width: int = 101, range_m: float = 30e3) -> dict:
    return {
        "cam_elevation": 90.0,
        "cam_azimuth": 180.0,
        "range_m": range_m,
        "fov_deg": 90.0,
        "crop_origin": [0, 0],
        "frame_width": width,
    }


def test_nadir_pixels_map_to_the_crater_north_up_east_right():
    row = _nadir_row()
    depth = np.full((101, 101), row["range_m"])  # flat ground through the crater centre
    lat, lon = sunmatch.ground_latlon(row, depth, {"lat": LAT, "lon": LON})
    # Pixel (50, 50) covers [50, 51): its centre is the frame centre, i.e. the crater centre.
    assert lat[50, 50] == pytest.approx(LAT, abs=1e-9)
    assert lon[50, 50] == pytest.approx(LON, abs=1e-9)
    assert lat[0, 50] > LAT > lat[100, 50]  # up is north
    assert lon[50, 100] > LON > lon[50, 0]  # right is east
    # 90 deg FOV at 30 km: the frame spans 60 km on the ground.
    span_m = np.radians(lat[0, 50] - lat[100, 50]) * geometry.MOON_RADIUS_M
    assert span_m == pytest.approx(60e3 * 100 / 101, rel=2e-3)


def test_real_mosaic_is_sampled_at_pixel_centres():
    size, pixel = 400, 400.0
    u_ramp = np.tile(np.arange(size, dtype=np.float32), (size, 1))  # value = column index
    mosaic = Mosaic("fake", None, u_ramp, extent_m=size * pixel / 2, pixel_m=pixel, radius_m=geometry.MOON_RADIUS_M)
    lat = np.array([-88.0, -87.5, -89.1])
    lon = np.array([10.0, -120.0, 75.0])
    x, _ = geometry.south_polar_stereo_forward(lat, lon)
    want = (x + mosaic.extent_m) / pixel - 0.5  # the value at a pixel centre is that pixel's index
    np.testing.assert_allclose(sunmatch.real_in_render_frame(mosaic, lat, lon), want, atol=1e-3)


def test_lit_iou():
    a = np.array([[1, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 0]], dtype=bool)
    b = np.array([1, 1, 1, 0], dtype=bool)
    np.testing.assert_allclose(sunmatch.lit_iou(a, b), [2 / 3, 1 / 4, 0.0])
    assert sunmatch.lit_iou(np.zeros((1, 4), bool), np.zeros(4, bool))[0] == 1.0  # nothing lit in either


def test_greedy_composite_finds_the_frames_of_a_mosaic():
    # The target is lit where either of renders 1 and 3 is: one sun explains half of it, their union all.
    lit = np.array([[1, 0, 0, 0, 0, 0], [1, 1, 1, 0, 0, 0], [1, 1, 0, 0, 0, 1], [0, 0, 0, 1, 1, 1]], dtype=bool)
    target = lit[1] | lit[3]
    chosen, ious = sunmatch.greedy_composite(lit, target, first=1, suns=3)
    assert chosen[:2] == [1, 3]
    np.testing.assert_allclose(ious, [0.5, 1.0, 1.0])
    # A target that one render explains gains nothing from a second sun.
    chosen, ious = sunmatch.greedy_composite(lit, lit[2], first=2, suns=2)
    assert ious[0] == 1.0 and ious[1] <= 1.0 and ious == sorted(ious, reverse=True)


@pytest.mark.parametrize("azimuths, fractions", [(7, 10), (2, 10), (36, 0)])
def test_nonsense_grids_are_refused(azimuths, fractions):
    with pytest.raises(ConfigError):
        sunmatch.sunmatch_overrides(["kocher"], azimuths, fractions)


def test_command_end_to_end(tmp_path):
    out = tmp_path / "out"
    proc = run_cli(
        "sunmatch",
        *TINY,
        f"data_dir={tmp_path / 'data'}",
        f"out_dir={tmp_path / 'ds'}",
        "--craters",
        "shackleton",
        "--azimuths",
        "4",
        "--fractions",
        "10",
        "--out",
        out,
        "--frames",
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads((out / "sunmatch.json").read_text())
    r = res["craters"]["shackleton"]
    assert res["roles"]["shackleton"] == "test"
    assert 0 < r["renders"] <= 40
    assert 0.0 <= r["median_iou"] <= r["best_iou"] <= 1.0
    assert r["best_iou_on_coarse_grid"] is not None and r["best_iou_on_coarse_grid"] <= r["best_iou"]
    assert set(r["iou_by_azimuth_step"]) <= {str(s) for s in sunmatch.AZIMUTH_STEPS_DEG}
    assert [c["suns"] for c in r["composite"]] == list(sunmatch.COMPOSITE_SUNS)
    assert all(len(c["azimuths_deg"]) == c["suns"] for c in r["composite"])
    # A union of lit areas chosen greedily from the best sun never explains the crop worse than it.
    assert r["best_iou"] - 1e-9 <= r["composite"][0]["iou"] <= r["composite"][1]["iou"] + 1e-9
    assert "| shackleton | test |" in (out / "sunmatch.md").read_text()
    assert (out / "sunmatch.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # The paired frames are a labels file the real-set loader reads (crater-synth evaluate uses it).
    from train.realset import load_labels_file

    crops = load_labels_file(out / "frames" / "labels.csv", ["shackleton"], [1.0])
    sources = {c.source for c in crops}
    assert {"real", "best", "real_roll15", "best_roll15"} <= sources
    assert len(crops) == len(sources) * len(sunmatch.FRAME_ROLLS_DEG)
    # One labels file per validate group, with only its craters (shackleton is in the test group).
    assert (out / "frames" / "labels_test.csv").read_text() == (out / "frames" / "labels.csv").read_text()
    assert (out / "frames" / "labels_validation1.csv").read_text().count("\n") == 1  # the header only


def test_command_bad_grid_is_one_line_and_writes_nothing(tmp_path):
    out = tmp_path / "out"
    proc = run_cli("sunmatch", *TINY, "--azimuths", "7", "--out", out)
    assert proc.returncode == 2
    assert "--azimuths 7" in proc.stderr and proc.stderr.strip().count("\n") == 0
    assert not out.exists()
