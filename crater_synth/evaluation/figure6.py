"""Figure 6: real-image accuracy against each sweep parameter's sample count (others at their maximum),
one curve per ROI ratio, for LunarNet_ex and LunarSVM_ex.

Every subset is a selection of rows from ONE rendered dataset (``crater_core.sweep.nearest_subset``
and ``rows_in_selection``), never a re-render. Outputs in ``run_dir``: ``experiments.csv`` (one row per
parameter, count, sigma and model; appended as points finish, so a rerun skips finished points) and
``figure6.png`` (four panels in the paper's layout).
"""

from __future__ import annotations

import copy
import csv
import io
import time
from pathlib import Path

import click
from omegaconf import DictConfig, OmegaConf

from crater_core.schema import atomic_write_bytes, atomic_write_text
from crater_core.sweep import AXES, grid_from_config, nearest_subset
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import ConfigError, compose, resolved, settings_from
from crater_synth.evaluation.validation import run_fingerprint
from train.pipeline import train_and_evaluate
from train.registry import FIGURE6_MODELS, SPECS

CSV_FILE, FIGURE_FILE = "experiments.csv", "figure6.png"
CSV_FIELDS = (
    "parameter",
    "count",
    "sigma",
    "model",
    "real_accuracy",
    "val_accuracy",
    "train_images",
    "seconds",
    "config",  # fingerprint of everything that decides a result (a rerun refuses to mix configurations)
)
PANEL_TITLES = {
    "sun_elevation": "Sun elevation θ1",
    "sun_azimuth": "Sun azimuth φ1",
    "cam_elevation": "Camera elevation θ2",
    "cam_azimuth": "Camera azimuth φ2",
}
MODELS = FIGURE6_MODELS  # the paper's Figure 6 plots LunarNet_ex and LunarSVM_ex


def plan_points(grid, counts: dict) -> list[dict]:
    """Every (parameter, count) point with its row selection; the other axes stay at all their values."""
    full = {a: list(getattr(grid, a)) for a in AXES}
    points = []
    for axis in AXES:
        for count in counts.get(axis) or []:
            selection = dict(full)
            selection[axis] = nearest_subset(full[axis], axis, int(count))
            points.append({"parameter": axis, "count": int(count), "select": selection})
    return points


_CSV_TYPES = {
    "count": int,
    "sigma": float,
    "real_accuracy": float,
    "val_accuracy": float,
    "train_images": int,
    "seconds": float,
}


def read_results(path: Path) -> list[dict]:
    """Rows of experiments.csv with their types restored (a rerun continues from them)."""
    if not path.is_file():
        return []
    try:
        with open(path, newline="") as fh:
            return [
                {
                    k: (
                        _CSV_TYPES[k](v)
                        if k in _CSV_TYPES and v not in ("", "None")
                        else (None if v in ("", "None") else v)
                    )
                    for k, v in row.items()
                }
                for row in csv.DictReader(fh)
            ]
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"{path}: corrupt experiments CSV ({exc}); delete it to start over") from None


def write_results(path: Path, rows: list[dict]) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_FIELDS)
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(path, buf.getvalue())


