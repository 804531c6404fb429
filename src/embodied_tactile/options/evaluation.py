"""evaluate.py's options and the baselines', typed, with their one default each (no heavy
imports). ``configs/evaluate.yaml`` names none of them again: it documents them and holds
what a user changes; :func:`embodied_tactile.eval.pipeline.parse_options` merges it over
:class:`EvaluationOptions`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from .alignment import LATENTS, TARGET_ENCODINGS
from .checks import one_of

#: the readers evaluate.py can put beside the run's (eval.baselines); a multirun's
#: evaluation skips the GRU, which trains per run
BASELINES = ("untrained", "handcrafted", "hybrid", "gru", "mean")


@dataclass
class GRUOptions:
    """``gru``: the supervised GRU baseline (:class:`~embodied_tactile.eval.baselines.GRURegressor`):
    6 random 50-frame crops per sequence and epoch, like the default training (whole
    sequences: 0.83 / 0.79 NMSE instead of 0.16 / 0.16), inputs standardised per channel by
    the training set's mean / std as the Latent Filter's encoder sees them (raw inputs: 0.87
    instead of 0.60 at 256 population objects, docs/experiments/population_readers.md; 1.0
    instead of 0.26 for acc, modality_bounds.md)."""

    epochs: int = 20
    window: Optional[int] = 50
    windows_per_trial: int = 6
    max_batches_per_epoch: Optional[int] = None
    batch_size: int = 16
    hidden: int = 64
    feat: int = 64
    lr: float = 1e-3
    weight_decay: float = 0.0
    seed: Optional[int] = None    # null = the run's seed (evaluate.py); 0 for a GRURegressor built directly
    input_standardize: bool = True
    arch: str = "gru"             # gru: conv + GRU | latent_filter: the Latent Filter's inference path + a head on y


@dataclass
class HandcraftedOptions:
    """``handcrafted``: the thresholds of the hand-crafted features
    (:func:`~embodied_tactile.data.features.handcrafted_features`), each a share of a running
    or per-frame maximum."""

    contact_fraction: float = 0.5  # a frame is in contact when its force exceeds this share of its running peak
    still_fraction: float = 0.1    # the action is still when its step |ds| is below this share of its running max
    area_fraction: float = 0.1     # a taxel is in the contact area above this share of the frame's maximum


@dataclass
class EvaluationLoaderOptions:
    """``data``: evaluate.py's loader settings (never the scene)."""

    batch_size: Optional[int] = None  # null = the run's batch size
    num_workers: int = 0


@dataclass
class EvaluationOptions:
    """evaluate.py's options (``configs/evaluate.yaml`` documents each)."""

    checkpoint: str = field(default="last", metadata=one_of("best", "last"))
    held_out: str = field(default="test", metadata=one_of("test", "val"))
    latent: str = field(default="y", metadata=one_of(*LATENTS))
    allow_changed_data: bool = False
    allow_running: bool = False
    targets: Optional[str] = field(default=None, metadata=one_of(*TARGET_ENCODINGS))  # null: the run's own
    baselines: Optional[List[str]] = field(default=None, metadata=one_of(*BASELINES))
    out: Optional[str] = None
    figures: bool = True
    umap: bool = True
    distance_mode: str = "pairwise"
    print_tables: bool = False
    alignment: Dict[str, Any] = field(default_factory=dict)
    gru: GRUOptions = field(default_factory=GRUOptions)
    handcrafted: HandcraftedOptions = field(default_factory=HandcraftedOptions)
    data: EvaluationLoaderOptions = field(default_factory=EvaluationLoaderOptions)
    # null: per run, the threads of its final read-out (metrics.json krr_final.torch_threads), so
    # that its latents, and its number, come out as the training printed them; 1 where it does not say
    torch_threads: Optional[int] = None


__all__ = ["BASELINES", "EvaluationLoaderOptions", "EvaluationOptions", "GRUOptions", "HandcraftedOptions"]
