"""Label-free terms added to the context objective (docs/reference/model.md, "Invariance and
physical terms"): they ask y to carry what touches of one object share, without property
labels. Weights are :class:`~.options.ContextOptions` ``invariance`` and ``physical`` (0:
off, the default); the terms are per sequence, averaged over the batch, in float32.

* :func:`invariance_terms`: VICReg (Bardes et al. 2022) between the posterior means of y
  inferred from two different touches of one object (the context touch and the target
  touch, another trial under another action with ``context.source=trial``): an invariance
  term (mean squared difference), a variance hinge per dimension over the batch (the
  standard deviation of each y dimension kept above ``gamma``, so agreement cannot be
  bought by collapse) and a covariance term (off-diagonal covariances squared, so the
  dimensions do not copy one another).
* :class:`FeatureHead` and :func:`physical_term`: y of one touch predicts fixed physical
  functions of ANOTHER touch's observations, the hand-crafted features
  (:func:`embodied_tactile.data.features.handcrafted_features`: peak force, force-depth
  slope, hysteresis, relaxation, contact area, vibration bands ...) of the target crop,
  standardised by the training trials. These features are the hand-crafted reader's: the
  term imports that reader's bias into y (what a person decided matters in a touch), it
  is not a neutral self-supervision. They are targets only, never property labels.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from embodied_tactile.data.features import handcrafted_features

from .networks import float32_region

#: VICReg's coefficients relative to its invariance term (25 : 25 : 1 in the paper)
VARIANCE_WEIGHT = 1.0
COVARIANCE_WEIGHT = 0.04
#: the standard deviation each y dimension is kept above, and the variance's epsilon
VARIANCE_TARGET = 1.0
VARIANCE_EPS = 1e-4


def _std(x: Tensor) -> Tensor:
    """Per-dimension standard deviation over the batch (B, d) -> (d,), with the epsilon."""
    var = ((x - x.mean(0)) ** 2).sum(0) / max(1, x.shape[0] - 1)
    return torch.sqrt(var + VARIANCE_EPS)


def _covariance(x: Tensor) -> Tensor:
    """Sum of the squared off-diagonal covariances over the batch, divided by d."""
    b, d = x.shape
    xc = x - x.mean(0)
    cov = xc.T @ xc / max(1, b - 1)
    off = cov - torch.diag(torch.diagonal(cov))
    return (off ** 2).sum() / d


def invariance_terms(y_a: Tensor, y_b: Tensor, gamma: float = VARIANCE_TARGET) -> dict[str, Tensor]:
    """VICReg terms of two views y_a, y_b (B, d) of the same objects (row i of each: one
    object), float32 scalars:

    invariance = mean_i sum_d (y_a - y_b)^2 / d  (the mean squared difference)
    variance   = mean_d max(0, gamma - std_d(y_a)) + the same of y_b
    covariance = C(y_a) + C(y_b),  C(x) = sum_{j != k} cov_jk(x)^2 / d
    total      = invariance + VARIANCE_WEIGHT variance + COVARIANCE_WEIGHT covariance

    A batch of identical rows gives finite values (std sqrt(eps), covariance 0); a batch of
    one row has no spread to measure (variance and covariance from a divisor of 1)."""
    if y_a.shape != y_b.shape or y_a.dim() != 2:
        raise ValueError(f"invariance_terms needs two (B, d) views alike, got {tuple(y_a.shape)}, {tuple(y_b.shape)}")
    with float32_region(y_a):
        a, b = y_a.float(), y_b.float()
        inv = ((a - b) ** 2).mean()
        var = torch.relu(gamma - _std(a)).mean() + torch.relu(gamma - _std(b)).mean()
        cov = _covariance(a) + _covariance(b)
        total = inv + VARIANCE_WEIGHT * var + COVARIANCE_WEIGHT * cov
    return {"invariance": inv, "variance": var, "covariance": cov, "total": total}


def feature_count(channels: list[str] | tuple[str, ...]) -> int:
    """How many hand-crafted features a touch of these channels has (the head's outputs)."""
    f, _ = handcrafted_features(np.zeros((1, 2, len(channels), 28, 28), np.float32), np.zeros((1, 2, 6)), channels)
    return int(f.shape[-1])


def action_summary(actions: Tensor) -> Tensor:
    """The target crop's actions (B, T, n_a) -> (B, 2 n_a): their mean and standard deviation
    over the crop (the features depend on how the touch was made as well as on the object)."""
    a = actions.float()
    return torch.cat([a.mean(1), a.std(1, unbiased=False)], dim=-1)


class FeatureHead(nn.Module):
    """[y, :func:`action_summary` of the target touch] -> its standardised hand-crafted
    features: one hidden layer (ReLU)."""

    def __init__(self, n_y: int, n_a: int, n_features: int, hidden: int = 64) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(n_y + 2 * n_a, hidden), nn.ReLU(), nn.Linear(hidden, n_features))
        self.n_features = int(n_features)

    def forward(self, y: Tensor, actions: Tensor) -> Tensor:
        return self.net(torch.cat([y.float(), action_summary(actions)], dim=-1))


def physical_term(pred: Tensor, target: Tensor) -> Tensor:
    """Per sequence: the mean squared error over the standardised features (B, k), averaged
    over the batch (float32)."""
    if pred.shape != target.shape:
        raise ValueError(f"physical_term: prediction {tuple(pred.shape)} and target {tuple(target.shape)} differ")
    return ((pred.float() - target.float()) ** 2).mean()


__all__ = ["FeatureHead", "action_summary", "feature_count", "invariance_terms", "physical_term"]
