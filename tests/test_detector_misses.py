"""python -m crater_synth.tools.detector_misses: catalogued craters found or missed, split by the DEM map."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from crater_synth.navigation.map.check import ListedCrater
from crater_synth.tools import detector_misses as dm


def test_a_catalogued_crater_is_in_the_map_by_the_scorings_match_rule():
    """Within 0.25 D and 25 % of the diameter: in the map, with the nearest such landmark's depth / D."""
    lm = [SimpleNamespace(x_m=0.0, y_m=0.0, diameter_km=20.0, depth_m=2000.0)]
    listed = [
        ListedCrater(4000.0, 0.0, 20.0),  # 0.2 D away: in
        ListedCrater(6000.0, 0.0, 20.0),  # 0.3 D away: out
        ListedCrater(0.0, 0.0, 27.0),  # 35 % larger: out
    ]
    inside, dd = dm.map_match(listed, lm)
    assert inside.tolist() == [True, False, False]
    assert dd[0] == pytest.approx(0.1) and np.isnan(dd[1:]).all()


def test_tables_split_recall_by_map_size_depth_and_rim():
    """Each part's recall over its own craters; a bin with none gives None."""
    listed = [ListedCrater(0.0, 0.0, 16.0), ListedCrater(1e6, 0.0, 40.0), ListedCrater(2e6, 0.0, 70.0)]
    lm = [SimpleNamespace(x_m=0.0, y_m=0.0, diameter_km=16.0, depth_m=2400.0)]  # depth / D 0.15
    t = np.array([(0, 1, 16.0, 1), (1, 0, 40.0, 0), (2, 1, 70.0, 1)], float)
    out = dm.tables(t, listed, lm)
    assert out["all"] == {"n": 3, "recall": pytest.approx(2 / 3, abs=1e-4)}
    assert out["in_map"]["n"] == 1 and out["in_map"]["recall"] == 1.0
    assert out["in_map"]["by_depth_d"][">=0.15"] == {"n": 1, "recall": 1.0}
    assert out["in_map"]["by_depth_d"]["0-0.05"] == {"n": 0, "recall": None}
    assert out["not_in_map"]["recall"] == 0.5 and out["not_in_map"]["rim_wholly_inside"] == {"n": 1, "recall": 1.0}
    assert out["not_in_map"]["by_size_km"]["30-60"] == {"n": 1, "recall": 0.0}


def test_the_north_needs_a_committed_choice_and_the_south_a_threshold(tmp_path, capsys):
    """--pole north without --choice, or with a choice file git does not hold, and the south without
    --threshold: one error line each, no output."""
    out = tmp_path / "misses.json"
    assert dm.main(["--pole", "north", "--out", str(out)]) == 1
    assert "--choice" in capsys.readouterr().err
    loose = tmp_path / "choice.json"
    loose.write_text("{}")
    assert dm.main(["--pole", "north", "--choice", str(loose), "--out", str(out)]) == 1
    assert "not committed" in capsys.readouterr().err
    assert dm.main(["--out", str(out)]) == 1
    assert "--threshold" in capsys.readouterr().err
    assert not out.exists()
