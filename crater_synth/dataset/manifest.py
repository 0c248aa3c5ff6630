"""Manifest rows of a dataset being rendered: one row per finished render, appended to this writer's
part file (``manifest.parts/<name>-<host>-<pid>.jsonl``, fsynced in batches: schema.RowAppender) and
merged into ``manifest.jsonl`` at the end (crater_core/schema.py holds the format and the merge)."""

from __future__ import annotations

import os
import re
import socket
from pathlib import Path

from crater_core import schema
from crater_synth.dataset.plan import code_version


def writer_tag() -> str:
    """``<host>-<pid>`` of this process: names its job and manifest part files, so concurrent shards
    (several processes, or several nodes on a shared filesystem) never write the same file."""
    host = re.sub(r"[^A-Za-z0-9.]+", "_", socket.gethostname()) or "host"
    return f"{host}-{os.getpid()}"


def part_file(out_dir: Path, shard: tuple[int, int] | None) -> Path:
    """This writer's part file for the whole sweep or one shard of it."""
    name = f"shard{shard[0]}of{shard[1]}" if shard else "all"
    return out_dir / schema.PARTS_DIR / f"{name}-{writer_tag()}.jsonl"


def _dead_writer(tag_and_pid: str) -> bool:
    """True for ``...-<host>-<pid>`` names of this host whose process no longer runs."""
    head, _, pid = tag_and_pid.rpartition("-")
    host = writer_tag().rsplit("-", 1)[0]
    if not pid.isdigit() or int(pid) == os.getpid() or not head.endswith("-" + host):
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except OSError:
        pass  # alive (another user's process)
    return False


def stale_parts(out_dir: Path) -> list[Path]:
    """Manifest part files of writers on this host that are no longer running (e.g. a sweep killed
    with -9), which are safe to merge. Part names end in ``-<host>-<pid>``; parts of other hosts are
    merged by their host's next run or by the Dask launcher's final merge."""
    return [p for p in sorted((out_dir / schema.PARTS_DIR).glob("*.jsonl")) if _dead_writer(p.stem)]


# Row fields the worker measures or the file gives; every other field is planned before rendering.
RESULT_FIELDS = ("lit_fraction", "mean_if", "sha256")


def planned_row(crater_name: str, terrain_id: str, plan: dict, fov_deg: float, renderer: str) -> dict:
    """The manifest row of a planned render, less :data:`RESULT_FIELDS` (``plan`` carries its ``seed``
    and ``digest``, the render identity)."""
    p = plan["params"]
    return {
        "schema_version": schema.SCHEMA_VERSION,
        "crater": crater_name,
        "index": p.index,
        "indices": list(p.indices),
        "sun_elevation": p.sun_elevation,
        "sun_azimuth": p.sun_azimuth,
        "cam_elevation": p.cam_elevation,
        "cam_azimuth": p.cam_azimuth,
        **({"sun_elevation_param": p.sun_elevation_param} if p.sun_elevation_param != p.sun_elevation else {}),
        **({"sun_azimuth_param": p.sun_azimuth_param} if p.sun_azimuth_param != p.sun_azimuth else {}),
        "range_m": plan["range_m"],
        "fov_deg": float(fov_deg),
        "width": plan["crop"][2] - plan["crop"][0],
        "height": plan["crop"][3] - plan["crop"][1],
        "frame_width": plan["frame_width"],
        "crop_origin": plan["crop"][:2],
        "center_px": plan["center_px"],
        "rim_ellipse": plan["rim_ellipse"],
        "sigma_boxes": plan["sigma_boxes"],
        "path": plan["rel_path"],
        "seed": plan["seed"],
        "code_version": code_version(),
        "renderer": renderer,
        "terrain_id": terrain_id,
        "render_digest": plan["digest"],
    }


def manifest_row(plan: dict, result: dict) -> dict:
    """The manifest row of one finished render: the planned row (``plan["row"]``) and the worker's
    RESULT line (``result``)."""
    if result["rel_path"] != plan["rel_path"]:
        raise ValueError(f"worker wrote {result['rel_path']}, planned {plan['rel_path']}")
    return {
        **plan["row"],
        "lit_fraction": float(result["lit_fraction"]),
        "mean_if": float(result["mean_if"]),
        "sha256": result["sha256"],
    }
