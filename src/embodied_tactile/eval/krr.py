"""Latent -> factor alignment: RBF kernel ridge regression, fitted on training sequences only.

Protocol (paper, "Analysis on Multi-Modality"; ``latent-filter-notes.md``, "Evaluation
protocol"):

* Rows for fitting come from the *final segment* of every *training* sequence
  (``final_segment``: a fraction of T, or a number of frames). ``reduce="frames"`` (default)
  takes ``frames_per_sequence`` frames evenly spaced over that segment (the last frame always
  included), so the regressor is trained on single-frame latents -- the same kind of input it
  is applied to; ``reduce="mean"`` takes the segment mean (one row per sequence).
* Inputs are standardised with a scaler fitted on those training rows; targets are
  standardised too; the regressor is ``KernelRidge(kernel="rbf")`` (sklearn's default kernel
  is linear -- never used here). ``alpha`` and ``gamma`` are chosen by a grid search (equivalent to ``GridSearchCV``, see ``_grid_cv``) over
  grouped folds (``GroupKFold``), on training rows only: grouped by sequence (the frames of
  one sequence never sit on both sides of a fold) or by object (:func:`alignment_kwargs`; what an
  object split asks). ``gamma`` grid values are multiples of 1/d; the ``alpha`` grid reaches
  100, where the fit is close to the training mean, so the search can choose "the latents do
  not help" when they do not.
* With more than ``nystroem_threshold`` rows, exact KRR (O(n^3)) is replaced by
  ``Nystroem`` RBF features + ``Ridge`` with the same grid search.
* ``readout="per_time"`` fits one such alignment per span of the trial (:func:`time_spans`:
  frame 0 alone, geometric edges, the final tenth last; each span's rows drawn from that
  span as above with ``final_segment=1.0``, its grid search scored on every frame of the
  span) and reads each frame with its span's probe (:class:`TimeResolvedAlignment`);
  ``readout="final_segment"`` (the paper's protocol) fits one on the final segment and reads
  every frame with it. The options and their defaults: :mod:`embodied_tactile.options.alignment`.
* The fitted :class:`Alignment` predicts at every frame of (held-out) sequences, in the
  factors' original units. When sequence ids are given at fit and predict time, predicting
  on a training id raises :class:`LeakageError`.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass, field
from typing import Any, Sequence

import numpy as np
import scipy.linalg
from sklearn.kernel_approximation import Nystroem
from sklearn.kernel_ridge import KernelRidge
from sklearn.linear_model import Ridge
from sklearn.model_selection import GroupKFold
from sklearn.pipeline import Pipeline

from ..options.alignment import DEFAULT_ALPHAS, DEFAULT_GAMMAS, READOUTS, AlignmentOptions


def resolve_cv_grouping(grouping: str, split: str) -> str:
    """'sequence' or 'object': how the alignment's CV folds group the training sequences.

    ``grouping`` (:attr:`AlignmentOptions.groups`): 'sequence' or 'object', or 'auto':
    'object' on an object split (the question is generalisation to objects never seen, so
    hyper-parameters are chosen on folds whose objects the fit did not see), 'sequence' on the
    trial split (held-out trials of objects the fit saw, the paper's question). ``split``: the
    run's split kind.
    """
    if grouping == "auto":
        return "object" if split == "object" else "sequence"
    return grouping


def alignment_kwargs(alignment: AlignmentOptions | None, split: str, object_ids) -> dict:
    """:func:`fit_alignment`'s keywords from the typed ``alignment`` (built where it entered:
    :func:`~embodied_tactile.options.alignment.alignment_options`; None: the defaults), with its ``groups`` name
    resolved to the object id per training sequence when :func:`resolve_cv_grouping` says
    'object', None (each sequence its own group) otherwise."""
    alignment = AlignmentOptions() if alignment is None else alignment
    if not isinstance(alignment, AlignmentOptions):
        raise TypeError(f"alignment_kwargs takes an AlignmentOptions (alignment_options(...) at the entry), "
                        f"got {type(alignment).__name__}")
    kw = asdict(alignment)
    if resolve_cv_grouping(kw["groups"], split) == "sequence":
        kw["groups"] = None
    elif object_ids is None:
        raise ValueError("alignment groups='object' needs the training sequences' object ids (object_id)")
    else:
        kw["groups"] = np.asarray(object_ids)
    return kw


class LeakageError(AssertionError):
    """An alignment was asked to score a sequence it was fitted on."""


def assert_disjoint(train_ids, test_ids, what: str = "sequence ids") -> None:
    """Raise :class:`LeakageError` when the two id sets intersect."""
    if train_ids is None or test_ids is None:
        return
    common = set(np.asarray(train_ids).ravel().tolist()) & set(np.asarray(test_ids).ravel().tolist())
    if common:
        some = sorted(common)[:5]
        raise LeakageError(f"{len(common)} {what} are in both the fitting and the scored set (e.g. {some})")


def final_segment_rows(
    latents: np.ndarray,
    *,
    final_segment: float | int = 0.1,
    reduce: str = "frames",
    frames_per_sequence: int = 4,
) -> tuple[np.ndarray, np.ndarray]:
    """Rows for fitting: latents (n, T, d) -> (rows (m, d), sequence index of each row (m,))."""
    lat = np.asarray(latents, dtype=np.float64)
    if lat.ndim == 2:
        lat = lat[:, None, :]
    n, t, _ = lat.shape
    if isinstance(final_segment, (float, np.floating)) and float(final_segment) > 1.0 and float(final_segment).is_integer():
        final_segment = int(final_segment)  # a frame count that passed through a float-typed option
    if isinstance(final_segment, (float, np.floating)):
        if not 0.0 < float(final_segment) <= 1.0:
            raise ValueError(f"final_segment as a fraction (float) must be in (0, 1], got {final_segment}")
        seg = max(1, int(round(float(final_segment) * t)))
    else:
        seg = int(final_segment)
        if seg < 1:
            raise ValueError(f"final_segment as a frame count (int) must be >= 1, got {final_segment}")
    seg = min(seg, t)
    tail = lat[:, t - seg :, :]
    if reduce == "mean":
        return tail.mean(axis=1), np.arange(n)
    if reduce != "frames":
        raise ValueError(f"reduce must be 'frames' or 'mean', got {reduce!r}")
    k = max(1, min(int(frames_per_sequence), seg))
    idx = np.unique(np.round(np.linspace(seg - 1, 0, k)).astype(int))
    rows = tail[:, idx, :].reshape(n * len(idx), -1)
    return rows, np.repeat(np.arange(n), len(idx))


@dataclass
class Alignment:
    """A fitted latent -> factor regressor; ``predict`` returns original factor units."""

    model: Any
    x_mean: np.ndarray
    x_scale: np.ndarray
    y_mean: np.ndarray
    y_scale: np.ndarray
    params: dict = field(default_factory=dict)
    train_ids: frozenset | None = None

    def predict(self, latents, ids=None, *, chunk_rows: int = 16384) -> np.ndarray:
        """latents (n, T, d) or (n, d) -> predictions (n, T, 4) (T = 1 for 2-D input)."""
        if ids is not None and self.train_ids is not None:
            assert_disjoint(list(self.train_ids), ids)
        lat = np.asarray(latents, dtype=np.float64)
        if lat.ndim == 2:
            lat = lat[:, None, :]
        n, t, d = lat.shape
        if d != self.x_mean.shape[0]:
            raise ValueError(f"latent dimension {d} != fitted dimension {self.x_mean.shape[0]}")
        x = ((lat.reshape(n * t, d) - self.x_mean) / self.x_scale).astype(np.float64)
        out = np.empty((n * t, self.y_mean.shape[0]))
        for s in range(0, n * t, chunk_rows):
            p = self.model.predict(x[s : s + chunk_rows])
            out[s : s + chunk_rows] = np.asarray(p).reshape(len(x[s : s + chunk_rows]), -1)
        return (out * self.y_scale + self.y_mean).reshape(n, t, -1)


class FactorwiseAlignment:
    """Alignments of groups of factor columns, each fitted on the sequences where those
    factors are known (a factor NaN on some sequences leaves only that factor's alignment
    without them); a column known on fewer than 2 sequences is predicted NaN. Same
    interface as :class:`Alignment`; ``params`` are the first fitted part's, with every
    part under ``parts``."""

    def __init__(self, parts: list[tuple[list[int], "Alignment | None"]], n_factors: int,
                 train_ids: frozenset | None = None) -> None:
        self.parts = parts
        self.n_factors = n_factors
        self.train_ids = train_ids
        fitted = [(cols, a) for cols, a in parts if a is not None]
        if not fitted:
            raise ValueError("fit_alignment needs at least 2 training rows with finite factors")
        self.params = {**fitted[0][1].params, "method": fitted[0][1].params["method"],
                       "parts": [{"factor_columns": cols, **(a.params if a is not None else {"left_out": True})}
                                 for cols, a in parts]}

    def predict(self, latents, ids=None, *, chunk_rows: int = 16384) -> np.ndarray:
        if ids is not None and self.train_ids is not None:
            assert_disjoint(list(self.train_ids), ids)
        out = None
        for cols, a in self.parts:
            if a is None:
                continue
            p = a.predict(latents, chunk_rows=chunk_rows)
            if out is None:
                out = np.full((*p.shape[:2], self.n_factors), np.nan)
            out[..., cols] = p
        return out


def fit_alignment(
    latents,
    factors,
    *,
    ids: Sequence | None = None,
    groups: Sequence | None = None,
    readout: str = AlignmentOptions.readout,
    time_bins: int = AlignmentOptions.time_bins,
    final_segment: float | int = AlignmentOptions.final_segment,
    reduce: str = "frames",
    frames_per_sequence: int = AlignmentOptions.frames_per_sequence,
    cv: int = AlignmentOptions.cv,
    alphas: Sequence[float] = DEFAULT_ALPHAS,
    gammas: Sequence[float] = DEFAULT_GAMMAS,
    nystroem_threshold: int = AlignmentOptions.nystroem_threshold,
    n_components: int = AlignmentOptions.n_components,
    seed: int = AlignmentOptions.seed,
    n_threads: int | None = None,
    cv_every_frame: bool = False,
) -> "Alignment | FactorwiseAlignment | TimeResolvedAlignment":
    """Fit the RBF-KRR alignment on TRAINING sequences only.

    latents (n, T, d) (or (n, d): one latent per sequence, e.g. hand-crafted features),
    factors (n, K) in original units (NaN = unknown: such rows are dropped). ``ids``: sequence
    ids (stored; :meth:`Alignment.predict` refuses them). ``groups``: CV group per sequence
    (default: the sequence itself; pass object ids for object-disjoint folds). ``readout``:
    'per_time' (a probe per span of :func:`time_spans`) or 'final_segment' (module docstring).
    ``n_threads``: BLAS threads during the fit (None: leave as is; 1 is much faster on a
    loaded small machine). ``cv_every_frame``: the grid search scores a held-out fold on every
    frame of its sequences' segment, not only on the rows it fits (the per-time read-out's
    probes: the quantity reported is every frame).
    """
    kw = dict(final_segment=final_segment, reduce=reduce, frames_per_sequence=frames_per_sequence, cv=cv,
              alphas=alphas, gammas=gammas, nystroem_threshold=nystroem_threshold, n_components=n_components,
              seed=seed, n_threads=None, cv_every_frame=cv_every_frame)
    if n_threads is not None:
        from threadpoolctl import threadpool_limits

        with threadpool_limits(int(n_threads)):
            return fit_alignment(latents, factors, ids=ids, groups=groups, readout=readout, time_bins=time_bins,
                                 **kw)
    if readout not in READOUTS:
        raise ValueError(f"readout must be one of {READOUTS}, got {readout!r}")
    lat = np.asarray(latents, dtype=np.float64)
    if readout == "per_time" and lat.ndim == 3 and lat.shape[1] > 1:  # one frame per row: nothing to resolve
        return TimeResolvedAlignment.fit(lat, factors, ids=ids, groups=groups, time_bins=time_bins, **kw)
    t0 = time.perf_counter()
    factors = np.asarray(factors, dtype=np.float64)
    if factors.ndim == 1:
        factors = factors[:, None]
    n = lat.shape[0]
    if factors.shape[0] != n:
        raise ValueError(f"{n} latent sequences but {factors.shape[0]} factor rows")
    known = np.isfinite(factors)
    by_mask: dict[bytes, list[int]] = {}
    for k in range(factors.shape[1]):
        by_mask.setdefault(known[:, k].tobytes(), []).append(k)
    if len(by_mask) > 1:  # factors unknown (NaN) on different sequences: one alignment per pattern
        parts: list[tuple[list[int], Alignment | None]] = []
        for cols in by_mask.values():
            mask = known[:, cols[0]]
            if mask.sum() < 2:
                warnings.warn(f"fit_alignment: factor column(s) {cols} known on {int(mask.sum())} sequence(s): "
                              "left out (predicted NaN)", stacklevel=2)
                parts.append((cols, None))
                continue
            parts.append((cols, fit_alignment(
                lat[mask], factors[mask][:, cols], ids=None if ids is None else np.asarray(ids)[mask],
                groups=None if groups is None else np.asarray(groups)[mask], readout="final_segment", **kw)))
        return FactorwiseAlignment(parts, factors.shape[1],
                                   frozenset(np.asarray(ids).tolist()) if ids is not None else None)
    if ids is not None and len(set(np.asarray(ids).tolist())) != n:
        raise ValueError("ids must be unique, one per training sequence")
    rows, seq = final_segment_rows(lat, final_segment=final_segment, reduce=reduce,
                                   frames_per_sequence=frames_per_sequence)
    y = factors[seq]
    ok = np.all(np.isfinite(y), axis=1) & np.all(np.isfinite(rows), axis=1)
    if not ok.all():
        warnings.warn(f"fit_alignment: dropping {int((~ok).sum())} rows with NaN factors/latents", stacklevel=2)
    rows, y, seq = rows[ok], y[ok], seq[ok]
    if len(rows) < 2:
        raise ValueError("fit_alignment needs at least 2 training rows with finite factors")
    grp = seq if groups is None else np.asarray(groups)[seq]

    x_mean = rows.mean(0)
    x_scale = rows.std(0)
    x_scale = np.where(x_scale > 1e-12, x_scale, 1.0)
    y_mean = y.mean(0)
    y_scale = y.std(0)
    y_scale = np.where(y_scale > 1e-12, y_scale, 1.0)
    xs = (rows - x_mean) / x_scale
    ys = (y - y_mean) / y_scale
    d = xs.shape[1]
    gamma_grid = [float(g) / d for g in gammas]

    nystroem = len(xs) > nystroem_threshold
    m = min(int(n_components), len(xs))
    n_groups = len(np.unique(grp))
    n_splits = min(int(cv), n_groups)
    if n_splits >= 2 and len(gamma_grid) * len(alphas) > 1:
        folds = list(GroupKFold(n_splits=n_splits, shuffle=True, random_state=seed).split(xs, ys, groups=grp))
        scored = None
        if cv_every_frame:  # every frame of the segment of each sequence with finite factors and latents
            every, every_seq = final_segment_rows(lat, final_segment=final_segment, reduce=reduce,
                                                  frames_per_sequence=lat.shape[1])
            fine = np.all(np.isfinite(factors[every_seq]), axis=1) & np.all(np.isfinite(every), axis=1)
            every, every_seq = every[fine], every_seq[fine]
            scored = ((every - x_mean) / x_scale, (factors[every_seq] - y_mean) / y_scale,
                      [np.isin(every_seq, np.unique(seq[te])) for _, te in folds])
        cv_scores = _grid_cv(xs, ys, folds, gamma_grid, list(alphas), nystroem=nystroem, m=m, seed=seed,
                             scored=scored)
        gi, ai = np.unravel_index(np.nanargmin(cv_scores), cv_scores.shape)
        gamma, alpha = gamma_grid[gi], float(alphas[ai])
        cv_mse = float(cv_scores[gi, ai])
    else:
        gamma, alpha = gamma_grid[len(gamma_grid) // 2], float(alphas[len(alphas) // 2])
        cv_mse = float("nan")
    if nystroem:
        model = Pipeline([
            ("features", Nystroem(kernel="rbf", gamma=gamma, n_components=m, random_state=seed)),
            ("ridge", Ridge(alpha=alpha)),
        ]).fit(xs, ys)
    else:
        model = KernelRidge(kernel="rbf", gamma=gamma, alpha=alpha).fit(xs, ys)
    params = {
        "method": "nystroem_ridge" if nystroem else "exact_krr",
        "readout": "final_segment",
        "kernel": "rbf",
        "alpha": float(alpha),
        "gamma": float(gamma),
        "gamma_times_d": float(gamma) * d,
        "cv_folds": int(n_splits),
        "cv_grid_mse": cv_scores.tolist() if n_splits >= 2 and len(gamma_grid) * len(alphas) > 1 else None,
        "cv_grouping": "sequence" if groups is None else "given groups",
        "cv_mse_standardised": cv_mse,
        "cv_every_frame": bool(cv_every_frame),
        "n_train_sequences": int(n),
        "n_train_rows": int(len(xs)),
        "final_segment": final_segment,
        "reduce": reduce,
        "frames_per_sequence": int(frames_per_sequence) if reduce == "frames" else 1,
        "n_components": m if nystroem else None,
        "seed": int(seed),
        "fit_time_s": time.perf_counter() - t0,
    }
    return Alignment(model, x_mean, x_scale, y_mean, y_scale, params,
                     frozenset(np.asarray(ids).tolist()) if ids is not None else None)


def time_spans(n_frames: int, time_bins: int) -> list[tuple[int, int]]:
    """The per-time read-out's spans: contiguous [start, stop) covering frames 0 .. n_frames - 1.
    Frame 0 is a span of its own, the last span is the final tenth (the paper's segment), the
    edges in between grow geometrically (``time_bins`` of them), so spans are short where a
    filter's posterior moves fastest, and no span is longer than ``n_frames / time_bins``
    (the edges of ``time_bins`` equal spans are added). For 300 frames and 10 bins: 18 spans,
    (0, 1), (1, 2), (2, 4), (4, 8), (8, 16), (16, 30), ..., (240, 270), (270, 300).
    Screened on the validation objects against equal spans and geometric spans alone
    (docs/experiments/readout_over_time.md)."""
    n, b = int(n_frames), max(1, int(time_bins))
    head = n - max(1, int(round(0.1 * n)))
    geometric = np.geomspace(1, head, b - 1) if head >= 1 and b > 1 else []
    edges = np.unique(np.round(np.concatenate([[0.0, n], geometric, np.linspace(0, n, b + 1)])).astype(int))
    return [(int(a), int(c)) for a, c in zip(edges[:-1], edges[1:])]


class TimeResolvedAlignment:
    """A probe per span of the trial (``readout='per_time'``): each span of
    :func:`time_spans` has its own :class:`Alignment`, fitted on the training latents of that span
    (with its own cross-validated ``alpha`` and ``gamma``); :meth:`predict` reads each frame
    with its span's probe. Spans are fractions of the trial, so a held-out trial of another
    length is cut the same way. ``params``: the last span's (the final segment's), with every
    span's under ``spans``."""

    def __init__(self, probes: list, time_bins: int, n_frames: int, train_ids: frozenset | None = None) -> None:
        self.probes, self.time_bins, self.n_frames, self.train_ids = probes, int(time_bins), int(n_frames), train_ids
        spans = time_spans(n_frames, time_bins)
        last = probes[-1].params
        self.params = {**last, "readout": "per_time", "time_bins": int(time_bins),
                       "fit_time_s": float(sum(p.params["fit_time_s"] for p in probes)),
                       "spans": [{"frames": [a, b], **{k: p.params.get(k) for k in ("alpha", "gamma", "method",
                                                                                        "cv_mse_standardised")}}
                                 for (a, b), p in zip(spans, probes)]}

    @classmethod
    def fit(cls, latents: np.ndarray, factors, *, ids=None, groups=None, time_bins: int, **kw) -> "TimeResolvedAlignment":
        n_frames = latents.shape[1]
        probes = []
        for a, b in time_spans(n_frames, time_bins):
            probes.append(fit_alignment(latents[:, a:b], factors, ids=ids, groups=groups, readout="final_segment",
                                        **{**kw, "final_segment": 1.0, "cv_every_frame": True}))
        return cls(probes, time_bins, n_frames, frozenset(np.asarray(ids).tolist()) if ids is not None else None)

    def predict(self, latents, ids=None, *, chunk_rows: int = 16384) -> np.ndarray:
        if ids is not None and self.train_ids is not None:
            assert_disjoint(list(self.train_ids), ids)
        lat = np.asarray(latents, dtype=np.float64)
        if lat.ndim != 3:
            raise ValueError(f"a per-time read-out reads (n, T, d) latents, got shape {lat.shape}")
        spans = time_spans(lat.shape[1], self.time_bins)
        if len(spans) != len(self.probes):
            raise ValueError(f"{lat.shape[1]} frames give {len(spans)} spans; the read-out has {len(self.probes)}")
        parts = [p.predict(lat[:, a:b], chunk_rows=chunk_rows) for (a, b), p in zip(spans, self.probes)]
        return np.concatenate(parts, axis=1)


