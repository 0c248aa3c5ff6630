"""Pieces shared by every subcommand: trailing overrides and one-line user errors."""

from __future__ import annotations

import functools
import sys

import click

from crater_core.errors import ContractError
from crater_synth.errors import UserError

OVERRIDES = click.argument("overrides", nargs=-1, metavar="[OVERRIDES]...")


def user_errors(fn):
    """Turn bad-input errors into one ``error: ...`` line on stderr and exit status 2."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (UserError, ContractError) as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(2)

    return wrapper
