"""Latent Filter networks, observation models (early / late fusion), annealing schedules and
the LightningModule (torch + lightning only), and their typed options (:mod:`.options`, plain
dataclasses). The names below load on first use, so that ``model.options`` imports
without torch."""

from importlib import import_module
from typing import Any

_WHERE = {
    **{name: ".annealing" for name in ("SCHEDULES", "AnnealingSchedule", "ConstrainedAnnealing", "DVBFAnnealing",
                                       "GeometricKLWeights", "LinearKLWarmup", "NoAnnealing", "build_schedule",
                                       "check_finite")},
    "EarlyFusion": ".fusion", "LateFusion": ".fusion",
    "LatentFilter": ".latent_filter", "resolve_modality": ".latent_filter",
    "LatentFilterModule": ".module",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(import_module(_WHERE[name], __name__), name)
