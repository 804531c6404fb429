"""Latent Filter networks, annealing schedules and LightningModules (torch + lightning only)."""

from .annealing import (
    SCHEDULES,
    AnnealingSchedule,
    ConstrainedAnnealing,
    DVBFAnnealing,
    GeometricKLWeights,
    LinearKLWarmup,
    NoAnnealing,
    build_schedule,
    check_finite,
)
from .latent_filter import LatentFilter, resolve_modality
from .module import EarlyFusionLatentFilter, LateFusionLatentFilter, LatentFilterModule

__all__ = [
    "SCHEDULES", "AnnealingSchedule", "ConstrainedAnnealing", "DVBFAnnealing", "GeometricKLWeights",
    "LinearKLWarmup", "NoAnnealing", "build_schedule", "check_finite", "LatentFilter",
    "resolve_modality", "EarlyFusionLatentFilter", "LateFusionLatentFilter", "LatentFilterModule",
]
