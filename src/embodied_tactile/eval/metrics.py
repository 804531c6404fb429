"""The one error metric of the project: normalised mean squared error (NMSE).

Every table, figure, callback and baseline calls :func:`nmse` (or the thin wrappers below,
which call it), so there is exactly one definition::

    NMSE_k = sum_i (y_ik - yhat_ik)^2 / sum_i (y_ik - mean_i(y_ik))^2

per factor ``k`` over held-out samples ``i``. NMSE = 1 is what the train-mean predictor
scores (up to the train/test mean shift); 0 is perfect. Unknown targets (NaN) are ignored.
A factor with zero variance among the scored samples has no defined NMSE: it is returned as
NaN with a :class:`NMSEUndefinedWarning`, never as inf or 0.

For subsets (one action index, one object group) the paper's tables need values even when
a factor is constant inside the subset (heterogeneity is 1 for every heterogeneous object).
There the denominator is the *reference variance* of the factor over all held-out sequences
of the same model: pass ``var_ref``. On the full held-out set of one model both forms agree.
"""

from __future__ import annotations

import warnings

import numpy as np

NMSE_DEFINITION = (
    "NMSE_k = sum_{i,t} (y_ik - yhat_ikt)^2 / sum_{i,t} (y_ik - mean_i y_ik)^2 per factor k over "
    "held-out sequences i (and frames t); for a subset (action index, object group) the denominator "
    "uses the variance of factor k over all held-out sequences of the same model; Overall = mean "
    "over factors. The alignment regressor is fitted on training sequences only (0 = perfect, "
    "1 = train-mean predictor)."
)


#: The convention of the authors' public code for the same model family, beside which the
#: study report sets its NMSE tables (the paper names its metric "NMSE" and defines it no further).
SCALED_MSE_DEFINITION = (
    "MSE_01_k = mean_{i,t} ((y_ik - yhat_ikt) / r_k)^2: the squared error on targets min-max scaled to "
    "[0, 1] per factor k over its design range r_k (3-level factors: r = 2 ranks; heterogeneity: 1), "
    "not divided by the targets' variance: the convention of the authors' public code for the same model "
    "family. The paper names its metric NMSE and does not define it further. From the same predictions "
    "MSE_01_k = NMSE_k * var_k / r_k^2, var_k the held-out variance NMSE_k divides by; Overall = mean over factors."
)


def scaled_mse_from_nmse(nmse_k, var_ref, value_range) -> np.ndarray:
    """Per-factor NMSE -> the squared error on targets min-max scaled to [0, 1] over
    ``value_range`` (:data:`SCALED_MSE_DEFINITION`): ``nmse * var_ref / value_range**2``.
    Exact for the same predictions when ``var_ref`` is the variance the NMSE divided by
    (:func:`nmse`'s denominator is ``n * var``; its numerator is the squared error)."""
    r = np.asarray(value_range, dtype=np.float64)
    return np.asarray(nmse_k, dtype=np.float64) * np.asarray(var_ref, dtype=np.float64) / (r * r)


class NMSEUndefinedWarning(UserWarning):
    """A factor has zero (or no) variance among the scored targets: its NMSE is NaN."""


def nmse(y, y_hat, axis=0, *, var_ref=None) -> np.ndarray:
    """Per-factor NMSE = sum (y - y_hat)^2 / sum (y - mean(y))^2 along ``axis``.

    ``y`` and ``y_hat`` broadcast against each other (e.g. ``y`` (n, 1, 4) against
    ``y_hat`` (n, T, 4) with ``axis=(0, 1)``). NaN targets are masked out. ``axis`` may be a
    tuple. ``var_ref`` (broadcastable to the result): use this variance per factor instead of
    the variance of the scored ``y`` (subset NMSE, see module docstring).
    """
    y = np.asarray(y, dtype=np.float64)
    y_hat = np.asarray(y_hat, dtype=np.float64)
    y, y_hat = np.broadcast_arrays(y, y_hat)
    mask = np.isfinite(y)
    n = mask.sum(axis=axis)
    yz = np.where(mask, y, 0.0)
    err = np.where(mask, (yz - np.where(mask, y_hat, 0.0)) ** 2, 0.0).sum(axis=axis)
    if var_ref is None:
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = yz.sum(axis=axis, keepdims=True) / mask.sum(axis=axis, keepdims=True)
        den = np.where(mask, (yz - mean) ** 2, 0.0).sum(axis=axis)
    else:
        den = n * np.asarray(var_ref, dtype=np.float64)
    den = np.asarray(den, dtype=np.float64)
    bad = ~(den > 1e-12 * np.maximum(1.0, n)) | (n == 0)
    if np.any(bad):
        warnings.warn(
            f"NMSE undefined (zero target variance or no finite targets) for {int(np.sum(bad))} "
            "entr(y/ies); returning NaN there",
            NMSEUndefinedWarning,
            stacklevel=2,
        )
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(bad, np.nan, np.asarray(err) / np.where(bad, 1.0, den))
    return out


