"""`crater-synth report`: a tiny run directory -> one self-contained HTML page whose every image loads in
headless Chromium; absent inputs become "not run" notes; a corrupt input is one error naming it."""

from __future__ import annotations

import csv
import json
import math
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from crater_core import schema
from crater_core.exr import write_exr
from train.registry import MODELS

from helpers.navresult import make_demo, make_frames

CRATERS = ("shackleton", "de_gerlache", "shoemaker")
SIZE, RIM_PX = 64, 40.0


# ------------------------------------------------------------------------------------------------
# Fixture: a few small EXRs + manifest, metrics.json, loop_history.json, experiments.csv
# ------------------------------------------------------------------------------------------------
def _render(k: int, sun_el: float, sun_az: float) -> dict[str, np.ndarray]:
    """A Lambert-shaded bowl (depth differs per crater), seeded roughness."""
    v, u = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    x, y = (u - SIZE / 2) / (RIM_PX / 2), (v - SIZE / 2) / (RIM_PX / 2)
    r = np.hypot(x, y)
    z = np.where(r < 1, -(0.3 + 0.2 * k) * (1 - r**2), 0.0) + 0.1 * np.exp(-(((r - 1) / 0.15) ** 2))
    z = z + 0.01 * np.random.default_rng(k).normal(size=z.shape)
    gy, gx = np.gradient(z, 2.0 / RIM_PX)
    n = np.stack([-gx, gy, np.ones_like(z)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    el, az = math.radians(sun_el * 10), math.radians(sun_az)  # exaggerated so some pixels are lit
    s = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
    mu0 = np.clip(n @ s, 0, None)
    return {
        "IF": 0.1 * mu0,
        "depth": 1e4 - 100 * z,
        "N.X": n[..., 0],
        "N.Y": n[..., 1],
        "N.Z": n[..., 2],
        "lit": (mu0 > 0).astype(np.float32),
    }


def make_dataset(d: Path, craters=CRATERS) -> list[dict]:
    rows = []
    c = SIZE / 2
    boxes = {
        f"{s:.1f}": [c - s * RIM_PX / 2, c - s * RIM_PX / 2, c + s * RIM_PX / 2, c + s * RIM_PX / 2]
        for s in (1.0, 1.2, 1.4)
    }
    for k, crater in enumerate(craters):
        for i, (se, sa, ce, ca) in enumerate(
            [(0.8, 0.0, 86.0, 0.0), (1.6, 120.0, 86.0, 180.0), (1.6, 240.0, 90.0, 0.0), (0.8, 90.0, 90.0, 180.0)]
        ):
            ch = _render(k % 3, se, sa)
            rel = schema.render_rel_path(crater, se, sa, ce, ca)
            write_exr(d / rel, ch)
            rows.append(
                schema.validate_row(
                    {
                        "schema_version": schema.SCHEMA_VERSION,
                        "crater": crater,
                        "index": i,
                        "indices": [0, 0, 0, i],
                        "sun_elevation": se,
                        "sun_azimuth": sa,
                        "cam_elevation": ce,
                        "cam_azimuth": ca,
                        "range_m": 30000.0,
                        "fov_deg": 90.0,
                        "width": SIZE,
                        "height": SIZE,
                        "frame_width": 210,
                        "crop_origin": [73, 73],
                        "center_px": [c, c],
                        "rim_ellipse": {"cu": c, "cv": c, "a": RIM_PX / 2, "b": RIM_PX / 2 * 0.97, "angle_rad": 0.1},
                        "sigma_boxes": boxes,
                        "lit_fraction": float(ch["lit"].mean()),
                        "mean_if": float(ch["IF"].mean()),
                        "path": rel,
                        "sha256": schema.sha256_file(d / rel),
                        "seed": 100 + i,
                        "code_version": "test",
                        "renderer": "fast",
                        "terrain_id": f"{crater}-test",
                        "render_digest": "0000abcd",
                    }
                )
            )
    schema.write_manifest(d / schema.MANIFEST_NAME, rows)
    return rows


def make_metrics() -> dict:
    conf = {
        "lunarnet_ex": [[9, 1, 0], [2, 7, 1], [0, 0, 10]],
        "lunarsvm_ex": [[8, 2, 0], [1, 8, 1], [1, 0, 9]],
        "hog_svm": [[3, 4, 3], [3, 3, 4], [4, 3, 3]],
    }
    out = {}
    for m, c in conf.items():
        a = np.array(c)
        acc = float(np.trace(a) / a.sum())
        out[m] = {
            "real_accuracy": acc,
            "real_accuracy_class_mean": acc,
            "val_accuracy": 0.93 if m != "hog_svm" else 0.41,
            "per_crater": {n: float(a[i, i] / a[i].sum()) for i, n in enumerate(CRATERS)},
            "per_sigma": {"1.0": 0.9, "1.2": 0.8, "1.4": None},
            "per_source": {"lroc_wac_south": 0.85},
            "confusion": c,
        }
    out.update(
        {
            "classes": list(CRATERS),
            "train_images": 9000,
            "val_images": 2250,
            "test_images": 30,
            "test_sources": ["lroc_wac_south"],
            "test_per_crater": {n: 10 for n in CRATERS},
            "limits": "The embedded real test set is one real observation per crater (test).",
            "evaluate_seconds": 1.5,
        }
    )
    return out


def make_run(tmp: Path, with_optional: bool = True) -> tuple[Path, Path]:
    ds, run = tmp / "ds", tmp / "run"
    make_dataset(ds)
    run.mkdir()
    # What `crater-synth train` saves: a resolved config naming the dataset (the report prefers it).
    (run / "config.yaml").write_text(
        f"seed: 0\nsweep: {{name: tiny}}\ntrain:\n  dataset_dir: {ds}\n  select: {{cam_elevation: [90.0]}}\n"
    )  # as a loop round / Fig. 6 point
    (run / "metrics.json").write_text(json.dumps(make_metrics()))
    if with_optional:
        from train.plots import plot_confusion

        plot_confusion(run / "confusion_lunarnet_ex.png", make_metrics()["lunarnet_ex"]["confusion"], CRATERS, "x")
        # The shape crater_synth/evaluation/closed_loop.py writes.
        rounds = [
            {
                "round": i,
                "sun_elevation_count": n,
                "renders_new": 4500,
                "renders_reused": 4500 * i,
                "images": 4500 * n,
                "lunarnet_ex": a,
                "lunarsvm_ex": a - 0.05,
                "hog_svm": 0.3,
                "val_accuracy": {m: 0.9 for m in MODELS},
                "render_s": 600.0 * n,
                "train_s": 120.0,
                "run_dir": f"{run}/rounds/round{i}-sun{n}",
            }
            for i, (n, a) in enumerate([(2, 0.6), (4, 0.8), (6, 0.9)])
        ]
        (run / "loop_history.json").write_text(
            json.dumps(
                {
                    "threshold": 0.85,
                    "schedule": [2, 4, 6, 8, 10],
                    "rounds": rounds,
                    "stopped_because": "threshold reached",
                }
            )
        )
        with open(run / "experiments.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(
                ["parameter", "count", "sigma", "model", "real_accuracy", "val_accuracy", "train_images", "seconds"]
            )  # crater_synth/evaluation/figure6.py
            for p, counts in (("sun_elevation", (2, 4)), ("cam_azimuth", (3, 6))):
                for n in counts:
                    for s in (1.0, 1.2):
                        for m in ("lunarnet_ex", "lunarsvm_ex"):
                            w.writerow(
                                [
                                    p,
                                    n,
                                    s,
                                    m,
                                    0.5 + 0.04 * n + 0.05 * s + (0.02 if m == "lunarnet_ex" else 0),
                                    0.9,
                                    2250 * n,
                                    12.5,
                                ]
                            )
        (run / "ablation.json").write_text(json.dumps(make_ablation()))
        make_demo(run / "navigation")  # what `make navigate-demo` and `nav-frames-eval --json` write
        make_frames(run / "navigation")
    return run, ds


def make_ablation() -> dict:
    """The shape crater_synth/evaluation/ablation.py writes (without recorded overrides: no images)."""

    def summary(v):
        return {
            "validation_mean": {m: v for m in MODELS},
            "test_mean": {m: v - 0.1 for m in MODELS},
            "groups": {
                "validation1-a+b+c": {
                    "role": "validation",
                    "models": {m: {"per_crater": {"a": v, "b": v, "c": v}} for m in MODELS},
                },
                "test-x+y+z": {"role": "test", "models": {m: {"per_crater": {"x": 0.5}} for m in MODELS}},
            },
        }

    return {
        "protocol": "docs/validation.md",
        "budget": ["train.max_epochs=5"],
        "variants": [
            {
                "variant": "all levers on",
                "lever": None,
                "overrides": [],
                "renders": {"g": 864},
                "summary": summary(0.81),
            },
            {
                "variant": "mosaic_composite off",
                "lever": "mosaic_composite",
                "overrides": ["sensor.mosaic_frames=1"],
                "why": "mosaic",
                "renders": {"g": 864},
                "summary": summary(0.62),
            },
        ],
    }


def _run(run: Path, *extra: str):
    from crater_synth.cli import main

    return CliRunner().invoke(main, ["report", str(run), "realset.per_crater=12", "--hist-samples", "2", "-q", *extra])


# ------------------------------------------------------------------------------------------------
# Headless Chromium
# ------------------------------------------------------------------------------------------------
def _chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        exe = shutil.which(name)
        if exe:
            return exe
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail("headless Chromium is required in CI (apt-get install -y chromium)")
    pytest.skip("chromium not installed (apt-get install -y chromium); the report page check needs it")


def _chromium_args(exe: str, profile: Path) -> list[str]:
    return [
        exe,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        "--hide-scrollbars",
        "--mute-audio",
        f"--user-data-dir={profile}",
    ]


CHECK_SCRIPT = """<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length;
  var d = document.createElement('div');
  d.id = 'imgcheck';
  d.textContent = 'IMGCHECK total=' + imgs.length + ' loaded=' + ok + ' broken=' + (imgs.length - ok) +
                  ' text=' + document.body.innerText.trim().length +
                  ' sections=' + document.querySelectorAll('section').length;
  // Tables wider than their box at this window size: a reader must scroll sideways to see them whole.
  var wide = Array.prototype.slice.call(document.querySelectorAll('.tablewrap')).filter(function (w) {
    return w.scrollWidth > w.clientWidth + 1; }).map(function (w) {
    var t = w.querySelector('table'); return (t && t.className) || 'table'; });
  d.textContent += ' wide=' + wide.length + ' [' + wide.join(',') + ']';
  document.body.appendChild(d);
});
</script>"""


@pytest.mark.integration
def test_report_page_loads_in_chromium(tmp_path):
    import time

    t0 = time.perf_counter()
    run, ds = make_run(tmp_path)
    res = _run(run)
    assert res.exit_code == 0, res.output
    page = run / "report" / "index.html"
    assert res.output.strip() == str(page)
    text = page.read_text()
    # Self-contained: relative image links only, no external URLs, no scripts.
    srcs = re.findall(r'<img[^>]+src="([^"]+)"', text)
    assert len(srcs) >= 3 + 3 + 1 + 3 + 1 + 1 + 2 + 1  # ... + annotated navigation windows + error plot
    for s in srcs:
        assert "/" not in s and (page.parent / s).is_file(), s
    assert not re.search(r'(src|href)="(https?:)?//', text) and "<script" not in text
    # The sections and what they must say.
    for anchor in (
        "contact",
        "compare",
        "histograms",
        "models",
        "loop",
        "figure6",
        "fidelity",
        "navigation",
        "provenance",
    ):
        assert f'id="{anchor}"' in text and f'href="#{anchor}"' in text
    assert "ONE real LROC WAC observation per crater, seen 10 ways" in text
    assert "no single sun direction" in text
    assert "re-plotted from <code>metrics.json</code>" in text  # 2 of 3 confusion PNGs absent
    assert "re-plotted from experiments.csv" in text  # no figure6.png
    assert str(ds) in text and "lroc_wac_south" in text and "lola_ldem256_south" in text
    assert "threshold reached" in text and "not run" not in text
    assert "mosaic_composite off" in text and "sensor.mosaic_frames=1" in text and "re-run crater-synth ablate" in text
    assert "6 (train.select" in text and "4 of 4" not in text and "2 of 2 renders" in text
    assert not list(run.glob(".report.*"))  # temp dir swapped in
    # A second run replaces the report in place.
    assert _run(run).exit_code == 0 and page.is_file() and not list(run.glob(".report.*"))

    exe = _chromium()
    check = page.parent / "_check.html"
    check.write_text(text.replace("</body>", CHECK_SCRIPT + "</body>"))
    try:
        out = subprocess.run(
            [
                *_chromium_args(exe, tmp_path / "profile"),
                "--window-size=1400,1000",
                "--virtual-time-budget=10000",
                "--dump-dom",
                check.as_uri(),
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
    finally:
        check.unlink()
    m = re.search(
        r"IMGCHECK total=(\d+) loaded=(\d+) broken=(\d+) text=(\d+) sections=(\d+) wide=(\d+) \[(.*?)\]", out.stdout
    )
    assert m, f"chromium printed no check line; stderr: {out.stderr[-2000:]}"
    total, loaded, broken, chars, sections, wide = map(int, m.groups()[:6])
    assert wide == 0, f"tables clipped at a 1400 px window: {m.group(7)}"
    assert total == len(srcs) and loaded == total and broken == 0, m.group(0)
    assert chars > 2000 and sections == 9
    # Not blank: a screenshot of the top of the page has real contrast.
    shot = tmp_path / "shot.png"
    subprocess.run(
        [
            *_chromium_args(exe, tmp_path / "profile2"),
            "--window-size=1280,1600",
            "--virtual-time-budget=10000",
            f"--screenshot={shot}",
            page.as_uri(),
        ],
        capture_output=True,
        timeout=60,
    )
    from PIL import Image

    px = np.asarray(Image.open(shot).convert("L"), dtype=float)
    assert px.shape[0] >= 1000 and px.std() > 20
    assert time.perf_counter() - t0 < 120


def test_absent_inputs_become_not_run_notes(tmp_path):
    run = tmp_path / "empty_run"
    run.mkdir()
    (run / "config.yaml").write_text("seed: 0\n")  # a run that got no further than its config (an empty
    # directory is an error: tests/test_errors_paths.py)
    res = _run(run, f"train.dataset_dir={tmp_path}/no_dataset")
    assert res.exit_code == 0, res.output
    text = (run / "report" / "index.html").read_text()
    assert text.count("not run:") >= 7
    for what in (
        "crater-synth dataset",
        "crater-synth train",
        "loop_history.json",
        "experiments.csv",
        "crater-synth ablate",
    ):
        assert what in text
    assert "ONE real LROC WAC observation per crater, seen 12 ways" in text  # realset.per_crater=12
    assert "<img" not in text


def test_dataset_override_beats_the_saved_config(tmp_path):
    from crater_synth.report import effective_config

    run, ds = make_run(tmp_path, with_optional=False)
    assert effective_config(run).dataset_dir == ds
    rc = effective_config(run, [f"train.dataset_dir={tmp_path}/other"])
    assert rc.dataset_dir == tmp_path / "other" and "override" in rc.dataset_dir_source


@pytest.mark.parametrize(
    "name, content, match",
    [
        ("metrics.json", "{not json", "metrics.json: corrupt JSON"),
        ("metrics.json", json.dumps({"lunarnet_ex": {"real_accuracy": "high"}}), "lunarnet_ex.real_accuracy"),
        ("loop_history.json", json.dumps({"rounds": [{"round": 1}]}), "rounds[0].sun_elevation_count"),
        ("experiments.csv", "parameter,count\nsun_elevation,2\n", "experiments.csv: corrupt experiments table"),
        (
            "experiments.csv",
            "parameter,count,sigma,model,real_accuracy,train_images\nsun_elevation,two,1.0,x,0.5,1\n",
            "experiments.csv:2: corrupt",
        ),
        ("figure6.png", "GIF89a not a png", "figure6.png: corrupt PNG"),
        ("config.yaml", "train: [unclosed", "config.yaml: corrupt YAML"),
        ("train_summary.json", "[]", "train_summary.json: corrupt training summary"),
        ("confusion_hog_svm.png", "", "confusion_hog_svm.png: corrupt PNG"),
        ("ablation.json", json.dumps({"variants": [{"summary": {}}]}), "ablation.json: not a crater-synth ablation"),
    ],
)
def test_corrupt_input_is_one_clear_error(tmp_path, name, content, match):
    run = tmp_path / "run"
    run.mkdir()
    (run / name).write_text(content)
    res = _run(run, f"train.dataset_dir={tmp_path}/no_dataset")
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and match in lines[0], res.output
    assert str(run / name) in lines[0]
    assert not (run / "report").exists() and not list(run.glob(".report.*"))


def test_chromium_is_required_in_ci(monkeypatch):
    monkeypatch.setattr(shutil, "which", lambda name: None)
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="required in CI"):
        _chromium()
    monkeypatch.setenv("CI", "false")
    with pytest.raises(pytest.skip.Exception, match="chromium not installed"):
        _chromium()


def test_missing_run_dir_is_an_error(tmp_path):
    res = _run(tmp_path / "nope")
    assert res.exit_code == 2 and "run directory" in res.output and "does not exist" in res.output


# South-polar craters (IAU Gazetteer, rounded) for runs with other class counts than the paper's three.
OTHER_CRATERS = {
    "faustini": (-87.3, 77.0, 39.0),
    "haworth": (-87.45, -5.0, 51.0),
    "cabeus": (-85.3, -42.1, 98.0),
    "amundsen": (-84.4, 85.6, 103.0),
    "nobile": (-85.2, 53.5, 73.0),
    "sverdrup": (-88.5, -152.0, 33.0),
    "slater": (-88.1, -110.5, 24.0),
    "malapert": (-84.9, 12.9, 69.0),
    "idelson": (-84.2, 114.0, 60.0),
}


def make_n_class_run(tmp: Path, names: list[str], with_crater_group: bool) -> Path:
    """A run whose classifier knows ``names``: dataset, metrics.json (n x n confusion), no confusion PNGs."""
    ds, run = tmp / "ds", tmp / "run"
    make_dataset(ds, names)
    run.mkdir()
    group = (
        "".join(
            f"  {n}: {{name: {n}, lat: {OTHER_CRATERS[n][0]}, lon: {OTHER_CRATERS[n][1]}, "
            f"diameter_km: {OTHER_CRATERS[n][2]}}}\n"
            for n in names
        )
        if with_crater_group
        else "  {}\n"
    )
    (run / "config.yaml").write_text(f"seed: 0\nsweep: {{name: tiny}}\ncrater:\n{group}train:\n  dataset_dir: {ds}\n")
    n = len(names)
    conf = (np.eye(n, dtype=int) * 6 + 1).tolist()  # 6 right, 1 into every other class
    metrics = {
        "classes": names,
        "train_images": 100 * n,
        "val_images": 20 * n,
        "test_images": (n + 5) * n,
        "test_sources": ["lroc_wac_south"],
        "test_per_crater": {c: n + 5 for c in names},
        "limits": "The embedded real test set is one real observation per crater (test).",
    }
    for m in MODELS:
        metrics[m] = {
            "real_accuracy": 6 / (n + 5),
            "real_accuracy_class_mean": 6 / (n + 5),
            "val_accuracy": 0.9,
            "per_crater": {c: 6 / (n + 5) for c in names},
            "per_sigma": {"1.0": 0.5},
            "per_source": {"lroc_wac_south": 6 / (n + 5)},
            "confusion": conf,
        }
    (run / "metrics.json").write_text(json.dumps(metrics))
    return run


@pytest.mark.parametrize(
    "names, crater_group",
    [(["faustini", "haworth"], True), (list(OTHER_CRATERS), False)],
    ids=["2-classes", "9-classes"],
)
def test_report_works_for_any_number_of_classes(tmp_path, names, crater_group):
    run = make_n_class_run(tmp_path, names, crater_group)
    res = _run(run, "realset.per_crater=3")
    assert res.exit_code == 0, res.output
    page = run / "report" / "index.html"
    text = page.read_text()
    n = len(names)
    for c in names:  # one contact sheet per crater
        assert (page.parent / f"contact_{c}.png").is_file() and f"<b>{c}</b>: 4 of 4 renders" in text
    per_crater = text[text.index("Real accuracy per crater") : text.index("Real accuracy per ROI")]
    assert [m for m in re.findall(r"<tr><td>([a-z_]+)</td>", per_crater)] == names  # one row per class
    from PIL import Image

    for m in MODELS:  # re-plotted n x n confusion, sized for n classes
        with Image.open(page.parent / f"confusion_{m}.png") as im:
            assert im.size[0] >= (552 if n <= 8 else 120 * (1.6 + 0.42 * n) - 1)
    assert "re-plotted from <code>metrics.json</code>" in text
    if crater_group:  # real crops exist for the configured craters
        assert all((page.parent / f"compare_{c}.png").is_file() for c in names)
        assert (page.parent / "histograms.png").is_file()
    else:
        assert "Real crops unavailable: none of the report" in text


def test_fidelity_section_draws_real_vs_synthetic_for_every_crater(tmp_path):
    """With recorded overrides, the fidelity section finds the chosen variant's renders and draws, per
    crater, the real crop, one render and a training image (mosaic composite + sensor)."""
    run, _ = make_run(tmp_path, with_optional=False)
    make_dataset(tmp_path / "synth" / "ablate-abc123")
    doc = make_ablation()
    doc["overrides"] = [f"data_dir={tmp_path}", "sensor=wac_mosaic"]
    for v in doc["variants"]:
        v["render_key"] = "abc123"
        v["summary"]["groups"] = {
            "test-s+d+s": {"role": "test", "models": {m: {"per_crater": {c: 0.5 for c in CRATERS}} for m in MODELS}}
        }
    (run / "ablation.json").write_text(json.dumps(doc))
    res = _run(run)
    assert res.exit_code == 0, res.output
    text = (run / "report" / "index.html").read_text()
    for c in CRATERS:
        assert f'src="fidelity_{c}.png"' in text and (run / "report" / f"fidelity_{c}.png").is_file()
    assert "1 frame(s) in the composite" in text  # the fixture has one render per camera pose


def test_fidelity_table_gets_held_out_columns_when_held_out_groups_ran(tmp_path):
    run, _ = make_run(tmp_path, with_optional=False)
    doc = make_ablation()
    (run / "ablation.json").write_text(json.dumps(doc))
    assert _run(run).exit_code == 0
    assert "held-out</th>" not in (run / "report" / "index.html").read_text()
    for v in doc["variants"]:
        v["summary"]["holdout_mean"] = {m: 0.77 for m in MODELS}
        v["summary"]["groups"]["holdout1-h+i+j"] = {
            "role": "holdout",
            "models": {m: {"per_crater": {"h": 0.77}} for m in MODELS},
        }
    (run / "ablation.json").write_text(json.dumps(doc))
    res = _run(run)
    assert res.exit_code == 0, res.output
    text = (run / "report" / "index.html").read_text()
    assert "LunarNet_ex held-out</th>" in text and "<b>held-out</b> h" in text
