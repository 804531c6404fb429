"""The training loader of a scene: milliseconds per batch, process CPU and wall
(docs/experiments/speed_levers.md, "The training loader").

    python benchmarks/bench_loader.py [--epochs 3] [--rounds 3] [overrides ...]

Builds the scene ``python train.py [overrides]`` trains (its data prepared as train.py
prepares it) and iterates its training loader for ``--epochs`` epochs per mode, the modes
interleaved over ``--rounds`` rounds; the table prints the median per batch. Modes:

  cached   the loader as it is: each (field, trial) HDF5 dataset looked up once per open file
  lookup   the same loader with the lookup by name at every read (the code before the cache)

Both read the same rows (the window draws come from torch's RNG, seeded per round).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time

import embodied_tactile.run.threadenv  # noqa: F401  train.py's OpenMP settings, before torch loads
import torch
from hydra.utils import instantiate

from embodied_tactile.data import datamodule as dm_module
from embodied_tactile.run.training import compose
from embodied_tactile.run.threadenv import set_threads


def _lookup_every_time(self, h, fld, tr):
    return h[fld]["trials"][tr.name][fld]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("overrides", nargs="*", help="train.py overrides of the scene (key=value)")
    args = ap.parse_args()
    set_threads(args.threads)
    with tempfile.TemporaryDirectory() as run_dir:
        cfg = compose(list(args.overrides), run_dir)
        dm = instantiate(cfg.data)
        dm.prepare_data()
        dm.setup("fit")
        cached = dm_module.TactileSequenceDataset._dataset
        modes = {"cached": cached, "lookup": _lookup_every_time}
        per_batch: dict[str, tuple[list[float], list[float]]] = {m: ([], []) for m in modes}
        batches = 0
        for r in range(args.rounds):
            for name, fn in modes.items():
                dm_module.TactileSequenceDataset._dataset = fn
                torch.manual_seed(r)
                c0, w0 = time.process_time(), time.perf_counter()
                batches = sum(1 for _ in range(args.epochs) for _ in dm.train_dataloader())
                cpu, wall = time.process_time() - c0, time.perf_counter() - w0
                per_batch[name][0].append(1000 * cpu / batches)
                per_batch[name][1].append(1000 * wall / batches)
        dm_module.TactileSequenceDataset._dataset = cached
    print(f"\nTraining loader: {batches} batches per mode and round ({args.epochs} epochs), {args.rounds} rounds, "
          f"{torch.get_num_threads()} torch thread(s), num_workers {cfg.data.num_workers}; "
          f"{platform.processor() or platform.machine()}, load {os.getloadavg()[0]:.1f}")
    print("| mode | CPU ms / batch (median) | wall ms / batch (median) | CPU vs lookup |")
    print("|---|---|---|---|")
    base = statistics.median(per_batch["lookup"][0])
    for name, (cpu, wall) in per_batch.items():
        print(f"| {name} | {statistics.median(cpu):.2f} | {statistics.median(wall):.2f} | "
              f"{base / statistics.median(cpu):.2f}x |")


if __name__ == "__main__":
    main()
