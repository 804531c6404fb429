"""Where the spread of the held-out NMSE comes from, and how it shrinks as the design grows.

    python experiments/variance_components.py train --work WORK &   # one lane of the runs (resumes)
    python experiments/variance_components.py train --work WORK &   # a second lane beside it, threads=1 each
    python experiments/variance_components.py analyse --work WORK                    # the tables of the page

Each design (``DESIGNS``) is trained at one base setting (seed 0, split seed 0, simulated
dataset 0) and with one source of variation changed at a time (``FACTORS``):

* ``init``: the model seed (initialisation, window draws, SGD order), data and split fixed;
* ``split``: the split seed (which trials train, validate, test), model seed and data fixed;
* ``data``: the simulator's noise seed (a new dataset of the same objects and actions),
  model seed and split fixed;
* ``main``: the model seed and the split seed together, the data fixed: what ``python
  train.py seed=S`` varies (the main job's seed spread).

Every run is ``python train.py threads=1`` in ``WORK/runs/<design>/<factor><level>`` with one
data folder ``WORK/data`` shared by all (simulated once per design and data seed). ``analyse``
reads every run's final weights (``last.ckpt``: the weights the main job reports), infers the
latents of the training and the held-out test trials once, and measures on them, within the run:

* the read-out's own noise: the alignment refitted with other cross-validation seeds
  (``alignment.seed``), and on a random half of the training sequences;
* the test set's sampling noise: the NMSE recomputed on bootstrap resamples of the test
  trials, and of the test objects (all trials of a drawn object together).

Between runs, the standard deviation over the levels of each factor (the base run included)
measures that factor's share; the within-run components say how much of it the read-out and
the test sample alone would produce. Prints Markdown tables (docs/experiments/variance_components.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

#: design -> train.py overrides on top of the default scene (the typed defaults). Every
#: design trains 960 optimiser steps (32 epochs of 480 windows at batch 16).
DESIGNS: dict[str, list[str]] = {
    "sets4": ["data.actions=[2,6,10,14]", "data.windows_per_trial=6", "data.windows_per_epoch=null"],  # 4 sets at 0.6 Hz, one touch (128 trials)
    "sets16": ["data.actions=null", "data.windows_per_trial=null", "data.windows_per_epoch=480"],  # all 16 (512): the default scene
    "sets16_rep2": ["data.actions=null", "data.repetitions=2", "data.windows_per_trial=null",
                    "data.windows_per_epoch=480"],  # all 16, two touches each (1,024)
    "sets16_steps2x": ["data.actions=null", "data.windows_per_trial=null", "data.windows_per_epoch=480",
                       "trainer.max_epochs=64"],  # all 16 at twice the steps (1,920)
}
#: factor -> the overrides of its level (level 0 is the base run, shared by all factors)
FACTORS = {
    "init": lambda s: [f"seed={s}", "data.split_seed=0", "data.sim_seed=0"],
    "split": lambda s: ["seed=0", f"data.split_seed={s}", "data.sim_seed=0"],
    "data": lambda s: ["seed=0", "data.split_seed=0", f"data.sim_seed={s}"],
    "main": lambda s: [f"seed={s}", f"data.split_seed={s}", "data.sim_seed=0"],  # as `python train.py seed=S` varies
}


def plan(designs: list[str], levels: int) -> list[tuple[str, str, list[str]]]:
    """(design, run name, overrides) of every run in the order the lanes take them: per design
    the base run, the first level of every factor, every level of ``main`` (the main job's
    seed spread), then the further levels of the others."""
    out = []
    for d in designs:
        out.append((d, "base", DESIGNS[d] + FACTORS["init"](0)))
        later = []
        for lvl in range(1, levels):
            for f, make in FACTORS.items():
                (out if lvl == 1 or f == "main" else later).append((d, f"{f}{lvl}", DESIGNS[d] + make(lvl)))
        out += later
    return out


def claim(run_dir: Path) -> int | None:
    """Take ``run_dir`` for this lane: an fd holding ``flock`` on ``<run>.claim`` (closing it,
    or the lane's end however it ends, releases it), or None when another lane holds it."""
    from embodied_tactile.run.runfolder import try_lock, write_holder

    run_dir.parent.mkdir(parents=True, exist_ok=True)
    fd, _ = try_lock(run_dir.with_name(run_dir.name + ".claim"))
    if fd is not None:
        write_holder(fd)
    return fd


def finished(run_dir: Path) -> bool:
    m = run_dir / "metrics.json"
    return m.exists() and json.loads(m.read_text()).get("status") == "finished"


def train(args) -> None:
    """Every run of the plan not finished and not taken by another lane, in plan order."""
    work = Path(args.work).resolve()
    for design, name, overrides in plan(args.designs, args.levels):
        run_dir = work / "runs" / design / name
        if finished(run_dir):
            continue
        fd = claim(run_dir)
        if fd is None:
            continue
        cmd = [sys.executable, str(REPO / "train.py"), "threads=1", "logger=none", f"paths.data_dir={work / 'data'}",
               f"hydra.run.dir={run_dir}", *overrides]
        print(time.strftime("%H:%M:%S"), " ".join(cmd[2:]), flush=True)
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=REPO, env=dict(os.environ, WANDB_MODE="disabled"), capture_output=True,
                              text=True)
        print(f"  rc {proc.returncode} in {time.perf_counter() - t0:.0f} s", flush=True)
        if proc.returncode != 0:
            print(proc.stderr[-2000:], flush=True)
        os.close(fd)


