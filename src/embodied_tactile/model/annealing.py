"""KL annealing schedules for the Latent Filter (config group ``annealing``).

Every schedule is an ``nn.Module`` called as ``schedule(step, terms) -> (loss, logs)``
with ``terms`` a dict of scalar tensors ``{nll, kl_z, kl_y, entropy, n_dims}`` as produced
by :meth:`LatentFilter.elbo_terms` (per-sequence sums, batch means). ``step`` is the
global optimisation step (0-based). ``logs`` maps names to floats (weights, lambda, ...).
Stateful schedules keep their state in the state_dict (``_extra_state``), so it travels in the LightningModule's
``state_dict`` and a checkpoint resumes it; state only changes in training mode
(``schedule.train()``), never during validation.

Each schedule also has ``config()`` -> plain dict (``name`` + constructor kwargs) and
:func:`build_schedule` rebuilds one from it (used for checkpoint-safe hyperparameters).

Schedule lengths (DVBF ``T_A``, the warm-up's and the geometric weights' ``n_steps``) are
given either as absolute optimiser steps or as ``fraction`` of the run's total optimiser
steps. A fraction is resolved by :meth:`AnnealingSchedule.set_total_steps`, which the
LightningModule calls at the start of ``fit`` with Lightning's
``trainer.estimated_stepping_batches``, so a schedule always finishes within the run
whatever its number of epochs, batch size or data size. Outside ``fit`` (evaluation of a
trained model) an unresolved fraction counts as a finished schedule; in training mode it
is an error.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Optional

import torch
from torch import Tensor, nn

TERMS = ("nll", "kl_z", "kl_y", "entropy", "n_dims")


def check_finite(step: int, terms: Mapping[str, Tensor], loss: Optional[Tensor] = None) -> None:
    """Raise ``FloatingPointError("non-finite loss at step 17: kl_y=nan")`` naming every
    non-finite term (and the loss itself when only the combination overflowed)."""
    bad = []
    for k, v in terms.items():
        if isinstance(v, Tensor) and v.numel() == 1 and not torch.isfinite(v.detach()).all():
            bad.append(f"{k}={v.item()}")
    if loss is not None and not torch.isfinite(loss.detach()).all():
        bad.append(f"loss={loss.item()}")
    if bad:
        raise FloatingPointError(f"non-finite loss at step {int(step)}: " + ", ".join(bad))


class AnnealingSchedule(nn.Module):
    """Base class. Subclasses define ``_loss`` and their constructor kwargs."""

    name = "base"

    #: whether the schedule has a length (absolute steps or a fraction of the run)
    has_length = False

    def __init__(self) -> None:
        super().__init__()
        self._config: dict[str, Any] = {}
        self.fraction: Optional[float] = None
        self._steps: Optional[float] = None  # absolute length, or the resolved fraction
        self.total_steps: Optional[int] = None

    def config(self) -> dict[str, Any]:
        return {"name": self.name, **self._config}

    def _init_length(self, what: str, steps: Optional[float], fraction: Optional[float]) -> None:
        """Exactly one of ``steps`` (absolute optimiser steps, > 0) and ``fraction`` (of the
        run's total optimiser steps, in (0, 1])."""
        if (steps is None) == (fraction is None):
            raise ValueError(f"{self.name} annealing: give exactly one of {what} (absolute optimiser steps) and "
                             f"fraction (of the run's optimiser steps), got {what}={steps}, fraction={fraction}")
        if fraction is not None:
            if not 0.0 < float(fraction) <= 1.0:
                raise ValueError(f"{self.name} annealing: fraction must be in (0, 1], got {fraction}")
            self.fraction = float(fraction)
        else:
            if not float(steps) > 0:
                raise ValueError(f"{self.name} annealing: {what} must be > 0, got {steps}")
            self._steps = float(steps)

    def set_total_steps(self, total_steps: float) -> None:
        """Resolve a fractional length against the run's total optimiser steps."""
        if self.fraction is None:
            return
        if not math.isfinite(float(total_steps)) or total_steps < 1:
            raise ValueError(f"{self.name} annealing with fraction={self.fraction} needs a finite number of "
                             f"optimiser steps (set trainer.max_epochs or max_steps), got {total_steps}")
        self.total_steps = int(total_steps)
        self._steps = max(1.0, self.fraction * self.total_steps)

    def progress(self, step: int, length: Optional[float] = None) -> float:
        """``min(1, step / length)``; ``length`` defaults to the schedule's own."""
        length = self.length if length is None else length
        return 1.0 if length is None else min(max(step, 0) / length, 1.0)

    @property
    def length(self) -> Optional[float]:
        """Length in optimiser steps; None = unresolved fraction outside training (finished)."""
        if self._steps is None and self.fraction is not None:
            if self.training:
                raise RuntimeError(f"{self.name} annealing: its length is fraction={self.fraction} of the run's "
                                   "optimiser steps; call set_total_steps(total) first (the LightningModule does "
                                   "at the start of fit)")
            return None
        return self._steps

    def forward(self, step: int, terms: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, float]]:
        missing = [k for k in ("nll", "kl_z", "kl_y") if k not in terms]
        if missing:
            raise KeyError(f"annealing terms missing {missing}")
        return self._loss(int(step), terms)

    def _loss(self, step: int, terms: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, float]]:
        raise NotImplementedError

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v}" for k, v in self._config.items())


