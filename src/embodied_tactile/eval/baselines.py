"""Baselines scored with the same splits, the same alignment and the same :func:`nmse`.

(a) Hand-crafted features -> KRR: the causal features of :mod:`embodied_tactile.data.features`
    (computed from the preprocessed sequences the model sees), read by the same alignment as
    the latents; the hybrid reader (:func:`evaluate_hybrid`) reads [features, latents].

(b) Supervised GRU regressor (upper bound): small conv frame encoder + GRU over
    [frame features, action] -> the 4 standardised factors at every step, trained on the
    train split only (MSE at every frame, NaN factors masked).

(c) Mean predictor: the train mean at every frame (NMSE ~ 1 by construction).

(d) Object-code regression (:func:`evaluate_code_regression`): the Latent Filter's inference
    path trained to output a fixed random code per training object, its outputs aligned to
    the factors by the KRR: the bound of the label-conditioned prior's route into y.
"""

from __future__ import annotations

import time
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from ..options.alignment import AlignmentOptions
from ..options.evaluation import GRUOptions, HandcraftedOptions
from ..model.options import LatentFilterOptions
from ..data.features import handcrafted_features
from .krr import alignment_kwargs, assert_disjoint, fit_alignment
from .results import Results, evaluate_latents



# =========================================================================== (a) features
def evaluate_handcrafted(train: Mapping[str, Any], test: Mapping[str, Any], channels: Sequence[str], *,
                         alignment: AlignmentOptions | None = None, split: str = "trial",
                         handcrafted: HandcraftedOptions | Mapping[str, Any] | None = None, **meta) -> Results:
    """Hand-crafted features -> the same KRR alignment -> Results (method 'handcrafted_krr').
    ``alignment`` and ``split``: as :func:`~embodied_tactile.eval.results.evaluate_latents`;
    ``handcrafted``: the features' thresholds (:func:`handcrafted_features`).

    ``train`` / ``test``: dicts with ``obs``, ``actions``, ``factors``, ``object_id``,
    ``action_index`` (and optional ``seq_id``). ``meta``: modality / skin / primitive / source.
    """
    assert_disjoint(train.get("seq_id"), test.get("seq_id"))
    t0 = time.perf_counter()
    f_tr, names = handcrafted_features(train["obs"], train["actions"], channels, handcrafted)
    f_te, _ = handcrafted_features(test["obs"], test["actions"], channels, handcrafted)
    t1 = time.perf_counter()
    align = fit_alignment(f_tr, train["factors"], ids=train.get("seq_id"),
                          **alignment_kwargs(alignment, split, train.get("object_id")))
    t2 = time.perf_counter()
    pred = align.predict(f_te, ids=test.get("seq_id"))
    t3 = time.perf_counter()
    n_te = len(f_te)
    params = {"alignment": align.params, "features": names, "feature_s": t1 - t0, "krr_fit_s": t2 - t1,
              "train_time_s": t2 - t0,
              "inference_s_per_sequence": ((t1 - t0) * n_te / (n_te + len(f_tr)) + (t3 - t2)) / max(1, n_te)}
    return Results(pred, test["factors"], test["object_id"], test["action_index"], method="handcrafted_krr",
                   n_train=len(f_tr), latents_last=f_te[:, -1], params=params,
                   seq_id=test.get("seq_id"), **meta)


