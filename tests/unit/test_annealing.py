"""Annealing schedules: each produces its documented loss on known inputs."""

import math

import pytest
import torch

from embodied_tactile.model.annealing import (
    ConstrainedAnnealing,
    DVBFAnnealing,
    GeometricKLWeights,
    LinearKLWarmup,
    NoAnnealing,
    build_schedule,
    check_finite,
)

torch.set_num_threads(1)


def terms(nll=100.0, kl_z=10.0, kl_y=4.0, entropy=7.0, n_dims=50.0):
    t = dict(nll=nll, kl_z=kl_z, kl_y=kl_y, entropy=entropy, n_dims=n_dims)
    return {k: torch.tensor(float(v)) for k, v in t.items()}


def test_none():
    loss, logs = NoAnnealing()(123, terms())
    assert loss.item() == pytest.approx(114.0)
    assert logs == {}


@pytest.mark.parametrize("step,c", [(0, 0.01), (500, 0.01 + 500 / 1000), (10_000, 1.0)])
def test_dvbf(step, c):
    s = DVBFAnnealing(c0=0.01, T_A=1000)
    loss, logs = s(step, terms())
    assert logs["anneal/c"] == pytest.approx(c)
    assert loss.item() == pytest.approx(c * (100 + 10 + 4) - (1 - c) * 7.0, rel=1e-6)


def test_dvbf_equals_tempered_elbo_identity():
    # c (NLL + KL) - (1 - c) H  ==  c NLL - c E[log p] - H   with KL = -H - E[log p]
    c, nll, H, logp = 0.3, 50.0, 4.0, -9.0
    kl = -H - logp
    loss, _ = DVBFAnnealing(c0=c, T_A=1e9)(0, terms(nll=nll, kl_z=kl, kl_y=0.0, entropy=H))
    assert loss.item() == pytest.approx(c * nll - c * logp - H, rel=1e-6)


def test_linear():
    s = LinearKLWarmup(beta0=0.2, n_steps=100)
    for step, beta in [(0, 0.2), (50, 0.6), (100, 1.0), (1000, 1.0)]:
        loss, logs = s(step, terms())
        assert logs["anneal/beta"] == pytest.approx(beta)
        assert loss.item() == pytest.approx(100 + beta * 14.0, rel=1e-6)


def test_linear_y_weight_scales_only_the_prior_term():
    s = LinearKLWarmup(beta0=0.5, n_steps=10, y_weight=10.0)
    loss, logs = s(0, terms())
    assert loss.item() == pytest.approx(100 + 0.5 * (10.0 + 10.0 * 4.0), rel=1e-6)
    assert s.config()["y_weight"] == 10.0
    with pytest.raises(ValueError, match="y_weight > 0"):
        LinearKLWarmup(y_weight=0.0)


def test_geometric():
    s = GeometricKLWeights(z_start=100, z_end=200, y_start=1, y_end=20, n_steps=10)
    loss, logs = s(5, terms())
    wz, wy = 100 * 2 ** 0.5, 20 ** 0.5
    assert logs["anneal/w_z"] == pytest.approx(wz)
    assert logs["anneal/w_y"] == pytest.approx(wy)
    assert loss.item() == pytest.approx(100 + wz * 10 + wy * 4, rel=1e-6)
    assert s.weights(0) == pytest.approx((100, 1))
    assert s.weights(10) == pytest.approx((200, 20))
    assert s.weights(99) == pytest.approx((200, 20))


def test_constrained_phases_and_lambda_rule():
    s = ConstrainedAnnealing(eps=1.5, update_every=100)
    s.train()
    # r = nll / D = 2 > eps: no KL, C starts at r, lambda frozen
    loss, logs = s(0, terms(nll=100.0, n_dims=50.0))
    assert loss.item() == pytest.approx(2.0)
    assert logs["anneal/kl_on"] == 0.0 and s.c_ma == pytest.approx(2.0) and s.lambda_ == 1.0
    # r = 1: C = 0.99*2 + 0.01*1 = 1.99 > eps, still off
    loss, _ = s(1, terms(nll=50.0))
    assert loss.item() == pytest.approx(1.0) and s.c_ma == pytest.approx(1.99)
    # drive C below eps
    s.c_ma = 1.4
    loss, logs = s(100, terms(nll=50.0))  # C = 0.99*1.4 + 0.01 = 1.396 < 1.5: KL on
    assert s.kl_on and logs["anneal/kl_on"] == 1.0
    assert loss.item() == pytest.approx(1.0 + 14.0 / 1.0)  # loss uses lambda before update
    # update at step 100: delta < 0, lambda == 1 -> f = tanh(0) = 0 -> factor 1
    assert s.lambda_ == pytest.approx(1.0) and s.last_update == 100
    # constraint violated: delta > 0 -> f = -1 -> lambda *= clip(exp(nu*delta), .9, 1.05)
    s.c_ma = 1.52 / 0.99  # next C = 1.52 + 0.01 * 1 = 1.53
    s(200, terms(nll=50.0))
    delta = 1.53 - 1.5
    assert s.lambda_ == pytest.approx(min(math.exp(delta), 1.05))
    lam = s.lambda_
    s(201, terms(nll=50.0))  # not an update step
    assert s.lambda_ == lam
    # satisfied with lambda > 1: f = tanh(tau (1/lam - 1)) < 0 -> lambda shrinks
    s.c_ma = 0.5
    s(300, terms(nll=50.0))
    c = 0.99 * 0.5 + 0.01
    f = math.tanh(100 * (1 / lam - 1))
    assert s.lambda_ == pytest.approx(lam * min(max(math.exp(-f * (c - 1.5)), 0.9), 1.05))
    assert s.lambda_ < lam
    loss, _ = s(301, terms(nll=50.0))
    assert loss.item() == pytest.approx(1.0 + 14.0 / s.lambda_, rel=1e-6)


