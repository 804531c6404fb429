"""How the label-conditioned prior's object codes and q(y) relate (docs/experiments/object_codes.md). Arrays only, NumPy.

The hierarchical prior gives every training object n a code e_n and pulls q(y_t) of that
object's sequences towards it (``KL(q(y_t) || N(e_n, sigma^2))``). Three questions tell
whether that pull puts the objects into y:

* :func:`code_spread`: how far apart the codes are in units of the prior's standard
  deviation (codes within a fraction of sigma of each other ask y for no distinction);
* :func:`affine_r2`: how much of the codes' final arrangement is an affine image of their
  initial random draws (1 = the codes did not learn an arrangement of their own);
* :func:`own_code_rank`: per sequence, the rank of its own object's code among all codes by
  the prior's Mahalanobis distance to q(y)'s mean (0 = q(y) is nearest its own object's
  code: y recognises the object).
"""

from __future__ import annotations

import numpy as np


def _check(codes: np.ndarray, var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    codes = np.asarray(codes, np.float64)
    var = np.broadcast_to(np.asarray(var, np.float64), codes.shape[-1:])
    if codes.ndim != 2:
        raise ValueError(f"codes must be (n_objects, n_y), got shape {codes.shape}")
    if not np.all(var > 0):
        raise ValueError("prior variances must be > 0")
    return codes, var


def code_spread(codes, var) -> float:
    """Median pairwise Mahalanobis distance sqrt(sum_d (e_n - e_m)_d^2 / var_d) between the
    codes (n_objects, n_y) under the prior's per-dimension variance ``var`` (n_y,)."""
    codes, var = _check(codes, var)
    if len(codes) < 2:
        raise ValueError("code_spread needs at least two codes")
    d = np.sqrt((((codes[:, None] - codes[None]) ** 2) / var).sum(-1))
    return float(np.median(d[np.triu_indices(len(codes), 1)]))


def affine_r2(initial, final) -> float:
    """R^2 of the least-squares fit final ~ initial @ A + b over all codes and dimensions:
    the share of the final codes' variance (around their per-dimension mean) that an affine
    map of the initial draws explains."""
    x, y = np.asarray(initial, np.float64), np.asarray(final, np.float64)
    if x.shape != y.shape or x.ndim != 2:
        raise ValueError(f"initial and final codes must be equal (n_objects, n_y) arrays, got {x.shape}, {y.shape}")
    xa = np.c_[x, np.ones(len(x))]
    w, *_ = np.linalg.lstsq(xa, y, rcond=None)
    ss = ((y - y.mean(0)) ** 2).sum()
    if ss == 0:
        raise ValueError("the final codes are all equal: R^2 is undefined")
    return float(1.0 - ((xa @ w - y) ** 2).sum() / ss)


def own_code_rank(y_mean, object_id, codes, var, objects=None) -> np.ndarray:
    """y_mean (n, n_y), object_id (n,) -> (n,) rank of each sequence's own code among the
    codes of ``objects`` (default: every row of ``codes``) by Mahalanobis distance to y_mean
    (0 = nearest). Every object id must be among ``objects``."""
    codes, var = _check(codes, var)
    objects = np.arange(len(codes)) if objects is None else np.asarray(objects)
    y = np.asarray(y_mean, np.float64)
    oid = np.asarray(object_id)
    pos = {int(o): i for i, o in enumerate(objects)}
    missing = sorted({int(o) for o in oid} - set(pos))
    if missing:
        raise ValueError(f"object ids {missing} have no code among the {len(objects)} objects given")
    d = (((y[:, None] - codes[objects][None]) ** 2) / var).sum(-1)  # (n, n_objects)
    own = d[np.arange(len(y)), [pos[int(o)] for o in oid]]
    return (d < own[:, None]).sum(1)
