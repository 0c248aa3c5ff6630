"""Render a sweep into a dataset directory: plan, resume, dispatch Blender workers, record the manifest.

Layout of a dataset directory::

    .crater-synth-dataset     marker: this directory is a dataset (crater_synth.dataset.marker)
    manifest.jsonl            merged, sorted rows (crater_core/schema.py)
    manifest.parts/*.jsonl    rows appended while rendering (merged at the end)
    <crater>/<params>.exr     one tiled EXR per render
    .jobs/                    worker job files and logs (bounded: crater_synth.dataset.disk.prune_jobs)
    .dataset.lock             held while a `crater-synth dataset` writes (one writer per dataset or shard)

Modules: :mod:`~crater_synth.dataset.plan` (the geometry of every render),
:mod:`~crater_synth.dataset.dispatch` (Blender worker processes, retries, a clean stop),
:mod:`~crater_synth.dataset.manifest` (rows and part files), :mod:`~crater_synth.dataset.disk`
(directory checks, free disk, the lock, orphans, ``.jobs/``) and :mod:`~crater_synth.dataset.build`
(:func:`build_dataset`, which strings them together). The ``dataset`` command lives in
:mod:`crater_synth.dataset.launcher`, which picks the local or the Dask path.
"""

from crater_synth.dataset.build import build_dataset
from crater_synth.dataset.dispatch import run_workers, worker_command
from crater_synth.dataset.identity import render_identity
from crater_synth.dataset.plan import CraterJob, code_version, plan_render, render_seed
from crater_synth.errors import RenderError

__all__ = [
    "CraterJob",
    "RenderError",
    "build_dataset",
    "code_version",
    "plan_render",
    "render_identity",
    "render_seed",
    "run_workers",
    "worker_command",
]
