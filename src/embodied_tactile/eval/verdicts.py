"""Verdicts on the paper's findings from the runs of a study (numpy / scipy only).

Follows the study protocol and docs/reference/evaluation.md ("Findings and
verdicts"). A finding is tested as one or more comparisons "A is better than B" on a score
(held-out whole-trajectory NMSE of the Latent Filter, per factor or the overall mean; for the
object-group findings the group's NMSE normalised by the run's total variance, the paper's
Table 2 convention). Per comparison:

* ``d = NMSE_B - NMSE_A`` per seed (positive = the paper's direction). Runs of A and B with the
  same seed whose held-out sets hold the same (object, action) pairs are *paired* (the study's
  seeds fix the split); the interval is then the 95 % Student t interval of the mean of the
  per-seed d (n - 1 degrees of freedom). When the held-out sets differ (e.g. two skins or two
  primitives: the trial names, so the split, differ) the difference of the cell means gets a
  Welch t interval (*unpaired*). Fewer than 3 seeds on a side: no interval.
* verdict: ``reproduced`` when the interval excludes 0 in the paper's direction,
  ``contradicted`` when it excludes 0 in the opposite one, ``inconclusive`` when it contains 0
  (or there is no interval), ``not measured`` when a cell has no run.
* ``detectable``: the smallest true mean difference the design would detect with 80 % power
  at the 5 % level, (t_0.975 + t_0.80) x standard error, at the observed spread and n.

The findings of the paper's Table 1, (g)-(j), compare the held-out trials of parameter sets
within each run of multi_l on the soft e-Skin (paired), or the spread over a run's 16 sets
(:data:`SET_SPREADS`) between primitives.
A claim (one finding, per factor / group where the paper states it so) is ``contradicted`` if
any of its comparisons is, ``reproduced`` if every measured comparison is, ``inconclusive``
otherwise, ``not measured`` if none is measured. Every claim is listed, whatever its verdict.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..constants import ACTIONS, FACTOR_NAMES, HETEROGENEOUS_OBJECTS, N_OBJECTS, N_ACTIONS, PRIMITIVES, SOFT_OBJECTS
from .metrics import overall
from .results import Results
from .tables import MISSING, Table, fmt_cell, seed_stats

VERDICTS = ("reproduced", "contradicted", "inconclusive", "not measured")
MIN_SEEDS = 3  # the study protocol's t interval needs n >= 3
SOFT_SKIN_MODALITIES = ("acc", "fsr_t", "fsr_b", "fsr_tb", "multi_e", "multi_l")
UNIMODAL = ("acc", "fsr_t", "fsr_b", "fsr_tb")
MULTIMODAL = ("multi_e", "multi_l")
GROUP_SIZES = {"soft": len(SOFT_OBJECTS), "heterogeneous": len(HETEROGENEOUS_OBJECTS),
               "hard": N_OBJECTS - len(SOFT_OBJECTS) - len(HETEROGENEOUS_OBJECTS)}

#: The paper's Table 2 (tab:environmentshape, MULTI-L): NMSE over the interaction sequence per
#: e-Skin, object group and primitive; values (spatial freq., amplitude, stiffness,
#: heterogeneity, overall) copied from the paper's LaTeX source.
PAPER_TABLE2: dict[tuple[str, str], dict[str, tuple[float, ...]]] = {
    ("soft", "soft"): {"pressing": (0.022, 0.008, 0.032, 0.017, 0.017), "precession": (0.025, 0.007, 0.047, 0.016, 0.023),
                       "sliding": (0.031, 0.013, 0.052, 0.043, 0.035)},
    ("soft", "hard"): {"pressing": (0.066, 0.027, 0.112, 0.017, 0.052), "precession": (0.072, 0.024, 0.108, 0.025, 0.057),
                       "sliding": (0.082, 0.036, 0.134, 0.032, 0.070)},
    ("soft", "heterogeneous"): {"pressing": (0.055, 0.009, 0.023, 0.516, 0.130),
                                "precession": (0.055, 0.007, 0.030, 0.376, 0.105),
                                "sliding": (0.070, 0.010, 0.070, 0.629, 0.191)},
    ("hard", "soft"): {"pressing": (0.021, 0.007, 0.042, 0.054, 0.032), "precession": (0.014, 0.006, 0.044, 0.052, 0.029),
                       "sliding": (0.040, 0.012, 0.070, 0.028, 0.037)},
    ("hard", "hard"): {"pressing": (0.052, 0.022, 0.088, 0.015, 0.040), "precession": (0.047, 0.018, 0.084, 0.027, 0.042),
                       "sliding": (0.096, 0.041, 0.125, 0.029, 0.072)},
    ("hard", "heterogeneous"): {"pressing": (0.045, 0.008, 0.031, 0.543, 0.130),
                                "precession": (0.048, 0.008, 0.047, 0.685, 0.176),
                                "sliding": (0.080, 0.017, 0.094, 1.172, 0.339)},
}
SCORES = (*FACTOR_NAMES, "overall")

#: (e) the skin the paper's text finds better per object group ("soft e-Skin offers a perceptual
#: advantage when interacting with soft objects ... hard e-Skin performs more reliably across hard
#: objects"; softer skin "achieves improved accuracy when interacting with complex heterogeneous objects")
PAPER_BETTER_SKIN = {"soft": "soft", "hard": "hard", "heterogeneous": "soft"}


def paper_table2(skin: str, group: str, primitive: str, score: str) -> float:
    return PAPER_TABLE2[(skin, group)][primitive][SCORES.index(score)]


def paper_all_objects(skin: str, primitive: str, score: str) -> float:
    """The paper's Table 2 pooled over the three groups, weighted by their object counts (all
    groups share one denominator there, so this is the NMSE over all objects)."""
    return sum(GROUP_SIZES[g] * paper_table2(skin, g, primitive, score) for g in GROUP_SIZES) / N_OBJECTS


def paper_best_primitive(score: str) -> str:
    """(f) the paper's best primitive for a property: lowest :func:`paper_all_objects` on the soft e-Skin."""
    return min(PRIMITIVES, key=lambda p: paper_all_objects("soft", p, score))


