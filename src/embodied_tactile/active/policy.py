"""Action selection: the active policy (expected posterior factor variance from imagined
rollouts, docs/reference/active.md) and the baselines (random order, fixed order, single action).

Every policy answers ``choose(k, history, state, model, rng) -> (B,) action indices`` for
touch ``k`` (0-based) of B episodes run in lockstep; ``history`` (B, k) holds the actions
already taken, ``state`` the Latent Filter state after touch k - 1 (None before the first).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any, Optional, Protocol

import numpy as np
import torch

from .model import PalpationModel


class Policy(Protocol):
    name: str

    def choose(self, k: int, history: np.ndarray, state: Optional[dict], model: PalpationModel,
               rng: np.random.Generator, posterior: Optional[tuple] = None) -> np.ndarray: ...


class FixedOrderPolicy:
    """Touch ``k`` uses ``order[k % len(order)]`` (the same for every episode)."""

    def __init__(self, order: Sequence[int], name: str = "fixed") -> None:
        if not len(order):
            raise ValueError("a fixed order needs at least one action")
        self.order, self.name = [int(a) for a in order], name

    def choose(self, k, history, state, model, rng, posterior=None):
        a = self.order[k % len(self.order)]
        if a not in model.actions:
            raise ValueError(f"{self.name}: action {a} unknown to the model (actions {list(model.actions)})")
        return np.full(len(history), a, dtype=np.int64)


class SingleActionPolicy(FixedOrderPolicy):
    """The paper's protocol: one fixed action, repeated."""

    def __init__(self, action: int, name: str = "single") -> None:
        super().__init__([action], name)


class RandomPolicy:
    """A random action order per episode: consecutive random permutations of the model's
    actions (each block of |A| touches uses every action once), drawn from the episode rng."""

    name = "random"

    def __init__(self) -> None:
        self._perm: Optional[np.ndarray] = None

    def choose(self, k, history, state, model, rng, posterior=None):
        acts = np.asarray(model.actions)
        n = len(acts)
        if k % n == 0:  # a new block: one permutation per episode
            self._perm = np.stack([rng.permutation(acts) for _ in range(len(history))])
        return self._perm[:, k % n].astype(np.int64)


def _repeat_state(state: dict, n: int) -> dict:
    return {key: v.repeat_interleave(n, dim=0) for key, v in state.items()}