def test_constrained_eval_does_not_change_state_and_state_dict_roundtrip():
    s = ConstrainedAnnealing(eps=10.0)
    s.train()
    for i in range(3):
        s(i * 100, terms())
    sd = s.state_dict()
    s.eval()
    before = s.get_extra_state()
    s(1000, terms(nll=1.0))
    assert s.get_extra_state() == before
    s2 = ConstrainedAnnealing(eps=10.0)
    s2.load_state_dict(sd)
    assert s2.get_extra_state() == before
    # loadable under weights_only (plain python values)
    import io

    buf = io.BytesIO()
    torch.save(sd, buf)
    buf.seek(0)
    assert torch.load(buf, weights_only=True)["_extra_state"] == before


def test_build_schedule_roundtrip():
    for s in [NoAnnealing(), DVBFAnnealing(0.1, 50), LinearKLWarmup(0.0, 7),
              GeometricKLWeights(n_steps=3), ConstrainedAnnealing(eps=0.3, tau=10)]:
        s2 = build_schedule(s.config())
        assert type(s2) is type(s) and s2.config() == s.config()
    assert isinstance(build_schedule(None), NoAnnealing)
    with pytest.raises(ValueError, match="unknown annealing"):
        build_schedule({"name": "cosine"})


def test_check_finite_names_step_and_term():
    t = terms()
    t["kl_y"] = torch.tensor(float("nan"))
    with pytest.raises(FloatingPointError, match=r"non-finite loss at step 17: kl_y=nan"):
        check_finite(17, t)
    check_finite(3, terms(), torch.tensor(1.0))


# ------------------------------------------------------------------ lengths that fit the run
def _full_weight(s, step):
    """Whether a schedule weighs every term fully at ``step``."""
    if isinstance(s, DVBFAnnealing):
        return s.weight(step) == 1.0
    if isinstance(s, LinearKLWarmup):
        return s.weight(step) == 1.0
    if isinstance(s, GeometricKLWeights):
        return s.weights(step) == pytest.approx((s.z_end, s.y_end))
    return isinstance(s, NoAnnealing)


def test_fraction_resolves_against_the_run_and_needs_resolving_in_training():
    s = LinearKLWarmup(beta0=0.0, fraction=0.25)
    s.train()
    with pytest.raises(RuntimeError, match="set_total_steps"):
        s(0, terms())
    s.set_total_steps(400)
    assert s.n_steps == 100 and s.weight(50) == pytest.approx(0.5) and s.weight(100) == 1.0
    s.eval()
    fresh = LinearKLWarmup(fraction=0.25).eval()  # a loaded model outside fit: schedule finished
    assert fresh.weight(0) == 1.0
    with pytest.raises(ValueError, match="exactly one of n_steps"):
        LinearKLWarmup(n_steps=10, fraction=0.1)
    with pytest.raises(ValueError, match="fraction must be in"):
        DVBFAnnealing(fraction=1.5)
    with pytest.raises(ValueError, match="finite number of optimiser steps"):
        DVBFAnnealing(fraction=0.5).set_total_steps(float("inf"))
    # absolute lengths stay available and ignore the run's length
    a = DVBFAnnealing(c0=0.0, T_A=1000)
    a.set_total_steps(10)
    assert a.weight(500) == pytest.approx(0.5)
    assert build_schedule(s.config()).config() == s.config()


def _configured(annealing, experiment):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.utils import instantiate

    from conftest import REPO

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"annealing={annealing}", *([f"experiment={experiment}"] if experiment else [])])
    return instantiate(cfg.annealing.schedule), cfg


@pytest.mark.slow
@pytest.mark.parametrize("experiment", [None, "paper"])  # None: the typed defaults
@pytest.mark.parametrize("annealing", ["none", "linear", "dvbf", "geometric", "constrained"])
def test_every_annealing_reaches_full_weight_before_training_ends(annealing, experiment):
    s, cfg = _configured(annealing, experiment)
    if annealing == "constrained":  # adaptive: the KL switches on when the reconstruction constraint is met
        assert not s.has_length
        return
    s.train()
    # the experiment's own optimiser steps (32 objects x its actions, 25 % test, 12.5 % validation)
    n_trials = 32 * len(cfg.data.actions or range(16))
    n_train = n_trials - n_trials // 4 - round(0.125 * n_trials)
    windows = cfg.data.windows_per_epoch or n_train * int(cfg.data.windows_per_trial)
    per_epoch = -(-int(windows) // int(cfg.data.batch_size))
    for total in (per_epoch * int(cfg.trainer.max_epochs), 2, 7):
        s.set_total_steps(total)
        assert _full_weight(s, total - 1), (annealing, experiment, total)
