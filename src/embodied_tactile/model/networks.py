"""Building blocks of the Latent Filter: Gaussian helpers and small networks.

Everything probabilistic (variances, Bayesian integration, KL, entropy) is computed in
float32 with autocast disabled, whatever precision the surrounding network runs in.
"""

from __future__ import annotations

import math
from contextlib import contextmanager, nullcontext
from typing import Any, Iterator, Optional, Sequence

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .options import PriorOptions, build

LOG_2PI = math.log(2.0 * math.pi)


@contextmanager
def _autocast_off(device_type: str) -> Iterator[None]:
    with torch.autocast(device_type=device_type, enabled=False):
        yield


_NULL = nullcontext()


def float32_region(x: Tensor):
    """Context with autocast disabled for the device of ``x`` (callers cast their inputs
    to float32). A no-op context when autocast is off (cheap on the online path)."""
    dev = x.device.type
    if torch.is_autocast_enabled(dev):
        return _autocast_off(dev)
    return _NULL


def softplus_var(raw: Tensor, floor: float) -> Tensor:
    """Variance head: ``softplus(raw) + floor`` in float32 (never below ``floor``)."""
    with float32_region(raw):
        return F.softplus(raw.float()) + floor


def fuse_gaussians(m1: Tensor, v1: Tensor, m2: Tensor, v2: Tensor) -> tuple[Tensor, Tensor]:
    """Product of two diagonal Gaussians N(m1, v1) * N(m2, v2), normalised, in variance form.

    mu = (v2 * m1 + v1 * m2) / (v1 + v2),  var = v1 * v2 / (v1 + v2).

    Algebraically identical to the precision form (1/var = 1/v1 + 1/v2) but never divides
    by a single small variance, so it stays finite where 1/v overflows (float16: 1/1e-5).
    Always evaluated in float32 with autocast disabled.
    """
    with float32_region(m1):
        m1, v1, m2, v2 = m1.float(), v1.float(), m2.float(), v2.float()
        s = v1 + v2
        mu = (v2 * m1 + v1 * m2) / s
        var = v1 * v2 / s
    return mu, var


def kl_diag_gaussians(mq: Tensor, vq: Tensor, mp: Tensor, vp: Tensor, per_dim: bool = False) -> Tensor:
    """KL(N(mq, vq) || N(mp, vp)) for diagonal Gaussians, summed over the last dim
    (``per_dim``: one value per dimension, not summed).

    Log-space with expm1 (precise for nearly equal variances): with lq = log vq,
    lp = log vp, d = lq - lp:  KL = 0.5 * sum(expm1(d) - d + (mq - mp)^2 * exp(-lp)).
    """
    with float32_region(mq):
        lq = torch.log(vq.float())
        lp = torch.log(vp.float())
        d = lq - lp
        diff = mq.float() - mp.float()
        kl = 0.5 * (torch.expm1(d) - d + diff * diff * torch.exp(-lp))
        return kl if per_dim else kl.sum(-1)


def gaussian_entropy(var: Tensor) -> Tensor:
    """Differential entropy of a diagonal Gaussian, summed over the last dim."""
    with float32_region(var):
        return 0.5 * (torch.log(var.float()) + 1.0 + LOG_2PI).sum(-1)


def gaussian_nll(x: Tensor, mean: Tensor, log_sigma: Tensor) -> Tensor:
    """Elementwise -log N(x; mean, sigma^2) in float32 (``log_sigma`` broadcasts)."""
    with float32_region(x):
        ls = log_sigma.float()
        r = (x.float() - mean.float()) * torch.exp(-ls)
        return 0.5 * r * r + ls + 0.5 * LOG_2PI


