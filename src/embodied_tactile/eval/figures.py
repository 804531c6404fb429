"""Figures (PNG, matplotlib Agg): NMSE vs interaction time, 3-D UMAP of last-step latents,
inter-class distance matrices, error vs training wall time.

Read as a paper's reader would: every curve is labelled once, in words (``METHOD_LABELS``,
``MODALITY_LABELS``), in one legend outside the axes; titles are short and the long
definitions (NMSE, splits, data source, scales) go into ``figures/captions.md``
(:func:`write_figures`). NMSE axes are logarithmic (stated on the axis), so the hand-crafted
baseline and the first frames do not squash the curves that matter. Sweeps are drawn in
facets (one panel per modality) rather than one legend entry per run. UMAP panels are
coloured by factor level, one panel per factor; class-distance matrices are ordered by
object group (soft / hard / heterogeneous, the paper's Table 2) and factor levels, groups marked.

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

from ..constants import FACTOR_NAMES, FACTOR_UNITS, get_object  # noqa: E402
from .metrics import overall  # noqa: E402
from .results import POPULATION_GROUP, Results, object_group  # noqa: E402
from .tables import FACTOR_LABELS, pooled_nmse  # noqa: E402

FRAME_RATE_HZ = 30.0  # preprocessed frames per second (docs/reference/architecture.md)
NMSE_AXIS = "held-out NMSE (log scale)"
METHOD_LABELS = {"latent_filter": "Latent Filter", "handcrafted_krr": "Hand-crafted + KRR", "gru": "GRU (supervised)",
                 "mean": "Mean predictor"}
MODALITY_LABELS = {"acc": "ACC", "fsr_t": "FSR$_t$", "fsr_b": "FSR$_b$", "fsr_tb": "FSR$_{tb}$", "multi_e": "MULTI-E",
                   "multi_l": "MULTI-L"}
GROUP_ORDER = ("soft", "hard", "heterogeneous")


def readable(value: str) -> str:
    """A method or modality key as the paper writes it ('multi_l' -> 'MULTI-L'); other
    strings unchanged, '@replicate' kept."""
    base, at, rep = str(value).partition("@")
    return METHOD_LABELS.get(base, MODALITY_LABELS.get(base, base)) + (f" ({rep})" if at else "")


def _legend_below(fig, handles, labels, ncol: int | None = None) -> None:
    """One legend for the whole figure, under the axes, each label once."""
    seen: dict[str, object] = {}
    for h, lab in zip(handles, labels):
        seen.setdefault(lab, h)
    if seen:
        fig.legend(list(seen.values()), list(seen), loc="lower center", ncol=ncol or min(len(seen), 4), fontsize=8,
                   frameon=False)


def log_nmse_axes(axes, values) -> float | None:
    """Logarithmic NMSE axis (shared by ``axes``) with plain decimal tick labels (0.5, 1, 2
    rather than 5x10^-1). A few near-zero values (e.g. one frame of a tiny held-out set)
    would otherwise stretch the axis over ten decades: the axis is clipped one decade
    below the decade of the 5th percentile of the positive values, and the y label says so
    (values below are drawn at the clip). Returns the clip, or None when nothing is cut."""
    from matplotlib.ticker import FuncFormatter

    v = np.asarray([x for x in np.ravel(np.asarray(values, dtype=float)) if np.isfinite(x) and x > 0])
    floor = None
    if v.size:
        cand = 10.0 ** (np.floor(np.log10(np.percentile(v, 5))) - 1)
        if v.min() < cand:
            floor = float(cand)
    for ax in axes:
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(FuncFormatter(lambda y, _: f"{y:g}"))
        ax.yaxis.set_minor_formatter(FuncFormatter(_minor_label(ax)))
        if floor is not None:
            ax.set_ylim(bottom=floor)
    return floor


def _minor_label(ax):
    """Minor tick labels 0.2 / 0.5 / 2 / 5 ... when the axis spans at most two decades, every
    minor tick under one decade (a narrow log axis would otherwise show one labelled tick or none)."""
    def label(y, _):
        lo, hi = ax.get_ylim()
        if y <= 0 or lo <= 0 or hi / lo > 100:
            return ""
        mant = y / 10.0 ** np.floor(np.log10(y) + 1e-9)
        return f"{y:.2g}" if hi / lo <= 10 or round(mant) in (2, 5) else ""  # under a decade: every tick
    return label


def nmse_axis_label(floor: float | None) -> str:
    """The NMSE axis label, naming the clip of :func:`log_nmse_axes` when there is one."""
    return NMSE_AXIS if floor is None else f"held-out NMSE (log scale, clipped at {floor:g})"


# ----------------------------------------------------------------------------- curves

def _save(fig, path: Path, *, tight: bool = True) -> Path:
    """Write a figure as PNG (creating its folder) and release it."""
    if tight:
        fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

def _panels(c: np.ndarray) -> list[np.ndarray]:
    """(T, 4) NMSE over time -> the five panels' curves: each factor, then their mean."""
    c = np.asarray(c, dtype=float)
    with np.errstate(all="ignore"):
        return [c[:, k] for k in range(4)] + [np.nanmean(c, axis=1)]


