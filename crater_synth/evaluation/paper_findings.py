"""The paper's findings, checked one by one against a Figure 6 run and a closed-loop run.

``crater-synth results`` reads ``experiments.csv`` (``crater-synth experiments``) and, when given,
``loop_history.json`` (``crater-synth loop``), and writes into ``--out`` (default ``outputs/results/``;
``make results`` records the paper-scale run in ``docs/results/``): the CSV, the Figure 6 image, the loop
history and its plot, and ``README.md``, which takes each finding of the paper (Section 4, Fig. 3 and
Fig. 6) and says with numbers whether it reproduces. Every verdict follows from a rule written next to
it, never from a hand-written sentence.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from statistics import mean

import click
import numpy as np

from crater_core.schema import atomic_write_bytes, atomic_write_text
from crater_synth.cli_common import user_errors
from crater_synth.config import ConfigError
from crater_synth.evaluation.figure6 import CSV_FILE, FIGURE_FILE, MODELS, PANEL_TITLES, plot_figure6, read_results
from train.registry import LOOP_MODEL, label
from train.registry import MODELS as ALL_MODELS  # the loop records every classifier

PAGE_FILE = "README.md"
HISTORY_FILE, HISTORY_PLOT = "loop_history.json", "loop_history.png"
# A change smaller than this (accuracy on 900 real crops: one crop is 0.0011) is read as noise.
NOISE = 0.02
PAPER_CAMERA_ELEVATION_GAIN = 0.05  # paper Section 4: "camera elevation adds about 5 %"
PAPER_LOOP_ACCURACY = 0.85  # paper Fig. 3 / abstract: the loop converges near 85 %
REPRODUCED, NOT_REPRODUCED, NOT_MEASURED = "reproduces", "does not reproduce", "not measured"


@dataclass
class Finding:
    claim: str  # the paper's statement
    rule: str  # how the verdict is decided from the numbers
    verdict: str
    evidence: list[str]  # one line per curve or number


def curves(rows: list[dict], parameter: str, sigma: float | None = None) -> dict[tuple, list[tuple[int, float]]]:
    """(sigma, model) -> [(count, real accuracy)] sorted by count, for one parameter."""
    out: dict[tuple, list[tuple[int, float]]] = {}
    for r in rows:
        if r["parameter"] != parameter or (sigma is not None and abs(float(r["sigma"]) - sigma) > 1e-6):
            continue
        out.setdefault((float(r["sigma"]), r["model"]), []).append((int(r["count"]), float(r["real_accuracy"])))
    return {k: sorted(v) for k, v in sorted(out.items())}


def spearman(points: list[tuple[int, float]]) -> float:
    """Rank correlation of count and accuracy (ties share their mean rank); 0 for a flat curve."""
    if len(points) < 2:
        return 0.0
    ranks = [_ranks(np.array(col, dtype=float)) for col in zip(*points)]
    a, b = (r - r.mean() for r in ranks)
    denom = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / denom) if denom > 0 else 0.0


def _ranks(x: np.ndarray) -> np.ndarray:
    order = np.argsort(x, kind="stable")
    ranks = np.empty(len(x))
    ranks[order] = np.arange(len(x), dtype=float)
    for value in np.unique(x):  # ties: mean rank
        tied = x == value
        ranks[tied] = ranks[tied].mean()
    return ranks


def turns(points: list[tuple[int, float]]) -> int:
    """Changes of direction along a curve, ignoring steps smaller than :data:`NOISE`."""
    steps = [b[1] - a[1] for a, b in zip(points, points[1:]) if abs(b[1] - a[1]) >= NOISE]
    return sum(1 for s, t in zip(steps, steps[1:]) if (s > 0) != (t > 0))


def _describe(key: tuple, pts: list[tuple[int, float]]) -> str:
    sigma, model = key
    values = ", ".join(f"{c}: {a:.3f}" for c, a in pts)
    return f"{label(model)}, σ {sigma:.1f}: {values} (ρ = {spearman(pts):+.2f})"


def _measured(rows: list[dict], parameter: str, min_points: int = 2) -> dict[tuple, list[tuple[int, float]]]:
    """The curves of ``parameter`` with at least ``min_points`` counts measured."""
    return {k: v for k, v in curves(rows, parameter).items() if len(v) >= min_points}


def _mean_gain(cs: dict[tuple, list[tuple[int, float]]]) -> float:
    """Accuracy at each curve's largest count minus its smallest, averaged over the curves."""
    return mean(v[-1][1] - v[0][1] for v in cs.values())


def sun_elevation_rises(rows: list[dict]) -> Finding:
    cs = _measured(rows, "sun_elevation")
    rule = (
        "reproduces when, averaged over σ and both classifiers, accuracy at the largest count exceeds the "
        f"smallest by more than {NOISE:.2f} and the mean rank correlation ρ(count, accuracy) is positive"
    )
    claim = "Accuracy rises with the number of sun-elevation samples."
    if not cs:
        return Finding(claim, rule, NOT_MEASURED, [])
    gain = _mean_gain(cs)
    rho = mean(spearman(v) for v in cs.values())
    ok = gain > NOISE and rho > 0
    evidence = [_describe(k, v) for k, v in cs.items()] + [f"mean gain {gain:+.3f}, mean ρ {rho:+.2f}"]
    return Finding(claim, rule, REPRODUCED if ok else NOT_REPRODUCED, evidence)


