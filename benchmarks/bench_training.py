"""Latent Filter training throughput and online filtering latency (CPU).

For every modality: sequences/s of one training step (forward + backward + Adam step)
of the batched model (encoders/decoders over all B*T frames in one call, only the
LSTM/transition recursion in a Python loop) against a naive reference that runs the
encoder and decoder inside the time loop, with the same weights, in the same run.
Then the median latency of ``filter_step`` for multi_l at batch 1 on one thread.

    python benchmarks/bench_training.py            # paper shapes B=48, T=300
    python benchmarks/bench_training.py --quick    # B=8, T=50
    python benchmarks/bench_training.py --batch 16 --seq 100 --modalities acc multi_l
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import torch

from embodied_tactile.model import LatentFilter
from embodied_tactile.data.modality import modality_names
from embodied_tactile.run.threadenv import set_threads
from steps import make_batch, naive_terms


def one_step(fn, opt) -> float:
    t0 = time.perf_counter()
    opt.zero_grad(set_to_none=True)
    terms = fn()
    (terms["nll"] + terms["kl_z"] + terms["kl_y"]).backward()
    opt.step()
    return time.perf_counter() - t0


def time_pair(fast, naive, opt, repeats: int, naive_repeats: int) -> tuple[list[float], list[float]]:
    """Alternate batched and naive steps (after one warm-up each) so that both see the
    same machine load; returns the timings of each."""
    one_step(fast, opt)
    if naive is not None:
        one_step(naive, opt)
    tf, tn = [], []
    for i in range(max(repeats, naive_repeats)):
        if i < repeats:
            tf.append(one_step(fast, opt))
        if naive is not None and i < naive_repeats:
            tn.append(one_step(naive, opt))
    return tf, tn


def bench_latency(model_kw: dict, n: int = 2000) -> tuple[float, float]:
    set_threads(1)
    m = LatentFilter("multi_l", **model_kw).eval()
    obs = torch.rand(n + 100, 1, 3, 28, 28)
    act = torch.randn(n + 100, 1, 6)
    times = []
    with torch.inference_mode():
        state, prev = None, None
        for i in range(n + 100):
            t0 = time.perf_counter()
            _, state = m.filter_step(obs[i], act[i], prev, state)
            dt = time.perf_counter() - t0
            prev = act[i]
            if i >= 100:
                times.append(dt)
    times.sort()
    return statistics.median(times) * 1e3, times[int(0.99 * len(times))] * 1e3


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", type=int, default=None, help="B (default 48, --quick 8)")
    p.add_argument("--seq", type=int, default=None, help="T (default 300, --quick 50)")
    p.add_argument("--quick", action="store_true", help="smaller shapes for a fast check")
    p.add_argument("--modalities", nargs="+", default=modality_names(), choices=modality_names())
    p.add_argument("--repeats", type=int, default=3, help="timed batched steps per model (after 1 warm-up)")
    p.add_argument("--naive-repeats", type=int, default=2, help="timed naive steps per model")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--widths", type=int, nargs=2, default=[16, 32], help="encoder conv widths")
    p.add_argument("--hidden", type=int, default=128)
    p.add_argument("--latency-steps", type=int, default=2000)
    p.add_argument("--no-naive", action="store_true")
    args = p.parse_args()
    B = args.batch or (8 if args.quick else 48)
    T = args.seq or (50 if args.quick else 300)
    model_kw = dict(encoder={"widths": args.widths, "hidden": args.hidden}, transition_hidden=128, lstm_hidden=128)
    set_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; shapes B={B}, T={T}, 28x28; "
          f"encoder widths {args.widths}, hidden {args.hidden}; n_z=16, n_y=16")
    print(f"load average at start: {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} CPUs")
    print("step s = min over repeats (median in brackets); seq/s = B / min step; speed-up = naive / batched (min)")
    print(f"{'modality':<9} {'C':>2} {'params':>8} {'step s':>16} {'seq/s':>7} {'naive step s':>16} "
          f"{'naive seq/s':>11} {'speed-up':>8}")
    for name in args.modalities:
        torch.manual_seed(0)
        m = LatentFilter(name, **model_kw)
        C = len(m.modality["channels"])
        batch = make_batch(C, B, T)
        opt = torch.optim.Adam(m.parameters(), lr=1e-5)
        n_params = sum(p.numel() for p in m.parameters())
        naive = None if args.no_naive else (lambda: naive_terms(m, batch))
        tf, tn = time_pair(lambda: m.elbo_terms(batch), naive, opt, args.repeats, args.naive_repeats)
        f_min = min(tf)
        row = f"{name:<9} {C:>2} {n_params:>8} {f_min:>7.2f} ({statistics.median(tf):>6.2f}) {B / f_min:>7.1f}"
        if tn:
            n_min = min(tn)
            row += (f" {n_min:>7.2f} ({statistics.median(tn):>6.2f}) {B / n_min:>11.1f} {n_min / f_min:>7.1f}x")
        print(row, flush=True)
    if not args.no_naive:
        # the reference computes the same loss (deterministic mode)
        m = LatentFilter("multi_l", **model_kw)
        small = make_batch(3, 2, 6)
        with torch.no_grad():
            a = m.elbo_terms(small, sample=False)
            b = naive_terms(m, small, sample=False)
        diff = max(abs(float(a[k]) - float(b[k])) / max(1.0, abs(float(a[k]))) for k in ("nll", "kl_z", "kl_y", "entropy"))
        print(f"naive reference vs batched loss, max relative difference: {diff:.1e}")
    med, p99 = bench_latency(model_kw, args.latency_steps)
    print(f"load average at end: {os.getloadavg()[0]:.2f}")
    print(f"filter_step multi_l, batch 1, 1 thread: median {med:.3f} ms, p99 {p99:.3f} ms "
          f"over {args.latency_steps} steps")


if __name__ == "__main__":
    main()