# ----------------------------------------------------------------------------- one comparison
@dataclass(frozen=True)
class Side:
    """One side of a comparison: a cell (modality, skin, primitive) and, optionally, an object
    group or the parameter sets with one action parameter at one value (``action``: the
    parameter's name in ``constants.ACTIONS``, its value)."""

    modality: str
    skin: str
    primitive: str
    group: str | None = None
    action: tuple[str, float] | None = None

    @property
    def label(self) -> str:
        return (f"{self.modality}/{self.skin}/{self.primitive}" + (f" [{self.group} objects]" if self.group else "")
                + (f" [{self.action[0]}={self.action[1]:g}]" if self.action else ""))


@dataclass
class Comparison:
    finding: str  # 'a' .. 'f'
    claim: str  # the statement the verdict is about
    better: Side  # A: the side the paper says is better (lower NMSE)
    worse: Side  # B
    score: str  # factor name, 'overall' or a spread over parameter sets (SET_SPREADS)
    paper_d: float = float("nan")  # the paper's NMSE_B - NMSE_A where its Table 2 gives both
    stats: dict = field(default_factory=dict)
    score_worse: str | None = None  # B's score where it is not A's (a spread against another)

    @property
    def verdict(self) -> str:
        return self.stats.get("verdict", "not measured")


#: each primitive's frequency and amplitude ("depth": the indentation of pressing, the tilt of
#: precession, the stroke of sliding) among the action parameters (constants.ACTIONS)
FREQUENCY = {"pressing": "omega_z_hz", "precession": "omega_alpha_beta_hz", "sliding": "omega_xy_gamma_hz"}
DEPTH = {"pressing": "A_z_mm", "precession": "A_alpha_beta_deg", "sliding": "A_xy_mm"}
#: scores over a run's 16 parameter sets (each set: its held-out trials' overall NMSE, the run's
#: total variance): the standard deviation over the sets of the whole-trajectory NMSE, of the
#: last frame's, and of their difference (the error spent converging: how fast a set converges)
SET_SPREADS = ("set_spread_whole", "set_spread_last", "set_spread_convergence")


def action_mask(r: Results, action: tuple[str, float]) -> np.ndarray:
    """The run's held-out trials whose parameter set has ``action``'s parameter at its value."""
    name, value = action
    return np.array([ACTIONS[r.primitive][int(a)].params[name] == value for a in r.action_index], bool)


def set_spread(r: Results, score: str) -> float:
    """A :data:`SET_SPREADS` score of one run (NaN with fewer than 3 parameter sets held out)."""
    whole, last = [], []
    for a in range(N_ACTIONS):
        m = r.action_index == a
        if m.any():
            whole.append(overall(r.subset_nmse(m)))
            last.append(overall(r.curve(m)[-1]))
    if len(whole) < 3:
        return float("nan")
    w, l_ = np.asarray(whole), np.asarray(last)
    v = {"set_spread_whole": w, "set_spread_last": l_, "set_spread_convergence": w - l_}[score]
    return float(np.std(v, ddof=1))


