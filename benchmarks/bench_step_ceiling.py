"""One Latent Filter training step against the same-run fp32 matmul ceiling, its profile,
and the step before / after a speed change.

For each mode: FLOPs of one step counted with ``torch.utils.flop_counter``, the step time
(median over ``--rounds``, every mode once per round so that all see the same machine load;
wall and process CPU seconds), GFLOP/s, and the 2048x2048 fp32 matmul rate measured before
the first round and after every round in the same process. Modes:

  fp32     the code as it is (float32, eager)
  before   the code as it was before 2026-11-27 (the reference of that day's changes): the
           decoder's last layer a oneDNN transposed conv with channels_last means, the
           likelihood elementwise then summed, the input check by ``isfinite().all()``
  bf16     CPU autocast to bfloat16 (the float32 regions of ``networks.float32_region`` kept)
  compile  torch.compile of encoders and decoders (not the time loop)
  naive    the per-frame reference: encoder and decoder called inside the time loop
           (``steps.naive_terms``), same weights

``--scene default|paper`` builds the model as ``python train.py`` does (the composed
config: ``experiment=paper`` for the paper's) at the scene's shapes (default: batch 16,
50-frame windows; paper: batch 48, whole 300-frame trials) and trains it with the module's
own ``training_step`` (its annealing and checks). Without ``--scene`` the network has the
class defaults (``LatentFilter(modality)``) at ``--batch`` / ``--seq``. ``--profile``
prints the first mode's ``torch.profiler`` tables: the top operators (self CPU) and the
step's parts (forward per module, backward per autograd node, Adam).

    python benchmarks/bench_step_ceiling.py --scene default --modes before fp32 --rounds 7 --profile
    python benchmarks/bench_step_ceiling.py --scene paper --modes before fp32 --rounds 2
    python benchmarks/bench_step_ceiling.py --modality multi_l --modes fp32 bf16 --threads 1
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import os
import platform
import statistics
import time

import embodied_tactile.run.threadenv  # noqa: F401  train.py's OpenMP spin count, set before torch loads OpenMP
import torch
from torch.utils.flop_counter import FlopCounterMode

from steps import make_batch, matmul_ceiling, naive_terms, step, training_module  # noqa: E402
from embodied_tactile.model import LatentFilter  # noqa: E402
from embodied_tactile.model import latent_filter as lf  # noqa: E402
from embodied_tactile.model import module as lf_module  # noqa: E402
from embodied_tactile.model import networks  # noqa: E402
from embodied_tactile.model.networks import ConvDecoder, ConvEncoder  # noqa: E402
from embodied_tactile.run.threadenv import set_threads

MODES = ("fp32", "before", "bf16", "compile", "naive")
#: whole trials of the simulated scenes (configs/data/sim.yaml ``seq_len: null``)
WHOLE_TRIAL_FRAMES = 300


def decoder_body_before(dec: ConvDecoder, z: torch.Tensor) -> torch.Tensor:
    """``ConvDecoder.body`` as it was before 2026-11-27: every transposed conv through
    oneDNN, the means left in channels_last."""
    h = dec.fc(z).view(z.shape[0], dec.w2, 7, 7)
    if z.shape[0] >= networks.CHANNELS_LAST_MIN_FRAMES and z.device.type == "cpu":
        h = h.contiguous(memory_format=torch.channels_last)
    return dec.deconv(h)


def nll_frames_before(x: torch.Tensor, mean: torch.Tensor, log_sigma: torch.Tensor) -> torch.Tensor:
    """The likelihood as the ELBO summed it before 2026-11-27: elementwise, then summed."""
    return networks.gaussian_nll(x, mean, log_sigma.view(-1, 1, 1)).sum(dim=(-3, -2, -1))


@contextlib.contextmanager
def code_before():
    """Mode ``before``: the decoder, the likelihood sum and the input check as they were
    before 2026-11-27 (the reference of that day's changes)."""
    saved = ConvDecoder.body, lf.gaussian_nll_frames, lf_module.nonfinite_inputs
    check = lf_module.nonfinite_inputs
    ConvDecoder.body, lf.gaussian_nll_frames = decoder_body_before, nll_frames_before
    lf_module.nonfinite_inputs = lambda batch, max_frames=8: (  # noqa: E731
        [] if all(not torch.is_tensor(x) or bool(torch.isfinite(x).all())
                  for x in (batch.get("obs"), batch.get("actions"))) else check(batch, max_frames))
    try:
        yield
    finally:
        ConvDecoder.body, lf.gaussian_nll_frames, lf_module.nonfinite_inputs = saved


def scene_module(scene: str, modality: str | None):
    """(LightningModule built from the composed train config, batch size, frames per window)."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from embodied_tactile.run.config import config_dir  # registers the typed configs

    overrides = ["hydra.runtime.output_dir=/tmp"] + (["experiment=paper"] if scene == "paper" else [])
    if modality:
        overrides.append(f"modality={modality}")
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides)
    module = instantiate(cfg.model)
    if hasattr(module.annealing, "set_total_steps"):  # what the module does at the start of fit
        module.annealing.set_total_steps(10_000)
    seq = cfg.data.train_window or cfg.data.seq_len or WHOLE_TRIAL_FRAMES
    return module, int(cfg.data.batch_size), int(seq)


class Mode:
    """One mode's module, optimiser, step function and context, and its timings."""

    def __init__(self, mode: str, args, batch_shape) -> None:
        import warnings

        warnings.filterwarnings("ignore", message=r".*self\.log\(\)` but the `self\.trainer` reference is not registered")
        torch.manual_seed(0)
        if args.scene:
            self.module, _, _ = scene_module(args.scene, args.modality)
        else:
            self.module = training_module(LatentFilter(args.modality or "multi_l"))
        m = self.module.model
        self.name = mode
        self.ctx = contextlib.nullcontext
        if mode == "bf16":
            self.ctx = lambda: torch.autocast("cpu", dtype=torch.bfloat16)
        elif mode == "before":
            self.ctx = code_before
        elif mode == "compile":
            for parent in list(m.observation.modules()):  # every encoder and decoder, in place
                for k, child in list(parent.named_children()):
                    if isinstance(child, (ConvEncoder, ConvDecoder)):
                        setattr(parent, k, torch.compile(child, dynamic=False))
        self.opt = torch.optim.Adam(m.parameters(), lr=1e-5)
        self.wall: list[float] = []
        self.cpu: list[float] = []

    def run(self, batch) -> None:
        if self.name == "naive":
            m = self.module.model

            def fn():
                self.opt.zero_grad(set_to_none=True)
                t = naive_terms(m, batch)
                (t["nll"] + t["kl_z"] + t["kl_y"]).backward()
                self.opt.step()
            c0, w0 = time.process_time(), time.perf_counter()
            fn()
            self.wall.append(time.perf_counter() - w0)
            self.cpu.append(time.process_time() - c0)
            return
        c0 = time.process_time()
        self.wall.append(step(self.module, batch, self.opt, self.ctx))
        self.cpu.append(time.process_time() - c0)


def profile_tables(mode: Mode, batch, steps: int, rows: int) -> None:
    """torch.profiler over ``steps`` training steps: the top operators by self CPU time, then
    the step's parts (forward per module via hooks, backward per autograd node, Adam)."""
    from torch.profiler import ProfilerActivity, profile, record_function

    m = mode.module.model
    watched = {mod: name for name, mod in m.named_modules()
               if isinstance(mod, (ConvEncoder, ConvDecoder)) or name in ("transition", "y_posterior", "prior")}
    ranges = {}

    def pre(mod, _):
        ranges[mod] = record_function(f"forward {watched[mod]}")
        ranges[mod].__enter__()

    def post(mod, *_):
        ranges.pop(mod).__exit__(None, None, None)

    hooks = [h for mod in watched for h in (mod.register_forward_pre_hook(pre), mod.register_forward_hook(post))]

    def one():
        mode.opt.zero_grad(set_to_none=True)
        with mode.ctx():
            with record_function("forward (whole)"):
                loss = mode.module.training_step(batch, 0)
            with record_function("backward (whole)"):
                loss.backward()
        with record_function("adam"):
            mode.opt.step()
    try:
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for _ in range(steps):
                one()
    finally:
        for h in hooks:
            h.remove()
    ka = prof.key_averages()
    total = sum(e.self_cpu_time_total for e in ka)
    print(f"\ntorch.profiler, mode {mode.name}, {steps} steps (wall time in each op; load {os.getloadavg()[0]:.1f}): "
          f"top operators by self CPU time")
    print("| operator | calls / step | self ms / step | share |\n|---|---|---|---|")
    for e in sorted(ka, key=lambda e: -e.self_cpu_time_total)[:rows]:
        if e.key.startswith(("forward ", "backward ", "adam")):
            continue
        print(f"| {e.key} | {e.count / steps:.0f} | {e.self_cpu_time_total / 1e3 / steps:.1f} | "
              f"{100 * e.self_cpu_time_total / total:.1f} % |")
    print("\nthe step's parts (forward per module: encoders/decoders over all frames, the recursion's "
          "modules summed over its T steps; backward per autograd node type)")
    print("| part | calls / step | ms / step | share |\n|---|---|---|---|")
    parts = [e for e in ka if e.key.startswith(("forward ", "backward (", "adam"))]
    bwd = collections.Counter()
    for e in ka:
        if e.key.startswith("autograd::engine::evaluate_function: "):
            bwd[e.key.split(": ", 1)[1]] += e.cpu_time_total
    for e in sorted(parts, key=lambda e: -e.cpu_time_total):
        print(f"| {e.key} | {e.count / steps:.0f} | {e.cpu_time_total / 1e3 / steps:.1f} | "
              f"{100 * e.cpu_time_total / total:.1f} % |")
    for k, v in bwd.most_common(8):
        print(f"| backward {k} | | {v / 1e3 / steps:.1f} | {100 * v / total:.1f} % |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", choices=["default", "paper"], default=None,
                   help="the model and shapes of python train.py (default) or experiment=paper")
    p.add_argument("--modality", default=None, help="default: the scene's, or multi_l without --scene")
    p.add_argument("--modes", nargs="+", default=["fp32", "bf16"], choices=MODES)
    p.add_argument("--batch", type=int, default=None, help="default: the scene's, or 48")
    p.add_argument("--seq", type=int, default=None, help="default: the scene's, or 300")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--rounds", "--repeats", type=int, default=2, dest="rounds",
                   help="timed steps per mode, interleaved round by round")
    p.add_argument("--profile", action="store_true", help="profile the first mode")
    p.add_argument("--profile-steps", type=int, default=3)
    args = p.parse_args()
    set_threads(args.threads)
    batch_size, seq = 48, WHOLE_TRIAL_FRAMES
    if args.scene:
        _, batch_size, seq = scene_module(args.scene, args.modality)
    batch_size, seq = args.batch or batch_size, args.seq or seq
    cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")),
               platform.processor()) if os.path.exists("/proc/cpuinfo") else platform.processor()
    print(f"{cpu}, torch {torch.__version__}, cpu capability {torch.backends.cpu.get_cpu_capability()}, "
          f"{torch.get_num_threads()} threads, scene {args.scene or '(class defaults)'}, B={batch_size} T={seq} "
          f"28x28, load {', '.join(f'{x:.1f}' for x in os.getloadavg())} on {os.cpu_count()} CPUs")
    modes = [Mode(mode, args, None) for mode in args.modes]
    m0 = modes[0].module.model
    batch = make_batch(m0.n_channels, batch_size, seq)
    print(f"model: {m0.modality['name']} ({type(m0.observation).__name__}), y_update {m0.y_posterior.update}, "
          f"obs_dropout {m0.obs_dropout}")
    flops = None
    for mode in modes:  # warm-up (and compilation); FLOPs of the first mode's step
        cm = FlopCounterMode(display=False) if flops is None else contextlib.nullcontext()
        t0 = time.perf_counter()
        with cm, code_before() if flops is None else contextlib.nullcontext():  # the useful FLOPs
            mode.run(batch)
        if flops is None:
            flops = cm.get_total_flops()
        print(f"warm-up {mode.name}: {time.perf_counter() - t0:.2f} s", flush=True)
        mode.wall.clear(), mode.cpu.clear()
    if args.profile:
        profile_tables(modes[0], batch, args.profile_steps, 30)
    ceil = [matmul_ceiling()]
    for _ in range(args.rounds):
        for mode in modes:
            mode.run(batch)
        ceil.append(matmul_ceiling())
    c = max(ceil)
    gflop = flops / 1e9
    print(f"\n{gflop:.1f} GFLOP per step (flop_counter, mode {modes[0].name} with the code before: the "
          f"sub-pixel layer's zero taps not counted); matmul ceiling "
          f"{', '.join(f'{x:.0f}' for x in ceil)} GFLOP/s (before the first round, after each; max {c:.0f} used); "
          f"load at end {', '.join(f'{x:.1f}' for x in os.getloadavg())}")
    ref = {name: statistics.median(md.wall) for md in modes for name in [md.name]}
    print(f"| mode | step s, median wall (all) | CPU s, median | GFLOP/s (wall) | % of ceiling | "
          f"vs {modes[0].name} | vs naive |")
    print("|---|---|---|---|---|---|---|")
    for mode in modes:
        t = statistics.median(mode.wall)
        rate = gflop / t
        vs0 = ref[modes[0].name] / t
        vsn = f"{ref['naive'] / t:.2f}x" if "naive" in ref else "-"
        print(f"| {mode.name} | {t:.3f} ({', '.join(f'{x:.2f}' for x in mode.wall)}) | "
              f"{statistics.median(mode.cpu):.3f} | {rate:.1f} | {100 * rate / c:.1f} % | {vs0:.2f}x | {vsn} |",
              flush=True)


if __name__ == "__main__":
    main()
