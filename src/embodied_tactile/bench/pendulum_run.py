"""Train the project's :class:`~embodied_tactile.model.LatentFilter` on the pendulum
benchmark (:mod:`embodied_tactile.data.pendulum`) and read it out (docs/reference/model.md,
"Pendulum benchmark"). Used by ``experiments/pendulum.py`` and tests/unit/test_pendulum.py.

Read-outs on held-out sequences, each fitted on the training sequences only, linear
(least squares) and RBF kernel ridge (:func:`embodied_tactile.eval.krr.fit_alignment`,
grid-searched on training rows, folds grouped by sequence), scored by R^2 (averaged over
outputs):

* ``z_angle``: q_filt mean z_t -> (cos theta_t, sin theta_t), frames t >= ``skip``;
* ``z_velocity``: z_t -> theta'_t, frames t >= ``skip``;
* ``y_frequency`` / ``y_damping``: q(y_T) mean at the last frame -> w0 / d;
* the same read-outs on systems never seen in training (:data:`~.pendulum.UNSEEN_SYSTEMS`,
  parameters between the training grid's), and every read-out of the untrained network;
* diagnostics ``z_frequency`` / ``z_damping``: q_filt mean z_T at the last frame -> w0 / d
  (a model can keep the trial-constant parameters in z instead of y), and ``y_velocity``:
  q(y_t) mean -> theta'_t, frames t >= ``skip`` (a per-step y can carry the moving state).

Open-loop prediction: filter the first ``n_filter`` frames, then
:meth:`LatentFilter.predict` the next ``horizon`` frames under the known actions; image MSE
per horizon against the noiseless rendering, next to copying the last observed (noisy)
frame and copying its noiseless rendering (the stricter baseline).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import lightning as L
import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf
from sklearn.linear_model import LinearRegression
from sklearn.metrics import r2_score
from torch import nn
from torch.utils.data import DataLoader, Dataset, RandomSampler

from embodied_tactile.run import quiet
from embodied_tactile.data.statistics import DataStatistics
from embodied_tactile.eval.krr import fit_alignment
from embodied_tactile.model.annealing import AnnealingSchedule
from embodied_tactile.model.latent_filter import LatentFilter
from embodied_tactile.model.module import LatentFilterModule
from embodied_tactile.model.networks import ConvDecoder, ConvEncoder
from embodied_tactile.run.paths import config_dir
from embodied_tactile.run.runtime import HandOverStatistics

from embodied_tactile.data.pendulum import N_OBJECTS, UNSEEN_SYSTEMS, PendulumData, generate, render

#: the benchmark's modality: one image channel (the channel name is only a label here)
MODALITY = {"name": "pendulum", "channels": ["fsr_t"], "fusion": "single"}
READOUTS = ("z_angle", "z_velocity", "y_frequency", "y_damping")
#: where the object's parameters live when y does not hold them: q_filt mean z_T -> w0 / d
#: and whether y_t carries the moving state instead (y_t -> angular velocity, frames t >= skip)
DIAGNOSTIC_READOUTS = ("z_frequency", "z_damping", "y_velocity")


@dataclass
class PendulumRun:
    model: LatentFilter
    steps: int
    train_s: float
    losses: list = field(default_factory=list)


def build_model(n_z: int = 8, n_y: int = 4, **kwargs: Any) -> LatentFilter:
    """The benchmark's Latent Filter: one channel, 1-D action, 8 objects, the project's
    defaults (:class:`LatentFilter`) except for what the pendulum's measurements used
    (docs/experiments/pendulum.md, default_recipe.md): the images as they are
    (``input_standardize=False``) and a prior whose sigma (and, with ``prior.labels``, object
    codes) are learned. ``kwargs`` go to :class:`LatentFilter` (remedies such as
    ``obs_dropout``); ``prior`` entries are merged."""
    prior = {"learn_sigma": True, "learn_embedding": True, **dict(kwargs.pop("prior", None) or {})}
    kwargs = {"input_standardize": False, **kwargs}
    return LatentFilter(MODALITY, n_z=n_z, n_y=n_y, n_a=1, n_objects=N_OBJECTS, prior=prior, **kwargs)


def _batch(data: PendulumData, idx: np.ndarray) -> dict[str, torch.Tensor]:
    return {"obs": torch.from_numpy(data.obs[idx]), "actions": torch.from_numpy(data.actions[idx]),
            "object_id": torch.from_numpy(data.object_id[idx])}


#: the pendulum measurements' learning rate (docs/experiments/pendulum.md), the benchmark's own setting
LR = 1e-3


class PendulumSequences(Dataset):
    """One pendulum sequence per item: ``obs`` (T, 1, 28, 28), ``actions`` (T, 1), ``object_id``.

    ``context=True`` (the context objective, docs/reference/model.md "The context objective") adds
    ``context_obs`` / ``context_actions``: another sequence of the same system, drawn by a
    generator seeded with ``seed`` (the loader reads items in one process, in order, so the
    draws repeat with the seed). The system id pairs the sequences and reaches the model
    only as ``object_id``, which the context objective never reads."""

    def __init__(self, data: PendulumData, context: bool = False, seed: int = 0) -> None:
        self.data = data
        self.context = bool(context)
        self._rng = np.random.default_rng(seed)
        #: system id -> its sequences (only the context pairing reads it)
        self._same = ({int(o): np.flatnonzero(data.object_id == o) for o in np.unique(data.object_id)}
                      if self.context else {})
        if self.context and min(len(v) for v in self._same.values()) < 2:
            raise ValueError("pendulum context pairing needs at least 2 sequences per system")

    def __len__(self) -> int:
        return len(self.data)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        item = {"obs": torch.from_numpy(self.data.obs[i]), "actions": torch.from_numpy(self.data.actions[i]),
                "object_id": torch.as_tensor(self.data.object_id[i])}
        if self.context:
            others = self._same[int(self.data.object_id[i])]
            j = int(self._rng.choice(others[others != i]))
            item.update(context_obs=torch.from_numpy(self.data.obs[j]),
                        context_actions=torch.from_numpy(self.data.actions[j]))
        return item


class PendulumDataModule(L.LightningDataModule):
    """The benchmark's training data for the project's Trainer: ``steps`` batches of
    ``batch_size`` sequences drawn with replacement (seeded), and the data's
    :class:`~embodied_tactile.data.statistics.DataStatistics` (handed to the module by
    :class:`~embodied_tactile.run.runtime.HandOverStatistics`)."""

    def __init__(self, data: PendulumData, steps: int, batch_size: int = 16, seed: int = 0,
                 context: bool = False) -> None:
        super().__init__()
        self.sequences = PendulumSequences(data, context=context, seed=seed)
        self.steps, self.batch_size, self.seed = int(steps), int(batch_size), int(seed)
        self.statistics = DataStatistics.of([{"obs": data.obs}], len(data))

    def train_dataloader(self) -> DataLoader:
        draws = RandomSampler(self.sequences, replacement=True, num_samples=self.steps * self.batch_size,
                              generator=torch.Generator().manual_seed(self.seed))
        return DataLoader(self.sequences, batch_size=self.batch_size, sampler=draws)


class _Losses(L.Callback):
    """Every step's training loss, printed every ``log_every`` steps (0: never)."""

    def __init__(self, log_every: int = 0) -> None:
        self.losses: list[float] = []
        self.log_every = int(log_every)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        self.losses.append(float(outputs["loss"]))
        if self.log_every and trainer.global_step % self.log_every == 0:
            m = trainer.callback_metrics
            print(f"step {trainer.global_step}: loss {self.losses[-1]:.1f} nll {float(m['train/nll']):.1f} "
                  f"kl_z {float(m['train/kl_z']):.1f} kl_y {float(m['train/kl_y']):.2f}", flush=True)


