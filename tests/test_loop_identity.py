"""A closed loop reuses a finished round only when the round's identity (its dataset and training
settings) is this run's; otherwise it refuses in one line naming the first setting that differs.

Rendering and training are replaced by fakes that count their calls: the reuse decision, not the
renderer or the classifier, is under test, so every test runs in well under a second.
"""

import json

import pytest
from click.testing import CliRunner

from crater_core.typed_config import as_plain
from crater_synth.config import ConfigError, compose, settings_from
from crater_synth.evaluation import closed_loop as loop_mod

BASE = ["crater=shackleton", "sweep=smoke", "sweep.sun_elevation.values=null", "loop.sun_elevation_schedule=[1,2]"]


@pytest.fixture()
def fakes(monkeypatch):
    """Rendering and training that only count their calls (by the round's sun-elevation count)."""
    calls = []

    def fake_build_dataset(settings, progress=None):
        calls.append(("render", settings.sweep.sun_elevation.count))
        return {"rendered": 1, "skipped_existing": 0}

    def fake_train_and_evaluate(settings, progress=None):
        n_sun = len(settings.train.select["sun_elevation"])
        calls.append(("train", n_sun))
        return {"train_images": n_sun, **{m: {"real_accuracy": 0.1, "val_accuracy": 0.9} for m in loop_mod.MODELS}}

    monkeypatch.setattr(loop_mod, "build_dataset", fake_build_dataset)
    monkeypatch.setattr(loop_mod, "train_and_evaluate", fake_train_and_evaluate)
    monkeypatch.setattr(loop_mod, "plot_history", lambda hist, png: None)
    return calls


def _args(tmp_path, *extra):
    return [*BASE, f"data_dir={tmp_path}/data", f"out_dir={tmp_path}/ds", f"run_dir={tmp_path}/run", *extra]


def run(tmp_path, *extra, **kw):
    return loop_mod.run_loop(compose(_args(tmp_path, *extra)), progress=False, **kw)


def _one_error(tmp_path, *extra) -> str:
    """The CLI's answer to a refused rerun: exit 2 and exactly one error line."""
    from crater_synth.cli import main

    res = CliRunner().invoke(main, ["loop", *_args(tmp_path, *extra)], catch_exceptions=False)
    assert res.exit_code == 2, res.output
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), res.output
    return lines[0]


def test_same_settings_reuse_every_round(tmp_path, fakes):
    first = run(tmp_path)
    assert fakes == [("render", 1), ("train", 1), ("render", 2), ("train", 2)]
    # Settings that cannot change a round's result are not in its identity.
    again = run(tmp_path, "train.progress=false", "render.workers=3", "train.num_threads=1", "loop.threshold=0.5")
    assert len(fakes) == 4, fakes  # nothing rendered or trained again
    assert again["rounds"] == first["rounds"]
    for k, r in enumerate(first["rounds"]):
        recorded = json.loads(
            (tmp_path / "run" / "rounds" / f"round{k}-sun{k + 1}" / loop_mod.IDENTITY_FILE).read_text()
        )
        assert r["identity"] == recorded["identity"] == loop_mod.content_key(recorded["settings"])


@pytest.mark.parametrize(
    "change, needle",
    [
        ("train.max_epochs=7", "train.max_epochs="),  # a training setting
        ("render.samples=3", "render.samples="),  # a dataset setting
        ("model.dropout=0.25", "model.dropout="),  # a model setting
    ],
)
def test_a_changed_setting_is_refused_in_one_line_naming_it(tmp_path, fakes, change, needle):
    run(tmp_path)
    history = (tmp_path / "run" / loop_mod.HISTORY_FILE).read_bytes()
    line = _one_error(tmp_path, change)
    assert needle in line and "round 0" in line and "--restart" in line and "another run_dir" in line, line
    assert len(fakes) == 4, fakes  # refused before anything ran
    assert (tmp_path / "run" / loop_mod.HISTORY_FILE).read_bytes() == history  # and nothing was touched


def test_restart_moves_the_old_rounds_aside_and_runs_again(tmp_path, fakes):
    run(tmp_path)
    hist = run(tmp_path, "train.max_epochs=7", fresh=True)
    assert len(fakes) == 8 and len(hist["rounds"]) == 2
    (kept,) = (tmp_path / "run" / "previous").iterdir()  # the old loop, whole, not deleted
    assert (kept / loop_mod.HISTORY_FILE).is_file() and (kept / "rounds" / "round1-sun2").is_dir()
    assert (
        json.loads((kept / loop_mod.HISTORY_FILE).read_text())["rounds"][0]["identity"] != hist["rounds"][0]["identity"]
    )
    run(tmp_path, "train.max_epochs=7")  # the new rounds are reused
    assert len(fakes) == 8


def test_rounds_without_an_identity_are_refused_unless_adopted(tmp_path, fakes):
    run(tmp_path)
    path = tmp_path / "run" / loop_mod.HISTORY_FILE
    hist = json.loads(path.read_text())
    for r in hist["rounds"]:  # as a loop wrote them before rounds had an identity
        del r["identity"]
    path.write_text(json.dumps(hist))
    line = _one_error(tmp_path)
    assert "round 0" in line and "--adopt-rounds" in line and "--restart" in line, line
    with pytest.raises(ConfigError, match="round 0"):
        run(tmp_path)
    run(tmp_path, adopt=True)
    assert len(fakes) == 4  # adopted, not redone
    assert all(r["identity"] for r in json.loads(path.read_text())["rounds"])
    with pytest.raises(ConfigError, match="train.max_epochs"):
        run(tmp_path, "train.max_epochs=7")  # adopted rounds are checked like any other


def test_round_identity_holds_every_setting_but_the_listed_ones(tmp_path):
    """Derived, not listed: every leaf of a round's settings is in its identity except the keys of
    ROUND_IGNORED (each of which exists), so a setting added later is in it from the start."""
    s = settings_from(loop_mod.round_config(compose(_args(tmp_path)), 2, tmp_path / "r"))
    plain = dict(loop_mod._leaves(json.loads(json.dumps(as_plain(s), default=str))))

    def ignored(key):
        return any(key == i or key.startswith(i + ".") for i in loop_mod.ROUND_IGNORED)

    for key in loop_mod.ROUND_IGNORED:
        assert any(k == key or k.startswith(key + ".") for k in plain), f"ROUND_IGNORED lists {key}, not a setting"
    payload = dict(loop_mod._leaves(loop_mod.round_identity_payload(s)))
    assert payload == {k: v for k, v in plain.items() if not ignored(k)}
    for key in ("train.select.sun_elevation", "train.seed", "sensor.enabled", "realset.seed", "crater.shackleton.lat"):
        assert key in payload, key
