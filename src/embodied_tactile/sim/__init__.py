"""Physically grounded palpation simulator (NumPy/SciPy only; see docs/reference/simulator.md)."""

from embodied_tactile.sim.dataset import OutputFileError, generate_dataset
from embodied_tactile.sim.physics import Mechanics, PhysicsOverrides, contact_pressure, mechanics, qlv_relax
from embodied_tactile.sim.trial import force_indentation, fsr_counts, simulate_trial
from embodied_tactile.sim.validation import SimParameterError

__all__ = [
    "Mechanics",
    "OutputFileError",
    "PhysicsOverrides",
    "SimParameterError",
    "contact_pressure",
    "force_indentation",
    "fsr_counts",
    "generate_dataset",
    "mechanics",
    "qlv_relax",
    "simulate_trial",
]