def plot_figure6(rows: list[dict], png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(9, 6.5), sharey=True)
    sigmas = sorted({float(r["sigma"]) for r in rows})
    colours = dict(zip(sigmas, ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e")))
    for ax, axis in zip(axes.ravel(), AXES):
        for sigma in sigmas:
            for model, style in zip(MODELS, ("o-", "s--", "^:", "d-.")):
                pts = sorted(
                    (int(r["count"]), float(r["real_accuracy"]))
                    for r in rows
                    if r["parameter"] == axis and float(r["sigma"]) == sigma and r["model"] == model
                )
                if pts:
                    ax.plot(
                        *zip(*pts),
                        style,
                        color=colours[sigma],
                        ms=4,
                        lw=1.2,
                        label=f"{SPECS[model].short} σ={sigma:.1f}",
                    )
        counts = sorted({int(r["count"]) for r in rows if r["parameter"] == axis})
        if counts:
            ax.set_xticks(counts)
        else:  # a run still in progress: say so rather than leave an unexplained empty panel
            ax.set_xticks([])
            ax.text(0.5, 0.5, "no results yet", ha="center", va="center", transform=ax.transAxes, color="grey")
        ax.set_title(PANEL_TITLES[axis], fontsize=10)
        ax.set_xlabel("sample count (others at maximum)")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("accuracy on real crops")
    axes[1, 0].set_ylabel("accuracy on real crops")
    axes[0, 0].legend(fontsize=7, ncol=2, loc="lower right")
    styles = ", ".join(f"{SPECS[m].label} {ls}" for m, ls in zip(MODELS, ("solid", "dashed", "dotted", "dash-dot")))
    fig.suptitle(f"Test accuracy by sample count (paper Fig. 6): {styles}", fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(png, buf.getvalue())  # temp file, fsync, rename


def experiments_fingerprint(cfg_resolved: dict) -> str:
    """What decides every point's result (renders, training budget, model, sensor, real set), without
    the Figure 6 plan itself: points with equal fingerprints can share one CSV."""
    return run_fingerprint({k: v for k, v in cfg_resolved.items() if k not in ("figure6", "loop")})


def run_experiments(cfg: DictConfig, progress: bool = True) -> list[dict]:
    """Train on every Figure 6 subset of the rendered dataset and record real-test accuracy."""
    cfg_r = resolved(cfg)
    grid = grid_from_config(cfg_r["sweep"])
    counts = cfg_r["figure6"]["counts"]
    unknown = set(counts) - set(AXES)
    if unknown:
        raise ConfigError(f"figure6.counts: unknown parameter(s) {sorted(unknown)}")
    points = plan_points(grid, counts)
    run_dir = Path(cfg_r["run_dir"])
    run_dir.mkdir(parents=True, exist_ok=True)
    csv_path = run_dir / CSV_FILE
    results = read_results(csv_path)
    config = experiments_fingerprint(cfg_r)
    other = sorted({str(r.get("config")) for r in results} - {config})
    if other:
        raise ConfigError(
            f"{csv_path}: its results were made with another configuration ({', '.join(other)}; this one is "
            f"{config}): continue with the same overrides, or use another run_dir"
        )
    done = {(r["parameter"], r["count"], r["sigma"]) for r in results}
    sigmas = [float(s) for s in cfg_r["figure6"].get("sigmas") or grid.sigmas]
    for point in points:
        for sigma in sigmas:
            if (point["parameter"], point["count"], sigma) in done:
                continue
            cfg_p = copy.deepcopy(cfg)
            OmegaConf.update(cfg_p, "train.select", point["select"], force_add=True)
            OmegaConf.update(cfg_p, "train.sigmas", [sigma])
            OmegaConf.update(cfg_p, "realset.sigmas", [sigma])
            OmegaConf.update(
                cfg_p, "run_dir", str(run_dir / "experiments" / f"{point['parameter']}-{point['count']}-s{sigma:.1f}")
            )
            if progress:
                click.echo(f"figure 6: {point['parameter']} count {point['count']} sigma {sigma:.1f}", err=True)
            t0 = time.perf_counter()
            metrics = train_and_evaluate(settings_from(cfg_p), progress=False)
            seconds = round(time.perf_counter() - t0, 2)
            for model in MODELS:
                results.append(
                    {
                        "parameter": point["parameter"],
                        "count": point["count"],
                        "sigma": sigma,
                        "model": model,
                        "real_accuracy": round(float(metrics[model]["real_accuracy"]), 6),
                        "val_accuracy": metrics[model].get("val_accuracy"),
                        "train_images": int(metrics["train_images"]),
                        "seconds": seconds,
                        "config": config,
                    }
                )
            write_results(csv_path, results)
            plot_figure6(results, run_dir / FIGURE_FILE)
    if results:
        plot_figure6(results, run_dir / FIGURE_FILE)
    return results


@click.command("experiments")
@OVERRIDES
@user_errors
def experiments_command(overrides):
    """Figure 6: vary each parameter's sample count (others at max) for each ROI sigma; train
    LunarNet_ex and LunarSVM_ex on each subset of ONE rendered dataset; CSV + four-panel figure.

    e.g. ``crater-synth experiments sweep=paper run_dir=outputs/paper`` (render the sweep first).
    """
    cfg = compose(overrides)
    results = run_experiments(cfg)
    run_dir = Path(str(resolved(cfg)["run_dir"]))
    click.echo(f"{len(results)} results in {run_dir / CSV_FILE}; figure {run_dir / FIGURE_FILE}")
