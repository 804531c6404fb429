"""What the population scene costs: data preparation of N objects, and training time beside
the embedded default scene's.

1. Data preparation: ``TactileDataModule.prepare_data`` of the population scene (soft,
   pressing, actions 6 and 14; N training + 32 validation + 64 test objects) into a new,
   empty folder: simulation, raw file, preprocessing cache. Wall time and CPU time (this
   process and its workers).
2. Training: ``train.py`` of the embedded default scene and of ``experiment=population``,
   one after the other, each with ``trainer.max_epochs=E`` on data prepared beforehand
   (untimed), reading ``train_wall_s`` (fitting, periodic checks included, data preparation
   excluded) from each run's metrics.json, and the fit alone (the KRR checks' own time
   excluded) from its krr_history.jsonl.

    python benchmarks/bench_population_scene.py --work /tmp/popbench            # N = 512, E = 4
    python benchmarks/bench_population_scene.py --work /tmp/popbench --n-objects 64 --epochs 2

Both scenes train 30 optimiser steps of 16 windows per epoch; the population scene checks
on 32 validation objects and aligns up to 256 training sequences per KRR check. Run it on
an otherwise idle machine. Measured results: docs/experiments/population_scene_cost.md.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def cpu_seconds() -> float:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def prepare(data_dir: Path, n_objects: int, workers: int) -> dict:
    from embodied_tactile.data.datamodule import TactileDataModule

    dm = TactileDataModule.from_config(data_dir=str(data_dir), objects="population", n_objects=n_objects, actions=[6, 14],
                           skin="soft", primitive="pressing", split="object", sim_workers=workers,
                           preprocess_workers=workers)
    c0, t0 = cpu_seconds(), time.perf_counter()
    dm.prepare_data()
    wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
    n_trials = 2 * (n_objects + 32 + 64)
    return {"trials": n_trials, "wall_s": wall, "cpu_s": cpu}


def train(run_dir: Path, data_dir: Path, epochs: int, overrides: list[str]) -> tuple[float, float]:
    """(train_wall_s, the fit alone): the fit is the last KRR check's ``train_wall_time_s``,
    training minus the alignment checks' own time."""
    cmd = [sys.executable, str(ROOT / "train.py"), *overrides, f"trainer.max_epochs={epochs}",
           f"paths.data_dir={data_dir}", f"hydra.run.dir={run_dir}", "logger=csv"]
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    last = (run_dir / "krr_history.jsonl").read_text().splitlines()[-1]
    return (float(json.loads((run_dir / "metrics.json").read_text())["train_wall_s"]),
            float(json.loads(last)["train_wall_time_s"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True, help="an empty or new folder for data and runs (removed at the end)")
    ap.add_argument("--n-objects", type=int, default=512)
    ap.add_argument("--epochs", type=int, default=4)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--keep", action="store_true", help="keep the work folder")
    args = ap.parse_args()
    work = Path(args.work)
    if work.exists() and any(work.iterdir()):
        ap.error(f"--work {work} is not empty")
    try:
        p = prepare(work / "data", args.n_objects, args.workers)
        print(f"| population data preparation, {args.n_objects} training objects | trials | wall s | CPU s | trials/s (wall) |")
        print("|---|---|---|---|---|")
        print(f"| simulate + write + preprocess + cache, {args.workers} workers | {p['trials']} | {p['wall_s']:.0f} | "
              f"{p['cpu_s']:.0f} | {p['trials'] / p['wall_s']:.1f} |")
        scenes = (("embedded default", []),
                  (f"experiment=population (n_objects {args.n_objects})",
                   ["experiment=population", f"data.n_objects={args.n_objects}"]))
        times = []
        for i, (_, over) in enumerate(scenes):  # prepare each scene's data untimed, then time training
            subprocess.run([sys.executable, str(ROOT / "train.py"), *over, "trainer.max_epochs=1",
                            "trainer.limit_train_batches=1", f"paths.data_dir={work / 'data'}",
                            f"hydra.run.dir={work / f'warm{i}'}", "logger=csv"], check=True, cwd=ROOT,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for i, (_, over) in enumerate(scenes):
            times.append(train(work / f"run{i}", work / "data", args.epochs, over))
        print(f"\n| scene ({args.epochs} epochs of 30 steps) | train_wall_s | ratio | fit alone, checks excluded s | ratio |")
        print("|---|---|---|---|---|")
        for (name, _), (t, fit) in zip(scenes, times):
            print(f"| {name} | {t:.0f} | {t / times[0][0]:.2f} | {fit:.0f} | {fit / times[0][1]:.2f} |")
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
