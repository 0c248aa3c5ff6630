"""User-facing errors: each ends a command with one clear line naming the bad input."""


class UserError(ValueError):
    """Bad input or configuration; the CLI prints ``error: <message>`` and exits with status 2."""
