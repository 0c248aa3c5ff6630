"""``crater-synth detection-frames launcher=dask``: a large detection set rendered on a Dask cluster as a
folder of shard folders (docs/distributed.md, "Detection sets"; imported only for ``launcher=dask``: Dask is
the ``dask`` extra).

- **Layout**: ``DIR/shard_NNNNN/`` holds frames [N x S, (N + 1) x S), S frames a shard (whole fields:
  :func:`crater_synth.dataset.detection.shard_frames`), each an ordinary detection-frames folder (its own
  marker, lock, manifest), so resume, verify, export and training work per shard and no folder holds a
  million rows. ``DIR`` itself is marked ``detection-shards``; its subject names the recipe and S, so a
  rerun with another recipe or shard size is refused; a rerun that does not set ``launcher.shards`` takes
  the S the set was begun with (``--frames`` may grow).
- **Frames**: shard N renders its range with :func:`crater_synth.dataset.detection_run.render_detection_frames`
  (``--start`` at its first frame); a frame is drawn from the seed and its index only, so frame k of a
  sharded set is frame k of one unsharded run.
- **Tasks**: one Dask task a shard, one Blender worker each (``render.workers=1``), resuming its folder as
  the command does: a shard whose frames are all kept renders nothing (skipped; its manifest compacted if
  a killed run left it appended); a task whose worker died is rescheduled (``launcher.retries``) and
  resumes its shard. The shards' resume checks (a manifest and a stat a frame) run in the tasks, in
  parallel, not on the host.
- **Pre-flight** on the host before any cluster starts (as :mod:`crater_synth.dataset.dask_launcher`): the
  recipe, the fields' fit, ``DIR``, and each shard folder's marker (another kind or recipe is refused in
  one line). A bad-input error inside a task (a file the command did not write in a shard) is returned,
  not raised, so Dask does not retry it.
"""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

from crater_core.errors import ContractError
from crater_core.progress import Progress
from crater_core.settings import replace
from crater_synth.dataset.dask_launcher import completed_summaries, open_client
from crater_synth.dataset.detection import SHARDS_KIND, shard_frames, shard_name
from crater_synth.dataset.detection_run import KIND, check_request, recipe_key, render_detection_frames
from crater_synth.errors import RenderError, UserError
from crater_synth.outfolder import MARKERS, OutFolder

_SHARD_FILE = re.compile(r"shard_\d{5}/")
_PER_SHARD = re.compile(r", (\d+) frames a shard$")


def _subject(settings, per_shard: int) -> str:
    return f"recipe {recipe_key(settings)}, {per_shard} frames a shard"


def _begun_with(out: Path) -> int | None:
    """The frames a shard of the set begun in ``out`` (its marker's subject), or None."""
    try:
        subject = json.loads((out / MARKERS[SHARDS_KIND]).read_text(encoding="utf-8"))["subject"]
        return int(_PER_SHARD.search(subject).group(1))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def layout(settings, out: Path, n_frames: int, start: int) -> tuple[int, list[tuple[int, int, int]]]:
    """(S: frames a shard, [(shard, its first frame in the range, frames)] of frames ``start`` ..
    ``start + n_frames - 1``). S: ``launcher.shards`` splits the range, or the set's own S, or the
    range split in 4 x ``launcher.n_workers`` shards of at most MAX_SHARD_FRAMES."""
    launcher = settings.launcher
    per = None if launcher.shards else _begun_with(out)
    if per is None:
        shards = launcher.shards or 4 * launcher.n_workers
        per = shard_frames(settings.detection, n_frames, shards, cap=not launcher.shards)
    end = start + n_frames
    ranges = []
    for k in range(start // per, -(-end // per)):
        first, last = max(start, k * per), min(end, (k + 1) * per)
        ranges.append((k, first, last - first))
    return per, ranges


def preflight(settings, out: Path, n_frames: int, start: int) -> tuple[OutFolder, dict]:
    """Every check before a cluster starts (module docstring): the request, ``out`` (claimed: marked and
    locked, one writer of the set) and each existing shard folder's marker (its kind and recipe: O(1) a
    shard; the files are checked by the shard's own task, in parallel). Returns ``out``'s hold and the plan
    ``{"per_shard": S, "shards": [(k, first frame, frames)]}``."""
    check_request(settings, n_frames)
    per, ranges = layout(settings, out, n_frames, start)
    parent = OutFolder(out, SHARDS_KIND, subject=_subject(settings, per), names=lambda rel: not _SHARD_FILE.match(rel))
    parent.check_clean()
    parent.claim()
    try:
        for k, _, _ in ranges:
            OutFolder(out / shard_name(k), KIND, subject=f"recipe {recipe_key(settings)}").check()
    except BaseException:
        parent.discard()
        raise
    return parent, {"per_shard": per, "shards": ranges}


def _render_shard(settings, folder: str, n_frames: int, start: int) -> dict:
    """Task body: one shard's frames, in a Dask worker process. Bad input is returned as ``{"error": ...}``
    (retrying it cannot help); a :class:`RenderError` (a Blender worker kept dying) is raised, so Dask
    retries the task."""
    try:
        return render_detection_frames(settings, Path(folder), n_frames, start, pipelined=False)
    except RenderError:
        raise
    except (UserError, ContractError) as exc:
        return {"error": str(exc)}


def _gather(client, futures, progress: bool, workers: int) -> list[dict]:
    """The tasks' summaries; a task's error or repeated worker death is one error."""
    done = []
    with Progress(
        len(futures), f"dask detection set ({workers} workers)", "shard", "auto" if progress else "off"
    ) as bar:
        for summary in completed_summaries(futures):
            done.append(summary)
            bar.update(1, frames=sum(s["rendered"] for s in done))
    return done


def run_detection_dask(settings, out_dir: Path, n_frames: int, start: int = 0, progress: bool = True) -> dict:
    """Render frames ``start`` .. ``start + n_frames - 1`` as a sharded set in ``out_dir`` on a Dask
    cluster (local on 127.0.0.1 unless ``launcher.address``); returns a summary."""
    out = Path(out_dir).resolve()  # every task on every node sees the same path
    settings = replace(settings, **{"render.workers": 1})
    parent, plan = preflight(settings, out, n_frames, start)
    t0 = time.perf_counter()
    try:
        client, cluster = open_client(settings.launcher)
        t_cluster = time.perf_counter() - t0
        try:
            workers = len(client.scheduler_info().get("workers", {}))
            futures = [
                client.submit(
                    _render_shard,
                    settings,
                    str(out / shard_name(k)),
                    n,
                    first,
                    key=f"detection-shard-{k}",
                    retries=settings.launcher.retries,
                    pure=False,
                )
                for k, first, n in plan["shards"]
            ]
            summaries = _gather(client, futures, progress, workers)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    finally:
        parent.release()
    seconds = time.perf_counter() - t0
    rendered = sum(s["rendered"] for s in summaries)
    return {
        "out_dir": str(out),
        "launcher": "dask",
        "workers": workers,
        "frames": n_frames,
        "frames_per_shard": plan["per_shard"],
        "shards": [shard_name(k) for k, _, _ in plan["shards"]],
        "shards_rendered": sum(1 for s in summaries if s["rendered"]),
        "shards_skipped": sum(1 for s in summaries if not s["rendered"]),
        "rendered": rendered,
        "kept": n_frames - rendered,
        "seconds": round(seconds, 2),
        "cluster_start_s": round(t_cluster, 2),
        "frames_per_s": round(rendered / seconds, 3) if rendered and seconds > 0 else None,
    }
