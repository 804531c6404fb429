"""Pendulum benchmark: the generator's physics, the Latent Filter's observation
mask / open-loop prediction, and a short training run with its read-outs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embodied_tactile.data.pendulum import (DAMPINGS, DT, N_OBJECTS, angle_precision, generate, integrate,
                                             least_squares_parameters, object_params, parameter_separation, render)


def _energy(theta, omega, w0):
    return 0.5 * omega ** 2 + np.asarray(w0)[:, None] ** 2 * (1.0 - np.cos(theta))


def test_generator_shapes_objects_and_determinism():
    a = generate(2, seed=3, n_steps=12)
    assert a.obs.shape == (2 * N_OBJECTS, 12, 1, 28, 28) and a.obs.dtype == np.float32
    assert a.actions.shape == (2 * N_OBJECTS, 12, 1) and a.theta.shape == a.omega.shape == (2 * N_OBJECTS, 12)
    assert sorted(set(zip(a.w0.tolist(), a.damping.tolist()))) == sorted(object_params(i) for i in range(N_OBJECTS))
    assert [object_params(i) for i in a.object_id] == list(zip(a.w0, a.damping))
    # piecewise-constant actions: a new value every 5 frames
    assert np.all(a.actions[:, 0:5] == a.actions[:, :1]) and not np.all(a.actions[:, 5] == a.actions[:, 0])
    b, c = generate(2, seed=3, n_steps=12), generate(2, seed=4, n_steps=12)
    assert np.array_equal(a.obs, b.obs) and np.array_equal(a.theta, b.theta)
    assert not np.array_equal(a.theta, c.theta)
    with pytest.raises(ValueError, match="object_id must be in"):
        object_params(N_OBJECTS)


def test_unseen_systems_lie_between_the_training_grid_and_have_no_object_id():
    from embodied_tactile.data.pendulum import DAMPINGS, FREQUENCIES, UNSEEN_SYSTEMS

    u = generate(3, seed=5, n_steps=12, systems=UNSEEN_SYSTEMS)
    assert len(u) == 3 * len(UNSEEN_SYSTEMS) and np.all(u.object_id == -1)
    assert sorted(set(zip(u.w0.tolist(), u.damping.tolist()))) == sorted(UNSEEN_SYSTEMS)
    grid = {(w, d) for w in FREQUENCIES for d in DAMPINGS}
    assert not grid & set(UNSEEN_SYSTEMS)
    assert min(FREQUENCIES) < u.w0.min() and u.w0.max() < max(FREQUENCIES)
    assert min(DAMPINGS) < u.damping.min() and u.damping.max() < max(DAMPINGS)
    with pytest.raises(ValueError, match="systems must be"):
        generate(1, seed=0, systems=[(0.0, 0.1)])


def test_energy_is_conserved_undamped_and_decays_with_damping():
    n, t_len = 6, 60
    rng = np.random.default_rng(0)
    th0, om0 = rng.uniform(-2.5, 2.5, n), rng.uniform(-2, 2, n)
    w0 = np.full(n, 4.0)
    u = np.zeros((n, t_len))
    th, om = integrate(th0, om0, w0, np.zeros(n), u)
    e = _energy(th, om, w0)
    assert np.abs(e - e[:, :1]).max() < 1e-5 * e.max()  # RK4 with 10 substeps per 50 ms frame
    for d in (0.1, 0.6):
        th, om = integrate(th0, om0, w0, np.full(n, d), u)
        e = _energy(th, om, w0)
        assert np.all(np.diff(e, axis=1) < 0)
        # dE/dt = -d omega^2: the loss over the sequence matches the integral of d omega^2
        loss = d * np.trapezoid(om ** 2, dx=DT, axis=1)
        np.testing.assert_allclose(e[:, 0] - e[:, -1], loss, rtol=2e-2)
    decay = lambda d: _energy(*integrate(th0, om0, w0, np.full(n, d), u), w0)[:, -1]  # noqa: E731
    assert np.all(decay(0.6) < decay(0.1))


@pytest.mark.slow
@pytest.mark.parametrize("w0,d", [(2.0, 0.0), (5.0, 0.0), (3.0, 0.6)])
def test_small_oscillation_frequency(w0, d):
    t_len = 1500  # 15 s: at least 3 periods of the slowest pendulum
    th, _ = integrate(np.array([0.02]), np.array([0.0]), np.array([w0]), np.array([d]), np.zeros((1, t_len)),
                      dt=0.01)
    s = th[0]
    up = np.nonzero((s[:-1] < 0) & (s[1:] >= 0))[0]
    cross = up + (-s[up]) / (s[up + 1] - s[up])  # linear interpolation of the upward zero crossings
    period = np.diff(cross).mean() * 0.01
    np.testing.assert_allclose(2 * np.pi / period, np.sqrt(w0 ** 2 - d ** 2 / 4), rtol=1e-3)


def test_render_puts_the_bob_where_the_angle_says():
    img = render(np.array([0.0, np.pi / 2]))
    r, c = np.unravel_index(img[0].argmax(), img[0].shape)
    assert r > 20 and 12 <= c <= 15  # theta = 0: straight down
    r, c = np.unravel_index(img[1].argmax(), img[1].shape)
    assert c > 20 and 12 <= r <= 15  # theta = pi / 2: to the right
    assert img.max() <= 1.0


# ----------------------------------------------------------------------------- model side


def _model(**kw):
    """The pendulum scene's network (configs/experiment/pendulum.yaml) at tiny widths."""
    from embodied_tactile.data.modality import load_modality
    from embodied_tactile.model import LatentFilter

    torch.manual_seed(0)
    prior = {"learn_sigma": True, "learn_embedding": True, **kw.pop("prior", {})}
    return LatentFilter(load_modality("pendulum").to_config(), n_z=4, n_y=2, n_a=1, n_objects=N_OBJECTS, prior=prior,
                        input_standardize=False, encoder={"widths": [4, 8], "hidden": 16}, transition_hidden=16,
                        lstm_hidden=16, **kw)


