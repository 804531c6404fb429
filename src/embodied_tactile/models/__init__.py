"""Latent Filter networks, observation models (early / late fusion), annealing schedules and
LightningModules (torch + lightning only)."""

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
from .fusion import EarlyFusion, LateFusion
from .latent_filter import LatentFilter, resolve_modality
from .module import EarlyFusionLatentFilter, LateFusionLatentFilter, LatentFilterModule

__all__ = [
    "SCHEDULES", "AnnealingSchedule", "ConstrainedAnnealing", "DVBFAnnealing", "GeometricKLWeights",
    "LinearKLWarmup", "NoAnnealing", "build_schedule", "check_finite", "EarlyFusion", "LateFusion", "LatentFilter",
    "resolve_modality", "EarlyFusionLatentFilter", "LateFusionLatentFilter", "LatentFilterModule",
]
