"""The illumination each crater really sees (crater_core.illumination) and the physical sweep."""

from __future__ import annotations

import numpy as np
import pytest

from crater_core.illumination import LUNAR_OBLIQUITY_DEG, max_sun_elevation_deg, sun_declination_deg
from crater_core.sweep import SweepError, SweepGrid, grid_from_config, rows_in_selection


@pytest.mark.parametrize("lat", [-89.67, -88.5, -88.1, -85.0, -75.0, 80.0])
def test_max_sun_elevation_matches_a_brute_force_scan(lat):
    """Scan elevations finely and keep those whose declination is within the obliquity."""
    elevations = np.linspace(-20.0, 20.0, 400_001)
    for az in (0.0, 45.0, 90.0, 135.0, 180.0, 300.0):
        ok = np.abs(sun_declination_deg(lat, elevations, az)) <= LUNAR_OBLIQUITY_DEG
        assert max_sun_elevation_deg(lat, az) == pytest.approx(elevations[ok].max(), abs=2e-4)


def test_spec_values_colatitude_plus_obliquity():
    """docs/specification.md: about 1.9 deg at Shackleton, 3.0 at de Gerlache, 3.4 at Shoemaker (towards the
    equator)."""
    assert max_sun_elevation_deg(-89.67, 0.0) == pytest.approx(0.33 + 1.54, abs=1e-3)
    assert max_sun_elevation_deg(-88.5, 0.0) == pytest.approx(1.5 + 1.54, abs=1e-3)
    assert max_sun_elevation_deg(-88.1, 0.0) == pytest.approx(1.9 + 1.54, abs=1e-3)
    # Towards the pole the Sun stays low: at Shoemaker it never rises from azimuth 180 deg.
    assert max_sun_elevation_deg(-88.1, 180.0) == pytest.approx(1.54 - 1.9, abs=1e-3)
    assert max_sun_elevation_deg(-88.1, 90.0) == pytest.approx(1.54, abs=0.01)


def _physical(**kw) -> SweepGrid:
    cfg = {
        "sun_model": "physical",
        "min_sun_elevation_deg": 0.16,
        "sun_elevation": {"count": 10},
        "sun_azimuth": {"count": 4},
        "cam_elevation": {"count": 1},
        "cam_azimuth": {"count": 1},
        "sigma": {"count": 1},
    }
    cfg.update(kw)
    return grid_from_config(cfg)


def test_physical_sweep_places_suns_per_crater_and_direction():
    grid = _physical()
    assert grid.sun_elevation == pytest.approx(tuple(0.1 * k for k in range(1, 11)))
    top = [grid.params(grid.index_of((9, j, 0, 0)), -88.1) for j in range(4)]  # fraction 1.0
    assert [p.sun_azimuth for p in top] == [0.0, 90.0, 180.0, 270.0]
    assert top[0].sun_elevation == pytest.approx(3.44, abs=1e-3)
    assert top[0].sun_elevation_param == pytest.approx(1.0)
    # Shoemaker never sees the Sun from the pole side: those renders are not part of the sweep.
    assert not grid.renders(top[2]) and grid.renders(top[0]) and grid.renders(top[1])
    # Shackleton: all directions lit up to ~1.2-1.9 deg.
    shack = [grid.params(grid.index_of((9, j, 0, 0)), -89.67) for j in range(4)]
    assert all(grid.renders(p) for p in shack)
    with pytest.raises(SweepError, match="latitude"):
        grid.params(0)


def test_physical_fractions_are_validated_and_paper_grid_unchanged():
    with pytest.raises(SweepError, match="fractions"):
        _physical(sun_elevation={"values": [0.5, 1.5]})
    paper = grid_from_config(
        {
            "sun_elevation": {"count": 3},
            "sun_azimuth": {"count": 2},
            "cam_elevation": {"count": 1},
            "cam_azimuth": {"count": 1},
            "sigma": {"count": 1},
        }
    )
    p = paper.params(paper.index_of((2, 1, 0, 0)), -88.1)
    assert p.sun_elevation == pytest.approx(0.48) and p.sun_elevation_param == pytest.approx(0.48)
    assert paper.renders(p)


def test_selection_of_physical_rows_uses_the_fraction():
    rows = [
        {
            "sun_elevation": 1.7,
            "sun_elevation_param": 0.5,
            "sun_azimuth": 0.0,
            "cam_elevation": 90.0,
            "cam_azimuth": 0.0,
        },
        {
            "sun_elevation": 3.4,
            "sun_elevation_param": 1.0,
            "sun_azimuth": 0.0,
            "cam_elevation": 90.0,
            "cam_azimuth": 0.0,
        },
        {"sun_elevation": 0.32, "sun_azimuth": 0.0, "cam_elevation": 90.0, "cam_azimuth": 0.0},
    ]
    assert rows_in_selection(rows, {"sun_elevation": [0.5]}) == [rows[0]]
    assert rows_in_selection(rows, {"sun_elevation": [0.32]}) == [rows[2]]
