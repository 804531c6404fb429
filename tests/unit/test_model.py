"""Latent Filter: structure per modality, learning, online filtering, numerics, checkpoints."""

import functools
import math

import lightning as L
import pytest
import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset

from embodied_tactile.model import (
    ConstrainedAnnealing,
    EarlyFusion,
    LateFusion,
    LatentFilter,
    LatentFilterModule,
)
from embodied_tactile.model.networks import (
    ConvDecoder,
    ConvEncoder,
    TransitionNet,
    fuse_gaussians,
    kl_diag_gaussians,
)
from embodied_tactile.data.modality import modality_names

torch.set_num_threads(2)

# small networks; input_standardize off: these networks are fitted without a TactileDataModule
# (the default needs its training-set channel statistics)
TINY = dict(encoder={"widths": [4, 8], "hidden": 32}, transition_hidden=32, lstm_hidden=32, input_standardize=False)
N_CH = {"acc": 1, "fsr_t": 1, "fsr_b": 1, "fsr_tb": 2, "multi_e": 3, "multi_l": 3, "pendulum": 1}


def make_batch(C, B=4, T=8, seed=0, n_objects=32):
    g = torch.Generator().manual_seed(seed)
    return {
        "obs": torch.rand(B, T, C, 28, 28, generator=g),
        "actions": torch.randn(B, T, 6, generator=g),
        "object_id": torch.randint(0, n_objects, (B,), generator=g),
        "factors": torch.rand(B, 4, generator=g),
        "action_index": torch.randint(0, 16, (B,), generator=g),
    }


class ListDataset(Dataset):
    def __init__(self, batch):
        self.batch = batch

    def __len__(self):
        return self.batch["obs"].shape[0]

    def __getitem__(self, i):
        return {k: v[i] for k, v in self.batch.items()}


def trainer(tmp_path, **kw):
    args = dict(default_root_dir=tmp_path, accelerator="cpu", devices=1, logger=False,
                enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                max_steps=2, limit_val_batches=1, num_sanity_val_steps=0)
    args.update(kw)
    return L.Trainer(**args)


# ------------------------------------------------------------------ structure
@pytest.mark.parametrize("name", modality_names())
def test_modality_builds_only_its_pathways(name):
    m = LatentFilter(name, **TINY)
    encs = [mod for mod in m.modules() if isinstance(mod, ConvEncoder)]
    decs = [mod for mod in m.modules() if isinstance(mod, ConvDecoder)]
    if name == "multi_l":
        assert isinstance(m.observation, LateFusion)
        assert set(m.observation.encoders) == {"vibration", "force"}
        assert sorted(e.in_channels for e in encs) == [1, 2]
        assert sorted(d.out_channels for d in decs) == [1, 2]
        assert m.observation.encoders["vibration"].in_channels == 1
        assert m.observation.decoders["force"].out_channels == 2
    else:
        assert isinstance(m.observation, EarlyFusion)
        assert len(encs) == len(decs) == 1
        assert encs[0].in_channels == decs[0].out_channels == N_CH[name]
        first_conv = next(mod for mod in encs[0].modules() if isinstance(mod, nn.Conv2d))
        assert first_conv.in_channels == N_CH[name]
    out = m(make_batch(N_CH[name], B=2, T=3)["obs"], torch.zeros(2, 3, 6))
    assert out["recon"].shape == (2, 3, N_CH[name], 28, 28)


def test_late_fusion_channel_routing():
    """Channel 0 (acc) only reaches the vibration encoder, 1-2 only the force encoder."""
    torch.manual_seed(0)
    m = LatentFilter("multi_l", **TINY).eval()
    o = torch.rand(2, 3, 28, 28)
    mv, vv = m.observation.encoders["vibration"](o[:, :1])
    mf, vf = m.observation.encoders["force"](o[:, 1:])
    mu, var = m.encode(o)
    mu_ref = (vf * mv + vv * mf) / (vv + vf)
    torch.testing.assert_close(mu, mu_ref)
    torch.testing.assert_close(var, vv * vf / (vv + vf))
    # decoder output: channel 0 from the vibration decoder, 1-2 from the force decoder
    z = torch.randn(2, 16)
    rec = m.decode(z)
    torch.testing.assert_close(rec[:, :1], m.observation.decoders["vibration"](z))
    torch.testing.assert_close(rec[:, 1:], m.observation.decoders["force"](z))


def test_custom_late_pathways_and_bad_configs():
    mod = {"name": "x", "channels": ["fsr_t", "acc", "fsr_b"], "fusion": "late",
           "pathways": {"force": ["fsr_t", "fsr_b"], "vibration": ["acc"]}}
    m = LatentFilter(mod, **TINY)
    assert m.modality["pathways"] == [["force", [0, 2]], ["vibration", [1]]]
    z = torch.randn(2, 16)
    rec = m.decode(z)
    torch.testing.assert_close(rec[:, 1:2], m.observation.decoders["vibration"](z))
    torch.testing.assert_close(rec[:, [0, 2]], m.observation.decoders["force"](z))
    with pytest.raises(ValueError, match="fusion"):
        LatentFilter({"name": "x", "channels": ["acc"], "fusion": "mid"})
    with pytest.raises(ValueError, match="late fusion needs a 'pathways' mapping"):  # no name-based grouping
        LatentFilter({"name": "x", "channels": ["acc", "fsr_t", "fsr_b"], "fusion": "late"})
    with pytest.raises(ValueError, match="2 pathways"):
        LatentFilter({"name": "x", "channels": ["fsr_t", "fsr_b"], "fusion": "late", "pathways": {"all": ["fsr_t", "fsr_b"]}})
    with pytest.raises(ValueError, match="expects obs"):
        LatentFilter("acc", **TINY)(torch.zeros(1, 2, 3, 28, 28), torch.zeros(1, 2, 6))
    with pytest.raises(TypeError, match="net must be a LatentFilter or its config mapping"):
        LatentFilterModule("multi_l")
    assert LatentFilterModule(LatentFilter("multi_l", **TINY)).model.modality["name"] == "multi_l"
    # the module rebuilds the network from its config: the arguments live in LatentFilter only
    net = LatentFilter("multi_e", **TINY)
    rebuilt = LatentFilterModule(net.config())
    assert rebuilt.model.modality["name"] == "multi_e" and rebuilt.hparams["net"] == net.config()
    assert sum(p.numel() for p in rebuilt.parameters()) == sum(p.numel() for p in net.parameters())