def _grid_cv(xs, ys, folds, gammas, alphas, *, nystroem: bool, m: int, seed: int, scored=None) -> np.ndarray:
    """Grouped K-fold CV error (mean squared error on standardised targets) per (gamma, alpha).

    Same numbers as ``GridSearchCV(KernelRidge(kernel="rbf") | Nystroem+Ridge, cv=folds,
    scoring="neg_mean_squared_error")``, but one kernel matrix (exact; a Cholesky solve per alpha) or one SVD
    (Nystroem) per (fold, gamma) serves every alpha. Only training sequences are ever touched.
    ``scored``: (x, y, one mask per fold) -- the rows a fold is scored on, when they are not
    the fold's fitted rows (every frame of its sequences).
    """
    scores = np.zeros((len(gammas), len(alphas)))
    counts = 0
    for k, (tr, te) in enumerate(folds):
        counts += 1  # unweighted mean over folds, like GridSearchCV
        x_te, y_te = (xs[te], ys[te]) if scored is None else (scored[0][scored[2][k]], scored[1][scored[2][k]])
        for gi, g in enumerate(gammas):
            if nystroem:
                feat = Nystroem(kernel="rbf", gamma=g, n_components=min(m, len(tr)), random_state=seed).fit(xs[tr])
                ftr, fte = feat.transform(xs[tr]), feat.transform(x_te)
                mu_f, mu_y = ftr.mean(0), ys[tr].mean(0)  # Ridge fits an intercept
                u, sv, vt = np.linalg.svd(ftr - mu_f, full_matrices=False)
                uy = u.T @ (ys[tr] - mu_y)
                for ai, a in enumerate(alphas):
                    coef = vt.T @ ((sv / (sv**2 + a))[:, None] * uy)
                    pred = (fte - mu_f) @ coef + mu_y
                    scores[gi, ai] += ((pred - y_te) ** 2).mean()
            else:
                k_tr = _rbf(xs[tr], xs[tr], g)
                k_te = _rbf(x_te, xs[tr], g)
                eye = np.eye(len(tr))
                for ai, a in enumerate(alphas):
                    try:  # Cholesky per alpha: cheaper than one eigendecomposition for a few alphas
                        coef = scipy.linalg.cho_solve(scipy.linalg.cho_factor(k_tr + a * eye, lower=True), ys[tr])
                    except np.linalg.LinAlgError:
                        coef = np.linalg.lstsq(k_tr + a * eye, ys[tr], rcond=None)[0]
                    pred = k_te @ coef  # KernelRidge: no intercept
                    scores[gi, ai] += ((pred - y_te) ** 2).mean()
    return scores / counts


def _rbf(a: np.ndarray, b: np.ndarray, gamma: float) -> np.ndarray:
    d2 = (a**2).sum(1)[:, None] + (b**2).sum(1)[None, :] - 2.0 * a @ b.T
    return np.exp(-gamma * np.maximum(d2, 0.0))
