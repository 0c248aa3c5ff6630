"""The report's crater-navigation section (section 8) from a small synthetic navigation result: what
`make navigate-demo` and `crater-synth nav-frames-eval --json` write into RUN_DIR/navigation/. Nothing
is detected or rendered here."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from helpers.navresult import make_demo, make_frames


def _report(run: Path, *extra: str):
    from crater_synth.cli import main

    return CliRunner().invoke(
        main,
        ["report", str(run), f"train.dataset_dir={run}/no_dataset", "realset.per_crater=12", "-q", *extra],
    )


def _section(html: str) -> str:
    start = html.index('<section id="navigation">')
    return html[start : html.index("</section>", start)]


def test_navigation_section_has_the_table_the_windows_and_the_error_plot(tmp_path):
    run = tmp_path / "run"
    nav = run / "navigation"  # only a navigation result: still a run to report
    demo = make_demo(nav)
    make_frames(nav)
    res = _report(run)
    assert res.exit_code == 0, res.output
    out = run / "report"
    html = (out / "index.html").read_text()
    assert '<a href="#navigation">8. Crater navigation</a>' in html and 'id="provenance"' in html
    sec = _section(html)
    # The metrics table: one row per method, split and window set, the summary values as written.
    rows = re.findall(r"<tr><td>classical</td><td>(\w+)</td><td>([^<]+)</td>(.*?)</tr>", sec)
    assert [(s, w) for s, w, _ in rows] == [
        ("validation", "≥ 3 landmarks D ≥ 15 km"),
        ("validation", "all windows"),
        ("test", "≥ 3 landmarks D ≥ 15 km"),
        ("test", "all windows"),
    ]
    cells = re.findall(r'<td class="num">([^<]*)</td>', rows[1][2])
    assert cells == ["1", "1.000", "1.30", "1.30", "0.000", "0.857", "0.522", "0.194"]
    assert re.findall(r'<td class="num">([^<]*)</td>', rows[3][2]) == ["1", "0.000", "–", "–", "0.000", "–"] + [
        "0.086",
        "0.031",
    ]
    # The annotated windows: copied next to the page, linked relatively, captioned with their result.
    for w in demo["windows"]:
        assert (out / f"nav_{w['png']}").read_bytes() == (nav / w["png"]).read_bytes()
        assert f'<img src="nav_{w["png"]}"' in sec
    assert "155 detections" in sec and "error <b>1.30 km</b>" in sec and "6 correct" in sec
    assert "<b>no fix</b>: only 4 landmarks agree (need 5)" in sec
    # Terrain patches alone: captioned as patches (cyan squares), not as map landmarks.
    assert "<b>terrain patches</b> (no crater): 12 of 16 patches found" in sec and "fix from 11 patches" in sec
    assert "<tr><td>patches</td><td>validation</td>" in sec
    assert "25 map landmarks (D ≥ 10.0 km) in view" in sec
    # The map against the complete catalogue, as written.
    assert "a crater catalogue (test)" in sec and "diameter within 25 %" in sec
    assert '<td>10-15</td><td class="num">2</td><td class="num">0.500</td><td class="num">4</td>' in sec
    assert '<td>&gt;= 50</td><td class="num">0</td><td class="num">–</td><td class="num">1</td>' in sec
    # Crater detection against the catalogue on the south validation windows: PNGs copied in, counts as written.
    assert "<h3>Crater detection on real windows</h3>" in sec
    assert "These are the demo's 1 south validation windows (development data)" in sec
    assert "scored against a crater catalogue (test) at D ≥ 15.0 km" in sec
    for w in demo["catalogue_detection"]["windows"]:
        assert (out / f"nav_{w['png']}").read_bytes() == (nav / w["png"]).read_bytes()
        assert f'<img src="nav_{w["png"]}"' in sec
    counts = r'<td class="num">([^<]*)</td>'
    row = re.search(r"<tr><td>learned-detect</td><td>S0_1728_0128</td>(.*?)</tr>", sec).group(1)
    assert re.findall(counts, row) == ["3", "1", "2", "5", "0.750", "0.600"]
    row = re.search(r"<tr><td>template</td><td>all windows</td>(.*?)</tr>", sec).group(1)
    assert re.findall(counts, row) == ["–", "–", "–", "1", "0.000", "0.000"]
    assert "<b>learned-detect</b>: 3 catalogued craters found (green), 1 missed (red), 2 false detections" in sec
    # The descent's error plot and its per-frame table (detector and perfect-detection check).
    assert '<img src="nav_trajectory_0.png"' in sec
    assert (out / "nav_trajectory_0.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "<b>1 of 3</b> frames fixed" in sec and "<b>2 of 3</b>" in sec
    assert "preset <code>appearance</code>" in sec and "0.93 km before the appearance refinement" in sec
    assert "0.41 km" in sec and "0.0102 m" in sec and "0.0063 m" in sec
    assert "no fix: only 3 landmarks agree on one position" in sec and "no fix: no putative landmark pairs" in sec
    assert "not run:" not in sec
    # Self-contained: every link of the section is a file next to the page; no script.
    for link in re.findall(r'(?:src|href)="([^"#][^"]*)"', sec):
        assert "/" not in link and ":" not in link and (out / link).is_file(), link
    assert "<script" not in html.lower()


def test_a_demo_from_before_the_catalogue_scoring_is_shown_without_it(tmp_path):
    run = tmp_path / "run"
    nav = run / "navigation"
    doc = make_demo(nav)
    del doc["catalogue_detection"]
    (nav / "navigation.json").write_text(json.dumps(doc))
    res = _report(run)
    assert res.exit_code == 0, res.output
    sec = _section((run / "report" / "index.html").read_text())
    assert "nav_S0_1728_0128_classical.png" in sec and "Crater detection on real windows" not in sec


def test_missing_navigation_is_a_not_run_note(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("seed: 0\n")
    res = _report(run)
    assert res.exit_code == 0, res.output
    sec = _section((run / "report" / "index.html").read_text())
    assert "not run:" in sec and "make navigate-demo NAV_DEMO_DIR=RUN_DIR/navigation" in sec
    assert "<img" not in sec


@pytest.mark.parametrize("part", ["demo", "frames"])
def test_one_missing_half_is_its_own_not_run_note(tmp_path, part):
    run = tmp_path / "run"
    (make_frames if part == "demo" else make_demo)(run / "navigation")
    res = _report(run)
    assert res.exit_code == 0, res.output
    sec = _section((run / "report" / "index.html").read_text())
    assert sec.count("not run:") == 1
    if part == "demo":
        assert "make navigate-demo" in sec and "nav_trajectory_0.png" in sec
    else:
        assert "crater-synth nav-frames-eval FRAMES_DIR --json RUN_DIR/navigation/frames_eval.json" in sec
        assert "nav_S0_1728_0128_classical.png" in sec and "nav_trajectory" not in sec


def _corrupt_demo_json(nav: Path) -> Path:
    (nav / "navigation.json").write_text("{not json")
    return nav / "navigation.json"


def _demo_without_png(nav: Path) -> Path:
    (nav / "S0_1728_0128_classical.png").unlink()
    return nav / "navigation.json"


def _demo_png_not_png(nav: Path) -> Path:
    (nav / "S1_2496_0832_classical.png").write_text("GIF89a")
    return nav / "S1_2496_0832_classical.png"


def _demo_map_check_bad(nav: Path) -> Path:
    doc = json.loads((nav / "navigation.json").read_text())
    doc["map_check"]["bins"][0]["recall"] = "high"
    (nav / "navigation.json").write_text(json.dumps(doc))
    return nav / "navigation.json"


def _demo_catalogue_test_window(nav: Path) -> Path:
    doc = json.loads((nav / "navigation.json").read_text())
    doc["catalogue_detection"]["windows"][1]["split"] = "test"
    (nav / "navigation.json").write_text(json.dumps(doc))
    return nav / "navigation.json"


def _demo_catalogue_without_png(nav: Path) -> Path:
    (nav / "S0_1728_0128_template_catalogue.png").unlink()
    return nav / "navigation.json"


def _demo_catalogue_count_bad(nav: Path) -> Path:
    doc = json.loads((nav / "navigation.json").read_text())
    doc["catalogue_detection"]["windows"][0]["false"] = None
    (nav / "navigation.json").write_text(json.dumps(doc))
    return nav / "navigation.json"


def _frames_without_perfect(nav: Path) -> Path:
    doc = json.loads((nav / "frames_eval.json").read_text())
    del doc["frames"][1]["perfect"]
    path = nav / "frames_eval_arc.json"  # any frames_eval*.json is read
    path.write_text(json.dumps(doc))
    return path


def _frames_fix_without_error(nav: Path) -> Path:
    doc = json.loads((nav / "frames_eval.json").read_text())
    doc["frames"][0]["error_km"] = "small"
    (nav / "frames_eval.json").write_text(json.dumps(doc))
    return nav / "frames_eval.json"


@pytest.mark.parametrize(
    "corrupt, match",
    [
        (_corrupt_demo_json, "corrupt JSON"),
        (_demo_without_png, "which does not exist"),
        (_demo_png_not_png, "corrupt PNG"),
        (_demo_map_check_bad, "map_check should hold 'bins'"),
        (_demo_catalogue_test_window, "catalogue_detection.windows[1].split is 'test', not the catalogue windows'"),
        (_demo_catalogue_without_png, "catalogue_detection.windows[1].png names"),
        (_demo_catalogue_count_bad, "catalogue_detection.windows[0] should hold the numbers found, missed, false"),
        (_frames_without_perfect, "frames[1] should be an object with a 'perfect' object"),
        (_frames_fix_without_error, "frames[0] has a fix but no error_km"),
    ],
)
def test_corrupt_navigation_input_is_one_error_naming_the_file(tmp_path, corrupt, match):
    run = tmp_path / "run"
    make_demo(run / "navigation")
    make_frames(run / "navigation")
    bad = corrupt(run / "navigation")
    res = _report(run)
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {bad}") and match in lines[0], res.output
    assert not (run / "report").exists() and not list(run.glob(".report.*"))


def test_frames_record_is_what_the_report_reads(tmp_path, monkeypatch):
    """nav-frames-eval's JSON writer (frames_record) against the report's loader, on rows in
    evaluate_frame's shape (no rendering: the render settings are stubbed)."""
    from crater_synth.navigation.fix.solve import FixParams
    from crater_synth.navigation.rendered import record as frames_record
    from crater_synth.navigation.settings import compose_nav
    from crater_synth.report.inputs import load_nav_frames

    def row(i, fix):
        r = {
            "id": f"descent_ridge/{i}",
            "index": i,
            "altitude_km": 150.0 - i,
            "ground_sample_m": 338.0,
            "n_detections": 140,
            "landmarks_in_view": 27,
            "truth": list(range(16)),
            "matched": {0: 1, 3: 4},
            "n_headline_landmarks": 4,
            "putative_pairs": 30,
            "fix": fix,
            "reason": "" if fix else "only 3 landmarks agree on one position",
        }
        if fix:
            r.update(error_km=1e-5, identified=15, identified_correct=15, rms_px=0.01)
        return r

    rows = [
        {**row(0, False), "perfect": {**row(0, True), "n_detections": 27}},
        {**row(1, True), "unrefined": {"error_km": 0.9, "error_horizontal_km": 0.3}, "perfect": row(1, False)},
    ]
    monkeypatch.setattr(frames_record, "_render_info", lambda d: {"mode": "fast", "samples": 1})
    summary = {
        "all": {"windows": 2},
        "headline": {"windows": 2},
        "perfect": {"all": {"windows": 2}, "headline": {"windows": 2}},
    }
    nav = compose_nav()  # the classical detector and the fix's defaults, the known-attitude fix
    doc = frames_record.frames_record(tmp_path, summary, rows, 0, nav)
    (tmp_path / "frames_eval.json").write_text(json.dumps(doc))
    got = load_nav_frames(tmp_path / "frames_eval.json")
    f0 = got["frames"][0]
    assert (f0["landmarks_in_view"], f0["landmarks_in_view_min_d"], f0["matched"], f0["n_detections"]) == (
        27,
        16,
        2,
        140,
    )
    assert not f0["fix"] and f0["perfect"]["fix"] and f0["perfect"]["error_km"] == 1e-5
    # A refined fix keeps its error before the refinement; the report's error plot draws both.
    assert got["frames"][1]["unrefined"]["error_km"] == 0.9 and f0["perfect"]["unrefined"] is None
    from crater_synth.report import figures

    figures.nav_trajectory(tmp_path / "errors.png", "descent_ridge", got["frames"])
    assert (tmp_path / "errors.png").stat().st_size > 0
    assert got["min_inliers"] == FixParams().min_inliers and got["trajectory"] == "descent_ridge"
    assert doc["method"] == "position" and doc["preset"] is None and doc["settings"] == []


def test_trajectory_fixed_by_terrain_patches_says_so(tmp_path):
    """A nav-frames-eval --patches --sequential result: the patch fixes are counted and ringed in the plot."""
    run = tmp_path / "run"
    nav = run / "navigation"
    make_demo(nav)
    doc = make_frames(nav)
    fixed = [f for f in doc["frames"] if f["fix"]]
    fixed[0]["fix_source"] = "patches"
    doc["summary"]["sequence"] = {"drift_share": 0.01, "sigma_factor": 3.0, "min_sigma_km": 1.0}
    (nav / "frames_eval.json").write_text(json.dumps(doc))
    res = _report(run)
    assert res.exit_code == 0, res.output
    sec = _section((run / "report" / "index.html").read_text())
    assert "1 of them by terrain patches" in sec and "each frame's prior carried from the last fix" in sec
    assert "a cyan diamond, a fix from terrain patches" in sec
