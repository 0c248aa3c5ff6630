"""``crater-synth detect IMAGE|DIR`` (crater_synth.navigation.detect_cmd): craters found where they were drawn,
georeferenced output consistent with the georeference, a folder in one run that survives its bad files, one
error line and no output for each bad input, no input overwritten, the detections output folder's contract."""

from __future__ import annotations

import csv
import json
import math
import os

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from crater_synth.cli import main
from crater_synth.navigation.detect_cmd import LIST_SUFFIX, PNG_SUFFIX, SUMMARY_NAME, TABLE_NAME
from crater_synth.navigation.detectors.template import crater_heights, shade_heights
from crater_synth.navigation.georef import Georef, scale_factor, stereo_inverse
from crater_synth.outfolder import LOCK_NAME, MARKERS

# (u, v, r) px of the drawn craters: radii the default detector searches (>= 9 px), apart from each other
CRATERS = [(70.0, 80.0, 16.0), (220.0, 70.0, 22.0), (150.0, 190.0, 28.0), (60.0, 250.0, 18.0), (250.0, 250.0, 20.0)]
GEOREF = {"pole": "south", "left_m": 150_000.0, "top_m": 250_000.0, "pixel_m": 400.0}


def crater_image(n: int = 320, light_deg: float = 35.0) -> np.ndarray:
    """8-bit nadir image of :data:`CRATERS` (Hapke-shaded bowls with cast shadows at 12 deg Sun, mild noise)."""
    vv, uu = np.mgrid[0:n, 0:n] + 0.5
    z = np.zeros((n, n))
    for cu, cv, r in CRATERS:
        z += crater_heights(np.hypot(uu - cu, vv - cv) / r, 0.2) * r
    img = shade_heights(z, math.radians(light_deg), 12.0)
    img = img / img.max() * 230.0 + 15.0 + np.random.default_rng(0).normal(0.0, 2.0, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def write_image(path, img=None, georef: dict | None = None):
    assert cv2.imwrite(str(path), crater_image() if img is None else img)
    if georef is not None:
        path.with_name(path.name + ".geo.json").write_text(json.dumps(georef))
    return path


def run(*args):
    return CliRunner().invoke(main, ["detect", *map(str, args)])


def one_error(r, *words, code: int = 2):
    assert r.exit_code == code, r.output
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    for w in words:
        assert str(w) in lines[0], lines[0]


def matched(records) -> list[dict]:
    """For each drawn crater the record that finds it (centre within 0.3 r, radius within 25 %), or None."""
    out = []
    for cu, cv, r in CRATERS:
        hits = [d for d in records if math.hypot(d["u"] - cu, d["v"] - cv) < 0.3 * r and abs(d["a"] / r - 1) < 0.25]
        out.append(hits[0] if hits else None)
    return out


# ------------------------------------------------------------------------------------------------
# Detections
# ------------------------------------------------------------------------------------------------
def test_the_default_detector_finds_the_drawn_craters_and_prints_one_line_each(tmp_path):
    img = write_image(tmp_path / "field.png")
    r = run(img)
    assert r.exit_code == 0, r.output
    records = [json.loads(line) for line in r.stdout.splitlines()]
    assert all(m is not None for m in matched(records)), records
    assert len(records) <= len(CRATERS) + 1  # the precise operating point: hardly a false crater
    assert all(d["a"] == d["b"] and d["angle_deg"] == 0.0 and 0 < d["score"] <= 1 for d in records)
    assert "lat" not in records[0] and "d_km" not in records[0]  # no georeference, no --pixel-m
    assert sorted(p.name for p in tmp_path.iterdir()) == ["field.png"]  # nothing written beside the input


def test_a_filter_detector_takes_the_light_given(tmp_path):
    img = write_image(tmp_path / "field.png")
    r = run(img, "--detector", "template", "--light-azimuth", "35")
    assert r.exit_code == 0, r.output
    records = [json.loads(line) for line in r.stdout.splitlines()]
    assert sum(m is not None for m in matched(records)) >= 4, records


def test_georeferenced_output_gives_latitude_longitude_and_diameter_from_the_georeference(tmp_path):
    img = write_image(tmp_path / "field.png", georef=GEOREF)
    out = tmp_path / "out" / "craters.geojson"
    r = run(img, "--out", out, "--png")
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["craters"] >= len(CRATERS) and summary["georeferenced"] and summary["out"] == str(out)
    doc = json.loads(out.read_text())
    assert doc["type"] == "FeatureCollection" and doc["crater_synth"]["georef"] == GEOREF
    g = Georef(**GEOREF)
    props = [f["properties"] for f in doc["features"]]
    for f in doc["features"]:
        p = f["properties"]
        assert f["geometry"] == {"type": "Point", "coordinates": [p["lon"], p["lat"]]}
    for (cu, cv, rad), p in zip(CRATERS, matched(props), strict=True):
        assert p is not None
        # Where the crater was drawn, through the georeference; D as drawn, over the scale factor.
        lat, lon = stereo_inverse(*g.uv_to_xy(cu, cv), "south")
        k = float(scale_factor(lat, "south"))
        assert abs(p["lat"] - lat) < 0.3 * rad * 400 / 30_300  # 0.3 r in degrees of latitude (~30.3 km/deg)
        assert abs(math.remainder(p["lon"] - lon, 360.0)) < 1.0
        assert p["d_km"] == pytest.approx(2 * p["a"] * 0.4 / k, rel=1e-3)
        assert p["d_km"] == pytest.approx(2 * rad * 0.4 / k, rel=0.25)
    drawn = cv2.imread(str(out.with_suffix(".png")))
    assert drawn.shape == (320, 320, 3) and (drawn[..., 1] > drawn[..., 2] + 100).any()  # green ellipses
    # The same craters as CSV, the same numbers.
    r = run(img, "--out", tmp_path / "craters.csv")
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader((tmp_path / "craters.csv").open()))
    assert [float(row["lat"]) for row in rows] == [p["lat"] for p in props]
    assert {row["image"] for row in rows} == {"field.png"}