@pytest.mark.parametrize("name", modality_names())
def test_module_fusion_class_is_the_one_that_encodes(name, monkeypatch):
    """The modality's fusion is the network's observation model, and its encode / decode are
    what the filter's encode / decode and forward run."""
    net = LatentFilter(name, **TINY)
    module = LatentFilterModule(net)
    fusion = LateFusion if name == "multi_l" else EarlyFusion
    assert type(module.model.observation) is fusion
    calls = []
    for method in ("encode", "decode"):
        orig = getattr(fusion, method)
        monkeypatch.setattr(fusion, method,
                            lambda self, x, _o=orig, _m=method: calls.append(_m) or _o(self, x))
    o = make_batch(N_CH[name], B=2, T=3)["obs"]
    out = module(o, torch.zeros(2, 3, 6))
    assert calls == ["encode", "decode"] and out["recon"].shape == o.shape
    enc_m, enc_v = module.model.encode(o[:, 0])
    torch.testing.assert_close(enc_m, out["enc_mean"][:, 0])
    torch.testing.assert_close(enc_v, out["enc_var"][:, 0])
    assert enc_m.dtype == enc_v.dtype == torch.float32


@pytest.mark.parametrize("name", modality_names())
def test_same_seed_same_initial_parameters(name):
    """The observation model draws its parameters first (encoder then decoder per pathway),
    then the transition: the order the fused-in-LatentFilter code used, so a seed keeps
    giving the same network and the same training."""
    torch.manual_seed(0)
    net = LatentFilter(name, **TINY)
    torch.manual_seed(0)
    encs, decs = [], []
    for _, idx in net.modality["pathways"]:  # drawn in this order
        encs.append(ConvEncoder(len(idx), 16, [4, 8], 32, 1e-3))
        decs.append(ConvDecoder(len(idx), 16, [4, 8], 32))
    transition = TransitionNet(16, 16, 6, 32, 1e-3)
    got = [*net.observation.parameters(), *net.transition.parameters()]
    want = [p for m in (*encs, *decs, transition) for p in m.parameters()]  # registered: encoders, then decoders
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert torch.equal(g, w)


def test_fusion_models_refuse_bad_pathways():
    with pytest.raises(ValueError, match="late fusion needs >= 2 pathways partitioning the channels 0..C-1"):
        LateFusion([("all", [0, 1])], 4, [4, 8], 16, 1e-3)
    with pytest.raises(ValueError, match="late fusion needs >= 2 pathways partitioning the channels 0..C-1"):
        LateFusion([("a", [0]), ("b", [2])], 4, [4, 8], 16, 1e-3)


@pytest.mark.slow
@pytest.mark.parametrize("name", modality_names())
def test_few_steps_decrease_loss(name):
    torch.manual_seed(0)
    m = LatentFilter(name, **TINY)
    batch = make_batch(N_CH[name])
    opt = torch.optim.Adam(m.parameters(), lr=3e-3)

    def loss_at(seed):
        torch.manual_seed(seed)
        t = m.elbo_terms(batch)
        return t["nll"] + t["kl_z"] + t["kl_y"]

    with torch.no_grad():
        before = loss_at(123).item()
    for i in range(15):
        opt.zero_grad()
        loss_at(i).backward()
        opt.step()
    with torch.no_grad():
        after = loss_at(123).item()
    assert after < 0.97 * before, (before, after)


# ------------------------------------------------------------------ online filtering
@pytest.mark.parametrize("name,y_update", [("acc", "evidence"), ("multi_l", "evidence"), ("multi_l", "direct")])
def test_filter_step_equals_batched_forward(name, y_update):
    torch.manual_seed(1)
    m = LatentFilter(name, **TINY, y_update=y_update).eval()
    batch = make_batch(N_CH[name], B=3, T=9)
    with torch.no_grad():
        ref = m(batch["obs"], batch["actions"], sample=False)
        state, prev = None, None
        for t in range(9):
            post, state = m.filter_step(batch["obs"][:, t], batch["actions"][:, t], prev, state)
            prev = batch["actions"][:, t]
            for k in ("z_mean", "z_var", "y_mean", "y_var"):
                torch.testing.assert_close(post[k], ref[k][:, t], rtol=1e-5, atol=1e-5)
    lat = m.infer_latents({"obs": batch["obs"], "actions": batch["actions"]})  # no object_id needed
    torch.testing.assert_close(lat["z_mean"], ref["z_mean"])
    assert set(lat) == {"z_mean", "z_var", "y_mean", "y_var"}