def evaluate_hybrid(train: Mapping[str, Any], test: Mapping[str, Any], channels: Sequence[str], *, latent: str = "y",
                    alignment: AlignmentOptions | None = None, split: str = "trial",
                    handcrafted: HandcraftedOptions | Mapping[str, Any] | None = None, **meta) -> Results:
    """The hybrid reader (method 'hybrid_krr'): the same KRR alignment on [hand-crafted
    features, the run's latents] frame by frame (features (n, T, k) then ``latent`` (n, T,
    d), :func:`~embodied_tactile.eval.results.select_latents`; the alignment standardises
    every column on the training rows). It answers whether the latents add what the features
    miss; it is reported beside the latents alone, never in their place. ``train`` /
    ``test``: as :func:`evaluate_handcrafted`, with the latents."""
    from .results import select_latents

    assert_disjoint(train.get("seq_id"), test.get("seq_id"))
    t0 = time.perf_counter()
    f_tr, names = handcrafted_features(train["obs"], train["actions"], channels, handcrafted)
    f_te, _ = handcrafted_features(test["obs"], test["actions"], channels, handcrafted)
    x_tr = np.concatenate([f_tr, select_latents(train, latent)], axis=-1)
    x_te = np.concatenate([f_te, select_latents(test, latent)], axis=-1)
    t1 = time.perf_counter()
    align = fit_alignment(x_tr, train["factors"], ids=train.get("seq_id"),
                          **alignment_kwargs(alignment, split, train.get("object_id")))
    t2 = time.perf_counter()
    pred = align.predict(x_te, ids=test.get("seq_id"))
    params = {"alignment": align.params, "features": names, "latent": latent, "feature_s": t1 - t0,
              "krr_fit_s": t2 - t1}
    return Results(pred, test["factors"], test["object_id"], test["action_index"], method="hybrid_krr",
                   n_train=len(x_tr), latents_last=x_te[:, -1], params=params, seq_id=test.get("seq_id"), **meta)


# =========================================================================== (c) mean
class MeanPredictor:
    """Predicts the train mean of every factor at every frame."""

    def fit(self, factors) -> "MeanPredictor":
        self.mean_ = np.nanmean(np.asarray(factors, dtype=np.float64), axis=0)
        return self

    def predict(self, n: int, t: int = 1) -> np.ndarray:
        return np.broadcast_to(self.mean_, (int(n), int(t), len(self.mean_))).copy()


def evaluate_mean(train: Mapping[str, Any], test: Mapping[str, Any], n_frames: int = 1, **meta) -> Results:
    """Mean-predictor Results (method 'mean')."""
    assert_disjoint(train.get("seq_id"), test.get("seq_id"))
    m = MeanPredictor().fit(train["factors"])
    n = len(test["factors"])
    return Results(m.predict(n, n_frames), test["factors"], test["object_id"], test["action_index"], method="mean",
                   n_train=len(train["factors"]), params={"train_time_s": 0.0, "inference_s_per_sequence": 0.0},
                   seq_id=test.get("seq_id"), **meta)


# =========================================================================== (b) GRU
def _batches(data, actions=None, factors=None, *, batch_size: int, shuffle: bool, rng) -> Iterable[dict]:
    """Arrays -> batch dicts; an iterable of batch dicts (a DataLoader) passes through."""
    if actions is None:
        yield from data
        return
    n = len(data)
    order = rng.permutation(n) if shuffle else np.arange(n)
    for s in range(0, n, batch_size):
        idx = order[s : s + batch_size]
        b = {"obs": data[idx], "actions": actions[idx]}
        if factors is not None:
            b["factors"] = factors[idx]
        yield b


#: GRURegressor ``arch`` -> the method name its Results carry
SUPERVISED_ARCHS = {"gru": "gru", "latent_filter": "latent_filter_supervised"}


