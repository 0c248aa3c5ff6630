"""Detection frames of procedural crater fields (crater_synth/dataset/detection.py, docs/procedural.md).

Fast tier: the labels' projection with a synthetic camera (no Blender), the conditions' ranges, the seeds.
Integration: tiny frames rendered through the workers, their labels checked against the rendered depth.
"""

from __future__ import annotations

import io
import json
import math

import numpy as np
import pytest

import crater_core.procedural as P
from crater_core import exr, geometry, schema
from crater_core.detection_labels import DETECTION_LABEL_FIELDS, label_file_name, with_labels
from crater_core.rim_fractions import hidden_rim_fraction, rim_circle
from crater_core.settings import replace
from crater_synth.config import load_settings
from crater_synth.dataset import detection as D
from crater_synth.dataset import detection_run as R
from crater_synth.dataset.verify import verify_dataset
from crater_synth.errors import ConfigError, UserError
from crater_synth.terrain.procedural_patch import grid_centre_m, grid_to_enu, height_at, patch_arrays

DET = load_settings(D.detection_overrides([])).detection  # configs/detection/default.yaml

SPACING = 20.0
SIZE = 257  # odd: the grid's centre is a vertex


def _one_crater(diameter_m: float = 1000.0, size: int = SIZE, spacing_m: float = SPACING) -> P.ProceduralTerrain:
    """A fresh crater at the centre of flat ground."""
    c = 0.5 * (size - 1) * spacing_m
    return P.build(np.zeros((size, size)), spacing_m, P.crater_table([diameter_m], [c], [c], [0.0], 0.0))


def _looking_at_crater(terrain, off_nadir_deg: float, azimuth_deg: float, gsd: float, width: int, fov: float = 30.0):
    crater = terrain.craters[0]
    target, _ = grid_to_enu(terrain, crater.x_m, crater.y_m, 0.0, D.PATCH_LAT, D.PATCH_LON)
    focal = 0.5 * width / math.tan(math.radians(fov) / 2.0)
    return geometry.look_at_camera(90.0 - off_nadir_deg, azimuth_deg, gsd * focal, fov, target=target)


def test_nadir_label_is_the_rim_circle_at_the_ground_sample():
    """Straight down on a fresh crater: the label is centred on the image centre and a = b = D/2 / gsd
    (the rim sits a rim height above the target: the ground sample there is range - h over f)."""
    terrain = _one_crater()
    crater = terrain.craters[0]
    w, gsd = 128, 25.0
    cam = _looking_at_crater(terrain, 0.0, 0.0, gsd, w)
    (label,) = D.frame_labels(terrain, cam, w)
    ell = label["ellipse"]
    assert ell["cu"] == pytest.approx(w / 2, abs=0.01) and ell["cv"] == pytest.approx(w / 2, abs=0.01)
    rim_h = float(height_at(terrain, crater.x_m + crater.diameter_m / 2, crater.y_m))
    assert rim_h == pytest.approx(crater.rim_height_m, rel=0.05) and rim_h > 10.0
    expected = 0.5 * crater.diameter_m / ((gsd * cam.focal_px(w) - rim_h) / cam.focal_px(w))
    assert ell["a"] == pytest.approx(expected, rel=2e-3) and ell["b"] == pytest.approx(expected, rel=2e-3)
    assert label["emission_deg"] < 0.05 and label["source"] == "procedural" and label["class"] == "simple"
    assert label["diameter_m"] == pytest.approx(1000.0) and label["rim_inside"]
    assert "lit_rim_fraction" not in label and "occluded" not in label  # no channels given


@pytest.mark.parametrize("off_nadir", [20.0, 35.0, 45.0])
def test_oblique_label_shrinks_across_the_view_by_the_cosine(off_nadir):
    """Seen off nadir, a rim near the image centre is an ellipse with b/a = cos(emission angle), its minor
    axis along the view's azimuth (image up is the ground track away from the camera)."""
    terrain = _one_crater()
    w = 128
    cam = _looking_at_crater(terrain, off_nadir, 30.0, 25.0, w)
    (label,) = D.frame_labels(terrain, cam, w)
    ell = label["ellipse"]
    assert label["emission_deg"] == pytest.approx(off_nadir, abs=0.3)  # the patch centre's normal is vertical
    assert ell["b"] / ell["a"] == pytest.approx(math.cos(math.radians(off_nadir)), rel=0.01)
    assert abs(math.sin(ell["angle_rad"])) < 0.02  # the major axis along image u: across the view


def test_labels_keep_only_craters_in_view_spanning_three_pixels():
    """A crater whose rim spans fewer than 3 px is not labelled; one whose centre is out of the frame neither."""
    terrain = _one_crater(diameter_m=300.0)
    w = 64
    focal = 0.5 * w / math.tan(math.radians(15.0))
    # 300 m spans 2.9 px at 103 m/px, 3.06 px at 98 m/px
    for gsd, n in ((103.0, 0), (98.0, 1)):
        assert len(D.frame_labels(terrain, _looking_at_crater(terrain, 0.0, 0.0, gsd, w), w)) == n
    far = geometry.look_at_camera(90.0, 0.0, 20.0 * focal, 30.0, target=(2000.0, 0.0, 0.0))
    assert D.frame_labels(terrain, far, w) == []