def test_one_step_ahead_separates_frequency_but_not_damping_beyond_one_frames_precision():
    """The damping diagnosis of docs/reference/model.md: the Cramer-Rao angle precision of one frame matches
    the analytic bound for a Gaussian blob (position sigma_noise sqrt(2/pi) / peak, over the
    10 px radius); one step ahead the two damping levels move the angle less than that, the
    adjacent frequencies 3 / 4 rad/s more; four steps ahead both are well above it."""
    prec = angle_precision(noise=0.05)
    assert prec == pytest.approx(0.05 * np.sqrt(2 / np.pi) / 10.0, rel=0.05)
    assert angle_precision(noise=0.1) == pytest.approx(2 * prec)
    data = generate(10, seed=1000)
    sep = lambda p, v, s: float(np.median(parameter_separation(data, p, v, s)))  # noqa: E731
    assert sep("damping", DAMPINGS, 1) < 0.6 * prec < prec < sep("w0", (3.0, 4.0), 1)
    assert sep("damping", DAMPINGS, 4) > 4 * prec
    assert sep("damping", (0.6, 0.6), 4) == 0.0
    with pytest.raises(ValueError, match="parameter must be 'damping' or 'w0'"):
        parameter_separation(data, "mass", (1.0, 2.0), 1)
    with pytest.raises(ValueError, match="outside the 60 frames"):
        parameter_separation(data, "w0", (3.0, 4.0), 55)


def test_least_squares_reader_told_the_equation_recovers_both_parameters():
    """The physics reader of docs/reference/model.md: on noiseless angles the per-sequence least squares
    recovers w0 and d to the finite differences' error (also across the angle's wrap at
    +-pi); with the per-frame Cramer-Rao noise the two damping levels stay apart on average
    and their spread grows; a trajectory too short for central differences is refused."""
    data = generate(4, seed=7)
    w0, d = least_squares_parameters(np.angle(np.exp(1j * data.theta)), data.actions)
    assert np.abs(w0 - data.w0).max() < 0.02 and np.abs(d - data.damping).max() < 0.02
    noisy = data.theta + angle_precision() * np.random.default_rng(0).standard_normal(data.theta.shape)
    _, d_noisy = least_squares_parameters(noisy, data.actions[..., 0])
    lo, hi = d_noisy[data.damping == DAMPINGS[0]], d_noisy[data.damping == DAMPINGS[1]]
    assert hi.mean() - lo.mean() > 0.3 and np.abs(d_noisy - data.damping).max() > np.abs(d - data.damping).max()
    with pytest.raises(ValueError, match=r"must both be \(N, T\) with T >= 4"):
        least_squares_parameters(data.theta[:, :3], data.actions[:, :3])


