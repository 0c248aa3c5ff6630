"""Run Python code as if some installed libraries were not: a meta path finder, first on sys.meta_path,
refuses them as a missing module is refused (ModuleNotFoundError naming it), in a fresh interpreter."""

from __future__ import annotations

import subprocess
import sys

from helpers.cli import REPO

_PRELUDE = """
import sys
_BLOCKED = {blocked!r}


class _NotInstalled:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in _BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None


sys.meta_path.insert(0, _NotInstalled())
"""


def run_blocked(blocked, code: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """``code`` run by this Python in the checkout with the top-level modules ``blocked`` missing."""
    script = _PRELUDE.format(blocked=sorted(blocked)) + code
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=timeout, cwd=REPO)


def cli_blocked(blocked, *args, timeout: float = 120) -> subprocess.CompletedProcess:
    """``crater-synth ARGS`` with ``blocked`` missing."""
    code = f"from crater_synth.cli import main\nmain({[str(a) for a in args]!r}, prog_name='crater-synth')\n"
    return run_blocked(blocked, code, timeout)