def gaussian_nll_frames(x: Tensor, mean: Tensor, log_sigma: Tensor) -> Tensor:
    """``gaussian_nll(x, mean, log_sigma.view(-1, 1, 1))`` summed over each frame's channels
    and pixels, for frames x, mean (..., C, H, W) and one ``log_sigma`` per channel (C,):
    (...,), float32. Per channel 0.5 exp(-2 log_sigma) sum (x - mean)^2 + H W (log_sigma
    + 0.5 log 2 pi): the same sum, float rounding aside, in three passes over the frames
    instead of about a dozen (the likelihood of a training step at the paper's shapes 0.71
    -> 0.37 s, docs/experiments/speed_levers.md, 2026-11-27)."""
    with float32_region(x):
        d = x.float() - mean.float()
        ls = log_sigma.float()
        sq = d.square().sum(dim=(-2, -1))  # (..., C)
        return (0.5 * sq * torch.exp(-2.0 * ls) + x.shape[-2] * x.shape[-1] * (ls + 0.5 * LOG_2PI)).sum(-1)


#: Largest batch at which ``small_batch_convs`` switches oneDNN off. Measured with
#: ``benchmarks/bench_small_batch_convs.py`` (torch 2.13 CPU, 1 thread, multi_l filter_step,
#: docs/reference/model.md "Speed and the CPU budget", docs/experiments/speed_levers.md): oneDNN off is 1.32x faster at batch 1 and 1.18x at 2, even at 4,
#: and 0.81x (slower) at 8.
SMALL_BATCH_ONEDNN_OFF = 2


@contextmanager
def small_batch_convs(n: int, threshold: int = SMALL_BATCH_ONEDNN_OFF) -> Iterator[None]:
    """The one speed switch of the models (used by ``LatentFilter.filter_step``): for a batch
    of at most ``threshold`` frames on CPU, run the convolutions with PyTorch's native
    kernels instead of oneDNN, whose per-call overhead dominates at batch 1 (see
    :data:`SMALL_BATCH_ONEDNN_OFF`). Uses the public ``torch.backends.mkldnn.enabled`` flag,
    restored on exit; a no-op for larger batches or where oneDNN is not built in. Results
    are the same either way (up to float rounding)."""
    mkldnn = torch.backends.mkldnn
    if n > threshold or not mkldnn.is_available() or not mkldnn.enabled:
        yield
        return
    mkldnn.enabled = False
    try:
        yield
    finally:
        mkldnn.enabled = True


# --------------------------------------------------------------------------- networks

#: Batches of at least this many frames run the conv encoders / decoders in channels_last
#: on CPU (oneDNN's fast layout; docs/reference/model.md "Speed and the CPU budget", docs/experiments/speed_levers.md).
CHANNELS_LAST_MIN_FRAMES = 64

#: The conv encoders / decoders take batches of more frames than this in chunks of this
#: size, without autograd and, on CPU, with it (per-frame results unchanged; the weight
#: gradients are summed over chunks, equal to float rounding). Whole-trial batches of thousands of frames
#: otherwise spill every layer's activations out of the caches: no-grad 19200 frames 1.8x
#: faster in chunks; a training step at the paper's shapes (B=48, T=300, multi_l, 2 threads)
#: 9.1 -> 5.9 s, where one call over all 14400 frames was slower than the naive per-frame
#: loop (6.7 s). The default budget's 800-frame batches are one chunk; smaller chunks
#: were slower there (0.28 s a step unchunked, 0.31 s in chunks of 400, 0.33 s of 200).
#: ``benchmarks/bench_step_levers.py``, docs/reference/model.md "Speed and the CPU budget", docs/experiments/speed_levers.md.
CONV_CHUNK_FRAMES = 1024


def _run(net: nn.Module, x: Tensor) -> Tensor:
    """``net.body(x)``, through its ``torch.compile``d copy where :func:`compile_convs`
    switched it on, the module is in training mode, autograd records and x is on the CPU
    (the training step); eager everywhere else (validation, inference, online filtering),
    so that their other batch shapes never trigger a recompilation."""
    if net.compiled and net.training and x.device.type == "cpu" and torch.is_grad_enabled():
        fn = net.__dict__.get("_compiled_body")
        if fn is None:
            fn = net.__dict__["_compiled_body"] = torch.compile(net.body)
        return fn(x)
    if x.shape[0] > CONV_CHUNK_FRAMES and (x.device.type == "cpu" or not torch.is_grad_enabled()):
        # chunks that stay in cache (see CONV_CHUNK_FRAMES); a GPU's training step keeps its
        # one large call
        return torch.cat([net.body(c) for c in x.split(CONV_CHUNK_FRAMES)])
    return net.body(x)