def write_geotiff(path, crs: str, img=None):
    """The crater image as a GeoTIFF with its own map georeference: :data:`GEOREF`'s corner and pixel in ``crs``."""
    import rasterio
    from rasterio.transform import Affine

    img = crater_image() if img is None else img
    g = GEOREF
    transform = Affine(g["pixel_m"], 0.0, g["left_m"], 0.0, -g["pixel_m"], g["top_m"])
    profile = dict(driver="GTiff", width=img.shape[1], height=img.shape[0], count=1, dtype="uint8")
    with rasterio.open(path, "w", crs=crs, transform=transform, **profile) as ds:
        ds.write(img, 1)
    return path


SOUTH_STEREO = "+proj=stere +lat_0=-90 +lon_0=0 +k=1 +x_0=0 +y_0=0 +R=1737400 +units=m +no_defs"


def test_a_geotiff_carries_its_own_georeference_and_gives_the_sidecar_s_values(tmp_path):
    """The same polar stereographic georeference as a GeoTIFF's CRS and as a PNG's sidecar: the same
    latitudes and longitudes, and D (great circles in the CRS, the scale factor with the sidecar) to 0.1 %."""
    png = write_image(tmp_path / "field.png", georef=GEOREF)
    tif = write_geotiff(tmp_path / "field.tif", SOUTH_STEREO)
    by_sidecar = [json.loads(line) for line in run(png).stdout.splitlines()]
    r = run(tif)
    assert r.exit_code == 0, r.output
    by_crs = [json.loads(line) for line in r.stdout.splitlines()]
    assert len(by_crs) == len(by_sidecar) >= len(CRATERS)
    for a, b in zip(by_crs, by_sidecar, strict=True):
        assert (a["u"], a["v"], a["a"]) == (b["u"], b["v"], b["a"])
        assert a["lat"] == pytest.approx(b["lat"], abs=1e-5) and a["lon"] == pytest.approx(b["lon"], abs=1e-5)
        assert a["d_km"] == pytest.approx(b["d_km"], rel=1e-3)
    one_error(run(tif, "--pixel-m", "400"), "field.tif", "own georeference")


