"""Fidelity ablation bookkeeping (crater_synth.evaluation.ablation): variants, shared renders, generated docs."""

from __future__ import annotations

import pytest

from crater_synth.config import ConfigError, compose, resolved
from crater_synth.evaluation import ablation as ab


def test_variants_are_the_baseline_the_reference_then_one_lever_off_each():
    acfg = {"levers": {"a": {"when_off": ["x=1"], "why": "physics"}, "b": {"when_off": ["y=2", "z=3"]}}}
    v = ab.plan_variants(acfg)
    assert [x["name"] for x in v] == ["all levers on", "all levers off", "a off", "b off"]
    assert v[0]["overrides"] == [] and v[3]["overrides"] == ["y=2", "z=3"]
    assert v[1]["overrides"] == v[2]["overrides"] + v[3]["overrides"]
    assert [x["name"] for x in ab.plan_variants({"levers": {"a": {"when_off": ["x=1"]}}})] == ["all levers on", "a off"]
    with pytest.raises(ConfigError, match="empty"):
        ab.plan_variants({"levers": {}})
    with pytest.raises(ConfigError, match="levers.a.when_off"):
        ab.plan_variants({"levers": {"a": {"why": "no overrides"}}})


def test_training_only_levers_share_renders_and_pixel_settings_do_not():
    base = resolved(compose(["sweep=demo"]))
    sensor_off = resolved(compose(["sweep=demo", "sensor=wac_mosaic", "train.max_epochs=3"]))
    physical = resolved(compose(["sweep=demo", "sweep.sun_model=physical", "sweep.sun_elevation.values=[0.5,1.0]"]))
    workers = resolved(compose(["sweep=demo", "render.workers=1"]))
    assert ab.render_key(base) == ab.render_key(sensor_off) == ab.render_key(workers)
    assert ab.render_key(base) != ab.render_key(physical)


def test_generated_table_replaces_only_the_marked_section(tmp_path):
    doc = tmp_path / "fidelity.md"
    doc.write_text(f"# Fidelity\n\nintro\n\n{ab.BEGIN}\nold table\n{ab.END}\n\nafter\n")
    summary = {
        "groups": {
            "validation1-a+b": {"role": "validation", "models": {"lunarnet_ex": {"per_crater": {"a": 0.5, "b": 0.7}}}}
        },
        "validation_mean": {"lunarnet_ex": 0.6, "lunarsvm_ex": 0.55},
        "test_mean": {"lunarnet_ex": None, "lunarsvm_ex": None},
    }
    results = [{"variant": "all levers on", "lever": None, "renders": {"validation1-a+b": 10}, "summary": summary}]
    ab._write(tmp_path, results, {"docs_file": str(doc)}, ["train.max_epochs=2"])
    text = doc.read_text()
    assert "old table" not in text and "intro" in text and "after" in text
    assert "| all levers on | 0.600 | n/a | 0.550 | n/a | a 0.50 b 0.70 | 10 |" in text
    assert (tmp_path / ab.TABLE_FILE).is_file() and (tmp_path / ab.RESULTS_FILE).is_file()
    # With held-out groups, their means get columns of their own and their craters are marked.
    held = dict(summary, holdout_mean={"lunarnet_ex": 0.9, "lunarsvm_ex": 0.8})
    held["groups"] = dict(
        summary["groups"],
        **{"holdout1-c+d": {"role": "holdout", "models": {"lunarnet_ex": {"per_crater": {"c": 1.0, "d": 0.8}}}}},
    )
    table = ab.table_markdown(results + [dict(results[0], variant="x off", summary=held)], [])
    assert "LunarNet_ex held-out" in table
    assert "| all levers on | 0.600 | n/a | n/a | 0.550 | n/a | n/a | a 0.50 b 0.70 | 10 |" in table
    assert "| x off | 0.600 | 0.900 | n/a | 0.550 | 0.800 | n/a | a 0.50 b 0.70; **held-out** c 1.00 d 0.80 |" in table
    doc.write_text("no markers")
    with pytest.raises(ConfigError, match="markers"):
        ab._write(tmp_path, results, {"docs_file": str(doc)}, [])


def test_an_evaluation_only_lever_starts_from_the_baselines_models(tmp_path):
    """A lever that changes only evaluation settings (train.tta_rotations) gets a copy of the baseline's
    finished runs, which the protocol then evaluates again instead of training; a variant that already
    has runs keeps them."""
    from crater_synth.evaluation.validation import RESULTS_FILE, evaluation_only

    assert evaluation_only(["train.tta_rotations=1"]) and not evaluation_only(["train.augment_offset_frac=0.0"])
    src = tmp_path / "baseline"
    (src / "g" / "seed0").mkdir(parents=True)
    (src / "g" / "seed0" / "lunarnet_ex.pt").write_bytes(b"model")
    ab._seed_from_baseline(src, tmp_path / "early")  # no finished baseline yet: nothing to copy
    assert not (tmp_path / "early").exists()
    (src / RESULTS_FILE).write_text("{}")
    ab._seed_from_baseline(src, tmp_path / "roll_averaging")
    assert (tmp_path / "roll_averaging" / "g" / "seed0" / "lunarnet_ex.pt").read_bytes() == b"model"
    (src / "g" / "seed0" / "lunarnet_ex.pt").write_bytes(b"retrained")
    ab._seed_from_baseline(src, tmp_path / "roll_averaging")
    assert (tmp_path / "roll_averaging" / "g" / "seed0" / "lunarnet_ex.pt").read_bytes() == b"model"
    assert not list(tmp_path.glob(".*.tmp"))
    # Runs the baseline gained later (held-out groups) are added; the variant's own runs stay.
    import json

    (src / "h" / "seed0").mkdir(parents=True)
    (src / "h" / "seed0" / "lunarnet_ex.pt").write_bytes(b"held")
    runs = [{"group": "g", "seed": 0, "tag": "baseline"}, {"group": "h", "seed": 0, "tag": "baseline"}]
    (src / RESULTS_FILE).write_text(json.dumps({"runs": runs}))
    dst = tmp_path / "roll_averaging"
    (dst / RESULTS_FILE).write_text(json.dumps({"runs": [{"group": "g", "seed": 0, "tag": "own"}]}))
    ab._seed_from_baseline(src, dst)
    assert (dst / "h" / "seed0" / "lunarnet_ex.pt").read_bytes() == b"held"
    assert (dst / "g" / "seed0" / "lunarnet_ex.pt").read_bytes() == b"model"
    got = json.loads((dst / RESULTS_FILE).read_text())["runs"]
    assert sorted((r["group"], r["tag"]) for r in got) == [("g", "own"), ("h", "baseline")]
    assert not list(dst.glob("*/.*.tmp"))
