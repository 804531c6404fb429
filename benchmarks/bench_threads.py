"""Thread policy under concurrency (docs/experiments/speed_levers.md, target 3): a lone training job against two
concurrent ones, each process with the threads ``run.threads`` gives it.

Each job is a subprocess that applies the policy exactly as ``train.py`` does
(``threads.thread_budget("auto", threads.concurrent_jobs(n_jobs))`` -> ``threadenv.set_threads``:
``auto`` = available cores / concurrent jobs; OpenMP's spin count as train.py's, ``threadenv``:
GOMP_SPINCOUNT=1000 unless it or OMP_WAIT_POLICY is set in the environment), builds a Latent Filter and times training steps
(``bench_step_ceiling.step``: ELBO, backward, Adam) after one warm-up step. Concurrent jobs
wait for each other after the warm-up (a file barrier), so their timed steps overlap.
Printed: every step time per job, the median, the ratio of each concurrent job's median to
the lone job's (target: at most 2.2x), and the load average before and after each run
(the box may be shared: the ratio then measures the other jobs too).

    python benchmarks/bench_threads.py [--modality multi_l] [--batch 16] [--seq 100] [--steps 5]
    python benchmarks/bench_threads.py --batch 48 --seq 300   # paper shapes
    python benchmarks/bench_threads.py --threads 2           # a fixed count, bypassing the policy (oversubscribed)
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def worker(args: argparse.Namespace) -> None:
    from embodied_tactile.run import threadenv, threads as share

    threads = threadenv.set_threads(share.thread_budget("auto", share.concurrent_jobs(args.jobs)) if args.threads == "auto"
                                  else int(args.threads))  # a fixed count bypasses the policy (its ceiling too)
    import contextlib

    import torch

    from steps import make_batch, step, training_module
    from embodied_tactile.model import LatentFilter

    torch.manual_seed(0)
    m = LatentFilter(args.modality)
    batch = make_batch(m.n_channels, args.batch, args.seq)
    module = training_module(m)
    opt = torch.optim.Adam(m.parameters(), lr=1e-5)
    step(module, batch, opt, contextlib.nullcontext)  # warm-up
    barrier = Path(args.barrier)
    (barrier / f"ready-{os.getpid()}").touch()
    while len(list(barrier.glob("ready-*"))) < args.jobs:
        time.sleep(0.01)
    c0 = time.process_time()
    ts = [step(module, batch, opt, contextlib.nullcontext) for _ in range(args.steps)]
    print(json.dumps({"threads": threads, "torch_threads": torch.get_num_threads(), "steps": ts,
                      "cpu_s": time.process_time() - c0}), flush=True)


def run_jobs(n: int, args: argparse.Namespace) -> tuple[list[dict], tuple[float, float]]:
    """Start ``n`` jobs at once; their results and the 1-min load average before / after."""
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench_threads_") as barrier:
        cmd = [sys.executable, __file__, "--worker", "--jobs", str(n), "--barrier", barrier, "--modality", args.modality,
               "--batch", str(args.batch), "--seq", str(args.seq), "--steps", str(args.steps), "--threads", str(args.threads)]
        env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
        procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=env) for _ in range(n)]
        outs = []
        for p in procs:
            out, _ = p.communicate()
            if p.returncode:
                raise SystemExit(f"job failed (exit {p.returncode})")
            outs.append(json.loads(out.strip().splitlines()[-1]))
    return outs, (load0, os.getloadavg()[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--modality", default="multi_l")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seq", type=int, default=100)
    ap.add_argument("--steps", type=int, default=5, help="timed steps per job (after one warm-up)")
    ap.add_argument("--threads", default="auto", help="auto (the policy) or a fixed count for every job (no policy)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--jobs", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--barrier", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args)
        return

    from embodied_tactile.run.threads import available_cores

    print(f"{args.modality}, B={args.batch} T={args.seq} 28x28, {args.steps} timed steps per job, threads={args.threads}, "
          f"{available_cores()} available cores, os.cpu_count() {os.cpu_count()}")
    print(f"uptime before: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}\n")
    lone, load_lone = run_jobs(1, args)
    pair, load_pair = run_jobs(2, args)
    ref = statistics.median(lone[0]["steps"])
    print(f"| {'run':<22} | {'threads':>7} | {'step times (s)':<40} | {'median s':>8} | {'vs lone':>7} | {'load 1-min before/after':>23} |")
    print(f"|{'-' * 24}|{'-' * 9}|{'-' * 42}|{'-' * 10}|{'-' * 9}|{'-' * 25}|")
    rows = [("lone job", lone[0], load_lone)] + [(f"concurrent job {i + 1} of 2", r, load_pair) for i, r in enumerate(pair)]
    for name, r, (l0, l1) in rows:
        med = statistics.median(r["steps"])
        times = ", ".join(f"{t:.2f}" for t in r["steps"])
        print(f"| {name:<22} | {r['torch_threads']:>7} | {times:<40} | {med:8.2f} | {med / ref:6.2f}x | {l0:10.1f} / {l1:<10.1f} |")
    worst = max(statistics.median(r["steps"]) for r in pair) / ref
    print(f"\nworst concurrent / lone median step: {worst:.2f}x (target <= 2.2x: {'met' if worst <= 2.2 else 'NOT met'})")
    print(f"uptime after: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")


if __name__ == "__main__":
    main()
