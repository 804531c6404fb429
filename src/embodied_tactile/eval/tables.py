"""Tables from :class:`~embodied_tactile.eval.results.Results`: the paper's Table 1 / Table 2
analogues, a per-run summary and a runtime table, with Markdown / CSV / LaTeX writers.

All numbers come from :func:`~embodied_tactile.eval.metrics.nmse` (through
:func:`pooled_nmse` on ONE run, with that run's reference variance). Runs are grouped by
every configuration axis that differs between them (:attr:`Results.cell`: method, modality,
skin, primitive and any other swept key); a table never averages across any of those, only
over the seeds (replicates) of one cell, with the study protocol's statistics
(:func:`seed_stats`: mean, std, 95 % t interval for n >= 3). Every table carries the NMSE
definition, the split sizes, the data source and what each number averages over in its
caption. A cell that was not measured prints ``–`` (explained in the caption), never ``nan``.
"""

from __future__ import annotations

import csv
import io
import math
import warnings
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..constants import ACTION_PARAM_NAMES, ACTIONS, FACTOR_NAMES, N_ACTIONS, OBJECT_GROUPS, PRIMITIVES, SKINS
from .metrics import NMSE_DEFINITION, NMSEUndefinedWarning, nmse, overall
from .results import SPLIT_KINDS, Results
from .targets import TARGET_ENCODINGS, describe_targets

FACTOR_LABELS = {"spatial_frequency": "Spatial Freq.", "amplitude": "Amplitude", "stiffness": "Stiffness",
                 "heterogeneity": "Heterogeneity"}
GROUPS = OBJECT_GROUPS
MISSING = "\u2013"  # en dash: a cell that was not measured
MISSING_NOTE = f"{MISSING} = not measured in these runs."
PARAM_LATEX = {"A_z_mm": r"$A_{z}$\,(mm)", "omega_z_hz": r"$\omega_z$\,(Hz)",
               "A_alpha_beta_deg": r"$A_{\alpha,\beta}\,(^{\circ})$", "omega_alpha_beta_hz": r"$\omega_{\alpha,\beta}$\,(Hz)",
               "A_xy_mm": r"$A_{x,y}$\,(mm)", "A_gamma_deg": r"$A_\gamma(^{\circ})$",
               "omega_xy_gamma_hz": r"$\omega_{x,y,\gamma}$\,(Hz)"}


@dataclass
class Table:
    name: str
    caption: str
    columns: list[str]
    rows: list[list] = field(default_factory=list)
    latex_body: str | None = None  # paper-layout tabular; generic booktabs when None

    @property
    def full_caption(self) -> str:
        """The caption, plus what ``–`` means when a cell was not measured."""
        missing = any(_missing(v) for r in self.rows for v in r)
        return self.caption + (f" {MISSING_NOTE}" if missing and MISSING_NOTE not in self.caption else "")

    def to_markdown(self) -> str:
        out = [f"**{self.name}.** {self.full_caption}", "", "| " + " | ".join(self.columns) + " |",
               "|" + "|".join("---" for _ in self.columns) + "|"]
        out += ["| " + " | ".join(fmt_cell(v) for v in r) + " |" for r in self.rows]
        return "\n".join(out) + "\n"

    def to_csv(self) -> str:
        buf = io.StringIO()
        cap = self.full_caption.replace(MISSING_NOTE, f"{MISSING_NOTE[:-1]} (an empty cell here).")
        buf.write(f"# {self.name}: {cap}\n")
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(self.columns)
        for r in self.rows:
            w.writerow([fmt_cell(v, csv_=True) for v in r])
        return buf.getvalue()

    def to_latex(self) -> str:
        body = self.latex_body
        if body is None:
            spec = "l" + "c" * (len(self.columns) - 1)
            lines = [rf"\begin{{tabular}}{{{spec}}}", r"\toprule", " & ".join(_tex(c) for c in self.columns) + r" \\",
                     r"\midrule"]
            lines += [" & ".join(_tex(fmt_cell(v)) for v in r) + r" \\" for r in self.rows]
            lines += [r"\bottomrule", r"\end{tabular}"]
            body = "\n".join(lines)
        return ("\\begin{table*}[!tbh]\n\\centering\n\\resizebox{\\textwidth}{!}{%\n" + body + "%\n}\n"
                f"\\caption{{{_tex(self.full_caption)}}}\n\\label{{tab:{self.name}}}\n\\end{{table*}}\n")

    def to_json(self) -> dict:
        return {"name": self.name, "caption": self.full_caption, "columns": self.columns,
                "rows": [[_num(v) for v in r] for r in self.rows]}