class GRURegressor:
    """Supervised upper bound: conv frame encoder + GRU -> standardised factors per frame.

    ``fit(obs, actions, factors)`` with arrays (obs (n, T, C, H, W), actions (n, T, 6),
    factors (n, 4)), or ``fit(loader)`` with an iterable of batch dicts (``obs``,
    ``actions``, ``factors``; re-iterated every epoch). ``predict`` returns (n, T, 4) in
    original units. Defaults: :class:`~embodied_tactile.options.evaluation.GRUOptions` (what
    evaluate.py trains). ``max_batches_per_epoch`` / small ``epochs`` make a tiny test run.
    ``window`` / ``windows_per_trial`` (array input only): train on that many random
    ``window``-frame crops of every sequence per epoch, as the Latent Filter's CPU budget
    does (same frames per epoch, more optimiser steps); prediction always runs over whole
    sequences. ``input_standardize``: the network sees each channel shifted and scaled by
    its training-set mean and standard deviation (set in ``fit``); without it, a small
    signal on a large offset (the acc image at pressing: spread ~0.03 around 0.5) left the
    GRU at the mean predictor (docs/experiments/modality_bounds.md, "Where the pressing information is lost").
    ``arch="latent_filter"``: the network is the Latent Filter's own inference path instead
    of the conv + GRU (``LatentFilter(modality, **latent_filter)``, the default sizes of
    configs/model/latent_filter.yaml: encoder, Bayesian fusion with the transition, the y
    LSTM; every frame observed, means, no decoder) with a linear head on q(y_t)'s mean:
    what the unsupervised model's y could hold if it were told the factors, at the same
    budget (method ``latent_filter_supervised``; ``modality`` is required for it).
    ``n_out``: the head's outputs (4 factors; :func:`evaluate_code_regression` fits n_y-
    dimensional object codes instead, any (n, n_out) target works).
    """

    def __init__(self, in_channels: int, action_dim: int = 6, hidden: int = GRUOptions.hidden,
                 feat: int = GRUOptions.feat, epochs: int = GRUOptions.epochs, lr: float = GRUOptions.lr,
                 batch_size: int = GRUOptions.batch_size, weight_decay: float = GRUOptions.weight_decay,
                 max_batches_per_epoch: int | None = GRUOptions.max_batches_per_epoch,
                 window: int | None = GRUOptions.window, windows_per_trial: int = GRUOptions.windows_per_trial,
                 seed: int = 0, device: str = "cpu", input_standardize: bool = GRUOptions.input_standardize,
                 arch: str = GRUOptions.arch, modality: Any = None, latent_filter: Mapping[str, Any] | None = None,
                 n_out: int = 4):
        import torch
        from torch import nn

        if arch not in SUPERVISED_ARCHS:
            raise ValueError(f"arch must be one of {tuple(SUPERVISED_ARCHS)}, got {arch!r}")
        if arch == "latent_filter" and modality is None:
            raise ValueError("arch='latent_filter' needs the modality (a configs/modality name or mapping)")

        if window is not None and int(window) < 1:
            raise ValueError(f"GRU window must be >= 1 frame, got {window}")
        if int(windows_per_trial) < 1:
            raise ValueError(f"GRU windows_per_trial must be >= 1, got {windows_per_trial}")
        self.cfg = dict(in_channels=in_channels, action_dim=action_dim, hidden=hidden, feat=feat, epochs=epochs,
                        lr=lr, batch_size=batch_size, weight_decay=weight_decay,
                        max_batches_per_epoch=max_batches_per_epoch, window=window,
                        windows_per_trial=int(windows_per_trial), seed=seed, device=device,
                        input_standardize=bool(input_standardize), arch=arch, n_out=int(n_out))
        self.method = SUPERVISED_ARCHS[arch]
        torch.manual_seed(seed)

        class Net(nn.Module):
            def __init__(self):
                super().__init__()
                self.enc = nn.Sequential(
                    nn.Conv2d(in_channels, 16, 3, stride=2, padding=1), nn.ReLU(),
                    nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.ReLU(),
                    nn.AdaptiveAvgPool2d(4), nn.Flatten(), nn.Linear(32 * 16, feat), nn.ReLU(),
                )
                self.gru = nn.GRU(feat + action_dim, hidden, batch_first=True)
                self.head = nn.Linear(hidden, n_out)

            def forward(self, obs, actions):
                b, t = obs.shape[:2]
                f = self.enc(obs.reshape(b * t, *obs.shape[2:])).reshape(b, t, -1)
                h, _ = self.gru(torch.cat([f, actions], -1))
                return self.head(h)

        class LatentFilterNet(nn.Module):
            def __init__(self):
                super().__init__()
                from ..model import LatentFilter

                self.lf = LatentFilter(modality, n_a=action_dim, **dict(latent_filter or {}))
                self.head = nn.Linear(self.lf.n_y, n_out)

            def forward(self, obs, actions):
                seen = torch.ones(obs.shape[:2], dtype=torch.bool, device=obs.device)
                out = self.lf(obs, actions, sample=False, observed=seen, decode=False)
                return self.head(out["y_mean"])

        self.net = (Net() if arch == "gru" else LatentFilterNet()).to(device)
        self.history: list[float] = []

    def _t(self, x):
        import torch

        return torch.as_tensor(x, dtype=torch.float32, device=self.cfg["device"])

    def _obs(self, x):
        """obs batch -> the network's input tensor (standardised per channel if asked)."""
        t = self._t(x)
        if self.cfg["input_standardize"]:
            shape = (1, 1, -1) + (1,) * (t.dim() - 3)
            t = (t - self._t(self.in_mean_).view(shape)) / self._t(self.in_scale_).view(shape)
        return t

    def fit(self, data, actions=None, factors=None) -> "GRURegressor":
        c = self.cfg
        if actions is not None:
            data, actions = np.asarray(data, np.float32), np.asarray(actions, np.float32)
            fac = np.asarray(factors, np.float64)
        elif c["window"] is not None or c["windows_per_trial"] != 1:
            raise ValueError("GRU training windows need array input (obs, actions, factors), not a loader")
        else:  # loader: one pass for the target statistics
            fac = np.concatenate([np.asarray(b["factors"], np.float64) for b in data])
        if c["input_standardize"]:
            from ..data.statistics import channel_stats

            chunks = ({"obs": data[i:i + 16]} for i in range(0, len(data), 16)) if actions is not None else data
            mean, sd = channel_stats(chunks)
            self.in_mean_, self.in_scale_ = mean, np.where(sd > 1e-12, sd, 1.0)
        self.y_mean_ = np.nanmean(fac, 0)
        sd = np.nanstd(fac, 0)
        self.y_scale_ = np.where(sd > 1e-12, sd, 1.0)
        rng = np.random.default_rng(c["seed"])
        t0 = time.perf_counter()

        def epoch_batches():
            if actions is None:
                yield from _batches(data, batch_size=c["batch_size"], shuffle=True, rng=rng)
                return
            for _ in range(c["windows_per_trial"]):
                obs_e, act_e = data, actions
                T = data.shape[1]
                if c["window"] is not None and c["window"] < T:
                    start = rng.integers(0, T - c["window"] + 1, size=len(data))
                    idx = start[:, None] + np.arange(c["window"])[None]
                    rows = np.arange(len(data))[:, None]
                    obs_e, act_e = data[rows, idx], actions[rows, idx]
                yield from _batches(obs_e, act_e, fac, batch_size=c["batch_size"], shuffle=True, rng=rng)

        def to_batch(b):
            y = (np.asarray(b["factors"], np.float64) - self.y_mean_) / self.y_scale_
            return {"obs": self._obs(b["obs"]), "actions": self._t(b["actions"]), "target": self._t(y)}

        from .supervised import EpochBatches, SupervisedRegression, fit

        module = SupervisedRegression(self.net, c["lr"], c["weight_decay"])
        fit(module, EpochBatches(epoch_batches, to_batch), c["epochs"], c["max_batches_per_epoch"], c["device"])
        self.history = module.epoch_losses
        self.train_time_s_ = time.perf_counter() - t0
        return self

    def predict(self, data, actions=None, batch_size: int | None = None) -> np.ndarray:
        import torch

        self.net.eval()
        outs = []
        with torch.no_grad():
            arr = actions is not None
            it = _batches(np.asarray(data, np.float32) if arr else data,
                          np.asarray(actions, np.float32) if arr else None, None,
                          batch_size=batch_size or self.cfg["batch_size"], shuffle=False, rng=None)
            for b in it:
                outs.append(self.net(self._obs(b["obs"]), self._t(b["actions"])).cpu().numpy().astype(np.float64))
        return np.concatenate(outs) * self.y_scale_ + self.y_mean_


