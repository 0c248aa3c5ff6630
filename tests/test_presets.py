"""The `experiment=` presets of the main jobs (configs/experiment/): each composes, and composes to exactly
the settings of the override list the Makefile and the docs passed for that job before the preset existed
(so the same run fingerprints, the same reused runs, the same outputs)."""

import shlex
import shutil
import subprocess

import pytest
import yaml

from crater_synth.config import CONFIG_DIR, load_settings

from helpers.cli import REPO

# Each preset and the overrides its job was run with (where they were written).
SPELLED_OUT = {
    # Makefile `demo` (DEMO_SWEEP, DEMO_TRAIN and DEMO_DIR at their defaults)
    "demo": ["sweep=demo_physical_noon", "train=sim2real", "run_dir=outputs/demo", "loop.sun_elevation_schedule=[2,4]"],
    # README "Paper scale": make dataset OVERRIDES="sweep=paper"
    "paper_sweep": ["sweep=paper"],
    # docs/results/notes.md: make loop OVERRIDES=...
    "paper_loop": ["sweep=paper", "train=paper_budget", "run_dir=outputs/paper_loop", "train.progress=false"],
    # docs/results/notes.md: make experiments OVERRIDES=... (docs/results/experiments.csv)
    "figure6": ["sweep=paper", "train=paper_budget", "run_dir=outputs/paper_fig6", "train.progress=false"],
    # README, docs/validation.md: make validate OVERRIDES="validate=holdout experiment=chosen"
    "heldout": ["validate=holdout", "sweep=demo_physical_noon", "train=sim2real"],
    # Makefile `navigate-frames-demo`: its orbit-arc nav-frames
    "navigation_demo": ["trajectory=polar_orbit_arc", "trajectory.frames=6", "render.samples=1"],
    # docs/configuration.md
    "chosen": ["sweep=demo_physical_noon", "train=sim2real"],
}


def test_every_preset_is_listed_here():
    assert sorted(p.stem for p in (CONFIG_DIR / "experiment").glob("*.yaml")) == sorted(SPELLED_OUT)


@pytest.mark.parametrize("preset", sorted(SPELLED_OUT))
def test_preset_composes_to_the_spelled_out_overrides(preset):
    settings = load_settings([f"experiment={preset}"])
    assert settings == load_settings(SPELLED_OUT[preset])
    assert settings != load_settings([])  # it sets something
    # later overrides still win over the preset, the run_dir included
    assert load_settings([f"experiment={preset}", "run_dir=elsewhere", "seed=7"]).run_dir == "elsewhere"


def test_figure6_preset_is_the_published_figure6_configuration():
    """docs/results/experiments.csv's fingerprint is the one experiment=figure6 gives."""
    import csv

    from crater_synth.config import compose, resolved
    from crater_synth.evaluation.figure6 import experiments_fingerprint

    published = {row["config"] for row in csv.DictReader((REPO / "docs" / "results" / "experiments.csv").open())}
    assert published == {experiments_fingerprint(resolved(compose(["experiment=figure6"])))}


def _make_dry_run(target: str, *args: str) -> list[list[str]]:
    """The `crater-synth` command lines `make -n TARGET` would run, as argument lists."""
    proc = subprocess.run(
        ["make", "--no-print-directory", "-n", target, "CLI=crater-synth", "BIN=.", *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    return [shlex.split(line)[1:] for line in proc.stdout.splitlines() if line.startswith("crater-synth ")]


@pytest.mark.skipif(shutil.which("make") is None, reason="make not installed")
def test_make_demo_runs_the_demo_preset():
    loop, report = _make_dry_run("demo")
    assert loop[0] == "loop" and "experiment=demo" in loop
    assert load_settings(loop[1:]) == load_settings(SPELLED_OUT["demo"])
    assert report[:2] == ["report", "outputs/demo"] and report[2:] == ["experiment=demo"]
    # DEMO_SWEEP / DEMO_TRAIN / DEMO_DIR still replace the preset's sweep, training and run directory
    loop, report = _make_dry_run("demo", "DEMO_SWEEP=demo", "DEMO_TRAIN=default", "DEMO_DIR=outputs/d2")
    old = ["sweep=demo", "train=default", "run_dir=outputs/d2", "loop.sun_elevation_schedule=[2,4]"]
    assert load_settings(loop[1:]) == load_settings(old)
    assert report[1] == "outputs/d2" and {"sweep=demo", "train=default"} <= set(report)


def test_report_of_the_demo_reads_the_same_configuration(tmp_path):
    """`report RUN experiment=demo` (make demo) reads the configuration the spelled-out
    `report RUN sweep=demo_physical_noon train=sim2real` read: the preset's groups from the command line
    (the last round's training subset is not the report's), the rest from the run's saved config.yaml."""
    from crater_synth.report.inputs import RUN_CONFIG_FILE, effective_config

    saved = load_settings(SPELLED_OUT["demo"]).as_dict()
    saved["run_dir"] = "outputs/demo/rounds/round1-sun4"  # what the closed loop's last round saves
    saved["train"]["select"] = {"sun_elevation": [0, 2]}
    saved["seed"] = 3
    (tmp_path / RUN_CONFIG_FILE).write_text(yaml.safe_dump(saved, sort_keys=False))
    now = effective_config(tmp_path, ["experiment=demo"])
    before = effective_config(tmp_path, ["sweep=demo_physical_noon", "train=sim2real"])
    assert now == before
    assert now.cfg["train"]["select"] is None and now.cfg["run_dir"] == saved["run_dir"] and now.cfg["seed"] == 3
    assert now.dataset_dir_source == "command-line override train.dataset_dir"


def test_the_figure6_counts_group_is_not_beside_the_presets():
    assert not (CONFIG_DIR / "experiments").exists()
    assert load_settings(["figure6=small"]).figure6.counts.sun_elevation == (2, 4)
