"""Embodied tactile perception of soft objects: simulator, recorder, Latent Filter, evaluation."""

from embodied_tactile.model.compat import install_moved_modules

__version__ = "0.1.0"

install_moved_modules()  # configs and checkpoints saved under the earlier module paths load
