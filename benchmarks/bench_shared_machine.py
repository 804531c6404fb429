"""Trainings that share the machine: one training alone against two started together.

    python benchmarks/bench_shared_machine.py --work /tmp/shared                 # the default `python train.py`
    python benchmarks/bench_shared_machine.py --work /tmp/shared -- trainer.max_epochs=1 trainer.limit_train_batches=10
    python benchmarks/bench_shared_machine.py --work /tmp/shared --omp-wait-policy ACTIVE   # OpenMP spinning, for comparison

The scene's data are prepared once first (``embodied-tactile prepare`` with the
same overrides; not timed). Then one ``python train.py`` runs alone, then two start at the
same moment, each in its own run folder under ``--work``, each with the default thread
policy (``threads=auto``: the cores divided among the trainings live on the machine,
re-counted at every epoch, ``run.threads.ThreadShare``) unless ``--threads`` gives a ceiling.
Printed: the CPU (``lscpu`` model name), the cores, the 1-minute load average before and
after each phase, and per training the threads it logged (at start, then each change),
the training phase (``metrics.json`` ``train_wall_s``), the process's wall time and the
ratio of each to the lone training's. The target: each of the pair at most 2.5x the lone
training. Run it on a quiet machine: another user's jobs are measured too.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TARGET = 2.5  # each of two trainings together at most this many times the lone one's wall time
THREADS_LINE = re.compile(r"torch threads: (\d+) \(threads=\S+, (\d+) training")
CHANGE_LINE = re.compile(r"threads (\d+) -> (\d+) \((\d+) training")


def cpu_model() -> str:
    """``lscpu``'s model name (``platform.processor()`` where lscpu is missing)."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        for line in out.splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.SubprocessError):
        pass
    import platform

    return platform.processor() or "unknown CPU"


def train_command(run_dir: Path, data_dir: Path, extra: list[str]) -> list[str]:
    return [sys.executable, str(REPO / "train.py"), f"paths.data_dir={data_dir}", f"hydra.run.dir={run_dir}",
            "resume=false", "logger=none", "plain_progress=true", *extra]


def environment(wait_policy: str | None) -> dict[str, str]:
    """The caller's environment without thread counts (the policy sets them); OMP_WAIT_POLICY
    as asked (None: train.py's own default, threadenv's GOMP_SPINCOUNT)."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env["WANDB_MODE"] = "disabled"
    if wait_policy:
        env["OMP_WAIT_POLICY"] = wait_policy
    return env


def start(run_dir: Path, data_dir: Path, extra: list[str], env: dict[str, str]) -> tuple[subprocess.Popen, float]:
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    log = open(run_dir.parent / f"{run_dir.name}.log", "w")
    proc = subprocess.Popen(train_command(run_dir, data_dir, extra), cwd=REPO, env=env, stdout=log,
                            stderr=subprocess.STDOUT, text=True)
    return proc, time.perf_counter()


def finish(name: str, proc: subprocess.Popen, t0: float, run_dir: Path) -> dict:
    """Wait for one training; its threads, training phase and wall time."""
    code = proc.wait()
    wall = time.perf_counter() - t0
    text = (run_dir.parent / f"{run_dir.name}.log").read_text()
    if code != 0:
        raise SystemExit(f"{name}: train.py exited {code}; see {run_dir.parent / (run_dir.name + '.log')}")
    threads = [m.group(1) for m in THREADS_LINE.finditer(text)] + [m.group(2) for m in CHANGE_LINE.finditer(text)]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    return {"name": name, "threads": " -> ".join(threads) or "?", "train_s": float(metrics["train_wall_s"]),
            "wall_s": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_shared_machine"), help="run folders and logs")
    ap.add_argument("--data-dir", type=Path, default=None, help="the scene's data (default: <work>/data)")
    ap.add_argument("--threads", default=None, help="threads=<n> for every training (a ceiling); default: auto")
    ap.add_argument("--omp-wait-policy", default=None, choices=["PASSIVE", "ACTIVE"],
                    help="OMP_WAIT_POLICY for every training (default: train.py's short spin, threadenv.SPIN_COUNT)")
    ap.add_argument("overrides", nargs="*", help="train.py overrides for every training (after --)")
    args = ap.parse_args()
    data_dir = args.data_dir or args.work / "data"
    extra = list(args.overrides) + ([f"threads={args.threads}"] if args.threads else [])
    env = environment(args.omp_wait_policy)
    from embodied_tactile.run.threads import available_cores

    subprocess.run([sys.executable, "-m", "embodied_tactile.run.prepare_cli", f"paths.data_dir={data_dir}", *extra],
                   cwd=REPO, env=env, check=True, capture_output=True)

    print(f"CPU: {cpu_model()}, {available_cores()} available cores; train.py {' '.join(extra) or '(default)'}; "
          f"OMP_WAIT_POLICY={args.omp_wait_policy or 'train.py default'}")
    stamp = time.strftime("%Y%m%d-%H%M%S")
    loads = {}
    loads["alone"] = [os.getloadavg()[0]]
    rows = [finish("alone", *start(args.work / f"{stamp}-alone", data_dir, extra, env), args.work / f"{stamp}-alone")]
    loads["alone"].append(os.getloadavg()[0])
    loads["together"] = [os.getloadavg()[0]]
    pair = [(f"together {i + 1} of 2", args.work / f"{stamp}-together{i + 1}") for i in range(2)]
    started = [(name, *start(d, data_dir, extra, env), d) for name, d in pair]
    rows += [finish(name, proc, t0, d) for name, proc, t0, d in started]
    loads["together"].append(os.getloadavg()[0])

    lone = rows[0]
    print(f"\n| run | threads (start -> changes) | train_wall_s | vs alone | process wall s | vs alone | load 1-min before / after |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        l0, l1 = loads["alone" if r is lone else "together"]
        print(f"| {r['name']} | {r['threads']} | {r['train_s']:.1f} | {r['train_s'] / lone['train_s']:.2f}x | "
              f"{r['wall_s']:.1f} | {r['wall_s'] / lone['wall_s']:.2f}x | {l0:.2f} / {l1:.2f} |")
    worst = max(r["train_s"] for r in rows[1:]) / lone["train_s"]
    print(f"\nworst of the two together / alone (train_wall_s): {worst:.2f}x "
          f"(target <= {TARGET}x: {'met' if worst <= TARGET else 'NOT met'}); run folders under {args.work}")


if __name__ == "__main__":
    main()
