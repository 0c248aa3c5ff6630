"""``crater-synth verify DIR``: check a dataset's manifest against its files."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import click

from crater_core import schema
from crater_core.exr import ExrError, exr_info
from crater_synth.cli_common import user_errors
from crater_synth.dataset.disk import find_orphans
from crater_synth.errors import UserError


def verify_dataset(dataset_dir: str | Path, decode: bool = True) -> dict:
    """Check every row: file exists, hashes to its sha256, opens as a tiled EXR with the contract's
    channels and the row's size; no duplicate rows or paths; no unreadable manifest lines.

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
    expected = set(schema.EXR_CHANNELS)
    for r in rows:
        f = d / r["path"]
        if not f.is_file():
            faults.append(f"{f}: missing")
            continue
        if schema.sha256_file(f) != r["sha256"]:
            faults.append(f"{f}: sha256 mismatch (corrupt or changed)")
            continue
        if decode:
            try:
                info = exr_info(f)
            except ExrError as exc:
                faults.append(str(exc))
                continue
            if set(info["channels"]) != expected:
                faults.append(f"{f}: channels {info['channels']} != {sorted(expected)}")
            if (info["width"], info["height"]) != (r["width"], r["height"]):
                faults.append(f"{f}: size {info['width']}x{info['height']} != row {r['width']}x{r['height']}")
            if not info["tiled"]:
                faults.append(f"{f}: not tiled")
            if not info["finite"]:
                faults.append(f"{f}: non-finite pixels")
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
@user_errors
def verify_command(dataset_dir, no_decode):
    """Verify a dataset: every row's file exists, opens and hashes right; no duplicates.

    Prints one summary line; exits non-zero on any fault (each fault on stderr). Files no row names
    are listed as `orphan:` lines (the next `crater-synth dataset` run removes them).
    """
    report = verify_dataset(dataset_dir, decode=not no_decode)
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