@torch.no_grad()
def imagine_touch(net: Any, state: dict, actions: torch.Tensor, sample: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Imagined rollout of one touch: from the filter ``state`` (R rows), run the model's own
    recursion (transition prior for z, the y posterior network on the imagined z) over
    ``actions`` (R, H, n_a) with every frame unobserved -- the recursion of
    ``LatentFilter.predict``, started from a filter state instead of frames. Returns y_mean,
    y_var (R, n_y) after the last imagined frame."""
    R, H = actions.shape[:2]
    n_z = state["z"].shape[1]
    hidden = torch.zeros(R, dtype=torch.bool)
    none_m, none_v = torch.zeros(R, n_z), torch.ones(R, n_z)
    out = None
    for t in range(H):
        out, state = net.step(none_m, none_v, actions[:, t], state, sample, observed=hidden)
    return out["y_mean"], out["y_var"]


CRITERIA = ("variance", "spread", "learned")


def expected_variance_reduction(model: PalpationModel, state: dict, candidates: Sequence[int], *,
                                n_rollouts: int = 4, horizon: Optional[int] = None, n_y_samples: int = 32,
                                seed: int = 0, criterion: str = "variance") -> np.ndarray:
    """The expected reduction of the normalised factor variance by one more touch with
    action a, for every episode row and candidate, (B, len(candidates)); larger = better.
    docs/reference/active.md, eqs. 3-5:

    * ``"variance"``: -E_m[ sum_k Var(f_k(y) | future m) / var_ref_k ] (the current variance
      is the same for every candidate and left out): the imagined posterior's own variance,
      ``n_y_samples`` draws of y through the KRR per future, averaged over the futures;
    * ``"spread"``: sum_k Var_m[ E(f_k(y) | future m) ] / var_ref_k: how much the estimate
      is expected to move, the other side of the law of total variance (equal to the
      expected reduction when the model is calibrated); needs M >= 2 sampled futures.

    M = ``n_rollouts`` imagined touches per candidate (M = 1: the mean rollout, no
    sampling; M > 1: sampled rollouts, torch seeded by ``seed``)."""
    if criterion not in CRITERIA[:2]:
        raise ValueError(f"criterion must be one of {CRITERIA[:2]} (imagined rollouts), got {criterion!r}")
    if criterion == "spread" and int(n_rollouts) < 2:
        raise ValueError("criterion 'spread' needs n_rollouts >= 2 sampled futures")
    B = state["z"].shape[0]
    A, M = len(candidates), int(n_rollouts)
    acts = model.nominal_batch(candidates)  # (A, T, n_a)
    if horizon is not None:
        acts = acts[:, : int(horizon)]
    rows = acts.unsqueeze(0).unsqueeze(2).expand(B, A, M, *acts.shape[1:]).reshape(B * A * M, *acts.shape[1:])
    st = _repeat_state(state, A * M)
    was_training = model.net.training
    model.net.eval()
    try:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(seed))
            y_m, y_v = imagine_touch(model.net, st, rows, sample=M > 1)
    finally:
        model.net.train(was_training)
    if criterion == "spread":
        f = model.factors_of(y_m.numpy()).reshape(B, A, M, -1)
        return model.normalised_variance(f.var(axis=2))
    _, var = model.factor_moments(y_m.numpy(), y_v.numpy(), n_y_samples, np.random.default_rng(int(seed)))
    return -model.normalised_variance(var).reshape(B, A, M).mean(axis=2)


def predicted_error(error_score: dict, y_mean: np.ndarray, candidates: Sequence[int]) -> np.ndarray:
    """The learned score (docs/reference/active.md, eq. 6): predicted normalised squared factor error
    after one more touch with each candidate, from the current posterior mean y (B, n_y);
    ``error_score[a]`` is a KRR alignment y -> error fitted on calibration episodes. -> (B, A)."""
    missing = [a for a in candidates if a not in error_score]
    if missing:
        raise ValueError(f"no learned error score for action(s) {missing}")
    y = np.asarray(y_mean, dtype=np.float64)
    return np.stack([error_score[a].predict(y)[:, 0, 0] for a in candidates], axis=1)


class ActivePolicy:
    """Choose the action maximising the expected reduction of the normalised factor variance
    (:func:`expected_variance_reduction`, ``criterion``). The first touch, with no
    posterior yet, uses ``first_action``. ``decision_s`` collects the wall time of each
    decision (all rows together)."""

    name = "active"

    def __init__(self, first_action: int, n_rollouts: int = 4, horizon: Optional[int] = None,
                 n_y_samples: int = 32, criterion: str = "variance", error_score: Optional[dict] = None) -> None:
        if criterion not in CRITERIA:
            raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
        if criterion == "learned" and not error_score:
            raise ValueError("criterion 'learned' needs an error score fitted on calibration episodes "
                             "(embodied_tactile.active.evaluation.fit_error_score)")
        self.error_score = error_score
        self.first_action, self.n_rollouts, self.horizon = int(first_action), int(n_rollouts), horizon
        self.criterion = criterion
        self.n_y_samples = int(n_y_samples)
        self.decision_s: list[float] = []
        self.last_scores: Optional[np.ndarray] = None

    def choose(self, k, history, state, model, rng, posterior=None):
        if k == 0 or (state is None and posterior is None):
            if self.first_action not in model.actions:
                raise ValueError(f"first action {self.first_action} unknown to the model (actions {list(model.actions)})")
            return np.full(len(history), self.first_action, dtype=np.int64)
        t0 = time.perf_counter()
        cand = list(model.actions)
        if self.criterion == "learned":
            if posterior is None:
                raise ValueError("criterion 'learned' needs the current posterior (y_mean, y_var)")
            scores = -predicted_error(self.error_score, posterior[0], cand)
            self.decision_s.append(time.perf_counter() - t0)
            self.last_scores = scores
            return np.asarray(cand, dtype=np.int64)[np.argmax(scores, axis=1)]
        if state is None:
            raise ValueError(f"criterion {self.criterion!r} needs the filter state after the previous touch")
        scores = expected_variance_reduction(model, state, cand, n_rollouts=self.n_rollouts, horizon=self.horizon,
                                             n_y_samples=self.n_y_samples, seed=int(rng.integers(2**31)),
                                             criterion=self.criterion)
        self.decision_s.append(time.perf_counter() - t0)
        self.last_scores = scores
        return np.asarray(cand, dtype=np.int64)[np.argmax(scores, axis=1)]


def make_policy(name: str, *, model: PalpationModel, first_action: int, single_action: int,
                fixed_order: Optional[Sequence[int]] = None, active: Optional[dict] = None,
                error_score: Optional[dict] = None) -> Any:
    """A policy by name: active | random | fixed (needs ``fixed_order``) | single."""
    if name == "active":
        return ActivePolicy(first_action, error_score=error_score, **(active or {}))
    if name == "random":
        return RandomPolicy()
    if name == "fixed":
        if not fixed_order:
            raise ValueError("policy 'fixed' needs a fixed order (fit one with fixed_order_from_training)")
        return FixedOrderPolicy(fixed_order)
    if name == "single":
        return SingleActionPolicy(single_action)
    raise ValueError(f"unknown policy {name!r}; choose from active, random, fixed, single")
