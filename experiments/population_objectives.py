"""The screen of label-free objectives on the population scene, over the number of training
objects that carry no labels.

    python experiments/population_objectives.py prepare --work WORK                    # the data, once, at the largest N
    python experiments/population_objectives.py train --work WORK --lane 0 --lanes 2   # one lane of the runs (resumes)
    python experiments/population_objectives.py train --work WORK --lane 1 --lanes 2   # beside it, threads=1 each
    python experiments/population_objectives.py evaluate --work WORK                   # validation and test sides (resumes)
    python experiments/population_objectives.py analyse --work WORK [--json OUT]       # the tables and the verdict

Objectives (``OBJECTIVES``, each a recipe of configs/recipe/ on ``experiment=population``):
``context`` (the population default), ``invariance`` (+ VICReg between y of two touches of one
object), ``physical`` (+ y of one touch predicting the hand-crafted features of another; it
imports the hand-crafted reader's bias) and ``both``. Each is trained at every N of
``--sizes`` (N = 256, 1,024 and 4,096 training objects: the population's 256 labelled
training objects and N - 256 unlabelled objects after them, ``data.n_unlabelled_objects``)
with every seed of ``--seeds`` (0, 1, 2). No objective reads a property label: the labels of
the unlabelled objects are NaN in the data, those of the labelled ones are read by the KRR
read-out only, which is fitted on the same 256 labelled training objects and scored on the
same 32 validation and 64 test objects at every N. The optimiser-step budget is the
population default's (16 epochs of 480 windows) at every N: more objects, not more steps.

The terms' weights are the recipes' (100 each, per sequence: a start, not a choice; a
smoke run at initialisation read a target NLL of about 4e5, KL_y about 13 and an unweighted
VICReg term about 2); ``--weight W`` trains the invariance, physical and both objectives at W
instead, in folders of their own (``<objective>-wW``), screened by the same rule.

Every run is ``python train.py threads=1`` with one KRR check (``SCREEN_CHECKS``) in ``WORK/runs/<objective>/n<N>/seed<s>`` with
one data folder ``WORK/data``. ``prepare`` simulates and caches the largest N first: the
smaller scenes read subsets of the same raw file and caches (a scene prepared first at a
smaller N would build caches of its own, then be rebuilt for the larger one). ``evaluate``
runs evaluate.py on the validation objects (``held_out=val``, no baseline) and on the test
objects (``baselines=[untrained,handcrafted,hybrid,mean]``; the hybrid row is KRR on
[hand-crafted features, y], beside y alone, never in its place).

Selection rule (written before any run; choices on the validation objects only):

* At each N, an objective is adopted over ``context`` only if its validation last-frame NMSE
  (mean over factors, the run's own read-out) is lower than the ``context`` run's of the same
  seed in every seed, and the mean of those paired differences exceeds the standard deviation
  (over seeds) of the ``context`` runs' validation last-frame NMSE.
* Where several objectives pass, the one with the lowest mean validation last-frame NMSE is
  adopted; where none passes, ``context`` stays.
* The default of the population scene (256 labelled objects, no unlabelled ones) is decided
  at N = 256; the larger N give the learning curve, on which nothing is selected. The test
  objects' numbers are read only after the choice, and reported with 95 % intervals over seeds.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: objective -> train.py overrides on top of experiment=population
OBJECTIVES: dict[str, list[str]] = {
    "context": ["recipe=context"],
    "invariance": ["recipe=context_invariance"],
    "physical": ["recipe=context_physical"],
    "both": ["recipe=context_both"],
}
#: the population's labelled training objects (configs/experiment/population.yaml)
LABELLED = 256
#: the population default's objective (configs/experiment/population.yaml's recipe): its rows at
#: N = LABELLED are marked ``population_default`` (the main job's closing line quotes them)
DEFAULT_OBJECTIVE = "context"
SIDES = {"val": "evaluation-val", "test": "evaluation"}
TEST_BASELINES = "baselines=[untrained,handcrafted,hybrid,mean]"
#: a toy size for a smoke run that shows the script works end to end and measures nothing
SMOKE = ["data.n_val_objects=2", "data.n_test_objects=2", "trainer.max_epochs=1", "data.windows_per_epoch=8",
         "data.batch_size=4", "alignment.cv=2"]


def plan(objectives: list[str], sizes: list[int], seeds: list[int], labelled: int,
         weight: float | None = None) -> list[tuple[str, int, int, list[str]]]:
    """(objective, N, seed, overrides) of every run; N counts the training objects, the
    ``labelled`` ones and N - labelled unlabelled ones. ``weight``: the label-free terms'
    weight instead of the recipes' (the objective then reads ``<objective>-w<weight>``)."""
    out = []
    for n in sizes:
        if n < labelled:
            raise SystemExit(f"--sizes: N={n} is below the {labelled} labelled training objects")
        for seed in seeds:
            for obj in objectives:
                overrides = ["experiment=population", *OBJECTIVES[obj], f"seed={seed}",
                             f"data.n_objects={labelled}", f"data.n_unlabelled_objects={n - labelled}"]
                name = obj
                if weight is not None and obj != "context":
                    keys = {"invariance": ["invariance"], "physical": ["physical"],
                            "both": ["invariance", "physical"]}[obj]
                    overrides += [f"model.context.{k}={weight}" for k in keys]
                    name = f"{obj}-w{weight:g}"
                out.append((name, n, seed, overrides))
    return out