# ----------------------------------------------------------------------------- analysis
def _overall(res) -> tuple[float, float]:
    from embodied_tactile.eval.metrics import nmse_over_time, nmse_trajectory, overall

    return overall(nmse_trajectory(res.factors, res.pred)), overall(nmse_over_time(res.factors, res.pred)[-1])


def analyse_run(run_dir: Path, n_boot: int, n_seeds: int) -> dict:
    """The run's test NMSE and its within-run components (module docstring); the read-out's
    refits (``n_seeds`` of each kind, 0: none) cost a full alignment each."""
    import warnings

    from embodied_tactile.eval.metrics import NMSEUndefinedWarning, bootstrap_overall
    from embodied_tactile.eval.pipeline import parse_options, run_alignment
    from embodied_tactile.eval.results import evaluate_latents
    from embodied_tactile.eval.runs import (DataCache, collect_splits, data_config, load_run, run_split, trial_names,
                                            trial_objects)
    from embodied_tactile.eval.targets import encode_split
    from embodied_tactile.eval.pipeline import run_targets
    from embodied_tactile.eval.runs import load_module
    from embodied_tactile.run.threadenv import set_threads

    warnings.simplefilter("ignore", NMSEUndefinedWarning)
    set_threads(1)
    opts = parse_options(["checkpoint=last"])
    run = load_run(run_dir, "last")
    cache = DataCache()
    key, dm = cache.get(data_config(run, opts))
    model = load_module(run)
    sides = ((cache.batches(key, dm, "train"), trial_names(dm, "train")),
             (cache.batches(key, dm, "test"), trial_names(dm, "test")))
    tr, te, _ = collect_splits(model, *sides, "y", 128)
    targets = run_targets(run.cfg, opts)
    tr, te = encode_split(tr, targets), encode_split(te, targets)
    split = run_split(run, data_config(run, opts)["split_file"], trial_objects(dm))["kind"]
    align = run_alignment(run.cfg, opts)
    res, _ = evaluate_latents(tr, te, alignment=align, split=split)
    whole, last = _overall(res)
    out = {"run": str(run_dir), "n_train": len(tr["factors"]), "n_test": len(te["factors"]),
           "whole": whole, "last": last,
           "train_s": json.loads((run_dir / "metrics.json").read_text()).get("train_wall_s")}
    # the read-out's noise: other CV seeds, and half the training sequences
    out["readout_seed"] = [_overall(evaluate_latents(tr, te, alignment=dataclasses.replace(align, seed=s), split=split)[0])
                           for s in range(1, n_seeds + 1)]
    rng = np.random.default_rng(0)
    n = len(tr["factors"])
    out["readout_half"] = []
    for _ in range(n_seeds):
        keep = np.sort(rng.choice(n, size=n // 2, replace=False))
        sub = {k: (v[keep] if hasattr(v, "__len__") and len(v) == n and not isinstance(v, str) else v)
               for k, v in tr.items()}
        out["readout_half"].append(_overall(evaluate_latents(sub, te, alignment=align, split=split)[0]))
    # the test sample: bootstrap over trials and over objects
    out["boot_trials"] = bootstrap_overall(res.factors, res.pred, np.arange(res.n_test), n_boot=n_boot).tolist()
    out["boot_objects"] = bootstrap_overall(res.factors, res.pred, res.object_id, n_boot=n_boot).tolist()
    return out


def analyse(args) -> None:
    work = Path(args.work).resolve()
    cache_file = work / "analysis.json"
    done = json.loads(cache_file.read_text()) if cache_file.exists() else {}
    for design, name, _ in plan(args.designs, args.levels):
        run_dir = work / "runs" / design / name
        key = f"{design}/{name}"
        if key in done or not finished(run_dir):
            continue
        print(time.strftime("%H:%M:%S"), "analysing", key, flush=True)
        done[key] = analyse_run(run_dir, args.boot, args.readout_seeds if name == "base" else 0)
        cache_file.write_text(json.dumps(done, indent=1))
    print_tables(done, args.designs, args.levels)
    print_power(done, args.designs, args.levels, args.delta)


def _sd(v) -> float:
    v = np.asarray(v, dtype=float)
    return float(v.std(ddof=1)) if len(v) > 1 else float("nan")


def print_tables(done: dict, designs: list[str], levels: int) -> None:
    print("\n| design | run | train / test trials | whole | last | training s |")
    print("|---|---|---|---|---|---|")
    for design, name, _ in plan(designs, levels):
        r = done.get(f"{design}/{name}")
        if r:
            print(f"| {design} | {name} | {r['n_train']} / {r['n_test']} | {r['whole']:.3f} | {r['last']:.3f} | "
                  f"{r['train_s']:.0f} |")
    print("\nStandard deviation of the test NMSE (whole / last frame) by source. Between runs: over the "
          "levels of one factor, the base run included. Within run: mean over the design's runs.\n")
    print("| design | init | split | data | main | read-out, other CV seed (base run) | read-out on half the training "
          "sequences: change (base run) | "
          "test trials (bootstrap) | test objects (bootstrap) | mean NMSE |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for design in designs:
        rows = {k.split("/", 1)[1]: v for k, v in done.items() if k.startswith(design + "/")}
        if "base" not in rows:
            continue
        cells = []
        for f in FACTORS:
            vals = [rows[n] for n in ["base"] + [f"{f}{lvl}" for lvl in range(1, levels)] if n in rows]
            cells.append(f"{_sd([v['whole'] for v in vals]):.3f} / {_sd([v['last'] for v in vals]):.3f} "
                         f"(n={len(vals)})" if len(vals) > 1 else "-")
        v = rows["base"]  # the read-out's refits, beside the run's own fit
        cells.append(f"{_sd([v['whole']] + [a for a, _ in v['readout_seed']]):.3f} / "
                     f"{_sd([v['last']] + [b for _, b in v['readout_seed']]):.3f}" if v.get("readout_seed") else "-")
        cells.append(f"{np.mean([a for a, _ in v['readout_half']]) - v['whole']:+.3f} / "
                     f"{np.mean([b for _, b in v['readout_half']]) - v['last']:+.3f}" if v.get("readout_half") else "-")
        for comp in ("boot_trials", "boot_objects"):
            sw = np.mean([_sd([a for a, _ in v[comp]]) for v in rows.values()])
            sl = np.mean([_sd([b for _, b in v[comp]]) for v in rows.values()])
            cells.append(f"{sw:.3f} / {sl:.3f}")
        mw = np.mean([v["whole"] for v in rows.values()])
        ml = np.mean([v["last"] for v in rows.values()])
        print(f"| {design} | " + " | ".join(cells) + f" | {mw:.3f} / {ml:.3f} (n={len(rows)}) |")


def seeds_for(sd_d: float, delta: float, n_max: int = 500) -> int | None:
    """The fewest seeds (>= 3) at which a paired difference of standard deviation ``sd_d`` is
    detected at ``delta`` with 80 % power (None: more than ``n_max``)."""
    from embodied_tactile.eval.verdicts import detectable_difference

    for n in range(3, n_max + 1):
        if detectable_difference(sd_d / np.sqrt(n), n - 1) <= delta:
            return n
    return None


def print_power(done: dict, designs: list[str], levels: int, delta: float) -> None:
    """The paired difference between two cells, whole trajectory: its standard deviation lies
    between sqrt(2) x sd(init) (the cells share data and split, and those effects cancel) and
    sqrt(2) x sqrt(v(seed) + sd(data)^2) (nothing cancels), where v(seed), the variance of
    changing the model and split seeds, is the larger of sd(init)^2 + sd(split)^2 and sd(main)^2
    (``main`` changes both at once: it is not added to them; each one-factor sd carries its own
    SGD noise, so the bound over-counts)."""
    from embodied_tactile.eval.verdicts import detectable_difference

    print(f"\nPaired difference of two cells (Overall, whole trajectory): detectable difference at 80 % power, "
          f"and the seeds needed for {delta}\n")
    print("| design | sd of d: best / worst | detectable, 3 seeds | 5 seeds | 10 seeds | seeds for "
          f"{delta}: best / worst |")
    print("|---|---|---|---|---|---|")
    for design in designs:
        rows = {k.split("/", 1)[1]: v for k, v in done.items() if k.startswith(design + "/")}
        sds = {}
        for f in FACTORS:
            vals = [rows[n]["whole"] for n in ["base"] + [f"{f}{lvl}" for lvl in range(1, levels)] if n in rows]
            sds[f] = _sd(vals)
        if not np.isfinite(sds["init"]):
            continue
        best = float(np.sqrt(2) * sds["init"])
        sq = {f: (v * v if np.isfinite(v) else 0.0) for f, v in sds.items()}
        worst = float(np.sqrt(2 * (max(sq["init"] + sq["split"], sq["main"]) + sq["data"])))
        det = [f"{detectable_difference(best / np.sqrt(n), n - 1):.3f} / "
               f"{detectable_difference(worst / np.sqrt(n), n - 1):.3f}" for n in (3, 5, 10)]
        print(f"| {design} | {best:.3f} / {worst:.3f} | " + " | ".join(det) +
              f" | {seeds_for(best, delta) or '> 500'} / {seeds_for(worst, delta) or '> 500'} |")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("command", choices=["train", "analyse"])
    ap.add_argument("--work", required=True, help="folder of the runs and their shared data folder")
    ap.add_argument("--designs", nargs="+", default=["sets4", "sets16"], choices=list(DESIGNS))
    ap.add_argument("--levels", type=int, default=3, help="levels per factor, the base run included")
    ap.add_argument("--boot", type=int, default=500, help="bootstrap resamples of the test trials / objects")
    ap.add_argument("--readout-seeds", type=int, default=2,
                    help="read-out refits of each kind (other CV seed, half the training sequences), base runs only")
    ap.add_argument("--delta", type=float, default=0.03, help="the paired difference the study should detect")
    args = ap.parse_args(argv)
    {"train": train, "analyse": analyse}[args.command](args)


if __name__ == "__main__":
    main()
