"""The closed loop: touch, preprocess, filter frame by frame, estimate, choose the next touch.

B episodes (one object each) run in lockstep so that the filter and the decisions are
batched; B = 1 is the single episode of ``embodied-tactile palpate``.

Across touches the Latent Filter state carries over unchanged: the first frame of touch
k + 1 is filtered as the frame that follows the last frame of touch k (transition prior from
z at the end of touch k, LSTM state kept, a_{t-1} = the last action of touch k). The lift-off
and repositioning between touches is not represented (the model never saw a gap), so the
online posterior over an episode equals the batched posterior over its concatenated frames
(tests/unit/test_active.py). Each touch's actions are relative to its own first pose, like every
trial the model was trained on.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import torch

from .model import PalpationModel
from .policy import Policy
from .source import TouchSource


@torch.no_grad()
def filter_touch(net, obs: torch.Tensor, actions: torch.Tensor, state: Optional[dict]) -> tuple[dict, dict]:
    """Filter one touch frame by frame with ``filter_step`` (means, no sampling):
    obs (B, T, C, 28, 28), actions (B, T, n_a), ``state`` from the previous touch (None at
    the start of an episode). Returns (outputs of the last frame, new state)."""
    was_training = net.training
    net.eval()
    out = None
    try:
        for t in range(obs.shape[1]):
            out, state = net.filter_step(obs[:, t], actions[:, t], state=state)
    finally:
        net.train(was_training)
    return out, state


class TouchCache:
    """Preprocessed touches of one source, kept by (object, action, use): policies run under
    the same episode seed share them (the same touch gives the same data whatever policy
    asked for it), so an evaluation simulates each touch once."""

    def __init__(self, model: PalpationModel, source: TouchSource) -> None:
        self.model, self.source = model, source
        self._store: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}
        self.misses = 0

    def get(self, object_id: int, action_index: int, use: int) -> tuple[np.ndarray, np.ndarray]:
        key = (int(object_id), int(action_index), int(use))
        if key not in self._store:
            self.misses += 1
            self._store[key] = self.model.observe(self.source.touch(*key))
        return self._store[key]


@dataclass
class EpisodeLog:
    """B episodes of K touches: ``actions`` (B, K), ``estimates`` / ``stds`` (B, K, 4) of the
    factors after each touch (KRR of the posterior mean; Monte-Carlo std through the KRR),
    ``truth`` (B, 4), all in the model's targets encoding."""

    policy: str
    seed: int
    object_ids: np.ndarray
    actions: np.ndarray
    estimates: np.ndarray
    stds: np.ndarray
    truth: np.ndarray
    decision_s: list = field(default_factory=list)
    scores: list = field(default_factory=list)  # active policy: (B, |A|) criterion per decision

    def sq_errors(self) -> np.ndarray:
        """(B, K, 4) squared errors."""
        return (self.estimates - self.truth[:, None, :]) ** 2


def run_episodes(model: PalpationModel, source: TouchSource, object_ids: Sequence[int], policy: Policy,
                 budget: int, *, seed: int = 0, n_factor_samples: int = 64, cache: Optional[TouchCache] = None,
                 on_touch: Optional[Callable[[int, np.ndarray, np.ndarray, np.ndarray], None]] = None
                 ) -> EpisodeLog:
    """Run one episode per object (lockstep) with ``budget`` touches. ``seed`` seeds the
    policy's random choices and the Monte-Carlo draws (the source carries its own seed
    stream). ``on_touch(k, actions (B,), estimates (B, 4), stds (B, 4))`` is called after
    every touch (printing / plotting). ``cache``: a :class:`TouchCache` of ``source`` to
    share touches between runs."""
    if int(budget) < 1:
        raise ValueError(f"budget must be >= 1 touch, got {budget}")
    obj = np.asarray(object_ids, dtype=np.int64)
    B, K = len(obj), int(budget)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xAC71]))
    mc_rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xF4C7]))
    actions = np.zeros((B, K), dtype=np.int64)
    est = np.zeros((B, K, 4))
    std = np.zeros((B, K, 4))
    uses: list[dict[int, int]] = [{} for _ in range(B)]
    state = None
    posterior = None
    scores = []
    for k in range(K):
        a = np.asarray(policy.choose(k, actions[:, :k], state, model, rng, posterior=posterior), dtype=np.int64)
        if getattr(policy, "last_scores", None) is not None and k > 0:
            scores.append(policy.last_scores)
        actions[:, k] = a
        obs_l, act_l = [], []
        for b in range(B):
            u = uses[b].get(int(a[b]), 0)
            uses[b][int(a[b])] = u + 1
            if cache is not None:
                o, ac = cache.get(int(obj[b]), int(a[b]), u)
            else:
                o, ac = model.observe(source.touch(int(obj[b]), int(a[b]), u))
            obs_l.append(o)
            act_l.append(ac)
        out, state = filter_touch(model.net, torch.from_numpy(np.stack(obs_l)), torch.from_numpy(np.stack(act_l)),
                                  state)
        y_m, y_v = out["y_mean"].float().numpy(), out["y_var"].float().numpy()
        posterior = (y_m, y_v)
        est[:, k] = model.factors_of(y_m)
        _, var = model.factor_moments(y_m, y_v, n_factor_samples, mc_rng)
        std[:, k] = np.sqrt(var)
        if on_touch is not None:
            on_touch(k, a, est[:, k], std[:, k])
    return EpisodeLog(policy=getattr(policy, "name", type(policy).__name__), seed=int(seed), object_ids=obj,
                      actions=actions, estimates=est, stds=std, truth=model.true_factors(obj),
                      decision_s=list(getattr(policy, "decision_s", [])), scores=scores)
