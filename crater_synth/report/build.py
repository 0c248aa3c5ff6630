"""``build_report`` and the ``crater-synth report`` command: validate every input, gather and render the
page in a temporary directory inside RUN_DIR, then publish it atomically."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Sequence

import click

from crater_core.files import umask
from crater_core.sweep import rows_in_selection
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.outfolder import OutFolder, check_replaceable, mark_filled
from crater_synth.report import gather
from crater_synth.report.inputs import (
    EXPERIMENTS_FILE,
    FIGURE6_FILE,
    LOOP_FILE,
    METRICS_FILE,
    NAVIGATION_DIR,
    RUN_CONFIG_FILE,
    SUMMARY_FILE,
    ReportError,
    check_png,
    dataset_rows,
    effective_config,
    load_experiments,
    load_loop_history,
    load_metrics,
    load_nav_demo,
    load_nav_frames,
    load_summary,
    nav_paths,
)
from crater_synth.report.page import render_page
from crater_synth.report.publish import publish
from train.registry import MODELS

REPORT_DIR = "report"
INDEX_FILE = "index.html"


def build_report(
    run_dir: str | Path,
    overrides: Sequence[str] = (),
    max_tiles: int = 36,
    hist_samples: int = 48,
    log: Callable[[str], None] | None = None,
) -> Path:
    """Write ``RUN_DIR/report/index.html`` (+ PNGs) and return its path. Holds RUN_DIR's lock: refused while
    `train`, `evaluate`, `loop` (crater_synth.evaluation.run_folder) or another report writes there."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ReportError(f"run directory {run_dir} does not exist (`{gather.PRODUCERS['metrics'][1]}` writes it)")
    lock = OutFolder(run_dir, "run", flag="RUN_DIR").lock()  # the lock a run_dir's writers take
    try:
        page = _build_report(run_dir, overrides, max_tiles, hist_samples, log)
    except BaseException:
        lock.discard()  # the lock file too, if this run created it
        raise
    lock.release()
    return page


def _build_report(
    run_dir: Path, overrides: Sequence[str], max_tiles: int, hist_samples: int, log: Callable[[str], None] | None
) -> Path:
    if max_tiles < 1 or hist_samples < 1:
        raise ReportError("--max-tiles and --hist-samples must be >= 1")
    # The old report is replaced whole: refused if it holds a file the report did not write.
    check_replaceable(run_dir / REPORT_DIR, "report", "RUN_DIR/report", _report_before_markers)
    run_outputs = (METRICS_FILE, LOOP_FILE, EXPERIMENTS_FILE, SUMMARY_FILE, RUN_CONFIG_FILE, gather.ABLATION_FILE)
    has_run = any((run_dir / name).exists() for name in (*run_outputs, FIGURE6_FILE))
    if not has_run and not any(run_dir.glob("confusion_*.png")) and not (run_dir / NAVIGATION_DIR).is_dir():
        # nothing of a run here: e.g. a typo in RUN_DIR
        raise ReportError(
            f"run directory {run_dir} holds no run to report (none of {', '.join(run_outputs)}, {NAVIGATION_DIR}/): "
            f"run `{gather.PRODUCERS['metrics'][1]}` first, or give the run_dir it wrote"
        )
    rc = effective_config(run_dir, overrides)
    metrics = load_metrics(run_dir / METRICS_FILE)
    # Validate every optional input up front: a corrupt one fails before any work.
    load_loop_history(run_dir / LOOP_FILE)
    load_experiments(run_dir / EXPERIMENTS_FILE)
    check_png(run_dir / FIGURE6_FILE)
    load_summary(run_dir / SUMMARY_FILE)
    gather.load_ablation(gather.ablation_path(run_dir, rc.cfg))
    for m in MODELS:
        check_png(run_dir / f"confusion_{m}.png")
    nav_demo, nav_frames = nav_paths(run_dir)
    load_nav_demo(nav_demo)
    for path in nav_frames:
        load_nav_frames(path)
    all_rows = dataset_rows(rc.dataset_dir)
    rows = all_rows
    selection = (rc.cfg.get("train") or {}).get("select")
    if all_rows is not None and selection:
        rows = rows_in_selection(all_rows, dict(selection))
    tmp = Path(tempfile.mkdtemp(prefix=".report.tmp-", dir=run_dir))
    try:
        mask = umask()
        os.chmod(tmp, 0o777 & ~mask)
        ctx = gather.Ctx(
            run_dir=run_dir,
            out=tmp,
            rc=rc,
            metrics=metrics,
            rows=rows,
            all_rows=all_rows,
            craters=gather.crater_order(metrics, rc.cfg, rows),
            max_tiles=max_tiles,
            hist_samples=hist_samples,
            log=log,
        )
        page = render_page(ctx)
        for f in tmp.iterdir():  # mkstemp-written PNGs (preview) are 0600
            os.chmod(f, 0o666 & ~mask)
        with open(tmp / INDEX_FILE, "w", encoding="utf-8") as fh:
            fh.write(page)
            fh.flush()
            os.fsync(fh.fileno())
        final = run_dir / REPORT_DIR
        mark_filled(tmp, "report")
        publish(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final / INDEX_FILE


def _report_before_markers(folder: Path) -> bool:
    """A report written before markers: its page and PNGs only, the page this command's."""
    try:
        page = (folder / INDEX_FILE).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return False
    files = [p for p in folder.rglob("*") if not p.is_dir()]
    return "crater-synth run report" in page and all(
        p.parent == folder and p.suffix in (".png", ".html") for p in files
    )


@click.command("report")
@click.argument("run_dir", type=click.Path(file_okay=False))
@OVERRIDES
@click.option("--max-tiles", default=36, show_default=True, help="Renders per contact sheet.")
@click.option(
    "--hist-samples", default=48, show_default=True, help="Renders per crater sampled for the input histograms."
)
@click.option("--quiet", "-q", is_flag=True, help="Only print the page's path.")
@user_errors
def report_command(run_dir, overrides, max_tiles, hist_samples, quiet):
    """Write RUN_DIR/report/index.html: contact sheets, real vs synthetic, input histograms, accuracies and
    confusion matrices, closed-loop history, Figure 6, fidelity ablation, crater navigation (RUN_DIR/navigation/),
    provenance and test-set limits.

    The dataset is the run's train.dataset_dir (from RUN_DIR/config.yaml when train saved it), or
    give train.dataset_dir=DIR. Absent inputs become "not run" notes; a corrupt one is an error.
    """
    log = None if quiet else (lambda msg: click.echo(f"report: {msg}", err=True))
    click.echo(str(build_report(run_dir, overrides, max_tiles, hist_samples, log)))
