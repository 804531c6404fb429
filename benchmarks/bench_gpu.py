"""The GPU path at the paper's shapes: time per epoch, peak GPU memory and projections.

    python benchmarks/bench_gpu.py                                   # every modality, experiment=paper trainer=gpu
    python benchmarks/bench_gpu.py --modalities multi_l acc --steps 5
    python benchmarks/bench_gpu.py --device cpu --steps 1 --batch 2 --seq 8 --modalities acc --no-population  # dry run

Per modality: the training module of ``python train.py experiment=paper trainer=gpu
modality=<m>`` (configs composed, the model instantiated as train.py does) takes timed
optimiser steps (its own ``training_step``: ELBO under its annealing, backward, Adam) on a
synthetic batch of the paper's shapes (batch 48, whole 300-frame trials, 28x28 frames),
under the trainer config's precision (``trainer=gpu``: ``bf16-mixed``, autocast to
bfloat16 with the fusion, KL, variances and likelihood kept float32 by
``networks.float32_region``), after one warm-up step; and one no-grad validation pass
of a validation batch. Printed per modality: the median step, the epoch (training steps
per epoch from the scene's split, ``data.split_trials`` over the catalogue's trials,
plus its validation batches), the peak GPU memory, 500 epochs (the paper's
``trainer.max_epochs``), and at the end the 24-model study (8 modality x e-Skin cells x 3
primitives: same shapes per primitive and skin) and the population scene
(``experiment=population``, multi_l) at 16x its optimiser-step budget. Not counted: data
loading, the KRR alignment checks, checkpoints.

Without CUDA it says so and exits 3, unless ``--device cpu`` asks for a dry run of the same
code (the tests run it at tiny shapes; its times are no GPU figures).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

import torch
from embodied_tactile.run.threadenv import set_threads

REPO = Path(__file__).resolve().parents[1]
MODALITIES = ("acc", "fsr_t", "fsr_b", "fsr_tb", "multi_e", "multi_l")
EXIT_NO_CUDA = 3
POPULATION_FACTOR = 16  # the population scene at this many times its optimiser-step budget


def compose(overrides: list[str]):
    from hydra import compose as hydra_compose, initialize_config_dir

    import embodied_tactile.run.config  # noqa: F401  typed configs and resolvers
    from embodied_tactile.run.config import config_dir

    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        return hydra_compose(config_name="train", overrides=[*overrides, "paths.data_dir=/nonexistent"])


def frames(cfg) -> int:
    """Frames per whole trial of the scene (``data.seq_len``, else the preprocessing's n_frames)."""
    from embodied_tactile.data.preprocess import PreprocessConfig

    return int(cfg.data.seq_len or PreprocessConfig(**dict(cfg.data.preprocess or {})).n_frames)


def epoch_shape(cfg) -> dict:
    """Optimiser steps and validation batches of one epoch, and the sequence lengths, from
    the scene's config and split: the catalogue's trials through ``split_trials``; a
    population's objects from its counts (training / validation objects x actions x repetitions)."""
    from embodied_tactile.data.datamodule import split_trials
    from embodied_tactile.data.prepare import catalogue_trials

    d = cfg.data
    acts = list(d.actions) if d.actions is not None else None
    if d.objects == "population":
        n_act = len(acts) if acts else 16
        n_train, n_val = d.n_objects * n_act * d.repetitions, d.n_val_objects * n_act * d.repetitions
    else:
        train, val, _ = split_trials(catalogue_trials(acts, d.repetitions), by=d.split, test_fraction=d.test_fraction,
                                     val_fraction=d.val_fraction, seed=0)
        n_train, n_val = len(train), len(val)
    items = d.windows_per_epoch or n_train * (d.windows_per_trial or 1)
    t_full = frames(cfg)
    context = cfg.model.get("context")
    return {"steps": math.ceil(items / d.batch_size), "val_batches": math.ceil(n_val / d.batch_size) if n_val else 0,
            "batch": int(d.batch_size), "t_train": int(d.train_window or t_full),
            "t_val": int(d.train_window or t_full) if context else t_full, "context": bool(context),
            "epochs": int(cfg.trainer.max_epochs), "precision": str(cfg.trainer.precision)}


def synthetic_batch(channels: int, batch: int, t: int, context: bool, device: str) -> dict:
    g = torch.Generator().manual_seed(0)
    out = {"obs": torch.rand(batch, t, channels, 28, 28, generator=g), "actions": torch.randn(batch, t, 6, generator=g),
           "object_id": torch.randint(0, 32, (batch,), generator=g), "factors": torch.rand(batch, 4, generator=g),
           "action_index": torch.zeros(batch, dtype=torch.long), "first_frame": torch.zeros(batch, dtype=torch.long)}
    if context:
        out["context_obs"] = torch.rand(batch, t, channels, 28, 28, generator=g)
        out["context_actions"] = torch.randn(batch, t, 6, generator=g)
    out = {k: v.to(device) for k, v in out.items()}
    out["trial"] = [f"synthetic{i}" for i in range(batch)]
    if context:
        out["context_trial"] = out["trial"]
    return out


def autocast(precision: str, device: str):
    if precision.startswith("bf16"):
        return torch.autocast(device_type=device, dtype=torch.bfloat16)
    if precision.startswith("16"):
        return torch.autocast(device_type=device, dtype=torch.float16)
    import contextlib

    return contextlib.nullcontext()


def sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def measure(overrides: list[str], args) -> dict:
    """One scene: the median training step, one validation pass, peak memory, the epoch."""
    import warnings

    from hydra.utils import instantiate

    warnings.filterwarnings("ignore", message=r".*self\.log\(\)` but the `self\.trainer` reference is not registered")
    cfg = compose(overrides)
    shape = epoch_shape(cfg)
    b = args.batch or shape["batch"]
    t_train, t_val = args.seq or shape["t_train"], args.seq or shape["t_val"]
    torch.manual_seed(0)
    module = instantiate(cfg.model).to(args.device)
    channels = module.model.n_channels
    module.annealing.set_total_steps(shape["steps"] * shape["epochs"])  # what fit() does from the trainer
    opt = module._optimizer(module.parameters())  # the config's optimiser (the lr schedule's steps are not timed)
    train_batch = synthetic_batch(channels, b, t_train, shape["context"], args.device)
    val_batch = synthetic_batch(channels, b, t_val, shape["context"], args.device)
    if args.device == "cuda":
        torch.cuda.reset_peak_memory_stats()

    def step() -> float:
        sync(args.device)
        t0 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        with autocast(shape["precision"], args.device):
            loss = module.training_step(train_batch, 0)
        loss.backward()
        opt.step()
        sync(args.device)
        return time.perf_counter() - t0

    module.train()
    warm = step()
    times = [step() for _ in range(args.steps)]
    module.eval()
    sync(args.device)
    t0 = time.perf_counter()
    with torch.no_grad(), autocast(shape["precision"], args.device):
        module.validation_step(val_batch, 0)
    sync(args.device)
    val_s = time.perf_counter() - t0
    step_s = statistics.median(times)
    epoch_s = shape["steps"] * step_s + shape["val_batches"] * val_s
    peak = torch.cuda.max_memory_allocated() / 2 ** 30 if args.device == "cuda" else float("nan")
    return {**shape, "batch": b, "t_train": t_train, "t_val": t_val, "warmup_s": warm, "step_s": step_s,
            "val_s": val_s, "epoch_s": epoch_s, "peak_gib": peak, "steps_timed": len(times)}


def gib(x: float) -> str:
    return "-" if x != x else f"{x:.2f}"  # NaN: no GPU memory on a CPU dry run


def hours(s: float) -> str:
    return f"{s / 3600:.2f} h" if s >= 360 else f"{s:.1f} s"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--modalities", nargs="+", default=list(MODALITIES), choices=MODALITIES)
    ap.add_argument("--steps", type=int, default=5, help="timed optimiser steps per modality (after one warm-up)")
    ap.add_argument("--device", default="cuda", choices=["cuda", "cpu"],
                    help="cpu: a dry run of the code path (no GPU figures)")
    ap.add_argument("--batch", type=int, default=None, help="override the scene's batch (dry runs)")
    ap.add_argument("--seq", type=int, default=None, help="override the sequence length (dry runs)")
    ap.add_argument("--no-population", action="store_true", help="skip the population scene")
    args = ap.parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        print("bench_gpu: no CUDA device here (torch.cuda.is_available() is False): nothing measured. "
              "Run it on a machine with a GPU, or --device cpu for a dry run of the code path.", file=sys.stderr)
        return EXIT_NO_CUDA
    if args.device == "cpu":
        set_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
        where = f"CPU dry run ({torch.get_num_threads()} thread(s)): NOT GPU figures"
    else:
        p = torch.cuda.get_device_properties(0)
        where = (f"{p.name}, {p.total_memory / 2 ** 30:.0f} GiB, CUDA {torch.version.cuda}, torch {torch.__version__}, "
                 f"bf16 supported: {torch.cuda.is_bf16_supported()}")
    print(f"device: {where}")
    sizes = "" if not (args.batch or args.seq) else f" (shapes overridden: batch {args.batch}, seq {args.seq})"
    print(f"experiment=paper trainer=gpu{sizes}; {args.steps} timed steps per modality after one warm-up\n")
    print("| modality | precision | batch x T | steps + val batches / epoch | warm-up s | step s | val pass s | "
          "epoch s | peak GiB | 500 epochs |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    per_model = {}
    for m in args.modalities:
        r = measure(["experiment=paper", "trainer=gpu", f"modality={m}"], args)
        per_model[m] = r["epoch_s"] * r["epochs"]
        print(f"| {m} | {r['precision']} | {r['batch']} x {r['t_train']} | {r['steps']} + {r['val_batches']} | "
              f"{r['warmup_s']:.2f} | {r['step_s']:.3f} | {r['val_s']:.3f} | {r['epoch_s']:.2f} | {gib(r['peak_gib'])} | "
              f"{hours(per_model[m])} ({r['epochs']} epochs) |", flush=True)
    from embodied_tactile.eval.study_report import PAPER_COMBOS
    from embodied_tactile.constants import PRIMITIVES

    cells = [(m, s) for m, s in PAPER_COMBOS if m in per_model]
    study = sum(per_model[m] for m, _ in cells) * len(PRIMITIVES)
    print(f"\nthe paper's study: {len(cells) * len(PRIMITIVES)} of its 24 models measured here: {hours(study)} "
          f"(each modality's 500 epochs x its e-Skins x {len(PRIMITIVES)} primitives; the paper: about 12 h per "
          "model on one RTX A4000)")
    if not args.no_population:
        r = measure(["experiment=population", "trainer=gpu"], args)
        epochs = r["epochs"] * POPULATION_FACTOR
        print(f"population scene (experiment=population, multi_l, context objective) at {POPULATION_FACTOR}x its "
              f"budget: {epochs} epochs x ({r['steps']} steps of {r['batch']} x {r['t_train']} + {r['val_batches']} "
              f"val batches) = {hours(epochs * r['epoch_s'])}; step {r['step_s']:.3f} s, peak {gib(r['peak_gib'])} GiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