class NoAnnealing(AnnealingSchedule):
    """Plain negative ELBO: ``loss = nll + kl_z + kl_y``."""

    name = "none"

    def _loss(self, step, terms):
        return terms["nll"] + terms["kl_z"] + terms["kl_y"], {}


class DVBFAnnealing(AnnealingSchedule):
    """DVBF annealing (Karl et al. 2017, as in their original code).

    ``c = min(1, c0 + step / T_A)`` (``T_A`` absolute, or ``fraction`` x the run's steps) and
    ``loss = c * (nll + kl_z + kl_y) - (1 - c) * entropy``
    i.e. -E_q[c log p(o|z) + c log p(z, y) - log q(z, y)]: the prior and likelihood are
    tempered while the full entropy of q is kept (an entropy bonus that keeps posteriors
    wide early on). This is NOT the beta warm-up ``nll + beta * kl`` (see
    :class:`LinearKLWarmup`). At c = 1 it is the plain negative ELBO.
    """

    name = "dvbf"

    has_length = True

    def __init__(self, c0: float = 0.01, T_A: Optional[float] = None, fraction: Optional[float] = None) -> None:
        super().__init__()
        if not 0.0 <= c0 <= 1.0:
            raise ValueError(f"dvbf annealing needs 0 <= c0 <= 1, got c0={c0}")
        self.c0 = float(c0)
        self._init_length("T_A", T_A, fraction)
        self._config = {"c0": self.c0, "T_A": None if T_A is None else float(T_A), "fraction": self.fraction}

    @property
    def T_A(self) -> Optional[float]:
        return self.length

    def weight(self, step: int) -> float:
        return min(1.0, self.c0 + self.progress(step))

    def _loss(self, step, terms):
        c = self.weight(step)
        if "entropy" not in terms:
            raise KeyError("dvbf annealing needs the 'entropy' term")
        loss = c * (terms["nll"] + terms["kl_z"] + terms["kl_y"]) - (1.0 - c) * terms["entropy"]
        return loss, {"anneal/c": c}


class LinearKLWarmup(AnnealingSchedule):
    """Linear KL warm-up: ``beta = min(1, beta0 + (1 - beta0) * step / n_steps)`` (``n_steps``
    absolute, or ``fraction`` x the run's optimiser steps),
    ``loss = nll + beta * (kl_z + y_weight * kl_y)``.

    ``y_weight`` (default 1: the plain ELBO at the end of the warm-up) up-weights the
    hierarchical-prior term, as the authors' geometric schedule does (w_y up to 20): the
    per-frame reconstruction of 3 x 28 x 28 pixels otherwise outweighs the 16-dimensional
    object prior by orders of magnitude in a short budget. With ``y_weight != 1`` the loss
    is a weighted bound, not the ELBO; the logged ``*/elbo`` stays the unweighted ELBO."""

    name = "linear"

    has_length = True

    def __init__(self, beta0: float = 0.0, n_steps: Optional[int] = None, y_weight: float = 1.0,
                 fraction: Optional[float] = None) -> None:
        super().__init__()
        if not 0.0 <= beta0 <= 1.0:
            raise ValueError(f"linear warm-up needs 0 <= beta0 <= 1, got {beta0}")
        if not y_weight > 0:
            raise ValueError(f"linear warm-up needs y_weight > 0, got {y_weight}")
        self.beta0, self.y_weight = float(beta0), float(y_weight)
        self._init_length("n_steps", None if n_steps is None else int(n_steps), fraction)
        self._config = {"beta0": self.beta0, "n_steps": None if n_steps is None else int(n_steps),
                        "fraction": self.fraction, "y_weight": self.y_weight}

    @property
    def n_steps(self) -> Optional[float]:
        return self.length

    def weight(self, step: int) -> float:
        return min(1.0, self.beta0 + (1.0 - self.beta0) * self.progress(step))

    def _loss(self, step, terms):
        beta = self.weight(step)
        return terms["nll"] + beta * (terms["kl_z"] + self.y_weight * terms["kl_y"]), {"anneal/beta": beta}


