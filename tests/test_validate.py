"""The real validation protocol's bookkeeping (crater_synth.evaluation.validation): groups, means, resume, table.

Rendering and training are replaced by scripted results: what is under test is which groups are
trained, that the test group is reported apart and never averaged into the validation mean, and that
finished runs are not redone.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from crater_synth.config import ConfigError
from crater_synth.evaluation import validation as v
from train.trainer import HOG_FILE, NET_FILE, SVM_FILE

CATALOGUE = ["a1", "a2", "a3", "b1", "b2", "b3", "h1", "h2", "h3", "t1", "t2", "t3", "n1", "n2", "n3", "s1"]
NORTH = ("n1", "n2", "n3")  # the scripted catalogue's north-polar craters (lat 88 N; the others 88 S)


def test_groups_must_be_disjoint_known_and_apart_from_the_test_craters():
    ok = v.plan_groups({"groups": [["a1", "a2", "a3"], ["b1", "b2", "b3"]], "test": ["t1", "t2", "t3"]}, CATALOGUE)
    assert [g.label for g in ok] == ["validation1-a1+a2+a3", "validation2-b1+b2+b3", "test-t1+t2+t3"]
    assert ok[0].crater_override() == "crater=[a1,a2,a3]"
    bad = [
        ({"groups": [["a1", "a2", "a3"]], "test": ["t1", "t2"]}, "at least two validation groups"),
        ({"groups": [["a1", "a2", "a3"], ["a3", "b1", "b2"]], "test": ["t1", "t2"]}, "disjoint"),
        ({"groups": [["a1", "a2", "t1"], ["b1", "b2", "b3"]], "test": ["t1", "t2"]}, "test crater"),
        ({"groups": [["a1", "zz", "a3"], ["b1", "b2", "b3"]], "test": ["t1", "t2"]}, "unknown crater 'zz'"),
        ({"groups": [["a1"], ["b1", "b2", "b3"]], "test": ["t1", "t2"]}, "at least two distinct"),
        # Held-out groups obey the same rules, and share no crater with a validation group.
        ({"groups": [["a1", "a2"], ["b1", "b2"]], "holdout": [["h1", "a2"]], "test": ["t1", "t2"]}, "already in"),
        ({"groups": [["a1", "a2"], ["b1", "b2"]], "holdout": [["h1", "t2"]], "test": ["t1", "t2"]}, "test crater"),
        ({"groups": [["a1", "a2"], ["b1", "b2"]], "holdout": [["h1"]], "test": ["t1", "t2"]}, "at least two"),
        ({"groups": [["a1", "a2"], ["b1", "b2"]], "holdout": [["h1", "zz"]], "test": []}, "holdout.0.*'zz'"),
    ]
    for cfg, msg in bad:
        with pytest.raises(ConfigError, match=msg):
            v.plan_groups(cfg, CATALOGUE)


def test_holdout_groups_come_between_validation_and_test():
    cfg = {"groups": [["a1", "a2"], ["b1", "b2"]], "holdout": [["h1", "h2", "h3"]], "test": ["t1", "t2"]}
    groups = v.plan_groups(cfg, CATALOGUE)
    assert [g.label for g in groups] == ["validation1-a1+a2", "validation2-b1+b2", "holdout1-h1+h2+h3", "test-t1+t2"]


def test_the_holdout_config_holds_out_the_rest_of_the_catalogue():
    from crater_synth.config import compose, resolved

    vcfg = resolved(compose(["validate=holdout"]))["validate"]
    groups = v.plan_groups(vcfg, v.catalogue_names())  # disjoint, known, none a test crater
    held = [g for g in groups if g.role == "holdout"]
    assert len(held) >= 2 and all(len(g.craters) == 3 for g in held)
    used = {c for g in groups for c in g.craters}
    south = {n for n in v.catalogue_names() if not n.startswith("_")} - set(_north_catalogue())
    assert used == south  # every south catalogue crater has exactly one role
    assert resolved(compose([]))["validate"]["holdout"] == []  # the plain protocol trains no held-out group


def _north_catalogue() -> list[str]:
    """The north catalogue entries, from the pole outwards."""
    from crater_synth.config import compose, craters

    entries = craters(compose([f"crater=[{','.join(v.catalogue_names())}]"]))
    return [c["name"] for c in sorted(entries, key=lambda c: -c["lat"]) if c["lat"] > 0]


def test_the_north_holdout_triples_follow_their_rule():
    """validate=holdout_north: the north catalogue from the pole outwards, three by three (a remainder of
    fewer than three left out), held out only, each group with the north DEM and mosaic."""
    from crater_synth.config import compose, resolved

    vcfg = resolved(compose(["validate=holdout_north"]))["validate"]
    groups = v.plan_groups(vcfg, v.catalogue_names())
    north = _north_catalogue()
    held = [list(g.craters) for g in groups if g.role == "holdout"]
    assert held == [north[i : i + 3] for i in range(0, len(north) - len(north) % 3, 3)]
    assert len(held) >= 5
    assert vcfg["roles"] == ["holdout"]  # the chosen settings are not chosen again here
    assert "dem=lola_ldem256_north" in vcfg["north_overrides"] and "realset=wac_north" in vcfg["north_overrides"]
    # The validation groups and the test are the south's: no north crater ever chooses a setting.
    assert not {c for g in groups if g.role != "holdout" for c in g.craters} & set(north)


def test_north_groups_run_with_the_north_dem_and_mosaic_and_only_the_roles_asked(scripted, tmp_path):
    ovr = scripted.overrides + [
        "validate.holdout=[[n1,n2,n3]]",
        "validate.roles=[holdout]",
        "validate.north_overrides=['dem=lola_ldem256_north','realset=wac_north']",
        "dem.stack=[]",
    ]
    res = v.run_validation(ovr, progress=False)
    assert [c[0] for c in scripted.calls] == [("n1", "n2", "n3")] * 2  # only the held-out group, 2 seeds
    assert scripted.products[("n1", "n2", "n3")] == ("lola_ldem256_north", "lroc_wac_north")
    assert res["summary"]["validation_mean"]["lunarnet_ex"] is None
    assert v.means_line(res["summary"], "lunarnet_ex").startswith("held-out mean")
    # South groups keep the configuration's DEM and mosaic.
    v.run_validation(ovr[:-3] + ["validate.roles=[validation]"], progress=False)
    assert scripted.products[("a1", "a2", "a3")] == ("lola_ldem256_south", "lroc_wac_south")


def test_a_group_mixing_the_hemispheres_is_refused(scripted):
    with pytest.raises(ConfigError, match="mixes north- and south-polar"):
        v.run_validation(scripted.overrides + ["validate.holdout=[[n1,n2,s1]]"], progress=False)


def test_default_groups_are_catalogue_craters_and_not_the_papers():
    from crater_synth.config import compose, resolved

    vcfg = resolved(compose([]))["validate"]
    groups = v.plan_groups(vcfg, v.catalogue_names())
    assert sum(g.role == "validation" for g in groups) >= 2
    assert all(len(g.craters) == 3 for g in groups)
    assert groups[-1].role == "test" and set(groups[-1].craters) == {"shackleton", "de_gerlache", "shoemaker"}


@pytest.fixture()
def scripted(monkeypatch, tmp_path):
    """build_dataset -> counts only; train_and_evaluate -> per-crater accuracies from a table."""
    calls = []

    def fake_build(settings, progress=True):
        return {"renders_total": 10 * len(settings.crater), "rendered": 0, "skipped_existing": 0}

    def fake_train(settings, progress=None):
        names = [c.name for c in settings.craters]
        calls.append((tuple(names), settings.train.seed))
        scripted.products[tuple(names)] = (settings.dem.product, settings.realset.source_product)
        run_dir = Path(settings.run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        for f in (NET_FILE, SVM_FILE, HOG_FILE):  # the saved models, as train_all writes them
            (run_dir / f).write_bytes(b"model")
        return fake_evaluate(settings)

    def fake_evaluate(settings, progress=None):
        names = [c.name for c in settings.craters]
        seed = settings.train.seed
        per = {n: scripted.acc[n] + 0.01 * seed + 0.1 * (settings.train.tta_rotations > 1) for n in names}
        mean = sum(per.values()) / len(per)
        return {
            "train_images": 100,
            **{
                m: {"real_accuracy": mean, "val_accuracy": 0.95, "per_crater": per, "confusion": [[1]]}
                for m in v.REPORTED_MODELS
            },
        }

    monkeypatch.setattr(v, "build_dataset", fake_build)
    monkeypatch.setattr(v, "train_and_evaluate", fake_train)
    monkeypatch.setattr(v, "evaluate_saved", fake_evaluate)
    monkeypatch.setattr(v, "catalogue_names", lambda: CATALOGUE)
    # Hydra needs real crater configs: give the protocol plain entries for the scripted names.
    from crater_synth import config as config_mod

    real_compose = config_mod.compose

    def compose(overrides):
        crater = next((o for o in overrides if o.startswith("crater=")), None)
        base = [o for o in overrides if not o.startswith("crater=")]
        cfg = real_compose(
            base + ["crater=custom", "crater.custom.lat=-88", "crater.custom.lon=0", "crater.custom.diameter_km=20"]
        )
        if crater:
            from omegaconf import OmegaConf

            names = crater[len("crater=[") : -1].split(",")
            cfg = OmegaConf.create(config_mod.resolved(cfg))  # untyped copy: the schema types crater entries
            cfg.crater = {
                n: {"name": n, "lat": 88.0 if n in NORTH else -88.0, "lon": 0.0, "diameter_km": 20.0, "source": "test"}
                for n in names
            }
        return cfg

    monkeypatch.setattr(v, "compose", compose)

    def compose_settings(overrides):
        cfg = compose(overrides)
        return cfg, config_mod.settings_from(cfg)

    monkeypatch.setattr(v, "compose_settings", compose_settings)
    scripted.acc = {n: 0.5 + 0.04 * i for i, n in enumerate(CATALOGUE)}
    scripted.calls = calls
    scripted.products = {}
    scripted.overrides = [
        "validate.groups=[[a1,a2,a3],[b1,b2,b3]]",
        "validate.test=[t1,t2,t3]",
        "validate.seeds=[0,1]",
        f"validate.out_dir={tmp_path}/val",
    ]
    return scripted


@pytest.mark.integration
def test_protocol_trains_every_group_and_seed_and_reports_test_apart(scripted, tmp_path):
    res = v.run_validation(scripted.overrides, progress=False)
    assert len(scripted.calls) == 6  # 3 groups x 2 seeds
    s = res["summary"]
    acc = scripted.acc
    val_mean = ((acc["a1"] + acc["a2"] + acc["a3"]) / 3 + (acc["b1"] + acc["b2"] + acc["b3"]) / 3) / 2 + 0.005
    test_mean = (acc["t1"] + acc["t2"] + acc["t3"]) / 3 + 0.005
    assert s["validation_mean"]["lunarnet_ex"] == pytest.approx(val_mean)
    assert s["test_mean"]["lunarnet_ex"] == pytest.approx(test_mean)
    assert s["groups"]["test-t1+t2+t3"]["models"]["lunarnet_ex"]["std_over_seeds"] == pytest.approx(0.005)
    table = (tmp_path / "val" / v.TABLE_FILE).read_text()
    assert "validation mean" in table and "test-t1+t2+t3" in table
    rows = (tmp_path / "val" / v.CSV_FILE).read_text().splitlines()
    assert len(rows) == 1 + 6 * 3 * 3  # header + runs x models x craters
    saved = json.loads((tmp_path / "val" / v.RESULTS_FILE).read_text())
    assert saved["summary"] == json.loads(json.dumps(s))
    # A rerun with the same configuration redoes nothing; a changed setting redoes everything.
    v.run_validation(scripted.overrides, progress=False)
    assert len(scripted.calls) == 6
    v.run_validation(scripted.overrides + ["train.lr=0.002"], progress=False)
    assert len(scripted.calls) == 12


@pytest.mark.integration
def test_holdout_groups_are_reported_apart_and_never_averaged_into_the_validation_mean(scripted, tmp_path):
    plain = v.run_validation(scripted.overrides, progress=False)
    assert plain["summary"]["holdout_mean"]["lunarnet_ex"] is None
    assert "held-out mean" not in (tmp_path / "val" / v.TABLE_FILE).read_text()
    res = v.run_validation(scripted.overrides + ["validate.holdout=[[h1,h2,h3]]"], progress=False)
    assert len(scripted.calls) == 6 + 2  # only the held-out group trains (2 seeds); the rest is reused
    s, acc = res["summary"], scripted.acc
    assert s["validation_mean"] == plain["summary"]["validation_mean"]
    assert s["test_mean"] == plain["summary"]["test_mean"]
    assert s["holdout_mean"]["lunarnet_ex"] == pytest.approx((acc["h1"] + acc["h2"] + acc["h3"]) / 3 + 0.005)
    table = (tmp_path / "val" / v.TABLE_FILE).read_text()
    assert "holdout1-h1+h2+h3" in table and "held-out mean" in table
    assert "holdout" in (tmp_path / "val" / v.CSV_FILE).read_text()


@pytest.mark.integration
def test_an_evaluation_only_change_evaluates_the_saved_models_again(scripted, tmp_path):
    """Changing only how the models are evaluated (train.tta_rotations) re-evaluates every finished run
    without training it again; the numbers are the new evaluation's."""
    base = scripted.overrides + ["train=sim2real", "train.tta_rotations=1"]
    first = v.run_validation(base, progress=False)
    assert len(scripted.calls) == 6
    again = v.run_validation(base + ["train.tta_rotations=8"], progress=False)
    assert len(scripted.calls) == 6  # nothing trained again
    assert again["summary"]["validation_mean"]["lunarnet_ex"] == pytest.approx(
        first["summary"]["validation_mean"]["lunarnet_ex"] + 0.1
    )
    assert all("evaluate_only_s" in r for r in again["runs"])
    assert {r["training_fingerprint"] for r in again["runs"]} == {r["training_fingerprint"] for r in first["runs"]}
    assert {r["fingerprint"] for r in again["runs"]}.isdisjoint({r["fingerprint"] for r in first["runs"]})
    # Records written before training fingerprints existed (tta_rotations at its neutral 1) are
    # re-evaluated the same way.
    v.run_validation(base, progress=False)
    saved = json.loads((tmp_path / "val" / v.RESULTS_FILE).read_text())
    for r in saved["runs"]:
        del r["training_fingerprint"]
    (tmp_path / "val" / v.RESULTS_FILE).write_text(json.dumps(saved))
    v.run_validation(base + ["train.tta_rotations=4"], progress=False)
    assert len(scripted.calls) == 6
    # Without the saved models there is nothing to evaluate: the run trains again.
    (tmp_path / "val" / "validation1-a1+a2+a3" / "seed0" / NET_FILE).unlink()
    v.run_validation(base, progress=False)
    assert len(scripted.calls) == 7
    assert v.evaluation_only(["train.tta_rotations=1"]) and not v.evaluation_only(["train.tta_rotations=1", "seed=2"])
    assert not v.evaluation_only([])


def test_protocol_refuses_overrides_it_owns(scripted):
    for o in ("crater=[t1,t2]", "run_dir=/tmp/x", "train.seed=3"):
        with pytest.raises(ConfigError, match="sets"):
            v.run_validation(scripted.overrides + [o], progress=False)
