"""Does switching oneDNN off around the encoder still pay for ``filter_step`` at tiny batch?

For batch sizes 1..8 (multi_l, default widths, one thread, inference mode) it times
``filter_step`` with oneDNN on and with oneDNN off around the call, interleaved in rounds
so both see the same machine load, and prints the median per-step latency of each and
their ratio. Short by design (the machine may be shared):

    python benchmarks/bench_small_batch_convs.py                 # 300 steps x 5 rounds
    python benchmarks/bench_small_batch_convs.py --steps 1000 --batches 1 4 8
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import time

import torch

from embodied_tactile.model import LatentFilter
from embodied_tactile.run.threadenv import set_threads


@contextlib.contextmanager
def onednn(enabled: bool):
    prev = torch.backends.mkldnn.enabled
    torch.backends.mkldnn.enabled = enabled
    try:
        yield
    finally:
        torch.backends.mkldnn.enabled = prev


def steps_ms(m: LatentFilter, obs: torch.Tensor, act: torch.Tensor, enabled: bool) -> list[float]:
    """Per-step latency (ms) of ``filter_step``'s work (encode, then one recursion step)
    over the frames of ``obs`` (T, B, C, 28, 28), oneDNN on or off around the whole step
    (called directly, so no switch inside ``filter_step`` decides for it)."""
    times = []
    state, prev = None, None
    with torch.inference_mode(), onednn(enabled):
        for i in range(obs.shape[0]):
            t0 = time.perf_counter()
            enc_m, enc_v = m.encode(obs[i])
            _, state = m.step(enc_m, enc_v, act[i].float(), state, False, prev)
            times.append((time.perf_counter() - t0) * 1e3)
            prev = act[i]
    return times


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batches", type=int, nargs="+", default=[1, 2, 4, 8])
    p.add_argument("--steps", type=int, default=300, help="filter steps per round and setting")
    p.add_argument("--rounds", type=int, default=5, help="interleaved on/off rounds")
    p.add_argument("--modality", default="multi_l")
    args = p.parse_args()
    set_threads(1)
    torch.manual_seed(0)
    print(f"torch {torch.__version__}, mkldnn available {torch.backends.mkldnn.is_available()}, "
          f"1 thread, {args.modality}, {args.steps} steps x {args.rounds} rounds, "
          f"load average {os.getloadavg()[0]:.2f}")
    print(f"{'batch':>5} {'oneDNN on ms':>13} {'oneDNN off ms':>14} {'on/off':>7}")
    for b in args.batches:
        m = LatentFilter(args.modality).eval()
        c = m.n_channels
        obs = torch.rand(args.steps, b, c, 28, 28)
        act = torch.randn(args.steps, b, 6)
        steps_ms(m, obs[:20], act[:20], True)  # warm-up both paths
        steps_ms(m, obs[:20], act[:20], False)
        on: list[float] = []
        off: list[float] = []
        for _ in range(args.rounds):
            on += steps_ms(m, obs, act, True)
            off += steps_ms(m, obs, act, False)
        mon, moff = statistics.median(on), statistics.median(off)
        print(f"{b:>5} {mon:>13.3f} {moff:>14.3f} {mon / moff:>6.2f}x", flush=True)
    print(f"load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
