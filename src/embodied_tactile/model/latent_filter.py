"""The Latent Filter (paper, section "Deep State-Space Model: Latent Filter") as a plain
``nn.Module``; the Lightning wrapper lives in :mod:`embodied_tactile.model.module`.

Time indexing (t = 1..T in the docs, 0-based in code):

* y_t ~ q(y_t | z_{t-1}, y_{t-1}, a_{t-1}): LSTMCell fed [z_{t-1}, a_{t-1}]. With
  ``y_update="direct"`` (the paper's recipe) its head gives q(y_t) itself; with ``"evidence"``
  (the class default, :class:`~.options.LatentFilterOptions`) it gives
  one step's Gaussian evidence about the trial-constant y and q(y_t) is the product of all
  evidence so far (see :class:`~embodied_tactile.model.networks.YPosterior`). At t = 1 the LSTM gets zeros from a zero state.
* p(z_t | z_{t-1}, y_t, a_t): residual MLP, N(z_{t-1} + f_mu, softplus(f_v) + floor).
* q_filt(z_t) = q(z_t | o_t) x p(z_t | z_{t-1}, y_t, a_t), normalised (variance form).
  z_1 comes from the encoder alone.
* Encoders and decoders run over all B*T frames in one call; only the LSTM/transition
  recursion is a Python loop. ``filter_step`` runs the same recursion one frame at a time.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict
from typing import Any, Optional

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from embodied_tactile.data.modality import Modality, load_modality

from .compat import upgrade_net_config
from .fusion import ObservationModel, observation_model
from .networks import (
    HierarchicalPrior,
    TransitionNet,
    YPosterior,
    float32_region,
    fuse_gaussians,
    gaussian_entropy,
    gaussian_nll_frames,
    kl_diag_gaussians,
    small_batch_convs,
)
from .options import ContextOptions, LatentFilterOptions, build


def to_plain(cfg: Any) -> Any:
    """Mapping / sequence (a Hydra DictConfig or ListConfig included: they are mappings and
    sequences) -> plain dict / list of checkpoint-safe primitives."""
    if isinstance(cfg, Mapping):
        return {str(k): to_plain(v) for k, v in cfg.items()}
    if isinstance(cfg, Sequence) and not isinstance(cfg, (str, bytes)):
        return [to_plain(v) for v in cfg]
    return cfg


def resolve_modality(modality: Any) -> dict[str, Any]:
    """A modality (its yaml mapping, a :class:`~embodied_tactile.data.modality.Modality`, or the
    name of a file in ``configs/modality/``) -> plain dict with ``name``, ``channels``,
    ``fusion`` and ``pathways`` as ``[[pathway, [channel indices]], ...]``. The modality is
    defined once, by its yaml (:mod:`embodied_tactile.data.modality`)."""
    mod = load_modality(modality) if isinstance(modality, str) else Modality.from_config(modality)
    out = {"name": mod.name, "channels": list(mod.channels), "fusion": mod.fusion,
           "pathways": [[name, idx] for name, idx in mod.pathway_indices()]}
    if mod.fusion == "late":
        out["pathway_channels"] = {name: list(chans) for name, chans in mod.pathways}
    return out


def _modality_config(modality: Any) -> dict[str, Any]:
    mod = load_modality(modality) if isinstance(modality, str) else Modality.from_config(modality)
    return mod.to_config()


_Y_STATE_KEYS = ("h", "c", "y_prec", "y_pm")
#: where the evidence product of q(y) starts (``y_start``): N(0, 1/y_prior_precision) or the
#: hierarchical prior's population marginal
Y_STARTS = ("fixed", "population")

def _state_to(z: Tensor, z_mean: Tensor, a: Tensor, y_state: tuple[Tensor, ...]) -> dict[str, Tensor]:
    return {"z": z, "z_mean": z_mean, "a": a, **dict(zip(_Y_STATE_KEYS, y_state))}


class LatentFilter(nn.Module):
    """Action-conditioned deep state-space model with z (directly) and y (indirectly
    observable) latents; see the module docstring for the time indexing.

    The options are keywords of :class:`~.options.LatentFilterOptions`, whose fields hold
    the project's defaults (the one source; Hydra composes the same dataclass as
    ``model.net``): a caller names only what it changes.

    Args:
        modality: preset name or mapping (see :func:`resolve_modality`). Its ``fusion``
            picks the observation model ``observation`` (:class:`~.fusion.EarlyFusion` or
            :class:`~.fusion.LateFusion`, :mod:`.fusion`); only this modality's encoders and
            decoders are built.
        n_z, n_y, n_a: latent and action sizes. n_objects: rows of the prior embedding.
        encoder: ``{"widths": [w1, w2], "hidden": h}`` for every encoder and its decoder
            (:class:`~.options.EncoderOptions` where not given).
        transition_hidden, lstm_hidden: widths of the transition MLP and LSTM.
        min_var: variance floor of encoder, transition and q(y) heads.
        obs_sigma: (initial) observation sigma on [0, 1]-scaled inputs; ``learn_obs_sigma``
            makes it a learnable per-channel parameter sigma_c = obs_sigma_min +
            softplus(raw_c). 0.1: from 1.0, most of a CPU budget went into shrinking it.
        prior: kwargs of :class:`HierarchicalPrior` (sigma_init, learn_sigma, var_floor,
            action_term, ...; its signature's defaults where not given). The network's
            ``config()`` stores the full set, so a checkpoint does not depend on defaults.
        y_update: ``"evidence"`` (default: accumulate per-step Gaussian evidence about the
            trial-constant y) or ``"direct"`` (the LSTM head is q(y_t)); y_prior_precision:
            precision of the N(0, 1/p) start of the evidence product; y_start: that start
            (``"fixed"``, default) or the prior's population marginal N(mu_0, sigma^2 + tau^2)
            (``"population"``: q(y_t) is then the posterior of an object never seen, and
            the frames before any evidence read as the population's centre); y_evidence_max: if
            set (default 1), one step's evidence precision is at most this; y_evidence_range:
            if set (default 2), the evidence means are squashed into (-r, r) (both
            ``evidence`` only).
        obs_dropout: in training mode each frame t >= 2 is hidden from the filter with this
            probability (default 0.5), so q_filt(z_t) is the transition prior alone there and
            the likelihood of that frame trains the transition (docs/reference/model.md, "The default
            recipe"). 0 = off.
        input_standardize: the encoders see each channel shifted and scaled by its
            training-set mean and standard deviation (buffers ``input_shift`` /
            ``input_scale``, set once by :meth:`set_input_stats`, carried by checkpoints);
            the decoder and the likelihood stay in the data's units. True (default;
            docs/experiments/modality_bounds.md, "Where the pressing information is lost");
            False = the [0, 1] images as they are (a network without data statistics, such
            as the pendulum benchmark's, whose inputs need none).
    """

    def __init__(self, modality: Any, **options: Any) -> None:
        super().__init__()
        opts: LatentFilterOptions = build(LatentFilterOptions, options, "Latent Filter")
        if not 0.0 <= float(opts.obs_dropout) < 1.0:
            raise ValueError(f"obs_dropout must be in [0, 1), got {opts.obs_dropout}")
        self.obs_dropout = float(opts.obs_dropout)
        self._config = to_plain(asdict(opts))
        self._config["modality"] = _modality_config(modality)
        self.modality = resolve_modality(modality)
        n_z, n_y, n_a, min_var = int(opts.n_z), int(opts.n_y), int(opts.n_a), float(opts.min_var)
        self.n_z, self.n_y, self.n_a = n_z, n_y, n_a
        self.n_channels = len(self.modality["channels"])
        enc = opts.encoder
        # built first: the same seed gives the same initial parameters as before the
        # fusion code moved to model/fusion.py
        self.observation: ObservationModel = observation_model(
            self.modality["fusion"], self.modality["pathways"], n_z, list(enc.widths), enc.hidden, min_var)
        self.transition = TransitionNet(n_z, n_y, n_a, opts.transition_hidden, min_var)
        self.y_posterior = YPosterior(n_z, n_y, n_a, opts.lstm_hidden, min_var,
                                      update=opts.y_update,
                                      prior_precision=opts.y_prior_precision, max_evidence=opts.y_evidence_max,
                                      evidence_range=opts.y_evidence_range)
        self.prior = HierarchicalPrior(n_y, n_a, opts.n_objects, **self._config["prior"])
        if opts.y_start not in Y_STARTS:
            raise ValueError(f"y_start must be one of {Y_STARTS}, got {opts.y_start!r}")
        if opts.y_start == "population" and opts.y_update != "evidence":
            raise ValueError("y_start='population' starts the evidence product: it needs y_update='evidence'")
        self.y_start = opts.y_start
        if opts.obs_sigma <= opts.obs_sigma_min:
            raise ValueError(f"obs_sigma={opts.obs_sigma} must exceed obs_sigma_min={opts.obs_sigma_min}")
        self.obs_sigma_min = float(opts.obs_sigma_min)
        raw = torch.full((self.n_channels,),
                         float(torch.log(torch.expm1(torch.tensor(opts.obs_sigma - opts.obs_sigma_min)))))
        if opts.learn_obs_sigma:
            self.obs_sigma_raw = nn.Parameter(raw)
        else:
            self.register_buffer("obs_sigma_raw", raw)
        self.input_standardize = bool(opts.input_standardize)
        if self.input_standardize:  # only then: checkpoints without the option load unchanged
            self.register_buffer("input_shift", torch.zeros(self.n_channels))
            self.register_buffer("input_scale", torch.ones(self.n_channels))
            self.register_buffer("input_stats_set", torch.tensor(False))

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> "LatentFilter":
        """Rebuild a network from its saved :meth:`config` (a checkpoint's ``net``), saved
        configs of earlier versions included (:func:`~.compat.upgrade_net_config`)."""
        config = upgrade_net_config(to_plain(config))
        return cls(**config)

    def config(self) -> dict[str, Any]:
        """The constructor arguments as plain, checkpoint-safe values (``modality`` as its
        mapping): ``LatentFilter(**net.config())`` rebuilds the same network. The Lightning
        modules store this once as their ``net`` hyperparameter."""
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in self._config.items()}

    # ------------------------------------------------------------------ pieces
    def obs_log_sigma(self) -> Tensor:
        """Log sigma of the Gaussian likelihood in float32, one per channel (C,)."""
        return torch.log(F.softplus(self.obs_sigma_raw.float()) + self.obs_sigma_min)

    def _check_obs(self, obs: Tensor) -> None:
        if obs.shape[-3:] != (self.n_channels, 28, 28):
            raise ValueError(f"modality {self.modality['name']!r} expects obs (..., {self.n_channels}, 28, 28) "
                             f"for channels {self.modality['channels']}, got {tuple(obs.shape)}")

    def set_input_stats(self, mean: Any, std: Any) -> None:
        """Per-channel training-set mean and standard deviation (C,) of the observations,
        used by the encoders when ``input_standardize`` (see :meth:`encode`)."""
        if not self.input_standardize:
            raise ValueError("set_input_stats needs input_standardize=True")
        mean = torch.as_tensor(mean, dtype=torch.float32).reshape(-1)
        std = torch.as_tensor(std, dtype=torch.float32).reshape(-1)
        if mean.shape != (self.n_channels,) or std.shape != (self.n_channels,):
            raise ValueError(f"input stats must have one value per channel {self.modality['channels']}, "
                             f"got mean {tuple(mean.shape)}, std {tuple(std.shape)}")
        if not (torch.isfinite(mean).all() and torch.isfinite(std).all() and (std > 0).all()):
            raise ValueError(f"input stats must be finite with std > 0, got mean {mean.tolist()}, std {std.tolist()}")
        self.input_shift.copy_(mean)
        self.input_scale.copy_(std)
        self.input_stats_set.fill_(True)

    def encode(self, o: Tensor) -> tuple[Tensor, Tensor]:
        """q(z | o) for frames o (N, C, 28, 28) -> mean, var (N, n_z) in float32, by the
        observation model (:mod:`.fusion`: one encoder over the stacked channels, or per
        pathway Gaussians multiplied in latent space). With ``input_standardize`` the
        encoders see (o - input_shift) / input_scale per channel."""
        self._check_obs(o)
        if self.input_standardize:
            shape = (1, self.n_channels, 1, 1)
            o = (o - self.input_shift.view(shape).to(o.dtype)) / self.input_scale.view(shape).to(o.dtype)
        return self.observation.encode(o)

    def decode(self, z: Tensor) -> Tensor:
        """Observation means for z (N, n_z) -> (N, C, 28, 28), channels in ``obs`` order."""
        return self.observation.decode(z)

    def initial_state(self, batch: int, device: torch.device, dtype: torch.dtype = torch.float32) -> dict[str, Tensor]:
        z = torch.zeros(batch, self.n_z, device=device, dtype=dtype)
        a = torch.zeros(batch, self.n_a, device=device, dtype=dtype)
        start = self.population_marginal(batch, device) if self.y_start == "population" else None
        return _state_to(z, z.clone(), a, self.y_posterior.initial_state(batch, device, dtype, start))

    @staticmethod
    def _draw(m: Tensor, v: Tensor, sample: bool) -> Tensor:
        if not sample:
            return m
        with float32_region(m):
            return m + torch.sqrt(v) * torch.randn_like(m)

    def step(self, enc_m: Tensor, enc_v: Tensor, a_t: Tensor, state: Optional[dict[str, Tensor]],
             sample: bool, prev_action: Optional[Tensor] = None, observed: Optional[Tensor] = None
             ) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """One recursion step given the measurement Gaussian of frame t (shared by
        ``forward``, ``filter_step`` and ``predict``). ``state=None`` marks the first frame.
        ``observed`` (B,) bool: where False the frame is not seen and q_filt(z_t) is the
        transition prior alone (N(0, I) at the first frame); None = all observed."""
        first = state is None
        if first:
            state = self.initial_state(enc_m.shape[0], enc_m.device)
            a_prev = state["a"]  # zeros: nothing precedes the first frame
        else:
            a_prev = state["a"] if prev_action is None else prev_action.float()
        y_state = tuple(state[k] for k in _Y_STATE_KEYS if k in state)
        y_m, y_v, y_state = self.y_posterior(state["z"], a_prev, y_state)
        y = self._draw(y_m, y_v, sample)
        out = self._z_step(enc_m, enc_v, None if first else state["z"], y, a_t, sample, observed)
        out.update(y_mean=y_m, y_var=y_v, y=y)
        return out, _state_to(out["z"], out["z_mean"], a_t.float(), y_state)

    def _z_step(self, enc_m: Tensor, enc_v: Tensor, z_prev: Optional[Tensor], y: Tensor, a_t: Tensor,
                sample: bool, observed: Optional[Tensor] = None) -> dict[str, Tensor]:
        """The z half of one recursion step, given y_t: the transition prior
        p(z_t | z_{t-1}, y_t, a_t) (N(0, I) when ``z_prev`` is None, the first frame) fused
        with the measurement Gaussian where ``observed`` (B,) (None = all observed); the
        prior alone elsewhere. Returns z_mean, z_var (q_filt), zp_mean, zp_var and z."""
        if z_prev is None:
            # z_1 from the encoder alone; its prior is N(0, I).
            zp_m, zp_v = torch.zeros_like(enc_m), torch.ones_like(enc_v)
            z_m, z_v = enc_m, enc_v
        else:
            zp_m, zp_v = self.transition(z_prev, y, a_t)
            z_m, z_v = fuse_gaussians(zp_m, zp_v, enc_m, enc_v)
        if observed is not None:
            seen = observed.view(-1, 1)
            z_m, z_v = torch.where(seen, z_m, zp_m), torch.where(seen, z_v, zp_v)
        z = self._draw(z_m, z_v, sample)
        return {"z_mean": z_m, "z_var": z_v, "z": z, "zp_mean": zp_m, "zp_var": zp_v}

    # ------------------------------------------------------------------ batched
    def observation_mask(self, B: int, T: int, device: torch.device) -> Optional[Tensor]:
        """Observation dropout: (B, T) bool, frames t >= 2 hidden with probability
        ``obs_dropout`` in training mode; None (all observed) otherwise."""
        if not (self.training and self.obs_dropout > 0.0):
            return None
        mask = torch.rand(B, T, device=device) >= self.obs_dropout
        mask[:, 0] = True  # z_1 has no transition prior to fall back on
        return mask

    def forward(self, obs: Tensor, actions: Tensor, sample: bool = True,
                observed: Optional[Tensor] = None, decode: bool = True) -> dict[str, Tensor]:
        """obs (B, T, C, 28, 28), actions (B, T, n_a) -> dict of (B, T, ...) tensors:
        z_mean/z_var (q_filt), z (sample, or mean if not ``sample``), y_mean/y_var/y,
        zp_mean/zp_var (transition prior; N(0, I) at t = 1), enc_mean/enc_var and
        recon (B, T, C, 28, 28) decoded from z. ``observed`` (B, T) bool hides frames from
        the filter (default: :meth:`observation_mask`; ``observed`` is returned when set).
        ``decode=False`` leaves out ``recon`` (and the decoders' compute, about half of a
        forward pass): the latents do not depend on it."""
        self._check_obs(obs)
        B, T = obs.shape[:2]
        if actions.shape != (B, T, self.n_a):
            raise ValueError(f"actions must be {(B, T, self.n_a)}, got {tuple(actions.shape)}")
        enc_m, enc_v = self.encode(obs.reshape(B * T, *obs.shape[2:]))
        enc_m, enc_v = enc_m.view(B, T, -1), enc_v.view(B, T, -1)
        actions = actions.float()
        if observed is None:
            observed = self.observation_mask(B, T, obs.device)
        elif observed.shape != (B, T):
            raise ValueError(f"observed must be {(B, T)}, got {tuple(observed.shape)}")
        state = None
        steps: list[dict[str, Tensor]] = []
        for t in range(T):
            out, state = self.step(enc_m[:, t], enc_v[:, t], actions[:, t], state, sample,
                                   observed=None if observed is None else observed[:, t])
            steps.append(out)
        res = {k: torch.stack([s[k] for s in steps], dim=1) for k in steps[0]}
        if observed is not None:
            res["observed"] = observed
        res["enc_mean"], res["enc_var"] = enc_m, enc_v
        if decode:  # infer_latents skips it: the latents never depend on the decoders
            res["recon"] = self.decode(res["z"].reshape(B * T, -1)).view(B, T, *obs.shape[2:])
        return res

    def elbo_terms(self, batch: Mapping[str, Tensor], sample: bool = True) -> dict[str, Tensor]:
        """Per-sequence terms averaged over the batch (all float32 scalars):

        nll     = sum_t sum_{c,pixels} -log N(o_t; dec(z_t), sigma_c^2)
        kl_z    = KL(q(z_1) || N(0, I)) + sum_{t>=2} KL(q_filt(z_t) || p(z_t | z_{t-1}, y_t, a_t))
        kl_y    = sum_{t>=2} KL(q(y_t | .) || p(y_t | a_t, N))
                  + w_pop * (-log p(E_seen | mu_0, tau))   (population level, ``pop``)
        entropy = sum_t H[q_filt(z_t)] + sum_{t>=2} H[q(y_t | .)]
        n_dims  = T * C * 28 * 28 (observation dimensions per sequence)
        pop     = the population term alone (also inside kl_y), logged for inspection
        ELBO = -(nll + kl_z + kl_y). ``out`` holds the forward outputs. ``w_pop`` is
        ``prior.population_weight`` (1 / training sequences; 1 / n_objects if unset).
        """
        obs, actions = batch["obs"], batch["actions"]
        out = self.forward(obs, actions, sample=sample)
        T = obs.shape[1]
        nll = gaussian_nll_frames(obs, out["recon"], self.obs_log_sigma()).sum(1).mean()
        kl_z = kl_diag_gaussians(out["z_mean"], out["z_var"], out["zp_mean"], out["zp_var"]).sum(1).mean()
        ent = gaussian_entropy(out["z_var"]).sum(1)
        if T > 1:
            py_m, py_v = self.prior(batch["object_id"], actions[:, 1:])
            kl_y = kl_diag_gaussians(out["y_mean"][:, 1:], out["y_var"][:, 1:], py_m, py_v).sum(1).mean()
            ent = ent + gaussian_entropy(out["y_var"][:, 1:]).sum(1)
        else:
            kl_y = out["y_mean"].new_zeros(()).float()
            self.prior(batch["object_id"], actions[:, :1])  # marks the objects seen in training
        w_pop = self.prior.population_weight
        pop = self.prior.population_nll() * (1.0 / self.prior.n_objects if w_pop is None else float(w_pop))
        kl_y = kl_y + pop
        n_dims = torch.tensor(float(T * obs.shape[2] * 28 * 28), device=obs.device)
        return {"nll": nll, "kl_z": kl_z, "kl_y": kl_y, "pop": pop.detach(), "entropy": ent.mean(), "n_dims": n_dims,
                "out": out}

    # ------------------------------------------------------------------ context objective
    def population_marginal(self, batch: int, device: torch.device) -> tuple[Tensor, Tensor]:
        """The prior of a new object's y without labels: the hierarchical prior's population
        marginal N(mu_0, sigma^2 + tau^2) (its action term at zero action), (B, n_y) each,
        float32. No object id is read: every row is an object never seen."""
        none = torch.full((batch,), -1, dtype=torch.long, device=device)
        m, v = self.prior(none, torch.zeros(batch, 1, self.n_a, device=device))
        return m[:, 0], v[:, 0]

    def touch_prior(self, device: Optional[torch.device] = None) -> tuple[Tensor, Tensor]:
        """The Gaussian each touch's q(y) was inferred from, for :func:`combine_touches`
        (n_y,) each: with ``y_update="evidence"`` the start of the evidence product,
        N(0, 1/y_prior_precision) or with ``y_start="population"`` the population marginal,
        its variance with the ``min_var`` floor as q(y) reports it (a touch without evidence
        then adds none); with ``"direct"`` (no explicit start) the population marginal."""
        yp = self.y_posterior
        if yp.update == "evidence" and self.y_start == "population":
            with torch.no_grad():
                m, v = self.population_marginal(1, device or torch.device("cpu"))
            return m[0], v[0] + yp.min_var
        if yp.update == "evidence":
            m = torch.zeros(self.n_y, device=device)
            return m, torch.full_like(m, 1.0 / yp.prior_precision + yp.min_var)
        with torch.no_grad():
            m, v = self.population_marginal(1, device or torch.device("cpu"))
        return m[0], v[0]

    def context_posterior(self, obs: Tensor, actions: Tensor, sample: bool = False) -> tuple[Tensor, Tensor]:
        """q(y | context): the inference path (encoder, filter, y posterior with its evidence
        accumulation) run over context frames obs (B, T, C, 28, 28) and their actions, every
        frame observed; the posterior at the last frame, mean and var (B, n_y). Gradients
        flow (the context objective trains this path); ``sample`` draws the filter's z.
        A context of M touches, obs (B, M, T, C, 28, 28) and actions (B, M, T, n_a): each
        touch's posterior, combined by :func:`combine_touches` (the K-touch read-out's rule)
        from :meth:`touch_prior`."""
        if obs.dim() == 6:
            B, M = obs.shape[:2]
            m, v = self.context_posterior(obs.flatten(0, 1), actions.flatten(0, 1), sample=sample)
            prior_m, prior_v = self.touch_prior(obs.device)
            return combine_touches(m.view(B, M, -1).transpose(0, 1), v.view(B, M, -1).transpose(0, 1),
                                   prior_m, prior_v)
        observed = torch.ones(obs.shape[:2], dtype=torch.bool, device=obs.device)
        out = self.forward(obs, actions, sample=sample, observed=observed, decode=False)
        return out["y_mean"][:, -1], out["y_var"][:, -1]

    def rollout(self, obs: Tensor, actions: Tensor, y: Tensor, initial_frames: int, sample: bool = True,
                refilter: bool = False) -> dict[str, Tensor]:
        """Target frames from a fixed y and the target's own actions: z filtered from the
        first ``initial_frames`` encoded frames of obs (B, T, C, 28, 28), then rolled forward
        by the transition p(z_t | z_{t-1}, y, a_t) with every later frame unobserved (they are
        never encoded, so they cannot reach z); ``refilter`` filters every frame instead (the
        per-frame posterior of the target, a leak control). y (B, n_y) is the same at every
        step. Returns z_mean, z_var, zp_mean, zp_var, z (B, T, n_z) and recon (B, T, C, 28,
        28), every frame decoded."""
        self._check_obs(obs)
        B, T = obs.shape[:2]
        if actions.shape != (B, T, self.n_a) or y.shape != (B, self.n_y):
            raise ValueError(f"rollout needs actions {(B, T, self.n_a)} and y {(B, self.n_y)}, "
                             f"got {tuple(actions.shape)} and {tuple(y.shape)}")
        if int(initial_frames) < 1:
            raise ValueError(f"initial_frames must be >= 1 (z_1 comes from the encoder), got {initial_frames}")
        k = T if refilter else min(int(initial_frames), T)
        enc_m, enc_v = self.encode(obs[:, :k].reshape(B * k, *obs.shape[2:]))
        enc_m, enc_v = enc_m.view(B, k, -1), enc_v.view(B, k, -1)
        none_m, none_v = torch.zeros_like(enc_m[:, 0]), torch.ones_like(enc_v[:, 0])
        hidden = torch.zeros(B, dtype=torch.bool, device=obs.device)
        actions = actions.float()
        z, steps = None, []
        for t in range(T):
            seen = t < k
            out = self._z_step(enc_m[:, t] if seen else none_m, enc_v[:, t] if seen else none_v, z, y,
                               actions[:, t], sample, observed=None if seen else hidden)
            z = out["z"]
            steps.append(out)
        res = {key: torch.stack([s[key] for s in steps], dim=1) for key in steps[0]}
        res["recon"] = self.decode(res["z"].reshape(B * T, -1)).view(B, T, *obs.shape[2:])
        return res

    def context_terms(self, batch: Mapping[str, Tensor], initial_frames: int = ContextOptions.initial_frames,
                      refilter: bool = ContextOptions.refilter,
                      sample: bool = True) -> dict[str, Tensor]:
        """The context objective (docs/reference/model.md, "The context objective"): per-sequence
        terms of the negative ELBO of a model in which one y is shared by every trial of an
        object, averaged over the batch (float32 scalars, the keys of :meth:`elbo_terms`).

        y ~ q(y | context) (:meth:`context_posterior` over ``context_obs`` /
        ``context_actions``; a reparameterised draw when ``sample``), then the target
        ``obs`` / ``actions`` by :meth:`rollout`:

        nll  = sum_t sum_{c,pixels} -log N(o_t; dec(z_t), sigma_c^2) over every target frame
        kl_z = KL(q(z_1) || N(0, I)) + sum_{2<=t<=k} KL(q_filt(z_t) || p(z_t | z_{t-1}, y, a_t))
               (0 at the rolled-forward frames, where q = p; every frame with ``refilter``)
        kl_y = KL(q(y | context) || p(y)), p(y) the population marginal (no label)
        The object id is never read: the pairing of context and target is the data's."""
        y_m, y_v = self.context_posterior(batch["context_obs"], batch["context_actions"], sample=sample)
        y = self._draw(y_m, y_v, sample)
        obs = batch["obs"]
        out = self.rollout(obs, batch["actions"], y, initial_frames, sample=sample, refilter=refilter)
        B, T = obs.shape[:2]
        nll = gaussian_nll_frames(obs, out["recon"], self.obs_log_sigma()).sum(1).mean()
        kl_z = kl_diag_gaussians(out["z_mean"], out["z_var"], out["zp_mean"], out["zp_var"]).sum(1).mean()
        py_m, py_v = self.population_marginal(B, obs.device)
        kl_y = kl_diag_gaussians(y_m, y_v, py_m, py_v).mean()
        ent = (gaussian_entropy(out["z_var"]).sum(1) + gaussian_entropy(y_v)).mean()
        n_dims = torch.tensor(float(T * obs.shape[2] * 28 * 28), device=obs.device)
        zero = kl_y.new_zeros(())
        return {"nll": nll, "kl_z": kl_z, "kl_y": kl_y, "pop": zero, "entropy": ent, "n_dims": n_dims,
                "out": {**out, "y_mean": y_m, "y_var": y_v}}

    # ------------------------------------------------------------------ inference
    @torch.no_grad()
    def infer_latents(self, batch: Mapping[str, Tensor] | Tensor, actions: Optional[Tensor] = None) -> dict[str, Tensor]:
        """Filtered latents without sampling (eval mode; no object label needed):
        z_mean, z_var (B, T, n_z) of q_filt and y_mean, y_var (B, T, n_y) of q(y_t | .)."""
        if isinstance(batch, Mapping):
            obs, actions = batch["obs"], batch["actions"]
        else:
            obs = batch
        was_training = self.training
        self.eval()
        try:
            out = self.forward(obs, actions, sample=False, decode=False)
        finally:
            self.train(was_training)
        return {k: out[k] for k in ("z_mean", "z_var", "y_mean", "y_var")}

    @torch.no_grad()
    def predict(self, obs: Tensor, actions: Tensor, horizon: int, sample: bool = False) -> dict[str, Tensor]:
        """Open-loop prediction ("imagination"): filter the T0 frames of ``obs`` (B, T0, C,
        28, 28), then run the same recursion ``horizon`` more steps with every frame
        unobserved (q_filt = transition prior; the LSTM keeps running on the predicted z)
        under ``actions`` (B, T0 + horizon, n_a). Eval mode; means unless ``sample``.
        Returns z_mean, z_var (B, horizon, n_z), y_mean (B, horizon, n_y) and recon
        (B, horizon, C, 28, 28), the decoded frames T0 + 1 .. T0 + horizon."""
        self._check_obs(obs)
        B, T0 = obs.shape[:2]
        if T0 < 1 or horizon < 1 or actions.shape != (B, T0 + horizon, self.n_a):
            raise ValueError(f"predict needs T0 >= 1 observed frames, horizon >= 1 and actions "
                             f"{(B, T0 + horizon, self.n_a)}, got obs {tuple(obs.shape)}, horizon {horizon}, "
                             f"actions {tuple(actions.shape)}")
        was_training = self.training
        self.eval()
        try:
            enc_m, enc_v = self.encode(obs.reshape(B * T0, *obs.shape[2:]))
            enc_m, enc_v = enc_m.view(B, T0, -1), enc_v.view(B, T0, -1)
            actions = actions.float()
            state = None
            for t in range(T0):
                _, state = self.step(enc_m[:, t], enc_v[:, t], actions[:, t], state, sample)
            hidden = torch.zeros(B, dtype=torch.bool, device=obs.device)
            none_m, none_v = torch.zeros_like(enc_m[:, 0]), torch.ones_like(enc_v[:, 0])
            steps = []
            for t in range(T0, T0 + horizon):
                out, state = self.step(none_m, none_v, actions[:, t], state, sample, observed=hidden)
                steps.append(out)
        finally:
            self.train(was_training)
        res = {k: torch.stack([s[k] for s in steps], dim=1) for k in ("z_mean", "z_var", "z", "y_mean")}
        res["recon"] = self.decode(res.pop("z").reshape(B * horizon, -1)).view(B, horizon, *obs.shape[2:])
        return res

    def filter_step(self, obs_t: Tensor, action_t: Tensor, prev_action: Optional[Tensor] = None,
                    state: Optional[dict[str, Tensor]] = None, sample: bool = False
                    ) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """Online filtering: one frame obs_t (B, C, 28, 28) and action a_t (B, n_a) in.

        ``state`` is None for the first frame, else the returned ``new_state``
        (z_{t-1} sample ``z`` and mean ``z_mean``, a_{t-1}, LSTM h and c, and with ``y_update="evidence"`` the
        accumulated precision ``y_prec`` and precision-weighted mean sum ``y_pm``). ``prev_action`` (a_{t-1})
        overrides the action stored in the state. With ``sample=False`` the posterior
        equals the batched ``forward(..., sample=False)`` at the same t.
        Returns ({z_mean, z_var, y_mean, y_var, zp_mean, zp_var, z, y}, new_state).
        """
        with small_batch_convs(obs_t.shape[0]):
            enc_m, enc_v = self.encode(obs_t)
        return self.step(enc_m, enc_v, action_t.float(), state, sample, prev_action)


def combine_touches(y_mean: Tensor, y_var: Tensor, prior_mean: Tensor, prior_var: Tensor,
                    ) -> tuple[Tensor, Tensor]:
    """q(y | K touches) from the posteriors q(y | touch k) of K separate touches (trials)
    of one object, y_mean / y_var (K, B, n_y), each inferred from the prior p(y) =
    N(prior_mean, prior_var) (B, n_y) or (n_y,): the product of the touches' Gaussian
    evidence with the prior counted once,

        q(y | 1..K) ∝ p(y) prod_k q(y | k) / p(y),
        precision P = 1/v_0 + sum_k e_k,   e_k = max(1/v_k - 1/v_0, 0),
        mean      m = (m_0/v_0 + sum_k (m_k/v_k - m_0/v_0 [where e_k > 0])) / P,

    in float32. A touch whose posterior is wider than the prior in a dimension adds no
    evidence there (e_k clamped at 0), so P never falls with K. K = 1 returns that touch's
    posterior where it is at least as tight as the prior. Returns mean, var (B, n_y)."""
    if y_mean.dim() != 3 or y_mean.shape != y_var.shape:
        raise ValueError(f"y_mean / y_var must be (K, B, n_y) alike, got {tuple(y_mean.shape)}, {tuple(y_var.shape)}")
    with float32_region(y_mean):
        m, v = y_mean.float(), y_var.float()
        p0 = 1.0 / prior_var.float()
        h0 = prior_mean.float() * p0
        e = 1.0 / v - p0
        used = e > 0
        prec = p0 + torch.where(used, e, torch.zeros_like(e)).sum(0)
        pm = h0 + torch.where(used, m / v - h0, torch.zeros_like(e)).sum(0)
        return pm / prec, 1.0 / prec
