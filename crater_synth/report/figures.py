"""The report's figures: matplotlib (Agg, object API, no global pyplot state), one function per figure.
Each takes plain data and an output path and returns the PNG's file name; none reads an input file."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from crater_synth.dataset.preview import tone_map
from train.plots import plot_confusion
from train.registry import MODELS, SPECS, label

REAL_COLOR, SYN_COLOR, SENSOR_COLOR = "#d9480f", "#1c7ed6", "#5c7cfa"
_RC = {
    "font.size": 9,
    "axes.titlesize": 9,
    "axes.labelsize": 9,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "legend.fontsize": 8,
    "legend.frameon": False,
    "figure.dpi": 110,
}


def _rc():
    import matplotlib

    matplotlib.use("Agg")
    return matplotlib.rc_context(_RC)


def _new_figure(w: float, h: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(w, h), dpi=110)


def _save(fig, path: Path) -> str:
    fig.savefig(path, dpi=110, facecolor="white")
    return path.name


def confusion(path: Path, conf, classes: Sequence[str], title: str) -> str:
    """Re-plot a confusion matrix from metrics.json with the training stage's own plotter."""
    plot_confusion(path, conf, classes, title)
    return path.name


def stretch(x: np.ndarray, lo: float = 0.5, hi: float = 99.5) -> np.ndarray:
    """Percentile display stretch to [0, 1]."""
    a, b = np.percentile(x, [lo, hi])
    return np.clip((x - a) / max(b - a, 1e-9), 0.0, 1.0)