def default_annealing() -> AnnealingSchedule:
    """The tactile scenes' default schedule, read from configs/annealing/linear.yaml."""
    return instantiate(OmegaConf.load(Path(config_dir()) / "annealing" / "linear.yaml").schedule)


def train(model: LatentFilter, data: PendulumData, steps: int, batch_size: int = 16, seed: int = 0,
          lr: float = LR, annealing: Any = None, log_every: int = 0,
          context: Optional[dict] = None) -> PendulumRun:
    """Unsupervised training by the project's LightningModule and Trainer (the training step,
    annealing and optimiser of the tactile scenes): the annealing group's default schedule
    (configs/annealing/linear.yaml: linear KL warm-up over the first 10 % of the steps, the
    plain ELBO afterwards) unless ``annealing`` names one, and Adam at ``lr``; the object
    label goes to the prior only, as in training on the tactile data. ``context``: the
    context objective's settings (:class:`~embodied_tactile.model.options.ContextOptions`;
    ``source`` must be ``trial``: y from another sequence of the same system); None = the
    filtering ELBO."""
    torch.manual_seed(seed)
    if context is not None and dict(context).get("source", "trial") != "trial":
        raise ValueError(f"the pendulum pairs whole sequences: context.source must be 'trial', got {context}")
    module = LatentFilterModule(model, annealing=annealing if annealing is not None else default_annealing(),
                                optimizer={"name": "Adam", "lr": lr}, context=context)
    losses = _Losses(log_every)
    trainer = L.Trainer(max_steps=steps, accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
                        num_sanity_val_steps=0, callbacks=[HandOverStatistics(), losses])
    t0 = time.perf_counter()
    quiet.silence_third_party()
    trainer.fit(module, datamodule=PendulumDataModule(data, steps, batch_size, seed, context=context is not None))
    model.eval()
    return PendulumRun(model, steps, time.perf_counter() - t0, losses.losses)


