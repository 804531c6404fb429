"""Typed options with their one default each (dataclasses, no heavy imports): the
alignment's, the data's, the simulator's, evaluation's and the baselines' here, their bounds
as field metadata (:mod:`.checks`); the Latent Filter's in :mod:`embodied_tactile.model.options`."""

from .alignment import AlignmentOptions, alignment_options

__all__ = ["AlignmentOptions", "alignment_options"]