def run_dir(work: Path, objective: str, n: int, seed: int) -> Path:
    return work / "runs" / objective / f"n{n}" / f"seed{seed}"


def finished(path: Path) -> bool:
    m = path / "metrics.json"
    return m.exists() and json.loads(m.read_text()).get("status") == "finished"


#: the KRR checks during training draw the error over training time and decide nothing here (the
#: rule reads evaluate.py's validation side): one check, on the final weights, and no row at t = 0.
#: At N = 256 a check took 254 s against 35 s per epoch (2 lanes, Intel Xeon 2.5 GHz, 2026-11-28),
#: so the population default's 8 checks and its t = 0 row would be most of a run's time.
SCREEN_CHECKS = ["callbacks.krr_alignment.initial=false", "callbacks.krr_alignment.points=1"]


def _common(work: Path, smoke: bool) -> list[str]:
    large = ["data.allow_large_population=true"]
    return ["threads=1", "logger=none", f"paths.data_dir={work / 'data'}", *large, *SCREEN_CHECKS,
            *(SMOKE if smoke else [])]


def _run(cmd: list[str]) -> int:
    print(time.strftime("%H:%M:%S"), " ".join(cmd[1:]), flush=True)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, env=dict(os.environ, WANDB_MODE="disabled"), capture_output=True, text=True)
    print(f"  rc {proc.returncode} in {time.perf_counter() - t0:.0f} s", flush=True)
    if proc.returncode != 0:
        print(proc.stderr[-2000:], flush=True)
    return proc.returncode


def prepare(args) -> int:
    """The data of the largest N (every smaller scene reads subsets of it)."""
    work = Path(args.work).resolve()
    n = max(args.sizes)
    cmd = [sys.executable, "-m", "embodied_tactile", "prepare", "experiment=population",
           f"data.n_objects={args.labelled}", f"data.n_unlabelled_objects={n - args.labelled}",
           *[o for o in _common(work, args.smoke) if not o.startswith(("threads", "logger", "callbacks"))]]
    return _run(cmd)


def train(args) -> int:
    work = Path(args.work).resolve()
    worst = 0
    for i, (obj, n, seed, overrides) in enumerate(plan(args.objectives, args.sizes, args.seeds, args.labelled, args.weight)):
        if i % args.lanes != args.lane:
            continue
        out = run_dir(work, obj, n, seed)
        if finished(out):
            continue
        worst = max(worst, _run([sys.executable, str(REPO / "train.py"), *_common(work, args.smoke),
                                 f"hydra.run.dir={out}", *overrides]))
    return worst


def evaluate(args) -> int:
    work = Path(args.work).resolve()
    worst = 0
    extra = ["alignment.cv=2"] if args.smoke else []
    for obj, n, seed, _ in plan(args.objectives, args.sizes, args.seeds, args.labelled, args.weight):
        out = run_dir(work, obj, n, seed)
        if not finished(out):
            continue
        for side, folder in SIDES.items():
            if (out / folder / "results.json").exists():
                continue
            what = ["held_out=val", "baselines=[]"] if side == "val" else [TEST_BASELINES]
            worst = max(worst, _run([sys.executable, str(REPO / "evaluate.py"), str(out), *what, "umap=false",
                                     "figures=false", "print_tables=false", *extra]))
    return worst


# ----------------------------------------------------------------------------- analysis
def scores(work: Path, objectives: list[str], sizes: list[int], seeds: list[int], labelled: int,
           weight: float | None = None) -> list[dict]:
    """One row per run, side and reader: last frame and whole trajectory (mean over factors), and
    whether the run is the population default as configured."""
    rows = []
    for obj, n, seed, _ in plan(objectives, sizes, seeds, labelled, weight):
        for side, folder in SIDES.items():
            path = run_dir(work, obj, n, seed) / folder / "results.json"
            if not path.exists():
                continue
            for r in json.loads(path.read_text())["runs"]:
                rows.append({"objective": obj, "n": n, "seed": seed, "side": side, "reader": r["method"],
                             "last": float(r["nmse_last_step_overall"]), "whole": float(r["nmse_trajectory_overall"]),
                             "population_default": obj == DEFAULT_OBJECTIVE and n == labelled})
    return rows


def _pick(rows, **match) -> dict[int, dict]:
    """seed -> row of the rows matching every key."""
    return {r["seed"]: r for r in rows if all(r[k] == v for k, v in match.items())}