@torch.no_grad()
def latents(model: LatentFilter, data: PendulumData, chunk: int = 64) -> dict[str, np.ndarray]:
    """z_mean (N, T, n_z) and y_mean (N, T, n_y) of the filter (eval mode, no sampling)."""
    outs = [model.infer_latents(_batch(data, np.arange(s, min(s + chunk, len(data)))))
            for s in range(0, len(data), chunk)]
    return {k: torch.cat([o[k] for o in outs]).numpy() for k in ("z_mean", "y_mean")}


def _r2_pair(x_tr: np.ndarray, t_tr: np.ndarray, x_te: np.ndarray, t_te: np.ndarray, groups: np.ndarray,
             seed: int) -> tuple[float, float]:
    """(linear R^2, RBF kernel ridge R^2) of rows x -> targets t, fitted on the training rows."""
    lin = LinearRegression().fit(x_tr, t_tr)
    r2_lin = r2_score(t_te, lin.predict(x_te))
    # one row per "sequence" for fit_alignment; CV folds grouped by the true sequence
    align = fit_alignment(x_tr[:, None, :], t_tr, groups=groups, final_segment=1, frames_per_sequence=1,
                          seed=seed, n_threads=1)
    r2_krr = r2_score(t_te, align.predict(x_te)[:, 0, :])
    return float(r2_lin), float(r2_krr)


def readouts(model: LatentFilter, train_data: PendulumData, test_data: PendulumData, skip: int = 5,
             max_rows: int = 1500, seed: int = 0) -> dict[str, tuple[float, float]]:
    """{read-out: (linear R^2, kernel R^2)} on ``test_data``, fitted on ``train_data``
    (z rows: frames t >= ``skip``, at most ``max_rows`` training rows drawn at random)."""
    lat_tr, lat_te = latents(model, train_data), latents(model, test_data)
    rng = np.random.default_rng(seed)
    n, t_len = train_data.theta.shape
    seq = np.repeat(np.arange(n), t_len - skip)

    def rows(lat, key):
        return lat[key][:, skip:].reshape(-1, lat[key].shape[-1])

    z_tr, z_te = rows(lat_tr, "z_mean"), rows(lat_te, "z_mean")
    pick = rng.choice(len(z_tr), size=min(max_rows, len(z_tr)), replace=False)
    th_tr, th_te = train_data.theta[:, skip:].ravel(), test_data.theta[:, skip:].ravel()
    ang_tr = np.stack([np.cos(th_tr), np.sin(th_tr)], -1)
    ang_te = np.stack([np.cos(th_te), np.sin(th_te)], -1)
    om_tr, om_te = train_data.omega[:, skip:].reshape(-1, 1), test_data.omega[:, skip:].reshape(-1, 1)
    yr_tr, yr_te = rows(lat_tr, "y_mean"), rows(lat_te, "y_mean")
    res = {
        "z_angle": _r2_pair(z_tr[pick], ang_tr[pick], z_te, ang_te, seq[pick], seed),
        "z_velocity": _r2_pair(z_tr[pick], om_tr[pick], z_te, om_te, seq[pick], seed),
        "y_velocity": _r2_pair(yr_tr[pick], om_tr[pick], yr_te, om_te, seq[pick], seed),
    }
    groups = np.arange(n)
    for latent in ("y", "z"):  # the last frame's mean -> the object's parameters
        x_tr, x_te = lat_tr[f"{latent}_mean"][:, -1], lat_te[f"{latent}_mean"][:, -1]
        for name, param in (("frequency", "w0"), ("damping", "damping")):
            t_tr, t_te = getattr(train_data, param)[:, None], getattr(test_data, param)[:, None]
            res[f"{latent}_{name}"] = _r2_pair(x_tr, t_tr, x_te, t_te, groups, seed)
    return res


