"""Wall time of evaluate.py on a 24-run multirun (the paper's ablation, debug=fast scenes).

    python benchmarks/bench_evaluate.py                          # builds the multirun, then times
    python benchmarks/bench_evaluate.py --multirun <folder>      # times an existing multirun
    python benchmarks/bench_evaluate.py --work /tmp/bench --repeat 2 -- umap=false

Building: ``python train.py -m sweep=ablation debug=fast paths.data_dir=<work>/data
hydra.sweep.dir=<work>/multi`` (8 modality x skin combos x 3 primitives; the tiny scene of
each skin x primitive is simulated / preprocessed once into the shared data folder).
Timing: ``python evaluate.py <multirun> print_tables=false [extra options]`` in a fresh
process (imports, numba/UMAP compilation and the report included), best of ``--repeat``.
Prints one table: runs, wall s, per-run s (+ the per-stage times evaluate.py recorded).
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


def build(work: Path) -> tuple[Path, float]:
    multi = work / "multi"
    t0 = time.perf_counter()
    subprocess.run([sys.executable, str(REPO / "train.py"), "-m", "sweep=ablation", "debug=fast",
                    f"paths.data_dir={work / 'data'}", f"hydra.sweep.dir={multi}"],
                   cwd=REPO, check=True, env=dict(os.environ, WANDB_MODE="disabled"),
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return multi, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--multirun", type=Path, help="existing multirun folder (skip building)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_evaluate"))
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("extra", nargs="*", help="evaluate.py options (key=value)")
    args = ap.parse_args()
    build_s = None
    if args.multirun is None:
        args.work.mkdir(parents=True, exist_ok=True)
        args.multirun, build_s = build(args.work)
    n_jobs = sum(1 for d in args.multirun.iterdir() if (d / "config_resolved.yaml").exists())
    walls = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, str(REPO / "evaluate.py"), str(args.multirun), "print_tables=false",
                            *args.extra], cwd=REPO, capture_output=True, text=True)
        walls.append(time.perf_counter() - t0)
        if p.returncode:
            sys.exit(f"evaluate.py failed:\n{p.stderr[-3000:]}")
    ev = json.loads((args.multirun / "evaluation" / "evaluation.json").read_text())
    runs = len(ev["runs"])
    wall = min(walls)
    stages = {k: sum(r["timings"].get(k, 0.0) for r in ev["runs"])
              for k in ("data_s", "load_and_infer_s", "handcrafted_s", "gru_s", "mean_s")}
    print(f"evaluate.py on {args.multirun} ({n_jobs} job folders, {os.cpu_count()} cores, "
          f"options: {' '.join(args.extra) or 'defaults'}, baselines {ev['baselines']})")
    if build_s is not None:
        print(f"building the multirun took {build_s:.0f} s")
    print()
    print("| runs | wall s | per-run s | runs loop s | report s | data s | load+infer s | handcrafted s | gru s | DataModules reused |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    print(f"| {runs} | {wall:.1f} | {wall / max(runs, 1):.2f} | {ev['timings']['evaluate_s']:.1f} | "
          f"{ev['timings']['report_s']:.1f} | {stages['data_s']:.1f} | {stages['load_and_infer_s']:.1f} | "
          f"{stages['handcrafted_s']:.1f} | {stages['gru_s']:.1f} | {ev['datamodule_reuse']} |")


if __name__ == "__main__":
    main()
