"""The types and bounds of what train.py reads beside the typed options: ``configs/train.yaml``'s
own keys (:class:`RunKeys`) and the Lightning ``Trainer`` arguments ``configs/trainer/*.yaml``
pass (:class:`TrainerKeys`). Their values are in ``configs/`` (no defaults here: these
dataclasses are never built, :func:`embodied_tactile.options.checks.check_options` reads
their fields); keys not named are Lightning's to check."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Union

from .checks import at_least, bounds


@dataclass
class RunKeys:
    """``configs/train.yaml``'s own keys."""

    seed: int
    resume: bool
    validate_at_end: bool
    plain_progress: Union[bool, str]


@dataclass
class TrainerKeys:
    """``trainer``: the Lightning ``Trainer`` arguments the run's numbers and flags reach."""

    max_epochs: Optional[int] = field(metadata=at_least(-1))
    max_steps: Optional[int] = field(metadata=at_least(-1))
    devices: Union[int, str, List[int]]
    num_nodes: int = field(metadata=at_least(1))
    gradient_clip_val: Optional[float] = field(metadata=at_least(0))
    log_every_n_steps: int = field(metadata=at_least(1))
    check_val_every_n_epoch: Optional[int] = field(metadata=at_least(1))
    num_sanity_val_steps: int = field(metadata=at_least(-1))
    limit_train_batches: Optional[Union[int, float]] = field(metadata=bounds(0))
    limit_val_batches: Optional[Union[int, float]] = field(metadata=bounds(0))
    accumulate_grad_batches: int = field(metadata=at_least(1))
    fast_dev_run: Union[bool, int]
    enable_progress_bar: bool
    deterministic: Union[bool, str]


__all__ = ["RunKeys", "TrainerKeys"]