def compile_convs(model: nn.Module, enabled: bool = True) -> int:
    """The speed switch of the training step (train.py's ``compile_convs``, default on;
    docs/reference/model.md "Speed and the CPU budget", docs/experiments/speed_levers.md): ``torch.compile`` (inductor) of the body of every
    :class:`ConvEncoder` and :class:`ConvDecoder` in ``model``, used for training steps on
    CPU only; the time loop stays eager. The same weights and the same function, float
    rounding aside (fused elementwise kernels). Returns the number of networks switched."""
    n = 0
    for mod in model.modules():
        if isinstance(mod, (ConvEncoder, ConvDecoder)):
            mod.compiled = bool(enabled)
            n += 1
    return n


class _CompilableBody(nn.Module):
    """Shared by the conv encoder and decoder: a ``compiled`` flag (:func:`compile_convs`)
    and a compiled copy of ``body`` that is never pickled or copied (rebuilt on use)."""

    compiled: bool = False

    def __getstate__(self):
        state = dict(super().__getstate__())
        state.pop("_compiled_body", None)
        return state


def _check_widths(widths: Sequence[int]) -> tuple[int, int]:
    widths = tuple(int(w) for w in widths)
    if len(widths) != 2 or min(widths) < 1:
        raise ValueError(f"encoder widths must be two positive ints (28->14->7), got {widths}")
    return widths  # type: ignore[return-value]


class ConvEncoder(_CompilableBody):
    """Inverse measurement model q(z_t | o_t): two stride-2 convs 28->14->7, MLP head.

    Input (N, C, 28, 28), output mean (N, n_z) and variance (N, n_z) (softplus + floor,
    float32). Runs over all B*T frames in one call.
    """

    def __init__(self, in_channels: int, n_z: int, widths: Sequence[int] = (16, 32),
                 hidden: int = 128, min_var: float = 1e-3) -> None:
        super().__init__()
        w1, w2 = _check_widths(widths)
        self.in_channels = int(in_channels)
        self.min_var = float(min_var)
        self.conv = nn.Sequential(
            nn.Conv2d(in_channels, w1, 4, stride=2, padding=1), nn.ELU(),
            nn.Conv2d(w1, w2, 4, stride=2, padding=1), nn.ELU(),
            nn.Flatten(),
            nn.Linear(w2 * 7 * 7, hidden), nn.ELU(),
        )
        self.head = nn.Linear(hidden, 2 * n_z)

    def forward(self, o: Tensor) -> tuple[Tensor, Tensor]:
        if o.shape[-3:] != (self.in_channels, 28, 28):
            raise ValueError(f"encoder expects (N, {self.in_channels}, 28, 28), got {tuple(o.shape)}")
        m, raw = _run(self, o).chunk(2, dim=-1)
        return m.float(), softplus_var(raw, self.min_var)

    def body(self, o: Tensor) -> Tensor:
        """Convs and MLP: (N, C, 28, 28) -> (N, 2 n_z) raw head output (what
        :func:`compile_convs` compiles). The channels_last copy is made here, so a chunked
        pass (:func:`_run`) copies one chunk at a time, never the whole input."""
        if o.shape[0] >= CHANNELS_LAST_MIN_FRAMES and o.device.type == "cpu":
            o = o.contiguous(memory_format=torch.channels_last)  # ~2-3x faster oneDNN convs
        return self.head(self.conv(o))