def test_evidence_y_posterior_is_the_product_of_its_evidence():
    """y_update='evidence': q(y_t) = N(0, 1/p0) x prod_k N(m_k, 1/lambda_k): the precision
    only grows, the mean is the precision-weighted mean of the evidence, and the floor holds."""
    from embodied_tactile.model.networks import YPosterior

    torch.manual_seed(0)
    yp = YPosterior(n_z=3, n_y=2, n_a=1, hidden=8, min_var=1e-3, update="evidence", prior_precision=2.0)
    state = yp.initial_state(4, torch.device("cpu"))
    lams, ms, variances = [], [], []
    for _ in range(6):
        z, a = torch.randn(4, 3), torch.randn(4, 1)
        h, _ = yp.cell(torch.cat([z, a], -1), (state[0], state[1]))
        m_k, raw = yp.head(h).chunk(2, -1)
        mean, var, state = yp(z, a, state)
        lams.append(torch.nn.functional.softplus(raw))
        ms.append(m_k)
        variances.append(var)
        lam, m = torch.stack(lams), torch.stack(ms)
        prec = 2.0 + lam.sum(0)
        torch.testing.assert_close(mean, (lam * m).sum(0) / prec, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(var, 1.0 / prec + 1e-3, rtol=1e-5, atol=1e-7)
    v = torch.stack(variances)
    assert (v[1:] <= v[:-1]).all() and (v > 1e-3).all()
    with pytest.raises(ValueError, match="y_update must be one of"):
        YPosterior(3, 2, 1, update="lstm")
    with pytest.raises(ValueError, match="y_prior_precision must be > 0"):
        YPosterior(3, 2, 1, prior_precision=0.0)


def test_bounded_evidence_caps_each_steps_precision():
    """y_evidence_max: lambda_k = max * sigmoid(raw_k), so P_t <= p0 + t * max even when the
    head asks for huge precision, and the latest frame's weight in the mean is at most
    max / P_t; the LatentFilter passes it through; the direct update ignores it."""
    from embodied_tactile.model.networks import YPosterior

    torch.manual_seed(0)
    yp = YPosterior(n_z=3, n_y=2, n_a=1, hidden=8, update="evidence", prior_precision=1.0, max_evidence=0.5)
    with torch.no_grad():
        yp.head.bias[2:] = 50.0  # softplus would give lambda = 50 per step
    state = yp.initial_state(4, torch.device("cpu"))
    for t in range(1, 8):
        _, var, state = yp(torch.randn(4, 3), torch.randn(4, 1), state)
        assert (state[2] <= 1.0 + 0.5 * t + 1e-5).all() and (state[2] >= 1.0 + 0.5 * t - 1e-3).all()
    assert YPosterior(3, 2, 1, update="direct", max_evidence=0.5).max_evidence is None  # direct ignores the bound
    with pytest.raises(ValueError, match="y_evidence_max=0.0 must be > 0"):
        YPosterior(3, 2, 1, update="evidence", max_evidence=0.0)
    net = LatentFilter("fsr_t", n_z=4, n_y=2, y_update="evidence", y_evidence_max=2.0)
    assert net.y_posterior.max_evidence == 2.0 and net.config()["y_evidence_max"] == 2.0


def test_evidence_range_bounds_how_far_one_step_moves_the_mean():
    """y_evidence_range r: evidence means r tanh(raw / r), so with the precision bound L one
    step moves the mean by at most L (r + |mean|) / P_t, however large the head's output."""
    from embodied_tactile.model.networks import YPosterior

    torch.manual_seed(0)
    yp = YPosterior(n_z=3, n_y=2, n_a=1, hidden=8, update="evidence", max_evidence=1.0, evidence_range=2.0)
    with torch.no_grad():
        yp.head.weight.mul_(1000.0)  # evidence means of order 1e3 before squashing
    state = yp.initial_state(16, torch.device("cpu"))
    mean_prev = torch.zeros(16, 2)
    for t in range(1, 10):
        mean, _, state = yp(torch.randn(16, 3), torch.randn(16, 1), state)
        assert ((mean - mean_prev).abs() <= 1.0 * (2.0 + mean_prev.abs()) / state[2] + 1e-5).all()
        assert (mean.abs() < 2.0).all()
        mean_prev = mean
    assert YPosterior(3, 2, 1, update="direct", evidence_range=1.0).evidence_range is None
    with pytest.raises(ValueError, match="y_evidence_range=-1.0 must be > 0"):
        YPosterior(3, 2, 1, update="evidence", evidence_range=-1.0)


def test_kl_matches_torch_distributions():
    torch.manual_seed(0)
    mq, mp = torch.randn(5, 7), torch.randn(5, 7)
    vq, vp = torch.rand(5, 7) + 0.05, torch.rand(5, 7) + 0.05
    ref = torch.distributions.kl_divergence(
        torch.distributions.Normal(mq.double(), vq.double().sqrt()),
        torch.distributions.Normal(mp.double(), vp.double().sqrt())).sum(-1)
    torch.testing.assert_close(kl_diag_gaussians(mq, vq, mp, vp).double(), ref, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("d", [1e-3, 1e-4, 1e-5])
def test_kl_precise_for_tiny_log_variance_difference(d):
    vp = torch.full((1, 16), 0.37)
    vq = vp * math.exp(d)
    m = torch.zeros(1, 16)
    got = kl_diag_gaussians(m, vq, m, vp).item()
    exact = 16 * 0.5 * (math.expm1(d) - d)  # float64
    assert got == pytest.approx(exact, rel=2e-2)
    d32 = torch.log(vq) - torch.log(vp)
    naive = (0.5 * (torch.exp(d32) - 1 - d32)).sum().item()
    if d <= 1e-4:  # the naive form is off by orders of magnitude here
        assert abs(naive - exact) > 10 * abs(got - exact)


def test_fusion_variance_form_equals_precision_form_and_survives_float16():
    torch.manual_seed(0)
    m1, m2 = torch.randn(100), torch.randn(100)
    v1, v2 = torch.rand(100) + 1e-2, torch.rand(100) + 1e-2
    mu, var = fuse_gaussians(m1, v1, m2, v2)
    p = 1 / v1.double() + 1 / v2.double()
    torch.testing.assert_close(var.double(), 1 / p, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(mu.double(), (m1.double() / v1.double() + m2.double() / v2.double()) / p,
                               rtol=1e-5, atol=1e-6)
    # float16: 1 / 1e-5 = 1e5 > 65504 overflows in the precision form
    h = lambda x: torch.tensor(x, dtype=torch.float16)  # noqa: E731
    a_m, a_v, b_m, b_v = h([0.5, 1.0]), h([1e-5, 2e-5]), h([-0.5, 2.0]), h([1e-5, 3e-5])
    prec = 1 / a_v + 1 / b_v
    assert not torch.isfinite(prec).all()
    mu, var = fuse_gaussians(a_m, a_v, b_m, b_v)
    assert mu.dtype == torch.float32 and torch.isfinite(mu).all() and torch.isfinite(var).all()
    av, bv = a_v.double(), b_v.double()
    torch.testing.assert_close(var.double(), av * bv / (av + bv), rtol=1e-4, atol=0)
    torch.testing.assert_close(mu.double(), (bv * a_m.double() + av * b_m.double()) / (av + bv), rtol=1e-4, atol=1e-6)


def test_bf16_autocast_keeps_probabilistic_parts_float32():
    torch.manual_seed(0)
    m = LatentFilter("multi_l", **TINY)
    batch = make_batch(3, B=2, T=4)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        t = m.elbo_terms(batch)
        loss = t["nll"] + t["kl_z"] + t["kl_y"]
    for k in ("z_mean", "z_var", "zp_var", "y_var", "enc_var"):
        assert t["out"][k].dtype == torch.float32, k
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in m.parameters() if p.grad is not None)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["zeros", "ones", "spikes", "T1", "T1000"])
def test_extreme_inputs_finite(case):
    torch.manual_seed(0)
    tiny = dict(encoder={"widths": [2, 2], "hidden": 8}, transition_hidden=8, lstm_hidden=8)
    name = "multi_l"
    B, T = (1, 1000) if case == "T1000" else (2, 1 if case == "T1" else 6)
    batch = make_batch(3, B=B, T=T)
    if case == "zeros":
        batch["obs"].zero_(), batch["actions"].zero_()
    elif case == "ones":
        batch["obs"].fill_(1.0), batch["actions"].fill_(1.0)
    elif case == "spikes":
        batch["obs"][:, ::2, :, 3:9, 5:7] = 1e4
        batch["actions"][:, 1] = 1e4
    m = LatentFilter(name, **tiny)
    t = m.elbo_terms(batch)
    loss = t["nll"] + t["kl_z"] + t["kl_y"] - 0.1 * t["entropy"]
    assert all(torch.isfinite(t[k]) for k in ("nll", "kl_z", "kl_y", "entropy")), t
    loss.backward()
    grads = [p.grad for p in m.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    if case == "T1":  # no y transition: kl_y is the population term alone
        assert t["kl_y"].item() == pytest.approx(t["pop"].item(), abs=0.0)


# ------------------------------------------------------------------ Lightning
def test_checkpoint_roundtrip(tmp_path):
    torch.manual_seed(0)
    batch = make_batch(3, B=4, T=5)
    module = LatentFilterModule(
        # eps above the reconstruction error at the default obs_sigma 0.1, so the KL switches on
        LatentFilter("multi_l", **TINY), annealing=ConstrainedAnnealing(eps=1e3, update_every=1),
        optimizer=functools.partial(torch.optim.Adam, lr=1e-3))
    tr = trainer(tmp_path, max_steps=3)
    dl = DataLoader(ListDataset(batch), batch_size=2)
    tr.fit(module, dl, dl)
    assert module.annealing.kl_on and module.annealing.last_update == 2
    path = tmp_path / "m.ckpt"
    tr.save_checkpoint(path)
    loaded = LatentFilterModule.load_from_checkpoint(path)  # torch.load weights_only default
    assert loaded.hparams["annealing"]["name"] == "constrained"
    assert loaded.hparams["optimizer"] == {"name": "Adam", "lr": 1e-3}
    assert isinstance(loaded.annealing, ConstrainedAnnealing)
    assert loaded.annealing.get_extra_state() == module.annealing.get_extra_state()
    a, b = module.infer_latents(batch), loaded.infer_latents(batch)
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)
    assert "train/loss" in tr.callback_metrics and "val/elbo" in tr.callback_metrics
    for k in ("train/nll", "train/kl_z", "train/kl_y", "val/loss"):
        assert k in tr.callback_metrics


def test_nonfinite_loss_raises_with_step_and_term(tmp_path):
    torch.manual_seed(0)
    batch = make_batch(1, B=2, T=4)
    module = LatentFilterModule(LatentFilter("acc", **TINY), optimizer=functools.partial(torch.optim.Adam, lr=1e-3))
    with torch.no_grad():
        module.model.prior.raw_var.fill_(float("nan"))
    tr = trainer(tmp_path, limit_val_batches=0)
    with pytest.raises(FloatingPointError, match=r"non-finite loss at step 0: kl_y=nan") as err:
        tr.fit(module, DataLoader(ListDataset(batch), batch_size=2))
    assert "train batch 0, finite inputs of batch row 0 (object_id " in str(err.value)


def test_nonfinite_loss_in_validation_raises_with_step_term_and_batch(tmp_path):
    torch.manual_seed(0)
    batch = make_batch(1, B=2, T=4)
    batch["trial"] = ["obj05_a", "obj09_b"]
    module = LatentFilterModule(LatentFilter("acc", **TINY))
    with torch.no_grad():
        module.model.prior.raw_var.fill_(float("nan"))
    with pytest.raises(FloatingPointError, match=r"non-finite loss at step 0: kl_y=nan") as err:
        trainer(tmp_path).validate(module, DataLoader(ListDataset(batch), batch_size=2), verbose=False)
    msg = str(err.value)
    assert "val batch 0" in msg and "trial 'obj05_a'" in msg and "trial 'obj09_b'" in msg


def test_nonfinite_input_names_trial_and_frame_in_training_and_validation(tmp_path):
    """A NaN / inf injected at known trials and frames: training_step and validation_step
    raise before the forward pass, naming those trials, fields and frames (in trial
    coordinates: a crop's first_frame is added), and no other trial."""
    torch.manual_seed(0)
    batch = make_batch(1, B=4, T=6)
    batch["trial"] = [f"obj{i:02d}_act00_rep0" for i in range(4)]
    batch["first_frame"] = torch.tensor([0, 0, 40, 0])
    batch["obs"][2, 3, 0, 5, 5] = float("nan")
    batch["actions"][3, 1, 2] = float("inf")
    batch["actions"][3, 4, 0] = float("nan")
    module = LatentFilterModule(LatentFilter("acc", **TINY), optimizer=functools.partial(torch.optim.Adam, lr=1e-3))
    before = {k: v.clone() for k, v in module.state_dict().items()}
    dl = DataLoader(ListDataset(batch), batch_size=4)
    runs = {"train": lambda: trainer(tmp_path, limit_val_batches=0).fit(module, dl),
            "val": lambda: trainer(tmp_path).validate(module, dl, verbose=False)}
    for stage, run in runs.items():
        with pytest.raises(FloatingPointError, match=rf"non-finite input at step 0 \({stage} batch 0\)") as err:
            run()
        msg = str(err.value)
        assert "trial 'obj02_act00_rep0' (object_id " in msg and "obs frame 43" in msg
        assert "trial 'obj03_act00_rep0'" in msg and "actions frames 1, 4" in msg
        assert "obj00" not in msg and "obj01" not in msg
    for k, v in module.state_dict().items():  # no step was taken
        torch.testing.assert_close(v, before[k], rtol=0, atol=0, equal_nan=True)


def test_hydra_instantiation_with_project_style_configs(tmp_path):
    """DictConfig modality (extra `label`, `pathways` mapping), `_target_` schedule and
    `_partial_` optimizer, as Hydra passes them; hparams stay checkpoint-safe."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    cfg = OmegaConf.create({
        "_target_": "embodied_tactile.model.module.LatentFilterModule",
        "net": {"_target_": "embodied_tactile.model.latent_filter.LatentFilter",
                "modality": {"name": "multi_l", "label": "MULTI-L", "channels": ["acc", "fsr_t", "fsr_b"],
                             "fusion": "late", "pathways": {"vibration": ["acc"], "force": ["fsr_t", "fsr_b"]}},
                "encoder": {"widths": [4, 8], "hidden": 32}, "transition_hidden": 32, "lstm_hidden": 32},
        "annealing": {"_target_": "embodied_tactile.model.annealing.DVBFAnnealing", "c0": 0.01, "T_A": 100},
        "optimizer": {"_target_": "torch.optim.Adam", "_partial_": True, "lr": 1e-5},
    })
    module = instantiate(cfg)
    assert set(module.model.observation.encoders) == {"vibration", "force"}
    assert module.hparams["annealing"] == {"name": "dvbf", "c0": 0.01, "T_A": 100.0, "fraction": None}
    assert module.hparams["optimizer"] == {"name": "Adam", "lr": 1e-5}
    assert type(module.hparams["net"]["modality"]) is dict and type(module.hparams["net"]["encoder"]) is dict
    assert module.hparams["net"]["modality"]["pathways"] == {"vibration": ["acc"], "force": ["fsr_t", "fsr_b"]}
    opt = module.configure_optimizers()
    assert isinstance(opt, torch.optim.Adam) and opt.defaults["lr"] == 1e-5


# ------------------------------------------------------------------ hierarchical prior
def test_hierarchical_prior_population_marginal_for_unseen_objects():
    from embodied_tactile.model.networks import HierarchicalPrior

    torch.manual_seed(0)
    p = HierarchicalPrior(n_y=3, n_a=2, n_objects=5, sigma_init=0.5, pop_sigma_init=0.4, var_floor=1e-2, labels=True)
    a = torch.zeros(2, 4, 2)
    p.train()
    p(torch.tensor([0, 2]), a)  # objects 0 and 2 met in training
    assert p.seen.tolist() == [True, False, True, False, False]
    p.eval()
    m, v = p(torch.tensor([2, 3]), a)
    # seen object: its own embedding and sigma^2; unseen: mu_0 and sigma^2 + tau^2
    torch.testing.assert_close(m[0, 0], p.embedding.weight[2].detach())
    torch.testing.assert_close(m[1, 0], p.pop_mean.detach())
    sigma2 = torch.nn.functional.softplus(p.raw_var.detach()) + 1e-2
    tau2 = torch.nn.functional.softplus(p.pop_raw_var.detach()) + 1e-2
    torch.testing.assert_close(v[0, 0], sigma2)
    torch.testing.assert_close(v[1, 0], sigma2 + tau2)
    torch.testing.assert_close(tau2, torch.full((3,), 0.16))
    m_new, v_new = p(torch.tensor([-1, -1]), a)  # id -1: a new object, in any mode
    torch.testing.assert_close(m_new[0, 0], p.pop_mean.detach())
    torch.testing.assert_close(v_new[0, 0], sigma2 + tau2)
    # the population term is -sum_{seen} log N(e_n; mu_0, tau^2)
    e = p.embedding.weight.detach()[[0, 2]]
    ref = -torch.distributions.Normal(p.pop_mean.detach(), tau2.sqrt()).log_prob(e).sum()
    torch.testing.assert_close(p.population_nll().detach(), ref)
    with pytest.raises(ValueError, match="object_id out of range"):
        p(torch.tensor([5]), a)


def test_prior_without_labels_gives_every_sequence_the_population_marginal():
    from embodied_tactile.model.networks import HierarchicalPrior

    torch.manual_seed(0)
    # learned codes, so that a gradient could reach them
    p = HierarchicalPrior(n_y=3, n_a=2, n_objects=5, sigma_init=0.5, pop_sigma_init=0.4, labels=False,
                          learn_embedding=True)
    a = torch.randn(2, 4, 2)
    p.train()
    m, v = p(torch.tensor([0, 2]), a)  # ids given in training are ignored
    assert not bool(p.seen.any())
    assert float(p.population_nll()) == 0.0
    m_new, v_new = p(torch.tensor([-1, -1]), a)
    torch.testing.assert_close(m, m_new)
    torch.testing.assert_close(v, v_new)
    torch.testing.assert_close(m[0, 0], p.pop_mean.detach())  # the action term starts at 0
    sigma2 = torch.nn.functional.softplus(p.raw_var.detach()) + 1e-2
    torch.testing.assert_close(v[1, 3], sigma2 + torch.full((3,), 0.16))
    m.sum().backward()
    assert float(p.embedding.weight.grad.abs().sum()) == 0.0  # no embedding row takes part


@pytest.mark.slow
def test_fixed_object_codes_stay_at_their_draws_while_the_rest_of_the_prior_learns(tmp_path):
    """prior.learn_embedding=False: training moves q(y), sigma, mu_0 and tau but never the
    object codes, which stay distinct draws of N(0, pop_sigma_init^2)."""
    torch.manual_seed(0)
    net = LatentFilter("fsr_t", prior={"labels": True, "learn_embedding": False, "learn_sigma": True, "pop_sigma_init": 0.5},
                       **TINY)
    codes = net.prior.embedding.weight.detach().clone()
    assert not net.prior.embedding.weight.requires_grad
    assert 0.3 < float(codes.std()) < 0.7  # the draws' spread is pop_sigma_init
    others = {k: v.detach().clone() for k, v in net.prior.named_parameters() if v.requires_grad}
    assert set(others) == {"pop_mean", "pop_raw_var", "raw_var", "action.weight"}
    module = LatentFilterModule(net, optimizer={"name": "Adam", "lr": 1e-2})
    data = ListDataset(make_batch(1, B=8, T=6))
    trainer(tmp_path, max_steps=4).fit(module, DataLoader(data, batch_size=4))
    torch.testing.assert_close(net.prior.embedding.weight.detach(), codes, rtol=0, atol=0)
    moved = [k for k, v in net.prior.named_parameters() if v.requires_grad and not torch.equal(v.detach(), others[k])]
    assert {"pop_mean", "pop_raw_var", "raw_var"} <= set(moved)
    # learned codes (learn_embedding=True) do move under the same training
    torch.manual_seed(0)
    learned = LatentFilter("fsr_t", prior={"labels": True, "learn_embedding": True}, **TINY)
    before = learned.prior.embedding.weight.detach().clone()
    trainer(tmp_path, max_steps=4).fit(LatentFilterModule(learned, optimizer={"name": "Adam", "lr": 1e-2}),
                                       DataLoader(data, batch_size=4))
    assert not torch.equal(learned.prior.embedding.weight.detach(), before)


def test_cosine_lr_schedule_falls_to_zero_over_the_runs_steps(tmp_path):
    torch.manual_seed(0)
    lrs = []

    class Record(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            lrs.append(trainer.optimizers[0].param_groups[0]["lr"])

    module = LatentFilterModule(LatentFilter("fsr_t", **TINY), optimizer={"name": "Adam", "lr": 1e-2},
                                     lr_schedule="cosine")
    data = DataLoader(ListDataset(make_batch(1, B=8, T=4)), batch_size=2)  # 4 steps per epoch
    trainer(tmp_path, max_steps=-1, max_epochs=2, callbacks=[Record()]).fit(module, data)
    expected = [0.5e-2 * (1 + math.cos(math.pi * i / 8)) for i in range(8)]
    assert lrs == pytest.approx(expected, rel=1e-6)
    assert module.hparams["lr_schedule"] == "cosine"
    constant = LatentFilterModule(LatentFilter("fsr_t", **TINY), optimizer={"name": "Adam", "lr": 1e-2})
    lrs.clear()
    trainer(tmp_path, max_steps=3, callbacks=[Record()]).fit(constant, data)
    assert lrs == [1e-2] * 3
    with pytest.raises(ValueError, match="lr_schedule must be one of"):
        LatentFilterModule(LatentFilter("fsr_t", **TINY), lr_schedule="step")


def test_code_lr_scale_puts_the_object_codes_in_a_group_of_their_own():
    """code_lr_scale != 1: two parameter groups, the prior's codes alone at scale x lr (the
    cosine schedule scales both); 1: one group; <= 0 refused."""
    net = LatentFilter("fsr_t", **TINY)
    module = LatentFilterModule(net, optimizer={"name": "Adam", "lr": 1e-2}, code_lr_scale=10.0)
    opt = module.configure_optimizers()
    assert [g["lr"] for g in opt.param_groups] == pytest.approx([1e-2, 1e-1])
    assert opt.param_groups[1]["params"] == [net.prior.embedding.weight]
    n_params = sum(1 for _ in module.parameters())
    assert len(opt.param_groups[0]["params"]) == n_params - 1
    assert module.hparams["code_lr_scale"] == 10.0
    one = LatentFilterModule(LatentFilter("fsr_t", **TINY), optimizer={"name": "Adam", "lr": 1e-2})
    assert len(one.configure_optimizers().param_groups) == 1
    with pytest.raises(ValueError, match="code_lr_scale must be > 0"):
        LatentFilterModule(LatentFilter("fsr_t", **TINY), code_lr_scale=0.0)


def test_population_term_enters_kl_y_and_old_checkpoints_load():
    from embodied_tactile.model.networks import HierarchicalPrior

    torch.manual_seed(0)
    m = LatentFilter("fsr_t", prior={"labels": True}, **{**TINY, "obs_dropout": 0.0})  # the same frames in both calls
    batch = make_batch(1)
    m.prior.population_weight = 0.0
    t0 = m.elbo_terms(batch, sample=False)
    m.prior.population_weight = 0.5
    t1 = m.elbo_terms(batch, sample=False)
    assert float(t1["pop"]) > 0  # embeddings far from mu_0 relative to tau cost density
    torch.testing.assert_close(t1["kl_y"] - t0["kl_y"], t1["pop"])
    # a state dict from before the population level loads, every object counted as seen
    p = HierarchicalPrior(n_y=3, n_a=2, n_objects=4)
    old = {k: v for k, v in p.state_dict().items() if k not in ("seen", "pop_mean", "pop_raw_var")}
    q = HierarchicalPrior(n_y=3, n_a=2, n_objects=4)
    q.load_state_dict(old)
    assert bool(q.seen.all())


@pytest.mark.parametrize("name", ["fsr_tb", "multi_l"])
def test_checkpoint_of_the_pre_fusion_module_layout_loads(name, tmp_path):
    """Weights saved as model.encoders.<pathway>.* (before models/fusion.py) load into the
    current layout unchanged; an unknown layout still fails."""
    import lightning as L

    net = LatentFilter(name, **TINY)
    module = LatentFilterModule(net)
    late = net.modality["fusion"] == "late"

    def old_key(k: str) -> str:
        for part in ("encoder", "decoder"):
            if late and k.startswith(f"model.observation.{part}s."):
                return k.replace(f"model.observation.{part}s.", f"model.{part}s.")
            if not late and k.startswith(f"model.observation.{part}."):
                return k.replace(f"model.observation.{part}.", f"model.{part}s.main.")
        return k

    state = {old_key(k): v for k, v in module.state_dict().items()}
    assert any(k.startswith("model.encoders.") for k in state) and not any("observation" in k for k in state)
    ckpt = tmp_path / "old.ckpt"
    torch.save({"state_dict": state, "hyper_parameters": dict(module.hparams),
                "pytorch-lightning_version": L.__version__}, ckpt)
    loaded = LatentFilterModule.load_from_checkpoint(str(ckpt), map_location="cpu")
    for k, v in module.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k
    torch.save({"state_dict": {k.replace("model.observation.", "model.other."): v for k, v in module.state_dict().items()},
                "hyper_parameters": dict(module.hparams), "pytorch-lightning_version": L.__version__}, ckpt)
    with pytest.raises(RuntimeError, match="state_dict"):
        LatentFilterModule.load_from_checkpoint(str(ckpt), map_location="cpu")


# ------------------------------------------------------------------ input standardisation
def test_standardised_encoder_does_not_see_the_channels_offset_and_scale():
    """input_standardize: shifting and scaling a channel's data together with its stats
    leaves the latents unchanged, so a small signal on a large offset (the acc image at
    pressing, docs/experiments/modality_bounds.md) reaches the encoder at unit scale."""
    torch.manual_seed(0)
    batch = make_batch(3, B=2, T=5)
    net = LatentFilter("multi_l", **{**TINY, "input_standardize": True}).eval()
    with pytest.raises(ValueError, match="one value per channel"):
        net.set_input_stats([0.5], [0.1])
    with pytest.raises(ValueError, match="std > 0"):
        net.set_input_stats([0.5, 0.2, 0.1], [0.1, 0.0, 0.2])
    assert not bool(net.input_stats_set)
    ref = net.infer_latents(batch)  # stats unset: shift 0, scale 1
    shift, scale = torch.tensor([0.5, -2.0, 3.0]), torch.tensor([0.04, 10.0, 1.0])
    net.set_input_stats(shift, scale)
    moved = {**batch, "obs": batch["obs"] * scale.view(1, 1, 3, 1, 1) + shift.view(1, 1, 3, 1, 1)}
    out = net.infer_latents(moved)
    for k in ref:
        torch.testing.assert_close(out[k], ref[k], rtol=1e-4, atol=1e-5)
    plain = LatentFilter("multi_l", **TINY)
    assert not hasattr(plain, "input_shift") and "input_shift" not in plain.state_dict()
    with pytest.raises(ValueError, match="input_standardize=True"):
        plain.set_input_stats([0.0] * 3, [1.0] * 3)


def test_fit_sets_the_input_stats_from_the_training_set_and_checkpoints_carry_them(tmp_path):
    """The DataModule computes its training split's statistics in setup("fit");
    HandOverStatistics hands them to the module; without them a standardising network
    refuses to fit; checkpoints carry them."""
    from embodied_tactile.data.statistics import DataStatistics
    from embodied_tactile.run.handover import HandOverStatistics

    torch.manual_seed(0)
    batch = make_batch(1, B=4, T=6)
    batch["obs"] = 0.5 + 0.03 * batch["obs"]  # the acc image's scale: a small spread on a large offset

    class DM(L.LightningDataModule):
        def __init__(self):
            super().__init__()
            self.train_set = ListDataset(batch)
            self.statistics = None

        def setup(self, stage=None):
            if stage == "fit":
                self.statistics = DataStatistics.of(self.train_eval_dataloader(), len(self.train_set))

        def train_dataloader(self):
            return DataLoader(self.train_set, batch_size=2, shuffle=True)

        def train_eval_dataloader(self):
            return DataLoader(self.train_set, batch_size=3)

        def val_dataloader(self):
            return DataLoader(self.train_set, batch_size=2)

    module = LatentFilterModule(LatentFilter("acc", **{**TINY, "input_standardize": True}),
                                optimizer=functools.partial(torch.optim.Adam, lr=1e-3))
    with pytest.raises(ValueError, match="channel statistics"):
        trainer(tmp_path, max_steps=2).fit(module, datamodule=DM())
    tr = trainer(tmp_path, max_steps=2, callbacks=[HandOverStatistics()])
    tr.fit(module, datamodule=DM())
    net = module.model
    assert bool(net.input_stats_set) and net.prior.population_weight == 1 / 4
    o = batch["obs"].double()
    torch.testing.assert_close(net.input_shift, o.mean().float().view(1), rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(net.input_scale, o.std(unbiased=False).float().view(1), rtol=1e-5, atol=1e-7)
    path = tmp_path / "m.ckpt"
    tr.save_checkpoint(path)
    loaded = LatentFilterModule.load_from_checkpoint(path)
    assert loaded.model.input_standardize and bool(loaded.model.input_stats_set)
    torch.testing.assert_close(loaded.model.input_scale, net.input_scale, rtol=0, atol=0)
    a, b = module.infer_latents(batch), loaded.infer_latents(batch)
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)



def test_saved_configs_with_removed_options_load_when_off_and_are_named_when_on():
    """A checkpoint's net config from before the removal of measured-and-rejected options
    (REMOVED_OPTIONS) rebuilds the same network when they were off; one that used an option
    is refused with the option named, never silently rebuilt as another model."""
    from embodied_tactile.model.compat import REMOVED_OPTIONS

    torch.manual_seed(0)
    net = LatentFilter("fsr_t", **TINY)
    old = {**net.config(), **{k: v for k, v in REMOVED_OPTIONS.items() if v is not None}, "overshoot_weight": 1.0}
    torch.manual_seed(0)
    rebuilt = LatentFilter.from_config(old)
    assert rebuilt.config() == net.config()
    assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), rebuilt.state_dict().values()))
    with pytest.raises(ValueError, match="elbo_samples=4"):
        LatentFilter.from_config({**old, "elbo_samples": 4})
    legacy = {k: v for k, v in net.config().items() if k != "input_standardize"}
    assert LatentFilter.from_config(legacy).input_standardize is False  # trained before the option existed
    # a config that names none of the options whose default changed was trained at their old values
    older = {k: v for k, v in net.config().items()
             if k not in ("y_update", "y_evidence_max", "y_evidence_range", "obs_dropout")}
    older["prior"] = {k: v for k, v in older["prior"].items() if k != "labels"}
    cfg = LatentFilter.from_config(older).config()
    assert (cfg["y_update"], cfg["y_evidence_max"], cfg["obs_dropout"], cfg["prior"]["labels"]) == ("direct", None, 0.0, True)
    assert LatentFilter("fsr_t").config()["prior"]["labels"] is False and LatentFilter("fsr_t").obs_dropout == 0.5
    with pytest.raises(ValueError, match="unknown Latent Filter options \\['overshoot'\\]"):
        LatentFilter("fsr_t", overshoot=2)


def test_benchmark_reference_loss_equals_the_vectorised_elbo_terms():
    """benchmarks/steps.py's naive_terms (encoder and decoder per time step, the speed
    benchmarks' reference) gives LatentFilter.elbo_terms' terms; its kl_y leaves out the
    population term."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("steps", Path(__file__).parents[2] / "benchmarks" / "steps.py")
    steps = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(steps)
    bench_batch, naive_terms = steps.make_batch, steps.naive_terms

    torch.manual_seed(0)
    m = LatentFilter("multi_l", **TINY).eval()
    batch = bench_batch(3, B=2, T=5)
    assert batch["obs"].shape == (2, 5, 3, 28, 28) and batch["object_id"].max() < 32
    with torch.no_grad():
        ref = m.elbo_terms(batch, sample=False)
        got = naive_terms(m, batch, sample=False)
    for k in ("nll", "kl_z", "entropy"):
        torch.testing.assert_close(got[k], ref[k], rtol=1e-4, atol=1e-3, msg=k)
    torch.testing.assert_close(got["kl_y"], ref["kl_y"] - ref["pop"], rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("old, new", [
    ("embodied_tactile.models.module.EarlyFusionLatentFilter", "embodied_tactile.model.module.LatentFilterModule"),
    ("embodied_tactile.models.module.LateFusionLatentFilter", "embodied_tactile.model.module.LatentFilterModule"),
    ("embodied_tactile.models.latent_filter.LatentFilter", "embodied_tactile.model.latent_filter.LatentFilter"),
    ("embodied_tactile.models.annealing.LinearKLWarmup", "embodied_tactile.model.annealing.LinearKLWarmup"),
    ("embodied_tactile.runtime.ResumableCSVLogger", "embodied_tactile.run.resume.ResumableCSVLogger"),
    ("embodied_tactile.run.runtime.ResumableCSVLogger", "embodied_tactile.run.resume.ResumableCSVLogger"),
])
def test_saved_configs_of_the_earlier_layout_name_todays_classes(old, new):
    """The ``_target_`` strings of a ``config_resolved.yaml`` written before the package was
    ordered by role resolve to today's classes (the same objects, so checkpoints load)."""
    from hydra.utils import get_class

    assert get_class(old) is get_class(new)


def test_saved_targets_compare_in_todays_spelling():
    from embodied_tactile.model.compat import current_target

    assert current_target("embodied_tactile.models.module.EarlyFusionLatentFilter") == \
        "embodied_tactile.model.module.LatentFilterModule"
    assert current_target("embodied_tactile.models.annealing.LinearKLWarmup") == "embodied_tactile.model.annealing.LinearKLWarmup"
    assert current_target("embodied_tactile.runtime.ResumableCSVLogger") == "embodied_tactile.run.resume.ResumableCSVLogger"
    assert current_target("embodied_tactile.run.runtime.ResumableCSVLogger") == "embodied_tactile.run.resume.ResumableCSVLogger"
    # the DataModule is built from a data config's flat keys by from_config (its constructor takes groups)
    assert current_target("embodied_tactile.data.datamodule.TactileDataModule") == \
        "embodied_tactile.data.datamodule.TactileDataModule.from_config"
    assert current_target("torch.optim.Adam") == "torch.optim.Adam"


# ------------------------------------------------------------------ weight averaging
class _SeedEachStep(L.Callback):
    """The step's draws from its step number: a resumed fit draws what an unbroken one does."""

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        torch.manual_seed(trainer.global_step)


def _averaged_fit(tmp_path, name, max_steps, ckpt_path=None, decay=0.5):
    torch.manual_seed(0)
    module = LatentFilterModule(LatentFilter("acc", **TINY), optimizer={"name": "Adam", "lr": 1e-2},
                                weight_average=decay)
    loader = DataLoader(ListDataset(make_batch(1, B=4, T=6)), batch_size=2)
    ckpt = L.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path / name, save_last=True, every_n_train_steps=1)
    trainer(tmp_path / name, max_steps=max_steps, enable_checkpointing=True, callbacks=[_SeedEachStep(), ckpt],
            limit_val_batches=0).fit(module, loader, ckpt_path=ckpt_path)
    return module, tmp_path / name / "last.ckpt"


