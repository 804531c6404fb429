"""Cost of one KRR check's latent inference (docs/experiments/speed_levers.md, target 5: the
callback is almost all this pass), by how the sequences are batched.

    python benchmarks/bench_callback_inference.py [--train 80] [--held-out 32] [--seq 300] [--rounds 5]

The default run's check infers its 80 training and 32 held-out whole trials (300 frames,
multi_l). ``per split`` batches each split on its own (the callback before: batches of up
to 64 -> 64 + 16 and 32); ``joint`` merges both into batches of up to 128 (the callback
now: one batch of 112), so the recursion's Python loop runs once over the frames. Random
inputs and an untrained network (the cost does not depend on the values); rounds are
interleaved; the table prints the median and min seconds per check.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import torch

from embodied_tactile.model.latent_filter import LatentFilter
from embodied_tactile.run.threadenv import set_threads


def split_sizes(n: int, size: int) -> list[int]:
    return [min(size, n - i) for i in range(0, n, size)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--modality", default="multi_l")
    ap.add_argument("--train", type=int, default=80)
    ap.add_argument("--held-out", type=int, default=32)
    ap.add_argument("--seq", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    set_threads(args.threads)
    torch.manual_seed(0)
    net = LatentFilter(args.modality).eval()
    n = args.train + args.held_out
    obs = torch.rand(n, args.seq, net.n_channels, 28, 28)
    actions = torch.randn(n, args.seq, net.n_a)
    layouts = {
        "per split, batches <= 64 (before)": split_sizes(args.train, 64) + split_sizes(args.held_out, 64),
        "joint, batches <= 128 (now)": split_sizes(n, 128),
    }
    times: dict[str, list[float]] = {k: [] for k in layouts}
    for _ in range(args.rounds):
        for name, sizes in layouts.items():
            i, t0 = 0, time.perf_counter()
            for b in sizes:
                net.infer_latents(obs[i:i + b], actions[i:i + b])
                i += b
            times[name].append(time.perf_counter() - t0)
    base = statistics.median(times[next(iter(layouts))])
    print(f"\nOne check's inference: {args.train} + {args.held_out} sequences x {args.seq} frames, {args.modality}, "
          f"{args.threads} threads, {args.rounds} interleaved rounds")
    print("| batching | batches | median s | min s | vs before |")
    print("|---|---|---|---|---|")
    for name, sizes in layouts.items():
        med = statistics.median(times[name])
        print(f"| {name} | {' + '.join(map(str, sizes))} | {med:.3f} | {min(times[name]):.3f} | {base / med:.2f}x |")
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