class ConvDecoder(_CompilableBody):
    """Observation model mean: mirror of :class:`ConvEncoder` (transposed convs 7->14->28).

    Input z (N, n_z), output (N, C, 28, 28) means; the Gaussian sigma lives in the model.
    """

    def __init__(self, out_channels: int, n_z: int, widths: Sequence[int] = (16, 32),
                 hidden: int = 128) -> None:
        super().__init__()
        w1, w2 = _check_widths(widths)
        self.out_channels = int(out_channels)
        self.w2 = w2
        self.fc = nn.Sequential(nn.Linear(n_z, hidden), nn.ELU(), nn.Linear(hidden, w2 * 7 * 7), nn.ELU())
        self.deconv = nn.Sequential(
            nn.ConvTranspose2d(w2, w1, 4, stride=2, padding=1), nn.ELU(),
            nn.ConvTranspose2d(w1, out_channels, 4, stride=2, padding=1),
        )

    def forward(self, z: Tensor) -> Tensor:
        return _run(self, z)

    def body(self, z: Tensor) -> Tensor:
        """MLP and transposed convs (what :func:`compile_convs` compiles). Batches of at
        least :data:`CHANNELS_LAST_MIN_FRAMES` frames on CPU run the convs in channels_last,
        the last transposed conv as :func:`subpixel_conv_transpose`, and return the means in
        the contiguous layout of the observations (the likelihood's elementwise ops read
        both alike)."""
        h = self.fc(z).view(z.shape[0], self.w2, 7, 7)
        if not (z.shape[0] >= CHANNELS_LAST_MIN_FRAMES and z.device.type == "cpu"):
            return self.deconv(h)
        h = h.contiguous(memory_format=torch.channels_last)  # ~2x faster transposed convs
        h = self.deconv[1](self.deconv[0](h))
        last = self.deconv[2]
        return subpixel_conv_transpose(h, last.weight, last.bias)


#: ``_SUBPIXEL_TAPS[r]``: for output phase r (row or column 2m + r) of a stride-2, 4-tap,
#: padding-1 transposed conv, the kernel tap that input m - 1, m, m + 1 meets (4: none)
_SUBPIXEL_TAPS = ((3, 1, 4), (4, 2, 0))


def subpixel_conv_transpose(x: Tensor, weight: Tensor, bias: Optional[Tensor]) -> Tensor:
    """``F.conv_transpose2d(x, weight, bias, stride=2, padding=1)`` for a 4x4 kernel
    (:class:`ConvDecoder`'s layers), computed as one 3x3 convolution to the four output
    phases (2 x 2 of each output pixel's row and column parity) and a pixel shuffle, the
    result contiguous. The same products and sums, float rounding aside
    (tests/unit/test_speed_switch.py). oneDNN's
    transposed-conv forward to 1-2 output channels runs far below its conv forward on CPU
    (docs/experiments/speed_levers.md, 2026-11-27)."""
    c_in, c_out = weight.shape[:2]
    if weight.shape[2:] != (4, 4):
        raise ValueError(f"subpixel_conv_transpose needs a 4x4 kernel, got {tuple(weight.shape)}")
    idx = torch.tensor(_SUBPIXEL_TAPS, device=weight.device)  # (phase, tap)
    w = F.pad(weight, (0, 1, 0, 1))[:, :, idx[:, :, None, None], idx[None, None, :, :]]  # (in, out, r, a, s, b)
    w = w.permute(1, 2, 4, 0, 3, 5).reshape(4 * c_out, c_in, 3, 3)
    b = None if bias is None else bias.repeat_interleave(4)
    y = F.conv2d(x, w, b, padding=1)  # (N, 4 c_out, H, W): channel 4 c + 2 r + s
    n, _, h, wd = y.shape  # the pixel shuffle as one copy into the contiguous layout, whatever y's
    return y.reshape(n, c_out, 2, 2, h, wd).permute(0, 1, 4, 2, 5, 3).reshape(n, c_out, 2 * h, 2 * wd)


class TransitionNet(nn.Module):
    """p(z_t | z_{t-1}, y_t, a_t) = N(z_{t-1} + f_mu(.), softplus(f_v(.)) + floor), f_mu and
    f_v an MLP on the concatenation [z_{t-1}, y_t, a_t].

    Residual form: the MLP predicts the change of z; the mean heads are zero-initialised so
    the untrained transition is a random walk around z_{t-1}.
    """

    def __init__(self, n_z: int, n_y: int, n_a: int, hidden: int = 128, min_var: float = 1e-3) -> None:
        super().__init__()
        self.min_var = float(min_var)
        self.body = nn.Sequential(nn.Linear(n_z + n_y + n_a, hidden), nn.ELU(),
                                  nn.Linear(hidden, hidden), nn.ELU())
        self.mean = nn.Linear(hidden, n_z)
        self.var = nn.Linear(hidden, n_z)
        nn.init.zeros_(self.mean.weight)
        nn.init.zeros_(self.mean.bias)

    def forward(self, z_prev: Tensor, y: Tensor, a: Tensor) -> tuple[Tensor, Tensor]:
        h = self.body(torch.cat([z_prev, y, a], dim=-1))
        return z_prev.float() + self.mean(h).float(), softplus_var(self.var(h), self.min_var)