def test_weight_average_follows_its_recursion_and_becomes_the_runs_weights(tmp_path):
    """The average after each optimiser step is lerp(average, weights, 1 - d_n),
    d_n = min(decay, (1 + n) / (10 + n)), from a copy of the initial weights; after fit the
    network holds it, the validation loop in fit reads it, and the checkpoint's state_dict
    holds it too, the optimiser's weights beside it under ``weight_average``."""
    torch.manual_seed(0)
    module = LatentFilterModule(LatentFilter("acc", **TINY), optimizer={"name": "Adam", "lr": 1e-2},
                                weight_average=0.5)
    seen, validated = [], []  # the optimiser's weights after each step; the weights validation reads

    class Record(L.Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            seen.append({k: p.detach().clone() for k, p in pl_module.named_parameters()})

        def on_validation_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0):
            validated.append({k: p.detach().clone() for k, p in pl_module.named_parameters()})

    initial = {k: p.detach().clone() for k, p in module.named_parameters()}
    ckpt = L.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path / "c", save_last=True, every_n_train_steps=3)
    data = DataLoader(ListDataset(make_batch(1, B=6, T=6)), batch_size=2)
    trainer(tmp_path, max_steps=3, enable_checkpointing=True, callbacks=[Record(), ckpt],
            limit_val_batches=1).fit(module, data, data)
    expected = {k: v.clone() for k, v in initial.items()}
    for n, w in enumerate(seen, start=1):
        d = min(0.5, (1 + n) / (10 + n))
        expected = {k: d * expected[k] + (1 - d) * w[k] for k in expected}
    for k, p in module.named_parameters():
        assert torch.allclose(p, expected[k], atol=1e-6), k
    assert any(not torch.equal(seen[-1][k], expected[k]) for k in expected)  # the average is not the last step
    assert len(validated) == 1  # the epoch's validation, after the third step: the average
    for k in expected:
        assert torch.allclose(validated[0][k], expected[k], atol=1e-6), k
    saved = torch.load(tmp_path / "c" / "last.ckpt", weights_only=False)
    for k in expected:
        assert torch.allclose(saved["state_dict"][k], expected[k], atol=1e-6), k
        assert torch.equal(saved["weight_average"]["weights"][k], seen[-1][k]), k
    assert saved["weight_average"]["updates"] == 3
    loaded = LatentFilterModule.load_from_checkpoint(tmp_path / "c" / "last.ckpt")
    assert loaded.hparams["weight_average"] == 0.5
    for k, p in loaded.named_parameters():
        assert torch.allclose(p, expected[k], atol=1e-6), k


