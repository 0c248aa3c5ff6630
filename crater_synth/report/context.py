"""What every section gatherer shares: the run context and the "not run" note of an absent input."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from crater_synth.report.inputs import RunConfig

# What produces each input, quoted in the "not run" notes: (what, command).
PRODUCERS = {
    "dataset": ("rendering a dataset (then point the report at it with train.dataset_dir=DIR)", "crater-synth dataset"),
    "metrics": (
        "training and evaluation (crater-synth evaluate for saved models)",
        "crater-synth train run_dir=RUN_DIR",
    ),
    "loop": ("the closed loop (configs/loop)", "crater-synth loop run_dir=RUN_DIR"),
    "experiments": ("the Figure 6 experiments (configs/figure6)", "crater-synth experiments run_dir=RUN_DIR"),
    "ablation": ("the fidelity ablation (configs/ablation, docs/fidelity.md)", "crater-synth ablate"),
    "navigation": (
        "the navigation demo on real mosaic windows (docs/navigation/overview.md)",
        "make navigate-demo NAV_DEMO_DIR=RUN_DIR/navigation",
    ),
    "navframes": (
        "rendering a trajectory and evaluating it (docs/navigation/rendered.md)",
        "crater-synth nav-frames trajectory=descent_ridge --out FRAMES_DIR && "
        "crater-synth nav-frames-eval FRAMES_DIR --json RUN_DIR/navigation/frames_eval.json",
    ),
}

# Quoted next to the real-vs-synthetic figures (section 2).
SYNTHETIC_CHOICE = (
    "For each crater the synthetic render shown is the manifest row whose camera elevation is closest to 90° "
    "(nadir, like the map-projected mosaic), then the one with the highest sun elevation, then the highest lit "
    "fraction (ties: the first row in manifest order). The LROC WAC polar mosaic is a composite of many "
    "orbits under different illumination: it has no single sun direction, so no render can match its lighting "
    "exactly; the highest, best-lit Sun of the sweep is the closest analogue of a mosaic assembled for "
    "illumination. The real crop is the realset's own σ = 1.0 box centred on the crater with no slewing offset "
    "and no rotation."
)


@dataclass
class Ctx:
    run_dir: Path
    out: Path  # the report's temporary directory
    rc: RunConfig
    metrics: dict | None
    rows: list[dict] | None  # the rows the run trained on (train.select applied)
    all_rows: list[dict] | None  # every row of the dataset's manifest
    craters: list[str]
    max_tiles: int
    hist_samples: int
    log: Callable[[str], None] | None = None
    real: dict = field(default_factory=dict)  # crater -> {"crop"} (canonical sigma = 1 crop)
    real_error: str | None = None

    def say(self, msg: str) -> None:
        if self.log:
            self.log(msg)


def not_run(what: str, producer: str) -> dict:
    desc, cmd = PRODUCERS[producer]
    return {"what": what, "desc": desc, "cmd": cmd}