def compare_panel(
    path: Path,
    crater: str,
    row: dict,
    real_orig: np.ndarray,
    syn_orig: np.ndarray,
    i_f: np.ndarray,
    sigma_key: str,
    sigma_box: Sequence[float],
    rim_points: np.ndarray,
    real_pp: np.ndarray,
    syn_pp: np.ndarray,
    syn_sensor: np.ndarray | None,
    size: int,
) -> str:
    """2 x 3 panel: display originals (real, synthetic sigma crop, whole render) over the network inputs."""
    n_r, n_s = real_orig.shape[0], syn_orig.shape[0]
    with _rc():
        fig = _new_figure(8.8, 6.4)
        axes = fig.subplots(2, 3)
        for ax in axes.ravel():
            ax.set_xticks([])
            ax.set_yticks([])
            for sp in ax.spines.values():
                sp.set_visible(True)
        axes[0, 0].set_ylabel("display original", fontsize=10, fontweight="bold")
        axes[1, 0].set_ylabel(f"after preprocessing\n({size}×{size} network input)", fontsize=10, fontweight="bold")
        a = axes[0, 0]
        a.imshow(stretch(real_orig), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        a.set_title(f"real WAC crop, {n_r}×{n_r} mosaic px\n8-bit DN, 0.5–99.5 % stretch")
        a = axes[0, 1]
        a.imshow(syn_orig, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        a.set_title(f"synthetic σ={sigma_key} crop, {n_s}×{n_s} px\nI/F tone-mapped, gamma 2.2")
        a = axes[0, 2]
        a.imshow(tone_map(i_f), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        u0, v0, u1, v1 = sigma_box
        a.plot([u0, u1, u1, u0, u0], [v0, v0, v1, v1, v0], "--", color="#50c0ff", lw=0.9)
        a.plot(rim_points[:, 0], rim_points[:, 1], "-", color="#ff5050", lw=0.8)
        a.set_xlim(-0.5, i_f.shape[1] - 0.5)
        a.set_ylim(i_f.shape[0] - 0.5, -0.5)
        a.set_title(f"whole synthetic render ({i_f.shape[1]}×{i_f.shape[0]})\nred: rim, blue: σ box")
        for a, im, t in (
            (axes[1, 0], real_pp, "real"),
            (axes[1, 1], syn_pp, "synthetic"),
            (axes[1, 2], syn_sensor, "synthetic + sensor model (training)"),
        ):
            a.set_title(t)
            if im is None:
                a.text(0.5, 0.5, "sensor model disabled", ha="center", va="center", transform=a.transAxes)
                continue
            a.imshow(im, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        fig.suptitle(
            f"{crater}: real WAC vs closest synthetic render "
            f"(sun el {row['sun_elevation']:.2f}°, az {row['sun_azimuth']:.0f}°; "
            f"camera el {row['cam_elevation']:.0f}°, az {row['cam_azimuth']:.0f}°)",
            fontsize=10.5,
        )
        fig.tight_layout()
        return _save(fig, path)


def histograms(path: Path, panels: Sequence[dict], bins: np.ndarray) -> str:
    """One panel per crater (3 per row, as many rows as needed): real vs synthetic densities (log)."""
    n = len(panels)
    with _rc():
        cols = min(3, n)
        nrows = int(math.ceil(n / cols))
        fig = _new_figure(3.6 * cols, 2.9 * nrows)
        axes = np.atleast_1d(fig.subplots(nrows, cols, squeeze=False)).ravel()
        for ax in axes[n:]:
            ax.axis("off")
        for ax, p in zip(axes, panels):
            ax.stairs(p["real_density"], bins, color=REAL_COLOR, lw=1.6, label=f"real ({p['real_crops']} crops)")
            ax.stairs(p["syn_density"], bins, color=SYN_COLOR, lw=1.6, label=f"synthetic ({p['syn_crops']} crops)")
            if p["sensor_density"] is not None:
                ax.stairs(
                    p["sensor_density"], bins, color=SENSOR_COLOR, lw=1.1, ls="--", label="synthetic + sensor model"
                )
            ax.set_yscale("log")
            ax.set_xlim(0, 1)
            ax.set_xlabel("normalised intensity after preprocessing")
            ax.set_ylabel("density (log)")
            ax.set_title(f"{p['crater']}  (overlap real/synthetic {p['overlap']:.2f})")
            ax.legend(loc="upper center")
        fig.tight_layout()
        return _save(fig, path)


def loop_history(path: Path, rounds: Sequence[dict], threshold: float | None) -> str:
    """Left: real accuracy of each model per round; right: render and train time per round."""
    nan = float("nan")
    x = np.array([r["sun_elevation_count"] for r in rounds], dtype=float)
    with _rc():
        fig = _new_figure(10.0, 3.6)
        ax, ax2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.4, 1.0]})
        for k in MODELS:
            y = np.array([nan if r.get(k) is None else 100.0 * r[k] for r in rounds], dtype=float)
            if np.all(np.isnan(y)):
                continue
            ax.plot(x, y, "o-", color=SPECS[k].color, label=SPECS[k].label, lw=1.6, ms=5)
        if threshold is not None:
            ax.axhline(100.0 * threshold, color="#868e96", ls="--", lw=1, label=f"threshold {100 * threshold:.0f} %")
        for r in rounds:
            ax.annotate(
                f"r{r['round']}",
                (r["sun_elevation_count"], 0),
                xytext=(0, 3),
                textcoords="offset points",
                ha="center",
                fontsize=7,
                color="#868e96",
            )
        ax.set_xticks(sorted(set(x.tolist())))
        ax.set_ylim(0, 102)
        ax.set_xlabel("sun-elevation sample count (round rN)")
        ax.set_ylabel("real accuracy (%)")
        ax.set_title("accuracy on real crops per loop round")
        ax.legend(loc="lower right")
        idx = np.arange(len(rounds))
        rs = np.array([r.get("render_s") or 0.0 for r in rounds], dtype=float) / 60.0
        ts = np.array([r.get("train_s") or 0.0 for r in rounds], dtype=float) / 60.0
        ax2.bar(idx, rs, color="#adb5bd", label="render")
        ax2.bar(idx, ts, bottom=rs, color="#495057", label="train + evaluate")
        for i, r in enumerate(rounds):
            if r.get("images") is not None:
                ax2.annotate(
                    f"{int(r['images']):,} img",
                    (i, rs[i] + ts[i]),
                    xytext=(0, 2),
                    textcoords="offset points",
                    ha="center",
                    fontsize=7,
                )
        ax2.set_xticks(idx, [f"r{r['round']}\n({r['sun_elevation_count']})" for r in rounds])
        ax2.set_ylabel("minutes")
        ax2.set_title("time per round")
        ax2.legend(loc="upper left")
        fig.tight_layout()
        return _save(fig, path)


def figure6(path: Path, rows: Sequence[dict], models: Sequence[str]) -> str:
    """Figure 6 re-plotted from experiments.csv: one panel per parameter, colour = sigma, style = model."""
    import matplotlib

    params = list(dict.fromkeys(r["parameter"] for r in rows))
    sigmas = sorted({r["sigma"] for r in rows})
    styles = ["-", "--", ":", "-."]
    cmap = matplotlib.colormaps["viridis"]
    with _rc():
        fig = _new_figure(3.0 * len(params) + 0.6, 3.2)
        axes = np.atleast_1d(fig.subplots(1, len(params), squeeze=False)).ravel()
        for ax, p in zip(axes, params):
            for si, s in enumerate(sigmas):
                color = cmap(0.15 + 0.7 * si / max(1, len(sigmas) - 1))
                for mi, mdl in enumerate(models):
                    pts = sorted(
                        (r["count"], r["real_accuracy"])
                        for r in rows
                        if r["parameter"] == p and r["sigma"] == s and r["model"] == mdl
                    )
                    if pts:
                        ax.plot(
                            [c for c, _ in pts],
                            [100 * a for _, a in pts],
                            styles[mi % 4],
                            marker="o",
                            ms=3,
                            color=color,
                            label=f"σ={s:.1f} {label(mdl)}",
                        )
            ax.set_title(p.replace("_", " "))
            ax.set_xticks(sorted({r["count"] for r in rows if r["parameter"] == p}))
            ax.set_xlabel("sample count")
            ax.set_ylim(0, 102)
        axes[0].set_ylabel("real accuracy (%)")
        axes[-1].legend(loc="lower right", fontsize=6)
        fig.tight_layout()
        return _save(fig, path)


def fidelity_panel(
    path: Path, crater: str, real: np.ndarray, single: np.ndarray, trained: np.ndarray, frames: int, row: dict
) -> str:
    """1 x 3 network inputs: the real crop, one render, and the training image (composite + sensor)."""
    with _rc():
        fig = _new_figure(7.5, 2.9)
        axes = fig.subplots(1, 3)
        for ax, im, t in (
            (axes[0], real, "real WAC mosaic"),
            (axes[1], single, f"one render (sun {row['sun_elevation']:.2f}°)"),
            (axes[2], trained, f"training image ({frames} frames + sensor)"),
        ):
            ax.imshow(im, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            ax.set_title(t, fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
        fig.suptitle(crater, fontsize=10.5)
        fig.tight_layout()
        return _save(fig, path)


NAV_DETECTOR_COLOR, NAV_PERFECT_COLOR = "#d9480f", "#1c7ed6"


_NAV_RUNS = (  # (frame record key, colour, marker, legend name, strip label) of each fix shown
    ("detector", NAV_DETECTOR_COLOR, "o", "detector", "detector"),
    ("perfect", NAV_PERFECT_COLOR, "s", "perfect detections", "perfect"),
)


def _plot_fix_errors(ax, strip, idx: np.ndarray, frames: Sequence[dict], false_fix_km: float) -> None:
    """Top panel: each run's fix error per frame (log scale), the detector's before refinement (hollow),
    the patch fixes (ringed) and the false-fix line; crosses in ``strip`` where a run has no fix."""
    errs = []
    for row, (key, color, marker, name, _) in enumerate(_NAV_RUNS):
        recs = [f if key == "detector" else f["perfect"] for f in frames]
        fixed = np.array([bool(r["fix"]) for r in recs])
        e_m = np.array([1000.0 * r["error_km"] if r["fix"] else np.nan for r in recs], dtype=float)
        e_m = np.maximum(e_m, 1e-4)  # an exact fix still shows on the log axis (0.1 mm)
        errs += e_m[fixed].tolist()
        ax.plot(
            idx[fixed],
            e_m[fixed],
            marker,
            color=color,
            ms=6,
            ls="-" if fixed.sum() > 1 else "none",
            lw=1,
            label=f"{name}: {int(fixed.sum())} of {len(recs)} frames fixed",
        )
        strip.plot(idx[~fixed], np.full(int((~fixed).sum()), row), "x", color=color, ms=7, mew=1.6)
    plain = [(i, 1000.0 * f["unrefined"]["error_km"]) for i, f in zip(idx, frames) if f.get("unrefined")]
    if plain:  # the same fixes before the appearance refinement (hollow)
        ax.plot(
            *np.array(plain).T, "o", mfc="none", color=NAV_DETECTOR_COLOR, ms=6, label="detector, before refinement"
        )
        errs += [e for _, e in plain]
    patched = [
        (i, 1000.0 * f["error_km"]) for i, f in zip(idx, frames) if f["fix"] and f.get("fix_source") == "patches"
    ]
    if patched:  # the frames the craters did not fix and terrain patches did (nav-frames-eval --patches)
        ax.plot(*np.array(patched).T, "D", mfc="none", color="#1c9fd6", ms=11, label="fixed by terrain patches")
    fx = 1000.0 * false_fix_km
    ax.axhline(fx, color="#868e96", ls="--", lw=1)
    ax.text(idx.max(), fx, f"false fix > {false_fix_km:g} km ", ha="right", va="bottom", fontsize=7, color="#868e96")
    lo, hi = (min(errs), max(errs)) if errs else (1e-2, 1e3)
    ax.set_yscale("log")
    ax.set_ylim(lo / 10.0, max(hi, fx) * 10.0)
    ax.set_ylabel("position error of the fix (m, log)")
    ax.legend(loc="upper left", ncol=2)
    strip.set_ylim(-0.7, 1.7)
    strip.set_yticks([0, 1], [short for *_, short in _NAV_RUNS], fontsize=7)
    strip.set_ylabel("no fix", fontsize=8, rotation=0, ha="right", va="center", labelpad=4)
    strip.spines["left"].set_visible(False)
    strip.tick_params(axis="y", length=0)


def _plot_landmark_counts(ax2, idx: np.ndarray, frames: Sequence[dict], min_inliers: int | None) -> None:
    """Bottom panel: landmarks in view (all, usable), matched by the detector, identified by the
    perfect-detection fix, the inliers a fix needs, and the detection count on the right axis."""
    view = np.array([f["landmarks_in_view"] for f in frames], dtype=float)
    usable = [f.get("landmarks_in_view_min_d") for f in frames]
    ax2.bar(idx, view, color="#e9ecef", width=0.75, label="landmarks in view (all labels)")
    if all(is_n is not None for is_n in usable):
        ax2.bar(idx, usable, color="#adb5bd", width=0.45, label="of the map's minimum size (usable)")
    ax2.plot(
        idx,
        [f["matched"] for f in frames],
        "o-",
        color=NAV_DETECTOR_COLOR,
        ms=4,
        lw=1.2,
        label="matched by the detector",
    )
    pf = np.array([bool(f["perfect"]["fix"]) for f in frames])
    ax2.plot(
        idx[pf],
        [f["perfect"]["identified"] for f, ok in zip(frames, pf) if ok],
        "s",
        color=NAV_PERFECT_COLOR,
        ms=5,
        label="identified in the perfect-detection fix",
    )
    if min_inliers:
        ax2.axhline(min_inliers, color="#868e96", ls="--", lw=1)
        ax2.text(
            idx.max(), min_inliers, f"a fix needs {min_inliers} ", ha="right", va="bottom", fontsize=7, color="#868e96"
        )
    ax2.set_ylabel("landmarks")
    ax2.set_ylim(0, max(1.0, view.max()) * 1.5)
    ax3 = ax2.twinx()
    ax3.plot(idx, [f["n_detections"] for f in frames], ":", color="#495057", lw=1.2, label="detections (right axis)")
    ax3.set_ylabel("detections", color="#495057")
    ax3.spines["right"].set_visible(True)
    ax3.set_ylim(0, max(1.0, max(f["n_detections"] for f in frames)) * 1.5)
    h1, l1 = ax2.get_legend_handles_labels()
    h2, l2 = ax3.get_legend_handles_labels()
    ax2.legend(h1 + h2, l1 + l2, loc="upper right", ncol=2)


def nav_trajectory(
    path: Path, trajectory: str, frames: Sequence[dict], false_fix_km: float = 5.0, min_inliers: int | None = None
) -> str:
    """Per frame of a rendered trajectory (x: frame number, with its altitude). Top: the position error
    of the fix (metres, log scale) of the detector (hollow: before its appearance refinement, where the
    frames record it) and of the perfect-detection check; below it, a strip
    with a cross where a frame has no fix. Bottom: the landmarks in view (all labels, and those of the
    map's minimum size the fix can use), those the detector matched, those the perfect-detection fix
    identified, and the detection count (right axis). A fix from terrain patches is ringed (a diamond)."""
    idx = np.array([f["index"] for f in frames], dtype=float)
    alt = [f["altitude_km"] for f in frames]
    with _rc():
        fig = _new_figure(9.0, 7.0)
        ax, strip, ax2 = fig.subplots(
            3, 1, sharex=True, gridspec_kw={"height_ratios": [1.5, 0.32, 1.1], "hspace": 0.08}
        )
        _plot_fix_errors(ax, strip, idx, frames, false_fix_km)
        ax.set_title(f"{trajectory}: fix error per frame")
        _plot_landmark_counts(ax2, idx, frames, min_inliers)
        step = max(1, len(idx) // 16)
        ax2.set_xticks(idx[::step], [f"{int(i)}\n{a:.0f} km" for i, a in zip(idx[::step], alt[::step])])
        ax2.set_xlabel("frame (altitude)")
        fig.subplots_adjust(left=0.15, right=0.9, top=0.95, bottom=0.1)
        return _save(fig, path)