def _summary(values: list[float]) -> str:
    """mean [95 % interval over seeds, t-based] or the single value."""
    if not values:
        return "–"
    if len(values) == 1:
        return f"{values[0]:.3f} (1 seed)"
    from scipy import stats

    m, sd = statistics.fmean(values), statistics.stdev(values)
    h = stats.t.ppf(0.975, len(values) - 1) * sd / len(values) ** 0.5
    return f"{m:.3f} [{m - h:.3f}, {m + h:.3f}]"


def verdict(rows: list[dict], n: int, objectives: list[str]) -> tuple[str, list[str]]:
    """The selection rule of the module docstring at one N: (adopted objective, reasons)."""
    base = _pick(rows, objective="context", n=n, side="val", reader="latent_filter")
    notes, passing = [], []
    if len(base) < 2:
        return "context", [f"N={n}: fewer than 2 seeds of context on the validation objects: no choice"]
    sd = statistics.stdev(r["last"] for r in base.values())
    for obj in objectives:
        if obj == "context":
            continue
        other = _pick(rows, objective=obj, n=n, side="val", reader="latent_filter")
        seeds = sorted(set(base) & set(other))
        if len(seeds) < len(base):
            notes.append(f"N={n} {obj}: {len(seeds)} of {len(base)} seeds evaluated: not judged")
            continue
        diffs = [base[s]["last"] - other[s]["last"] for s in seeds]
        ok = all(d > 0 for d in diffs) and statistics.fmean(diffs) > sd
        notes.append(f"N={n} {obj}: lower in {sum(d > 0 for d in diffs)}/{len(seeds)} seeds, mean difference "
                     f"{statistics.fmean(diffs):+.3f} against the context seeds' sd {sd:.3f}: "
                     + ("passes" if ok else "does not pass"))
        if ok:
            passing.append((statistics.fmean(other[s]["last"] for s in seeds), obj))
    return (min(passing)[1] if passing else "context"), notes


def tables(rows: list[dict], objectives: list[str], sizes: list[int]) -> str:
    lines = []
    for side in SIDES:
        head = ["objective", "reader"] + [f"N={n} last" for n in sizes] + [f"N={n} whole" for n in sizes]
        lines += [f"\n{side} objects (mean over seeds [95 % interval])\n", "| " + " | ".join(head) + " |",
                  "|---" * len(head) + "|"]
        readers = sorted({r["reader"] for r in rows if r["side"] == side}, key=lambda m: (m != "latent_filter", m))
        for obj in objectives:
            for reader in readers:
                cells = [[r[k] for r in rows if r["objective"] == obj and r["side"] == side and r["reader"] == reader
                          and r["n"] == n] for k in ("last", "whole") for n in sizes]
                if any(cells):
                    lines.append(f"| {obj} | {reader} | " + " | ".join(_summary(c) for c in cells) + " |")
    return "\n".join(lines)


def analyse(args) -> int:
    work = Path(args.work).resolve()
    rows = scores(work, args.objectives, args.sizes, args.seeds, args.labelled, args.weight)
    names = list(dict.fromkeys(r["objective"] for r in rows))
    if not rows:
        print(f"no evaluated run under {work / 'runs'}", file=sys.stderr)
        return 1
    print(tables(rows, names, args.sizes))
    print("\nselection (validation objects, last frame):")
    for n in args.sizes:
        if n != args.labelled:  # the rule decides the default at N = labelled only
            print(f"  N={n}: a point of the learning curve; nothing is selected there")
            continue
        chosen, notes = verdict(rows, n, names)
        for line in notes:
            print("  " + line)
        print(f"  N={n}: adopted {chosen}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("command", choices=["prepare", "train", "evaluate", "analyse"])
    ap.add_argument("--work", required=True, help="folder of the runs and their shared data folder")
    ap.add_argument("--objectives", nargs="+", default=list(OBJECTIVES), choices=list(OBJECTIVES))
    ap.add_argument("--sizes", nargs="+", type=int, default=[256, 1024, 4096],
                    help="training objects N: the labelled ones and N - labelled unlabelled ones")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--labelled", type=int, default=LABELLED, help="labelled training objects (the read-out's)")
    ap.add_argument("--lane", type=int, default=0)
    ap.add_argument("--lanes", type=int, default=1)
    ap.add_argument("--smoke", action="store_true",
                    help="a toy scene (2 validation and 2 test objects, 1 epoch of 8 windows): measures nothing")
    ap.add_argument("--weight", type=float, default=None,
                    help="the label-free terms' weight instead of the recipes' (runs in folders of their own)")
    ap.add_argument("--json", type=Path, default=None, help="analyse: every row as JSON")
    args = ap.parse_args(argv)
    if not 0 <= args.lane < args.lanes:
        ap.error(f"--lane must be in [0, --lanes), got {args.lane} of {args.lanes}")
    return {"prepare": prepare, "train": train, "evaluate": evaluate, "analyse": analyse}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
