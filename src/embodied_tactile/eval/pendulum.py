"""Read-outs of a Latent Filter trained on the pendulum scene (``python train.py
experiment=pendulum``; docs/reference/model.md, "Pendulum benchmark"), beside the run's own
KRR NMSE on (w0, d): what ``experiments/pendulum.py`` prints and the tests check.

Read-outs on held-out sequences, each fitted on the training sequences only, linear
(least squares) and RBF kernel ridge (:func:`embodied_tactile.eval.krr.fit_alignment`,
grid-searched on training rows, folds grouped by sequence), scored by R^2 (averaged over
outputs):

* ``z_angle``: q_filt mean z_t -> (cos theta_t, sin theta_t), frames t >= ``skip``;
* ``z_velocity``: z_t -> theta'_t, frames t >= ``skip``;
* ``y_frequency`` / ``y_damping``: q(y_T) mean at the last frame -> w0 / d;
* the same read-outs on systems never seen in training (:data:`~embodied_tactile.data.pendulum.UNSEEN_SYSTEMS`),
  and every read-out of the untrained network;
* diagnostics ``z_frequency`` / ``z_damping``: q_filt mean z_T at the last frame -> w0 / d
  (a model can keep the trial-constant parameters in z instead of y), and ``y_velocity``:
  q(y_t) mean -> theta'_t, frames t >= ``skip`` (a per-step y can carry the moving state).

The latents are read by :func:`~embodied_tactile.eval.latents.collect_split_latents`, as the
run's KRR read-out and evaluate.py read them. Open-loop prediction: filter the first
``n_filter`` frames, then :meth:`LatentFilter.predict` the next ``horizon`` frames under the
known actions; image MSE per horizon against the noiseless rendering, next to copying the
last observed (noisy) frame and copying its noiseless rendering (the stricter baseline).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch
from sklearn.linear_model import LinearRegression
from sklearn.metrics import r2_score
from torch import nn

from ..data.pendulum import PendulumData, render
from ..model.latent_filter import LatentFilter
from ..model.networks import ConvDecoder, ConvEncoder
from .latents import collect_split_latents
from .krr import fit_alignment

READOUTS = ("z_angle", "z_velocity", "y_frequency", "y_damping")
#: where the object's parameters live when y does not hold them: q_filt mean z_T -> w0 / d
#: and whether y_t carries the moving state instead (y_t -> angular velocity, frames t >= skip)
DIAGNOSTIC_READOUTS = ("z_frequency", "z_damping", "y_velocity")
#: LatentFilter training-remedy attributes and their values for the plain single-sample ELBO
PLAIN_ELBO = {"obs_dropout": 0.0}


def _batch(data: PendulumData, idx: np.ndarray) -> dict[str, torch.Tensor]:
    return {"obs": torch.from_numpy(data.obs[idx]), "actions": torch.from_numpy(data.actions[idx]),
            "object_id": torch.from_numpy(data.object_id[idx])}


def split_latents(module, datamodule, held: str = "test") -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(training, held-out) latents ``z`` (N, T, n_z) and ``y`` (N, T, n_y) of a set-up
    :class:`~embodied_tactile.data.pendulum_module.PendulumDataModule`; ``held``: ``test``
    (held-out sequences of the training systems) or ``unseen`` (the unseen systems)."""
    loader = {"test": datamodule.test_dataloader, "unseen": datamodule.unseen_dataloader}[held]()
    return collect_split_latents(module, list(datamodule.train_eval_dataloader()), list(loader), latent="both")


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