# ----------------------------------------------------------------------------- pooling
def pooled_nmse(results: Sequence[Results], select: Callable[[Results], np.ndarray] | None = None,
                *, curve: bool = False) -> np.ndarray:
    """NMSE per factor over the selected sequences of several runs, each normalised by its
    own run's reference variance: sum (y - yhat)^2 / var_ref_run, over all (run, sequence,
    frame), divided by the number of terms. For one run this is exactly
    ``nmse(..., var_ref=run.var_ref)``. ``curve=True`` -> (T, 4) (runs truncated to min T)."""
    rs = [r for r in results if r.n_test]
    if not rs:
        return np.full((1, 4) if curve else 4, np.nan)
    t_min = min(r.pred.shape[1] for r in rs)
    ys, ps = [], []
    for r in rs:
        m = np.ones(r.n_test, bool) if select is None else np.asarray(select(r), bool)
        if not m.any():
            continue
        sd = np.sqrt(r.var_ref)
        ys.append(r.factors[m] / sd)
        ps.append(r.pred[m][:, -t_min:] / sd)  # align on the end of the interaction
    if not ys:
        return np.full((t_min, 4) if curve else 4, np.nan)
    y = np.concatenate(ys)[:, None, :]
    p = np.concatenate(ps)
    axis = 0 if curve else (0, 1)
    return nmse(y, p, axis=axis, var_ref=np.ones(4))


def split_sizes(results: Sequence[Results]) -> dict:
    return {r.label: {"n_train": int(r.n_train), "n_test": r.n_test} for r in results}


def caption_note(results: Sequence[Results]) -> str:
    """NMSE definition + split sizes + data source, for every caption."""
    sizes = sorted({(int(r.n_train), r.n_test) for r in results})
    srcs = sorted({r.source for r in results})
    sz = "; ".join(f"{a} train / {b} held-out sequences" for a, b in sizes) if sizes else "none"
    n_runs = len({(r.cell[1:], r.seed, r.replicate) for r in results})
    val = any(r.params.get("held_out") == "val" for r in results)
    return (f"{NMSE_DEFINITION} Splits ({n_runs} run(s)): {sz}. {split_note(results)} "
            + ("Scored on the validation side (for choosing settings), not the test side. " if val else "")
            + f"Data source: {', '.join(srcs) or 'unknown'}. "
            + " ".join(describe_targets(t) if t in TARGET_ENCODINGS else f"Targets: {t}."
                       for t in sorted({r.targets for r in results})))


def split_note(results: Sequence[Results]) -> str:
    """The split kind(s) of the runs and whether their held-out objects were unseen in training."""
    parts = []
    for kind in sorted({r.split for r in results}):
        rs = [r for r in results if r.split == kind]
        flags = {r.unseen_objects for r in rs}
        seen = ("held-out objects never in training (checked from split.json)" if flags == {True}
                else "held-out objects also in training" if flags == {False}
                else "no split.json check" if flags == {None}
                else "unseen-object check: " + ", ".join(sorted({str(f) for f in flags})))
        parts.append(f"{kind} ({SPLIT_KINDS.get(kind, 'not recorded')}; {seen})")
    return "Split kind: " + ("; ".join(parts) or "none") + "."


def _filter(results, method=None, modality=None, skin=None, primitive=None):
    return [r for r in results if (method is None or r.method == method) and (modality is None or r.modality == modality)
            and (skin is None or r.skin == skin) and (primitive is None or r.primitive == primitive)]


