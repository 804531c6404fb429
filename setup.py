"""Builds the wheel with the top-level ``configs/`` copied into the package
(``embodied_tactile/configs``), so that an installed ``embodied-tactile`` finds its configs
from any folder (``embodied_tactile.paths.config_dir``). The rest is pyproject.toml."""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildWithConfigs(build_py):
    """build_py, then ``configs/`` (but the machine's own ``local/``) into the built package;
    an editable install reads the checkout's ``configs/`` and gets no copy."""

    def run(self) -> None:
        super().run()
        if not getattr(self, "editable_mode", False):
            shutil.copytree(Path(__file__).parent / "configs", Path(self.build_lib) / "embodied_tactile" / "configs",
                            dirs_exist_ok=True, ignore=shutil.ignore_patterns("local", "__pycache__"))


setup(cmdclass={"build_py": BuildWithConfigs})
