"""A tiny end-to-end `crater-synth train` / `evaluate` on a procedural dataset, the benchmark
function, and one-line errors for bad input."""

import json

import pytest
import torch
from click.testing import CliRunner

from crater_synth.config import compose, resolved
from train.toydata import write_toy_dataset

torch.set_num_threads(1)
MODELS = ("lunarnet_ex", "lunarsvm_ex", "hog_svm")


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    d = tmp_path_factory.mktemp("toy_e2e")
    write_toy_dataset(d, sun_elevations=(15.0, 30.0), sun_azimuths=(0.0, 120.0, 240.0), cam_elevations=(90.0,),
                      cam_azimuths=(0.0, 90.0, 180.0, 270.0), rim_px=40.0)
    return d


def _overrides(toy, tmp, *extra):
    return [f"train.dataset_dir={toy}", f"data_dir={tmp}", f"run_dir={tmp}/run", f"train.cache_dir={tmp}/cache",
            "train.num_threads=1", "train.progress=false", "train.max_epochs=3", "train.batch_size=32",
            "realset.per_crater=15", "train.hog.max_train_images=60", *extra]


def _cli():
    from crater_synth.cli import main

    return main


def test_train_then_evaluate_writes_valid_metrics(toy, tmp_path):
    runner = CliRunner()
    res = runner.invoke(_cli(), ["train", *_overrides(toy, tmp_path)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert "one real observation per crater" in res.output
    run = tmp_path / "run"
    m = json.loads((run / "metrics.json").read_text())
    for name in MODELS:
        r = m[name]
        assert 0.0 <= r["real_accuracy"] <= 1.0 and 0.0 <= r["val_accuracy"] <= 1.0
        assert set(r["per_crater"]) == {"shackleton", "de_gerlache", "shoemaker"}
        assert set(r["per_sigma"]) == {"1.0", "1.2", "1.4"} and set(r["per_source"]) == {"lroc_wac_south"}
        conf = r["confusion"]
        assert len(conf) == 3 and all(len(row) == 3 for row in conf)
        assert sum(map(sum, conf)) == m["test_images"] == 45
        assert sum(conf[i][i] for i in range(3)) / 45 == pytest.approx(r["real_accuracy"])
        assert (run / f"confusion_{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert m["train_images"] > 0 and m["test_sources"] == ["lroc_wac_south"]
    assert "one real observation per crater" in m["limits"]
    rows = [json.loads(line) for line in (run / "realset.jsonl").read_text().splitlines()]
    assert len(rows) == 45 and {"box", "sigma", "offset_px", "rotation_deg", "source", "pred_lunarnet_ex"} <= set(rows[0])
    summary = json.loads((run / "train_summary.json").read_text())
    assert summary["data"]["split_by"] == "camera" and summary["lunarnet_ex"]["history"]
    ck = torch.load(run / "lunarnet_ex.pt", weights_only=False)
    assert ck["config"]["train"]["dataset_dir"] == str(toy) and ck["class_names"] == ["shackleton", "de_gerlache", "shoemaker"]
    assert not list(run.glob(".*.tmp"))                       # atomic writes leave no temp files
    # `evaluate` reloads the saved models and reproduces the metrics.
    res = runner.invoke(_cli(), ["evaluate", *_overrides(toy, tmp_path)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    m2 = json.loads((run / "metrics.json").read_text())
    for name in MODELS:
        assert m2[name]["confusion"] == m[name]["confusion"]


def test_bench_reports_throughput_and_time_to_target(toy, tmp_path):
    from train.bench import run_train_bench

    cfg = resolved(compose(_overrides(toy, tmp_path, "train.max_epochs=2", "train.target_val_accuracy=0.0")))
    r = run_train_bench(cfg)
    assert r["train_images_per_s"] > 0 and r["model_images_per_s"] > 0
    assert r["reached_target"] and r["epochs"] == 1 and r["time_to_target_s"] > 0
    assert r["parameters"] == 1_062_723


@pytest.mark.parametrize("extra, match", [
    (("train.dataset_dir=/nonexistent/ds",), "no manifest.jsonl in /nonexistent/ds"),
    (("realset.labels_file=LABELS",), "unknown crater 'Faustini'"),
    (("train.split_by=moon",), "train.split_by='moon'"),
])
def test_bad_inputs_give_one_line_errors(toy, tmp_path, extra, match):
    labels = tmp_path / "labels.csv"
    labels.write_text("image_path,crater,center_u,center_v,diameter_px,source\nx.png,Faustini,1,1,1,lroc_nac\n")
    extra = [e.replace("LABELS", str(labels)) for e in extra]
    res = CliRunner().invoke(_cli(), ["train", *_overrides(toy, tmp_path), *extra])
    assert res.exit_code == 2, res.output
    assert res.output.startswith("error: ") and match in res.output


def test_evaluate_without_a_run_is_a_clear_error(tmp_path):
    res = CliRunner().invoke(_cli(), ["evaluate", f"run_dir={tmp_path}/none", "train.num_threads=1"])
    assert res.exit_code == 2 and "no trained LunarNet_ex" in res.output
