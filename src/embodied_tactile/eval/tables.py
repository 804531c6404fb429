"""Tables from :class:`~embodied_tactile.eval.results.Results`: the paper's Table 1 / Table 2
analogues, a per-run summary and a runtime table, with Markdown / CSV / LaTeX writers.

All numbers come from :func:`pooled_nmse` (= :func:`~embodied_tactile.eval.metrics.nmse`
with each run's reference variance), and every table carries the NMSE definition, the split
sizes and the data source in its caption.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..constants import ACTION_PARAM_NAMES, ACTIONS, FACTOR_NAMES, N_ACTIONS, PRIMITIVES, SKINS
from .metrics import NMSE_DEFINITION, nmse, overall
from .results import Results

FACTOR_LABELS = {"spatial_frequency": "Spatial Freq.", "amplitude": "Amplitude", "stiffness": "Stiffness",
                 "heterogeneity": "Heterogeneity"}
GROUPS = ("soft", "hard", "heterogeneous")
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

    def to_markdown(self) -> str:
        out = [f"**{self.name}.** {self.caption}", "", "| " + " | ".join(self.columns) + " |",
               "|" + "|".join("---" for _ in self.columns) + "|"]
        out += ["| " + " | ".join(_fmt(v) for v in r) + " |" for r in self.rows]
        return "\n".join(out) + "\n"

    def to_csv(self) -> str:
        buf = io.StringIO()
        buf.write(f"# {self.name}: {self.caption}\n")
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(self.columns)
        for r in self.rows:
            w.writerow([_fmt(v, csv_=True) for v in r])
        return buf.getvalue()

    def to_latex(self) -> str:
        body = self.latex_body
        if body is None:
            spec = "l" + "c" * (len(self.columns) - 1)
            lines = [rf"\begin{{tabular}}{{{spec}}}", r"\toprule", " & ".join(_tex(c) for c in self.columns) + r" \\",
                     r"\midrule"]
            lines += [" & ".join(_tex(_fmt(v)) for v in r) + r" \\" for r in self.rows]
            lines += [r"\bottomrule", r"\end{tabular}"]
            body = "\n".join(lines)
        return ("\\begin{table*}[!tbh]\n\\centering\n\\resizebox{\\textwidth}{!}{%\n" + body + "%\n}\n"
                f"\\caption{{{_tex(self.caption)}}}\n\\label{{tab:{self.name}}}\n\\end{{table*}}\n")

    def to_json(self) -> dict:
        return {"name": self.name, "caption": self.caption, "columns": self.columns,
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
    n_runs = len({(r.modality, r.skin, r.primitive) for r in results})
    return (f"{NMSE_DEFINITION} Splits ({n_runs} run(s)): {sz}. Data source: {', '.join(srcs) or 'unknown'}.")


def _filter(results, method=None, modality=None, skin=None, primitive=None):
    return [r for r in results if (method is None or r.method == method) and (modality is None or r.modality == modality)
            and (skin is None or r.skin == skin) and (primitive is None or r.primitive == primitive)]


# ----------------------------------------------------------------------------- Table 1
def table_actions(results: Sequence[Results], *, method: str | None = "latent_filter", modality: str | None = None,
                  skin: str | None = None) -> Table:
    """Table 1 analogue: per action index (1..16) and primitive, the action parameters and
    the whole-trajectory NMSE (mean over factors), printed in units of 1e-2 like the paper."""
    rs = _filter(results, method, modality, skin)
    prims = [p for p in PRIMITIVES if any(r.primitive == p for r in rs)] or list(PRIMITIVES)
    columns = ["Action Index"]
    for p in prims:
        columns += [f"{p}:{k}" for k in ACTION_PARAM_NAMES[p]] + [f"{p}:NMSE_1e-2"]
    rows = []
    for a in range(N_ACTIONS):
        row: list = [a + 1]
        for p in prims:
            row += [ACTIONS[p][a].params[k] for k in ACTION_PARAM_NAMES[p]]
            v = pooled_nmse(_filter(rs, primitive=p), lambda r, a=a: r.action_index == a)
            row.append(100.0 * overall(v) if np.isfinite(v).any() else float("nan"))
        rows.append(row)
    # paper layout
    spec = "c " + " ".join("c" * (len(ACTION_PARAM_NAMES[p]) + 1) for p in prims)
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
    for row in rows:
        cells, i = [str(row[0])], 1
        for p in prims:
            k = len(ACTION_PARAM_NAMES[p])
            col_vals = [r[i + k] for r in rows]
            cells += [f"{v:.1f}" for v in row[i : i + k]] + [_cell(row[i + k], col_vals, "orange", 3)]
            i += k + 1
        lines.append(" & ".join(cells) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    what = ", ".join(x for x in (method, modality, skin) if x) or "all runs"
    cap = (f"NMSE over the whole interaction trajectory (mean over the four factors, x1e-2) per action "
           f"parameter set ({what}); lower is better. " + caption_note(rs))
    return Table("action_config", cap, columns, rows, "\n".join(lines))


# ----------------------------------------------------------------------------- Table 2
def table_groups(results: Sequence[Results], *, method: str | None = "latent_filter", modality: str | None = None) -> Table:
    """Table 2 analogue: NMSE per factor x object group x skin x primitive + Overall rows."""
    rs = _filter(results, method, modality)
    skins = [s for s in SKINS if any(r.skin == s for r in rs)] or list(SKINS)
    prims = [p for p in PRIMITIVES if any(r.primitive == p for r in rs)] or list(PRIMITIVES)
    columns = ["Skin", "Factor"] + [f"{g}:{p}" for g in GROUPS for p in prims]
    rows = []
    for s in skins:
        vals = np.full((len(GROUPS) * len(prims), 4), np.nan)
        for gi, g in enumerate(GROUPS):
            for pi, p in enumerate(prims):
                vals[gi * len(prims) + pi] = pooled_nmse(_filter(rs, skin=s, primitive=p), lambda r, g=g: r.group == g)
        for k, f in enumerate(FACTOR_NAMES):
            rows.append([s, f, *vals[:, k]])
        rows.append([s, "Overall", *[overall(v) for v in vals]])
    ng = len(prims)
    spec = "c c " + " ".join("c" * ng for _ in GROUPS)
    lines = [rf"\begin{{tabular}}{{{spec}}}", r"\toprule",
             " & & " + " & ".join(rf"\multicolumn{{{ng}}}{{c}}{{{g.capitalize()} Objects}}" for g in GROUPS) + r" \\",
             " ".join(rf"\cmidrule(lr){{{3 + i * ng}-{2 + (i + 1) * ng}}}" for i in range(len(GROUPS))),
             " & & " + " & ".join(p.capitalize() for _ in GROUPS for p in prims) + r" \\", r"\midrule"]
    for si, s in enumerate(skins):
        block = [r for r in rows if r[0] == s]
        for j, r in enumerate(block):
            first = rf"\multirow{{{len(block)}}}{{*}}{{\rotatebox{{90}}{{{s.capitalize()} e-Skin}}}}" if j == 0 else ""
            if r[1] == "Overall":
                lines.append(rf"\cmidrule(lr){{2-{2 + len(GROUPS) * ng}}}")
            label = FACTOR_LABELS.get(r[1], r[1])
            allv = [v for rr in rows for v in rr[2:]]
            hues = [h for h in ("red", "green", "blue") for _ in prims]
            lines.append(" & ".join([first, label] + [_cell(v, allv, h, 3) for v, h in zip(r[2:], hues)]) + r" \\")
        if si < len(skins) - 1:
            lines.append(r"\midrule")
    lines += [r"\bottomrule", r"\end{tabular}"]
    what = ", ".join(x for x in (method, modality) if x) or "all runs"
    cap = (f"NMSE over the entire interaction sequence per factor, object group (soft / hard / heterogeneous), "
           f"e-Skin and primitive ({what}); Overall = mean over the four factors; lower is better. "
           + caption_note(rs))
    return Table("environmentshape", cap, columns, rows, "\n".join(lines))


# ----------------------------------------------------------------------------- summary / runtime
def table_summary(results: Sequence[Results]) -> Table:
    """One row per run/method: whole-trajectory and last-step NMSE per factor + overall."""
    columns = ["method", "modality", "skin", "primitive", "n_train", "n_test",
               *[f"traj:{f}" for f in FACTOR_NAMES], "traj:overall", *[f"last:{f}" for f in FACTOR_NAMES], "last:overall"]
    rows = []
    for r in results:
        traj, last = r.subset_nmse(), r.curve()[-1]
        rows.append([r.method, r.modality, r.skin, r.primitive, r.n_train, r.n_test, *traj, overall(traj), *last, overall(last)])
    cap = "Whole-trajectory (traj) and last-frame (last) NMSE per factor. " + caption_note(results)
    return Table("summary", cap, columns, rows)


def table_runtime(results: Sequence[Results]) -> Table:
    """NMSE, training wall time and inference time per trial, per run and method.

    Training time: ``params['train_time_s']`` (Latent Filter: the training wall time of the
    run, e.g. the last ``train_wall_time_s`` of krr_history.jsonl; baselines: their own fit).
    Inference: ``params['inference_s_per_sequence']`` (+ the KRR predict time per sequence)."""
    columns = ["method", "modality", "skin", "primitive", "nmse_overall", "train_time_s", "inference_s_per_trial"]
    rows = []
    for r in results:
        p = r.params
        inf = float(p.get("inference_s_per_sequence", 0.0)) + float(p.get("krr_predict_s_per_sequence", 0.0))
        rows.append([r.method, r.modality, r.skin, r.primitive, overall(r.subset_nmse()),
                     float(p.get("train_time_s", float("nan"))), inf])
    cap = "Error vs run time per trial and method (times in seconds, this machine). " + caption_note(results)
    return Table("runtime", cap, columns, rows)


# ----------------------------------------------------------------------------- formatting
def _fmt(v, nd: int = 4, csv_: bool = False) -> str:
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(float(v)):
            return "nan"
        return repr(float(v)) if csv_ else f"{float(v):.{nd}g}" if abs(float(v)) < 1e-3 else f"{float(v):.{nd}f}"
    return str(v)


def _cell(v, column, hue: str, nd: int) -> str:
    """Paper-style heat cell: ``\\cellcolor{hue!P!white}`` with P min-max scaled over ``column``
    (needs ``\\usepackage[table]{xcolor}``); lower NMSE = lighter."""
    vals = np.asarray([x for x in column if isinstance(x, (int, float, np.floating)) and math.isfinite(float(x))])
    if not (isinstance(v, (float, np.floating)) and math.isfinite(float(v))) or vals.size == 0:
        return _fmt(v, nd)
    lo, hi = float(vals.min()), float(vals.max())
    pct = int(round(99 * (float(v) - lo) / (hi - lo))) if hi > lo else 0
    return rf"\cellcolor{{{hue}!{pct}!white}}{_fmt(v, nd)}"


def _num(v):
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(float(v)) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def _tex(s: str) -> str:
    if "$" in s or "\\" in s:
        return s
    return s.replace("_", r"\_").replace("%", r"\%").replace("&", r"\&").replace("#", r"\#")
