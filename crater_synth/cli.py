"""``crater-synth``: one click group; every subcommand takes trailing Hydra overrides.

Entry points stay thin: each subcommand composes the config and calls one function of the module
that owns that pipeline stage.
"""

from __future__ import annotations

import importlib

import click

# (module, attribute) of each subcommand, in `crater-synth --help` order.
_COMMANDS = (
    ("crater_synth.terrain", "terrain_command"),
    ("crater_synth.catalogue", "catalogue_command"),
    ("crater_synth.fetch", "fetch_data_command"),
    ("crater_synth.dataset", "dataset_command"),
    ("crater_synth.verify", "verify_command"),
    ("crater_synth.preview", "preview_command"),
    ("crater_synth.training", "train_command"),
    ("crater_synth.training", "evaluate_command"),
    ("crater_synth.loop", "loop_command"),
    ("crater_synth.experiments", "experiments_command"),
    ("crater_synth.report", "report_command"),
    ("crater_synth.validate", "validate_command"),
    ("crater_synth.ablation", "ablate_command"),
    ("crater_synth.bench", "bench_command"),
)

@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main():
    """DEM-synthesised lunar crater images: terrain, rendering, training, closed loop.

    Every subcommand accepts Hydra overrides, e.g.
    ``crater-synth terrain crater=shoemaker terrain.detail.enabled=false``.
    """


for _module, _attr in _COMMANDS:
    main.add_command(getattr(importlib.import_module(_module), _attr))


if __name__ == "__main__":  # pragma: no cover
    main()