def large_roi_falls(rows: list[dict], sigma: float = 1.4) -> Finding:
    cs = {(p, *k): v for p in PANEL_TITLES for k, v in curves(rows, p, sigma).items() if len(v) >= 2}
    rule = (
        f"reproduces when, at σ {sigma}, most curves (4 parameters × 2 classifiers) have a negative rank "
        "correlation ρ(count, accuracy) and the mean ρ is negative"
    )
    claim = f"At σ {sigma} (the widest crop) accuracy falls as the sampling rises."
    if not cs:
        return Finding(claim, rule, NOT_MEASURED, [])
    rhos = {k: spearman(v) for k, v in cs.items()}
    falling = sum(1 for r in rhos.values() if r < 0)
    ok = falling > len(rhos) / 2 and mean(rhos.values()) < 0
    evidence = [f"{PANEL_TITLES[k[0]]}: " + _describe(k[1:], v) for k, v in cs.items()]
    evidence.append(f"{falling} of {len(rhos)} curves fall; mean ρ {mean(rhos.values()):+.2f}")
    return Finding(claim, rule, REPRODUCED if ok else NOT_REPRODUCED, evidence)


def camera_elevation_gain(rows: list[dict]) -> Finding:
    cs = _measured(rows, "cam_elevation")
    lo, hi = PAPER_CAMERA_ELEVATION_GAIN - NOISE - 0.01, PAPER_CAMERA_ELEVATION_GAIN + NOISE + 0.03
    rule = (
        "the gain is the accuracy at the largest camera-elevation count minus the smallest, averaged over σ "
        f"and both classifiers; it reproduces when it lies in [{lo:.2f}, {hi:.2f}] (about 5 %)"
    )
    claim = "Adding camera elevations improves accuracy by about 5 %."
    if not cs:
        return Finding(claim, rule, NOT_MEASURED, [])
    gain = _mean_gain(cs)
    evidence = [_describe(k, v) for k, v in cs.items()] + [f"mean gain {gain:+.3f} (paper ≈ +0.05)"]
    return Finding(claim, rule, REPRODUCED if lo <= gain <= hi else NOT_REPRODUCED, evidence)


def camera_azimuth_not_monotonic(rows: list[dict]) -> Finding:
    cs = _measured(rows, "cam_azimuth", min_points=3)
    rule = (
        f"a curve is non-monotonic when it changes direction at least once (steps under {NOISE:.2f} "
        "ignored); it reproduces when most curves are"
    )
    claim = "Accuracy is not monotonic in the number of camera azimuths."
    if not cs:
        return Finding(claim, rule, NOT_MEASURED, [])
    bent = {k: turns(v) for k, v in cs.items()}
    evidence = [_describe(k, v) + f", {bent[k]} turn(s)" for k, v in cs.items()]
    n_bent = sum(1 for t in bent.values() if t > 0)
    evidence.append(f"{n_bent} of {len(bent)} curves change direction")
    return Finding(claim, rule, REPRODUCED if n_bent > len(bent) / 2 else NOT_REPRODUCED, evidence)


def loop_converges(history: dict | None) -> Finding:
    rule = (
        f"reproduces when the last round's {label(LOOP_MODEL)} real accuracy lies within "
        f"{PAPER_LOOP_ACCURACY:.2f} ± 0.05"
    )
    claim = "The closed loop converges near 85 % accuracy on real images."
    rounds = (history or {}).get("rounds") or []
    if not rounds:
        return Finding(claim, rule, NOT_MEASURED, [])
    evidence = [
        f"round {r['round']}: {r['sun_elevation_count']} sun elevations, {r['images']} training images, "
        + ", ".join(
            f"{label(m)} {r[m]:.3f}" for m in (LOOP_MODEL, *[m for m in ALL_MODELS if m != LOOP_MODEL]) if m in r
        )
        for r in rounds
    ]
    evidence.append(f"stopped: {history.get('stopped_because')}")
    final = float(rounds[-1][LOOP_MODEL])
    ok = abs(final - PAPER_LOOP_ACCURACY) <= 0.05
    return Finding(claim, rule, REPRODUCED if ok else NOT_REPRODUCED, evidence)


def findings(rows: list[dict], history: dict | None) -> list[Finding]:
    """The paper's five findings, in the order docs/results/README.md lists them, each with its verdict."""
    return [
        sun_elevation_rises(rows),
        large_roi_falls(rows),
        camera_elevation_gain(rows),
        camera_azimuth_not_monotonic(rows),
        loop_converges(history),
    ]


