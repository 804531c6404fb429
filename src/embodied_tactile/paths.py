"""Where the project's Hydra configs are."""

import os
from pathlib import Path

#: environment variable naming another config folder
CONFIG_ENV = "EMBODIED_TACTILE_CONFIG_DIR"
#: the copy of the top-level ``configs/`` that a built wheel carries (setup.py's build_py)
PACKAGED = Path(__file__).resolve().parent / "configs"
#: the checkout's ``configs/`` (an editable install: the package under ``src/``)
CHECKOUT = Path(__file__).resolve().parents[2] / "configs"


def config_dir() -> str:
    """The Hydra config folder: ``$EMBODIED_TACTILE_CONFIG_DIR`` if set, else the checkout's
    ``configs/``, else the copy built into an installed wheel (the first that exists; the
    checkout's path when none does)."""
    env = os.environ.get(CONFIG_ENV)
    if env:
        return str(Path(env).resolve())
    if not CHECKOUT.is_dir() and PACKAGED.is_dir():
        return str(PACKAGED)
    return str(CHECKOUT)
