"""``navigate DIR --out FOLDER`` (every map window of a folder in one process, as each alone) and ``navigate
--heading`` (a window that is not north-up, turned north-up before detection). The real windows are south
validation windows (development data)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from crater_synth.cli import main
from crater_synth.navigation.detectors.classical import Detection
from crater_synth.navigation.georef import Georef, ground_distance_km, stereo_forward
from crater_synth.navigation.windows.navigate import turned_back, turned_footprint, turned_north_up

SOUTH_VALIDATION = ("S0_1536_0320", "S0_1600_0320")  # two windows of a validation sector


def _noise_window(folder, name="frame.png", n=128):
    """A textured south-pole map window (PNG + georeference) whose checks come before any fix."""
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    img = folder / name
    rng = np.random.default_rng(0)
    plt.imsave(img, rng.uniform(0, 255, (n, n)), cmap="gray", vmin=0, vmax=255)
    img.with_name(img.name + ".geo.json").write_text(
        json.dumps({"pole": "south", "left_m": 2e5, "top_m": 2e5, "pixel_m": 400.0})
    )
    return img


def _one_line_error(r, *words):
    assert r.exit_code == 2, r.output
    assert len(r.output.strip().splitlines()) == 1, r.output
    for w in words:
        assert w in r.output, r.output


def _rotated(image: np.ndarray, heading_deg: float) -> np.ndarray:
    """A north-up window as a camera whose up points ``heading_deg`` clockwise from the map's up sees it:
    the content turned counter-clockwise on the screen (cv2's positive angle), the corners its median."""
    h, w = image.shape
    turn = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), heading_deg, 1.0)
    fill = float(np.median(image))
    out = cv2.warpAffine(image.astype(np.float32), turn, (w, h), flags=cv2.INTER_LINEAR, borderValue=fill)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------------------------
# Fast: refusals, bad input, the turn's geometry
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_a_non_finite_heading_is_one_error_line(tmp_path, value):
    img = _noise_window(tmp_path / "in")
    r = CliRunner().invoke(main, ["navigate", str(img), "--heading", value])
    _one_line_error(r, "--heading", "finite")
    r = CliRunner().invoke(main, ["navigate", str(tmp_path / "in"), "--out", str(tmp_path / "o"), "--heading", value])
    _one_line_error(r, "--heading", "finite")
    assert not (tmp_path / "o").exists() and not list((tmp_path / "in").glob("*.nav.*"))


def test_a_folder_needs_its_own_output_folder_and_refuses_a_foreign_one(tmp_path):
    src = tmp_path / "in"
    _noise_window(src)
    r = CliRunner().invoke(main, ["navigate", str(src)])
    _one_line_error(r, "give --out FOLDER")
    r = CliRunner().invoke(main, ["navigate", str(src), "--out", str(src)])
    _one_line_error(r, "is the input folder")
    r = CliRunner().invoke(main, ["navigate", str(src), "--out", str(tmp_path / "r.json")])
    _one_line_error(r, "not one file")
    r = CliRunner().invoke(main, ["navigate", str(src), "--out", str(tmp_path / "o"), "--prior", "-80,20"])
    _one_line_error(r, "--prior", "--lost-in-space")
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("a user's file")
    r = CliRunner().invoke(main, ["navigate", str(src), "--out", str(foreign)])
    _one_line_error(r, "notes.txt", "did not write")
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]
    # detect's output folder is another kind
    det = tmp_path / "det"
    det.mkdir()
    (det / ".crater-synth-detections").write_text(json.dumps({"kind": "detections", "files": {}}))
    r = CliRunner().invoke(main, ["navigate", str(src), "--out", str(det)])
    _one_line_error(r, "crater lists", "not crater-synth navigate's")
    (src / "frame_0000.exr").write_bytes(b"x")
    r = CliRunner().invoke(main, ["navigate", str(src), "--out", str(tmp_path / "o")])
    _one_line_error(r, "rendered frames", "frame_0000.exr")
    assert not (tmp_path / "o").exists()
    img = src / "frame.png"
    r = CliRunner().invoke(main, ["navigate", str(img), "--png"])
    _one_line_error(r, "--png")


def test_one_bad_image_does_not_stop_the_folder(tmp_path):
    src = tmp_path / "in"
    _noise_window(src, "a.png")
    _noise_window(src, "c.png")
    (src / "b.png").write_bytes(b"\x89PNG not really")
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["navigate", str(src), "--out", str(out)])
    assert r.exit_code == 1, r.output
    errors = [line for line in r.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "b.png" in errors[0]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["images"] == 3 and [f["image"] for f in summary["failed"]] == ["b.png"]
    assert [x["image"] for x in summary["results"]] == [str(src / "a.png"), str(src / "c.png")]
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "a.png.nav.json",
        "c.png.nav.json",
        "summary.json",
    ]
    # the same folder again (the bad image mended by removing it) replaces the run's own files only
    (src / "b.png").unlink()
    r = CliRunner().invoke(main, ["navigate", str(src), "--out", str(out), "--png"])
    assert r.exit_code == 0, r.output
    assert (out / "a.png.nav.png").is_file() and json.loads((out / "summary.json").read_text())["failed"] == []