def render_page(rows: list[dict], history: dict | None, notes: str = "", figures: tuple[str, ...] = ()) -> str:
    """The comparison page (markdown); ``figures`` are image files beside it."""
    points = {(r["parameter"], r["count"], r["sigma"]) for r in rows}
    budget = sorted({int(r["train_images"]) for r in rows})
    lines = [
        "# The paper's findings at paper scale",
        "",
        "Generated by `crater-synth results` from `experiments.csv` and `loop_history.json` in this folder.",
        "",
        f"- Figure 6: {len(rows)} results ({len(points)} trainings of the planned "
        f"{len(PANEL_TITLES)} parameters × 5 counts × 3 σ = 60), models: "
        + ", ".join(label(m) for m in MODELS)
        + "."
        + (
            f" Training images per point: {budget[0]:,}" + (f"–{budget[-1]:,}." if len(budget) > 1 else ".")
            if budget
            else ""
        ),
        f"- Closed loop: {len((history or {}).get('rounds') or [])} round(s).",
    ]
    planned = len(PANEL_TITLES) * 5 * 3
    if rows and len(points) < planned:
        lines.append(
            f"- **Figure 6 is incomplete** ({len(points)} of {planned} trainings): each verdict below is read "
            "from the counts measured so far and is provisional."
        )
    if notes:
        lines += ["", notes.strip()]
    lines += ["", "| finding (paper) | here |", "|---|---|"]
    found = findings(rows, history)
    lines += [f"| {f.claim} | **{f.verdict}** |" for f in found]
    for f in found:
        lines += ["", f"## {f.claim}", "", f"**{f.verdict}**. Rule: {f.rule}.", ""]
        lines += [f"- {e}" for e in f.evidence] or ["- no results yet"]
    captions = {FIGURE_FILE: "Figure 6 at the paper's counts", HISTORY_PLOT: "closed loop (paper Fig. 3)"}
    if figures:
        lines += ["", "## Figures", ""] + [f"![{captions.get(f, f)}]({f})" for f in figures]
    return "\n".join(lines) + "\n"


def publish(experiments_dir: Path | None, loop_dir: Path | None, out: Path, notes: str = "") -> list[Finding]:
    """Copy the results into ``out`` and write the comparison page there. Every input is read and
    checked before the first file is written, so a bad input leaves ``out`` as it was."""
    rows: list[dict] = []
    csv_bytes = history_bytes = plot_bytes = None
    history = None
    if experiments_dir is not None:
        csv_path = experiments_dir / CSV_FILE
        if not csv_path.is_file():
            raise ConfigError(f"{csv_path} does not exist: run `crater-synth experiments` first")
        rows = read_results(csv_path)
        csv_bytes = csv_path.read_bytes()
    if loop_dir is not None:
        hist_path = loop_dir / HISTORY_FILE
        try:
            history_bytes = hist_path.read_bytes()
            history = json.loads(history_bytes)
        except FileNotFoundError:
            raise ConfigError(f"{hist_path} does not exist: run `crater-synth loop` first") from None
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{hist_path}: corrupt loop history ({exc})") from None
        if (loop_dir / HISTORY_PLOT).is_file():
            plot_bytes = (loop_dir / HISTORY_PLOT).read_bytes()
    out.mkdir(parents=True, exist_ok=True)
    figures: list[str] = []
    if csv_bytes is not None:
        atomic_write_bytes(out / CSV_FILE, csv_bytes)
        if rows:  # drawn again from the CSV, so the figure always shows exactly the published results
            plot_figure6(rows, out / FIGURE_FILE)
            figures.append(FIGURE_FILE)
    if history_bytes is not None:
        atomic_write_bytes(out / HISTORY_FILE, history_bytes)
        if plot_bytes is not None:
            atomic_write_bytes(out / HISTORY_PLOT, plot_bytes)
            figures.append(HISTORY_PLOT)
    atomic_write_text(out / PAGE_FILE, render_page(rows, history, notes, tuple(figures)))
    return findings(rows, history)


@click.command("results")
@click.option("--experiments", "experiments_dir", type=click.Path(path_type=Path), help="run_dir of `experiments`")
@click.option("--loop", "loop_dir", type=click.Path(path_type=Path), help="run_dir of `loop`")
@click.option("--out", type=click.Path(path_type=Path), default=Path("outputs/results"), show_default=True)
@click.option("--notes", type=click.Path(exists=True, path_type=Path), help="markdown put under the summary")
@user_errors
def results_command(experiments_dir, loop_dir, out, notes):
    """Check the paper's findings against a Figure 6 run and a loop run; write the page into --out.

    e.g. ``crater-synth results --experiments outputs/paper_fig6 --loop outputs/paper_loop``
    """
    if experiments_dir is None and loop_dir is None:
        raise ConfigError("give --experiments RUN_DIR and/or --loop RUN_DIR")
    found = publish(experiments_dir, loop_dir, out, notes.read_text() if notes else "")
    for f in found:
        click.echo(f"{f.verdict:>18}: {f.claim}")
    click.echo(f"page: {out / PAGE_FILE}")