def readouts(lat_tr: dict, lat_te: dict, train_data: PendulumData, test_data: PendulumData, skip: int = 5,
             max_rows: int = 1500, seed: int = 0) -> dict[str, tuple[float, float]]:
    """{read-out: (linear R^2, kernel R^2)} on ``test_data`` (latents ``lat_te``), fitted on
    ``train_data`` (``lat_tr``) (z rows: frames t >= ``skip``, at most ``max_rows`` training
    rows drawn at random)."""
    rng = np.random.default_rng(seed)
    n, t_len = train_data.theta.shape
    seq = np.repeat(np.arange(n), t_len - skip)

    def rows(lat, key):
        return lat[key][:, skip:].reshape(-1, lat[key].shape[-1])

    z_tr, z_te = rows(lat_tr, "z"), rows(lat_te, "z")
    pick = rng.choice(len(z_tr), size=min(max_rows, len(z_tr)), replace=False)
    th_tr, th_te = train_data.theta[:, skip:].ravel(), test_data.theta[:, skip:].ravel()
    ang_tr = np.stack([np.cos(th_tr), np.sin(th_tr)], -1)
    ang_te = np.stack([np.cos(th_te), np.sin(th_te)], -1)
    om_tr, om_te = train_data.omega[:, skip:].reshape(-1, 1), test_data.omega[:, skip:].reshape(-1, 1)
    yr_tr, yr_te = rows(lat_tr, "y"), rows(lat_te, "y")
    res = {
        "z_angle": _r2_pair(z_tr[pick], ang_tr[pick], z_te, ang_te, seq[pick], seed),
        "z_velocity": _r2_pair(z_tr[pick], om_tr[pick], z_te, om_te, seq[pick], seed),
        "y_velocity": _r2_pair(yr_tr[pick], om_tr[pick], yr_te, om_te, seq[pick], seed),
    }
    groups = np.arange(n)
    for latent in ("y", "z"):  # the last frame's mean -> the object's parameters
        x_tr, x_te = lat_tr[latent][:, -1], lat_te[latent][:, -1]
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


def gradient_snr(model: LatentFilter, data: PendulumData, n_draws: int = 16, batch_size: int = 16,
                 seed: int = 0) -> dict[str, float]:
    """One-sample ELBO noise: gradients of the negative ELBO on ONE fixed batch for
    ``n_draws`` independent samples; per network (encoder, decoder, transition, y
    posterior, prior) the median over its parameters of |mean| / std of the gradient
    (< 1: a single sample's gradient is mostly noise; K samples scale it by sqrt(K))."""
    was_training = model.training
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
        model.train(was_training)
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
    ``last_frame`` (the last observed, noisy frame), ``last_clean`` (its noiseless
    rendering) and ``mean_image`` (the mean noiseless image)."""
    if data.obs.shape[1] < n_filter + horizon:
        raise ValueError(f"open-loop prediction needs {n_filter + horizon} frames, the data has {data.obs.shape[1]}")
    model.eval()
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


def read_out(trained, untrained, datamodule, n_filter: int = 20, horizon: int = 40, max_rows: int = 1500,
             snr_draws: int = 16, seed: int = 0) -> dict[str, Any]:
    """Every read-out of a trained pendulum run: ``trained`` / ``untrained`` LightningModules
    (:func:`embodied_tactile.eval.runs.load_module` / ``untrained_module``), ``datamodule`` a
    set-up PendulumDataModule. ``readouts`` / ``readouts_unseen``: held-out sequences of the
    training systems / of the unseen systems, both fitted on the training sequences;
    ``*_untrained``: the same read-outs of the network at its initialisation; ``open_loop``
    (None when the sequences are shorter than ``n_filter + horizon``), ``diagnostics`` on the
    held-out sequences, ``gradient_snr`` on the training sequences, ``eval_s``."""
    t0 = time.perf_counter()
    data = datamodule.data
    res: dict[str, Any] = {}
    for module, suffix in ((untrained, "_untrained"), (trained, "")):
        for held, key in (("test", "readouts"), ("unseen", "readouts_unseen")):
            lat_tr, lat_te = split_latents(module, datamodule, held)
            res[key + suffix] = readouts(lat_tr, lat_te, data["train"], data[held], max_rows=max_rows, seed=seed)
    net = trained.model
    res["open_loop"] = (open_loop(net, data["test"], n_filter, horizon)
                        if data["test"].obs.shape[1] >= n_filter + horizon else None)
    res["diagnostics"] = diagnostics(net, data["test"])
    res["gradient_snr"] = gradient_snr(net, data["train"], snr_draws, seed=seed)
    net.eval()
    res["eval_s"] = time.perf_counter() - t0
    return res


__all__ = ["DIAGNOSTIC_READOUTS", "PLAIN_ELBO", "READOUTS", "diagnostics", "gradient_snr", "open_loop", "read_out",
           "readouts", "split_latents"]