def run_score(r: Results, score: str, group: str | None = None, action: tuple[str, float] | None = None) -> float:
    """Held-out whole-trajectory NMSE of one run (the group's sequences, or those of the
    parameter sets with ``action``, with the run's total variance), one factor or the overall
    mean; or a spread over the run's parameter sets (:data:`SET_SPREADS`)."""
    if score in SET_SPREADS:
        return set_spread(r, score)
    m = np.ones(r.n_test, bool) if group is None else r.group == group
    if action is not None:
        m &= action_mask(r, action)
    if not m.any():
        return float("nan")
    v = r.subset_nmse(m)
    return overall(v) if score == "overall" else float(v[FACTOR_NAMES.index(score)])


def _signature(r: Results) -> tuple:
    return tuple(sorted(zip(r.object_id.tolist(), r.action_index.tolist())))


def verdict_of(lo: float, hi: float) -> str:
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return "inconclusive"
    return "reproduced" if lo > 0 else "contradicted" if hi < 0 else "inconclusive"


def detectable_difference(se: float, df: float) -> float:
    """The true mean difference a two-sided 5 % t test with ``df`` degrees of freedom detects
    with 80 % power when its standard error is ``se``: (t_0.975 + t_0.80) x se."""
    from scipy.stats import t as student_t

    if not (math.isfinite(se) and math.isfinite(df) and df > 0):
        return float("nan")
    return float((student_t.ppf(0.975, df) + student_t.ppf(0.80, df)) * se)


def difference(a_runs: Sequence[Results], b_runs: Sequence[Results], score_a: Callable[[Results], float],
               score_b: Callable[[Results], float]) -> dict:
    """d = score_b(B) - score_a(A): paired by seed where the held-out sets match, else Welch.
    -> {pairing, n_a, n_b, n, mean, std, ci95_low, ci95_high, detectable, verdict}."""
    if not a_runs or not b_runs:
        return {"pairing": MISSING, "n_a": len(a_runs), "n_b": len(b_runs), "n": 0, "mean": float("nan"),
                "std": float("nan"), "ci95_low": float("nan"), "ci95_high": float("nan"),
                "detectable": float("nan"), "verdict": "not measured"}
    sa, sb = {r.seed: r for r in a_runs}, {r.seed: r for r in b_runs}
    unique = len(sa) == len(a_runs) and len(sb) == len(b_runs) and None not in sa and None not in sb
    common = sorted(set(sa) & set(sb), key=str) if unique else []
    if common and all(_signature(sa[s]) == _signature(sb[s]) for s in common):
        d = np.array([score_b(sb[s]) - score_a(sa[s]) for s in common])
        st = seed_stats(d)
        se = st["std"] / math.sqrt(st["n"]) if st["n"] >= 2 else float("nan")
        out = {"pairing": "paired by seed", "n_a": len(a_runs), "n_b": len(b_runs), "seeds": [str(s) for s in common],
               **st, "detectable": detectable_difference(se, st["n"] - 1) if st["n"] >= MIN_SEEDS else float("nan")}
    else:
        a = np.array([score_a(r) for r in a_runs], dtype=np.float64)
        b = np.array([score_b(r) for r in b_runs], dtype=np.float64)
        a, b = a[np.isfinite(a)], b[np.isfinite(b)]
        mean = float(b.mean() - a.mean()) if a.size and b.size else float("nan")
        lo = hi = std = det = float("nan")
        if min(a.size, b.size) >= MIN_SEEDS:
            from scipy.stats import t as student_t

            va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
            se = math.sqrt(va + vb)
            std = se
            if se > 0:
                df = (va + vb) ** 2 / (va ** 2 / (a.size - 1) + vb ** 2 / (b.size - 1))
                h = float(student_t.ppf(0.975, df)) * se
                det = detectable_difference(se, df)
            else:
                h, det = 0.0, 0.0
            lo, hi = mean - h, mean + h
        out = {"pairing": "unpaired (Welch)", "n_a": int(a.size), "n_b": int(b.size), "n": int(min(a.size, b.size)),
               "mean": mean, "std": std, "ci95_low": lo, "ci95_high": hi, "detectable": det}
    out["verdict"] = verdict_of(out["ci95_low"], out["ci95_high"])
    return out