class GeometricKLWeights(AnnealingSchedule):
    """Geometric KL weights of the authors' earlier code, separate for z and y:
    ``w(i) = w_start * (w_end / w_start) ** (min(i, n_steps) / n_steps)`` (constant w_end
    after ``n_steps``; absolute, or ``fraction`` x the run's optimiser steps),
    ``loss = nll + w_z(step) * kl_z + w_y(step) * kl_y``.
    Defaults z: 100 -> 200, y: 1 -> 20 (they pair with a fixed-sigma likelihood)."""

    name = "geometric"

    has_length = True

    def __init__(self, z_start: float = 100.0, z_end: float = 200.0, y_start: float = 1.0,
                 y_end: float = 20.0, n_steps: Optional[int] = None, fraction: Optional[float] = None) -> None:
        super().__init__()
        if min(z_start, z_end, y_start, y_end) <= 0:
            raise ValueError("geometric weights must be > 0")
        self.z_start, self.z_end, self.y_start, self.y_end = map(float, (z_start, z_end, y_start, y_end))
        self._init_length("n_steps", None if n_steps is None else int(n_steps), fraction)
        self._config = {"z_start": self.z_start, "z_end": self.z_end, "y_start": self.y_start,
                        "y_end": self.y_end, "n_steps": None if n_steps is None else int(n_steps),
                        "fraction": self.fraction}

    @property
    def n_steps(self) -> Optional[float]:
        return self.length

    def weights(self, step: int) -> tuple[float, float]:
        f = self.progress(step)
        return (self.z_start * (self.z_end / self.z_start) ** f,
                self.y_start * (self.y_end / self.y_start) ** f)

    def _loss(self, step, terms):
        wz, wy = self.weights(step)
        return terms["nll"] + wz * terms["kl_z"] + wy * terms["kl_y"], {"anneal/w_z": wz, "anneal/w_y": wy}