def test_hidden_frames_take_the_transition_prior_and_cost_no_kl():
    m = _model()
    obs, act = torch.rand(3, 6, 1, 28, 28), torch.randn(3, 6, 1)
    observed = torch.ones(3, 6, dtype=torch.bool)
    observed[:, 2:] = False
    out = m(obs, act, sample=False, observed=observed)
    torch.testing.assert_close(out["z_mean"][:, 2:], out["zp_mean"][:, 2:])
    torch.testing.assert_close(out["z_var"][:, 2:], out["zp_var"][:, 2:])
    full = m(obs, act, sample=False)
    torch.testing.assert_close(out["z_mean"][:, :2], full["z_mean"][:, :2])
    assert not torch.allclose(out["z_mean"][:, 2:], full["z_mean"][:, 2:])
    with pytest.raises(ValueError, match="observed must be"):
        m(obs, act, observed=observed[:, :4])


def test_observation_dropout_masks_frames_in_training_only():
    with pytest.raises(ValueError, match="obs_dropout must be in"):
        _model(obs_dropout=1.0)
    m = _model(obs_dropout=0.5)
    obs, act = torch.rand(8, 20, 1, 28, 28), torch.randn(8, 20, 1)
    torch.manual_seed(1)
    out = m(obs, act)
    mask = out["observed"]
    assert mask[:, 0].all() and 0.3 < (~mask[:, 1:]).float().mean() < 0.7
    torch.testing.assert_close(out["z_mean"][~mask], out["zp_mean"][~mask])
    terms = m.elbo_terms({"obs": obs, "actions": act, "object_id": torch.zeros(8, dtype=torch.long)})
    assert torch.isfinite(terms["nll"] + terms["kl_z"] + terms["kl_y"])
    m.eval()
    assert "observed" not in m(obs, act) and m.observation_mask(8, 20, obs.device) is None
    assert "observed" not in _model(obs_dropout=0.0)(obs, act)  # off at 0


def test_predict_is_the_filter_with_the_future_hidden():
    m = _model()
    m.eval()
    obs, act = torch.rand(2, 9, 1, 28, 28), torch.randn(2, 9, 1)
    pred = m.predict(obs[:, :4], act, horizon=5)
    assert pred["recon"].shape == (2, 5, 1, 28, 28) and pred["z_mean"].shape == (2, 5, 4)
    observed = torch.zeros(2, 9, dtype=torch.bool)
    observed[:, :4] = True
    ref = m(obs, act, sample=False, observed=observed)
    torch.testing.assert_close(pred["z_mean"], ref["z_mean"][:, 4:])
    torch.testing.assert_close(pred["recon"], ref["recon"][:, 4:])
    with pytest.raises(ValueError, match="predict needs"):
        m.predict(obs[:, :4], act[:, :8], horizon=5)


# ----------------------------------------------------------------------------- training

#: the plain ELBO's inference (recipe=elbo: every frame observed, y the LSTM's q(y_t)) with the
#: systems' labels in the prior; the short runs below were measured with it and with the two
#: remedies alone (unbounded evidence)
PLAIN = ["recipe=elbo", "model.net.prior.labels=true"]
#: widths small enough for a few-steps run in seconds
TINY = ["model.net.encoder.widths=[2,2]", "model.net.encoder.hidden=8", "model.net.transition_hidden=8",
        "model.net.lstm_hidden=8"]


def train_scene(folder, steps: int, overrides=(), n_train: int = 8, n_test: int = 4, n_steps: int = 30,
                batch_size: int = 16, **read):
    """The pendulum scene trained ``steps`` steps in ``folder`` through run.training.train, then
    eval.pendulum.read_out (``read``: its keywords) -> (its result, metrics.json)."""
    import json
    import math
    import signal

    from hydra.core.hydra_config import HydraConfig
    from hydra.utils import instantiate

    from embodied_tactile.eval.pendulum import read_out
    from embodied_tactile.eval.runs import load_module, load_run, untrained_module
    from embodied_tactile.run.training import compose, train

    per_epoch = math.ceil(n_train * N_OBJECTS / batch_size)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        cfg = compose(["experiment=pendulum", "seed=0", "threads=1", "plain_progress=true", "logger=none",
                       f"paths.log_dir={folder}/logs", f"paths.data_dir={folder}/data", f"data.n_train={n_train}",
                       f"data.n_test={n_test}", f"data.n_steps={n_steps}", f"data.batch_size={batch_size}",
                       f"trainer.max_epochs={math.ceil(steps / per_epoch)}", f"+trainer.max_steps={steps}",
                       "callbacks.krr_alignment.points=1", *overrides], str(folder / "run"))
        train(cfg, str(folder / "run"))
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
        HydraConfig.instance().cfg = None
    run = load_run(folder / "run", "last")
    trained = load_module(run)
    dm = instantiate(run.cfg.data)
    dm.setup("fit")
    res = read_out(trained, untrained_module(run, trained), dm, **read)
    return res, json.loads((folder / "run" / "metrics.json").read_text())


