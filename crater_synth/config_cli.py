"""``crater-synth config``: print the composed configuration."""

from __future__ import annotations

import json

import click
import yaml

from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import ConfigError, load_settings


@click.command("config")
@OVERRIDES
@click.option("--group", "-g", default=None, metavar="GROUP", help="Print only this group (e.g. render).")
@click.option("--json", "as_json", is_flag=True, help="JSON instead of YAML.")
@user_errors
def config_command(overrides, group, as_json):
    """Print the composed configuration: configs/ with these overrides, validated and resolved.

    The values every command would run with (Hydra's `--cfg job`), e.g.
    `crater-synth config sweep=paper render.samples=4 --group render`.
    """
    data = load_settings(overrides).as_dict()
    if group is not None:
        if group not in data:
            raise ConfigError(f"--group {group}: no such group; choose one of {', '.join(data)}")
        data = {group: data[group]}
    click.echo(json.dumps(data, indent=1) if as_json else yaml.safe_dump(data, sort_keys=False).rstrip())
