"""Where the training step's time goes, and the speed levers one at a time.

Part 1 (breakdown): the pieces of one training step (forward + backward), timed alone at
the same shapes: the batched conv encoders, the batched conv decoders, the Python
recursion loop (LSTMCell + transition MLP per step, T steps, from given encoder outputs),
the Gaussian likelihood, and the whole step; then the top ops of ``torch.profiler``.

Part 2 (levers): one training step (forward + backward + Adam) of the default model and
of each lever on its own, in the same process, interleaved round by round so that every
variant sees the same machine load; the 2048x2048 fp32 matmul ceiling is measured before
and after every round. For each: min step time, GFLOP/s (``torch.utils.flop_counter``
GFLOPs of the default step / time), % of the round's ceiling and the speed-up over the
default and over the naive per-step reference.

    python benchmarks/bench_step_levers.py --modality multi_l --batch 16 --seq 50
    python benchmarks/bench_step_levers.py --modality fsr_tb --batch 48 --seq 300 --rounds 1

Levers (``--levers``):
  naive          the naive reference: encoder and decoder called per frame inside the
                 time loop (``bench_training.naive_terms``), same weights, eager
  eager          everything eager (the default before ``compile_convs``): the baseline
                 every lever below is compared with, each lever on its own
  compile_convs  ``networks.compile_convs``: torch.compile of the encoder / decoder
                 bodies for training steps (train.py's default, ``compile_convs=true``)
  cl_end_to_end  parameters and every conv input in channels_last (eager already uses
                 channels_last inputs for >= 64 frames: ``CHANNELS_LAST_MIN_FRAMES``)
  onednn_off     ``torch.backends.mkldnn.enabled = False`` for the step (PyTorch's native
                 convolution kernels)
  compile_step   ``torch.compile`` of the recursion step function (``LatentFilter.step``)
  grouped_enc    (multi_l) the two pathway encoders' first conv as one grouped conv of
                 the zero-padded channels, timed as encoder forward + backward only
                 (a proxy: the model keeps separate pathways)
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import time

import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from steps import make_batch, matmul_ceiling, naive_terms  # noqa: E402

from embodied_tactile.model import LatentFilter  # noqa: E402
from embodied_tactile.model import networks  # noqa: E402
from embodied_tactile.model.networks import gaussian_nll  # noqa: E402
from embodied_tactile.run.threadenv import set_threads

LEVERS = ("naive", "eager", "compile_convs", "cl_end_to_end", "onednn_off", "compile_step")


def _best(fn, repeats: int) -> float:
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def breakdown(m: LatentFilter, batch: dict, repeats: int) -> None:
    obs, act = batch["obs"], batch["actions"]
    B, T = obs.shape[:2]
    N = B * T
    flat = obs.reshape(N, *obs.shape[2:])
    z = torch.randn(N, m.n_z, requires_grad=True)
    em = torch.randn(B, T, m.n_z, requires_grad=True)
    ev = (torch.rand(B, T, m.n_z) + 0.1).requires_grad_()
    rec = torch.rand(B, T, m.n_channels, 28, 28, requires_grad=True)

    def enc():
        mu, var = m.encode(flat)
        (mu.sum() + var.sum()).backward()

    def dec():
        m.decode(z).sum().backward()

    def loop():
        state, outs = None, []
        for t in range(T):
            o, state = m.step(em[:, t], ev[:, t], act[:, t], state, True)
            outs.append(o)
        sum(torch.stack([s[k] for s in outs], 1).sum() for k in outs[0]).backward()

    def nll():
        ls = m.obs_log_sigma().view(1, 1, -1, 1, 1)
        gaussian_nll(obs, rec, ls).sum(dim=(1, 2, 3, 4)).mean().backward()

    def full():
        t = m.elbo_terms(batch)
        (t["nll"] + t["kl_z"] + t["kl_y"]).backward()

    parts = [("encoders (batched convs)", enc), ("decoders (batched convs)", dec),
             ("recursion loop (T steps)", loop), ("likelihood (nll)", nll), ("whole fwd+bwd", full)]
    times = {k: _best(f, repeats) for k, f in parts}
    whole = times["whole fwd+bwd"]
    print(f"\nbreakdown, forward + backward, min of {repeats} (load {os.getloadavg()[0]:.1f}):")
    print(f"| part | s | share of whole |\n|---|---|---|")
    for k, v in times.items():
        print(f"| {k} | {v:.3f} | {100 * v / whole:.0f} % |")
    from torch.profiler import ProfilerActivity, profile
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        full()
    print("\ntorch.profiler, one fwd+bwd, top ops by self CPU time:")
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=12, max_name_column_width=40))


def build(lever: str, modality: str, batch: dict):
    """-> (model, step function returning the loss terms, context manager)."""
    torch.manual_seed(0)
    m = LatentFilter(modality)
    ctx = contextlib.nullcontext
    fn = lambda: m.elbo_terms(batch)  # noqa: E731
    networks.compile_convs(m, lever == "compile_convs")
    if lever == "naive":
        fn = lambda: naive_terms(m, batch)  # noqa: E731
    elif lever == "cl_end_to_end":
        m = m.to(memory_format=torch.channels_last)
        networks.CHANNELS_LAST_MIN_FRAMES = 1
    elif lever == "onednn_off":
        @contextlib.contextmanager
        def ctx():
            torch.backends.mkldnn.enabled = False
            try:
                yield
            finally:
                torch.backends.mkldnn.enabled = True
    elif lever == "compile_step":
        m.step = torch.compile(m.step, dynamic=False)
    return m, fn, ctx


def one_step(m, fn, opt, ctx) -> float:
    t0 = time.perf_counter()
    with ctx():
        opt.zero_grad(set_to_none=True)
        terms = fn()
        (terms["nll"] + terms["kl_z"] + terms["kl_y"]).backward()
        opt.step()
    return time.perf_counter() - t0


def grouped_proxy(batch: dict, repeats: int) -> tuple[float, float]:
    """multi_l's two first encoder convs (1 and 2 input channels, 16 filters each) as two
    convs vs one grouped conv over zero-padded channels (2 groups x 2 channels); forward +
    weight gradient, channels_last like the model. -> (separate s, grouped s)."""
    obs = batch["obs"]
    x = obs.reshape(-1, 3, 28, 28).contiguous(memory_format=torch.channels_last)
    xp = torch.cat([x[:, :1], torch.zeros_like(x[:, :1]), x[:, 1:]], 1).contiguous(memory_format=torch.channels_last)
    a, f = nn.Conv2d(1, 16, 4, 2, 1), nn.Conv2d(2, 16, 4, 2, 1)
    g = nn.Conv2d(4, 32, 4, 2, 1, groups=2)
    sep = _best(lambda: (a(x[:, :1]).sum() + f(x[:, 1:]).sum()).backward(), repeats)
    grp = _best(lambda: g(xp).sum().backward(), repeats)
    return sep, grp


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--modality", default="multi_l")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--seq", type=int, default=50)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--rounds", type=int, default=2, help="timed steps per lever (interleaved rounds)")
    p.add_argument("--levers", nargs="+", default=list(LEVERS), choices=LEVERS)
    p.add_argument("--no-breakdown", action="store_true")
    args = p.parse_args()
    set_threads(args.threads)
    print(f"torch {torch.__version__}, cpu capability {torch.backends.cpu.get_cpu_capability()}, "
          f"{torch.get_num_threads()} threads, {args.modality} B={args.batch} T={args.seq} 28x28, "
          f"load {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    torch.manual_seed(0)
    probe = LatentFilter(args.modality)
    batch = make_batch(probe.n_channels, args.batch, args.seq)
    if not args.no_breakdown:
        breakdown(probe, batch, max(1, args.rounds))
    # FLOPs of the default step (every lever computes the same loss; the naive one too)
    opt = torch.optim.Adam(probe.parameters(), lr=1e-5)
    with FlopCounterMode(display=False) as fc:
        one_step(probe, lambda: probe.elbo_terms(batch), opt, contextlib.nullcontext)
    gflop = fc.get_total_flops() / 1e9
    print(f"\nlevers: {gflop:.1f} GFLOP per step (flop_counter); warm-up = first step (compilation included)")
    default_min_frames = networks.CHANNELS_LAST_MIN_FRAMES
    runs = {}
    for lever in args.levers:
        m, fn, ctx = build(lever, args.modality, batch)
        opt = torch.optim.Adam(m.parameters(), lr=1e-5)
        warm = one_step(m, fn, opt, ctx)
        networks.CHANNELS_LAST_MIN_FRAMES = default_min_frames
        runs[lever] = {"m": m, "fn": fn, "ctx": ctx, "opt": opt, "warm": warm, "t": []}
    ceil = []
    for _ in range(args.rounds):
        ceil.append(matmul_ceiling())
        for lever, r in runs.items():
            if lever == "cl_end_to_end":
                networks.CHANNELS_LAST_MIN_FRAMES = 1
            r["t"].append(one_step(r["m"], r["fn"], r["opt"], r["ctx"]))
            networks.CHANNELS_LAST_MIN_FRAMES = default_min_frames
        ceil.append(matmul_ceiling())
    c = max(ceil)
    print(f"matmul ceiling over the rounds: {', '.join(f'{x:.0f}' for x in ceil)} GFLOP/s (max {c:.0f} used); "
          f"load at end {os.getloadavg()[0]:.1f}")
    base = min(runs["eager"]["t"]) if "eager" in runs else None
    naive = min(runs["naive"]["t"]) if "naive" in runs else None
    print("| lever | warm-up s | step s (min; all) | GFLOP/s | % of ceiling | vs eager | vs naive |")
    print("|---|---|---|---|---|---|---|")
    for lever, r in runs.items():
        t = min(r["t"])
        rate = gflop / t
        vs_d = f"{base / t:.2f}x" if base else "-"
        vs_n = f"{naive / t:.2f}x" if naive else "-"
        print(f"| {lever} | {r['warm']:.1f} | {t:.3f} ({', '.join(f'{x:.2f}' for x in r['t'])}) | {rate:.1f} | "
              f"{100 * rate / c:.1f} % | {vs_d} | {vs_n} |", flush=True)
    if args.modality == "multi_l":
        sep, grp = grouped_proxy(batch, max(2, args.rounds))
        print(f"grouped first conv proxy (multi_l, fwd + weight grad): two convs {sep * 1e3:.1f} ms, "
              f"one grouped conv {grp * 1e3:.1f} ms -> {sep / grp:.2f}x")


if __name__ == "__main__":
    main()
