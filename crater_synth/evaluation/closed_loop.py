"""The closed loop of the paper's Fig. 3: train -> test on real crops -> if below the threshold, add
sun elevations, render only the new renders, retrain; stop at the threshold or when the schedule ends.

Every round is recorded in ``<run_dir>/loop_history.json`` (written atomically after each round) and
plotted in ``loop_history.png``. Re-running continues after the last finished round. The final
round's models, metrics.json and confusion matrices are copied to ``run_dir`` itself.
"""

from __future__ import annotations

import copy
import io
import json
import shutil
import time
from pathlib import Path

import click
from omegaconf import DictConfig, OmegaConf

from crater_core.schema import atomic_write_bytes, atomic_write_text
from crater_core.sweep import grid_from_config
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import ConfigError, compose, resolved, settings_from
from crater_synth.dataset import build_dataset
from train.pipeline import train_and_evaluate
from train.registry import ARTEFACTS, LOOP_MODEL, MODELS, SPECS
from train.runs import StagedRun

HISTORY_FILE = "loop_history.json"
# Files of the last round that represent the run as a whole.
FINAL_FILES = ("metrics.json", "realset.jsonl", "train_summary.json", "config.yaml", *ARTEFACTS)


def round_config(cfg: DictConfig, sun_count: int, round_dir: Path) -> DictConfig:
    """The configuration of one round: ``sun_count`` sun elevations, training restricted to that grid."""
    cfg_k = copy.deepcopy(cfg)
    values = resolved(cfg)["sweep"]["sun_elevation"].get("values")
    if values is not None:  # explicit positions: round k uses the first ``sun_count`` of them (nested rounds)
        if sun_count > len(values):
            raise ConfigError(
                f"loop.sun_elevation_schedule asks for {sun_count} sun elevations but "
                f"sweep.sun_elevation.values has only {len(values)}"
            )
        OmegaConf.update(cfg_k, "sweep.sun_elevation.values", list(values)[: int(sun_count)])
    else:
        OmegaConf.update(cfg_k, "sweep.sun_elevation.count", int(sun_count))
    grid = grid_from_config(resolved(cfg_k)["sweep"])
    OmegaConf.update(
        cfg_k,
        "train.select",
        {
            "sun_elevation": list(grid.sun_elevation),
            "sun_azimuth": list(grid.sun_azimuth),
            "cam_elevation": list(grid.cam_elevation),
            "cam_azimuth": list(grid.cam_azimuth),
        },
        force_add=True,
    )
    OmegaConf.update(cfg_k, "run_dir", str(round_dir))
    return cfg_k


def load_history(path: Path, threshold: float, schedule: list[int]) -> dict:
    if path.is_file():
        try:
            hist = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{path}: corrupt loop history ({exc}); delete it to restart the loop") from None
        if hist.get("schedule") != schedule:
            raise ConfigError(
                f"{path}: recorded schedule {hist.get('schedule')} != loop.sun_elevation_schedule "
                f"{schedule}; use another run_dir or delete the history"
            )
        hist["threshold"] = threshold
        return hist
    return {"threshold": threshold, "schedule": schedule, "rounds": [], "stopped_because": None}


