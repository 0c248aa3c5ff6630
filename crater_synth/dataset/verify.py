"""``crater-synth verify DIR``: check a dataset's manifest against its files and their labels.

What a passing ``verify`` proves, and what it does not, is stated in docs/manifest.md ("What verify
proves and what it does not")."""

from __future__ import annotations

import errno
import fcntl
import os
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import click

from crater_core import schema
from crater_core.exr import ExrError, exr_info
from crater_core.progress import Progress
from crater_core.render_labels import label_faults
from crater_synth.cli_common import user_errors
from crater_synth.dataset.disk import JOBS_DIR, find_orphans, holder
from crater_synth.dataset.manifest import stale_parts
from crater_synth.errors import UserError

# Below this many files per process, a pool costs more than it saves (process start-up).
PARALLEL_MIN_FILES_PER_JOB = 200
RESUME_HINT = "re-run `crater-synth dataset` with the same settings to resume"


def check_file(check: tuple) -> list[str]:
    """Faults of one row's file: ``check`` = (dataset dir, row, decode). The file must stay inside the
    dataset, exist, hash to the row's sha256, open as a tiled EXR with the contract's channels and the
    row's size, carry in its header the labels the row states and (``decode``) hold finite pixels."""
    d, row, decode = check
    try:
        f = schema.row_file(d, row)
    except schema.ManifestError as exc:
        return [str(exc)]
    if not f.is_file():
        return [f"{f}: missing"]
    if schema.sha256_file(f) != row["sha256"]:
        return [f"{f}: sha256 mismatch (corrupt or changed)"]
    try:
        info = exr_info(f, decode)
    except ExrError as exc:
        return [str(exc)]
    faults = []
    expected = set(schema.EXR_CHANNELS)
    if set(info["channels"]) != expected:
        faults.append(f"{f}: channels {info['channels']} != {sorted(expected)}")
    if (info["width"], info["height"]) != (row["width"], row["height"]):
        faults.append(f"{f}: size {info['width']}x{info['height']} != row {row['width']}x{row['height']}")
    if not info["tiled"]:
        faults.append(f"{f}: not tiled")
    if info["finite"] is False:
        faults.append(f"{f}: non-finite pixels")
    return faults + label_faults(row, info["header"], str(f))


def live_writer(dataset_dir: Path) -> str | None:
    """Who is writing the dataset now (``pid N on HOST, since ...``), or None.

    A writer holds ``.dataset.lock`` exclusively (a whole sweep) or a shard lock exclusively
    (``launcher.shard``; crater_synth.dataset.disk.DatasetLock). Each lock is probed with a shared,
    non-blocking flock released at once: it fails only while an exclusive holder lives (the kernel drops
    the lock of a killed writer). No lock file is created. A writer that starts within the microseconds
    of a probe is refused as if a shard held the directory; it can simply be started again."""
    for lock in sorted(Path(dataset_dir).glob(".dataset*.lock")):
        try:
            fh = open(lock)
        except OSError:
            continue
        with fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except OSError as exc:
                if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    return holder(lock)
                continue
            fcntl.flock(fh, fcntl.LOCK_UN)
    return None


def _part_writer(part: Path, stale: bool) -> str:
    """Who wrote a part file named ``<name>-<host>-<pid>.jsonl``."""
    fields = part.stem.rsplit("-", 2)
    if len(fields) != 3:
        return f"writer {part.stem}"
    _, host, pid = fields
    return f"pid {pid}, no longer running" if stale else f"pid {pid} on {host}"


def unmerged_parts(dataset_dir: Path, writer: str | None) -> list[tuple[Path, list[dict], str]]:
    """Manifest part files no running writer will merge: (part, its rows, whose). While a writer runs
    (``writer``), only the parts of dead writers on this host count (the others may be its own)."""
    parts_dir = Path(dataset_dir) / schema.PARTS_DIR
    if not parts_dir.is_dir():
        return []
    stale = set(stale_parts(Path(dataset_dir)))
    out = []
    for part in sorted(parts_dir.glob("*.jsonl")):
        if writer is not None and part not in stale:
            continue
        rows = list(schema.iter_rows(part))
        if rows:
            out.append((part, rows, _part_writer(part, part in stale)))
    return out


def _exr_files(d: Path) -> list[Path]:
    """The render files one level down (``<crater>/*.exr``), not temp files."""
    return [
        f
        for sub in d.iterdir()
        if sub.is_dir() and sub.name != JOBS_DIR
        for f in sub.glob("*.exr")
        if not f.name.startswith(".")
    ]