@pytest.mark.slow
def test_a_resumed_weight_averaged_fit_continues_both_the_weights_and_their_average(tmp_path):
    """Four steps in one fit equal two steps, a checkpoint and two more resumed from it:
    the optimiser's weights and the average both continue (the checkpoint's state_dict holds
    the average; the resumed fit puts the optimiser's weights back)."""
    whole, _ = _averaged_fit(tmp_path, "whole", 4)
    _, ckpt = _averaged_fit(tmp_path, "half", 2)
    resumed, _ = _averaged_fit(tmp_path, "resumed", 4, ckpt_path=ckpt)
    assert resumed.average.tensors is None and resumed.average.updates == 4
    for (k, a), b in zip(whole.named_parameters(), resumed.parameters()):
        assert torch.allclose(a, b, atol=1e-6), k


def test_averaged_weights_is_a_noop_without_averaging_and_swaps_back():
    module = LatentFilterModule(LatentFilter("acc", **TINY))
    before = [p.detach().clone() for p in module.parameters()]
    with module.averaged_weights():
        assert all(torch.equal(a, p) for a, p in zip(before, module.parameters()))
    averaged = LatentFilterModule(LatentFilter("acc", **TINY), weight_average=0.9)
    averaged.average.start(averaged)
    for t in averaged.average.tensors.values():
        t.add_(1.0)
    own = [p.detach().clone() for p in averaged.parameters()]
    with averaged.averaged_weights():
        assert all(torch.equal(a + 1.0, p) for a, p in zip(own, averaged.parameters()))
    assert all(torch.equal(a, p) for a, p in zip(own, averaged.parameters()))
    with pytest.raises(ValueError, match="weight_average must be a decay in"):
        LatentFilterModule(LatentFilter("acc", **TINY), weight_average=1.0)


def test_checkpoint_without_weight_average_loads_unaveraged(tmp_path):
    """A checkpoint written before ``weight_average`` existed was trained without an average:
    it loads without one (compat.UNSAVED_MODULE_OPTIONS), not with today's default 0.99, and
    its weights unchanged."""
    import lightning

    module = LatentFilterModule(LatentFilter("acc", **TINY), weight_average=None)
    hparams = {k: v for k, v in module.hparams.items() if k != "weight_average"}
    path = tmp_path / "old.ckpt"
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": hparams,
                "pytorch-lightning_version": lightning.__version__}, path)
    assert LatentFilterModule(LatentFilter("acc", **TINY)).average is not None  # today's default averages
    loaded = LatentFilterModule.load_from_checkpoint(str(path), map_location="cpu")
    assert loaded.average is None and loaded.hparams["weight_average"] is None
    for (k, a), b in zip(module.state_dict().items(), loaded.state_dict().values()):
        assert torch.equal(a, b), k
