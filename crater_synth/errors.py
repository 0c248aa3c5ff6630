"""User-facing errors: each ends a command with one clear line naming the bad input."""

import signal

# The signals that stop a command cleanly (a resumable stop): kill, Ctrl-C, the terminal closing.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)


class UserError(ValueError):
    """Bad input or configuration; the CLI prints ``error: <message>`` and exits with status 2."""


class ConfigError(UserError):
    """A configuration value is missing, unknown, of the wrong type or out of range."""


class RenderError(UserError):
    """A Blender worker reported bad input, kept failing, or the disk filled up while rendering."""


class DatasetBusyError(UserError):
    """Another process is writing the same dataset (or the same shard of it)."""


class Interrupted(BaseException):
    """SIGINT or SIGTERM reached a running command. A BaseException, like KeyboardInterrupt, so that no
    ``except ValueError`` on the way up swallows it; ``finally`` blocks stop workers and clean up."""

    def __init__(self, signum: int, message: str):
        super().__init__(message)
        self.signum = signum
