"""Closed-loop bookkeeping: only new renders per round, stop conditions, resume after interruption.

Rendering is real (tiny Cycles renders through the Blender worker); training is replaced by a
scripted accuracy per round, because the bookkeeping, not the classifier, is under test here.
"""

import json

import pytest

from crater_synth.config import compose
from crater_synth.evaluation import closed_loop as loop_mod

TINY = [
    "crater=shackleton",
    "sweep=smoke",
    "sweep.sun_elevation.values=null",
    "sweep.sun_azimuth.count=1",
    "sweep.cam_azimuth.count=1",
    "terrain.near_vertices=48",
    "terrain.far_radius_km=0",
    "terrain.detail.enabled=false",
    "render.samples=1",
    "render.shadow_map_px=96",
    "render.roi_min_px=24",
]


@pytest.fixture()
def scripted_training(monkeypatch):
    """Replace training by accuracies read from a script; record the grids it was asked to train on."""
    calls = []

    def fake_train_and_evaluate(settings, progress=None):
        n_sun = len(settings.train.select["sun_elevation"])
        calls.append(n_sun)
        acc = fake_train_and_evaluate.accuracy[n_sun]
        return {"train_images": n_sun, **{m: {"real_accuracy": acc, "val_accuracy": 0.9} for m in loop_mod.MODELS}}

    monkeypatch.setattr(loop_mod, "train_and_evaluate", fake_train_and_evaluate)
    fake_train_and_evaluate.calls = calls
    return fake_train_and_evaluate


def run(tmp_path, *extra):
    cfg = compose(TINY + [f"data_dir={tmp_path}/data", f"out_dir={tmp_path}/ds", f"run_dir={tmp_path}/run", *extra])
    return loop_mod.run_loop(cfg, progress=False)


@pytest.mark.integration
def test_loop_renders_only_new_samples_and_stops_at_threshold(tmp_path, scripted_training):
    scripted_training.accuracy = {1: 0.5, 2: 0.7, 3: 0.9, 4: 0.95}
    hist = run(tmp_path, "loop.sun_elevation_schedule=[1,2,3,4]", "loop.threshold=0.85")
    rounds = hist["rounds"]
    assert [r["sun_elevation_count"] for r in rounds] == [1, 2, 3]  # stops once 0.9 >= 0.85
    assert [r["renders_new"] for r in rounds] == [1, 1, 1]  # one new sun elevation per round
    assert [r["renders_reused"] for r in rounds] == [0, 1, 2]
    assert hist["stopped_because"] == "threshold reached"
    assert (tmp_path / "run" / "loop_history.png").is_file()
    assert json.loads((tmp_path / "run" / "loop_history.json").read_text())["rounds"] == rounds


def test_loop_exhausts_schedule_and_resumes_after_last_round(tmp_path, scripted_training):
    scripted_training.accuracy = {1: 0.2, 2: 0.3, 3: 0.4}
    hist = run(tmp_path, "loop.sun_elevation_schedule=[1,2]")
    assert hist["stopped_because"] == "sun-elevation schedule exhausted"
    assert scripted_training.calls == [1, 2]
    # A longer schedule on the same run directory continues after the finished rounds.
    with pytest.raises(Exception, match="schedule"):
        run(tmp_path, "loop.sun_elevation_schedule=[1,2,3]")  # another schedule: refused, not mixed
    history = tmp_path / "run" / "loop_history.json"
    hist_data = json.loads(history.read_text())
    hist_data["rounds"] = hist_data["rounds"][:1]  # as if interrupted during round 1
    history.write_text(json.dumps(hist_data))
    hist = run(tmp_path, "loop.sun_elevation_schedule=[1,2]")
    assert scripted_training.calls == [1, 2, 2]  # round 0 not redone
    assert [r["renders_new"] for r in hist["rounds"]] == [1, 0]  # round 1's render already existed


def test_bad_loop_settings_are_refused(tmp_path, scripted_training):
    from crater_synth.config import ConfigError

    with pytest.raises(ConfigError, match="threshold"):
        run(tmp_path, "loop.threshold=1.5")
    with pytest.raises(ConfigError, match="increasing"):
        run(tmp_path, "loop.sun_elevation_schedule=[4,2]")


def test_rounds_take_prefixes_of_explicit_sun_elevations(tmp_path):
    """With explicit positions (e.g. physical fractions) round k trains on the first counts of them,
    so rounds stay nested and only the new renders are added."""
    from crater_synth.config import resolved

    cfg = compose(
        TINY
        + ["sweep.sun_model=physical", "sweep.sun_elevation.values=[0.25,0.5,0.75,1.0]", f"data_dir={tmp_path}/data"]
    )
    sel = [
        resolved(loop_mod.round_config(cfg, n, tmp_path / f"r{n}"))["train"]["select"]["sun_elevation"] for n in (2, 4)
    ]
    assert sel == [[0.25, 0.5], [0.25, 0.5, 0.75, 1.0]]
    from crater_synth.config import ConfigError

    with pytest.raises(ConfigError, match="only 4"):
        loop_mod.round_config(cfg, 5, tmp_path / "r5")
