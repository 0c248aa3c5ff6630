"""Figure 6 subset selection: every subset has exactly the paper's counts and comes from one dataset."""

import pytest

from crater_synth.config import compose, resolved
from crater_synth.experiments import plan_points
from crater_core.sweep import AXES, SweepError, grid_from_config, nearest_subset, rows_in_selection


@pytest.fixture(scope="module")
def paper_grid():
    return grid_from_config(resolved(compose(["sweep=paper"]))["sweep"])


def test_each_subset_has_exactly_the_paper_counts_from_the_rendered_grid(paper_grid):
    counts = resolved(compose(["sweep=paper"]))["experiments"]["counts"]
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
    rows = [{"sun_elevation": p.sun_elevation, "sun_azimuth": p.sun_azimuth, "cam_elevation": p.cam_elevation,
             "cam_azimuth": p.cam_azimuth} for p in paper_grid]
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
    cfg = resolved(compose(["sweep=demo", "experiments=small"]))
    points = plan_points(grid_from_config(cfg["sweep"]), cfg["experiments"]["counts"])
    assert {(p["parameter"], p["count"]) for p in points} == {
        ("sun_elevation", 2), ("sun_elevation", 4), ("sun_azimuth", 3), ("sun_azimuth", 6),
        ("cam_elevation", 1), ("cam_elevation", 2), ("cam_azimuth", 3), ("cam_azimuth", 6)}


def test_experiments_end_to_end_on_a_toy_dataset(tmp_path):
    """Two Figure 6 points trained for real on a procedural dataset: CSV rows, figure, and a rerun
    that skips the finished points."""
    import torch

    from crater_synth.experiments import read_results, run_experiments
    from train.toydata import write_toy_dataset

    torch.set_num_threads(1)
    ds = tmp_path / "toy"
    write_toy_dataset(ds, sun_elevations=(15.0, 30.0), sun_azimuths=(0.0, 120.0, 240.0), cam_elevations=(90.0,),
                      cam_azimuths=(0.0, 90.0, 180.0, 270.0), rim_px=40.0)
    overrides = ["sweep=smoke", "sweep.sun_elevation.values=[15.0,30.0]", "sweep.sun_azimuth.values=[0.0,120.0,240.0]",
                 "sweep.cam_elevation.values=[90.0]", "sweep.cam_azimuth.values=[0.0,90.0,180.0,270.0]",
                 "experiments.counts.sun_elevation=[1,2]", "experiments.counts.sun_azimuth=null",
                 "experiments.counts.cam_elevation=null", "experiments.counts.cam_azimuth=null", "experiments.sigmas=[1.0]",
                 f"train.dataset_dir={ds}", f"data_dir={tmp_path}", f"run_dir={tmp_path}/run",
                 f"train.cache_dir={tmp_path}/cache", "train.num_threads=1", "train.progress=false",
                 "train.max_epochs=2", "train.batch_size=32", "realset.per_crater=15", "train.hog.max_train_images=60"]
    results = run_experiments(compose(overrides), progress=False)
    rows = read_results(tmp_path / "run" / "experiments.csv")
    assert rows == results
    assert {(r["parameter"], r["count"], r["model"]) for r in rows} == {
        ("sun_elevation", c, m) for c in (1, 2) for m in ("lunarnet_ex", "lunarsvm_ex")}
    images = {r["count"]: r["train_images"] for r in rows}
    assert images[2] > images[1] > 0  # the bigger subset trains on more rendered rows
    assert all(0.0 <= r["real_accuracy"] <= 1.0 for r in rows)
    assert (tmp_path / "run" / "figure6.png").stat().st_size > 10_000
    assert run_experiments(compose(overrides), progress=False) == results  # finished points are skipped