# ----------------------------------------------------------------------------- seeds -> statistics
def seed_stats(values) -> dict:
    """The study protocol's per-cell statistics over seeds (one value per run): n, mean, std
    (ddof 1) and the 95 % t interval (n >= 3 only; NaN below). NaN values are not counted."""
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    n = int(v.size)
    mean = float(v.mean()) if n else float("nan")
    std = float(v.std(ddof=1)) if n >= 2 else float("nan")
    lo = hi = float("nan")
    if n >= 3:
        from scipy.stats import t as student_t

        h = float(student_t.ppf(0.975, n - 1)) * std / math.sqrt(n)
        lo, hi = mean - h, mean + h
    return {"n": n, "mean": mean, "std": std, "ci95_low": lo, "ci95_high": hi}


def cells(results: Sequence[Results]) -> dict[tuple, list[Results]]:
    """Results grouped by :attr:`Results.cell` (every axis but the seed), in a stable order
    (method as given, then modality, skin, primitive in the constants' order, then axes)."""
    methods = list(dict.fromkeys(r.method for r in results))
    out: dict[tuple, list[Results]] = {}
    for r in sorted(results, key=lambda r: (methods.index(r.method), r.modality, _order(SKINS, r.skin),
                                            _order(PRIMITIVES, r.primitive), r.cell[4])):
        out.setdefault(r.cell, []).append(r)
    return out


GROUP_NORMS = {
    "total": "each factor's squared error divided by the variance of that factor over ALL held-out sequences "
             "of the run (MSE / total variance, the paper's Table 2 convention: a group in which a factor is "
             "constant still has a value, and a minority group such as the heterogeneous objects can exceed 1)",
    "group": "each factor's squared error divided by the variance of that factor over the group's OWN held-out "
             "sequences (NMSE within the group; undefined, printed as \u2013, where the factor is constant in "
             "the group: heterogeneity in every group, stiffness among the heterogeneous objects)",
}


def cell_mean(runs: Sequence[Results], select: Callable[[Results], np.ndarray] | None = None,
              *, norm: str = "total") -> tuple[np.ndarray, int]:
    """Per-factor NMSE of each run (its own sequences, optionally masked), averaged over the
    runs (= seeds of one cell) -> (mean (4,), number of runs that had sequences).
    ``norm``: 'total' (the run's reference variance) or 'group' (the masked sequences' own
    variance), see :data:`GROUP_NORMS`."""
    if norm not in GROUP_NORMS:
        raise ValueError(f"norm must be one of {sorted(GROUP_NORMS)}, got {norm!r}")
    vals = []
    for r in runs:
        m = np.ones(r.n_test, bool) if select is None else np.asarray(select(r), bool)
        if r.n_test and m.any():
            if norm == "group":
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", NMSEUndefinedWarning)
                    vals.append(r.group_nmse(m))
            else:
                vals.append(pooled_nmse([r], select))
    if not vals:
        return np.full(4, np.nan), 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(np.asarray(vals), axis=0), len(vals)


def _order(seq, v) -> tuple:
    return (seq.index(v), "") if v in seq else (len(seq), str(v))


def _blocks(rs: Sequence[Results]) -> dict[tuple, list[Results]]:
    """Cells without the primitive: (method, modality, skin, axes) -> runs (every primitive)."""
    out: dict[tuple, list[Results]] = {}
    for key, runs in cells(rs).items():
        out.setdefault((key[0], key[1], key[2], key[4]), []).extend(runs)
    return out


def _block_columns(blocks) -> tuple[list[str], Callable[[tuple], list]]:
    """Leading columns naming a block: Method (only when several), Modality, Skin, other axes."""
    methods = {k[0] for k in blocks}
    axes = sorted({a for k in blocks for a, _ in k[3]})
    cols = (["Method"] if len(methods) > 1 else []) + ["Modality", "Skin"] + axes

    def values(k):
        ax = dict(k[3])
        return ([k[0]] if len(methods) > 1 else []) + [k[1], k[2]] + [ax.get(a, MISSING) for a in axes]

    return cols, values


def _seeds_note(rs: Sequence[Results]) -> str:
    ns = sorted({len(v) for v in cells(rs).values()})
    n = ", ".join(str(x) for x in ns) or "0"
    return (f"Each number is the mean over the seeds of one configuration (n = {n} per cell; "
            "table_aggregate gives std and 95 % intervals); configurations (method, modality, skin, "
            "primitive and any other swept setting) are never averaged together.")


def _block_title(key, values_of) -> str:
    return " / ".join(str(v) for v in values_of(key))