@pytest.mark.parametrize("heading", [20.0, -35.0, 90.0])
def test_a_turned_frame_is_turned_back_north_up_and_its_detections_back(heading):
    """A bright dot of a north-up frame, seen by a camera turned by ``heading``, is back at its north-up place
    on the canvas, and the canvas's place of it maps back to the turned frame's; the canvas keeps the centre."""
    north = np.zeros((128, 128), dtype=np.float32)
    north[30, 90] = 1.0  # pixel centre (90.5, 30.5) from the corner
    seen = cv2.warpAffine(north, cv2.getRotationMatrix2D((63.5, 63.5), heading, 1.0), (128, 128))
    truth = Georef("south", 1000.0, 5000.0, 10.0)
    canvas, canvas_truth, turn = turned_north_up(seen, truth, heading)
    side = math.ceil(128 * (abs(math.cos(math.radians(heading))) + abs(math.sin(math.radians(heading)))) - 1e-6)
    assert canvas.shape == (side, side)
    ch, cw = canvas.shape
    # the same map point at the centre of both
    assert np.allclose(canvas_truth.uv_to_xy(cw / 2, ch / 2), truth.uv_to_xy(64, 64))
    v, u = np.unravel_index(np.argmax(canvas), canvas.shape)
    x, y = canvas_truth.uv_to_xy(u + 0.5, v + 0.5)
    assert math.hypot(x - truth.uv_to_xy(90.5, 30.5)[0], y - truth.uv_to_xy(90.5, 30.5)[1]) <= 15.0  # 1.5 px
    sv, su = np.unravel_index(np.argmax(seen), seen.shape)
    (back,) = turned_back([Detection(float(u) + 0.5, float(v) + 0.5, 3.0, 1.0)], turn)
    assert abs(back.u - (su + 0.5)) <= 1.5 and abs(back.v - (sv + 0.5)) <= 1.5 and back.r == 3.0
    # the canvas's filled corners are not the frame's: a correlation masks them
    inside = turned_footprint(turn, seen.shape, canvas.shape)
    assert inside.shape == canvas.shape and inside[ch // 2, cw // 2]
    assert abs(inside.sum() - seen.size) <= 0.02 * seen.size
    if heading % 90:
        assert not inside[0, 0] and not inside[-1, -1]


# ------------------------------------------------------------------------------------------------
# Real windows (south validation)
# ------------------------------------------------------------------------------------------------
def _real_windows(folder):
    from crater_synth.navigation.windows.mosaic import windows
    from crater_synth.navigation.windows.navigate import write_window

    folder.mkdir(parents=True, exist_ok=True)
    frames = {f.id: f for f in windows("validation", "south") if f.id in SOUTH_VALIDATION}
    for wid in SOUTH_VALIDATION:
        write_window(folder / f"{wid}.png", frames[wid])
    return frames


def _same(result: dict) -> dict:
    return {k: v for k, v in result.items() if k not in ("image", "annotated", "detections_file", "list", "png")}


@pytest.mark.integration
def test_a_folder_in_one_process_gives_each_window_its_single_result(tmp_path):
    src = tmp_path / "in"
    _real_windows(src)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["navigate", str(src), "--out", str(out)])
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["images"] == 2 and summary["fixes"] >= 1 and not summary["failed"]
    for wid, folder_result in zip(SOUTH_VALIDATION, summary["results"], strict=True):
        one = tmp_path / "one" / f"{wid}.png"
        one.parent.mkdir(exist_ok=True)
        for suffix in ("", ".geo.json"):
            (tmp_path / "one" / f"{wid}.png{suffix}").write_bytes((src / f"{wid}.png{suffix}").read_bytes())
        r = CliRunner().invoke(main, ["navigate", str(one)])
        assert r.exit_code == 0, r.output
        single = json.loads(r.output.strip().splitlines()[-1])
        assert _same(single) == {k: v for k, v in _same(folder_result).items() if k != "seconds"}
        listed = json.loads((out / f"{wid}.png.nav.json").read_text())
        assert listed["detections"] == json.loads(one.with_name(f"{wid}.nav.json").read_text())["detections"]


@pytest.mark.integration
def test_a_window_turned_by_20_degrees_fixes_with_its_heading_and_not_without(tmp_path):
    from crater_synth.navigation.georef import Frame
    from crater_synth.navigation.windows.navigate import write_window

    frames = _real_windows(tmp_path / "north_up")
    frame = frames[SOUTH_VALIDATION[0]]
    turned = tmp_path / "turned.png"
    write_window(turned, Frame(frame.id, frame.split, frame.sector, _rotated(frame.image, 20.0), frame.georef))
    runner = CliRunner()

    def fix_of(image, *args):
        r = runner.invoke(
            main, ["navigate", str(image), *args, "--out", str(tmp_path / f"{image.stem}.nav{''.join(args)}.png")]
        )
        assert r.exit_code == 0, r.output
        return json.loads(r.output.strip().splitlines()[-1])

    north_up = fix_of(tmp_path / "north_up" / f"{frame.id}.png")
    with_heading = fix_of(turned, "--heading", "20")
    assert north_up["fix"] and with_heading["fix"] and with_heading["heading_deg"] == 20.0
    x0, y0 = stereo_forward(north_up["lat"], north_up["lon"], "south")
    x1, y1 = stereo_forward(with_heading["lat"], with_heading["lon"], "south")
    assert float(ground_distance_km(float(x0), float(y0), float(x1), float(y1), "south")) < 0.3
    assert with_heading["error_km"] < 1.0
    # Its detections are listed in the turned frame's own pixels: inside it.
    listed = json.loads((tmp_path / "turned.nav--heading20.json").read_text())["detections"]
    assert listed and all(0 <= d["u"] <= 512 and 0 <= d["v"] <= 512 for d in listed)
    without = fix_of(turned)
    assert not without["fix"] or without["error_km"] > 2.0
    wrong = fix_of(turned, "--heading", "-20")
    assert not wrong["fix"] or wrong["error_km"] > 2.0
