"""The ``crater-synth dataset`` command and its launchers.

``launcher=local`` renders on this machine (:func:`crater_synth.dataset.build_dataset`, optionally one
``launcher.shard``); ``launcher=dask`` renders on a Dask cluster (:mod:`crater_synth.dataset.dask_launcher`,
imported only for it: a render-only install has no Dask, docs/install.md).
"""

from __future__ import annotations

import json

import click

from crater_core.settings import Settings
from crater_synth.cli_common import OVERRIDES, user_errors, warn
from crater_synth.config import load_settings
from crater_synth.dataset import build_dataset


def run_sweep(settings: Settings, progress: bool = True) -> dict:
    """Render the sweep with the configured launcher (``launcher=local``: this machine; ``dask``)."""
    if settings.launcher.name == "dask":
        for w in settings.warnings():
            warn(w)
        from crater_synth.dataset.dask_launcher import run_dask  # needs the dask extra

        return run_dask(settings, progress=progress)
    return build_dataset(settings, progress=progress, warn=warn)


@click.command("dataset")
@OVERRIDES
@user_errors
def dataset_command(overrides):
    """Render the sweep into out_dir (resumable; `launcher.shard=i/n` renders one slice).

    One writer per out_dir (or per shard): a second run on the same one refuses to start.
    Examples: `crater-synth dataset sweep=smoke crater=shoemaker render.samples=2`,
    `crater-synth dataset sweep=paper render.workers=2 out_dir=/big/disk/paper`,
    `crater-synth dataset sweep=paper launcher=dask launcher.address=tcp://head:8786`.
    """
    click.echo(json.dumps(run_sweep(load_settings(overrides))))
