"""The closed loop of the paper's Fig. 3: train -> test on real crops -> if below the threshold, add
sun elevations, render only the new renders, retrain; stop at the threshold or when the schedule ends.

Every round is recorded in ``<run_dir>/loop_history.json`` (written atomically after each round) and
plotted in ``loop_history.png``. Re-running continues after the last finished round. The final
round's models, metrics.json and confusion matrices are copied to ``run_dir`` itself.

A finished round is reused only when its identity -- the hash of every setting its models and
accuracies can depend on (:func:`round_identity`: the dataset's settings, the grid it trains on, the
model, training, sensor and real-test settings) -- equals the one the round would have now. Each
round records its identity in the history and the settings behind it in ``<round dir>/round_identity.json``,
so a refusal names the first setting that differs.
"""

from __future__ import annotations

import copy
import io
import json
import shutil
import time
from collections.abc import Iterator
from datetime import datetime, timezone
from pathlib import Path

import click
from omegaconf import DictConfig, OmegaConf

from crater_core.schema import atomic_write_bytes, atomic_write_json, atomic_write_text, content_key
from crater_core.settings import Settings
from crater_core.sweep import grid_from_config
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import ConfigError, compose, resolved, settings_from
from crater_synth.dataset import build_dataset
from crater_synth.dataset.identity import IGNORED, settings_payload
from crater_synth.evaluation.run_folder import (
    HISTORY_FILE,
    HISTORY_PLOT,
    IDENTITY_FILE,
    LOOP_FILES,
    ROUNDS_DIR,
    round_dir,
    run_writer,
)
from train.pipeline import train_and_evaluate
from train.registry import LOOP_MODEL, MODELS, SPECS
from train.runs import TRAIN_FILES, StagedRun

FINAL_FILES = TRAIN_FILES  # the last round's run, copied to run_dir: it represents the run as a whole
RESTART_FLAG = "--restart"
ADOPT_FLAG = "--adopt-rounds"

# A round's result depends on every setting except these, each with why. The dataset's own list applies
# (crater_synth.dataset.identity.IGNORED) but for the keys that choose what a round trains on or how.
_ROUND_USES = ("crater", "model", "train", "sensor", "realset", "sweep.min_sun_elevation_deg")
_ROUND_USES += tuple(f"sweep.{axis}" for axis in ("sun_elevation", "sun_azimuth", "cam_elevation", "cam_azimuth"))
ROUND_IGNORED: dict[str, str] = {k: why for k, why in IGNORED.items() if k not in _ROUND_USES} | {
    "loop": "the schedule is checked on its own (load_history); the threshold only says where to stop",
    "train.dataset_dir": "where the round's renders are read; the settings that make them are in the identity",
    "train.export_dir": "an export of the same renders: the same crops",
    "train.num_threads": "CPU threads: the same model",
    "train.device": "where the model trains, not what it learns",
    "train.cache_dir": "where crops are cached; the cache is keyed by its own inputs",
    "train.cache_workers": "processes that fill the crop cache: the same crops",
    "train.progress": "progress lines",
}


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


def round_identity_payload(settings: Settings) -> dict:
    """The plain settings hashed into :func:`round_identity`: all of a round's, less :data:`ROUND_IGNORED`."""
    return json.loads(json.dumps(settings_payload(settings, ROUND_IGNORED), default=str))


def round_identity(settings: Settings) -> str:
    """16 hex digits of the sha256 of :func:`round_identity_payload` (crater_core.schema.content_key)."""
    return content_key(round_identity_payload(settings))


def _leaves(node: dict, prefix: str = "") -> Iterator[tuple[str, object]]:
    for key, value in node.items():
        if isinstance(value, dict) and value:
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def first_difference(recorded: dict, now: dict) -> str:
    """``key=<then> then, <now> now`` for the first setting (in settings order) whose values differ."""
    old, new = dict(_leaves(recorded)), dict(_leaves(now))
    for key in [*new, *(k for k in old if k not in new)]:
        if old.get(key, "<absent>") != new.get(key, "<absent>"):
            then, now_ = (json.dumps(d[key]) if key in d else "<absent>" for d in (old, new))
            return f"{key}={then} then, {now_} now"
    return "the same settings but another identity"


