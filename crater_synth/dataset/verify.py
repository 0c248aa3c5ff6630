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
from crater_core.detection_labels import LABEL_FILE_SUFFIX
from crater_core.progress import Progress
from crater_core.verify_file import RECORD_NAME, file_faults, manifest_kind, row_files, write_record
from crater_synth.cli_common import user_errors
from crater_synth.dataset.disk import JOBS_DIR, find_orphans, holder, temp_target
from crater_synth.dataset.manifest import stale_parts
from crater_synth.errors import UserError

# Below this many files per process, a pool costs more than it saves (process start-up).
PARALLEL_MIN_FILES_PER_JOB = 200
RESUME_HINT = "re-run `crater-synth dataset` with the same settings to resume"


def check_file(check: tuple) -> list[str]:
    """Faults of one row's file: ``check`` = (dataset dir, row, decode[, record kind, default render]);
    :func:`crater_core.verify_file.file_faults`, the one check of every reader."""
    d, row, decode, *kind = check
    return file_faults(kind[0] if kind else "render", d, row, decode)


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
    """Check a render dataset (``crater-synth dataset``), a nav-frames folder (``crater-synth nav-frames``)
    or a detection-frames folder (``crater-synth detection-frames``), its kind told by its manifest's rows
    (:func:`crater_core.verify_file.manifest_kind`): every row against its file
    (:func:`crater_core.verify_file.file_faults`: inside the dataset, exists, hashes to its sha256, a tiled
    EXR of the contract's channels and the row's size whose header carries the
    row's labels; with ``decode`` finite pixels under an intact seal) and the manifest as a whole. The
    files are checked by ``jobs`` processes (default: one per core; one for small datasets);
    ``progress``: the files checked, with rate and ETA, on stderr.

    Returns a report dict with ``kind``, ``faults`` (list of one-line strings), counts, ``in_progress``
    (the live writer, or None: then the dataset is not verified, ``ok`` is False), ``orphans``: files no
    row names, which are not faults, and ``recorded``: the ``.verified.json`` a pass writes (None when
    it failed or the directory is read-only), which train, export, nav-frames-eval and navigate trust
    for the files it lists unchanged. Raises :class:`UserError` where there is no manifest to check.
    """
    d = Path(dataset_dir)
    # No readable first row, or one of neither kind: the render reader reports every bad line.
    kind = manifest_kind(d) or "render"
    if kind == "render":
        report, rows = _verify_renders(d, decode, jobs, progress)
    else:
        report, rows = _verify_frames(d, kind, decode, jobs, progress)
    report["kind"], report["recorded"] = kind, None
    try:
        if report["ok"]:
            report["recorded"] = str(write_record(d, kind, rows, decode))
        elif d.is_dir():  # a recorded pass no longer holds
            (d / RECORD_NAME).unlink(missing_ok=True)
    except OSError:  # a read-only dataset: verified (or not), only not recorded
        pass
    return report


def _verify_renders(d: Path, decode: bool, jobs: int | None, progress: bool) -> tuple[dict, list[dict]]:
    """A render dataset: every row (readable line, its file), no duplicate renders, paths or files; no
    empty manifest beside renders; no rows of an interrupted run left unmerged. Orphans are files no row
    names (EXRs, temp files of interrupted writes): the next ``crater-synth dataset`` run removes them."""
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
    report = {
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
    return report, rows


def _frame_lines(manifest: Path) -> tuple[list[dict], list[str]]:
    """(rows, faults) of a frame folder's manifest: a line that is not a JSON object is one fault naming it."""
    lines = list(schema.manifest_lines(manifest, schema.json_object))
    return [row for _, row, _ in lines if row is not None], [error for _, _, error in lines if error is not None]


def orphan_note(path: Path, kind: str) -> str:
    """What the folder's writer does with a file no row names (docs/manifest.md): an interrupted write's temp
    file is removed by the next run; any other file is left alone (``dataset`` names those in its renders'
    folders in a warning; a file a planned render would write is proved or rendered again in place)."""
    if temp_target(path) is not None:
        return "an interrupted write's temp file; the next run that writes this folder removes it"
    if kind == "render":
        return "no manifest row; not a fault; `crater-synth dataset` leaves it alone unless a planned render writes it"
    return (
        "no manifest row; not a fault; `crater-synth nav-frames` adopts it where its header proves it one of the "
        "trajectory's frames, and otherwise refuses the folder while it is there"
    )


def _verify_frames(d: Path, kind: str, decode: bool, jobs: int | None, progress: bool) -> tuple[dict, list[dict]]:
    """A nav-frames or detection-frames folder (``kind``): every row against its frame, no frame index, file
    or content twice. Orphans are frame EXRs and label files no row names."""
    rows, faults = _frame_lines(d / schema.MANIFEST_NAME)
    for field in ("index", "rel_path", "sha256"):
        seen = Counter(str(r.get(field)) for r in rows)
        faults += [f"{d / schema.MANIFEST_NAME}: {field} {v} in {n} rows" for v, n in seen.items() if n > 1]
    faults += _check_files([(str(d), r, decode, kind) for r in rows], jobs, progress)
    named = {rel for r in rows for rel in row_files(kind, r)}
    candidates = [*d.glob("frame_*.exr"), *d.glob(f"frame_*{LABEL_FILE_SUFFIX}")]
    orphans = [str(f) for f in sorted(candidates) if f.name not in named]
    report = {
        "dataset": str(d),
        "rows": len(rows),
        "craters": dict(Counter(str(r.get("trajectory", kind)) for r in rows)),
        "faults": faults,
        "orphan_files": len(orphans),
        "orphans": orphans,
        "in_progress": None,
        "in_flight_files": 0,
        "ok": not faults,
    }
    return report, rows


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
@click.option(
    "--no-decode",
    is_flag=True,
    help="Hash the files and check their headers; do not decode the pixels or check their seal.",
)
@click.option(
    "--jobs", type=click.IntRange(min=1), default=None, help="Processes checking files [default: one per core]."
)
@user_errors
def verify_command(dataset_dir, no_decode, jobs):
    """Verify a dataset or a nav-frames folder: every row's file exists, opens, hashes right, carries
    the row's labels in its header and (unless --no-decode) its pixels under an intact seal; no duplicates.

    Prints one summary line (and, on stderr, the files checked with rate and ETA); exits non-zero on any
    fault (each fault on stderr) and while a `crater-synth dataset` run is still writing the directory.
    Files no row names are listed as `orphan:` lines, with what the folder's writer does with them.
    A pass is recorded in DATASET_DIR/.verified.json, which train, export, nav-frames-eval and navigate
    trust for the files it lists unchanged. docs/manifest.md says what a pass proves and what it does not.
    """
    report = verify_dataset(dataset_dir, decode=not no_decode, jobs=jobs, progress=True)
    for fault in report["faults"]:
        click.echo(f"fault: {fault}", err=True)
    for orphan in report["orphans"]:
        click.echo(f"orphan: {orphan} ({orphan_note(Path(orphan), report.get('kind', 'render'))})", err=True)
    if report["in_progress"]:
        status = f"INCOMPLETE, dataset in progress ({report['in_progress']})"
        files = f"{report['in_flight_files']} files not merged yet"
    else:
        status = "OK" if report["ok"] else f"FAILED ({len(report['faults'])} faults)"
        files = f"{report['orphan_files']} orphan files"
    what = "rows" if report["kind"] == "render" else "frames"
    click.echo(f"verify {status}: {report['rows']} {what} {report['craters']}, {files}, in {report['dataset']}")
    if not report["ok"]:
        raise SystemExit(1)