# ----------------------------------------------------------------------------- the paper's findings
def _comparisons() -> list[Comparison]:
    """Every comparison the paper's findings (a)-(f) imply, in the protocol's order."""
    out: list[Comparison] = []
    for p in PRIMITIVES:  # (a) multimodal beats each unimodal input (soft skin)
        for m in MULTIMODAL:
            for u in UNIMODAL:
                out.append(Comparison("a", "multimodal (multi_e, multi_l) beats each unimodal input",
                                      Side(m, "soft", p), Side(u, "soft", p), "overall"))
    for p in PRIMITIVES:  # (b)
        out.append(Comparison("b", "late fusion (multi_l) beats early fusion (multi_e)",
                              Side("multi_l", "soft", p), Side("multi_e", "soft", p), "overall"))
    for f in ("stiffness", "heterogeneity"):  # (c)
        for p in PRIMITIVES:
            for one in ("fsr_t", "fsr_b"):
                out.append(Comparison("c", f"two FSR layers (fsr_tb) beat one (fsr_t, fsr_b) on {f}",
                                      Side("fsr_tb", "soft", p), Side(one, "soft", p), f))
    for skin in ("soft", "hard"):  # (d) Table 2's MULTI-L, within each run
        for p in PRIMITIVES:
            for g in ("soft", "hard"):
                out.append(Comparison("d", "heterogeneous objects are the hardest group (multi_l)",
                                      Side("multi_l", skin, p, g), Side("multi_l", skin, p, "heterogeneous"), "overall",
                                      paper_table2(skin, "heterogeneous", p, "overall") - paper_table2(skin, g, p, "overall")))
    for g, good in PAPER_BETTER_SKIN.items():  # (e)
        bad = "hard" if good == "soft" else "soft"
        for p in PRIMITIVES:
            out.append(Comparison("e", f"{g} objects: the {good} e-Skin is better (multi_l)",
                                  Side("multi_l", good, p, g), Side("multi_l", bad, p, g), "overall",
                                  paper_table2(bad, g, p, "overall") - paper_table2(good, g, p, "overall")))
    for s in SCORES:  # (f)
        best = paper_best_primitive(s)
        for q in PRIMITIVES:
            if q != best:
                out.append(Comparison("f", f"best primitive for {s}: {best} (multi_l, soft e-Skin)",
                                      Side("multi_l", "soft", best), Side("multi_l", "soft", q), s,
                                      paper_all_objects("soft", q, s) - paper_all_objects("soft", best, s)))
    for p in PRIMITIVES:  # (g)-(j): the paper's Table 1, within the runs of multi_l on the soft e-Skin
        f, lo, hi = FREQUENCY[p], min(DEPTH_VALUES[p]), max(DEPTH_VALUES[p])
        for other in (0.2, 0.8):
            out.append(Comparison("g", "about 0.6 Hz is the best frequency, the highest is worse (multi_l, soft e-Skin)",
                                  Side("multi_l", "soft", p, action=(f, 0.6)), Side("multi_l", "soft", p, action=(f, other)),
                                  "overall"))
        out.append(Comparison("h", "deeper contact (the larger amplitude) is better (multi_l, soft e-Skin)",
                              Side("multi_l", "soft", p, action=(DEPTH[p], hi)),
                              Side("multi_l", "soft", p, action=(DEPTH[p], lo)), "overall"))
    out.append(Comparison("i", "pressing: the parameter sets change the speed of convergence more than the final "
                               "error (multi_l, soft e-Skin)",
                          Side("multi_l", "soft", "pressing"), Side("multi_l", "soft", "pressing"),
                          "set_spread_last", score_worse="set_spread_convergence"))
    for q in ("precession", "sliding"):
        out.append(Comparison("j", "the parameter sets matter more in precession and sliding than in pressing "
                                   "(multi_l, soft e-Skin)",
                              Side("multi_l", "soft", "pressing"), Side("multi_l", "soft", q), "set_spread_whole"))
    return out


#: the amplitudes ("depths") of each primitive's parameter sets
DEPTH_VALUES = {p: sorted({a.params[DEPTH[p]] for a in ACTIONS[p]}) for p in PRIMITIVES}