@pytest.mark.slow  # plain_run: trains the Latent Filter 150 steps (the remedies' comparison's plain run)
def test_short_training_learns_the_angle(plain_run):
    short_run = plain_run
    r = short_run["readouts"]
    assert set(r) == {"z_angle", "z_velocity", "y_frequency", "y_damping", "z_frequency", "z_damping", "y_velocity"}
    assert all(np.isfinite(v).all() for v in r.values())
    assert r["z_angle"][1] >= 0.9, r  # the per-frame code is learnt quickly
    # the same read-outs on the unseen systems, and both sets of the untrained network
    for part in ("readouts_unseen", "readouts_untrained", "readouts_unseen_untrained"):
        assert set(short_run[part]) == set(r) and all(np.isfinite(v).all() for v in short_run[part].values())
    assert short_run["readouts_unseen"]["z_angle"][1] >= 0.9  # the angle code does not depend on the system
    assert set(short_run["gradient_snr"]) == {"encoder", "decoder", "transition", "y_posterior", "prior"}
    assert all(np.isfinite(v) and v > 0 for v in short_run["gradient_snr"].values())
    assert 0.0 <= short_run["diagnostics"]["transition_weight"] <= 1.0
    ol = short_run["open_loop"]
    assert ol["model"].shape == (20,) and np.all(ol["model"] < ol["last_frame"][0] * 10)


REMEDIES = ["model.net.obs_dropout=0.5", "model.net.y_update=evidence"]


def _read_run(folder, overrides):
    """One 150-step training of the remedies' comparison (module-level: a spawned process runs it).
    Read-outs fitted on 300 rows: half the 600 rows' time, and the same outcomes as 600 rows in
    seeds 0-2 of a 100-step training (measured 2026-11-29). 150 steps stay: at 100 the remedies'
    open loop missed the last frame in seed 1."""
    torch.set_num_threads(1)
    return train_scene(folder, 150, overrides, n_filter=10, horizon=20, max_rows=300, snr_draws=2)[0]


@pytest.fixture(scope="module")
def remedy_and_plain(tmp_path_factory):
    """The short run with the remedies that make the filter filter (docs/reference/model.md, "Pendulum
    benchmark"): observation dropout 0.5 and the evidence y update; and the same data, seed and
    steps under the plain ELBO. The two trainings run side by side, one torch thread each, the
    plain one in a spawned process (the same numbers as one after the other: each is
    deterministic at one thread)."""
    import concurrent.futures
    import multiprocessing

    with concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        plain = pool.submit(_read_run, tmp_path_factory.mktemp("plain"), PLAIN)
        remedy = _read_run(tmp_path_factory.mktemp("remedy"), [*PLAIN, *REMEDIES])
        return remedy, plain.result()


@pytest.fixture(scope="module")
def remedy_run(remedy_and_plain):
    return remedy_and_plain[0]


@pytest.fixture(scope="module")
def plain_run(remedy_and_plain):
    return remedy_and_plain[1]


@pytest.mark.slow  # remedy_run, plain_run: train the Latent Filter 150 steps each
def test_remedies_make_the_model_predict(remedy_run, plain_run):
    """Observation dropout makes the model predict: same data, seed 0 and 150 steps of the
    pendulum scene, the remedies' open-loop prediction beats the plain ELBO's and the last
    frame at every horizon up to 10 (so they do in seeds 0-2 at 150 and at 300 steps:
    docs/experiments/pendulum.md, "150 steps"). (At 300 steps the remedies' z carries the angular
    velocity in 2 of 3 seeds only, seed 0 not among them: docs/experiments/pendulum.md,
    "300 steps, 3 seeds"; the velocity claim rests on the 2,500-step measurements.)"""
    r, ol = remedy_run["readouts"], remedy_run["open_loop"]
    assert r["z_angle"][1] >= 0.9, r
    assert np.all(ol["model"][:10] < plain_run["open_loop"]["model"][:10]), (ol, plain_run["open_loop"])
    assert np.all(ol["model"][:10] < ol["last_clean"][:10]), ol


