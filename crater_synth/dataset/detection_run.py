"""``crater-synth detection-frames``: render a detection set into its folder, resumably (docs/procedural.md,
"Detection frames"; what one frame is: :mod:`crater_synth.dataset.detection`).

- **The folder** keeps the output-folder contract (:mod:`crater_synth.outfolder`, kind ``detection``): its
  marker names the set's recipe (:func:`recipe_key`: every setting that can change a pixel or a label, the
  frame width and the grouping), so frames of two recipes never mix; a folder holding a file the command
  did not write is refused; one writer at a time.
- **Resumption**: a frame whose row is in the manifest and whose files (frame, label file) are unchanged
  since they were written is kept; the others of the requested range are rendered. Each frame's row is
  appended to the manifest as soon as it is labelled (its own bytes, flushed; one fsync a chunk), where a
  rewrite would cost O(rows so far); the run compacts it (sorted, one row per frame, rows outside the
  range kept, rewritten atomically) once when it ends, normally or stopped by an exception or signal,
  copying each row's line from where it lies (a run holds a few numbers a frame, not its rows). A
  hard-killed run leaves an appended file, which the next run reads
  (:func:`crater_synth.dataset.detection.scan_manifest`) and compacts; its last chunk's files were never
  sealed, so each of its frames with a row is kept when its files hash to the row (:func:`kept_rows`):
  a kill loses only the frames not yet labelled.
- **Pipelining**: while the workers render one chunk of fields, a second process generates the next
  chunk's fields and writes their patches (``generate`` and the patch take ~1 s per field, which would
  otherwise leave the workers idle between chunks).
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from crater_core import schema
from crater_core.detection_labels import label_count, label_file_name, label_ref, label_rel_paths
from crater_core.horizon import HORIZON_VERSION
from crater_core.settings import replace
from crater_synth.dataset.detection import (
    CHUNK_PER_WORKER,
    PATCH_DIR,
    check_field_fits,
    field_of,
    frame_rel_path,
    frame_row,
    grouping,
    plan_field,
    scan_manifest,
)
from crater_synth.dataset.dispatch import run_workers
from crater_synth.dataset.identity import IGNORED, settings_payload
from crater_synth.errors import ConfigError, UserError
from crater_synth.outfolder import OutFolder

KIND = "detection-frames"


def recipe_key(settings) -> str:
    """The set's recipe: every setting that can change a frame's pixels or labels (the dataset's identity
    rule, crater_synth.dataset.identity), ``detection.*`` (which a sweep's identity leaves out) and the
    horizon maps' version."""
    payload = settings_payload(settings, IGNORED) | {"detection": settings.detection.as_dict()}
    return schema.content_key(payload | {"horizon_version": HORIZON_VERSION})


def kept_rows(
    folder: OutFolder, wanted: range, on_disk: dict[int, dict] | None = None
) -> tuple[dict[int, dict], set[int]]:
    """(the manifest's rows to keep, the wanted frames among them): rows outside ``wanted``, and wanted
    frames whose files (the frame, its label file) are unchanged since this writer wrote them
    (:func:`_unchanged`: sealed with the same size and mtime, or never sealed and hashing to the row).
    ``on_disk``: the manifest's :func:`_ref` of each row, read here when not given."""
    rows: dict[int, dict] = {}
    done: set[int] = set()
    for i, r in (manifest_refs(folder.path)[0] if on_disk is None else on_disk).items():
        if i not in wanted:
            rows[i] = r
        elif all(_unchanged(folder, rel, sha) for rel, sha in _files_and_hashes(r)):
            rows[i] = r
            done.add(i)
    return rows, done


def _files_and_hashes(ref: dict) -> list[tuple[str, str | None]]:
    """(file, its sha256 in the row) of a :func:`_ref`: the frame and its label file."""
    return [(ref["rel_path"], ref.get("sha256")), *zip(ref.get("label_files", []), ref.get("label_sha256", []))]


def _unchanged(folder: OutFolder, rel: str, sha: str | None) -> bool:
    """``rel`` is as this writer wrote it: sealed and unchanged since (size and mtime), or, listed but never
    sealed (a hard-killed run wrote it and then its row), hashing to the row's sha256."""
    if not (folder.path / rel).is_file() or rel not in folder.files:
        return False
    if folder.files[rel]:
        return folder.proved(rel)
    return sha is not None and schema.sha256_file(folder.path / rel) == sha


def _plan_chunk(settings, by_field: dict[int, list[int]], chunk_dir: Path):
    chunk_dir.mkdir(parents=True, exist_ok=True)
    return [plan_field(settings, f, idx, chunk_dir) for f, idx in by_field.items()]


def _kept(row: dict) -> dict:
    """What a run keeps of a manifest row (not the row: a frame's labels inline ran to ~0.5 MB in memory):
    its files and what the summary counts."""
    ref = label_ref(row)
    return {
        "rel_path": row["rel_path"],
        "sha256": row.get("sha256"),
        "label_files": label_rel_paths(row),
        "label_sha256": [] if ref is None else [ref.get("sha256")],
        "mode": row.get("mode"),
        "labels": label_count(row),
    }


def _ref(row: dict, at: tuple[int, int]) -> dict:
    """:func:`_kept` of a manifest row and where its line lies in the manifest (byte offset, length)."""
    return _kept(row) | {"at": at}


def manifest_refs(out_dir: Path) -> tuple[dict[int, dict], bool]:
    """(frame index -> :func:`_ref` of its row, compact) of the manifest in ``out_dir`` (:func:`scan_manifest`).
    Each row is reduced as it is read: a 22,528-frame set's manifest is ~10 GB of labels, which held as rows
    did not fit in 24 GB."""
    found, compact = scan_manifest(out_dir, keep=_kept)
    return {i: kept | {"at": (start, length)} for i, (start, length, kept) in found.items()}, compact


def _render_chunk(settings, fields: list[dict], folder: OutFolder, refs: dict) -> None:
    """Render the planned ``fields``, labelling each frame as it arrives (the host labels while the workers
    render) and appending its row to the manifest then (flushed: a killed process loses no row it wrote;
    fsynced once at the chunk's end); the frames' files are listed before and sealed after
    (:func:`_end_chunk`), and each frame's :func:`_ref` put in ``refs``. A hard-killed run's rows name files
    it never sealed; the next run keeps such a frame when its files hash to its row (:func:`kept_rows`)."""
    frames = {i: f for field in fields for i, f in field["frames"].items()}
    names = [name for i in frames for name in frame_files(i)]
    # The manifest is listed as being written while the chunk renders: a run killed while appending leaves
    # a file whose size the marker cannot know, still this writer's (OutFolder.proved).
    folder.files.pop(schema.MANIFEST_NAME, None)
    folder.record([schema.MANIFEST_NAME, *names])
    for i in frames:
        refs.pop(i, None)
    done: list[int] = []

    def on_result(_job, _plan, result):
        idx = int(result["index"])
        row = frame_row(frames[idx], result, folder.path)
        refs[idx] = _ref(row, append_rows(folder.path, [row], sync=False)[0])
        done.append(idx)

    try:
        run_workers([f["job"] for f in fields], settings.render, settings.hapke, folder.path, on_result)
    finally:
        _end_chunk(folder, done)
    missing = sorted(set(frames) - set(done))
    if missing:
        raise UserError(f"detection frames {missing} were not rendered (see {folder.path}/.jobs/*.log)")


def frame_files(index: int) -> list[str]:
    """The files a run writes for frame ``index``: its EXR and its label file."""
    rel = frame_rel_path(index)
    return [rel, label_file_name(rel)]


def _end_chunk(folder: OutFolder, done: list[int]) -> None:
    """The manifest's appended rows made durable (one fsync a chunk) and the chunk's files sealed."""
    with open(folder.path / schema.MANIFEST_NAME, "ab") as fh:
        os.fsync(fh.fileno())
    folder.seal([*(name for i in sorted(done) for name in frame_files(i)), schema.MANIFEST_NAME])


def append_rows(out_dir: Path, rows: list[dict], sync: bool = True) -> list[tuple[int, int]]:
    """Append ``rows`` to the manifest in one write, flushed (a killed process loses none of them) and,
    with ``sync``, fsynced (durable through a power loss); returns where each line lies (byte offset,
    length)."""
    if not rows:
        return []
    lines = [(schema.dumps_row(r) + "\n").encode("utf-8") for r in rows]
    with open(Path(out_dir) / schema.MANIFEST_NAME, "ab") as fh:
        offset = os.fstat(fh.fileno()).st_size
        fh.write(b"".join(lines))
        fh.flush()
        if sync:
            os.fsync(fh.fileno())
    at = []
    for line in lines:
        at.append((offset, len(line)))
        offset += len(line)
    return at


def _write_manifest(folder: OutFolder, refs: dict) -> None:
    """The compact manifest: the lines of ``refs`` (read where they lie in the current file), sorted by
    frame index, streamed into a new file renamed over it (listed as being written meanwhile, as in
    :func:`_render_chunk`); ``refs`` then point into the new file."""
    path = folder.path / schema.MANIFEST_NAME
    folder.files.pop(schema.MANIFEST_NAME, None)
    folder.record([schema.MANIFEST_NAME])
    moved: dict[int, tuple[int, int]] = {}

    def lines():
        if not refs:
            return
        offset = 0
        with open(path, "rb") as src:
            for i in sorted(refs):
                start, length = refs[i]["at"]
                src.seek(start)
                line = src.read(length)
                line = line if line.endswith(b"\n") else line + b"\n"  # a last line whose newline was lost
                moved[i] = (offset, len(line))
                offset += len(line)
                yield line

    schema.atomic_write_chunks(path, lines())
    for i, at in moved.items():
        refs[i]["at"] = at
    folder.seal([schema.MANIFEST_NAME])


def _render_chunks(settings, folder: OutFolder, chunks: list[dict], refs: dict, pipelined: bool = True) -> None:
    """Render ``chunks`` (field -> its frames to render) in order, planning chunk k + 1 in a second process
    while chunk k renders (``pipelined``; else each chunk is planned here before it renders: a Dask task,
    whose daemonic worker process may start no process pool); each chunk's rows are appended to the
    manifest, which is compacted when the run ends, or stops early."""
    patches = folder.path / PATCH_DIR
    shutil.rmtree(patches, ignore_errors=True)  # a stopped run's patches (bookkeeping under .jobs/)
    # spawned, not forked: the planner must not inherit the folder's lock or the CLI's signal handlers
    spawn = multiprocessing.get_context("spawn")
    planner = ProcessPoolExecutor(max_workers=1, mp_context=spawn) if pipelined else None
    try:
        # the first chunk here: the workers have nothing to do yet
        fields = _plan_chunk(settings, chunks[0], patches / "chunk_0")
        for k in range(len(chunks)):
            nxt = None
            if k + 1 < len(chunks):
                args = (settings, chunks[k + 1], patches / f"chunk_{k + 1}")
                nxt = planner.submit(_plan_chunk, *args) if planner is not None else args
            _render_chunk(settings, fields, folder, refs)
            shutil.rmtree(patches / f"chunk_{k}", ignore_errors=True)
            if isinstance(nxt, tuple):
                fields = _plan_chunk(*nxt)
            elif nxt is not None:
                try:
                    fields = nxt.result()
                except BrokenProcessPool:
                    raise UserError(
                        "the process generating the next crater fields died (out of memory?); rerun to resume"
                    ) from None
    finally:
        if planner is not None:
            planner.shutdown(cancel_futures=True)
        shutil.rmtree(patches, ignore_errors=True)
        _write_manifest(folder, refs)  # compacted once: the frames rendered and kept, however the run ends


def check_request(settings, n_frames: int) -> None:
    """One error for a request no frame can be rendered for (before anything is written)."""
    if settings.procedural is None or settings.detection is None:
        raise ConfigError(
            "no procedural field or detection recipe selected: add procedural=detection detection=default"
        )
    if n_frames < 1:
        raise UserError(f"--frames {n_frames}: must be >= 1")
    check_field_fits(settings.procedural, settings.detection)


def render_detection_frames(settings, out_dir: Path, n_frames: int, start: int = 0, pipelined: bool = True) -> dict:
    """Render frames ``start`` .. ``start + n_frames - 1`` into ``out_dir`` with their labels, keeping the
    frames of the range already there (module docstring); ``settings.detection`` sets the conditions and
    how frames share fields, views and Sun azimuths. ``pipelined``: plan the next chunk in a second process
    (:func:`_render_chunks`). Returns a summary."""
    check_request(settings, n_frames)
    det = settings.detection
    settings = replace(settings, **{"render.horizon_cache_dir": None})  # maps beside the patches, removed with them
    folder = OutFolder(Path(out_dir), KIND, subject=f"recipe {recipe_key(settings)}").check_clean()
    folder.claim()
    try:
        folder.record([schema.MANIFEST_NAME])
        wanted = range(start, start + n_frames)
        on_disk, compact = manifest_refs(folder.path)
        refs, done = kept_rows(folder, wanted, on_disk)
        proved = [rel for i in done for rel, _ in _files_and_hashes(refs[i]) if not folder.files.get(rel)]
        if proved:  # a hard-killed run's frames, proved by their hashes: sealed now, so no later run hashes them
            folder.seal(proved)
        if not compact:  # a hard-killed run's appended file: compacted before anything is appended to it
            _write_manifest(folder, refs)
        by_field: dict[int, list[int]] = {}
        for i in wanted:
            if i not in done:
                by_field.setdefault(field_of(det, i), []).append(i)
        size = max(1, CHUNK_PER_WORKER * int(settings.render.workers))
        ids = sorted(by_field)
        chunks = [{f: by_field[f] for f in ids[k : k + size]} for k in range(0, len(ids), size)]
        t0 = time.perf_counter()
        if chunks:
            _render_chunks(settings, folder, chunks, refs, pipelined)
        seconds = time.perf_counter() - t0
    finally:
        folder.release()
    ordered = [refs[i] for i in wanted]
    rendered = n_frames - len(done)
    return {
        "frames": len(ordered),
        "rendered": rendered,
        "kept": len(done),
        "fields": len({field_of(det, i) for i in wanted}),
        "frames_in_manifest": len(refs),
        "out_dir": str(folder.path),
        "width_px": det.width_px,
        "grouping": grouping(det),
        "modes_used": sorted({r["mode"] for r in ordered}),
        "labels": sum(r["labels"] for r in ordered),
        "seconds": round(seconds, 2),
        "frames_per_s": round(rendered / seconds, 3) if rendered and seconds > 0 else None,
    }
