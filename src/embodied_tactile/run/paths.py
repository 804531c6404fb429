"""Where the project's Hydra configs are."""

import os
from pathlib import Path


def config_dir() -> str:
    """The Hydra config folder: ``$EMBODIED_TACTILE_CONFIG_DIR`` if set, else the project
    checkout's ``configs/``."""
    env = os.environ.get("EMBODIED_TACTILE_CONFIG_DIR")
    if env:
        return str(Path(env).resolve())
    return str(Path(__file__).resolve().parents[3] / "configs")