def evaluate_gru(train: Mapping[str, Any], test: Mapping[str, Any], *, gru: Mapping[str, Any] | None = None,
                 **meta) -> Results:
    """Train :class:`GRURegressor` on ``train`` only, predict ``test`` -> Results (method 'gru')."""
    assert_disjoint(train.get("seq_id"), test.get("seq_id"))
    obs = np.asarray(train["obs"])
    model = GRURegressor(in_channels=obs.shape[2], action_dim=np.shape(train["actions"])[-1], **dict(gru or {}))
    model.fit(obs, train["actions"], train["factors"])
    t0 = time.perf_counter()
    pred = model.predict(test["obs"], test["actions"])
    dt = time.perf_counter() - t0
    params = {"gru": model.cfg, "train_time_s": model.train_time_s_, "loss_history": model.history,
              "inference_s_per_sequence": dt / max(1, len(pred))}
    return Results(pred, test["factors"], test["object_id"], test["action_index"], method=model.method,
                   n_train=len(obs), params=params, seq_id=test.get("seq_id"), **meta)


def evaluate_code_regression(train: Mapping[str, Any], test: Mapping[str, Any], *, gru: Mapping[str, Any],
                             alignment: AlignmentOptions | None = None, code_sigma: float = 0.5,
                             split: str = "trial", **meta) -> Results:
    """What the label-conditioned prior could put into y at a budget, if its pull acted like a
    regression (method ``latent_filter_codes``; docs/experiments/object_codes.md).

    Every object id gets a fixed random code, N(0, code_sigma^2) in each of n_y dimensions
    (n_y of ``gru["latent_filter"]``, else LatentFilter's default; drawn with ``gru["seed"]``), as the prior's
    fixed codes (``prior.learn_embedding: false``) are; :class:`GRURegressor` with
    ``arch="latent_filter"`` (required in ``gru``) learns to output its sequence's code at
    every frame, trained on ``train`` only; the predicted codes are then aligned to the
    factors by the evaluation's KRR (:func:`~embodied_tactile.eval.results.evaluate_latents`,
    fitted on the training sequences' predictions), as a Latent Filter's y is. Under the
    object split the held-out objects' codes are never seen (the bound is then for
    recognising the training objects only)."""
    gru = dict(gru)
    if gru.get("arch") != "latent_filter":
        raise ValueError(f"evaluate_code_regression trains the Latent Filter's inference path: gru['arch'] must be "
                         f"'latent_filter', got {gru.get('arch')!r}")
    assert_disjoint(train.get("seq_id"), test.get("seq_id"))
    n_y = dict(gru.get("latent_filter") or {}).get("n_y")
    n_y = int(LatentFilterOptions.n_y if n_y is None else n_y)  # the network's own default
    oid_tr, oid_te = np.asarray(train["object_id"]), np.asarray(test["object_id"])
    n_obj = int(max(oid_tr.max(), oid_te.max())) + 1
    codes = np.random.default_rng(int(gru.get("seed", 0))).normal(0.0, code_sigma, size=(n_obj, n_y))
    obs = np.asarray(train["obs"])
    model = GRURegressor(in_channels=obs.shape[2], action_dim=np.shape(train["actions"])[-1], n_out=n_y, **gru)
    model.fit(obs, train["actions"], codes[oid_tr])
    t0 = time.perf_counter()
    p_tr = model.predict(obs, train["actions"])
    p_te = model.predict(test["obs"], test["actions"])
    dt = time.perf_counter() - t0
    params = {"gru": model.cfg, "code_sigma": float(code_sigma), "train_time_s": model.train_time_s_,
              "loss_history": model.history, "inference_s_per_sequence": dt / max(1, len(p_tr) + len(p_te))}
    res, _ = evaluate_latents(dict(train, y=p_tr), dict(test, y=p_te), latent="y", method="latent_filter_codes",
                              alignment=alignment, params=params, split=split, **meta)
    return res
