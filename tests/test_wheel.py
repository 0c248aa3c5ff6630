"""The wheel a user's non-editable ``pip install .`` builds carries the Hydra configuration tree as
``crater_synth/configs`` (setup.py), which ``crater_synth.paths.CONFIG_DIR`` reads when no checkout is there."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.integration
def test_the_wheel_carries_every_config_file(tmp_path):
    # Built from a copy of the tracked files: a build writes build/ and *.egg-info into its source tree.
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    src = tmp_path / "src"
    for name in tracked.splitlines():
        if (ROOT / name).is_file():
            (src / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, src / name)
    r = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(tmp_path)] + [str(src)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    (wheel,) = tmp_path.glob("crater_synth-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    configs = {p.relative_to(src).as_posix() for p in (src / "configs").rglob("*.yaml")}
    assert len(configs) > 50 and {f"crater_synth/{c}" for c in configs} <= names
    assert "blender_gen/worker.py" in names and any(n.startswith("data_manifest/embedded/") for n in names)
