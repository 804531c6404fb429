"""Figures (PNG, matplotlib Agg): NMSE vs interaction time, 3-D UMAP of last-step latents,
inter-class distance matrices, error vs training wall time.

Class distances use ``scipy.spatial.distance.cdist`` between the members of two classes
(mean pairwise distance; the diagonal is the mean intra-class distance over distinct pairs)
or between class means (``mode="centroid"``) -- never between a stacked pair of classes,
which mixes intra-class pairs into an "inter-class" number.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial.distance import cdist  # noqa: E402

from ..constants import FACTOR_NAMES  # noqa: E402
from .metrics import overall  # noqa: E402
from .results import Results  # noqa: E402
from .tables import FACTOR_LABELS, pooled_nmse  # noqa: E402

FRAME_RATE_HZ = 30.0  # preprocessed frames per second (docs/architecture.md)


# ----------------------------------------------------------------------------- curves

def _save(fig, path: Path, *, tight: bool = True) -> Path:
    """Write a figure as PNG (creating its folder) and release it."""
    if tight:
        fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

def plot_nmse_curves(curves: Mapping[str, np.ndarray], path, *, title: str = "", frame_rate: float = FRAME_RATE_HZ,
                     note: str = "") -> Path:
    """curves: label -> (T, 4) NMSE over time. One panel per factor + one for the mean."""
    path = Path(path)
    fig, axes = plt.subplots(1, 5, figsize=(18, 3.4), sharex=True)
    for label, c in curves.items():
        c = np.asarray(c, dtype=float)
        t = np.arange(c.shape[0]) / frame_rate
        for k in range(4):
            axes[k].plot(t, c[:, k], label=label, lw=1.2)
        with np.errstate(all="ignore"):
            axes[4].plot(t, np.nanmean(c, axis=1), label=label, lw=1.2)
    for k, ax in enumerate(axes):
        ax.set_title(FACTOR_LABELS[FACTOR_NAMES[k]] if k < 4 else "Overall (mean)")
        ax.set_xlabel("interaction time (s)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("NMSE (held-out)")
    axes[-1].legend(fontsize=7, loc="upper right")
    fig.suptitle(title + (f"\n{note}" if note else ""), fontsize=8)
    return _save(fig, path)


def curves_by(results: Sequence[Results], key: str) -> dict[str, np.ndarray]:
    """Pool runs by one attribute ('modality', 'skin', 'primitive', 'method') -> label -> (T, 4)."""
    out = {}
    for v in sorted({getattr(r, key) for r in results}):
        out[str(v)] = pooled_nmse([r for r in results if getattr(r, key) == v], curve=True)
    return out


def best_worst_action_curves(results: Sequence[Results]) -> dict[str, np.ndarray]:
    """Per primitive, the NMSE-vs-time curves of the best and worst action index (by the
    whole-trajectory overall NMSE)."""
    out = {}
    for p in sorted({r.primitive for r in results}):
        rs = [r for r in results if r.primitive == p]
        idx = sorted({int(a) for r in rs for a in r.action_index})
        scores = {a: overall(pooled_nmse(rs, lambda r, a=a: r.action_index == a)) for a in idx}
        scores = {a: s for a, s in scores.items() if np.isfinite(s)}
        if not scores:
            continue
        best, worst = min(scores, key=scores.get), max(scores, key=scores.get)
        out[f"{p} best (action {best + 1})"] = pooled_nmse(rs, lambda r: r.action_index == best, curve=True)
        if worst != best:
            out[f"{p} worst (action {worst + 1})"] = pooled_nmse(rs, lambda r: r.action_index == worst, curve=True)
    return out


# ----------------------------------------------------------------------------- latent space
def umap_embed(latents, *, n_components: int = 3, n_neighbors: int = 15, seed: int = 0) -> np.ndarray:
    """UMAP of (n, d) latents; tiny n lowers n_neighbors (>= 2) and falls back to PCA for n < 5."""
    x = np.asarray(latents, dtype=np.float64)
    n = len(x)
    if n < 5:
        xc = x - x.mean(0)
        u, s, _ = np.linalg.svd(xc, full_matrices=False)
        e = u * s
        return np.pad(e, ((0, 0), (0, max(0, n_components - e.shape[1]))))[:, :n_components]
    os.environ.setdefault("NUMBA_CACHE_DIR", str(Path.home() / ".cache" / "numba"))
    import umap

    nn = max(2, min(int(n_neighbors), n - 1))
    reducer = umap.UMAP(n_components=n_components, n_neighbors=nn, random_state=seed,
                        init="random" if n < n_components + 2 else "spectral")
    return reducer.fit_transform(x)


def plot_umap(latents, labels, path, *, title: str = "", seed: int = 0, n_neighbors: int = 15) -> Path:
    """3-D UMAP scatter of last-step latents colored by label (object id)."""
    path = Path(path)
    emb = umap_embed(latents, n_neighbors=n_neighbors, seed=seed)
    labels = np.asarray(labels)
    fig = plt.figure(figsize=(5.5, 5))
    ax = fig.add_subplot(111, projection="3d")
    sc = ax.scatter(emb[:, 0], emb[:, 1], emb[:, 2], c=labels, cmap="nipy_spectral", s=10)
    fig.colorbar(sc, ax=ax, shrink=0.6, label="object id")
    ax.set_title(title, fontsize=8)
    return _save(fig, path, tight=False)


def class_distances(latents, labels, *, mode: str = "pairwise") -> tuple[np.ndarray, np.ndarray]:
    """Inter-class Euclidean distance matrix -> (classes, D (K, K)).

    ``pairwise``: D[a, b] = mean of cdist(X_a, X_b); diagonal = mean distance over distinct
    pairs inside the class (NaN for a singleton). ``centroid``: cdist between class means.
    """
    x = np.asarray(latents, dtype=np.float64)
    labels = np.asarray(labels)
    classes = np.unique(labels)
    groups = [x[labels == c] for c in classes]
    if mode == "centroid":
        return classes, cdist(np.stack([g.mean(0) for g in groups]), np.stack([g.mean(0) for g in groups]))
    if mode != "pairwise":
        raise ValueError(f"mode must be 'pairwise' or 'centroid', got {mode!r}")
    k = len(classes)
    d = np.full((k, k), np.nan)
    for i in range(k):
        for j in range(i, k):
            m = cdist(groups[i], groups[j])
            if i == j:
                n = len(groups[i])
                d[i, i] = m.sum() / (n * (n - 1)) if n > 1 else np.nan
            else:
                d[i, j] = d[j, i] = m.mean()
    return classes, d


def plot_distance_matrix(classes, dist, path, *, title: str = "", normalise: bool = True) -> Path:
    """Heatmap of a class distance matrix (min-max normalised to [0, 1] like the paper)."""
    path = Path(path)
    d = np.asarray(dist, dtype=float)
    if normalise and np.isfinite(d).any():
        lo, hi = np.nanmin(d), np.nanmax(d)
        d = (d - lo) / (hi - lo) if hi > lo else np.zeros_like(d)
    fig, ax = plt.subplots(figsize=(5, 4.4))
    im = ax.imshow(d, cmap="viridis")
    ax.set_xticks(range(len(classes)), [str(c) for c in classes], fontsize=5, rotation=90)
    ax.set_yticks(range(len(classes)), [str(c) for c in classes], fontsize=5)
    fig.colorbar(im, ax=ax, label="distance" + (" (min-max)" if normalise else ""))
    ax.set_title(title, fontsize=8)
    return _save(fig, path)


# ----------------------------------------------------------------------------- error vs run time
def read_history(path) -> list[dict]:
    """Rows of a krr_history.jsonl written by :class:`KRRAlignmentCallback`."""
    rows = []
    with open(path) as fh:
        for line in fh:
            line = line.strip()
            if line:
                rows.append(json.loads(line))
    return rows


def plot_error_vs_runtime(histories: Mapping[str, Sequence[Mapping]], path, *, title: str = "",
                          baselines: Mapping[str, tuple[float, float]] | None = None) -> Path:
    """NMSE (overall, held-out) vs training wall time, one line per run; ``baselines``:
    label -> (train_time_s, nmse_overall) drawn as markers."""
    path = Path(path)
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for label, rows in histories.items():
        t = [r["train_wall_time_s"] for r in rows]
        e = [r["nmse_overall"] for r in rows]
        ax.plot(t, e, marker="o", ms=3, label=label)
    for label, (t, e) in (baselines or {}).items():
        ax.scatter([t], [e], marker="x", label=label)
    ax.set_xlabel("training wall time (s, excluding evaluation)")
    ax.set_ylabel("held-out NMSE (mean over factors)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(title, fontsize=8)
    return _save(fig, path)