def test_lit_and_hidden_rim_fractions_from_the_channels():
    """The rim's lit fraction is read from the lit channel; relief nearer than the rim by more than the
    margin over more than half the rim flags the label occluded."""
    terrain = _one_crater()
    w = 96
    cam = _looking_at_crater(terrain, 0.0, 0.0, 25.0, w)
    lit = np.zeros((w, w), np.float32)
    lit[:, : w // 2] = 1.0  # the left half lit: half the rim
    far = np.full((w, w), 1e9, np.float32)
    (label,) = D.frame_labels(terrain, cam, w, lit, far)
    assert label["lit_rim_fraction"] == pytest.approx(0.5, abs=0.03)
    assert label["occluded_rim_fraction"] == 0.0 and label["occluded"] is False
    (label,) = D.frame_labels(terrain, cam, w, lit, np.full((w, w), 10.0, np.float32))
    assert label["occluded_rim_fraction"] == 1.0 and label["occluded"] is True


def test_hidden_rim_fraction_uses_the_margin_given():
    theta = np.arange(90) * 2 * np.pi / 90
    rim_uv = np.stack([20 + 10 * np.cos(theta), 20 + 10 * np.sin(theta)], 1)
    depth = np.full((40, 40), 1000.0)
    assert hidden_rim_fraction(depth, rim_uv, np.full(90, 1050.0), 100.0) == 0.0
    assert hidden_rim_fraction(depth, rim_uv, np.full(90, 1050.0), 10.0) == 1.0
    pts = rim_circle([0.0, 0.0, 5.0], [0.0, 0.0, 1.0], 3.0)
    assert np.allclose(np.hypot(pts[:, 0], pts[:, 1]), 3.0) and np.allclose(pts[:, 2], 5.0)


def test_conditions_stay_in_their_ranges_and_the_footprint_in_the_field():
    """Sun 0.5-60 deg at any azimuth, nadir or up to 45 deg off, ground sample never finer than the grid nor
    coarser than twice it; every corner ray of the frame meets the ground inside the field."""
    terrain = P.generate(P.ProceduralSettings(size_px=768, spacing_m=50.0, seed=1, density_scale=0.1))
    half = grid_centre_m(terrain)
    w = 256
    nadir = 0
    for i in range(60):
        _, rng, _ = D.frame_seeds(7, i)
        c = D.draw_conditions(rng, terrain, DET)
        assert 0.5 <= c["sun_elevation_deg"] <= 60.0 and 0.0 <= c["sun_azimuth_deg"] < 360.0
        assert 0.0 <= c["off_nadir_deg"] <= 45.0
        nadir += c["off_nadir_deg"] == 0.0
        assert 50.0 <= c["ground_sample_m"] <= 100.0
        cam = c["camera"]
        corners = np.array([[0, 0], [w, 0], [0, w], [w, w]], float)
        rays = geometry.back_project_pixels(corners, np.ones(4), cam, w) - cam.position
        ground = cam.position + rays * (-(cam.position[2] - c["target_enu_m"][2]) / rays[:, 2])[:, None]
        assert np.abs(ground[:, :2]).max() < half
    assert 5 <= nadir <= 30  # a quarter of the frames look straight down
    small = P.generate(P.ProceduralSettings(size_px=128, spacing_m=50.0, seed=1))
    with pytest.raises(D.UserError, match="raise procedural.size_px"):
        D.draw_conditions(np.random.default_rng(0), small, DET)
    D.check_field_fits(P.ProceduralSettings(size_px=768), DET)  # the command's default field
    with pytest.raises(D.UserError, match=r"procedural.size_px=600: .* at least 66\d px"):
        D.check_field_fits(P.ProceduralSettings(size_px=600), DET)
    D.check_field_fits(P.ProceduralSettings(size_px=600), replace(DET, nadir_share=1.0))  # nadir only: smaller


def _grouped_conditions(grouping, terrain, n: int, seed: int = 7) -> list[dict]:
    det = replace(
        DET, width_px=64, views_per_field=grouping[0], suns_per_view=grouping[1], azimuths_per_field=grouping[2]
    )
    az = D.sun_azimuths(det, seed, 0)
    return [D.draw_conditions(D.frame_seeds(seed, i)[1], terrain, det, az, D.view_rng(det, seed, i)) for i in range(n)]


def test_frames_of_a_view_share_its_camera_and_a_field_its_azimuths():
    """--suns-per-view: consecutive frames share the first one's camera exactly (one G-buffer), each under
    its own Sun; --azimuths-per-field: every Sun azimuth is one of the field's evenly spaced set. A view's
    first frame is the frame it would be without grouping."""
    terrain = P.generate(P.ProceduralSettings(size_px=768, spacing_m=50.0, seed=2))
    plain = _grouped_conditions((1, 1, 0), terrain, 8)
    views = _grouped_conditions((8, 4, 0), terrain, 8)
    both = _grouped_conditions((8, 4, 3), terrain, 8)
    for i, c in enumerate(views):
        first = views[i - i % 4]
        assert np.array_equal(c["camera"].position, first["camera"].position)
        assert np.array_equal(c["camera"].rotation, first["camera"].rotation)
        assert c["sun_elevation_deg"] == plain[i]["sun_elevation_deg"]
        assert c["sun_azimuth_deg"] == plain[i]["sun_azimuth_deg"]

    def same(a, b):
        return np.array_equal(a["camera"].position, b["camera"].position) and {
            k: v for k, v in a.items() if k != "camera"
        } == {k: v for k, v in b.items() if k != "camera"}

    assert same(views[0], plain[0]) and same(views[4], plain[4]) and not same(views[0], views[4])
    assert len({c["sun_elevation_deg"] for c in views}) == 8
    az = D.field_azimuths(7, 0, 3)
    assert np.allclose(np.diff(np.sort(az)), 120.0) and set(c["sun_azimuth_deg"] for c in both) <= set(az)
    assert all(np.array_equal(a["camera"].position, b["camera"].position) for a, b in zip(both, views))
    assert not np.allclose(D.field_azimuths(7, 0, 3), D.field_azimuths(7, 1, 3))


@pytest.mark.parametrize(
    "override, key",
    [
        ("detection.views_per_field=0", "views_per_field"),
        ("detection.suns_per_view=0", "suns_per_view"),
        ("detection.azimuths_per_field=-1", "azimuths_per_field"),
        ("detection.views_per_field=6", "views_per_field"),  # not a multiple of suns_per_view=4
        ("detection.off_nadir_deg=[50,40]", "off_nadir_deg"),
        ("detection.spacing_m=[0,10]", "spacing_m"),
        ("detection.width_px=8", "width_px"),
    ],
)
def test_a_detection_recipe_that_cannot_be_is_one_error(override, key):
    with pytest.raises(ConfigError, match=f"detection.{key}"):
        load_settings(D.detection_overrides([override]))


def test_field_spacing_is_drawn_per_field_in_its_range():
    """detection.spacing_m=[lo, hi]: each field its own grid spacing, log-uniform, from the field's stream."""
    det = replace(DET, spacing_m=(20.0, 1000.0))
    proc = P.ProceduralSettings()
    got = [D.field_spacing(det, proc, 3, f) for f in range(200)]
    assert all(20.0 <= g <= 1000.0 for g in got) and got == [D.field_spacing(det, proc, 3, f) for f in range(200)]
    assert 0.4 < np.mean(np.log(got) < np.log(np.sqrt(20.0 * 1000.0))) < 0.6  # log-uniform: half below the middle
    assert D.field_spacing(DET, proc, 3, 0) == proc.spacing_m


def test_frame_seeds_depend_on_the_run_seed_and_the_index_only():
    a, ra, sa = D.frame_seeds(3, 5)
    b, rb, sb = D.frame_seeds(3, 5)
    assert (a, sa) == (b, sb) and ra.random() == rb.random()
    assert len({D.frame_seeds(3, i)[0] for i in range(50)} | {D.frame_seeds(4, 0)[0]}) == 51


def test_command_defaults_yield_to_the_users_settings():
    assert D.detection_overrides([]) == ["procedural=detection", "detection=default", "render.gbuffer_samples=1"]
    assert D.detection_overrides(["procedural=default", "detection=default", "render.samples=2"]) == [
        "procedural=default",
        "detection=default",
        "render.samples=2",
    ]
    settings = load_settings(D.detection_overrides(["procedural.size_px=400"]))
    assert settings.procedural.size_px == 400 and settings.render.gbuffer_samples == 1


def test_patch_vertices_and_labels_share_one_mapping():
    """The patch's vertex (i, j) is grid point (x_j, y_i) at its height, through the labels' own mapping."""
    terrain = _one_crater(size=65)
    arrays = patch_arrays(terrain, D.PATCH_LAT, D.PATCH_LON)
    xyz, _ = grid_to_enu(terrain, 40 * SPACING, 12 * SPACING, terrain.height[12, 40], D.PATCH_LAT, D.PATCH_LON)
    assert np.allclose(arrays["near_xyz"][12, 40], xyz, atol=0.01)
    assert np.allclose(arrays["near_xyz"][32, 32, :2], 0.0, atol=1e-6)


# --------------------------------------------------------------------------------------------
# Rendered (Blender)
# --------------------------------------------------------------------------------------------
def _render(tmp_path, name: str, nadir_share: float, off_range=(0.0, 45.0), frames=1, views=1):
    overrides = ["procedural.size_px=384", "procedural.spacing_m=40", "render.workers=1", "seed=3"]
    overrides += [f"detection.nadir_share={nadir_share}", f"detection.off_nadir_deg=[{off_range[0]},{off_range[1]}]"]
    overrides += ["detection.width_px=96", f"detection.views_per_field={views}", "detection.suns_per_view=1"]
    settings = load_settings(D.detection_overrides([*overrides, "detection.azimuths_per_field=0"]))
    out = tmp_path / name
    summary = R.render_detection_frames(settings, out, frames)
    rows = list(D.manifest_rows(out).values())
    assert summary["frames"] == len(rows) == frames and summary["fields"] == -(-frames // views)
    names = sorted(p.name for p in out.iterdir() if p.name[0] != ".")
    frame_names = [D.frame_rel_path(i) for i in range(frames)]
    assert names == sorted(frame_names + [label_file_name(n) for n in frame_names]) + ["manifest.jsonl"]
    raw = [v[2] for v in D.scan_manifest(out)[0].values()]
    for r, r_raw in zip(rows, raw):
        assert schema.sha256_file(out / r["rel_path"]) == r["sha256"]
        ref = r_raw["labels"]  # the row references its label file, whose labels read_manifest put inline
        assert ref["file"] == label_file_name(r["rel_path"]) and ref["count"] == len(r["labels"])
        assert schema.sha256_file(out / ref["file"]) == ref["sha256"]
    assert not (out / D.PATCH_DIR).exists()
    return out, rows[0] if frames == 1 else rows


def _rim_back_projection_error(out, row) -> float:
    """Median over the unoccluded labels of |horizontal distance from the crater's axis - D/2| (in ground
    samples) of the rendered surface points under the label's ellipse: where the rendered frame has the rim."""
    ch, _ = exr.read_exr(out / row["rel_path"])
    cam = geometry.CameraPose(
        np.array(row["camera_enu"]["position_m"]), np.array(row["camera_enu"]["rotation"]), row["camera_enu"]["fov_deg"]
    )
    w = row["camera_enu"]["width_px"]
    errs = []
    for lb in row["labels"]:
        ell = lb["ellipse"]
        if lb["occluded"] or not lb["rim_inside"] or ell["a"] < 3.0:
            continue
        uv = geometry.Ellipse(ell["cu"], ell["cv"], ell["a"], ell["b"], ell["angle_rad"]).points(64)
        px = np.clip(np.floor(uv).astype(int), 0, w - 1)
        pts = geometry.back_project_pixels(uv, ch["depth"][px[:, 1], px[:, 0]], cam, w)
        centre, up = grid_to_enu(_Grid(row), lb["x_m"], lb["y_m"], 0.0, D.PATCH_LAT, D.PATCH_LON)
        rel = pts - centre
        horiz = np.linalg.norm(rel - (rel @ up)[:, None] * up, axis=1)
        errs.append(np.median(np.abs(horiz - lb["diameter_m"] / 2)) / row["ground_sample_m"])
    assert len(errs) >= 3, "too few checkable labels"
    return float(np.median(errs))


class _Grid:
    """The grid geometry a row records (what grid_to_enu reads of a terrain)."""

    def __init__(self, row):
        n = row["terrain"]["size_px"]
        self.height = np.zeros((n, n))
        self.spacing_m = row["terrain"]["spacing_m"]


@pytest.mark.integration
def test_rendered_frames_have_their_rims_where_the_labels_say_and_are_deterministic(tmp_path):
    """A nadir and an oblique frame (96 px): the rendered depth puts the surface under each unoccluded
    label's ellipse at D/2 from the crater's axis (to half a ground sample, median); near the image centre
    b/a = cos(view angle); the same seed renders the same bytes and labels."""
    out, row = _render(tmp_path, "nadir", 1.0)
    assert row["view"]["off_nadir_deg"] == 0.0 and row["mode"] == "fast" and row["labels"]
    report = verify_dataset(out, jobs=1)  # the one verification reads detection folders too
    assert report["ok"] and report["kind"] == "detection", report["faults"]
    assert _rim_back_projection_error(out, row) < 0.5
    for lb in row["labels"]:
        assert lb["ellipse"]["b"] / lb["ellipse"]["a"] > 0.97
        gsd_here = row["ground_sample_m"]  # nadir over nearly flat ground: the ground sample everywhere
        assert lb["ellipse"]["a"] == pytest.approx(lb["diameter_m"] / 2 / gsd_here, rel=0.08)
    out2, row2 = _render(tmp_path, "oblique", 0.0, (30.0, 40.0))
    view = row2["view"]["off_nadir_deg"]
    assert 30.0 <= view <= 40.0
    assert _rim_back_projection_error(out2, row2) < 0.5
    # within 12 px (3.7 deg) of the boresight: the view angle is the crater's emission angle to ~4 deg
    central = [lb for lb in row2["labels"] if np.hypot(lb["centre_px"][0] - 48, lb["centre_px"][1] - 48) < 12]
    assert central
    for lb in central:
        assert lb["ellipse"]["b"] / lb["ellipse"]["a"] == pytest.approx(math.cos(math.radians(view)), abs=0.03)
    # Again, with a second view of the same field: frame 0 is the same pixels and labels (frame i's draws
    # depend on the seed and i only; its header and row record the other grouping); frame 1 views the same
    # field under its own Sun and view.
    out3, (row3, row31) = _render(tmp_path, "again", 0.0, (30.0, 40.0), frames=2, views=2)
    ch3, ch2 = exr.read_exr(out3 / "frame_000000.exr")[0], exr.read_exr(out2 / "frame_000000.exr")[0]
    assert all(np.array_equal(ch3[c], ch2[c]) for c in schema.EXR_CHANNELS)
    assert row3["grouping"]["views_per_field"] == 2 and row2["grouping"]["views_per_field"] == 1
    skip = {"render_seconds", "sha256", "grouping"}
    assert {k: v for k, v in row3.items() if k not in skip} == {k: v for k, v in row2.items() if k not in skip}
    again = _render(tmp_path, "oblique", 0.0, (30.0, 40.0))[1]  # resumed: kept, not rendered
    assert again == row2
    assert row31["terrain"] == row3["terrain"] and row31["sun_enu"] != row3["sun_enu"] and row31["labels"]
    assert json.loads(json.dumps(row2["labels"][0]))["source"] == "procedural"


def _fake_frames(tmp_path, n: int = 2):
    """``n`` detection frames as the command writes them, the EXRs made up (no Blender): rows and label files
    by :func:`detection.frame_row` over a generated field and drawn conditions; returned with their labels."""
    terrain = P.generate(P.ProceduralSettings(size_px=768, spacing_m=50.0, seed=2))
    out = tmp_path / "frames"
    out.mkdir()
    rows = []
    for i in range(n):
        terrain_seed, rng, _ = D.frame_seeds(0, i)
        cond = D.draw_conditions(rng, terrain, replace(DET, width_px=64))
        rel = D.frame_rel_path(i)
        chans = {c: np.full((64, 64), 0.5 + i, np.float32) for c in schema.EXR_CHANNELS}
        chans["depth"] = np.full((64, 64), 1e9, np.float32)
        exr.write_exr(out / rel, chans, {"crater_synth:mode": "fast"})
        res = {
            "index": i,
            "rel_path": rel,
            "sha256": schema.sha256_file(out / rel),
            "mode": "fast",
            "seconds": 0.1,
            "lit_fraction": 0.5,
            "mean_if": 0.5,
        }
        frame = {"terrain": terrain, "cond": cond, "field": i, "terrain_seed": terrain_seed, "terrain_id": "t"}
        frame |= {"view_first": i, "grouping": D.grouping(DET)}
        rows.append(D.frame_row(frame, res, out))
    (out / schema.MANIFEST_NAME).write_text("".join(schema.dumps_row(r) + "\n" for r in rows))
    return out, [with_labels(out, r) for r in rows]  # each row as read_manifest gives it: its labels inline


def test_labels_carry_the_fields_the_export_types(tmp_path):
    _, rows = _fake_frames(tmp_path, 1)
    assert rows[0]["labels"]
    for lb in rows[0]["labels"]:
        assert list(lb) == [name for name, _ in DETECTION_LABEL_FIELDS]


def test_detection_frames_export_to_parquet_with_typed_labels(tmp_path):
    """`crater-synth export` detects the kind and writes every label as a typed struct, images bit for bit."""
    import pyarrow.parquet as pq

    from crater_synth.dataset import export as ex

    frames, rows = _fake_frames(tmp_path)
    assert ex.detect_kind(frames) == "detection"
    index = ex.export_dataset(frames, tmp_path / "pq", "parquet", channels=["IF", "lit"], shard_rows=1)
    assert index["record_kind"] == "detection" and index["rows"] == 2
    table = pq.read_table(sorted((tmp_path / "pq").glob("*.parquet"))[1])
    rec = table.to_pylist()[0]
    assert rec["key"] == "frame_000001" and rec["frame_index"] == 1 and rec["terrain_field"] == 1
    assert table.schema.field("labels").type.value_type.field("ellipse").type.field("a").type.bit_width == 64
    assert len(rec["labels"]) == len(rows[1]["labels"]) > 0
    for got, want in zip(rec["labels"], rows[1]["labels"]):
        assert got == want
    assert json.loads(rec["labels_json"]) == rows[1]
    img = np.load(io.BytesIO(rec[f"{ex.column_name('IF')}_npy"]))
    assert np.array_equal(img, exr.read_channel(frames / rows[1]["rel_path"], "IF"))


SMALL = ("procedural.size_px=384", "procedural.spacing_m=40")


def _refusal(out, *overrides) -> str:
    settings = load_settings(D.detection_overrides([*SMALL, "detection.width_px=96", *overrides]))
    with pytest.raises(UserError) as exc:
        R.render_detection_frames(settings, out, 1)
    return str(exc.value)


def test_verify_and_export_check_each_frames_label_file(tmp_path):
    """A label file changed after a passing verify is one fault for verify and refused by export (the
    recorded pass no longer covers it); a label file no row names is an orphan."""
    from crater_synth.dataset import export as ex

    frames, _ = _fake_frames(tmp_path)
    report = verify_dataset(frames, decode=False, jobs=1)
    assert report["ok"] and report["orphans"] == [], report["faults"]
    (frames / "frame_000001.labels.npz").write_bytes(b"x")
    (frames / "frame_000009.labels.npz").write_bytes(b"y")
    report = verify_dataset(frames, decode=False, jobs=1)
    assert not report["ok"] and len(report["faults"]) == 1 and "frame_000001.labels.npz" in report["faults"][0]
    assert report["orphans"] == [str(frames / "frame_000009.labels.npz")]
    with pytest.raises(ex.ExportError, match="frame_000001.labels.npz"):
        ex.export_dataset(frames, tmp_path / "pq", "parquet", channels=["IF"], shard_rows=1)
    assert not (tmp_path / "pq" / ex.INDEX_FILE).exists()  # no export.json: not a complete export


def test_detection_folder_refuses_a_file_it_did_not_write_and_another_kind(tmp_path):
    """The output-folder contract: a user's file (even one named like a frame) is refused and left alone;
    a folder of another kind is refused; nothing is written either way."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "frame_000000.exr").write_bytes(b"my own file")
    assert "frame_000000.exr" in _refusal(out) and (out / "frame_000000.exr").read_bytes() == b"my own file"
    assert sorted(p.name for p in out.iterdir()) == ["frame_000000.exr"]
    nav = tmp_path / "nav"
    nav.mkdir()
    (nav / ".crater-synth-navframes").write_text("{}")
    assert "navigation frames" in _refusal(nav) and sorted(p.name for p in nav.iterdir()) == [".crater-synth-navframes"]


def test_detection_folder_of_another_recipe_is_refused(tmp_path):
    """Frames of two recipes never mix: a folder marked for one recipe refuses a run of another seed. The
    recipe is every setting that can change a frame (detection.* included), not where or how it runs."""
    from crater_synth.outfolder import OutFolder

    out = tmp_path / "set"
    base = [*SMALL, "detection.width_px=96"]

    def key(*more):
        return R.recipe_key(load_settings(D.detection_overrides([*base, *more])))

    OutFolder(out, R.KIND, subject=f"recipe {key()}").claim().release()
    assert f"recipe {key()}" in _refusal(out, "seed=9")
    assert key() == key("render.workers=1") == key("render.threads=3")
    others = ["seed=9", "detection.suns_per_view=2", "detection.nadir_share=0.5", "procedural.hurst=0.7"]
    assert len({key(), *(key(o) for o in others)}) == 1 + len(others)


def test_a_rerun_keeps_only_the_unchanged_frames_of_its_range(tmp_path):
    """Resumption: a frame whose row is in the manifest and whose file is unchanged since written is kept; a
    deleted or rewritten one is rendered again; rows outside the range stay."""
    from crater_synth.outfolder import OutFolder

    out = tmp_path / "set"
    settings = load_settings(D.detection_overrides([*SMALL, "detection.width_px=96"]))
    folder = OutFolder(out, R.KIND, subject=f"recipe {R.recipe_key(settings)}").claim()
    rows = {}
    for i in range(4):
        rel = D.frame_rel_path(i)
        (out / rel).write_bytes(b"frame %d" % i)
        rows[i] = {"index": i, "rel_path": rel, "labels": []}
    folder.record([*(r["rel_path"] for r in rows.values()), "manifest.jsonl"])
    folder.seal([r["rel_path"] for r in rows.values()])
    (out / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows.values()))
    folder.seal(["manifest.jsonl"])
    (out / D.frame_rel_path(1)).unlink()
    (out / D.frame_rel_path(2)).write_bytes(b"edited, longer than before")
    kept, done = R.kept_rows(folder, range(0, 3))
    folder.release()
    assert done == {0} and sorted(kept) == [0, 3]


# --------------------------------------------------------------------------------------------
# The manifest at scale: appended per chunk, compacted once (the workers faked: no Blender)
# --------------------------------------------------------------------------------------------
# 2 frames a field, 2 fields a chunk (one worker): 4 frames a chunk
TINY = (*SMALL, "detection.width_px=64", "detection.views_per_field=2", "detection.suns_per_view=1", "render.workers=1")


class _Killed(BaseException):
    """A hard kill: nothing after it runs but the finally clauses, which the tests neutralise."""


def _fake_workers(monkeypatch, fail_on_call: int | None = None) -> list:
    """``run_workers`` replaced by one that writes each planned frame as a made-up EXR (its values from the
    frame index, so two runs write the same bytes) and reports it as a worker does; the ``fail_on_call``-th
    call (a chunk) fails before rendering anything. Returns the frames of each call."""
    calls: list = []

    def run(jobs, _render, _hapke, out_dir, on_result):
        calls.append(sorted(p["item"]["index"] for j in jobs for p in j.plans))
        if len(calls) == fail_on_call:
            raise UserError("this chunk's workers failed")
        for job in jobs:
            for plan in job.plans:
                i, rel, w = plan["item"]["index"], plan["item"]["rel_path"], plan["item"]["frame_width"]
                chans = {c: np.full((w, w), 0.25 + i, np.float32) for c in schema.EXR_CHANNELS}
                chans["depth"] = np.full((w, w), 1e9, np.float32)
                exr.write_exr(out_dir / rel, chans, {"crater_synth:mode": "fast"})
                res = {"index": i, "rel_path": rel, "sha256": schema.sha256_file(out_dir / rel), "mode": "fast"}
                on_result(job, plan, res | {"seconds": 0.5, "lit_fraction": 0.5, "mean_if": 0.25})

    monkeypatch.setattr(R, "run_workers", run)
    return calls


def _tiny(tmp_path, name: str, frames: int = 8, start: int = 0) -> dict:
    return R.render_detection_frames(load_settings(D.detection_overrides(list(TINY))), tmp_path / name, frames, start)


def _same_set(a, b) -> None:
    names = sorted(p.name for p in a.iterdir() if p.name[0] != ".")
    assert names == sorted(p.name for p in b.iterdir() if p.name[0] != ".")
    for n in names:
        assert (a / n).read_bytes() == (b / n).read_bytes(), n


def test_a_stopped_run_resumes_to_the_manifest_of_an_uninterrupted_one(tmp_path, monkeypatch):
    """Stopped by an error in its second chunk, a run leaves the first chunk's frames and a compact
    manifest; the rerun keeps them, renders the rest and ends with the uninterrupted run's bytes."""
    assert _fake_workers(monkeypatch) == [] and _tiny(tmp_path, "whole")["rendered"] == 8
    calls = _fake_workers(monkeypatch, fail_on_call=2)
    with pytest.raises(UserError, match="workers failed"):
        _tiny(tmp_path, "stopped")
    assert calls == [[0, 1, 2, 3], [4, 5, 6, 7]]
    rows, compact = D.read_manifest(tmp_path / "stopped")
    assert sorted(rows) == [0, 1, 2, 3] and compact
    calls = _fake_workers(monkeypatch)
    summary = _tiny(tmp_path, "stopped")
    assert calls == [[4, 5, 6, 7]] and summary["kept"] == 4 and summary["rendered"] == 4
    _same_set(tmp_path / "whole", tmp_path / "stopped")


def test_a_hard_killed_run_leaves_a_readable_manifest_and_resumes(tmp_path, monkeypatch):
    """Killed halfway through appending the row of its second chunk's third frame (no compaction, no seal,
    no fsync): the torn line is dropped, the folder is still the writer's, the export refuses the
    uncompacted manifest in one line, and the rerun keeps a frame of that chunk whose row was written and
    whose never-sealed files hash to it (then seals them), renders the others (one whose file no longer
    hashes to its row among them) and compacts to the uninterrupted run's bytes."""
    from crater_synth.dataset import export as ex

    _fake_workers(monkeypatch)
    _tiny(tmp_path, "whole")
    real_append = R.append_rows

    def torn_append(out_dir, rows, sync=True):
        if rows and rows[0]["index"] >= 6:
            with open(out_dir / schema.MANIFEST_NAME, "a") as fh:
                fh.write(schema.dumps_row(rows[0])[:99])  # torn in its first row
            raise _Killed
        return real_append(out_dir, rows, sync)

    monkeypatch.setattr(R, "append_rows", torn_append)
    monkeypatch.setattr(R, "_write_manifest", lambda *_: None)  # a killed run compacts nothing
    monkeypatch.setattr(R, "_end_chunk", lambda *_: None)  # nor fsyncs and seals its chunk
    with pytest.raises(_Killed):
        _tiny(tmp_path, "killed")
    out = tmp_path / "killed"
    rows, compact = D.read_manifest(out)
    assert sorted(rows) == [0, 1, 2, 3, 4, 5] and not compact
    with pytest.raises(ex.ExportError, match="rerun that command"):
        ex.export_dataset(out, tmp_path / "pq", "parquet", channels=["IF"])
    monkeypatch.undo()
    (out / D.frame_rel_path(5)).write_bytes(b"not what its row hashed")  # listed, never sealed: the run's own
    calls = _fake_workers(monkeypatch)
    summary = _tiny(tmp_path, "killed")
    assert summary["rendered"] == 3 and summary["kept"] == 5 and calls == [[5, 6, 7]]
    _same_set(tmp_path / "whole", out)
    stamps = json.loads((out / ".crater-synth-detection-frames").read_text())["files"]
    assert all(stamps[n] for i in (4, 5) for n in R.frame_files(i))  # sealed: a later run need not hash them


def test_a_manifest_with_a_torn_last_line_and_a_repeated_index_reads_each_frame_once(tmp_path):
    """The last row of an index wins; a torn last line is dropped; a bad line elsewhere is one error."""
    out = tmp_path / "set"
    out.mkdir()
    rows = [{"index": i, "rel_path": D.frame_rel_path(i), "labels": [i]} for i in (0, 1, 2)]
    again = rows[1] | {"labels": ["again"]}
    lines = [schema.dumps_row(r) + "\n" for r in (*rows, again)]
    (out / schema.MANIFEST_NAME).write_text("".join(lines) + lines[0][:9])
    got, compact = D.read_manifest(out)
    assert got == {0: rows[0], 1: again, 2: rows[2]} and not compact
    assert D.manifest_rows(out) == got
    (out / schema.MANIFEST_NAME).write_text("".join(lines[:3]))
    assert D.read_manifest(out) == ({r["index"]: r for r in rows}, True)
    (out / schema.MANIFEST_NAME).write_text(lines[0] + "{not json\n" + lines[1])
    with pytest.raises(UserError, match="line 2: not a detection-frames row"):
        D.read_manifest(out)


def test_compaction_copies_each_frames_last_whole_line_in_order(tmp_path):
    """Compaction streams each kept row's line from where it lies: sorted, the last of a repeated index,
    a last line that lost its newline given one, the torn tail and rows not kept gone."""
    from crater_synth.outfolder import OutFolder

    out = tmp_path / "set"
    folder = OutFolder(out, R.KIND, subject="recipe test").claim()
    folder.record([schema.MANIFEST_NAME])
    rows = {i: {"index": i, "rel_path": D.frame_rel_path(i), "labels": [i], "mode": "fast"} for i in range(4)}
    line = {i: schema.dumps_row(r) + "\n" for i, r in rows.items()}
    again = rows[2] | {"labels": ["again"]}
    (out / schema.MANIFEST_NAME).write_text(line[3] + line[2] + line[1] + schema.dumps_row(again) + "\n" + line[0][:-1])
    refs, compact = R.manifest_refs(out)
    assert not compact and sorted(refs) == [0, 1, 2, 3] and refs[2]["labels"] == 1
    del refs[1]  # a row the run does not keep
    R._write_manifest(folder, refs)
    folder.release()
    assert (out / schema.MANIFEST_NAME).read_text() == line[0] + schema.dumps_row(again) + "\n" + line[3]
    assert R.manifest_refs(out) == (refs, True)
    assert OutFolder(out, R.KIND, subject="recipe test").check_clean().proved(schema.MANIFEST_NAME)


def test_the_command_renders_a_sharded_set_with_launcher_dask(tmp_path, monkeypatch):
    """`detection-frames ... launcher=dask` goes to the Dask path with the command's settings."""
    pytest.importorskip("distributed")
    from click.testing import CliRunner

    from crater_synth.dataset import detection_dask as DD
    from crater_synth.dataset.detection_cli import detection_frames_command

    seen = []
    monkeypatch.setattr(
        DD, "run_detection_dask", lambda s, out, n, start: seen.append((s.launcher.name, n, start)) or {}
    )
    args = ["--out", str(tmp_path / "set"), "--frames", "256", "--start", "64", "launcher=dask"]
    result = CliRunner().invoke(detection_frames_command, args)
    assert result.exit_code == 0, result.output
    assert seen == [("dask", 256, 64)]


def test_the_manifest_is_written_once_per_chunk_and_compacted_once(tmp_path, monkeypatch):
    """Each frame appends only its own row; the whole file is written once, when the run ends: the run
    writes the manifest's bytes twice in all, whatever the number of chunks (a rewrite per chunk: O(chunks x
    rows))."""
    appended, compactions = [], []
    real_append, real_write = R.append_rows, R._write_manifest

    def count_append(out_dir, rows, sync=True):
        appended.append(sum(len(schema.dumps_row(r)) + 1 for r in rows))
        return real_append(out_dir, rows, sync)

    def count_write(folder, rows):
        compactions.append(len(rows))
        real_write(folder, rows)

    monkeypatch.setattr(R, "append_rows", count_append)
    monkeypatch.setattr(R, "_write_manifest", count_write)
    calls = _fake_workers(monkeypatch)
    _tiny(tmp_path, "set", frames=16)
    size = (tmp_path / "set" / schema.MANIFEST_NAME).stat().st_size
    assert len(calls) == 4 and len(appended) == 16 and compactions == [16]
    assert sum(appended) == size and max(appended) < size / 12


# --------------------------------------------------------------------------------------------
# Sharded sets (launcher=dask): the layout and the shard tasks, in-process; the cluster: integration
# --------------------------------------------------------------------------------------------
def _items(monkeypatch) -> dict:
    """The worker item of each frame the faked workers are given (what Blender would render), by index."""
    items: dict = {}
    real = R.run_workers

    def run(jobs, *args):
        items.update({p["item"]["index"]: p["item"] for j in jobs for p in j.plans})
        real(jobs, *args)

    monkeypatch.setattr(R, "run_workers", run)
    return items


def test_a_sharded_set_holds_the_unsharded_runs_frames_and_resumes_per_shard(tmp_path, monkeypatch):
    """Two shards of 4 frames (2 fields each): shard k is an ordinary folder holding frames 4k .. 4k + 3,
    the same worker items, files and rows as one unsharded run's; a complete shard's task renders nothing,
    a damaged one's renders its missing frame; a rerun of another shard size, a shard of another recipe and
    a file the command did not write are refused before any cluster; a rerun without launcher.shards takes
    the set's own size."""
    pytest.importorskip("distributed")
    from crater_synth.dataset import detection_dask as DD

    _fake_workers(monkeypatch)
    whole_items = _items(monkeypatch)
    _tiny(tmp_path, "whole")
    dask = load_settings(D.detection_overrides([*TINY, "launcher=dask", "launcher.shards=2"]))
    out = tmp_path / "sharded"

    def tasks(settings, frames=8):
        parent, plan = DD.preflight(settings, out, frames, 0)
        parent.release()
        one = replace(settings, **{"render.workers": 1})
        return plan, [DD._render_shard(one, str(out / D.shard_name(k)), n, first) for k, first, n in plan["shards"]]

    _fake_workers(monkeypatch)
    shard_items = _items(monkeypatch)
    plan, done = tasks(dask)
    assert plan == {"per_shard": 4, "shards": [(0, 0, 4), (1, 4, 4)]} and [s["rendered"] for s in done] == [4, 4]
    assert D.shard_folders(out) == [out / "shard_00000", out / "shard_00001"]
    assert shard_items == whole_items and sorted(shard_items) == list(range(8))
    whole = D.manifest_rows(tmp_path / "whole")
    for k, shard in enumerate(D.shard_folders(out)):
        assert D.manifest_rows(shard) == {i: whole[i] for i in range(4 * k, 4 * k + 4)}
        for i in range(4 * k, 4 * k + 4):
            rel = D.frame_rel_path(i)
            assert (shard / rel).read_bytes() == (tmp_path / "whole" / rel).read_bytes()
    (out / "shard_00001" / D.frame_rel_path(5)).unlink()
    plan, done = tasks(replace(dask, **{"launcher.shards": None}))
    assert plan["per_shard"] == 4 and [s["rendered"] for s in done] == [0, 1]
    with pytest.raises(UserError, match="4 frames a shard"):
        DD.preflight(replace(dask, **{"launcher.shards": 4}), out, 8, 0)
    with pytest.raises(UserError, match="frames a shard"):
        DD.preflight(replace(dask, **{"seed": 9, "launcher.shards": None}), out, 8, 0)  # another recipe
    from crater_synth.outfolder import OutFolder

    other = load_settings(D.detection_overrides([*TINY, "seed=9"]))
    OutFolder(out / "shard_00002", R.KIND, subject=f"recipe {R.recipe_key(other)}").claim().release()
    with pytest.raises(UserError, match="shard_00002"):
        DD.preflight(replace(dask, **{"launcher.shards": None}), out, 12, 0)
    (out / "notes.txt").write_text("mine")
    with pytest.raises(UserError, match="notes.txt"):
        DD.preflight(dask, out, 8, 0)


def test_shards_hold_whole_fields_and_at_most_the_cap_by_default():
    det = replace(DET, views_per_field=64)
    assert D.shard_frames(det, 256, 2) == 128 and D.shard_frames(det, 100, 2) == 64
    assert D.shard_frames(det, 1_000_000, 8) == D.MAX_SHARD_FRAMES == 2048
    assert D.shard_frames(replace(det, views_per_field=48), 1_000_000, 8) == 2016  # whole fields
    assert D.shard_frames(det, 1_000_000, 8, cap=False) == 125_056


@pytest.mark.integration
def test_a_sharded_set_on_a_local_dask_cluster_renders_the_unsharded_runs_frames(tmp_path):
    """launcher=dask on 2 local workers, 2 shards of one field: each frame is byte for byte the frame one
    unsharded run renders (its row the same but for the render time); a rerun skips both shards."""
    from crater_synth.dataset.detection_dask import run_detection_dask

    base = [*TINY[:-1], "seed=3"]
    one = load_settings(D.detection_overrides([*base, "render.workers=1"]))
    R.render_detection_frames(one, tmp_path / "one", 4)
    dask = load_settings(D.detection_overrides([*base, "launcher=dask", "launcher.n_workers=2", "launcher.shards=2"]))
    summary = run_detection_dask(dask, tmp_path / "set", 4, progress=False)
    assert (summary["workers"], summary["shards_rendered"], summary["rendered"]) == (2, 2, 4), summary
    whole = D.manifest_rows(tmp_path / "one")
    shards = D.shard_folders(tmp_path / "set")
    assert [s.name for s in shards] == summary["shards"] == ["shard_00000", "shard_00001"]
    for k, shard in enumerate(shards):
        rows = D.manifest_rows(shard)
        assert sorted(rows) == [2 * k, 2 * k + 1]
        for i, row in rows.items():
            rel = D.frame_rel_path(i)
            assert (shard / rel).read_bytes() == (tmp_path / "one" / rel).read_bytes()
            assert {**row, "render_seconds": 0} == {**whole[i], "render_seconds": 0}
    again = run_detection_dask(dask, tmp_path / "set", 4, progress=False)
    assert (again["shards_skipped"], again["rendered"]) == (2, 0)