def test_a_geotiff_of_another_body_is_refused(tmp_path):
    tif = write_geotiff(tmp_path / "earth.tif", "EPSG:3857")
    one_error(run(tif, "--out", tmp_path / "x.geojson"), "earth.tif", "not the Moon")
    assert not (tmp_path / "x.geojson").exists()


def test_pixel_size_alone_gives_the_diameter_and_a_conflicting_one_is_refused(tmp_path):
    img = write_image(tmp_path / "field.png")
    r = run(img, "--pixel-m", "100")
    records = [json.loads(line) for line in r.stdout.splitlines()]
    assert records and all(d["d_km"] == pytest.approx(2 * d["a"] * 0.1, abs=1e-3) and "lat" not in d for d in records)
    geo = write_image(tmp_path / "geo.png", georef=GEOREF)
    one_error(run(geo, "--pixel-m", "100"), geo, "disagrees with its georeference")


# ------------------------------------------------------------------------------------------------
# Bad input: one line naming it, nothing written
# ------------------------------------------------------------------------------------------------
def bad_image(tmp_path, kind: str):
    path = tmp_path / f"{kind}.png"
    if kind == "constant":
        write_image(path, np.full((64, 64), 90, np.uint8))
    elif kind == "tiny":
        write_image(path, np.zeros((1, 1), np.uint8))
    elif kind == "corrupt":
        path.write_bytes(write_image(tmp_path / "good.png").read_bytes()[:300])
    elif kind == "nan":
        path = tmp_path / "nan.tiff"
        a = crater_image().astype(np.float32)
        a[10:20, 10:20] = np.nan
        assert cv2.imwrite(str(path), a)
    elif kind == "grey+alpha":
        import OpenImageIO as oiio

        out = oiio.ImageOutput.create(str(path))
        out.open(str(path), oiio.ImageSpec(64, 64, 2, oiio.UINT8))
        out.write_image(np.zeros((64, 64, 2), np.uint8))
        out.close()
    elif kind == "directory":
        path.mkdir()
    return path


@pytest.mark.parametrize(
    "kind, words",
    [
        ("constant", ["the frame is empty"]),
        ("tiny", ["at least 32x32 px"]),
        ("corrupt", ["corrupt.png"]),
        ("nan", ["non-finite pixels"]),
        ("grey+alpha", ["2 channels"]),
        ("directory", []),
    ],
)
def test_a_bad_image_is_one_error_line_naming_it_and_writes_nothing(tmp_path, kind, words):
    path = bad_image(tmp_path, kind)
    out = tmp_path / "out.geojson"
    one_error(run(path, "--out", out, "--png"), path.name, *words)
    assert not out.exists() and not out.with_suffix(".png").exists()


def test_a_missing_image_and_one_too_large_are_one_line_read_from_the_header(tmp_path, monkeypatch):
    from crater_synth.navigation import frame_file

    one_error(run(tmp_path / "nothing.png"), "nothing.png", "no such image file")
    img = write_image(tmp_path / "field.png")
    monkeypatch.setattr(frame_file, "MAX_FRAME_PIXELS", 100 * 100)
    one_error(run(img, "--out", tmp_path / "x.csv"), "field.png", "320 x 320 px", "more than the 10000 px")
    assert not (tmp_path / "x.csv").exists()