class ConstrainedAnnealing(AnnealingSchedule):
    """Constrained optimisation (Latent Matters, Klushyn et al. 2021 / GECO-style).

    With ``r = nll / n_dims`` (per-dimension NLL, same units as ``eps``) and
    ``kl = kl_z + kl_y``:

    * ``loss = r + kl / lambda`` once the KL is on, ``loss = r`` before.

    Training-mode state update, in this order at each call:

    1. moving average ``C <- 0.99 * C + 0.01 * r`` (``C`` starts at the first ``r``);
    2. the KL switches on (for good) the first time ``C < eps``;
    3. the loss is formed with the current ``lambda`` (a constant, no gradient);
    4. if the KL is on and ``step % update_every == 0`` (once per step):
       ``delta = C - eps``, ``f = (1 - H(delta)) * tanh(tau * (1/lambda - 1)) - H(delta)``,
       ``lambda <- clip(lambda * clip(exp(-nu * f * delta), 0.9, 1.05), 1e-6, 1e8)``
       (H = Heaviside, H(0) = 0). The new lambda applies from the next call.

    Choice: lambda is frozen while the KL is off (otherwise it would only grow during the
    reconstruction phase). ``eps`` is in NLL-per-dimension units, including log sigma
    and 0.5 log 2pi of the Gaussian likelihood; pick it from the NLL/D an autoencoder
    reaches on the data. State (C, lambda, KL-on flag, last update step) is kept as
    plain Python values exposed through ``get_extra_state`` (saved in the state_dict).
    """

    name = "constrained"

    def __init__(self, eps: float = 0.0, lambda0: float = 1.0, nu: float = 1.0, tau: float = 100.0,
                 alpha: float = 0.99, update_every: int = 100,
                 lambda_min: float = 1e-6, lambda_max: float = 1e8) -> None:
        super().__init__()
        if update_every < 1 or not 0.0 <= alpha < 1.0 or lambda0 <= 0:
            raise ValueError("constrained annealing needs update_every >= 1, 0 <= alpha < 1, lambda0 > 0")
        self.eps, self.nu, self.tau, self.alpha = float(eps), float(nu), float(tau), float(alpha)
        self.update_every = int(update_every)
        self.lambda_min, self.lambda_max = float(lambda_min), float(lambda_max)
        self._config = {"eps": self.eps, "lambda0": float(lambda0), "nu": self.nu, "tau": self.tau,
                        "alpha": self.alpha, "update_every": self.update_every,
                        "lambda_min": self.lambda_min, "lambda_max": self.lambda_max}
        self.lambda_ = float(lambda0)
        self.c_ma = 0.0
        self.initialised = False
        self.kl_on = False
        self.last_update = -1

    # State goes into the owner's state_dict as plain Python values (``_extra_state``):
    # immune to dtype casts of the module (bf16-true, half()) and loadable with
    # torch.load(weights_only=True).
    def get_extra_state(self) -> dict[str, Any]:
        return {"lambda": self.lambda_, "c_ma": self.c_ma, "initialised": self.initialised,
                "kl_on": self.kl_on, "last_update": self.last_update}

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self.lambda_ = float(state["lambda"])
        self.c_ma = float(state["c_ma"])
        self.initialised = bool(state["initialised"])
        self.kl_on = bool(state["kl_on"])
        self.last_update = int(state["last_update"])

    def _update_lambda(self, step: int) -> None:
        delta = self.c_ma - self.eps
        lam = self.lambda_
        heav = 1.0 if delta > 0 else 0.0
        f = (1.0 - heav) * math.tanh(self.tau * (1.0 / lam - 1.0)) - heav
        factor = min(max(math.exp(min(-self.nu * f * delta, 50.0)), 0.9), 1.05)
        self.lambda_ = min(max(lam * factor, self.lambda_min), self.lambda_max)
        self.last_update = step

    def _loss(self, step, terms):
        if "n_dims" not in terms:
            raise KeyError("constrained annealing needs the 'n_dims' term")
        r = terms["nll"] / terms["n_dims"]
        if self.training:
            rv = float(r.detach())
            if not self.initialised:
                self.c_ma, self.initialised = rv, True
            else:
                self.c_ma = self.alpha * self.c_ma + (1.0 - self.alpha) * rv
            if not self.kl_on and self.c_ma < self.eps:
                self.kl_on = True
        lam, kl_on = self.lambda_, self.kl_on
        loss = r + (terms["kl_z"] + terms["kl_y"]) / lam if kl_on else r
        if self.training and kl_on and step % self.update_every == 0 and self.last_update != step:
            self._update_lambda(step)
        logs = {"anneal/lambda": lam, "anneal/C": self.c_ma, "anneal/kl_on": float(kl_on)}
        return loss, logs


SCHEDULES: dict[str, type[AnnealingSchedule]] = {
    cls.name: cls for cls in (NoAnnealing, DVBFAnnealing, LinearKLWarmup, GeometricKLWeights, ConstrainedAnnealing)
}


def build_schedule(spec: Any) -> AnnealingSchedule:
    """Schedule from an instance (returned as is; Hydra instantiates the ``_target_`` of
    ``configs/annealing/*.yaml`` before it gets here), ``None`` (-> ``none``), a name, or a
    mapping ``{"name": ..., **kwargs}`` (what :meth:`AnnealingSchedule.config` returns)."""
    if spec is None:
        return NoAnnealing()
    if isinstance(spec, AnnealingSchedule):
        return spec
    if isinstance(spec, str):
        spec = {"name": spec}
    if isinstance(spec, Mapping):
        spec = {str(k): v for k, v in spec.items()}
        if "_target_" in spec:
            raise TypeError(f"annealing {spec['_target_']!r}: a _target_ mapping is built by Hydra's instantiate, "
                            "pass the instance (or {name: ..., **kwargs})")
        name = spec.pop("name", None)
        if name not in SCHEDULES:
            raise ValueError(f"unknown annealing schedule {name!r}; choose from {sorted(SCHEDULES)}")
        return SCHEDULES[name](**spec)
    raise TypeError(f"cannot build an annealing schedule from {type(spec).__name__}")