@torch.no_grad()
def diagnostics(model: LatentFilter, data: PendulumData) -> dict[str, float]:
    """Where the filter's information comes from, on ``data`` (eval mode, means):
    ``transition_weight`` = mean over t >= 2 and dimensions of s2 / (s2 + v2), the weight of
    the transition mean p_t in q_filt's mean (0: q_filt follows the encoder), the median
    encoder and transition variances, and the ELBO terms per sequence (one sample)."""
    model.eval()
    b = _batch(data, np.arange(len(data)))
    out = model(b["obs"], b["actions"], sample=False)
    enc_v, zp_v = out["enc_var"][:, 1:], out["zp_var"][:, 1:]
    terms = model.elbo_terms(b, sample=True)
    return {"transition_weight": float((enc_v / (enc_v + zp_v)).mean()),
            "encoder_var": float(enc_v.median()), "transition_var": float(zp_v.median()),
            **{k: float(terms[k]) for k in ("nll", "kl_z", "kl_y")}}


#: LatentFilter training-remedy attributes and their values for the plain single-sample ELBO
PLAIN_ELBO = {"obs_dropout": 0.0}


def gradient_snr(model: LatentFilter, data: PendulumData, n_draws: int = 16, batch_size: int = 16,
                 seed: int = 0) -> dict[str, float]:
    """One-sample ELBO noise: gradients of the negative ELBO on ONE fixed batch for
    ``n_draws`` independent samples; per network (encoder, decoder, transition, y
    posterior, prior) the median over its parameters of |mean| / std of the gradient
    (< 1: a single sample's gradient is mostly noise; K samples scale it by sqrt(K))."""
    model.train()
    batch = _batch(data, np.random.default_rng(seed).integers(0, len(data), batch_size))
    nets = list(model.observation.modules())  # one encoder/decoder, or one per late-fusion pathway
    parts = {"encoder": nn.ModuleList(m for m in nets if isinstance(m, ConvEncoder)),
             "decoder": nn.ModuleList(m for m in nets if isinstance(m, ConvDecoder)), "transition": model.transition,
             "y_posterior": model.y_posterior, "prior": model.prior}
    grads: dict[str, list] = {k: [] for k in parts}
    torch.manual_seed(seed)
    saved = {name: getattr(model, name) for name in PLAIN_ELBO}
    for name, value in PLAIN_ELBO.items():  # the plain single-sample ELBO, whatever remedies trained the model
        setattr(model, name, value)
    try:
        params = {k: [p for p in mod.parameters() if p.requires_grad] for k, mod in parts.items()}
        flat = [p for ps in params.values() for p in ps]
        for _ in range(n_draws):  # gradients by autograd.grad: the parameters' .grad stays untouched
            t = model.elbo_terms(batch)
            g = torch.autograd.grad(t["nll"] + t["kl_z"] + t["kl_y"], flat, allow_unused=True)
            at = 0
            for k, ps in params.items():
                part = [gi for gi in g[at:at + len(ps)] if gi is not None]
                at += len(ps)
                grads[k].append(torch.cat([gi.flatten() for gi in part]))
    finally:
        for name, value in saved.items():
            setattr(model, name, value)
    out = {}
    for k, g in grads.items():
        g = torch.stack(g)
        out[k] = float((g.mean(0).abs() / (g.std(0) + 1e-12)).median())
    return out