def test_sixteen_bit_and_rgb_images_are_read_as_grey_and_give_the_same_craters(tmp_path):
    grey = crater_image()
    base = run(write_image(tmp_path / "grey.png", grey))
    r16 = run(write_image(tmp_path / "w16.png", grey.astype(np.uint16) * 257))
    rgb_path = write_image(tmp_path / "rgb.png", cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    rgb = run(rgb_path)
    assert base.exit_code == r16.exit_code == rgb.exit_code == 0, (r16.output, rgb.output)
    assert r16.stdout == base.stdout and rgb.stdout == base.stdout and base.stdout
    assert r16.stderr == ""
    assert rgb.stderr.strip() == f"note: {rgb_path}: 3 channels (RGB), read as grey: the mean of R, G, B"
    r = run(tmp_path, "--out", tmp_path / "out")  # in a folder run the note is in the summary too
    assert r.exit_code == 0, r.output
    notes = {d["image"]: d.get("note") for d in json.loads((tmp_path / "out" / SUMMARY_NAME).read_text())["results"]}
    note = f"{rgb_path}: 3 channels (RGB), read as grey: the mean of R, G, B"
    assert notes == {"grey.png": None, "rgb.png": note, "w16.png": None}


def test_a_rendered_frame_is_read_by_its_radiance_channel(tmp_path):
    """An EXR of the renderer (I/F and other channels) gives the craters of its I/F channel."""
    import OpenImageIO as oiio

    path = tmp_path / "frame_0000.exr"
    i_f = crater_image().astype(np.float32) / 255.0 * 0.05  # I/F of a few per cent
    depth = np.full(i_f.shape, 5e4, np.float32)  # a depth channel would mix in as "colour"
    out = oiio.ImageOutput.create(str(path))
    spec = oiio.ImageSpec(i_f.shape[1], i_f.shape[0], 2, oiio.FLOAT)
    spec.channelnames = ("depth", "IF")
    assert out.open(str(path), spec) and out.write_image(np.stack([depth, i_f], -1))
    out.close()
    r = run(path)
    assert r.exit_code == 0, r.output
    assert all(m is not None for m in matched([json.loads(line) for line in r.stdout.splitlines()]))


def test_a_corrupt_model_file_is_one_line_before_any_output(tmp_path):
    img = write_image(tmp_path / "field.png")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"\x00" * 64)
    one_error(run(img, "--out", tmp_path / "x.geojson", "--detector", "learned", f"nav.detector.model={bad}"), bad)
    assert not (tmp_path / "x.geojson").exists()
    one_error(run(tmp_path, "--out", tmp_path / "o", f"nav.detector.model={bad}"), bad)
    assert not (tmp_path / "o").exists()
    # the same for the FCOS detector: checked once, before the folder's first image
    one_error(run(tmp_path, "--out", tmp_path / "o", "--detector", "fcos", f"nav.detector.model={bad}"), bad)
    assert not (tmp_path / "o").exists()
    # and a trained detector's model is an input no output may replace, whichever detector it is
    from crater_synth.navigation.detect_cmd import Detector, model_inputs
    from crater_synth.navigation.detectors.fcos import FcosSettings
    from crater_synth.navigation.detectors.learned import DEFAULT_MODEL, LearnedSettings

    assert model_inputs(Detector("fcos", FcosSettings(model=str(bad)), None)) == [bad]
    assert model_inputs(Detector("learned-detect", LearnedSettings(), None)) == [DEFAULT_MODEL]
    many = LearnedSettings(ensemble=(str(tmp_path / "e.pt"),), verifier=str(tmp_path / "v.pt"))
    assert model_inputs(Detector("learned-detect", many, None)) == [DEFAULT_MODEL, tmp_path / "e.pt", tmp_path / "v.pt"]
    # an ensemble's bad model file is refused up front too, by name
    one_error(run(img, "--detector", "learned", f"nav.detector.ensemble=[{bad}]"), bad)


