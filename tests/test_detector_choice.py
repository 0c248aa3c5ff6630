"""tools.detector_choice: the rule that picks a learned model and threshold on the south validation windows."""

from crater_synth.tools.detector_choice import POLE, SPLIT, choose, f1


def _run(model, t, p, r):
    cat = {"precision_15km": p, "recall_15km": r, "f1": f1(p, r)}
    return {"model": model, "threshold": t, "catalogue_15km": cat, "model_sha256": f"sha of {model}"}


def test_f1_and_the_choice_rule():
    assert f1(0.9, 0.5) == round(2 * 0.45 / 1.4, 4) and f1(0.0, 0.5) == 0.0 and f1(None, 0.5) is None
    runs = [_run("committed", 0.3, 0.91, 0.38), _run("a.pt", 0.3, 0.7, 0.7), _run("a.pt", 0.4, 0.8, 0.6)]
    runs.append(_run("b.pt", 0.2, None, None))  # no detection of D >= 15 km: never chosen
    assert choose(runs)["model"] == "a.pt" and choose(runs)["threshold"] == 0.3
    assert choose(runs)["model_sha256"] == "sha of a.pt"  # what the north test checks its model against
    tie = [_run("x", 0.2, 0.6, 0.8), _run("y", 0.3, 0.8, 0.6)]  # same F1: the more precise
    assert choose(tie)["model"] == "y"
    assert (POLE, SPLIT) == ("south", "validation")  # never the north test, nor the spent south test


def test_a_variant_adds_its_overrides_to_every_run_and_the_choice_keeps_them():
    from crater_synth.tools.detector_choice import detector_overrides

    assert detector_overrides("committed", 0.2, ("nav.detector.tta=4",)) == [
        "nav/detector=learned-detect",
        "nav.detector.threshold=0.2",
        "nav.detector.tta=4",
    ]
    assert detector_overrides("fcos:f.pt", 0.4)[-1] == "nav.detector.model=f.pt"
    runs = [_run("a.pt", 0.2, 0.8, 0.5) | {"variant": ["nav.detector.tta=4"]}, _run("a.pt", 0.2, 0.8, 0.4)]
    assert choose(runs)["variant"] == ["nav.detector.tta=4"]
