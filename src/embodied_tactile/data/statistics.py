"""What a model needs to know about its training data, computed by the data side
(:class:`~embodied_tactile.data.datamodule.TactileDataModule` in ``setup``; the baselines
from their arrays): per-channel mean and standard deviation of the observations and the
number of training sequences. Pure numpy."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np


def channel_stats(batches: Iterable[Mapping[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and standard deviation (C,) over every frame and pixel of an
    iterable of batches with ``obs`` (B, T, C, H, W) (float64 sums)."""
    n, s, ss = 0, None, None
    for b in batches:
        o = np.asarray(b["obs"], dtype=np.float64)
        o = np.moveaxis(o, 2, 0).reshape(o.shape[2], -1)
        s = o.sum(1) if s is None else s + o.sum(1)
        ss = (o ** 2).sum(1) if ss is None else ss + (o ** 2).sum(1)
        n += o.shape[1]
    if not n:
        raise ValueError("channel_stats: no observations")
    mean = s / n
    return mean, np.sqrt(np.maximum(ss / n - mean ** 2, 0.0))


@dataclass(frozen=True)
class DataStatistics:
    """The training split's channel mean and standard deviation (C,) and its number of
    sequences (the prior's population term counts once per dataset)."""

    channel_mean: np.ndarray
    channel_std: np.ndarray
    n_train_sequences: int

    @classmethod
    def of(cls, batches: Iterable[Mapping[str, Any]], n_train_sequences: int) -> "DataStatistics":
        mean, std = channel_stats(batches)
        return cls(mean, std, int(n_train_sequences))
