"""K touches of an object never touched: the NMSE of y after K separate touches
(docs/experiments/population_budget.md, "More touches").

    python experiments/touches.py RUN [RUN ...] [--held-out val|test] [--k 1 2 4]

For a population-scene RUN whose objects are touched several times (``data.actions``), every
object's trials get one fixed random order (``--seed``); for each K the last-frame posteriors
q(y | touch k) of its first K trials are combined by
:func:`~embodied_tactile.model.latent_filter.combine_touches` (the prior counted once:
``LatentFilter.touch_prior``). The read-out is fitted at the same K on the training objects
(one row per object; alpha and gamma cross-validated by object, the run's own alignment
grids) and scores the held-out objects at that K: NMSE mean over factors, normalised by the
held-out targets' variance. K larger than an object's number of trials is skipped. Every run is
read twice: its final weights, and the same network at its initialisation (``untrained``: the
run's seed, its input statistics), the floor its numbers are compared with. Several runs (seeds)
end with the mean over them and its 95 % t interval per K. ``--json OUT`` writes the rows.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch
from embodied_tactile.run.threadenv import set_threads


def combined(split: dict, k: int, prior, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per object with at least ``k`` trials: q(y | its first k trials in a random order)."""
    from embodied_tactile.model.latent_filter import combine_touches

    objects = np.asarray(split["object_id"])
    means, facs, ids = [], [], []
    for o in sorted(set(objects.tolist())):
        idx = np.flatnonzero(objects == o)
        if len(idx) < k:
            continue
        pick = torch.as_tensor(rng.permutation(idx)[:k])
        cm, _ = combine_touches(split["y_last"][pick][:, None], split["y_var_last"][pick][:, None], *prior)
        means.append(cm[0].numpy())
        facs.append(split["factors"][int(idx[0])])
        ids.append(o)
    if not means:
        return np.empty((0, 0)), np.empty((0, 0)), np.asarray(ids)
    return np.stack(means), np.stack(facs), np.asarray(ids)


def score(run_dir: Path, held_out: str, ks, seed: int, untrained: bool = False) -> dict:
    from context_ladder import split_posteriors  # experiments/ is the script's folder

    from embodied_tactile.eval.krr import fit_alignment
    from embodied_tactile.eval.metrics import nmse, overall, reference_variance
    from embodied_tactile.eval.pipeline import parse_options, run_alignment

    run, net, tr, te = split_posteriors(run_dir, "last", held_out, untrained=untrained)
    opts = parse_options([])
    align = {k: v for k, v in dataclasses.asdict(run_alignment(run.cfg, opts)).items()
             if k in ("cv", "alphas", "gammas", "nystroem_threshold", "n_components", "seed", "n_threads")}
    prior = net.touch_prior()
    out = {"run": run_dir.name, "seed": int(run.cfg.seed), "held_out": held_out,
           "network": "untrained" if untrained else "trained"}
    for k in ks:
        x_tr, f_tr, o_tr = combined(tr, k, prior, np.random.default_rng(seed))
        x_te, f_te, _ = combined(te, k, prior, np.random.default_rng(seed + 1))
        if len(x_te) == 0 or len(x_tr) == 0:
            continue
        fit = fit_alignment(x_tr, f_tr, groups=o_tr, **align)
        out[f"K={k}"] = overall(nmse(f_te, fit.predict(x_te)[:, 0], var_ref=reference_variance(f_te)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--held-out", default="val", choices=("val", "test"))
    ap.add_argument("--k", nargs="+", type=int, default=[1, 2, 4])
    ap.add_argument("--seed", type=int, default=0, help="the order in which each object's trials are taken")
    ap.add_argument("--json", type=Path, default=None, help="write every row (run, seed, side, network, K=...) here")
    args = ap.parse_args(argv)
    set_threads(1)
    print("| run | seed | side | network | " + " | ".join(f"K={k}" for k in args.k) + " |")
    print("|---" * (4 + len(args.k)) + "|")
    rows = []
    for run in args.runs:
        for untrained in (False, True):
            r = score(run, args.held_out, args.k, args.seed, untrained=untrained)
            rows.append({"path": str(run), **r})
            print(f"| {r['run']} | {r['seed']} | {r['held_out']} | {r['network']} | "
                  + " | ".join(f"{r[f'K={k}']:.3f}" if f"K={k}" in r else "–" for k in args.k) + " |", flush=True)
    if len(args.runs) > 1:
        print(summary(rows, args.k))
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


def summary(rows: list[dict], ks) -> str:
    """Per network (trained, untrained): mean over the runs [95 % t interval] at each K."""
    from embodied_tactile.eval.generalisation import mean_interval

    lines = ["", "| network | runs | " + " | ".join(f"K={k}" for k in ks) + " |", "|---" * (2 + len(ks)) + "|"]
    for network in ("trained", "untrained"):
        mine = [r for r in rows if r["network"] == network]
        cells = []
        for k in ks:
            m, lo, hi = mean_interval([r[f"K={k}"] for r in mine if f"K={k}" in r])
            cells.append(f"{m:.3f} [{lo:.3f}, {hi:.3f}]")
        lines.append(f"| {network} | {len(mine)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
