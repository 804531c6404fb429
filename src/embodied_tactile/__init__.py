"""Embodied tactile perception of soft objects: simulator, recorder, Latent Filter, evaluation."""

__version__ = "0.1.0"