def nmse_curves_figure(curves: Mapping[str, np.ndarray], *, title: str = "", frame_rate: float = FRAME_RATE_HZ,
                       bands: Mapping[str, np.ndarray] | None = None):
    """curves: label -> (T, 4) NMSE over time -> Figure: one panel per factor + the mean,
    log NMSE axis, one legend below (labels made readable). ``bands``: label -> (n seeds, T, 4),
    each seed's curve; the range over seeds is shaded around the label's line."""
    fig, axes = plt.subplots(1, 5, figsize=(16, 3.9), sharex=True, sharey=True)
    drawn = []
    for label, c in curves.items():
        c = np.asarray(c, dtype=float)
        t = np.arange(c.shape[0]) / frame_rate
        per_seed = [_panels(b[-c.shape[0]:]) for b in (bands or {}).get(label, ())]
        drawn.append((label, t, _panels(c), per_seed))
    floor = log_nmse_axes(axes, [y for _, _, cols, _ in drawn for y in cols])
    for label, t, cols, per_seed in drawn:
        for k, (ax, y) in enumerate(zip(axes, cols)):
            y = np.where(y > 0, y, np.nan)
            line, = ax.plot(t, y if floor is None else np.maximum(y, floor), label=readable(label), lw=1.3)
            if len(per_seed) > 1:
                seeds = np.stack([panels[k] for panels in per_seed])
                with np.errstate(all="ignore"):
                    lo, hi = np.nanmin(seeds, axis=0), np.nanmax(seeds, axis=0)
                if floor is not None:
                    lo, hi = np.maximum(lo, floor), np.maximum(hi, floor)
                ax.fill_between(t, np.where(lo > 0, lo, np.nan), np.where(hi > 0, hi, np.nan),
                                color=line.get_color(), alpha=0.2, lw=0)
    for k, ax in enumerate(axes):
        ax.set_title(FACTOR_LABELS[FACTOR_NAMES[k]] if k < 4 else "Mean over factors", fontsize=9)
        ax.set_xlabel("interaction time (s)")
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel(nmse_axis_label(floor))
    _legend_below(fig, *axes[0].get_legend_handles_labels(), ncol=min(len(curves), 6))
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    return fig


def plot_nmse_curves(curves: Mapping[str, np.ndarray], path, *, title: str = "", frame_rate: float = FRAME_RATE_HZ,
                     bands: Mapping[str, np.ndarray] | None = None) -> Path:
    """:func:`nmse_curves_figure` saved as PNG."""
    return _save(nmse_curves_figure(curves, title=title, frame_rate=frame_rate, bands=bands), Path(path), tight=False)


def _values_in_order(results: Sequence[Results], key: str) -> list:
    """The values of one attribute over ``results``, in the paper's order (modalities ACC,
    FSR_t, FSR_b, FSR_tb, MULTI-E, MULTI-L; methods Latent Filter first), else alphabetical."""
    order = list(MODALITY_LABELS) + list(METHOD_LABELS)
    return sorted({getattr(r, key) for r in results}, key=lambda v: (order.index(v) if v in order else len(order), v))


def curves_by(results: Sequence[Results], key: str) -> dict[str, np.ndarray]:
    """Pool runs by one attribute ('modality', 'skin', 'primitive', 'method') -> label -> (T, 4),
    in :func:`_values_in_order`'s order."""
    return {str(v): pooled_nmse([r for r in results if getattr(r, key) == v], curve=True)
            for v in _values_in_order(results, key)}


def seed_curves_by(results: Sequence[Results], key: str) -> dict[str, np.ndarray]:
    """:func:`curves_by`, seed by seed: label -> (n seeds, T, 4), each seed's runs pooled
    (truncated to the shortest, aligned on the end of the interaction); labels with one seed
    are left out (no spread to draw)."""
    out = {}
    for v in _values_in_order(results, key):
        rs = [r for r in results if getattr(r, key) == v]
        per_seed = [pooled_nmse([r for r in rs if r.seed == s], curve=True) for s in sorted({r.seed for r in rs}, key=str)]
        if len(per_seed) > 1:
            t_min = min(c.shape[0] for c in per_seed)
            out[str(v)] = np.stack([c[-t_min:] for c in per_seed])
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


