"""The Latent Filter (paper, section "Deep State-Space Model: Latent Filter") as a plain
``nn.Module``; the Lightning wrapper lives in :mod:`embodied_tactile.models.module`.

Time indexing (t = 1..T in the docs, 0-based in code):

* y_t ~ q(y_t | z_{t-1}, y_{t-1}, a_{t-1}): LSTMCell fed [z_{t-1}, a_{t-1}]. With
  ``y_update="direct"`` (default) its head gives q(y_t) itself; with ``"evidence"`` it gives
  one step's Gaussian evidence about the trial-constant y and q(y_t) is the product of all
  evidence so far (see :class:`~embodied_tactile.models.networks.YPosterior`). At t = 1 the LSTM gets zeros from a zero state.
* p(z_t | z_{t-1}, y_t, a_t): residual MLP, N(z_{t-1} + f_mu, softplus(f_v) + floor).
* q_filt(z_t) = q(z_t | o_t) x p(z_t | z_{t-1}, y_t, a_t), normalised (variance form).
  z_1 comes from the encoder alone.
* Encoders and decoders run over all B*T frames in one call; only the LSTM/transition
  recursion is a Python loop. ``filter_step`` runs the same recursion one frame at a time.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping, Sequence
from typing import Any, Optional

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from embodied_tactile.modality import Modality, load_modality

from .fusion import ObservationModel, observation_model
from .networks import (
    HierarchicalPrior,
    TransitionNet,
    YPosterior,
    float32_region,
    free_bits_kl,
    fuse_gaussians,
    gaussian_entropy,
    gaussian_nll,
    kl_diag_gaussians,
    small_batch_convs,
)

def to_plain(cfg: Any) -> Any:
    """Mapping / sequence (a Hydra DictConfig or ListConfig included: they are mappings and
    sequences) -> plain dict / list of checkpoint-safe primitives."""
    if isinstance(cfg, Mapping):
        return {str(k): to_plain(v) for k, v in cfg.items()}
    if isinstance(cfg, Sequence) and not isinstance(cfg, (str, bytes)):
        return [to_plain(v) for v in cfg]
    return cfg


def resolve_modality(modality: Any) -> dict[str, Any]:
    """A modality (its yaml mapping, a :class:`~embodied_tactile.modality.Modality`, or the
    name of a file in ``configs/modality/``) -> plain dict with ``name``, ``channels``,
    ``fusion`` and ``pathways`` as ``[[pathway, [channel indices]], ...]``. The modality is
    defined once, by its yaml (:mod:`embodied_tactile.modality`)."""
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

#: ``obs_sigma_shape``: one likelihood sigma per channel, or one per channel and pixel
OBS_SIGMA_SHAPES = ("channel", "pixel")


#: ``y_input``: what the y posterior's LSTM reads at step t: the sample of z_{t-1}, the filtered
#: mean, the sample and the innovation (filtered mean minus the transition's prediction), or
#: the measurement of frame t-1 (the encoder's mean and whether the frame was seen: no z)
Y_INPUTS = ("sample", "mean", "innovation", "measurement")


def _state_to(z: Tensor, z_mean: Tensor, innovation: Tensor, a: Tensor, y_state: tuple[Tensor, ...],
              measurement: Tensor) -> dict[str, Tensor]:
    return {"z": z, "z_mean": z_mean, "innovation": innovation, "a": a, "measurement": measurement,
            **dict(zip(_Y_STATE_KEYS, y_state))}


ENCODER_DEFAULTS: dict[str, Any] = {"widths": [16, 32], "hidden": 128}
"""Every encoder's (and its decoder's) convolution widths and hidden width, unless
``LatentFilter(encoder=...)`` names them."""


def _signature_defaults(cls: type, skip: Sequence[str] = ()) -> dict[str, Any]:
    return {k: p.default for k, p in inspect.signature(cls.__init__).parameters.items()
            if k != "self" and k not in skip and p.default is not inspect.Parameter.empty}


def default_option(name: str) -> Any:
    """The project's default of one Latent Filter option: ``"obs_sigma"`` (an argument of
    :class:`LatentFilter`), ``"prior.<name>"`` (of :class:`HierarchicalPrior`) or
    ``"encoder.<name>"`` (:data:`ENCODER_DEFAULTS`). The signatures are the one source;
    configs/model/latent_filter.yaml reads them through ``${lf_default:<name>}``."""
    group, _, key = name.rpartition(".")
    if group == "encoder" and key in ENCODER_DEFAULTS:
        value = ENCODER_DEFAULTS[key]
        return list(value) if isinstance(value, list) else value
    owner = {"": LatentFilter, "prior": HierarchicalPrior}.get(group)
    parameter = inspect.signature(owner.__init__).parameters.get(key) if owner else None
    if parameter is None or parameter.default is inspect.Parameter.empty:
        raise KeyError(f"{name!r} is not an option of the Latent Filter with a default")
    return parameter.default


class LatentFilter(nn.Module):
    """Action-conditioned deep state-space model with z (directly) and y (indirectly
    observable) latents; see the module docstring for the time indexing.

    The signature's values are the project's defaults (one source: a config names what a
    scene changes and reads the rest through :func:`default_option`).

    Args:
        modality: preset name or mapping (see :func:`resolve_modality`). Its ``fusion``
            picks the observation model ``observation`` (:class:`~.fusion.EarlyFusion` or
            :class:`~.fusion.LateFusion`, :mod:`.fusion`); only this modality's encoders and
            decoders are built.
        n_z, n_y, n_a: latent and action sizes. n_objects: rows of the prior embedding.
        encoder: ``{"widths": [w1, w2], "hidden": h}`` for every encoder and its decoder
            (:data:`ENCODER_DEFAULTS` where not given).
        transition_hidden, lstm_hidden: widths of the transition MLP and LSTM.
        min_var: variance floor of encoder, transition and q(y) heads.
        obs_sigma: (initial) observation sigma on [0, 1]-scaled inputs; ``learn_obs_sigma``
            makes it a learnable per-channel parameter sigma_c = obs_sigma_min +
            softplus(raw_c). 0.1: from 1.0, most of a CPU budget went into shrinking it.
        obs_sigma_shape: ``"channel"`` (default, one sigma per channel) or ``"pixel"``
            (one learnable sigma per channel and pixel, sigma_{c,ij}: a heteroscedastic
            likelihood for images whose pixels differ in noise, such as the acc log-mel
            bins; docs/model.md, "Options of `model.net`").
        prior: kwargs of :class:`HierarchicalPrior` (sigma_init, learn_sigma, var_floor,
            action_term, ...; its signature's defaults where not given). The network's
            ``config()`` stores the full set, so a checkpoint does not depend on defaults.
        y_update: ``"direct"`` (the LSTM head is q(y_t)) or ``"evidence"`` (accumulate
            per-step Gaussian evidence about the trial-constant y); y_prior_precision:
            precision of the N(0, 1/p) start of the evidence product; y_evidence_max: if
            set, one step's evidence precision is at most this; y_evidence_range: if set,
            the evidence means are squashed into (-r, r) (both ``evidence`` only).
        y_input: what the y posterior's LSTM reads of z_{t-1}: ``"sample"`` (default, the
            paper's q(y_t | z_{t-1}, y_{t-1}, a_{t-1}) on the drawn z) or ``"mean"`` (the
            filtered mean of q_filt(z_{t-1}), a function of the frames so far: the LSTM
            integrates the belief over many frames without each draw's noise; still a
            valid q, so still the ELBO; docs/model.md, "Options of `model.net`") or
            ``"innovation"`` (the draw and the innovation q_filt mean minus the transition's
            mean at t-1: the prediction error that carries a hidden parameter's evidence) or
            ``"measurement"`` (frame t-1's encoder mean and a seen flag, zeros where the
            frame was hidden: y's inference then does not depend on z, as ``y_static`` needs).
        y_static: y is one latent per sequence in training (docs/model.md, "Options of `model.net`"): the transition gets one draw from q(y | the window's frames), the
            evidence product at the last step, at every step, and kl_y is one KL of that
            posterior to p(y | object) per sequence. Needs ``y_update="evidence"`` and
            ``y_input="measurement"``. In evaluation the filter is causal: the transition at
            step t gets q(y_t | frames before t). False (default) = a y_t per step.
        obs_dropout: training remedy (docs/model.md, "Options of `model.net`"): in training
            mode each frame t >= 2 is hidden from the filter with this probability, so
            q_filt(z_t) is the transition prior alone there and the likelihood of that
            frame trains the transition. 0 (default) = off.
        obs_dropout_span: observation dropout in runs of this many consecutive frames
            (docs/model.md, "Options of `model.net`"): the frames are cut into blocks
            of ``span`` (at a random phase per sequence) and each block is hidden with
            probability ``obs_dropout``, so the hidden fraction stays ``obs_dropout`` and the
            transition must predict ``span`` frames or more at a time. 1 (default) = each
            frame on its own.
        elbo_samples: training remedy (docs/model.md, "Options of `model.net`"): in training
            mode ``elbo_terms`` averages the single-sample estimate over K independent
            samples per sequence (K x the compute). 1 (default) = one sample.
        overshoot: training remedy (docs/model.md, "Options of `model.net`"): in training mode
            ``kl_z`` adds the mean over d = 2..D of KL(sg[q_filt(z_{t+d})] || p_d(z_{t+d})),
            p_d the transition rolled d steps open loop from a sample of q_filt(z_t), weighted
            by ``overshoot_weight``. 1 (default) = off (one-step prior only).
        free_bits_z, free_bits_y: training remedy (docs/model.md, "Options of `model.net`"): in training
            mode kl_z / kl_y are taken per latent dimension, averaged over the batch and the
            steps, and floored at this many nats per dimension and step
            (:func:`networks.free_bits_kl`): a dimension under the floor costs the floor and
            gets no gradient from its KL. 0 (default) = the plain KL.
        transition_form: ``"mlp"`` (default: the transition MLP reads [z, y, a]) or
            ``"affine_y"`` (the drift is affine in y with z- and a-dependent coefficients,
            the linear-in-parameters form of mechanical dynamics; :class:`TransitionNet`,
            docs/model.md, "Options of `model.net`").
        input_standardize: the encoders see each channel shifted and scaled by its
            training-set mean and standard deviation (buffers ``input_shift`` /
            ``input_scale``, set once by :meth:`set_input_stats`, carried by checkpoints);
            the decoder and the likelihood stay in the data's units. True (default;
            docs/experiments/modality_bounds.md, "Where the pressing information is lost");
            False = the [0, 1] images as they are (a network without data statistics, such
            as the pendulum benchmark's, whose inputs need none).
    """

    def __init__(self, modality: Any, n_z: int = 16, n_y: int = 16, n_a: int = 6,
                 n_objects: int = 32, encoder: Optional[Mapping] = None,
                 transition_hidden: int = 128, lstm_hidden: int = 128, min_var: float = 1e-3,
                 obs_sigma: float = 0.1, learn_obs_sigma: bool = True, obs_sigma_min: float = 1e-2,
                 prior: Optional[Mapping] = None, y_update: str = "direct",
                 y_prior_precision: float = 1.0, y_evidence_max: Optional[float] = None,
                 y_evidence_range: Optional[float] = None, obs_dropout: float = 0.0,
                 obs_dropout_span: int = 1, elbo_samples: int = 1, overshoot: int = 1, overshoot_weight: float = 1.0,
                 input_standardize: bool = True, obs_sigma_shape: str = "channel", y_input: str = "sample",
                 free_bits_z: float = 0.0, free_bits_y: float = 0.0, transition_form: str = "mlp",
                 y_static: bool = False) -> None:
        super().__init__()
        if y_input not in Y_INPUTS:
            raise ValueError(f"y_input must be one of {Y_INPUTS}, got {y_input!r}")
        self.y_input = y_input
        if y_static and not (y_update == "evidence" and y_input == "measurement"):
            raise ValueError(f"y_static needs y_update='evidence' and y_input='measurement' (y's inference must not "
                             f"read z, which the static y drives), got y_update={y_update!r}, y_input={y_input!r}")
        self.y_static = bool(y_static)
        if obs_sigma_shape not in OBS_SIGMA_SHAPES:
            raise ValueError(f"obs_sigma_shape must be one of {OBS_SIGMA_SHAPES}, got {obs_sigma_shape!r}")
        if int(overshoot) != overshoot or overshoot < 1:
            raise ValueError(f"overshoot must be an integer >= 1 (1 = off), got {overshoot}")
        if not float(overshoot_weight) >= 0.0:
            raise ValueError(f"overshoot_weight must be >= 0, got {overshoot_weight}")
        self.overshoot, self.overshoot_weight = int(overshoot), float(overshoot_weight)
        if not 0.0 <= float(obs_dropout) < 1.0:
            raise ValueError(f"obs_dropout must be in [0, 1), got {obs_dropout}")
        if int(elbo_samples) != elbo_samples or elbo_samples < 1:
            raise ValueError(f"elbo_samples must be an integer >= 1, got {elbo_samples}")
        if int(obs_dropout_span) != obs_dropout_span or obs_dropout_span < 1:
            raise ValueError(f"obs_dropout_span must be an integer >= 1 (1 = single frames), got {obs_dropout_span}")
        self.obs_dropout, self.elbo_samples = float(obs_dropout), int(elbo_samples)
        self.obs_dropout_span = int(obs_dropout_span)
        args = dict(locals())
        args["prior"] = {**_signature_defaults(HierarchicalPrior, skip=("n_y", "n_a", "n_objects")),
                         **(to_plain(prior) or {})}
        args["encoder"] = {**ENCODER_DEFAULTS, **(to_plain(encoder) or {})}
        self._config = {k: to_plain(v) for k, v in args.items() if k not in ("self", "__class__")}
        self._config["modality"] = _modality_config(modality)
        for name, floor in (("free_bits_z", free_bits_z), ("free_bits_y", free_bits_y)):
            if not float(floor) >= 0.0:
                raise ValueError(f"{name} must be >= 0 nats per dimension and step (0 = off), got {floor}")
        self.free_bits_z, self.free_bits_y = float(free_bits_z), float(free_bits_y)
        self.modality = resolve_modality(modality)
        self.n_z, self.n_y, self.n_a = int(n_z), int(n_y), int(n_a)
        self.n_channels = len(self.modality["channels"])
        enc = dict(self._config["encoder"])
        unknown = set(enc) - {"widths", "hidden"}
        if unknown:
            raise ValueError(f"unknown encoder options {sorted(unknown)}")
        # built first: the same seed gives the same initial parameters as before the
        # fusion code moved to models/fusion.py
        self.observation: ObservationModel = observation_model(
            self.modality["fusion"], self.modality["pathways"], n_z, enc["widths"], enc["hidden"], min_var)
        self.transition = TransitionNet(n_z, n_y, n_a, transition_hidden, min_var, form=transition_form)
        y_in = {"innovation": 2 * n_z, "measurement": n_z + 1}.get(y_input, n_z)
        self.y_posterior = YPosterior(y_in, n_y, n_a, lstm_hidden, min_var,
                                      update=y_update,
                                      prior_precision=y_prior_precision, max_evidence=y_evidence_max,
                                      evidence_range=y_evidence_range)
        self.prior = HierarchicalPrior(n_y, n_a, n_objects, **self._config["prior"])
        if obs_sigma <= obs_sigma_min:
            raise ValueError(f"obs_sigma={obs_sigma} must exceed obs_sigma_min={obs_sigma_min}")
        self.obs_sigma_min = float(obs_sigma_min)
        shape = (self.n_channels,) if obs_sigma_shape == "channel" else (self.n_channels, 28, 28)
        raw = torch.full(shape, float(torch.log(torch.expm1(torch.tensor(obs_sigma - obs_sigma_min)))))
        if learn_obs_sigma:
            self.obs_sigma_raw = nn.Parameter(raw)
        else:
            self.register_buffer("obs_sigma_raw", raw)
        self.input_standardize = bool(input_standardize)
        if self.input_standardize:  # only then: checkpoints without the option load unchanged
            self.register_buffer("input_shift", torch.zeros(self.n_channels))
            self.register_buffer("input_scale", torch.ones(self.n_channels))
            self.register_buffer("input_stats_set", torch.tensor(False))

    def config(self) -> dict[str, Any]:
        """The constructor arguments as plain, checkpoint-safe values (``modality`` as its
        mapping): ``LatentFilter(**net.config())`` rebuilds the same network. The Lightning
        modules store this once as their ``net`` hyperparameter."""
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in self._config.items()}

    # ------------------------------------------------------------------ pieces
    def obs_log_sigma(self) -> Tensor:
        """Log sigma of the Gaussian likelihood in float32: shape (C,) per channel, or
        (C, 28, 28) per pixel (``obs_sigma_shape="pixel"``)."""
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
        return _state_to(z, z.clone(), z.clone(), a, self.y_posterior.initial_state(batch, device, dtype),
                         torch.zeros(batch, self.n_z + 1, device=device, dtype=dtype))

    @staticmethod
    def _draw(m: Tensor, v: Tensor, sample: bool) -> Tensor:
        if not sample:
            return m
        with float32_region(m):
            return m + torch.sqrt(v) * torch.randn_like(m)

    def step(self, enc_m: Tensor, enc_v: Tensor, a_t: Tensor, state: Optional[dict[str, Tensor]],
             sample: bool, prev_action: Optional[Tensor] = None, observed: Optional[Tensor] = None,
             y_given: Optional[Tensor] = None, y_post: Optional[tuple[Tensor, Tensor]] = None
             ) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """One recursion step given the measurement Gaussian of frame t (shared by
        ``forward``, ``filter_step`` and ``predict``). ``state=None`` marks the first frame.
        ``observed`` (B,) bool: where False the frame is not seen and q_filt(z_t) is the
        transition prior alone (N(0, I) at the first frame); None = all observed.
        ``y_given`` (B, n_y): the y the transition uses (and ``out["y"]``) instead of a draw
        from q(y_t) (``y_static`` in training). ``y_post``: q(y_t)'s mean and variance computed
        beforehand (``forward`` with ``y_input="measurement"``, :meth:`measurement_y`); the
        y posterior is then not run here and the returned state's y entries stay as given."""
        first = state is None
        if first:
            state = self.initial_state(enc_m.shape[0], enc_m.device)
            a_prev = state["a"]  # zeros: nothing precedes the first frame
        else:
            a_prev = state["a"] if prev_action is None else prev_action.float()
        y_state = tuple(state[k] for k in _Y_STATE_KEYS if k in state)
        if y_post is not None:
            y_m, y_v = y_post
        else:
            if self.y_input == "innovation":
                z_in = torch.cat([state["z"], state["innovation"].to(state["z"].dtype)], dim=-1)
            elif self.y_input == "mean":
                z_in = state["z_mean"]
            elif self.y_input == "measurement":
                z_in = state["measurement"]
            else:
                z_in = state["z"]
            y_m, y_v, y_state = self.y_posterior(z_in, a_prev, y_state)
        y = self._draw(y_m, y_v, sample) if y_given is None else y_given
        if first:
            # z_1 from the encoder alone; its prior is N(0, I).
            zp_m, zp_v = torch.zeros_like(enc_m), torch.ones_like(enc_v)
            z_m, z_v = enc_m, enc_v
        else:
            zp_m, zp_v = self.transition(state["z"], y, a_t)
            z_m, z_v = fuse_gaussians(zp_m, zp_v, enc_m, enc_v)
        if observed is not None:
            seen = observed.view(-1, 1)
            z_m, z_v = torch.where(seen, z_m, zp_m), torch.where(seen, z_v, zp_v)
        z = self._draw(z_m, z_v, sample)
        out = {"z_mean": z_m, "z_var": z_v, "z": z, "y_mean": y_m, "y_var": y_v, "y": y,
               "zp_mean": zp_m, "zp_var": zp_v}
        # what frame t taught the filter beyond the transition's prediction: 0 at the first
        # frame (no prediction) and wherever the frame was hidden (q_filt = the prediction)
        innovation = torch.zeros_like(z_m) if first else z_m - zp_m
        measurement = self._measurement(enc_m, observed) if self.y_input == "measurement" else state["measurement"]
        return out, _state_to(z, z_m, innovation, a_t.float(), y_state, measurement)

    @staticmethod
    def _measurement(enc_m: Tensor, observed: Optional[Tensor]) -> Tensor:
        """What ``y_input="measurement"`` feeds the y LSTM about a frame: [encoder mean x seen,
        seen] (B, n_z + 1), zeros and flag 0 where the frame was hidden."""
        seen = enc_m.new_ones(enc_m.shape[0], 1) if observed is None else observed.view(-1, 1).to(enc_m.dtype)
        return torch.cat([enc_m * seen, seen], dim=-1)

    # ------------------------------------------------------------------ batched
    def observation_mask(self, B: int, T: int, device: torch.device) -> Optional[Tensor]:
        """Observation dropout: (B, T) bool, frames t >= 2 hidden with probability
        ``obs_dropout`` in training mode, in runs of ``obs_dropout_span`` frames (blocks
        of that length at a random phase per sequence, each hidden or seen as a whole);
        None (all observed) otherwise."""
        if not (self.training and self.obs_dropout > 0.0):
            return None
        span = self.obs_dropout_span
        if span == 1:
            mask = torch.rand(B, T, device=device) >= self.obs_dropout
        else:
            phase = torch.randint(0, span, (B, 1), device=device)
            block = (torch.arange(T, device=device).view(1, T) + phase) // span
            seen = torch.rand(B, (T - 1 + span) // span + 1, device=device) >= self.obs_dropout
            mask = torch.gather(seen, 1, block)
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
        # y_input="measurement": q(y_t) does not read z, so every step's is computed once up front
        y_seq = self.measurement_y(enc_m, actions, observed) if self.y_input == "measurement" else None
        y_window = None
        if self.y_static and self.training:  # one draw of q(y | window) = q(y_T) for every step
            y_window = self._draw(y_seq[0][:, -1], y_seq[1][:, -1], sample)
        state = None
        steps: list[dict[str, Tensor]] = []
        for t in range(T):
            out, state = self.step(enc_m[:, t], enc_v[:, t], actions[:, t], state, sample,
                                   observed=None if observed is None else observed[:, t], y_given=y_window,
                                   y_post=None if y_seq is None else (y_seq[0][:, t], y_seq[1][:, t]))
            steps.append(out)
        res = {k: torch.stack([s[k] for s in steps], dim=1) for k in steps[0]}
        if observed is not None:
            res["observed"] = observed
        res["enc_mean"], res["enc_var"] = enc_m, enc_v
        if decode:  # infer_latents skips it: the latents never depend on the decoders
            res["recon"] = self.decode(res["z"].reshape(B * T, -1)).view(B, T, *obs.shape[2:])
        return res

    def measurement_y(self, enc_m: Tensor, actions: Tensor, observed: Optional[Tensor]) -> tuple[Tensor, Tensor]:
        """``y_input="measurement"``: the causal q(y_t | frames before t) of every step, mean and
        variance (B, T, n_y), from the y posterior run alone over the measurements (it does not
        read z). The last step's is q(y | the window's frames 1..T-1), which ``y_static`` draws
        once per sequence in training. enc_m (B, T, n_z), actions (B, T, n_a)."""
        B, T = enc_m.shape[:2]
        state = self.initial_state(B, enc_m.device)
        y_state = tuple(state[k] for k in _Y_STATE_KEYS if k in state)
        z_in, a_prev = state["measurement"], state["a"]
        means, variances = [], []
        for t in range(T):
            y_m, y_v, y_state = self.y_posterior(z_in, a_prev, y_state)
            means.append(y_m)
            variances.append(y_v)
            z_in = self._measurement(enc_m[:, t], None if observed is None else observed[:, t])
            a_prev = actions[:, t]
        return torch.stack(means, dim=1), torch.stack(variances, dim=1)

    def elbo_terms(self, batch: Mapping[str, Tensor], sample: bool = True) -> dict[str, Tensor]:
        """Per-sequence terms averaged over the batch (all float32 scalars):

        nll     = sum_t sum_{c,pixels} -log N(o_t; dec(z_t), sigma_c^2)
        kl_z    = KL(q(z_1) || N(0, I)) + sum_{t>=2} KL(q_filt(z_t) || p(z_t | z_{t-1}, y_t, a_t))
        kl_y    = sum_{t>=2} KL(q(y_t | .) || p(y_t | a_t, N))
                  + w_pop * (-log p(E_seen | mu_0, tau))   (population level, ``pop``)
                  (``y_static``: KL(q(y_T | .) || p(y | N)) once, the prior without its action term)
        entropy = sum_t H[q_filt(z_t)] + sum_{t>=2} H[q(y_t | .)]   (``y_static``: H[q(y_T | .)])
        n_dims  = T * C * 28 * 28 (observation dimensions per sequence)
        pop     = the population term alone (also inside kl_y), logged for inspection
        ELBO = -(nll + kl_z + kl_y). ``out`` holds the forward outputs. ``w_pop`` is
        ``prior.population_weight`` (1 / training sequences; 1 / n_objects if unset).
        With ``elbo_samples`` K > 1 in training mode (and ``sample``) every sequence is
        filtered K times with independent samples and the terms are averaged over all
        B x K rows (``out`` then has B x K rows, sample-major within a sequence).
        """
        obs, actions = batch["obs"], batch["actions"]
        if self.elbo_samples > 1 and self.training and sample:
            k = self.elbo_samples
            obs, actions = obs.repeat_interleave(k, 0), actions.repeat_interleave(k, 0)
            batch = {**batch, "obs": obs, "actions": actions, "object_id": batch["object_id"].repeat_interleave(k, 0)}
        out = self.forward(obs, actions, sample=sample)
        B, T = obs.shape[:2]
        log_sigma = self.obs_log_sigma()  # (C,) or (C, 28, 28)
        if log_sigma.dim() == 1:
            log_sigma = log_sigma.view(-1, 1, 1)
        log_sigma = log_sigma[None, None]  # broadcasts over (B, T, C, 28, 28)
        nll = gaussian_nll(obs, out["recon"], log_sigma).sum(dim=(1, 2, 3, 4)).mean()
        floors = self.training and sample and (self.free_bits_z > 0 or self.free_bits_y > 0)
        extra = out["z"].new_zeros(()).float()  # what the free-bits floors add to kl_z + kl_y

        def kl_term(kl: Tensor, floor: float) -> Tensor:  # (B, T', D) -> per-sequence KL, batch mean
            nonlocal extra
            plain = kl.sum(-1).sum(1).mean()
            if not (floors and floor > 0):
                return plain
            used = free_bits_kl(kl, floor)
            extra = extra + (used - plain).detach()
            return used

        kl_z = kl_term(kl_diag_gaussians(out["z_mean"], out["z_var"], out["zp_mean"], out["zp_var"], per_dim=True),
                       self.free_bits_z)
        ent = gaussian_entropy(out["z_var"]).sum(1)
        if self.y_static:  # one y per sequence: one KL of q(y | window) = q(y_T) to p(y | object)
            py_m, py_v = self.prior(batch["object_id"], torch.zeros_like(actions[:, :1]))
            kl_y = kl_term(kl_diag_gaussians(out["y_mean"][:, -1:], out["y_var"][:, -1:], py_m, py_v, per_dim=True),
                           self.free_bits_y)
            ent = ent + gaussian_entropy(out["y_var"][:, -1:]).sum(1)
        elif T > 1:
            py_m, py_v = self.prior(batch["object_id"], actions[:, 1:])
            kl_y = kl_term(kl_diag_gaussians(out["y_mean"][:, 1:], out["y_var"][:, 1:], py_m, py_v, per_dim=True),
                           self.free_bits_y)
            ent = ent + gaussian_entropy(out["y_var"][:, 1:]).sum(1)
        else:
            kl_y = out["y_mean"].new_zeros(()).float()
            self.prior(batch["object_id"], actions[:, :1])  # marks the objects seen in training
        over = self.overshooting_kl(out, actions) if self.training and sample else None
        if over is not None:
            kl_z = kl_z + self.overshoot_weight * over
        w_pop = self.prior.population_weight
        pop = self.prior.population_nll() * (1.0 / self.prior.n_objects if w_pop is None else float(w_pop))
        kl_y = kl_y + pop
        n_dims = torch.tensor(float(T * obs.shape[2] * 28 * 28), device=obs.device)
        terms = {"nll": nll, "kl_z": kl_z, "kl_y": kl_y, "pop": pop.detach(), "entropy": ent.mean(), "n_dims": n_dims,
                 "out": out}
        if over is not None:
            terms["overshoot"] = over.detach()
        if floors:
            terms["free_bits"] = extra
        return terms

    def overshooting_kl(self, out: Mapping[str, Tensor], actions: Tensor) -> Optional[Tensor]:
        """Latent overshooting (Hafner et al. 2019): per sequence (batch mean), the mean over
        d = 2..D (D = ``overshoot``) of sum_t KL(sg[q_filt(z_{t+d})] || p_d(z_{t+d} | z_t)),
        where p_d rolls the transition d steps from the sample z_t of q_filt under the
        posterior's y samples and the actions, sampling the intermediate states; the last
        step's Gaussian is p_d. The posterior is held fixed (stop-gradient), so these terms
        train the transition (and through it y) to predict several frames ahead, without
        pulling q_filt towards the open-loop prediction. None when D = 1 or T <= 2."""
        T = out["z"].shape[1]
        horizon = min(self.overshoot, T - 1)
        if horizon < 2:
            return None
        z, y = out["z"], out["y"]
        q_m, q_v = out["z_mean"].detach(), out["z_var"].detach()
        total = z.new_zeros(()).float()
        for d in range(2, horizon + 1):
            n = T - d  # start frames t = 0 .. T-d-1
            zs = z[:, :n]
            for j in range(1, d + 1):
                m, v = self.transition(zs, y[:, j:j + n], actions[:, j:j + n].float())
                zs = self._draw(m, v, True) if j < d else zs
            total = total + kl_diag_gaussians(q_m[:, d:], q_v[:, d:], m, v).sum(1).mean()
        return total / (horizon - 1)

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