# ----------------------------------------------------------------------------- Table 1
def table_actions(results: Sequence[Results], *, method: str | None = "latent_filter", modality: str | None = None,
                  skin: str | None = None) -> Table:
    """Table 1 analogue: per action index (1..16) and primitive, the action parameters and
    the whole-trajectory NMSE (mean over factors), printed in units of 1e-2 like the paper.
    One block of rows per (modality, skin, other axes); an action no run of a block measured
    is left out, a cell measured for another primitive only prints ``–``."""
    rs = _filter(results, method, modality, skin)
    prims = [p for p in PRIMITIVES if any(r.primitive == p for r in rs)] or list(PRIMITIVES)
    blocks = _blocks(rs)
    bcols, bvals = _block_columns(blocks)
    columns = bcols + ["Action Index"]
    for p in prims:
        columns += [f"{p}:{k}" for k in ACTION_PARAM_NAMES[p]] + [f"{p}:NMSE_1e-2"]
    rows, block_rows = [], {}
    for key, runs in blocks.items():
        block_rows[key] = []
        for a in range(N_ACTIONS):
            row: list = bvals(key) + [a + 1]
            measured = False
            for p in prims:
                row += [ACTIONS[p][a].params[k] for k in ACTION_PARAM_NAMES[p]]
                v, n = cell_mean(_filter(runs, primitive=p), lambda r, a=a: r.action_index == a)
                measured |= n > 0
                row.append(100.0 * overall(v) if n else float("nan"))
            if measured:
                rows.append(row)
                block_rows[key].append(row)
    # paper layout
    nb = len(bcols)
    spec = "c " + " ".join("c" * (len(ACTION_PARAM_NAMES[p]) + 1) for p in prims)
    width = 1 + sum(len(ACTION_PARAM_NAMES[p]) + 1 for p in prims)
    head1 = [r"\multirow{2}{*}{Action Index}"]
    cmid, col = [], 2
    for p in prims:
        w = len(ACTION_PARAM_NAMES[p]) + 1
        head1.append(rf"\multicolumn{{{w}}}{{c}}{{{p.capitalize()}}}")
        cmid.append(rf"\cmidrule(lr){{{col}-{col + w - 1}}}")
        col += w
    head2 = [""]
    for p in prims:
        head2 += [PARAM_LATEX[k] for k in ACTION_PARAM_NAMES[p]] + [r"NMSE $10^{-2}$"]
    lines = [rf"\begin{{tabular}}{{{spec}}}", r"\toprule", " & ".join(head1) + r" \\", " ".join(cmid),
             " & ".join(head2) + r" \\", r"\midrule"]
    for bi, (key, brows) in enumerate(block_rows.items()):
        if len(block_rows) > 1:
            if bi:
                lines.append(r"\midrule")
            lines.append(rf"\multicolumn{{{width}}}{{l}}{{\textit{{{_tex(_block_title(key, bvals))}}}}} \\")
        for row in brows:
            cells_, i = [str(row[nb])], nb + 1
            for p in prims:
                k = len(ACTION_PARAM_NAMES[p])
                col_vals = [r[i + k] for r in brows]
                cells_ += [f"{v:.1f}" for v in row[i : i + k]] + [_cell(row[i + k], col_vals, "orange", 3)]
                i += k + 1
            lines.append(" & ".join(cells_) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    what = ", ".join(x for x in (method, modality, skin) if x) or "all runs"
    cap = (f"NMSE over the whole interaction trajectory (mean over the four factors, x1e-2) per action "
           f"parameter set ({what}), one block per {', '.join(bcols).lower()}; lower is better. "
           f"Action sets no run of a block used are left out. {_seeds_note(rs)} " + caption_note(rs))
    return Table("action_config", cap, columns, rows, "\n".join(lines))


# ----------------------------------------------------------------------------- Table 2
def table_groups(results: Sequence[Results], *, method: str | None = "latent_filter", modality: str | None = None,
                 norm: str = "total") -> Table:
    """Table 2 analogue: NMSE per factor x object group x primitive, one block (factor rows +
    Overall) per modality x skin (x other swept axes), as the paper writes it per modality.
    ``norm='total'`` (table ``environmentshape``, comparable with the paper's Table 2) divides by
    the factor's variance over all held-out sequences of the run; ``norm='group'`` (table
    ``environmentshape_groupvar``) by the group's own variance (:data:`GROUP_NORMS`)."""
    rs = _filter(results, method, modality)
    prims = [p for p in PRIMITIVES if any(r.primitive == p for r in rs)] or list(PRIMITIVES)
    blocks = _blocks(rs)
    bcols, bvals = _block_columns(blocks)
    columns = bcols + ["Factor"] + [f"{g}:{p}" for g in GROUPS for p in prims]
    rows = []
    for key, runs in blocks.items():
        vals = np.full((len(GROUPS) * len(prims), 4), np.nan)
        for gi, g in enumerate(GROUPS):
            for pi, p in enumerate(prims):
                vals[gi * len(prims) + pi] = cell_mean(_filter(runs, primitive=p), lambda r, g=g: r.group == g,
                                                       norm=norm)[0]
        for k, f in enumerate(FACTOR_NAMES):
            rows.append([*bvals(key), f, *vals[:, k]])
        rows.append([*bvals(key), "Overall", *[overall(v) for v in vals]])
    nb = len(bcols)
    ng = len(prims)
    spec = "c c " + " ".join("c" * ng for _ in GROUPS)
    lines = [rf"\begin{{tabular}}{{{spec}}}", r"\toprule",
             " & & " + " & ".join(rf"\multicolumn{{{ng}}}{{c}}{{{g.capitalize()} Objects}}" for g in GROUPS) + r" \\",
             " ".join(rf"\cmidrule(lr){{{3 + i * ng}-{2 + (i + 1) * ng}}}" for i in range(len(GROUPS))),
             " & & " + " & ".join(p.capitalize() for _ in GROUPS for p in prims) + r" \\", r"\midrule"]
    allv = [v for rr in rows for v in rr[nb + 1:]]
    hues = [h for h in ("red", "green", "blue") for _ in prims]
    keys = list(blocks)
    for bi, key in enumerate(keys):
        block = [r for r in rows if r[:nb] == bvals(key)]
        title = _tex(_block_title(key, bvals)).replace(" / ", ", ")
        for j, r in enumerate(block):
            first = rf"\multirow{{{len(block)}}}{{*}}{{\rotatebox{{90}}{{{title}}}}}" if j == 0 else ""
            if r[nb] == "Overall":
                lines.append(rf"\cmidrule(lr){{2-{2 + len(GROUPS) * ng}}}")
            label = FACTOR_LABELS.get(r[nb], r[nb])
            lines.append(" & ".join([first, label] + [_cell(v, allv, h, 3) for v, h in zip(r[nb + 1:], hues)]) + r" \\")
        if bi < len(keys) - 1:
            lines.append(r"\midrule")
    lines += [r"\bottomrule", r"\end{tabular}"]
    what = ", ".join(x for x in (method, modality) if x) or "all runs"
    cap = (f"NMSE over the entire interaction sequence per factor, object group (soft / hard / heterogeneous) "
           f"and primitive, one block per {', '.join(bcols).lower()} ({what}); Overall = mean over the four "
           f"factors; lower is better. Normalisation: {GROUP_NORMS[norm]}. {_seeds_note(rs)} " + caption_note(rs))
    return Table("environmentshape" if norm == "total" else "environmentshape_groupvar", cap, columns, rows,
                 "\n".join(lines))


def table_heterogeneity(results: Sequence[Results]) -> Table:
    """Heterogeneity as a binary decision, one row per run and method: class counts, balanced
    accuracy (prediction >= 0.5) and ROC-AUC of the continuous prediction, last frame and whole
    trajectory (:meth:`Results.heterogeneity_scores`)."""
    axes = _axis_columns(results)
    keys = ["balanced_accuracy_last", "roc_auc_last", "balanced_accuracy_trajectory", "roc_auc_trajectory"]
    columns = ["method", "modality", "skin", "primitive", *axes, "seed", "n_pos", "n_neg", *keys]
    rows = []
    for r in results:
        h = r.heterogeneity_scores()
        rows.append([r.method, r.modality, r.skin, r.primitive, *[r.axes.get(a, MISSING) for a in axes],
                     MISSING if r.seed is None else r.seed, h["n_pos"], h["n_neg"], *[h[k] for k in keys]])
    cap = ("Heterogeneity (0/1) read as a decision from the continuous predicted value: balanced accuracy = mean "
           "of the true-positive and true-negative rates of prediction >= 0.5; ROC-AUC = probability that a "
           "heterogeneous sequence scores above a homogeneous one (ties count 1/2), 0.5 = chance. 'last': last "
           "frame of each held-out sequence; 'trajectory': every frame of every held-out sequence a sample. "
           f"n_pos / n_neg: held-out heterogeneous / homogeneous sequences ({MISSING} where a class is absent). "
           "One row per run (no averaging). " + caption_note(results))
    return Table("heterogeneity", cap, columns, rows)


# ----------------------------------------------------------------------------- summary / runtime
def _axis_columns(results: Sequence[Results]) -> list[str]:
    return sorted({a for r in results for a in r.axes})


def table_summary(results: Sequence[Results]) -> Table:
    """One row per run/method: whole-trajectory and last-step NMSE per factor + overall."""
    axes = _axis_columns(results)
    columns = ["method", "modality", "skin", "primitive", *axes, "seed", "n_train", "n_test",
               *[f"traj:{f}" for f in FACTOR_NAMES], "traj:overall", *[f"last:{f}" for f in FACTOR_NAMES], "last:overall"]
    rows = []
    for r in results:
        traj, last = r.subset_nmse(), r.curve()[-1]
        rows.append([r.method, r.modality, r.skin, r.primitive, *[r.axes.get(a, MISSING) for a in axes],
                     MISSING if r.seed is None else r.seed, r.n_train, r.n_test, *traj, overall(traj), *last, overall(last)])
    cap = "Whole-trajectory (traj) and last-frame (last) NMSE per factor, one row per run (no averaging). " + caption_note(results)
    return Table("summary", cap, columns, rows)


def table_aggregate(results: Sequence[Results]) -> Table:
    """One row per configuration (every axis but the seed): the study protocol's statistics
    over its seeds (n, mean, std, 95 % t interval for n >= 3) of the whole-trajectory and
    last-frame overall NMSE, and the mean per factor."""
    axes = _axis_columns(results)
    columns = ["method", "modality", "skin", "primitive", *axes, "n_seeds", "seeds", "traj:overall mean",
               "traj:overall std", "traj:overall 95% CI", "last:overall mean", "last:overall 95% CI",
               *[f"traj:{f} mean" for f in FACTOR_NAMES]]
    rows = []
    for key, runs in cells(results).items():
        traj = np.array([r.subset_nmse() for r in runs])
        t_all = seed_stats([overall(v) for v in traj])
        l_all = seed_stats([overall(r.curve()[-1]) for r in runs])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            per_factor = np.nanmean(traj, axis=0)
        seeds = ",".join(MISSING if r.seed is None else str(r.seed) for r in runs)
        ax = dict(key[4])
        rows.append([*key[:4], *[ax.get(a, MISSING) for a in axes], t_all["n"], seeds, t_all["mean"], t_all["std"],
                     _interval(t_all), l_all["mean"], _interval(l_all), *per_factor])
    cap = ("Per configuration, statistics over its seeds only (one value per run): mean, std and the 95 % "
           f"t interval (Student t, n-1 degrees of freedom; {MISSING} for n < 3, std {MISSING} for n < 2). "
           + caption_note(results))
    return Table("aggregate", cap, columns, rows)


def _interval(st: dict) -> str:
    if not (math.isfinite(st["ci95_low"]) and math.isfinite(st["ci95_high"])):
        return MISSING
    return f"[{fmt_cell(st['ci95_low'])}, {fmt_cell(st['ci95_high'])}]"


RUNTIME_DEFINITION = (
    "Training time: wall time of fitting the method on the run's prepared training data, excluding data "
    "preparation (simulation, preprocessing, cache) and evaluation (the Latent Filter: training with its "
    "periodic KRR checks subtracted, from the run's final krr_history.jsonl row; baselines: their fit in "
    "evaluate.py). NMSE: evaluate.py's held-out whole-trajectory NMSE (mean over factors) for every method. "
    "Data preparation of the Latent Filter run (train.py, before fitting) is reported apart.")


def runtime_points(results: Sequence[Results]) -> list[dict]:
    """The one source of the runtime table AND the error-vs-run-time figure's markers: per
    run and method, the held-out overall NMSE (evaluate.py) and the training time on one time
    base (:data:`RUNTIME_DEFINITION`). Keys: label, method, modality, skin, primitive, seed,
    nmse_overall, train_time_s, data_prepare_s, inference_s_per_trial."""
    out = []
    for r in results:
        p = r.params
        inf = float(p.get("inference_s_per_sequence", 0.0)) + float(p.get("krr_predict_s_per_sequence", 0.0))
        prep = p.get("data_prepare_s")
        out.append({"label": r.label, "method": r.method, "modality": r.modality, "skin": r.skin,
                    "primitive": r.primitive, "axes": dict(r.axes), "seed": r.seed,
                    "nmse_overall": overall(r.subset_nmse()),
                    "train_time_s": float(p["train_time_s"]) if p.get("train_time_s") is not None else float("nan"),
                    "data_prepare_s": float(prep) if prep is not None else float("nan"),
                    "inference_s_per_trial": inf})
    return out


def table_runtime(results: Sequence[Results]) -> Table:
    """NMSE, training time, data preparation time and inference time per trial, per run and
    method, from :func:`runtime_points` (the error-vs-run-time figure plots the same points).

    Training time: ``params['train_time_s']`` (Latent Filter: the last ``train_wall_time_s``
    of krr_history.jsonl; baselines: their own fit). Data preparation: ``params['data_prepare_s']``
    (the run's train.py; baselines reuse the prepared data). Inference: ``params['inference_s_per_sequence']``
    (+ the KRR predict time per sequence)."""
    columns = ["method", "modality", "skin", "primitive", "seed", "nmse_overall", "train_time_s", "data_prepare_s",
               "inference_s_per_trial"]
    rows = [[p["method"], p["modality"] + "".join(f"/{k}={v}" for k, v in sorted(p["axes"].items())), p["skin"],
             p["primitive"], MISSING if p["seed"] is None else p["seed"], p["nmse_overall"], p["train_time_s"],
             p["data_prepare_s"], p["inference_s_per_trial"]] for p in runtime_points(results)]
    cap = ("Error vs run time per trial and method (times in seconds, this machine). " + RUNTIME_DEFINITION + " "
           + caption_note(results))
    return Table("runtime", cap, columns, rows)


# ----------------------------------------------------------------------------- formatting
def _missing(v) -> bool:
    return v is None or (isinstance(v, (float, np.floating)) and not math.isfinite(float(v)))


def fmt_cell(v, nd: int = 4, csv_: bool = False) -> str:
    """A cell as text: a non-finite number / None is ``–`` (empty in CSV), never ``nan``."""
    if _missing(v):
        return "" if csv_ else MISSING
    if isinstance(v, (float, np.floating)):
        return repr(float(v)) if csv_ else f"{float(v):.{nd}g}" if abs(float(v)) < 1e-3 else f"{float(v):.{nd}f}"
    return str(v)


def _cell(v, column, hue: str, nd: int) -> str:
    """Paper-style heat cell: ``\\cellcolor{hue!P!white}`` with P min-max scaled over ``column``
    (needs ``\\usepackage[table]{xcolor}``); lower NMSE = lighter."""
    vals = np.asarray([x for x in column if isinstance(x, (int, float, np.floating)) and math.isfinite(float(x))])
    if _missing(v):
        return "--"
    if not isinstance(v, (float, np.floating)) or vals.size == 0:
        return fmt_cell(v, nd)
    lo, hi = float(vals.min()), float(vals.max())
    pct = int(round(99 * (float(v) - lo) / (hi - lo))) if hi > lo else 0
    return rf"\cellcolor{{{hue}!{pct}!white}}{fmt_cell(v, nd)}"


def _num(v):
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(float(v)) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def _tex(s: str) -> str:
    s = s.replace(MISSING, "--")
    if "$" in s or "\\" in s:
        return s
    return s.replace("_", r"\_").replace("%", r"\%").replace("&", r"\&").replace("#", r"\#")