def physical_factors(r: Results) -> np.ndarray:
    """(n, 4) the held-out trials' factors in physical units (FACTOR_UNITS), whatever target
    encoding the alignment used: figure legends name real levels. From the trials' attributes
    (``Results.factors_physical``) when the evaluation kept them, else from the catalogue by id."""
    if r.factors_physical is not None:
        return np.asarray(r.factors_physical, dtype=float)
    return np.stack([get_object(int(o)).factors() for o in np.asarray(r.object_id)]).astype(float)


def factor_levels(values) -> tuple[np.ndarray, list[str]]:
    """Categorical levels of one factor column -> (level index per row, level labels);
    NaN (unknown) becomes its own level 'unknown'."""
    v = np.asarray(values, dtype=float)
    levels = np.unique(v[np.isfinite(v)])
    idx = np.full(len(v), len(levels), dtype=int)
    for i, lv in enumerate(levels):
        idx[v == lv] = i
    names = [f"{lv:.3g}" for lv in levels] + (["unknown"] if (~np.isfinite(v)).any() else [])
    return idx, names


def umap_figure(latents, colour_by, *, title: str = "", seed: int = 0, n_neighbors: int = 15,
                embedding: np.ndarray | None = None):
    """3-D UMAP of last-step latents -> Figure. ``colour_by``: (n, 4) factors -> one panel per
    factor, points coloured by the factor's level (legend in the factor's unit); (n,) labels
    -> one panel coloured by label. Axes 'UMAP 1..3'."""
    emb = umap_embed(latents, n_neighbors=n_neighbors, seed=seed) if embedding is None else np.asarray(embedding)
    c = np.asarray(colour_by)
    if c.ndim == 2:
        panels = [(FACTOR_LABELS[f] + f" ({u})", c[:, k]) for k, (f, u) in enumerate(zip(FACTOR_NAMES, FACTOR_UNITS))]
    else:
        panels = [("label", c)]
    fig = plt.figure(figsize=(4.2 * len(panels), 4.6))
    for k, (name, vals) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1, projection="3d")
        idx, names = factor_levels(vals)
        cmap = plt.get_cmap("viridis" if len(names) > 2 else "coolwarm", max(len(names), 2))
        for i, lv in enumerate(names):
            m = idx == i
            ax.scatter(emb[m, 0], emb[m, 1], emb[m, 2], s=9, color=cmap(i / max(len(names) - 1, 1)), label=lv,
                       depthshade=False)
        ax.set_xlabel("UMAP 1", fontsize=8, labelpad=-6)
        ax.set_ylabel("UMAP 2", fontsize=8, labelpad=-6)
        ax.set_zlabel("UMAP 3", fontsize=8, labelpad=-6)
        ax.set_xticklabels([])
        ax.set_yticklabels([])
        ax.set_zticklabels([])
        ax.set_title(name, fontsize=9)
        ax.legend(fontsize=7, loc="upper left", title="level", title_fontsize=7, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.02, top=0.86, wspace=0.05)
    return fig


def plot_umap(latents, colour_by, path, *, title: str = "", seed: int = 0, n_neighbors: int = 15) -> Path:
    """:func:`umap_figure` saved as PNG."""
    return _save(umap_figure(latents, colour_by, title=title, seed=seed, n_neighbors=n_neighbors), Path(path), tight=False)


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


def object_order(classes) -> list[int]:
    """Positions of ``classes`` (object ids) ordered by object group (soft, hard,
    heterogeneous: the paper's Table 2) and then by spatial frequency, amplitude, stiffness."""
    def key(i):
        o = int(classes[i])
        if object_group(o) == POPULATION_GROUP:  # outside the catalogue: after it, by id
            return (len(GROUP_ORDER), 0.0, 0.0, 0.0, o)
        return (GROUP_ORDER.index(object_group(o)), *get_object(o).factors()[:3], o)
    return sorted(range(len(classes)), key=key)