def reference_variance(factors) -> np.ndarray:
    """Per-factor variance over sequences (NaN-aware) used as ``var_ref`` for subsets."""
    f = np.asarray(factors, dtype=np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanvar(f, axis=0)


def nmse_over_time(factors, pred, *, var_ref=None) -> np.ndarray:
    """NMSE at every frame: factors (n, 4), pred (n, T, 4) -> (T, 4) (across sequences)."""
    factors = np.asarray(factors, dtype=np.float64)
    return nmse(factors[:, None, :], pred, axis=0, var_ref=var_ref)


def nmse_trajectory(factors, pred, *, var_ref=None) -> np.ndarray:
    """NMSE over the whole trajectory (all sequences x all frames): -> (4,)."""
    factors = np.asarray(factors, dtype=np.float64)
    return nmse(factors[:, None, :], pred, axis=(0, 1), var_ref=var_ref)


def overall(per_factor) -> float:
    """Mean over factors (NaN factors skipped; NaN if all are NaN)."""
    v = np.asarray(per_factor, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


# ----------------------------------------------------------------------------- binary factor (heterogeneity)
def _binary(y, score) -> tuple[np.ndarray, np.ndarray]:
    """Broadcast labels against scores, flatten, drop non-finite labels or scores."""
    y, s = np.broadcast_arrays(np.asarray(y, dtype=np.float64), np.asarray(score, dtype=np.float64))
    y, s = y.ravel(), s.ravel()
    keep = np.isfinite(y) & np.isfinite(s)
    y, s = y[keep], s[keep]
    if np.any((y != 0) & (y != 1)):
        raise ValueError(f"binary labels must be 0/1, got {sorted(set(np.unique(y)) - {0.0, 1.0})[:3]}")
    return y.astype(bool), s


def balanced_accuracy(y, score, threshold: float = 0.5) -> float:
    """Mean of the true-positive and true-negative rates of ``score >= threshold`` against 0/1
    labels ``y`` (broadcast: labels (n, 1) against scores (n, T) score every frame). NaN when
    one class is absent."""
    y, s = _binary(y, score)
    if y.all() or not y.any():
        return float("nan")
    hit = s >= threshold
    return float(0.5 * (hit[y].mean() + (~hit[~y]).mean()))


def roc_auc(y, score) -> float:
    """Area under the ROC curve of the continuous ``score`` against 0/1 labels ``y``: the
    probability that a random positive scores above a random negative, ties counting one
    half (Mann-Whitney U / (n_pos n_neg), from mid-ranks). NaN when one class is absent."""
    from scipy.stats import rankdata

    y, s = _binary(y, score)
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    ranks = rankdata(s)
    return float((ranks[y].sum() - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))


def bootstrap_overall(factors, pred, groups, *, n_boot: int = 1000, seed: int = 0) -> np.ndarray:
    """The test sample's own noise: Overall NMSE (whole trajectory, last frame) recomputed on
    ``n_boot`` resamples of the held-out sequences drawn by ``groups`` (an object id per
    sequence: every sequence of a drawn object comes along, so the objects are the sampled
    units; a sequence id per sequence resamples sequences). factors (n, K), pred (n, T, K)
    -> (n_boot, 2). Each resample's NMSE divides by its own targets' variance, as the full
    set's does; a resample whose factor has no variance gives NaN for that factor, which
    :func:`overall` skips."""
    factors = np.asarray(factors, dtype=np.float64)
    pred = np.asarray(pred, dtype=np.float64)
    groups = np.asarray(groups)
    units = np.unique(groups)
    members = [np.flatnonzero(groups == u) for u in units]
    rng = np.random.default_rng(seed)
    out = np.empty((int(n_boot), 2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NMSEUndefinedWarning)
        for b in range(int(n_boot)):
            idx = np.concatenate([members[i] for i in rng.integers(0, len(units), len(units))])
            f, p = factors[idx], pred[idx]
            out[b] = overall(nmse_trajectory(f, p)), overall(nmse_over_time(f, p)[-1])
    return out