@pytest.mark.slow  # remedy_run: trains the Latent Filter 150 steps
@pytest.mark.xfail(strict=True, reason="targets of docs/experiments/pendulum.md: at 150 steps on 64 sequences y does not yet identify the "
                   "pendulum's frequency / damping (2500 steps: docs/reference/model.md); flips when it does")
def test_short_training_meets_the_pendulum_targets(remedy_run):
    r, u = remedy_run["readouts"], remedy_run["readouts_unseen"]
    assert r["z_velocity"][1] >= 0.9, r
    assert r["y_frequency"][1] >= 0.8, r
    assert r["y_damping"][1] >= 0.6, r
    assert u["y_frequency"][1] >= 0.8, u  # systems never seen (parameters between the grid's)
    assert u["y_damping"][1] >= 0.5, u


@pytest.mark.slow
def test_the_scene_trains_and_reads_out_every_part_after_a_few_steps(tmp_path):
    """The pendulum scene through run.training.train on a tiny budget (the read-out tests above
    train 150 steps and are slow): the steps asked, the run's KRR NMSE on (w0, d), and
    every read-out, diagnostic and gradient SNR there and finite."""
    res, metrics = train_scene(tmp_path, 3, [*PLAIN, *TINY], n_train=2, n_test=1, n_steps=12, batch_size=4,
                               n_filter=4, horizon=6, max_rows=200, snr_draws=2)
    final = metrics["krr_final"]
    assert metrics["status"] == "finished" and final["step"] == 3
    assert set(final["nmse"]) == {"natural_frequency", "damping"} and np.isfinite(final["nmse_overall"])
    keys = {"z_angle", "z_velocity", "y_frequency", "y_damping", "z_frequency", "z_damping", "y_velocity"}
    for part in ("readouts", "readouts_unseen", "readouts_untrained", "readouts_unseen_untrained"):
        assert set(res[part]) == keys and all(np.isfinite(v).all() for v in res[part].values()), part
    assert set(res["gradient_snr"]) == {"encoder", "decoder", "transition", "y_posterior", "prior"}
    assert all(np.isfinite(v) and v > 0 for v in res["gradient_snr"].values())
    assert 0.0 <= res["diagnostics"]["transition_weight"] <= 1.0
    assert res["open_loop"]["model"].shape == (6,)
    # the run's closing block and evaluate.py name the pendulum's own reader, not evaluate.py's tactile one
    from embodied_tactile.eval.runs import EvaluationError, data_config, load_run
    from embodied_tactile.run.summary import run_summary_lines

    run = tmp_path / "run"
    text = "\n".join(run_summary_lines(run))
    assert f"pendulum_probes.py --load {run} --no-frames" in text and "evaluate.py" not in text
    assert "held-out sequences of the 8 training systems" in text and "Objects never touched" not in text
    with pytest.raises(EvaluationError, match="is a pendulum run.*pendulum_probes.py --load"):
        data_config(load_run(run, "last"), None)


@pytest.mark.slow
def test_remedies_are_config_switches(tmp_path):
    from hydra.utils import instantiate
    from test_configs import _compose_job

    cfg = _compose_job(["model.net.obs_dropout=0.25", "model.net.y_update=evidence", "model.net.y_evidence_max=1"],
                       tmp_path)
    module = instantiate(cfg.model)
    net = next(m for m in module.modules() if type(m).__name__ == "LatentFilter")
    assert net.obs_dropout == 0.25 and net.config()["y_update"] == "evidence" and net.config()["y_evidence_max"] == 1
    filter_ = _compose_job(["recipe=filter"], tmp_path)  # the pendulum benchmark's recipe
    assert (filter_.model.net.obs_dropout, filter_.model.net.y_update) == (0.5, "evidence")
    elbo = _compose_job(["recipe=elbo"], tmp_path)
    assert (elbo.model.net.obs_dropout, elbo.model.net.y_update) == (0.0, "direct")