def verify_dataset(
    dataset_dir: str | Path, decode: bool = True, jobs: int | None = None, progress: bool = False
) -> dict:
    """Check every row: readable line, path inside the dataset, file exists, hashes to its sha256,
    opens as a tiled EXR with the contract's channels and the row's size, and carries in its header
    the labels the row states; no duplicate renders, paths or files; no empty manifest beside renders;
    no rows of an interrupted run left unmerged. The files are checked by ``jobs`` processes (default:
    one per core; one for small datasets); ``progress``: the files checked, with rate and ETA, on stderr.

    Returns a report dict with ``faults`` (list of one-line strings), counts, ``in_progress`` (the live
    writer, or None: then the dataset is not verified, ``ok`` is False) and ``orphans``: files no row
    names (EXRs, temp files of interrupted writes), which are not faults -- the next ``crater-synth
    dataset`` run removes them. Raises :class:`UserError` where there is no manifest to check.
    """
    d = Path(dataset_dir)
    manifest = d / schema.MANIFEST_NAME
    writer = live_writer(d) if d.is_dir() else None
    unmerged = unmerged_parts(d, writer)
    if not manifest.is_file():
        if writer is not None:
            raise UserError(
                f"{d}: dataset in progress ({writer}), no {schema.MANIFEST_NAME} yet: verify it when the run has ended"
            )
        if unmerged:
            n = sum(len(rows) for _, rows, _ in unmerged)
            raise UserError(
                f"{d}: an interrupted `crater-synth dataset` run ({unmerged[0][2]}) left {n} rows in "
                f"{schema.PARTS_DIR}/ and no {schema.MANIFEST_NAME}: {RESUME_HINT}"
            )
        raise UserError(f"{d}: no {schema.MANIFEST_NAME} (not a dataset directory)")
    faults: list[str] = []
    rows: list[dict] = []
    for _, row, error in schema.manifest_lines(manifest):
        if error is None:
            rows.append(row)
        else:
            faults.append(error)
    faults += schema.duplicate_faults(rows)
    if not rows and not faults and writer is None:  # an emptied manifest must not pass as an empty dataset
        unmerged_files = {str(d / r["path"]) for _, part_rows, _ in unmerged for r in part_rows}
        n_files = sum(str(f) not in unmerged_files for f in _exr_files(d))
        if n_files:
            faults.append(f"{manifest} lists no rows, but {n_files} EXR files lie beside it")
    checks = [(str(d), r, decode) for r in rows]
    faults += _check_files(checks, jobs, progress)
    faults += [
        f"{part}: {len(part_rows)} rows of an interrupted run ({who}) were never merged: {RESUME_HINT}"
        for part, part_rows, who in unmerged
    ]
    known = rows + [r for _, part_rows, _ in unmerged for r in part_rows]
    found = [str(p) for p in find_orphans(d, known)]
    # While a writer runs, files without a merged row are its renders in progress, not orphans.
    orphans, in_flight = (found, []) if writer is None else ([], found)
    return {
        "dataset": str(d),
        "rows": len(rows),
        "craters": dict(Counter(r["crater"] for r in rows)),
        "faults": faults,
        "orphan_files": len(orphans),
        "orphans": orphans,
        "in_progress": writer,
        "in_flight_files": len(in_flight),
        "ok": not faults and writer is None,
    }


def _check_files(checks: list[tuple], jobs: int | None, progress: bool) -> list[str]:
    """:func:`check_file` of every check, in ``jobs`` processes where there are enough files."""
    n_jobs = max(1, min(jobs or os.cpu_count() or 1, len(checks) // PARALLEL_MIN_FILES_PER_JOB))
    faults: list[str] = []
    with Progress(len(checks), "verify", "file", "auto" if progress and checks else "off") as bar:
        if n_jobs > 1:  # hashing and decoding are CPU-bound: one process per core
            with ProcessPoolExecutor(n_jobs) as pool:
                for result in pool.map(check_file, checks, chunksize=64):
                    faults += result
                    bar.update()
        else:
            for check in checks:
                faults += check_file(check)
                bar.update()
    return faults


@click.command("verify")
@click.argument("dataset_dir", type=click.Path(file_okay=False))
@click.option("--no-decode", is_flag=True, help="Hash the files and check their headers; do not decode the pixels.")
@click.option(
    "--jobs", type=click.IntRange(min=1), default=None, help="Processes checking files [default: one per core]."
)
@user_errors
def verify_command(dataset_dir, no_decode, jobs):
    """Verify a dataset: every row's file exists, opens, hashes right and carries the row's labels in
    its header; no duplicates.

    Prints one summary line (and, on stderr, the files checked with rate and ETA); exits non-zero on any
    fault (each fault on stderr) and while a `crater-synth dataset` run is still writing the directory.
    Files no row names are listed as `orphan:` lines (the next `crater-synth dataset` run removes them).
    docs/manifest.md says what a pass proves and what it does not.
    """
    report = verify_dataset(dataset_dir, decode=not no_decode, jobs=jobs, progress=True)
    for fault in report["faults"]:
        click.echo(f"fault: {fault}", err=True)
    for orphan in report["orphans"]:
        click.echo(f"orphan: {orphan} (no manifest row; the next `crater-synth dataset` run removes it)", err=True)
    if report["in_progress"]:
        status = f"INCOMPLETE, dataset in progress ({report['in_progress']})"
        files = f"{report['in_flight_files']} files not merged yet"
    else:
        status = "OK" if report["ok"] else f"FAILED ({len(report['faults'])} faults)"
        files = f"{report['orphan_files']} orphan files"
    click.echo(f"verify {status}: {report['rows']} rows {report['craters']}, {files}, in {report['dataset']}")
    if not report["ok"]:
        raise SystemExit(1)
