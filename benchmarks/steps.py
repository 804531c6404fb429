"""Training-step timing helpers of the speed benchmarks (bench_training, bench_step_ceiling,
bench_step_levers, bench_threads; benchmark code, imported as a sibling module): a synthetic
batch, the per-step reference loss, the matmul ceiling and a timed optimiser step of the
LightningModule's own training step."""

from __future__ import annotations

import time
import warnings

import torch

from embodied_tactile.model import LatentFilter, LatentFilterModule
from embodied_tactile.model.networks import gaussian_entropy, gaussian_nll, kl_diag_gaussians


def naive_terms(m: LatentFilter, batch: dict, sample: bool = True) -> dict:
    """Same loss as ``LatentFilter.elbo_terms``, encoder and decoder called per time step."""
    obs, actions = batch["obs"], batch["actions"].float()
    B, T = obs.shape[:2]
    log_sigma = m.obs_log_sigma().view(1, -1, 1, 1)
    state, nll, kl_z, kl_y, ent = None, 0.0, 0.0, 0.0, 0.0
    if T > 1:
        py_m, py_v = m.prior(batch["object_id"], actions)
    for t in range(T):
        enc_m, enc_v = m.encode(obs[:, t])
        out, state = m.step(enc_m, enc_v, actions[:, t], state, sample)
        rec = m.decode(out["z"])
        nll = nll + gaussian_nll(obs[:, t], rec, log_sigma).sum(dim=(1, 2, 3))
        kl_z = kl_z + kl_diag_gaussians(out["z_mean"], out["z_var"], out["zp_mean"], out["zp_var"])
        ent = ent + gaussian_entropy(out["z_var"])
        if t > 0:
            kl_y = kl_y + kl_diag_gaussians(out["y_mean"], out["y_var"], py_m[:, t], py_v[:, t])
            ent = ent + gaussian_entropy(out["y_var"])
    return {"nll": nll.mean(), "kl_z": kl_z.mean(), "kl_y": torch.as_tensor(kl_y).mean(), "entropy": ent.mean()}


def make_batch(C: int, B: int, T: int) -> dict:
    """A fixed random batch: obs (B, T, C, 28, 28), actions (B, T, 6), object ids in 0..31."""
    g = torch.Generator().manual_seed(0)
    return {"obs": torch.rand(B, T, C, 28, 28, generator=g), "actions": torch.randn(B, T, 6, generator=g),
            "object_id": torch.randint(0, 32, (B,), generator=g)}


def matmul_ceiling(n: int = 2048, repeats: int = 3) -> float:
    """GFLOP/s of an n x n fp32 matmul (best of ``repeats``)."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    a @ b
    best = min(timed(lambda: a @ b) for _ in range(repeats))
    return 2 * n ** 3 / best / 1e9


def timed(fn) -> float:
    """Wall seconds of one call."""
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def training_module(m: LatentFilter) -> LatentFilterModule:
    """The network in the LightningModule that trains it (plain ELBO: no annealing), for
    :func:`step` outside a Trainer (its ``self.log`` calls then do nothing)."""
    warnings.filterwarnings("ignore", message=r".*self\.log\(\)` but the `self\.trainer` reference is not registered")
    return LatentFilterModule(m, weight_average=None)  # the optimiser step alone, as the benchmarks measured it


def step(module: LatentFilterModule, batch: dict, opt, ctx) -> float:
    """Seconds of one optimiser step on the module's own training step (its loss: the ELBO
    terms under its annealing schedule), the forward pass under ``ctx()``."""
    def run():
        opt.zero_grad(set_to_none=True)
        with ctx():
            loss = module.training_step(batch, 0)
        loss.backward()
        opt.step()
    return timed(run)

