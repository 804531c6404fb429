"""Wall time of evaluate.py on a 24-run multirun (the paper's ablation, debug=fast scenes).

    python benchmarks/bench_evaluate.py                          # builds the multirun, then times
    python benchmarks/bench_evaluate.py --multirun <folder>      # times an existing multirun
    python benchmarks/bench_evaluate.py --work /tmp/bench --repeat 2 -- umap=false
    python benchmarks/bench_evaluate.py --multirun <folder> modality=multi_l skin=soft primitive=pressing  # one job
    python benchmarks/bench_evaluate.py --multirun logs/train/runs/<run>   # one run folder (all baselines)

Building: ``python train.py -m sweep=ablation debug=fast paths.data_dir=<work>/data
hydra.sweep.dir=<work>/multi`` (8 modality x skin combos x 3 primitives; the tiny scene of
each skin x primitive is simulated / preprocessed once into the shared data folder).
Timing: ``python evaluate.py <multirun> print_tables=false [extra options]`` in a fresh
process (imports, numba/UMAP compilation and the report included), best of ``--repeat``.
Prints one table: runs, wall s, per-run s, peak RSS of the evaluate.py process (its own
``wait4`` rusage, the 3 GB target whatever the number of runs) and the per-stage
times evaluate.py recorded. ``--train-args`` builds a heavier scene (e.g. the default
scene's 128 trials: ``--train-args trainer.max_epochs=1``) instead of ``debug=fast``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def build(work: Path, train_args: list[str] | None = None) -> tuple[Path, float]:
    multi = work / "multi"
    t0 = time.perf_counter()
    scene = ["debug=fast"] if train_args is None else list(train_args)
    subprocess.run([sys.executable, str(REPO / "train.py"), "-m", "sweep=ablation", *scene,
                    f"paths.data_dir={work / 'data'}", f"hydra.sweep.dir={multi}"],
                   cwd=REPO, check=True, env=dict(os.environ, WANDB_MODE="disabled"),
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return multi, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--multirun", type=Path, help="existing multirun folder (skip building)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_evaluate"))
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--train-args", nargs="*", default=None, help="train.py overrides of the built sweep "
                    "(default: debug=fast)")
    ap.add_argument("extra", nargs="*", help="evaluate.py options (key=value), run selectors too (primitive=pressing)")
    args = ap.parse_args()
    build_s = None
    if args.multirun is None:
        args.work.mkdir(parents=True, exist_ok=True)
        args.multirun, build_s = build(args.work, args.train_args)
    n_jobs = 1 if (args.multirun / "config_resolved.yaml").exists() else sum(  # a run folder: one job
        1 for d in args.multirun.iterdir() if (d / "config_resolved.yaml").exists())
    walls, peaks = [], []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        with open(args.work / "evaluate.log", "w") as log:
            p = subprocess.Popen([sys.executable, str(REPO / "evaluate.py"), str(args.multirun), "print_tables=false",
                                  *args.extra], cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
            _, status, usage = os.wait4(p.pid, 0)  # this child's own rusage (not the training jobs')
        walls.append(time.perf_counter() - t0)
        peaks.append(usage.ru_maxrss * 1024)  # Linux: KiB
        if os.waitstatus_to_exitcode(status):
            sys.exit(f"evaluate.py failed, see {args.work / 'evaluate.log'}")
    out = [line.rsplit("-> ", 1)[1].strip() for line in (args.work / "evaluate.log").read_text().splitlines()
           if line.startswith("evaluated ") and "-> " in line]
    ev = json.loads((Path(out[-1]) if out else args.multirun / "evaluation").joinpath("evaluation.json").read_text())
    runs = len(ev["runs"])
    wall = min(walls)
    stages = {k: sum(r["timings"].get(k, 0.0) for r in ev["runs"])
              for k in ("data_s", "load_and_infer_s", "handcrafted_s", "gru_s", "mean_s")}
    print(f"evaluate.py on {args.multirun} ({n_jobs} job folders, {os.cpu_count()} cores, "
          f"options: {' '.join(args.extra) or 'defaults'}, baselines {ev['baselines']})")
    if build_s is not None:
        print(f"building the multirun took {build_s:.0f} s")
    print()
    print("| runs | wall s | per-run s | peak RSS GB | runs loop s | report s | data s | load+infer s | handcrafted s | gru s | DataModules reused |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print(f"| {runs} | {wall:.1f} | {wall / max(runs, 1):.2f} | {max(peaks) / 1e9:.2f} | {ev['timings']['evaluate_s']:.1f} | "
          f"{ev['timings']['report_s']:.1f} | {stages['data_s']:.1f} | {stages['load_and_infer_s']:.1f} | "
          f"{stages['handcrafted_s']:.1f} | {stages['gru_s']:.1f} | {ev['datamodule_reuse']} |")


if __name__ == "__main__":
    main()
