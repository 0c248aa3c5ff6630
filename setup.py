"""The build step setuptools runs (the project's metadata is in pyproject.toml).

A wheel carries the Hydra configuration tree ``configs/`` as ``crater_synth/configs``: the tree stays at the
checkout's root, where Hydra users look for it, and an installed (not editable) project still composes its
settings (``crater_synth.paths.CONFIG_DIR`` takes whichever exists)."""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildWithConfigs(build_py):
    def run(self):
        super().run()
        if not self.editable_mode:  # an editable install reads configs/ from the checkout
            shutil.copytree(
                Path(__file__).parent / "configs", Path(self.build_lib) / "crater_synth" / "configs", dirs_exist_ok=True
            )


setup(cmdclass={"build_py": BuildWithConfigs})