def evaluate_findings(results: Sequence[Results], method: str = "latent_filter") -> list[Comparison]:
    """Every comparison of findings (a)-(f) with its statistics, from the runs of ``method``
    (runs with other swept axes than modality / skin / primitive / seed are kept apart: pass one
    axes setting at a time, see :func:`verdict_tables`)."""
    rs = [r for r in results if r.method == method]

    def runs(side: Side) -> list[Results]:
        return [r for r in rs if (r.modality, r.skin, r.primitive) == (side.modality, side.skin, side.primitive)]

    comps = _comparisons()
    for c in comps:
        c.stats = difference(runs(c.better), runs(c.worse),
                             lambda r, c=c: run_score(r, c.score, c.better.group, c.better.action),
                             lambda r, c=c: run_score(r, c.score_worse or c.score, c.worse.group, c.worse.action))
    return comps


def summarise(comps: Sequence[Comparison]) -> list[dict]:
    """One row per claim: verdict (module docstring's rule) and the counts of its comparisons."""
    out: dict[tuple, dict] = {}
    for c in comps:
        row = out.setdefault((c.finding, c.claim), {"finding": c.finding, "claim": c.claim,
                                                    **{v: 0 for v in VERDICTS}})
        row[c.verdict] += 1
    for row in out.values():
        measured = sum(row[v] for v in VERDICTS[:3])
        row["verdict"] = ("not measured" if not measured else "contradicted" if row["contradicted"]
                          else "reproduced" if row["reproduced"] == measured else "inconclusive")
    return list(out.values())


def verdict_tables(results: Sequence[Results], method: str = "latent_filter") -> list[Table]:
    """The findings table (one row per claim) and the comparisons table (one row per
    comparison: the difference, its interval, n, pairing, what was detectable, the paper's
    difference where its Table 2 gives one). Runs that differ in other swept axes are judged
    apart, one block per axes setting."""
    rs = [r for r in results if r.method == method]
    contexts = sorted({r.cell[4] for r in rs}, key=str) or [()]
    ctx_col = len(contexts) > 1
    f_rows, c_rows = [], []
    for ctx in contexts:
        comps = evaluate_findings([r for r in rs if r.cell[4] == ctx], method)
        tag = ["; ".join(f"{k}={v}" for k, v in ctx) or MISSING] if ctx_col else []
        for s in summarise(comps):
            f_rows.append([*tag, f"({s['finding']})", s["claim"], s["verdict"],
                           *[s[v] for v in VERDICTS]])
        for c in comps:
            st = c.stats
            ci = (MISSING if not (math.isfinite(st["ci95_low"]) and math.isfinite(st["ci95_high"]))
                  else f"[{fmt_cell(st['ci95_low'])}, {fmt_cell(st['ci95_high'])}]")
            score = c.score if c.score_worse is None else f"{c.score} vs {c.score_worse}"
            c_rows.append([*tag, f"({c.finding})", c.better.label, c.worse.label, score, st["pairing"],
                           f"{st['n_a']}/{st['n_b']}", st["mean"], ci, st["detectable"], c.paper_d, c.verdict])
    head = ["axes"] if ctx_col else []
    n_note = (f"d = NMSE(worse) - NMSE(better) per the paper (positive = the paper's direction), held-out "
              f"whole-trajectory NMSE of {method}; 95 % Student t interval over seeds (paired by seed where the "
              "held-out sets match, Welch otherwise; none with fewer than 3 seeds a side). reproduced: the interval "
              "excludes 0 in the paper's direction; contradicted: in the opposite one; inconclusive: it contains 0 "
              "or there is no interval. detectable: the mean difference the design detects with 80 % power at the "
              "observed spread and n. Group comparisons use the group's NMSE with the run's total variance "
              "(Table 2's convention).")
    findings = Table("findings", "The paper's findings (a)-(j), one row per claim, with their verdicts: contradicted "
                     "if any comparison is, reproduced if every measured one is, inconclusive otherwise; the "
                     "counts are the claim's comparisons (table 'comparisons'). " + n_note,
                     head + ["finding", "claim", "verdict", *VERDICTS], f_rows)
    comparisons = Table("comparisons", "Every comparison behind the findings: better side, worse side, score, "
                        "pairing, n seeds (better/worse), mean d, its 95 % interval, detectable difference, the "
                        "paper's d from its Table 2 (MULTI-L only; " + MISSING + " otherwise) and the verdict. "
                        + n_note, head + ["finding", "better", "worse", "score", "pairing", "n", "mean d", "95% CI",
                                          "detectable", "paper d", "verdict"], c_rows)
    return [findings, comparisons]