def _recorded_payload(round_dir: Path) -> dict | None:
    try:
        return json.loads((round_dir / IDENTITY_FILE).read_text())["settings"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def check_rounds(cfg: DictConfig, hist: dict, hist_path: Path, adopt: bool) -> None:
    """Refuse (ConfigError, one line) to reuse a finished round whose identity differs from what this run
    would give it, or that recorded none (written before rounds had one) unless ``adopt``: then it is
    taken as trained with these settings and this identity is recorded for it."""
    redo = (
        f"use another run_dir, or rerun with {RESTART_FLAG} to move this loop's history and rounds "
        f"into {hist_path.parent / 'previous'}/ and start again"
    )
    adopted = False
    for k, rec in enumerate(hist["rounds"]):
        count = hist["schedule"][k]
        rdir = round_dir(hist_path.parent, k, count)
        payload = round_identity_payload(settings_from(round_config(cfg, count, rdir)))
        identity, where = content_key(payload), f"{hist_path}: round {k} ({count} sun elevations)"
        if rec.get("identity") is None and adopt:
            rec["identity"], adopted = identity, True
            if rdir.is_dir():
                atomic_write_json(rdir / IDENTITY_FILE, {"identity": identity, "settings": payload})
        elif rec.get("identity") is None:
            raise ConfigError(
                f"{where} was written before rounds recorded their settings; rerun with {ADOPT_FLAG} "
                f"if it was trained with these settings, or {redo}"
            )
        elif rec["identity"] != identity:
            recorded = _recorded_payload(rdir)
            what = first_difference(recorded, payload) if recorded else f"{IDENTITY_FILE} unreadable"
            raise ConfigError(f"{where} was trained with other settings ({what}); {redo}")
    if adopted:
        atomic_write_text(hist_path, json.dumps(hist, indent=2))


def restart(run_dir: Path) -> Path | None:
    """Move the loop's history, plot and rounds into ``run_dir/previous/loop-<UTC time>/`` (never deleted);
    returns that folder, or None when there was nothing to move."""
    names = [n for n in (HISTORY_FILE, HISTORY_PLOT, ROUNDS_DIR) if (run_dir / n).exists()]
    if not names:
        return None
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    target = run_dir / "previous" / f"loop-{stamp}"
    n = 1
    while target.exists():
        n += 1
        target = run_dir / "previous" / f"loop-{stamp}-{n}"
    target.mkdir(parents=True)
    for name in names:
        (run_dir / name).rename(target / name)
    return target


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


def run_loop(cfg: DictConfig, progress: bool = True, adopt: bool = False, fresh: bool = False) -> dict:
    """Run (or continue) the closed loop; returns the history dict. A finished round is reused only when
    its identity is this run's (:func:`check_rounds`; ``adopt``: rounds that recorded none are taken as this
    run's); ``fresh`` first moves an earlier loop's rounds aside (:func:`restart`)."""
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
        round_config(cfg, count, round_dir(run_dir, k, count))
    run_dir.mkdir(parents=True, exist_ok=True)
    moved = restart(run_dir) if fresh else None
    if moved is not None:
        click.echo(f"moved the earlier loop's history and rounds to {moved}", err=True)
    hist_path = run_dir / HISTORY_FILE
    hist = load_history(hist_path, threshold, schedule)
    check_rounds(cfg, hist, hist_path, adopt)

    def reached(r: dict) -> bool:
        return r[LOOP_MODEL] >= threshold

    for k, count in enumerate(schedule):
        if k < len(hist["rounds"]):  # finished in an earlier run
            if reached(hist["rounds"][k]):
                break
            continue
        rdir = round_dir(run_dir, k, count)
        cfg_k = round_config(cfg, count, rdir)
        if progress:
            click.echo(f"loop round {k}: {count} sun elevations", err=True)
        t0 = time.perf_counter()
        settings_k = settings_from(cfg_k)  # the round's configuration, validated once: renders and trains
        payload = round_identity_payload(settings_k)
        render = build_dataset(settings_k, progress=progress)
        t1 = time.perf_counter()
        metrics = train_and_evaluate(settings_k, progress=progress)
        t2 = time.perf_counter()
        atomic_write_json(rdir / IDENTITY_FILE, {"identity": content_key(payload), "settings": payload})
        hist["rounds"].append(
            {
                "round": k,
                "identity": content_key(payload),
                "sun_elevation_count": count,
                "renders_new": render["rendered"],
                "renders_reused": render["skipped_existing"],
                "images": int(metrics["train_images"]),
                **{m: float(metrics[m]["real_accuracy"]) for m in MODELS},
                "val_accuracy": {m: metrics[m].get("val_accuracy") for m in MODELS},
                "render_s": round(t1 - t0, 2),
                "train_s": round(t2 - t1, 2),
                "run_dir": str(rdir),
            }
        )
        atomic_write_text(hist_path, json.dumps(hist, indent=2))
        plot_history(hist, run_dir / HISTORY_PLOT)
        if reached(hist["rounds"][-1]):
            break

    last = hist["rounds"][-1]
    hist["stopped_because"] = "threshold reached" if reached(last) else "sun-elevation schedule exhausted"
    atomic_write_text(hist_path, json.dumps(hist, indent=2))
    plot_history(hist, run_dir / HISTORY_PLOT)
    final = Path(last["run_dir"])
    with StagedRun(run_dir) as stage:  # the last round's run is published whole, never half of it
        for name in FINAL_FILES:
            if (final / name).is_file():
                shutil.copyfile(final / name, stage / name)
    return hist


@click.command("loop")
@click.option(
    RESTART_FLAG, "restart_", is_flag=True, help="Move the loop's history and rounds into run_dir/previous/ first."
)
@click.option(ADOPT_FLAG, "adopt", is_flag=True, help="Reuse rounds that recorded no settings as trained with these.")
@OVERRIDES
@user_errors
def loop_command(overrides, restart_, adopt):
    """Closed loop: add sun elevations until LunarNet_ex's real accuracy reaches loop.threshold.

    Paper Fig. 3. Each round renders only the new renders, retrains and tests on the real crops;
    a rerun resumes after the last finished round whose settings are this run's, and refuses rounds
    trained with other settings (--restart moves them aside into run_dir/previous/).

    e.g. ``crater-synth loop sweep=demo run_dir=outputs/demo loop.sun_elevation_schedule=[2,4]``
    """
    cfg = compose(overrides)
    # One loop at a time in a run_dir; its rounds train in-process under this one hold.
    with run_writer(str(resolved(cfg)["run_dir"]), LOOP_FILES, rounds=True):
        hist = run_loop(cfg, adopt=adopt, fresh=restart_)
    for r in hist["rounds"]:
        accs = " ".join(f"{m} {r[m]:.3f}" for m in MODELS)
        click.echo(
            f"round {r['round']}: sun count {r['sun_elevation_count']:2d}, {r['images']} train images, "
            f"real accuracy {accs} (render {r['render_s']:.0f} s, train {r['train_s']:.0f} s)"
        )
    click.echo(f"stopped: {hist['stopped_because']}")
