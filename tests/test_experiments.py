"""Figure 6 subset selection: every subset has exactly the paper's counts and comes from one dataset."""

import pytest

from crater_core.sweep import AXES, SweepError, grid_from_config, nearest_subset, rows_in_selection
from crater_synth.config import ConfigError, compose, resolved
from crater_synth.evaluation.figure6 import plan_points
from train.registry import FIGURE6_MODELS


@pytest.fixture(scope="module")
def paper_grid():
    return grid_from_config(resolved(compose(["sweep=paper"]))["sweep"])


def test_each_subset_has_exactly_the_paper_counts_from_the_rendered_grid(paper_grid):
    counts = resolved(compose(["sweep=paper"]))["figure6"]["counts"]
    points = plan_points(paper_grid, counts)
    assert len(points) == 20
    for p in points:
        sel = p["select"]
        assert len(sel[p["parameter"]]) == p["count"]
        assert len(set(sel[p["parameter"]])) == p["count"]
        assert set(sel[p["parameter"]]) <= set(getattr(paper_grid, p["parameter"]))  # never a re-render
        for other in AXES:
            if other != p["parameter"]:
                assert sel[other] == list(getattr(paper_grid, other))  # others at their maximum


def test_training_image_counts_match_the_paper(paper_grid):
    """Camera-elevation counts 1..9 of the paper -> 2,250 .. 20,250 training images (SPEC Table 2)."""
    rows = [
        {
            "sun_elevation": p.sun_elevation,
            "sun_azimuth": p.sun_azimuth,
            "cam_elevation": p.cam_elevation,
            "cam_azimuth": p.cam_azimuth,
        }
        for p in paper_grid
    ]
    full = {a: list(getattr(paper_grid, a)) for a in AXES}
    for count, expected in [(1, 2250), (2, 4500), (9, 20250), (10, 22500)]:
        sel = dict(full, cam_elevation=nearest_subset(full["cam_elevation"], "cam_elevation", count))
        assert len(rows_in_selection(rows, sel)) == expected


def test_elevation_subsets_are_exact_and_azimuths_snap(paper_grid):
    assert nearest_subset(paper_grid.sun_elevation, "sun_elevation", 4) == pytest.approx([0.16, 0.32, 0.48, 0.64])
    assert nearest_subset(paper_grid.cam_elevation, "cam_elevation", 3) == pytest.approx([90.0, 86.0, 82.0])
    assert nearest_subset(paper_grid.sun_azimuth, "sun_azimuth", 6) == [0.0, 48.0, 120.0, 168.0, 240.0, 288.0]


def test_impossible_subset_is_refused():
    with pytest.raises(SweepError, match="only 4 rendered"):
        nearest_subset([0.16, 0.32, 0.48, 0.64], "sun_elevation", 6)
    with pytest.raises(SweepError, match="unknown selection axis"):
        rows_in_selection([{"sun_elevation": 1.0}], {"sun_height": [1.0]})


def test_small_config_fits_the_demo_sweep():
    cfg = resolved(compose(["sweep=demo", "figure6=small"]))
    points = plan_points(grid_from_config(cfg["sweep"]), cfg["figure6"]["counts"])
    assert {(p["parameter"], p["count"]) for p in points} == {
        ("sun_elevation", 2),
        ("sun_elevation", 4),
        ("sun_azimuth", 3),
        ("sun_azimuth", 6),
        ("cam_elevation", 1),
        ("cam_elevation", 2),
        ("cam_azimuth", 3),
        ("cam_azimuth", 6),
    }


