"""``crater-synth verify DIR``: check a dataset's manifest against its files."""

from __future__ import annotations

import json
import os
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import click

from crater_core import schema
from crater_core.exr import ExrError, exr_info
from crater_synth.cli_common import user_errors
from crater_synth.dataset.disk import find_orphans
from crater_synth.errors import UserError

# Below this many files per process, a pool costs more than it saves (process start-up).
PARALLEL_MIN_FILES_PER_JOB = 200


def check_file(check: tuple) -> list[str]:
    """Faults of one row's file: ``check`` = (path, sha256, width, height, decode)."""
    path, sha256, width, height, decode = check
    f = Path(path)
    if not f.is_file():
        return [f"{f}: missing"]
    if schema.sha256_file(f) != sha256:
        return [f"{f}: sha256 mismatch (corrupt or changed)"]
    if not decode:
        return []
    try:
        info = exr_info(f)
    except ExrError as exc:
        return [str(exc)]
    faults = []
    expected = set(schema.EXR_CHANNELS)
    if set(info["channels"]) != expected:
        faults.append(f"{f}: channels {info['channels']} != {sorted(expected)}")
    if (info["width"], info["height"]) != (width, height):
        faults.append(f"{f}: size {info['width']}x{info['height']} != row {width}x{height}")
    if not info["tiled"]:
        faults.append(f"{f}: not tiled")
    if not info["finite"]:
        faults.append(f"{f}: non-finite pixels")
    return faults


def verify_dataset(dataset_dir: str | Path, decode: bool = True, jobs: int | None = None) -> dict:
    """Check every row: file exists, hashes to its sha256, opens as a tiled EXR with the contract's
    channels and the row's size; no duplicate rows or paths; no unreadable manifest lines.
    The files are checked by ``jobs`` processes (default: one per core; one for small datasets).

    Returns a report dict with ``faults`` (list of one-line strings), counts, and ``orphans``: files no
    row names (EXRs, temp files of interrupted writes), which are not faults -- the next
    ``crater-synth dataset`` run on the directory removes them.
    """
    d = Path(dataset_dir)
    manifest = d / schema.MANIFEST_NAME
    if not manifest.is_file():
        raise UserError(f"{d}: no {schema.MANIFEST_NAME} (not a dataset directory, or never merged)")
    faults: list[str] = []
    rows: list[dict] = []
    with open(manifest, encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, 1):
            try:
                rows.append(schema.validate_row(json.loads(line), f"{manifest}:{lineno}"))
            except (ValueError, schema.ManifestError) as exc:
                faults.append(f"{manifest}:{lineno}: unreadable row ({exc})")
    keys = Counter(schema.row_key(r) for r in rows)
    paths = Counter(r["path"] for r in rows)
    faults += [f"duplicate row {k}" for k, n in keys.items() if n > 1]
    faults += [f"duplicate path {p}" for p, n in paths.items() if n > 1]
    checks = [(str(d / r["path"]), r["sha256"], r["width"], r["height"], decode) for r in rows]
    n_jobs = max(1, min(jobs or os.cpu_count() or 1, len(checks) // PARALLEL_MIN_FILES_PER_JOB))
    if n_jobs > 1:  # hashing and decoding are CPU-bound: one process per core
        with ProcessPoolExecutor(n_jobs) as pool:
            results = list(pool.map(check_file, checks, chunksize=64))
    else:
        results = [check_file(c) for c in checks]
    faults += [fault for result in results for fault in result]
    orphans = [str(p) for p in find_orphans(d, rows)]
    return {
        "dataset": str(d),
        "rows": len(rows),
        "craters": dict(Counter(r["crater"] for r in rows)),
        "faults": faults,
        "orphan_files": len(orphans),
        "orphans": orphans,
        "ok": not faults,
    }


@click.command("verify")
@click.argument("dataset_dir", type=click.Path(file_okay=False))
@click.option("--no-decode", is_flag=True, help="Only hash the files; do not decode the EXRs.")
@click.option(
    "--jobs", type=click.IntRange(min=1), default=None, help="Processes checking files [default: one per core]."
)
@user_errors
def verify_command(dataset_dir, no_decode, jobs):
    """Verify a dataset: every row's file exists, opens and hashes right; no duplicates.

    Prints one summary line; exits non-zero on any fault (each fault on stderr). Files no row names
    are listed as `orphan:` lines (the next `crater-synth dataset` run removes them).
    """
    report = verify_dataset(dataset_dir, decode=not no_decode, jobs=jobs)
    for fault in report["faults"]:
        click.echo(f"fault: {fault}", err=True)
    for orphan in report["orphans"]:
        click.echo(f"orphan: {orphan} (no manifest row; the next `crater-synth dataset` run removes it)", err=True)
    status = "OK" if report["ok"] else f"FAILED ({len(report['faults'])} faults)"
    click.echo(
        f"verify {status}: {report['rows']} rows {report['craters']}, "
        f"{report['orphan_files']} orphan files, in {report['dataset']}"
    )
    if not report["ok"]:
        raise SystemExit(1)