Y_UPDATES = ("evidence", "direct")


class YPosterior(nn.Module):
    """q(y_t | z_{t-1}, y_{t-1}, a_{t-1}): an LSTMCell fed [z_{t-1}, a_{t-1}] and a Gaussian head.

    ``update`` says what the head's Gaussian N(m_t, s_t) is:

    * ``"direct"``: q(y_t) itself; y_{t-1} enters only through the LSTM state (the authors'
      earlier code).
    * ``"evidence"``: one step's evidence about the trial-constant y. q(y_t) is the normalised
      product of a N(0, 1/prior_precision) start and all evidence so far,
      precision P_t = prior_precision + sum_k lambda_k, mean = (sum_k lambda_k m_k) / P_t,
      with lambda_k = softplus(raw_k) (no floor needed: P_t >= prior_precision > 0), or
      lambda_k = max_evidence * sigmoid(raw_k) when ``max_evidence`` is set: one frame's
      evidence is then bounded, so the mean cannot follow the latest frame by giving it
      ever larger precision (unbounded lambda lets q(y_t) carry the moving state);
      ``evidence_range`` r bounds the evidence means, m_k = r tanh(raw_m / r), so that
      one step moves the mean by at most lambda_k (r + |mean|) / P_t.
      This is the exact Bayesian filter for a static latent, so the posterior can only
      sharpen as evidence accumulates, and the evidence network is a local function that
      short training windows teach as well as whole trials. The variance 1/P_t + min_var
      keeps the floor. y_{t-1} enters through (P_{t-1}, sum lambda m) and the LSTM state.

    The recurrent state is a tuple of tensors (h, c) or (h, c, P, sum lambda m); see
    :meth:`initial_state`. All Gaussian arithmetic runs in float32.
    """

    def __init__(self, n_z: int, n_y: int, n_a: int, hidden: int = 128, min_var: float = 1e-3,
                 update: str = "direct", prior_precision: float = 1.0, max_evidence: float | None = None,
                 evidence_range: float | None = None) -> None:
        super().__init__()
        if update not in Y_UPDATES:
            raise ValueError(f"y_update must be one of {Y_UPDATES}, got {update!r}")
        if not prior_precision > 0:
            raise ValueError(f"y_prior_precision must be > 0, got {prior_precision}")
        for name, value in (("y_evidence_max", max_evidence), ("y_evidence_range", evidence_range)):
            if value is not None and not value > 0:
                raise ValueError(f"{name}={value} must be > 0 (or None: unbounded)")
        evidence = update == "evidence"  # the bounds act on the evidence update only; direct ignores them
        self.max_evidence = float(max_evidence) if evidence and max_evidence is not None else None
        self.evidence_range = float(evidence_range) if evidence and evidence_range is not None else None
        self.hidden, self.n_y = int(hidden), int(n_y)
        self.min_var = float(min_var)
        self.update = update
        self.prior_precision = float(prior_precision)
        self.cell = nn.LSTMCell(n_z + n_a, hidden)
        self.head = nn.Linear(hidden, 2 * n_y)

    def initial_state(self, batch: int, device: torch.device, dtype: torch.dtype = torch.float32,
                      start: Optional[tuple[Tensor, Tensor]] = None) -> tuple[Tensor, ...]:
        """Zero LSTM state and, with ``update="evidence"``, the start of the evidence product:
        N(0, 1/prior_precision), or ``start`` = (mean, var) (batch, n_y) when given (the
        population marginal, ``y_start="population"``)."""
        h = torch.zeros(batch, self.hidden, device=device, dtype=dtype)
        if self.update == "direct":
            return h, h.clone()
        if start is None:
            prec = torch.full((batch, self.n_y), self.prior_precision, device=device, dtype=torch.float32)
            return h, h.clone(), prec, torch.zeros_like(prec)
        with float32_region(start[0]):
            prec = 1.0 / start[1].float()
            return h, h.clone(), prec, start[0].float() * prec

    def forward(self, z_prev: Tensor, a_prev: Tensor, state: tuple[Tensor, ...]
                ) -> tuple[Tensor, Tensor, tuple[Tensor, ...]]:
        h, c = self.cell(torch.cat([z_prev, a_prev], dim=-1), (state[0], state[1]))
        m, raw = self.head(h).chunk(2, dim=-1)
        if self.update == "direct":
            return m.float(), softplus_var(raw, self.min_var), (h, c)
        with float32_region(raw):
            raw = raw.float()
            lam = F.softplus(raw) if self.max_evidence is None else self.max_evidence * torch.sigmoid(raw)
            m = m.float()
            if self.evidence_range is not None:
                m = self.evidence_range * torch.tanh(m / self.evidence_range)
            prec = state[2] + lam
            pm = state[3] + lam * m
            mean, var = pm / prec, 1.0 / prec + self.min_var
        return mean, var, (h, c, prec, pm)


