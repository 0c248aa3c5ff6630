"""``navigate`` on a map window: its options are checked before any work, it never overwrites an input, it
bounds the image it reads, and with the light estimated on the frame it gives no fix it cannot tell from
the opposite light's (navigate.either_light_fix). The off-grid windows of tools/navigate_offgrid."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from crater_synth.cli import main
from crater_synth.navigation import frame_file
from crater_synth.navigation import navigate as nv
from crater_synth.navigation.fix.solve import Fix
from crater_synth.paths import LANDMARKS_DIR


def _window(tmp_path, name="frame.png", n=128):
    """A textured south-pole map window (PNG + georeference); navigate's checks come before any fix."""
    import matplotlib.pyplot as plt

    img = tmp_path / name
    rng = np.random.default_rng(0)
    plt.imsave(img, rng.uniform(0, 255, (n, n)), cmap="gray", vmin=0, vmax=255)
    geo = img.with_name(img.name + ".geo.json")
    geo.write_text(json.dumps({"pole": "south", "left_m": 2e5, "top_m": 2e5, "pixel_m": 400.0}))
    return img, geo


def _one_line_error(r, *words):
    assert r.exit_code == 2, r.output
    assert len(r.output.strip().splitlines()) == 1, r.output
    for w in words:
        assert w in r.output, r.output


@pytest.mark.parametrize(
    "args, words",
    [
        (["--prior", "95,10"], ["--prior", "within +-90"]),
        (["--prior", "nan,10"], ["--prior", "finite"]),
        (["--prior", "80,10"], ["--prior", "south pole's side"]),
        (["--prior", "-80"], ["--prior", "LAT,LON"]),
        (["--pixel-m", "-1"], ["--pixel-m"]),
        (["--pixel-m", "0"], ["--pixel-m"]),
        (["--pixel-m", "nan"], ["--pixel-m"]),
        (["--pixel-m", "1e9"], ["--pixel-m"]),
        (["--light-azimuth", "inf"], ["--light-azimuth"]),
    ],
)
def test_navigate_refuses_implausible_options_in_one_line(tmp_path, args, words):
    img, _ = _window(tmp_path)
    r = CliRunner().invoke(main, ["navigate", str(img), *args])
    _one_line_error(r, *words)
    assert not list(tmp_path.glob("*.nav.*"))


def test_navigate_refuses_a_map_of_the_other_pole(tmp_path):
    img, _ = _window(tmp_path)
    r = CliRunner().invoke(main, ["navigate", str(img), "--map", str(LANDMARKS_DIR / "north.geojson")])
    _one_line_error(r, "north pole", "south-pole frame")
    assert not list(tmp_path.glob("*.nav.*"))


def test_navigate_never_overwrites_its_inputs(tmp_path):
    img, geo = _window(tmp_path)
    before = img.read_bytes(), geo.read_bytes()
    for out in (img, geo, tmp_path / "frame.png.geo.png"):  # the last one's listing is frame.png.geo.json
        r = CliRunner().invoke(main, ["navigate", str(img), "--out", str(out)])
        _one_line_error(r, "--out", "would overwrite the input")
    mp = tmp_path / "map.geojson"
    mp.write_bytes((LANDMARKS_DIR / "south.geojson").read_bytes())
    r = CliRunner().invoke(main, ["navigate", str(img), "--map", str(mp), "--out", str(mp)])
    _one_line_error(r, "would overwrite the input")
    assert (img.read_bytes(), geo.read_bytes()) == before


def test_navigate_refuses_an_image_too_large_from_its_header(tmp_path, monkeypatch):
    img, _ = _window(tmp_path, n=128)
    monkeypatch.setattr(frame_file, "MAX_FRAME_PIXELS", 100 * 100)
    r = CliRunner().invoke(main, ["navigate", str(img)])
    _one_line_error(r, "128 x 128 px", "more than the 10000 px")


# ------------------------------------------------------------------------------------------------
# Both light directions
# ------------------------------------------------------------------------------------------------
def _fake(monkeypatch, fixes: dict):
    """detect() gives the light it ran with as its "detections"; fit() the fix ``fixes`` names for that
    light: "est" (the estimate, 0.5 rad) or "flip" (its opposite)."""
    calls = []

    def detect(img, params, light_dir=None, what=""):
        theta = 0.5 if light_dir is None else light_dir
        calls.append(light_dir)
        return ["est" if abs(theta - 0.5) < 1e-9 else "flip"], theta

    monkeypatch.setattr(nv, "detect", detect)
    return (lambda dets: fixes[dets[0]]), calls


def _fix(x_km, n):
    return Fix(True, x_m=x_km * 1000.0, y_m=0.0, inliers=[(i, i) for i in range(n)], rms_px=2.0)


NO = Fix(False, reason="no")


@pytest.mark.parametrize(
    "est, flip, expect",
    [
        (_fix(0, 12), _fix(4, 6), "est"),  # the estimate's fix has twice the landmarks: kept
        (_fix(4, 7), _fix(0, 16), "flip"),  # the light read 180 deg wrong: the opposite's fix is kept
        (_fix(0, 6), _fix(6, 5), None),  # close support, 6 km apart: no fix, and the reason says why
        (_fix(0, 6), _fix(0.5, 6), "est"),  # the two agree: one place
        (NO, _fix(0, 9), None),  # found only with the opposite light: not taken
        (_fix(0, 6), NO, "est"),
    ],
)
def test_either_light_fix_keeps_the_clearly_better_light_or_none(monkeypatch, est, flip, expect):
    fit, calls = _fake(monkeypatch, {"est": est, "flip": flip})
    dets, theta, fix = nv.either_light_fix(np.zeros((8, 8)), SimpleNamespace(), None, fit, "f")
    if expect is None:
        assert not fix.ok
        if est.ok:
            assert "--light-azimuth" in fix.reason and "km apart" in fix.reason
    else:
        assert fix.ok and dets == [expect]
        assert theta == pytest.approx(0.5 if expect == "est" else 0.5 + math.pi)


def test_a_given_light_runs_the_detector_once(monkeypatch):
    fit, calls = _fake(monkeypatch, {"est": _fix(0, 6), "flip": _fix(4, 20)})
    dets, theta, fix = nv.either_light_fix(np.zeros((8, 8)), SimpleNamespace(), 0.5, fit, "f")
    assert calls == [0.5] and dets == ["est"] and fix.ok


def test_offgrid_windows_are_seeded_inside_their_split_and_off_the_grid():
    from crater_synth.navigation.windows.mosaic import SPLITS, STRIDE_PX, sector_of
    from crater_synth.tools.navigate_offgrid import offgrid_windows

    a = offgrid_windows("south", "validation", 12, seed=3)
    b = offgrid_windows("south", "validation", 12, seed=3)
    assert [f.id for f in a] == [f.id for f in b] and len({f.id for f in a}) == 12
    off_grid = 0
    for f in a:
        h, w = f.image.shape
        x, y = f.georef.uv_to_xy(np.array([0.0, w, 0.0, w]), np.array([0.0, 0.0, h, h]))
        sectors = sector_of(x, y, "south")
        assert len(set(sectors.tolist())) == 1 and SPLITS["south"][int(sectors[0])] == "validation"
        u0, v0 = (int(t) for t in f.id.split("_")[1:])
        off_grid += u0 % STRIDE_PX != 0 or v0 % STRIDE_PX != 0
    assert off_grid >= 10