@pytest.mark.integration
def test_experiments_end_to_end_on_a_toy_dataset(tmp_path):
    """Two Figure 6 points trained for real on a procedural dataset and tested on held-out toy frames:
    CSV rows equal to each point's evaluated metrics, the full-grid point clears a stated accuracy
    (chance is 1/3), a figure, and a rerun that skips the finished points."""
    import json

    import torch

    from crater_synth.evaluation.figure6 import read_results, run_experiments
    from train.toydata import TOY_FRAME_SOURCE, write_toy_dataset, write_toy_frames

    torch.set_num_threads(1)
    ds = tmp_path / "toy"
    write_toy_dataset(
        ds,
        sun_elevations=(15.0, 30.0),
        sun_azimuths=(0.0, 120.0, 240.0),
        cam_elevations=(90.0,),
        cam_azimuths=(0.0, 90.0, 180.0, 270.0),
        rim_px=40.0,
    )
    frames = write_toy_frames(tmp_path / "frames")
    overrides = [
        "sweep=smoke",
        "sweep.sun_elevation.values=[15.0,30.0]",
        "sweep.sun_azimuth.values=[0.0,120.0,240.0]",
        "sweep.cam_elevation.values=[90.0]",
        "sweep.cam_azimuth.values=[0.0,90.0,180.0,270.0]",
        "figure6.counts.sun_elevation=[1,2]",
        "figure6.counts.sun_azimuth=null",
        "figure6.counts.cam_elevation=null",
        "figure6.counts.cam_azimuth=null",
        "figure6.sigmas=[1.0]",
        f"train.dataset_dir={ds}",
        f"data_dir={tmp_path}",
        f"run_dir={tmp_path}/run",
        f"train.cache_dir={tmp_path}/cache",
        "train.num_threads=1",
        "train.progress=false",
        "model.input_size=64",
        "train.batch_size=16",
        "train.lr=3e-3",
        "train.max_epochs=16",
        "train.target_val_accuracy=0.85",
        "train.hog.max_train_images=200",
        "realset.include_embedded=false",
        f"realset.labels_file={frames}",
    ]
    results = run_experiments(compose(overrides), progress=False)
    rows = read_results(tmp_path / "run" / "experiments.csv")
    assert rows == results
    assert {(r["parameter"], r["count"], r["model"]) for r in rows} == {
        ("sun_elevation", c, m) for c in (1, 2) for m in FIGURE6_MODELS
    }
    images = {r["count"]: r["train_images"] for r in rows}
    assert images[2] > images[1] > 0  # the bigger subset trains on more rendered rows
    for r in rows:  # the CSV records what evaluation measured for that point
        point = tmp_path / "run" / "experiments" / f"sun_elevation-{r['count']}-s1.0"
        metrics = json.loads((point / "metrics.json").read_text())
        assert r["real_accuracy"] == pytest.approx(metrics[r["model"]]["per_source"][TOY_FRAME_SOURCE], abs=1e-6)
        assert r["real_accuracy"] == pytest.approx(metrics[r["model"]]["real_accuracy"], abs=1e-6)
    full = {r["model"]: r["real_accuracy"] for r in rows if r["count"] == 2}
    assert full["lunarnet_ex"] >= 0.7 and full["lunarsvm_ex"] >= 0.6, full
    assert (tmp_path / "run" / "figure6.png").stat().st_size > 10_000
    assert run_experiments(compose(overrides), progress=False) == results  # finished points are skipped
    assert len({r["config"] for r in rows}) == 1
    with pytest.raises(ConfigError, match="another configuration"):  # a changed budget never mixes in
        run_experiments(compose(overrides + ["train.max_train_images=100"]), progress=False)


def test_paper_budget_cuts_only_the_budget():
    """train=paper_budget (the 2-core budget of the paper-scale runs) changes the budget keys and
    nothing else of the training configuration."""
    base = resolved(compose(["sweep=paper"]))["train"]
    cut = resolved(compose(["sweep=paper", "train=paper_budget"]))["train"]
    assert (cut["max_epochs"], cut["max_train_images"], cut["max_val_images"]) == (2, 6000, 1500)
    assert cut["hog"]["max_train_images"] == 3000
    changed = {k for k in base if base[k] != cut[k]}
    assert changed == {"max_epochs", "max_train_images", "max_val_images", "hog"}
    assert {k for k in base["hog"] if base["hog"][k] != cut["hog"][k]} == {"max_train_images"}
