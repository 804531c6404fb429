"""Do the label-conditioned prior's object codes put the objects into y? One row per run.

    python experiments/object_codes.py <run or multirun folder> [...]

For each training run (a run folder, or every job of a multirun / study folder, found as
evaluate.py finds them) on its own saved split and best checkpoint:

* ``nmse``: the run's held-out NMSE (whole trajectory) from its training-time final
  alignment (``metrics.json``, evaluate.py's settings);
* ``sigma``: the prior's standard deviation (median over y's dimensions);
* ``spread``: the median pairwise Mahalanobis distance between the training objects' codes
  under that prior (``eval.codes.code_spread``; ~0 = the codes collapsed onto one point);
* ``R2 init``: the share of the final codes' variance that an affine map of their initial
  random draws explains (``eval.codes.affine_r2``; the initial draws are rebuilt exactly as
  train.py builds the model: ``seed_everything(seed)``, the DataModule, then the model);
* ``own code, train / held-out``: the share of sequences whose q(y) mean at the last frame
  is nearest (Mahalanobis, the prior's variance) to their own object's code
  (``eval.codes.own_code_rank`` == 0; chance = 1 / the number of objects), on the training
  and on the held-out trials, with the median rank of the own code.

Prints one Markdown table. Trial split only (under the object split the held-out objects
have no code). docs/experiments/object_codes.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from embodied_tactile.run.threadenv import set_threads

os.environ.setdefault("OMP_NUM_THREADS", "1")


def initial_codes(cfg) -> np.ndarray:
    """The object codes the run started from: train.py's seeding and construction order."""
    import lightning as L
    from hydra.utils import instantiate

    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    instantiate(cfg.data)
    model = instantiate(cfg.model)
    return model.model.prior.embedding.weight.detach().numpy().astype(np.float64)


def run_row(run, opts, cache) -> dict:
    from embodied_tactile.eval import runs as ev
    from embodied_tactile.eval.codes import affine_r2, code_spread, own_code_rank
    from embodied_tactile.model.networks import softplus_var

    data = ev.data_config(run, opts)
    key, dm = cache.get(data)
    model = ev.load_module(run)
    prior = model.model.prior
    codes = prior.embedding.weight.detach().numpy().astype(np.float64)
    var = softplus_var(prior.raw_var.detach(), prior.var_floor).numpy().astype(np.float64)
    seen = np.flatnonzero(prior.seen.numpy())
    row = {"run": run.name, "seed": int(run.cfg.seed), "sigma": float(np.sqrt(np.median(var))),
           "spread": code_spread(codes[seen], var), "r2_init": affine_r2(initial_codes(run.cfg)[seen], codes[seen])}
    metrics = ev.read_json(run.run_dir / "metrics.json")
    row["nmse"] = (metrics.get("krr_final") or {}).get("nmse_overall", float("nan"))
    for which in ("train", "test"):
        split, _ = ev.collect_split(model, cache.batches(key, dm, which), ev.trial_names(dm, which), "y")
        ranks = own_code_rank(split["y"][:, -1], split["object_id"], codes, var, objects=seen)
        row[f"own_{which}"], row[f"rank_{which}"] = float((ranks == 0).mean()), float(np.median(ranks))
    row["n_objects"] = len(seen)
    return row


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", type=Path, help="run, multirun or study folders made by train.py")
    args = ap.parse_args(argv)

    import torch

    set_threads(1)
    from embodied_tactile.run import quiet
    from embodied_tactile.eval import runs as ev
    from embodied_tactile.eval.pipeline import parse_options

    quiet.silence_third_party()
    opts = parse_options([])
    cache = ev.DataCache()
    runs = []
    for f in args.folders:
        dirs = [f] if (f / "config_resolved.yaml").exists() else ev.job_dirs(f)
        runs += [ev.load_run(d, "best") for d in dirs]
    rows = []
    for run in runs:
        t0 = time.perf_counter()
        if str(run.cfg.data.get("split", "trial")) != "trial":
            print(f"# {run.run_dir}: object split, skipped (held-out objects have no code)", file=sys.stderr)
            continue
        rows.append(run_row(run, opts, cache))
        print(f"# {run.run_dir} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    print("| run | seed | held-out NMSE | prior sigma | code spread (sigma units) | R^2 codes ~ initial draws "
          "| own code nearest, train / held-out (median rank) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['run']} | {r['seed']} | {r['nmse']:.3f} | {r['sigma']:.2f} | {r['spread']:.2f} | "
              f"{r['r2_init']:.2f} | {r['own_train']:.2f} / {r['own_test']:.2f} "
              f"({r['rank_train']:.0f} / {r['rank_test']:.0f} of {r['n_objects']}) |")


if __name__ == "__main__":
    main()