class HierarchicalPrior(nn.Module):
    """Hierarchical prior over the indirectly observable latent y (docs/reference/model.md):

    * population:  e_n ~ N(mu_0, diag tau^2)            (learned mu_0, tau^2 = softplus + floor)
    * object n:    p(y_t | a_t, n) = N(e_n + W a_t, diag sigma^2)
    * new object:  p(y_t | a_t)    = N(mu_0 + W a_t, diag(sigma^2 + tau^2))  (e marginalised)

    ``e_n`` is one ``nn.Embedding`` row per object id (a point estimate of the object's
    embedding, collision-free), ``W`` a zero-initialised linear action term
    (``action_term=False`` drops it, as in the authors' earlier code), ``sigma^2`` a
    per-dimension variance ``softplus(raw) + var_floor`` at ``sigma_init**2``, fixed by
    default (``learn_sigma=True`` learns it; a learned sigma widened to make the pull
    cheap, docs/experiments/object_codes.md); tau^2 starts at ``pop_sigma_init**2``.

    The population term ``-log p(E_seen | mu_0, tau)`` over the objects met in training
    (:meth:`population_nll`) makes the embeddings draws of one population and fits the
    population to them; the Latent Filter adds it, scaled by ``population_weight`` (1 / the
    number of training sequences, so that the dataset's bound counts it once), to ``kl_y``.
    Objects are marked *seen* (a persistent buffer) when they occur in a training-mode call;
    in evaluation an unseen object id, or id -1, gets the population marginal, so an object
    never touched in training still has a prior.

    ``labels=False`` (default) ignores every object id, in training too: every sequence gets
    the population marginal, no embedding is used and the population term is 0, so y can only
    carry what the observations and actions carry (a new object comes with no label).
    ``labels=True`` is the paper's label-conditioned prior (``recipe=recognition``,
    ``experiment=paper``).

    ``learn_embedding=False`` (default) keeps the object codes e_n at their initial draws from
    N(0, pop_sigma_init^2) (a fixed random projection of the one-hot label): the codes cannot
    follow q(y) to one shared point, so KL_y is small only where q(y) tells the training
    objects apart (docs/reference/model.md, "Fixed object codes"). mu_0 and tau are still fitted to
    the codes, so a new object keeps its population marginal.
    """

    def __init__(self, n_y: int, n_a: int, n_objects: int, **options: Any) -> None:
        super().__init__()
        opts: PriorOptions = build(PriorOptions, options, "prior")
        sigma_init, learn_sigma, var_floor = opts.sigma_init, opts.learn_sigma, opts.var_floor
        pop_sigma_init, population_weight = opts.pop_sigma_init, opts.population_weight
        labels, learn_embedding, action_term = opts.labels, opts.learn_embedding, opts.action_term
        self.labels = bool(labels)
        if sigma_init ** 2 <= var_floor:
            raise ValueError(f"prior sigma_init**2={sigma_init ** 2} must exceed var_floor={var_floor}")
        if pop_sigma_init ** 2 <= var_floor:
            raise ValueError(f"prior pop_sigma_init**2={pop_sigma_init ** 2} must exceed var_floor={var_floor}")
        if population_weight is not None and not population_weight >= 0:
            raise ValueError(f"prior population_weight must be >= 0 or null, got {population_weight}")
        self.n_objects = int(n_objects)
        self.var_floor = float(var_floor)
        #: weight of the population term per training sequence; None = 1 / n_objects until
        #: the LightningModule sets 1 / (number of training sequences) at the start of fit
        self.population_weight = population_weight
        self.embedding = nn.Embedding(n_objects, n_y)
        nn.init.normal_(self.embedding.weight, std=pop_sigma_init)
        self.embedding.weight.requires_grad_(bool(learn_embedding))
        self.pop_mean = nn.Parameter(torch.zeros(n_y))
        self.pop_raw_var = nn.Parameter(torch.full((n_y,), math.log(math.expm1(pop_sigma_init ** 2 - var_floor))))
        self.register_buffer("seen", torch.zeros(n_objects, dtype=torch.bool))
        self.action = nn.Linear(n_a, n_y, bias=False) if action_term else None
        if self.action is not None:
            nn.init.zeros_(self.action.weight)
        v = sigma_init ** 2 - var_floor
        raw = torch.full((n_y,), math.log(math.expm1(v)))  # softplus^-1
        if learn_sigma:
            self.raw_var = nn.Parameter(raw)
        else:
            self.register_buffer("raw_var", raw)

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs):
        # checkpoints from before the population level: every object counts as seen, the
        # population starts at N(0, pop_sigma_init^2)
        if prefix + "embedding.weight" in state_dict:
            if prefix + "seen" not in state_dict:
                state_dict[prefix + "seen"] = torch.ones_like(self.seen)
            for name in ("pop_mean", "pop_raw_var"):
                state_dict.setdefault(prefix + name, getattr(self, name).detach().clone())
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                                      error_msgs)

    @property
    def learn_embedding(self) -> bool:
        """Whether the object codes train (``learn_embedding``): read off the embedding itself."""
        return self.embedding.weight.requires_grad

    def pop_var(self) -> Tensor:
        return softplus_var(self.pop_raw_var, self.var_floor)

    def population_nll(self) -> Tensor:
        """``-sum_{n seen} log N(e_n; mu_0, tau^2)`` in float32 (0 before any object is seen)."""
        with float32_region(self.pop_mean):
            e = self.embedding.weight.float()[self.seen]
            if e.numel() == 0:
                return self.pop_mean.new_zeros((), dtype=torch.float32)
            return gaussian_nll(e, self.pop_mean.float(), 0.5 * torch.log(self.pop_var())).sum()

    def forward(self, object_id: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        """object_id (B,), actions (B, T, n_a) -> mean (B, T, n_y), var (B, T, n_y).

        Id -1, or (in evaluation) an object never seen in training, gets the population
        marginal N(mu_0 + W a_t, sigma^2 + tau^2)."""
        if object_id.dtype not in (torch.int64, torch.int32):
            raise TypeError(f"object_id must be an integer tensor, got {object_id.dtype}")
        if object_id.numel() and (int(object_id.min()) < -1 or int(object_id.max()) >= self.n_objects):
            raise ValueError(f"object_id out of range [-1, {self.n_objects}) (-1 = a new object): "
                             f"min={int(object_id.min())} max={int(object_id.max())}")
        oid = object_id.long() if self.labels else torch.full_like(object_id, -1, dtype=torch.long)
        known = oid >= 0
        if self.training:
            self.seen[oid[known]] = True
        else:
            known = known & self.seen[oid.clamp(min=0)]
        with float32_region(actions):
            obj = self.embedding(oid.clamp(min=0)).float()
            pop = self.pop_mean.float().expand_as(obj)
            mean = torch.where(known[:, None], obj, pop)[:, None, :].expand(-1, actions.shape[1], -1)
            if self.action is not None:
                mean = mean + self.action(actions.float())
            var_y = softplus_var(self.raw_var, self.var_floor)
            var = torch.where(known[:, None], var_y, var_y + self.pop_var())[:, None, :].expand_as(mean)
        return mean, var