@pytest.mark.parametrize(
    "args, words",
    [
        (["--png"], ["--png", "--out"]),
        (["--light-azimuth", "30"], ["--light-azimuth", "learned-detect uses no light"]),
        (["--light-azimuth", "nan", "--detector", "template"], ["--light-azimuth", "finite"]),
        (["--pixel-m", "-3"], ["--pixel-m"]),
        (["--detector", "template", "nav/detector=classical"], ["give one of them"]),
        (["nav/detector=appearance"], ["landmark map"]),
        (["nav/preset=synthetic"], ["nav/preset"]),
        (["--out", "x.txt"], ["--out", ".geojson or .csv"]),
    ],
)
def test_contradictory_options_are_refused_in_one_line(tmp_path, args, words):
    img = write_image(tmp_path / "field.png")
    one_error(run(img, *args), *words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["field.png"]


def test_an_output_that_would_overwrite_an_input_is_refused(tmp_path):
    img = write_image(tmp_path / "field.png", georef=GEOREF)
    before = img.read_bytes()
    one_error(run(img, "--out", img), "--out")
    # field.geojson's PNG would be field.png, the image itself
    one_error(run(img, "--out", tmp_path / "field.geojson", "--png"), "would overwrite the input", img)
    assert img.read_bytes() == before and not (tmp_path / "field.geojson").exists()
    one_error(run(tmp_path, "--out", tmp_path), "is the input folder")


# ------------------------------------------------------------------------------------------------
# A folder in one run
# ------------------------------------------------------------------------------------------------
def test_a_folder_in_one_run_survives_its_bad_files(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    write_image(src / "a.png", georef=GEOREF)
    write_image(src / "b.png")
    bad_image(src, "corrupt")
    (src / "good.png").unlink()  # corrupt.png's source
    bad_image(src, "constant")
    (src / "notes.txt").write_text("not an image")
    (src / "sub.png").mkdir()  # an entry with an image's name that is no file
    out = tmp_path / "out"
    r = run(src, "--out", out, "--png")
    assert r.exit_code == 1, r.output  # some failed
    errors = r.stderr.strip().splitlines()
    assert len(errors) == 3 and "constant.png" in errors[0] and "corrupt.png" in errors[1], errors
    assert errors[2] == f"error: {src / 'sub.png'}: not a file"
    assert all(e.startswith("error: ") for e in errors)
    line = json.loads(r.stdout)
    assert (line["images"], line["failed"]) == (5, 3)
    summary = json.loads((out / SUMMARY_NAME).read_text())
    assert [f["image"] for f in summary["failed"]] == ["constant.png", "corrupt.png", "sub.png"]
    assert [d["image"] for d in summary["results"]] == ["a.png", "b.png"] and summary["not_images"] == ["notes.txt"]
    written = sorted(p.name for p in out.iterdir())
    want = [f"{n}{s}" for n in ("a.png", "b.png") for s in (LIST_SUFFIX, PNG_SUFFIX)] + [TABLE_NAME, SUMMARY_NAME]
    assert written == sorted([*want, MARKERS["detections"], LOCK_NAME])
    a = json.loads((out / f"a.png{LIST_SUFFIX}").read_text())
    assert all(m is not None for m in matched([f["properties"] for f in a["features"]]))
    assert all("lat" in f["properties"] for f in a["features"])
    b = json.loads((out / f"b.png{LIST_SUFFIX}").read_text())
    assert all(f["geometry"] is None for f in b["features"])  # no georeference: pixels only
    rows = list(csv.DictReader((out / TABLE_NAME).open()))
    assert len(rows) == len(a["features"]) + len(b["features"])
    # Run again without b.png: its outputs (the run's own) go; a corrupt image fixed now succeeds.
    (src / "b.png").unlink()
    (src / "corrupt.png").unlink()
    (src / "constant.png").unlink()
    (src / "sub.png").rmdir()
    r = run(src, "--out", out)
    assert r.exit_code == 0, r.output
    written = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
    assert written == sorted([f"a.png{LIST_SUFFIX}", TABLE_NAME, SUMMARY_NAME])


def test_the_output_folder_refuses_foreign_files_another_kind_and_another_input(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    write_image(src / "a.png")
    users = tmp_path / "users"
    users.mkdir()
    (users / "thesis.tex").write_text("mine")
    one_error(run(src, "--out", users), users / "thesis.tex", "did not write")
    assert sorted(p.name for p in users.iterdir()) == ["thesis.tex"]  # no marker, no lock left
    export = tmp_path / "export"
    export.mkdir()
    (export / MARKERS["export"]).write_text("{}")
    one_error(run(src, "--out", export), "export")
    out = tmp_path / "out"
    assert run(src, "--out", out).exit_code == 0
    other = tmp_path / "other"
    other.mkdir()
    write_image(other / "c.png")
    one_error(run(other, "--out", out), "give another folder")
    assert not (out / f"c.png{LIST_SUFFIX}").exists()


def test_a_folder_needs_an_output_folder(tmp_path):
    write_image(tmp_path / "a.png")
    one_error(run(tmp_path), "give --out FOLDER")
    one_error(run(tmp_path, "--out", tmp_path / "x.geojson"), "output folder")
    empty = tmp_path / "empty"
    empty.mkdir()
    one_error(run(empty, "--out", tmp_path / "o"), "holds no image")


# ------------------------------------------------------------------------------------------------
# bench --part detect
# ------------------------------------------------------------------------------------------------
def test_detect_bench_sets_one_folder_process_against_one_process_per_image(monkeypatch, tmp_path):
    """Seconds per frame from the command's own summary, wall and RSS from the child; the folder's one
    process against the sum of one process per image (crater_synth.bench.detect)."""
    from crater_synth.bench import detect as bd

    monkeypatch.setattr(bd, "FRAMES", {"64x96": (64, 96)})
    monkeypatch.setattr(bd, "FOLDER_FRAMES", 3)
    monkeypatch.setattr(bd, "CELL_PX", 32)
    calls = []

    def fake_run(log, source, flag, out, *detector):
        calls.append((source.name, *detector))
        if source.is_dir():  # the folder run writes its summary
            out.mkdir()
            (out / SUMMARY_NAME).write_text(json.dumps({"seconds": 1.5}))
            return {"wall_s": 6.0, "peak_rss_mb": 700.0, "last": "{}"}
        assert cv2.imread(str(source), cv2.IMREAD_UNCHANGED).dtype == np.uint8
        return {"wall_s": 4.0, "peak_rss_mb": 500.0, "last": json.dumps({"seconds": 0.5, "craters": 6})}

    monkeypatch.setattr(bd, "run_detect", fake_run)
    r = bd.bench_detect(tmp_path)
    assert r["frames"]["64x96"] == {"seconds_per_frame": 0.5, "wall_s": 4.0, "peak_rss_mb": 500.0, "craters": 6}
    f = r["folder"]
    assert (f["one_process_s"], f["process_per_image_s"], f["speedup"]) == (6.0, 12.0, 2.0)
    assert f["inside_per_image_s"] == 0.5 and f["one_process_per_image_s"] == 2.0
    assert r["other_detectors"] == dict.fromkeys(bd.OTHER_DETECTORS, 0.5)
    others = [("frame_64x96.png", "--detector", name) for name in bd.OTHER_DETECTORS]
    views = [("frame_64x96.png", *bd.VIEWS)]
    assert r["views"] == {"overrides": list(bd.VIEWS), "seconds_per_frame": {"64x96": 0.5}}
    assert calls == [("frame_64x96.png",), *others, *views, ("folder",), *[(f"frame_{k}.png",) for k in range(3)]]
    # The synthetic frames are seeded: one crater per cell, the same every run.
    a, b = bd.crater_frame(64, 96, 1), bd.crater_frame(64, 96, 1)
    assert np.array_equal(a, b) and a.shape == (64, 96) and (a < 20).sum() > 6  # six shadows


def test_a_second_writer_of_the_output_folder_is_refused_naming_the_first(tmp_path):
    from crater_synth.outfolder import OutFolder

    src = tmp_path / "in"
    src.mkdir()
    write_image(src / "a.png")
    out = tmp_path / "out"
    with OutFolder(out, "detections", subject=str(src.resolve())):  # another detect run, still writing
        one_error(run(src, "--out", out), "being written by another crater-synth process", f"pid {os.getpid()}")
        assert not (out / f"a.png{LIST_SUFFIX}").exists()
    assert run(src, "--out", out).exit_code == 0  # once it is done
