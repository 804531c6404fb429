"""One Latent Filter training step at paper shapes against the same-run fp32 matmul ceiling.

For each mode (fp32; bf16 = CPU autocast to bfloat16, the float32 regions of
``networks.float32_region`` kept; compile = torch.compile of encoders and decoders, not the
time loop): FLOPs of one step counted with ``torch.utils.flop_counter``, the step time (min
over repeats, all listed), GFLOP/s, and the 2048x2048 fp32 matmul rate measured just before
and after in the same process, so that machine load is visible next to every figure.

    python benchmarks/bench_step_ceiling.py --modality multi_l --modes fp32 bf16 --threads 1
"""

from __future__ import annotations

import argparse
import contextlib
import os

import torch
from torch.utils.flop_counter import FlopCounterMode


from steps import make_batch, matmul_ceiling, step, training_module  # noqa: E402
from embodied_tactile.model import LatentFilter  # noqa: E402
from embodied_tactile.model.networks import ConvDecoder, ConvEncoder  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--modality", default="multi_l")
    p.add_argument("--modes", nargs="+", default=["fp32", "bf16"], choices=["fp32", "bf16", "compile"])
    p.add_argument("--batch", type=int, default=48)
    p.add_argument("--seq", type=int, default=300)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, cpu capability {torch.backends.cpu.get_cpu_capability()}, "
          f"{torch.get_num_threads()} threads, B={args.batch} T={args.seq} 28x28, load {os.getloadavg()[0]:.1f}")
    for mode in args.modes:
        torch.manual_seed(0)
        m = LatentFilter(args.modality)
        batch = make_batch(m.n_channels, args.batch, args.seq)
        ctx = (lambda: torch.autocast("cpu", dtype=torch.bfloat16)) if mode == "bf16" else contextlib.nullcontext
        if mode == "compile":
            for parent in list(m.observation.modules()):  # every encoder and decoder, in place
                for k, child in list(parent.named_children()):
                    if isinstance(child, (ConvEncoder, ConvDecoder)):
                        setattr(parent, k, torch.compile(child, dynamic=False))
        module = training_module(m)
        opt = torch.optim.Adam(m.parameters(), lr=1e-5)
        with FlopCounterMode(display=False) as fc:  # also the warm-up (and compilation)
            step(module, batch, opt, ctx)
        flops = fc.get_total_flops()
        c0 = matmul_ceiling()
        ts = [step(module, batch, opt, ctx) for _ in range(args.repeats)]
        c1 = matmul_ceiling()
        t = min(ts)
        rate = flops / t / 1e9
        print(f"{args.modality} {mode:<8} step {t:6.2f} s (all {', '.join(f'{x:.2f}' for x in ts)}) "
              f"{flops / 1e9:6.1f} GFLOP {rate:6.1f} GFLOP/s | matmul ceiling before/after {c0:.0f}/{c1:.0f} GFLOP/s "
              f"-> {100 * rate / max(c0, c1):.1f} % | load {os.getloadavg()[0]:.1f}", flush=True)


if __name__ == "__main__":
    main()
