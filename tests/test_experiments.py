"""Figure 6 subset selection: every subset has exactly the paper's counts and comes from one dataset."""

import pytest

from crater_synth.config import compose, resolved
from crater_synth.experiments import plan_points
from data_manifest.sweep import AXES, SweepError, grid_from_config, nearest_subset, rows_in_selection


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
