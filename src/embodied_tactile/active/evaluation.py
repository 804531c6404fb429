"""Evaluation of action selection: NMSE against the number of touches for the active policy
and the baselines, over held-out objects and several episode seeds (docs/reference/active.md).

* The fixed order is fitted on the training side: greedy over calibration episodes on the
  run's training objects under the calibration seed stream (never an evaluation seed).
* Every policy of one seed sees the same touches whenever it asks for the same one
  (:class:`~embodied_tactile.active.episode.TouchCache`): the comparison is paired.
* NMSE at touch k: per factor sum_objects (f_hat - f)^2 / (n var_ref), var_ref the factor's
  variance over the 32-object catalogue in the targets encoding, then the mean over factors
  (:func:`embodied_tactile.eval.metrics.nmse`, :func:`~embodied_tactile.eval.metrics.overall`).
  Across seeds: mean, std and the 95 % t interval (:func:`embodied_tactile.eval.tables.seed_stats`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from embodied_tactile.eval.metrics import nmse, overall
from embodied_tactile.eval.tables import MISSING, Table, seed_stats

from .episode import EpisodeLog, TouchCache, filter_touch, run_episodes
from .model import PalpationModel
from .policy import make_policy
from .source import SimulatedTouchSource

#: episode seed of the calibration episodes (fixed order); evaluation seeds must differ
CALIBRATION_SEED = 999


def nmse_curve(log: EpisodeLog, ref_var: np.ndarray) -> np.ndarray:
    """(K,) overall NMSE after each touch of the episodes in ``log``."""
    return np.array([overall(nmse(log.truth, log.estimates[:, k], axis=0, var_ref=ref_var))
                     for k in range(log.estimates.shape[1])])


def calibration_cache(model: PalpationModel, calibration_seed: int = CALIBRATION_SEED) -> TouchCache:
    """Touches of the calibration episodes (simulated under the calibration seed)."""
    return TouchCache(model, SimulatedTouchSource(model.skin, model.primitive, calibration_seed))


def fit_fixed_order(model: PalpationModel, objects: Sequence[int], n_touches: int, *,
                    cache: Optional[TouchCache] = None) -> tuple[list[int], list[list[float]]]:
    """Greedy fixed order: touch k is the action that, after the k touches chosen so far,
    gives the lowest mean NMSE over calibration episodes on ``objects`` (the run's training
    objects). Returns (order, NMSE of every candidate at every step)."""
    cache = cache or calibration_cache(model)
    obj = np.asarray(objects, dtype=np.int64)
    truth = model.true_factors(obj)
    order: list[int] = []
    table: list[list[float]] = []
    state = None
    for _ in range(int(n_touches)):
        best = None
        row = []
        for a in model.actions:
            use = order.count(a)
            batch = [cache.get(int(o), a, use) for o in obj]
            out, st = filter_touch(model.net, torch.from_numpy(np.stack([b[0] for b in batch])),
                                   torch.from_numpy(np.stack([b[1] for b in batch])), state)
            est = model.factors_of(out["y_mean"].float().numpy())
            v = overall(nmse(truth, est, axis=0, var_ref=model.ref_var))
            row.append(v)
            if best is None or v < best[0]:
                best = (v, a, st)
        table.append(row)
        order.append(int(best[1]))
        state = best[2]
    return order, table


def fit_error_score(model: PalpationModel, objects: Sequence[int], *, cache: Optional[TouchCache] = None,
                    cv: int = 5) -> dict[int, Any]:
    """The learned score of the active policy (docs/reference/active.md, eq. 6), from calibration
    episodes on ``objects`` (the run's training objects): for every first touch a1 and next
    touch a2, the posterior mean y after a1 (features) and the normalised squared factor
    error after a2, e = mean_k (f_hat_k - f_k)^2 / var_ref_k (target). One KRR per a2
    (:func:`~embodied_tactile.eval.krr.fit_alignment`, CV folds grouped by object)."""
    from embodied_tactile.eval.krr import fit_alignment

    cache = cache or calibration_cache(model)
    obj = np.asarray(objects, dtype=np.int64)
    truth = model.true_factors(obj)
    xs: dict[int, list] = {a: [] for a in model.actions}
    es: dict[int, list] = {a: [] for a in model.actions}

    def touch(a, use, state):
        batch = [cache.get(int(o), a, use) for o in obj]
        return filter_touch(model.net, torch.from_numpy(np.stack([b[0] for b in batch])),
                            torch.from_numpy(np.stack([b[1] for b in batch])), state)

    for a1 in model.actions:
        out1, st1 = touch(a1, 0, None)
        y1 = out1["y_mean"].float().numpy()
        for a2 in model.actions:
            out2, _ = touch(a2, 1 if a2 == a1 else 0, st1)
            est = model.factors_of(out2["y_mean"].float().numpy())
            xs[a2].append(y1)
            es[a2].append(((est - truth) ** 2 / model.ref_var).mean(axis=1))
    groups = np.tile(obj, len(model.actions))
    return {a: fit_alignment(np.concatenate(xs[a]), np.concatenate(es[a])[:, None], groups=groups, cv=cv, n_threads=1)
            for a in model.actions}


def evaluate_policies(model: PalpationModel, objects: Sequence[int], *, budget: int, seeds: Sequence[int],
                      policies: Sequence[str], fixed_order: Sequence[int], first_action: int, single_action: int,
                      active: Optional[dict] = None, n_factor_samples: int = 64, error_score: Optional[dict] = None,
                      log=print) -> dict[str, Any]:
    """Run every policy on every object for every seed. -> {"curves": {policy: (S, K)},
    "actions": {policy: [(B, K) per seed]}, "decision_s": [...], "touches_simulated": n}."""
    if CALIBRATION_SEED in seeds:
        raise ValueError(f"seed {CALIBRATION_SEED} is the calibration seed of the fixed order; use other seeds")
    curves: dict[str, list[np.ndarray]] = {p: [] for p in policies}
    acts: dict[str, list[list]] = {p: [] for p in policies}
    decision_s: list[float] = []
    n_sim = 0
    for s in seeds:
        cache = TouchCache(model, SimulatedTouchSource(model.skin, model.primitive, int(s)))
        for p in policies:
            pol = make_policy(p, model=model, first_action=first_action, single_action=single_action,
                              fixed_order=fixed_order, active=active, error_score=error_score)
            t0 = time.perf_counter()
            ep = run_episodes(model, cache.source, objects, pol, budget, seed=int(s), n_factor_samples=n_factor_samples,
                              cache=cache)
            c = nmse_curve(ep, model.ref_var)
            curves[p].append(c)
            acts[p].append(ep.actions.tolist())
            decision_s += ep.decision_s
            log(f"seed {s} {p:>6}: NMSE per touch {np.round(c, 3).tolist()} ({time.perf_counter() - t0:.0f} s)")
        n_sim += cache.misses
    return {"curves": {p: np.stack(v) for p, v in curves.items()}, "actions": acts, "decision_s": decision_s,
            "touches_simulated": n_sim}


def touches_to_reach(curve: np.ndarray, level: float) -> Optional[int]:
    """First touch count (1-based) at which ``curve`` <= ``level``; None if never."""
    hit = np.nonzero(np.asarray(curve) <= level + 1e-12)[0]
    return int(hit[0]) + 1 if hit.size else None


def summarise(curves: dict[str, np.ndarray], reference: str = "random", policy: str = "active") -> dict[str, Any]:
    """Per touch and policy: seed statistics; the target check: touches the policy needs to
    reach the reference's final NMSE (on the seed-mean curves and per seed)."""
    K = next(iter(curves.values())).shape[1]
    stats = {p: [seed_stats(c[:, k]) for k in range(K)] for p, c in curves.items()}
    out: dict[str, Any] = {"stats": stats, "budget": K}
    if reference in curves and policy in curves:
        ref_final = float(curves[reference][:, -1].mean())
        need = touches_to_reach(curves[policy].mean(axis=0), ref_final)
        per_seed = [touches_to_reach(curves[policy][i], float(curves[reference][i, -1]))
                    for i in range(curves[policy].shape[0])]
        out["target"] = {"reference": reference, "policy": policy, "reference_final_nmse": ref_final,
                         "touches_needed": need, "fraction": None if need is None else need / K,
                         "met": need is not None and need <= 0.6 * K, "touches_needed_per_seed": per_seed}
    return out


def curve_table(summary: dict[str, Any], caption: str) -> Table:
    pols = list(summary["stats"])
    cols = ["Touches"] + [f"{p} mean" for p in pols] + [f"{p} 95% CI" for p in pols]
    rows = []
    for k in range(summary["budget"]):
        st = [summary["stats"][p][k] for p in pols]
        ci = [f"[{s['ci95_low']:.4f}, {s['ci95_high']:.4f}]" if np.isfinite(s["ci95_low"]) else MISSING for s in st]
        rows.append([k + 1] + [s["mean"] for s in st] + ci)
    return Table("active_nmse", caption, cols, rows)


def plot_curves(summary: dict[str, Any], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    k = np.arange(1, summary["budget"] + 1)
    for p, st in summary["stats"].items():
        m = np.array([s["mean"] for s in st])
        lo = np.array([s["ci95_low"] for s in st])
        hi = np.array([s["ci95_high"] for s in st])
        ax.plot(k, m, marker="o", label=p)
        if np.all(np.isfinite(lo)):
            ax.fill_between(k, lo, hi, alpha=0.2)
    tgt = summary.get("target")
    if tgt:
        ax.axhline(tgt["reference_final_nmse"], color="grey", ls=":", lw=1,
                   label=f"{tgt['reference']} final NMSE")
    ax.set_xlabel("touches")
    ax.set_ylabel("NMSE (mean over factors)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


#: the files of one evaluation's table and figure, beside its record ``<stem>.json``
TABLE_FILES = ("md", "csv", "tex", "png")


def write_tables(out_dir: Path, stem: str, summary: dict[str, Any], caption: str, title: str) -> dict[str, Path]:
    """The NMSE-against-touches table (``<stem>.md`` / ``.csv`` / ``.tex``) and its figure
    (``<stem>.png``) of one evaluation's summary."""
    tab = curve_table(summary, caption)
    paths = {ext: out_dir / f"{stem}.{ext}" for ext in TABLE_FILES}
    paths["md"].write_text(tab.to_markdown())
    paths["csv"].write_text(tab.to_csv())
    paths["tex"].write_text(tab.to_latex())
    plot_curves(summary, paths["png"], title)
    return paths


def rewrite_tables(record: Path) -> dict[str, Path]:
    """The table and figure of a saved evaluation (its record ``<stem>.json``, written by
    :func:`write_outputs`) written again beside it, from the record alone."""
    meta = json.loads(Path(record).read_text())["meta"]
    if "caption" not in meta:
        raise ValueError(f"{record}: no meta.caption (not a record written by active.evaluation.write_outputs)")
    summary = json.loads(Path(record).read_text())["summary"]
    return write_tables(Path(record).parent, Path(record).stem, summary, meta["caption"],
                        meta.get("title", "active palpation"))


def write_outputs(out_dir: Path, summary: dict[str, Any], result: dict[str, Any], meta: dict[str, Any],
                  caption: str) -> dict[str, str]:
    """``active_nmse.{md,csv,tex,png}`` and the record ``active_nmse.json`` (meta with the
    caption, summary, curves, actions) from which :func:`rewrite_tables` rewrites the others."""
    out_dir.mkdir(parents=True, exist_ok=True)
    from embodied_tactile.jsonio import write_json

    meta = {**meta, "caption": caption}
    paths = write_tables(out_dir, "active_nmse", summary, caption, meta.get("title", "active palpation"))
    paths["json"] = out_dir / "active_nmse.json"
    write_json(paths["json"], {"meta": meta, "summary": summary,
                               "curves": {p: c.tolist() for p, c in result["curves"].items()},
                               "actions": result["actions"], "decision_s": result["decision_s"],
                               "touches_simulated": result["touches_simulated"]})
    return {k: str(v) for k, v in paths.items()}
