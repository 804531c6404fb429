"""The simulator's options, typed, with their one default each (no heavy imports): how many
trials of a scene are simulated, with which seed, in how many processes and for how long.
``embodied-tactile simulate`` (:class:`SimulateOptions`), the simulated scene of the data
(:class:`~embodied_tactile.options.data.SceneOptions`: ``repetitions``, ``sim_seed``,
``sim_workers``) and :func:`embodied_tactile.sim.dataset.generate_dataset` read them from
here; the valid ranges are :mod:`embodied_tactile.sim.validation`'s (docs/reference/simulator.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from embodied_tactile import constants as C


@dataclass
class SimulationOptions:
    """How a scene's trials are simulated."""

    repetitions: int = 1                # trials per object and action
    seed: int = 0                       # the simulator's noise seed
    workers: int = 2                    # simulation processes (0 or 1: in this process)
    duration: float = C.TRIAL_DURATION  # seconds per trial


@dataclass
class SimulateOptions(SimulationOptions):
    """``embodied-tactile simulate``: one skin and primitive into one HDF5 file."""

    skin: str = "soft"
    primitive: str = "sliding"
    out: str = "data/raw/${skin}_${primitive}.h5"
    objects: list = field(default_factory=lambda: list(range(C.N_OBJECTS)))  # the whole catalogue
    actions: list = field(default_factory=lambda: list(range(C.N_ACTIONS)))  # the whole action table
    overwrite: bool = False             # true: regenerate the requested trials
    log_level: str = "INFO"
    physics: Optional[dict] = None  # physics overrides (stress tests), e.g. physics.force_scale=10


__all__ = ["SimulateOptions", "SimulationOptions"]