@torch.no_grad()
def open_loop(model: LatentFilter, data: PendulumData, n_filter: int = 20, horizon: int = 40
              ) -> dict[str, np.ndarray]:
    """Image MSE per horizon h = 1..horizon (arrays of length ``horizon``) against the
    noiseless rendering of frame n_filter + h: ``model`` (:meth:`LatentFilter.predict`),
    ``last_frame`` (the last observed, noisy frame) and ``last_clean`` (its noiseless
    rendering)."""
    if data.obs.shape[1] < n_filter + horizon:
        raise ValueError(f"open-loop prediction needs {n_filter + horizon} frames, the data has {data.obs.shape[1]}")
    obs = torch.from_numpy(data.obs[:, :n_filter])
    acts = torch.from_numpy(data.actions[:, :n_filter + horizon])
    pred = model.predict(obs, acts, horizon)["recon"][:, :, 0].numpy()
    target = render(data.theta[:, n_filter:n_filter + horizon])
    last = data.obs[:, n_filter - 1, 0][:, None].astype(np.float64)
    last_clean = render(data.theta[:, n_filter - 1])[:, None]
    mean_image = render(data.theta).mean(axis=(0, 1))
    mse = lambda x: ((x - target) ** 2).mean(axis=(0, 2, 3))  # noqa: E731
    return {"model": mse(pred), "last_frame": mse(last), "last_clean": mse(last_clean),
            "mean_image": mse(mean_image)}


def run(steps: int, seed: int = 0, batch_size: int = 16, n_train: int = 128, n_test: int = 8, n_steps: int = 60,
        model_kwargs: Optional[dict] = None, annealing: Any = None, log_every: int = 0,
        n_filter: int = 20, horizon: int = 40, max_rows: int = 1500, snr_draws: int = 16,
        context: Optional[dict] = None) -> dict[str, Any]:
    """Generate (train seed ``seed``, held-out sequences of the training systems seed
    ``seed + 1000``, :data:`~.pendulum.UNSEEN_SYSTEMS` seed ``seed + 2000``, ``n_test`` per
    system), read out the untrained network (the floor), train, read out, predict.
    ``readouts`` / ``readouts_unseen``: held-out sequences of the training systems / of the
    unseen systems, both fitted on the training sequences; ``*_untrained``: the same
    read-outs of the network at its initialisation. ``context``: see :func:`train`."""
    train_data = generate(n_train, seed=seed, n_steps=n_steps)
    test_data = generate(n_test, seed=seed + 1000, n_steps=n_steps)
    unseen_data = generate(n_test, seed=seed + 2000, n_steps=n_steps, systems=UNSEEN_SYSTEMS)
    torch.manual_seed(seed)
    model = build_model(**(model_kwargs or {}))
    floor = {f"{key}_untrained": readouts(model, train_data, data, max_rows=max_rows, seed=seed)
             for key, data in (("readouts", test_data), ("readouts_unseen", unseen_data))}
    fit = train(model, train_data, steps, batch_size, seed, annealing=annealing, log_every=log_every,
                context=context)
    t0 = time.perf_counter()
    res = readouts(model, train_data, test_data, max_rows=max_rows, seed=seed)
    res_unseen = readouts(model, train_data, unseen_data, max_rows=max_rows, seed=seed)
    pred = open_loop(model, test_data, n_filter, horizon) if n_steps >= n_filter + horizon else None
    return {"readouts": res, "readouts_unseen": res_unseen, **floor, "open_loop": pred,
            "diagnostics": diagnostics(model, test_data),
            "gradient_snr": gradient_snr(model, train_data, snr_draws, seed=seed), "train_s": fit.train_s, "eval_s": time.perf_counter() - t0,
            "model": model, "losses": fit.losses}