def test_the_pendulum_scene_composes_its_settings_and_takes_overrides(tmp_path):
    """experiment=pendulum: the pendulum's data, modality and recipe (filter), its network
    (n_z 8, n_y 4, n_a 1, 8 systems, raw images, learned prior sigma and codes), Adam at 1e-3,
    batch 16, targets in the systems' units; ``model.net.X=V`` (the earlier ``--remedy``)
    reaches the network."""
    from hydra.utils import instantiate
    from test_configs import _compose_job

    cfg = _compose_job(["experiment=pendulum"], tmp_path)
    net = cfg.model.net
    assert (cfg.modality.name, cfg.data.batch_size, cfg.model.optimizer.lr, cfg.targets) == ("pendulum", 16, 1e-3, "physical")
    assert (net.n_z, net.n_y, net.n_a, net.n_objects, net.input_standardize) == (8, 4, 1, N_OBJECTS, False)
    assert net.prior.learn_sigma and net.prior.learn_embedding and not net.prior.labels and net.obs_dropout == 0.5
    assert type(instantiate(cfg.data)).__name__ == "PendulumDataModule"
    cfg = _compose_job(["experiment=pendulum", "model.net.prior.learn_embedding=false", "model.net.prior.learn_sigma=false",
                        "model.net.obs_dropout=0.0", *TINY], tmp_path)
    module = instantiate(cfg.model)
    prior = module.model.prior
    assert module.model.obs_dropout == 0.0 and not prior.embedding.weight.requires_grad
    assert "raw_var" not in dict(prior.named_parameters()) and "raw_var" in dict(prior.named_buffers())


def test_the_datamodule_serves_the_sets_and_their_targets():
    """PendulumDataModule: the training, validation, test (seed + 1000, the benchmark's
    held-out) and unseen sets, batches with the systems' (w0, d) as factors and sequence ids
    unique over the sets, the training images' statistics; a pairing other than trial is refused."""
    from embodied_tactile.data.pendulum import UNSEEN_SYSTEMS
    from embodied_tactile.data.pendulum_module import PendulumDataModule

    dm = PendulumDataModule(seed=3, n_train=2, n_val=2, n_test=1, n_steps=12, batch_size=4)
    dm.prepare_data()
    dm.setup("fit")
    assert np.array_equal(dm.data["test"].obs, generate(1, seed=1003, n_steps=12).obs)
    batch = next(iter(dm.test_dataloader()))
    assert batch["obs"].shape == (4, 12, 1, 28, 28) and batch["factors"].shape == (4, 2)
    np.testing.assert_allclose(batch["factors"].numpy(), np.stack([dm.data["test"].w0, dm.data["test"].damping], -1)[:4],
                               rtol=1e-6)
    ids = [int(i) for loader in (dm.train_eval_dataloader(), dm.val_dataloader(), dm.test_dataloader(),
                                 dm.unseen_dataloader()) for b in loader for i in b["seq_id"]]
    assert len(ids) == len(set(ids)) == (2 + 2 + 1) * N_OBJECTS + len(UNSEEN_SYSTEMS)
    assert dm.statistics.n_train_sequences == 2 * N_OBJECTS
    assert dm.describe()["factors"] == ["natural_frequency", "damping"]
    with pytest.raises(ValueError, match="data.context must be null or 'trial'"):
        PendulumDataModule(context="window")


def test_context_pairing_draws_another_sequence_of_the_same_system():
    """PendulumSequences(context=True): each item's context is a different sequence of the
    same system, the draws repeat with the seed; without context there is none."""
    from embodied_tactile.data.pendulum_module import PendulumSequences

    data = generate(3, seed=2, n_steps=12)
    paired = PendulumSequences(data, context=True, seed=5)
    for i in range(len(data)):
        item = paired[i]
        j = [k for k in range(len(data)) if np.array_equal(data.obs[k], item["context_obs"].numpy())]
        assert len(j) == 1 and j[0] != i and data.object_id[j[0]] == data.object_id[i]
        assert np.array_equal(data.actions[j[0]], item["context_actions"].numpy())
    first = [PendulumSequences(data, context=True, seed=5)[i]["context_obs"] for i in range(len(data))]
    second = [PendulumSequences(data, context=True, seed=5)[i]["context_obs"] for i in range(len(data))]
    assert all(torch.equal(a, b) for a, b in zip(first, second))
    assert "context_obs" not in PendulumSequences(data)[0]
    with pytest.raises(ValueError, match="at least 2 sequences per system"):
        PendulumSequences(generate(1, seed=2, n_steps=12), context=True)


@pytest.mark.slow
def test_the_scene_trains_the_context_objective_after_a_few_steps(tmp_path):
    """recipe=context on the pendulum: the DataModule pairs sequences of a system, the module
    trains on context / target pairs, and the run's read-out is there."""
    res, metrics = train_scene(tmp_path, 3, ["recipe=context", *TINY], n_train=2, n_test=1, n_steps=12,
                               batch_size=4, n_filter=4, horizon=6, max_rows=200, snr_draws=2)
    assert metrics["status"] == "finished" and np.isfinite(metrics["krr_final"]["nmse_overall"])
    assert all(np.isfinite(v).all() for v in res["readouts_unseen"].values())