def plot_history(hist: dict, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rounds = hist["rounds"]
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    counts = [r["sun_elevation_count"] for r in rounds]
    for name, style in zip(MODELS, ("o-", "s--", "^:", "d-.", "v-")):
        ax.plot(counts, [r[name] for r in rounds], style, color=SPECS[name].color, label=SPECS[name].label)
    ax.axhline(hist["threshold"], color="grey", lw=0.8, ls="--", label=f"threshold {hist['threshold']:.2f}")
    ax.set_xlabel("sun-elevation sample count")
    ax.set_ylabel("accuracy on real crops")
    ax.set_ylim(0, 1)
    ax.set_xticks(counts or [0])
    ax.set_title("Closed loop (paper Fig. 3)")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(png, buf.getvalue())  # temp file, fsync, rename


def run_loop(cfg: DictConfig, progress: bool = True) -> dict:
    """Run (or continue) the closed loop; returns the history dict."""
    cfg_r = resolved(cfg)
    loop = cfg_r["loop"]
    threshold = float(loop["threshold"])
    schedule = [int(c) for c in loop["sun_elevation_schedule"]]
    if not 0.0 < threshold <= 1.0:
        raise ConfigError(f"loop.threshold={threshold}: must lie in (0, 1]")
    if not schedule or schedule != sorted(set(schedule)) or schedule[0] < 1:
        raise ConfigError(f"loop.sun_elevation_schedule={schedule}: must be increasing positive counts")
    run_dir = Path(cfg_r["run_dir"])
    for k, count in enumerate(schedule):  # every round's configuration, before round 0 renders anything
        round_config(cfg, count, run_dir / "rounds" / f"round{k}-sun{count}")
    run_dir.mkdir(parents=True, exist_ok=True)
    hist_path = run_dir / HISTORY_FILE
    hist = load_history(hist_path, threshold, schedule)

    def reached(r: dict) -> bool:
        return r[LOOP_MODEL] >= threshold

    for k, count in enumerate(schedule):
        if k < len(hist["rounds"]):  # finished in an earlier run
            if reached(hist["rounds"][k]):
                break
            continue
        round_dir = run_dir / "rounds" / f"round{k}-sun{count}"
        cfg_k = round_config(cfg, count, round_dir)
        if progress:
            click.echo(f"loop round {k}: {count} sun elevations", err=True)
        t0 = time.perf_counter()
        settings_k = settings_from(cfg_k)  # the round's configuration, validated once: renders and trains
        render = build_dataset(settings_k, progress=progress)
        t1 = time.perf_counter()
        metrics = train_and_evaluate(settings_k, progress=progress)
        t2 = time.perf_counter()
        hist["rounds"].append(
            {
                "round": k,
                "sun_elevation_count": count,
                "renders_new": render["rendered"],
                "renders_reused": render["skipped_existing"],
                "images": int(metrics["train_images"]),
                **{m: float(metrics[m]["real_accuracy"]) for m in MODELS},
                "val_accuracy": {m: metrics[m].get("val_accuracy") for m in MODELS},
                "render_s": round(t1 - t0, 2),
                "train_s": round(t2 - t1, 2),
                "run_dir": str(round_dir),
            }
        )
        atomic_write_text(hist_path, json.dumps(hist, indent=2))
        plot_history(hist, run_dir / "loop_history.png")
        if reached(hist["rounds"][-1]):
            break

    last = hist["rounds"][-1]
    hist["stopped_because"] = "threshold reached" if reached(last) else "sun-elevation schedule exhausted"
    atomic_write_text(hist_path, json.dumps(hist, indent=2))
    plot_history(hist, run_dir / "loop_history.png")
    final = Path(last["run_dir"])
    with StagedRun(run_dir) as stage:  # the last round's run is published whole, never half of it
        for name in FINAL_FILES + tuple(p.name for p in final.glob("confusion_*.png")):
            if (final / name).is_file():
                shutil.copyfile(final / name, stage / name)
    return hist


@click.command("loop")
@OVERRIDES
@user_errors
def loop_command(overrides):
    """Closed loop: add sun elevations until LunarNet_ex's real accuracy reaches loop.threshold.

    Paper Fig. 3. Each round renders only the new renders, retrains and tests on the real crops;
    a rerun resumes after the last finished round.

    e.g. ``crater-synth loop sweep=demo run_dir=outputs/demo loop.sun_elevation_schedule=[2,4]``
    """
    hist = run_loop(compose(overrides))
    for r in hist["rounds"]:
        accs = " ".join(f"{m} {r[m]:.3f}" for m in MODELS)
        click.echo(
            f"round {r['round']}: sun count {r['sun_elevation_count']:2d}, {r['images']} train images, "
            f"real accuracy {accs} (render {r['render_s']:.0f} s, train {r['train_s']:.0f} s)"
        )
    click.echo(f"stopped: {hist['stopped_because']}")
