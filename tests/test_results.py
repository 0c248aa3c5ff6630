"""The paper's findings: each verdict follows from its stated rule on the numbers, and the page and
copied files land in --out."""

import json
from pathlib import Path

import pytest

from crater_synth.config import ConfigError
from crater_synth.evaluation.figure6 import CSV_FILE, write_results
from crater_synth.evaluation.paper_findings import (
    NOT_MEASURED,
    NOT_REPRODUCED,
    PAGE_FILE,
    REPRODUCED,
    camera_azimuth_not_monotonic,
    camera_elevation_gain,
    findings,
    large_roi_falls,
    loop_converges,
    publish,
    spearman,
    sun_elevation_rises,
    turns,
)

COUNTS = (2, 4, 6, 8, 10)
SIGMAS = (1.0, 1.2, 1.4)


def _rows(shape):
    """Figure 6 rows whose accuracy is ``shape(parameter, count, sigma, model)``."""
    return [
        {
            "parameter": p,
            "count": c,
            "sigma": s,
            "model": m,
            "real_accuracy": shape(p, c, s, m),
            "val_accuracy": 0.9,
            "train_images": 1000 * c,
            "seconds": 1.0,
            "config": "abc",
        }
        for p in ("sun_elevation", "sun_azimuth", "cam_elevation", "cam_azimuth")
        for c in COUNTS
        for s in SIGMAS
        for m in ("lunarnet_ex", "lunarsvm_ex")
    ]


def paper_like(p, c, s, m):
    if s == 1.4 and p != "cam_elevation":
        return 0.8 - 0.01 * c  # the widest crop falls as sampling rises
    if p == "sun_elevation":
        return 0.5 + 0.03 * c
    if p == "cam_elevation":
        return 0.75 + 0.00625 * (c - 2)  # +0.05 from 2 to 10
    if p == "cam_azimuth":
        return 0.7 + (0.05 if c in (4, 8) else 0.0)  # up, down, up, down
    return 0.7


def flat(p, c, s, m):
    return 0.7


def test_rank_correlation_and_turns():
    assert spearman([(2, 0.1), (4, 0.2), (6, 0.3)]) == pytest.approx(1.0)
    assert spearman([(2, 0.3), (4, 0.2), (6, 0.1)]) == pytest.approx(-1.0)
    assert spearman([(2, 0.5), (4, 0.5), (6, 0.5)]) == 0.0
    assert turns([(2, 0.5), (4, 0.6), (6, 0.5), (8, 0.6)]) == 2
    assert turns([(2, 0.5), (4, 0.505), (6, 0.5)]) == 0  # under the noise floor


def test_paper_like_numbers_reproduce_every_figure6_finding():
    rows = _rows(paper_like)
    for check in (sun_elevation_rises, large_roi_falls, camera_elevation_gain, camera_azimuth_not_monotonic):
        assert check(rows).verdict == REPRODUCED, check(rows)


def test_flat_numbers_reproduce_none_and_missing_numbers_are_not_measured():
    rows = _rows(flat)
    for check in (sun_elevation_rises, large_roi_falls, camera_elevation_gain, camera_azimuth_not_monotonic):
        assert check(rows).verdict == NOT_REPRODUCED
        assert check([]).verdict == NOT_MEASURED
    big = _rows(lambda p, c, s, m: 0.5 + 0.03 * c)  # +0.24 from 2 to 10 is not "about 5 %"
    assert camera_elevation_gain(big).verdict == NOT_REPRODUCED


def test_loop_verdict_reads_the_last_round():
    def hist(acc):
        rounds = [{"round": 0, "sun_elevation_count": 2, "images": 10, "lunarnet_ex": acc}]
        for r in rounds:
            r.update(lunarsvm_ex=0.5, hog_svm=0.4)
        return {"rounds": rounds, "stopped_because": "threshold reached"}

    assert loop_converges(hist(0.86)).verdict == REPRODUCED
    assert loop_converges(hist(0.65)).verdict == NOT_REPRODUCED
    assert loop_converges(None).verdict == NOT_MEASURED


def test_publish_copies_the_results_and_writes_the_page(tmp_path):
    exp, loop, out = tmp_path / "exp", tmp_path / "loop", tmp_path / "out"
    exp.mkdir()
    loop.mkdir()
    write_results(exp / CSV_FILE, _rows(paper_like))
    history = {
        "rounds": [
            {"round": 0, "sun_elevation_count": 2, "images": 9, "lunarnet_ex": 0.7, "lunarsvm_ex": 0.6, "hog_svm": 0.5}
        ],
        "stopped_because": "sun-elevation schedule exhausted",
    }
    (loop / "loop_history.json").write_text(json.dumps(history))
    found = publish(exp, loop, out)
    assert [f.verdict for f in found] == [REPRODUCED] * 4 + [NOT_REPRODUCED]
    assert found == findings(_rows(paper_like), history)
    page = (out / PAGE_FILE).read_text()
    assert "120 results" in page and "**does not reproduce**" in page
    assert (out / CSV_FILE).read_bytes() == (exp / CSV_FILE).read_bytes()
    assert (out / "figure6.png").stat().st_size > 10_000  # drawn from the CSV (the run dir has no figure)
    assert json.loads((out / "loop_history.json").read_text()) == history
    with pytest.raises(ConfigError, match="experiments.csv does not exist"):
        publish(tmp_path / "nowhere", None, out)
    # A corrupt loop history is refused before anything is written: out keeps the last good results.
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    (loop / "loop_history.json").write_text("{not json")
    write_results(exp / CSV_FILE, _rows(flat))
    with pytest.raises(ConfigError, match="corrupt loop history"):
        publish(exp, loop, out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_published_figure6_csv_is_resumable_with_todays_configuration():
    """docs/results/experiments.csv was made with the overrides in docs/results/notes.md; its `config`
    fingerprint must still be what today's configuration gives for them, or `make experiments` would
    refuse to continue it (settings added later are neutral at their defaults: validate.NEUTRAL_LATER_KEYS).
    A change that really alters the training must fail here, and the published results be redone."""
    import csv

    from crater_synth.config import compose, resolved
    from crater_synth.evaluation.figure6 import experiments_fingerprint

    csv_path = Path(__file__).resolve().parent.parent / "docs" / "results" / "experiments.csv"
    published = {row["config"] for row in csv.DictReader(csv_path.open())}
    overrides = ["sweep=paper", "train=paper_budget", "run_dir=outputs/paper_fig6", "train.progress=false"]
    assert published == {experiments_fingerprint(resolved(compose(overrides)))}
    changed = experiments_fingerprint(resolved(compose(overrides + ["train.preprocess.support=disc"])))
    assert changed not in published