def distance_figure(classes, dist, *, title: str = "", normalise: bool = True):
    """Heatmap of a class distance matrix (min-max normalised to [0, 1] like the paper), rows
    and columns in :func:`object_order`, object groups separated by lines and named."""
    from matplotlib.transforms import blended_transform_factory

    order = object_order(classes)
    cls = [int(classes[i]) for i in order]
    d = np.asarray(dist, dtype=float)[np.ix_(order, order)]
    if normalise and np.isfinite(d).any():
        lo, hi = np.nanmin(d), np.nanmax(d)
        d = (d - lo) / (hi - lo) if hi > lo else np.zeros_like(d)
    fig, ax = plt.subplots(figsize=(6.2, 5.6))
    im = ax.imshow(d, cmap="viridis")
    tick_size = 6 if len(cls) > 16 else 8
    ax.set_xticks(range(len(cls)), [str(c) for c in cls], fontsize=tick_size, rotation=90)
    ax.set_yticks(range(len(cls)), [str(c) for c in cls], fontsize=tick_size)
    above = blended_transform_factory(ax.transData, ax.transAxes)
    ax.set_xlabel("object id (ordered by group, then frequency, amplitude, stiffness)", fontsize=8)
    ax.set_ylabel("object id", fontsize=8)
    groups = [object_group(c) for c in cls]
    start = 0
    for i in range(1, len(cls) + 1):
        if i == len(cls) or groups[i] != groups[start]:
            if i < len(cls):
                for line in (ax.axhline, ax.axvline):
                    line(i - 0.5, color="white", lw=1.5)
            ax.text((start + i - 1) / 2, 1.01, groups[start], ha="center", va="bottom", fontsize=8,
                    transform=above)  # just above the matrix, under the title
            start = i
    fig.colorbar(im, ax=ax, shrink=0.8, label="distance" + (" (min-max normalised)" if normalise else ""))
    if title:
        ax.set_title(title, fontsize=9, pad=16)
    fig.tight_layout()
    return fig


def plot_distance_matrix(classes, dist, path, *, title: str = "", normalise: bool = True) -> Path:
    """:func:`distance_figure` saved as PNG."""
    return _save(distance_figure(classes, dist, title=title, normalise=normalise), Path(path), tight=False)


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


def _scene(label: str) -> tuple[str, str]:
    """'modality/skin/primitive[/axis=v...][@rep]' -> (facet 'modality[@rep]', series 'skin, primitive, ...')."""
    base, at, rep = label.partition("@")
    parts = base.split("/")
    return parts[0], ", ".join(parts[1:]) + (f" ({rep})" if at else "")


def error_vs_runtime_figure(histories: Mapping[str, Sequence[Mapping]], *, title: str = "",
                            points: Mapping[str, tuple[float, float]] | None = None):
    """Held-out NMSE vs training time, one panel per modality (facets, not one legend entry
    per run): colour = scene (skin, primitive, other axes), style = method.

    ``histories``: 'modality/skin/primitive...' -> krr_history rows (the Latent Filter's
    training-time checks, a line: the final alignment's row is left out, it reads the last
    check's weights with another read-out); ``points``: 'method/modality/skin/primitive...' ->
    (train_time_s, nmse_overall) (each method's evaluate.py result, a marker)."""
    items = []  # (facet, series, method, kind, x, y)
    for label, rows in histories.items():
        rows = [r for r in rows if not r.get("final")] or list(rows)
        f, se = _scene(label)
        items.append((f, se, "latent_filter", "line", [r["train_wall_time_s"] for r in rows],
                      [r["nmse_overall"] for r in rows]))
    for label, (t, e) in (points or {}).items():
        method, _, rest = label.partition("/")
        f, se = _scene(rest)
        items.append((f, se, method, "point", [t], [e]))
    facets = sorted({it[0] for it in items}, key=lambda f: (list(MODALITY_LABELS).index(f.split("@")[0])
                                                             if f.split("@")[0] in MODALITY_LABELS else 99, f))
    series = sorted({it[1] for it in items})
    methods = [m for m in METHOD_LABELS if any(it[2] == m for it in items)] + sorted(
        {it[2] for it in items} - set(METHOD_LABELS))
    colours = {se: plt.get_cmap("tab10")(i % 10) for i, se in enumerate(series)}
    markers = dict(zip(methods, "o^sDvP*X"))
    ncol = min(len(facets), 3) or 1
    nrow = -(-max(len(facets), 1) // ncol)
    n_labels = len(series) + 1 + len(methods)
    leg_cols = min(n_labels, 3 if ncol == 1 else 4)
    leg_rows = -(-n_labels // leg_cols)
    height = 3.3 * nrow + 0.5 + 0.28 * leg_rows
    fig, axes = plt.subplots(nrow, ncol, figsize=(max(4.3 * ncol, 8.0), height), sharex=True, sharey=True,
                             squeeze=False)
    floor = log_nmse_axes(axes.flat, [v for it in items for v in it[5] if v is not None])
    for ax, f in zip(axes.flat, facets):
        for _, se, method, kind, x, y in (it for it in items if it[0] == f):
            y = [v if v is not None and v > 0 else np.nan for v in y]
            y = y if floor is None else list(np.maximum(y, floor))
            if kind == "line":
                ax.plot(x, y, color=colours[se], lw=1.2, alpha=0.8)
            else:
                ax.scatter(x, y, color=colours[se], marker=markers[method], s=36, edgecolor="black", lw=0.5)
        ax.set_title(readable(f), fontsize=9)
        ax.grid(alpha=0.3, which="both")
    for ax in axes.flat[len(facets):]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("training time (s)")
    for ax in axes[:, 0]:
        ax.set_ylabel(nmse_axis_label(floor))
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=colours[se], lw=4) for se in series]
    labels = list(series)
    handles.append(Line2D([], [], color="grey", lw=1.2))
    labels.append("Latent Filter during training (KRR checks)")
    for m in methods:
        handles.append(Line2D([], [], color="grey", marker=markers[m], ls="", markeredgecolor="black"))
        labels.append(readable(m))
    _legend_below(fig, handles, labels, ncol=leg_cols)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, (0.15 + 0.28 * leg_rows) / height, 1, 1))
    return fig


def plot_error_vs_runtime(histories: Mapping[str, Sequence[Mapping]], path, *, title: str = "",
                          baselines: Mapping[str, tuple[float, float]] | None = None) -> Path:
    """:func:`error_vs_runtime_figure` saved as PNG (``baselines``: its ``points``)."""
    return _save(error_vs_runtime_figure(histories, title=title, points=baselines), Path(path), tight=False)


# ----------------------------------------------------------------------------- captions
def figure_caption(name: str, note: str, *, distance_mode: str = "pairwise") -> str:
    """The caption of one figure file of :func:`~embodied_tactile.eval.report.write_report`
    (by its file name): what is drawn, the scales, and ``note`` (NMSE definition, splits,
    data source: :func:`~embodied_tactile.eval.tables.caption_note`)."""
    stem = Path(name).stem
    if stem.startswith("nmse_time_by_"):
        by = stem[len("nmse_time_by_"):].replace("_", " ")
        what = (f"Held-out NMSE per frame against interaction time (s), by {by}; one panel per factor and their "
                "mean. The NMSE axis is logarithmic: the first frames (before any contact information) and the "
                "hand-crafted baseline would otherwise squash the other curves. When a few near-zero frames would "
                "stretch it over many decades, it is clipped one decade below the 5th percentile of the values "
                "(the axis label gives the clip; values below are drawn at it).")
        if by in ("modality", "skin"):
            what += " Shaded: the range over seeds (each seed's runs pooled), where a label has several."
        if by == "modality":
            what += " Soft skin only when the runs include it (the paper's multi-modality figure)."
        if by == "best worst action":
            what += " Per primitive, the action set with the lowest and the highest whole-trajectory NMSE."
    elif stem.startswith("umap_"):
        what = ("3-D UMAP of the last-step latents of the held-out sequences, one panel per factor, each point "
                "coloured by the level of that factor (legend: the level in the factor's unit). UMAP axes have no unit.")
    elif stem.startswith("distances_"):
        what = (f"Inter-class distance matrix of the last-step latents ({distance_mode}: "
                + ("mean Euclidean distance between members of two objects; diagonal = mean within-object distance"
                   if distance_mode == "pairwise" else "Euclidean distance between object means")
                + "), min-max normalised. Objects ordered by group (soft, hard, heterogeneous: the paper's Table 2 "
                  "groups, separated by white lines), then spatial frequency, amplitude and stiffness.")
    elif stem == "error_vs_runtime":
        what = ("Held-out NMSE (mean over factors, log scale) against training time (s); one panel per modality. "
                "Lines: the Latent Filter's KRR checks during training; markers: each method's final evaluation. "
                "Colour: skin and primitive (and any other axis that differs between runs).")
    else:
        what = stem.replace("_", " ")
    return f"{what} {note}".strip()


def write_captions(paths: Sequence[str | os.PathLike], note: str, out, *, distance_mode: str = "pairwise") -> Path:
    """``captions.md``: one '**file**: caption' paragraph per figure."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    text = "# Figure captions\n\n" + "".join(
        f"**{Path(p).name}**: {figure_caption(Path(p).name, note, distance_mode=distance_mode)}\n\n" for p in paths)
    out.write_text(text)
    return out
