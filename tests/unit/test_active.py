"""Active palpation (docs/reference/active.md): the selection on a constructed model whose most
informative action is known, determinism of an episode under a seed, the online posterior
across touches against the batched one, and the CLI (errors; one episode on a tiny run)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from embodied_tactile.active.episode import filter_touch, run_episodes
from embodied_tactile.active.model import PalpationModel
from embodied_tactile.active.policy import ActivePolicy, RandomPolicy, expected_variance_reduction
from embodied_tactile.active.source import SimulatedTouchSource, TouchSource
from embodied_tactile.data.preprocess import PreprocessConfig
from embodied_tactile.eval.krr import fit_alignment
from embodied_tactile.model.latent_filter import LatentFilter

REPO = Path(__file__).resolve().parents[2]
N_Y = 4
#: action index -> value of action column 0 in its nominal trajectory; the constructed y
#: posterior gains evidence softplus(10 tanh(tanh(a0)) - 5) per frame: action 6 is the most
#: informative, 14 the least.
A0 = {2: 0.1, 6: 0.9, 10: 0.3, 14: 0.0}


def _net(y_update: str = "evidence", seed: int = 0) -> LatentFilter:
    torch.manual_seed(seed)
    return LatentFilter("acc", n_z=2, n_y=N_Y, n_a=6, encoder={"widths": [2, 2], "hidden": 8},
                        transition_hidden=8, lstm_hidden=4, y_update=y_update).eval()


def _informative_net() -> LatentFilter:
    """Evidence about y comes only through action column 0 (see A0)."""
    net = _net("evidence")
    cell, head = net.y_posterior.cell, net.y_posterior.head
    H, n_in = cell.hidden_size, cell.input_size
    with torch.no_grad():
        for p in (cell.weight_ih, cell.weight_hh, cell.bias_ih, cell.bias_hh, head.weight, head.bias):
            p.zero_()
        cell.bias_ih[0:H] = 20.0  # input gate open
        cell.bias_ih[H:2 * H] = -20.0  # forget gate closed: c = tanh(g)
        cell.bias_ih[3 * H:4 * H] = 20.0  # output gate open
        cell.weight_ih[2 * H + 0, n_in - 6] = 1.0  # g of unit 0 = tanh(a_0)
        head.weight[N_Y:, 0] = 10.0  # evidence precision from unit 0
        head.bias[N_Y:] = -5.0
    return net


def _alignment():
    rng = np.random.default_rng(0)
    y = rng.standard_normal((80, N_Y))
    return fit_alignment(y, y.copy(), cv=2)  # factors = y: the variance of f(y) follows y's


def _model(net: LatentFilter, T: int = 10) -> PalpationModel:
    nominal = {a: np.tile(np.array([[v, 0, 0, 0, 0, 0]], dtype=np.float32), (T, 1)) for a, v in A0.items()}
    return PalpationModel(net=net, channels=("acc",), preprocess=PreprocessConfig(), alignment=_alignment(),
                          ref_var=np.ones(4), nominal_actions=nominal)


def _touch_state(model: PalpationModel, B: int, action: int) -> dict:
    obs = torch.rand(B, 6, 1, 28, 28, generator=torch.Generator().manual_seed(1))
    acts = torch.from_numpy(np.stack([model.nominal_actions[action][:6]] * B))
    _, state = filter_touch(model.net, obs, acts, None)
    return state


def test_selection_picks_the_known_most_informative_action():
    model = _model(_informative_net())
    state = _touch_state(model, 3, action=14)
    scores = expected_variance_reduction(model, state, list(A0), n_rollouts=2, n_y_samples=256, seed=0)
    assert scores.shape == (3, 4)
    order = [list(A0)[i] for i in np.argsort(-scores[0])]
    assert order == [6, 10, 2, 14], (order, scores[0])  # ranked by the constructed evidence
    pol = ActivePolicy(first_action=14, n_rollouts=2, n_y_samples=256)
    rng = np.random.default_rng(0)
    assert pol.choose(0, np.zeros((3, 0)), None, model, rng).tolist() == [14, 14, 14]  # no posterior yet
    assert pol.choose(1, np.zeros((3, 1)), state, model, rng).tolist() == [6, 6, 6]
    assert len(pol.decision_s) == 1 and pol.decision_s[0] > 0


def test_learned_score_picks_the_action_with_the_lowest_predicted_error():
    model = _model(_informative_net())
    rng = np.random.default_rng(0)
    y = rng.standard_normal((40, N_Y))
    err = {2: 0.5, 6: 0.3, 10: 0.1 + 0.0 * y[:, 0], 14: 0.9}
    score = {a: fit_alignment(y, (np.broadcast_to(e, (40,)) + 0.01 * rng.standard_normal(40))[:, None], cv=2)
             for a, e in err.items()}
    pol = ActivePolicy(first_action=14, criterion="learned", error_score=score)
    post = (y[:3], np.ones((3, N_Y)))
    assert pol.choose(1, np.zeros((3, 1)), None, model, rng, posterior=post).tolist() == [10, 10, 10]
    np.testing.assert_allclose(-pol.last_scores[0], [0.5, 0.3, 0.1, 0.9], atol=0.05)
    with pytest.raises(ValueError, match="needs an error score"):
        ActivePolicy(first_action=14, criterion="learned")


def test_selection_rejects_unknown_criterion_and_action():
    model = _model(_informative_net())
    state = _touch_state(model, 1, action=14)
    with pytest.raises(ValueError, match="criterion must be one of"):
        expected_variance_reduction(model, state, [2], criterion="entropy")
    with pytest.raises(ValueError, match=r"action\(s\) \[3\] unknown to this model"):
        expected_variance_reduction(model, state, [3])


def test_online_posterior_across_touches_equals_batched_concatenation():
    net = _net("direct", seed=3)
    g = torch.Generator().manual_seed(2)
    obs = [torch.rand(2, 7, 1, 28, 28, generator=g) for _ in range(3)]
    acts = [torch.randn(2, 7, 6, generator=g) for _ in range(3)]
    state = None
    for o, a in zip(obs, acts):
        out, state = filter_touch(net, o, a, state)
    batched = net.infer_latents(torch.cat(obs, dim=1), torch.cat(acts, dim=1))
    torch.testing.assert_close(out["y_mean"], batched["y_mean"][:, -1], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out["y_var"], batched["y_var"][:, -1], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out["z_mean"], batched["z_mean"][:, -1], atol=1e-5, rtol=1e-5)


@pytest.mark.slow  # three simulated palpation episodes of 300-frame touches
def test_episode_is_deterministic_under_a_seed():
    model = _model(_net("direct", seed=5), T=300)
    model.nominal_actions = {a: model.nominal_actions[a] for a in (6, 14)}

    def episode(seed):
        src = SimulatedTouchSource("soft", "pressing", episode_seed=seed)
        assert isinstance(src, TouchSource)
        return run_episodes(model, src, [8], RandomPolicy(), 2, seed=seed, n_factor_samples=8)

    a, b, c = episode(0), episode(0), episode(1)
    np.testing.assert_array_equal(a.actions, b.actions)
    np.testing.assert_array_equal(a.estimates, b.estimates)
    np.testing.assert_array_equal(a.stds, b.stds)
    assert a.estimates.shape == (1, 2, 4) and np.isfinite(a.estimates).all()
    assert not np.array_equal(a.estimates, c.estimates)  # another seed: other sensor data


@pytest.mark.slow
def test_touch_seed_stream_and_a_touch_is_the_trial_of_its_stream():
    """sim.episode: touch ``use`` of an action in episode s is the simulator's trial with
    repetition ``use`` and seed EPISODE_SEED_BASE + s; a bad episode seed is refused."""
    from embodied_tactile.sim import simulate_trial
    from embodied_tactile.sim.episode import EPISODE_SEED_BASE, simulate_touch, touch_seed

    assert touch_seed(0) == EPISODE_SEED_BASE and touch_seed(7) == EPISODE_SEED_BASE + 7
    for bad in (-1, 1.5):
        with pytest.raises(ValueError, match="episode seed must be an integer >= 0"):
            touch_seed(bad)
    touch = simulate_touch(8, "soft", "pressing", 6, use=1, episode_seed=2)
    same = simulate_trial(8, "soft", "pressing", 6, repetition=1, seed=EPISODE_SEED_BASE + 2)
    np.testing.assert_array_equal(touch.acc, same.acc)
    np.testing.assert_array_equal(touch.fsr, same.fsr)
    assert touch.attrs["repetition"] == 1 and touch.attrs["seed"] == EPISODE_SEED_BASE + 2


def test_touches_to_reach_and_the_target_summary():
    """active.evaluation: the touches the active policy needs to reach random's final NMSE,
    on the seed-mean curves and per seed, and the per-touch table."""
    from embodied_tactile.active.evaluation import curve_table, summarise, touches_to_reach

    assert touches_to_reach([0.9, 0.5, 0.3], 0.5) == 2 and touches_to_reach([0.9, 0.8], 0.5) is None
    curves = {"random": np.array([[0.9, 0.6, 0.5, 0.45, 0.4], [0.8, 0.7, 0.5, 0.45, 0.4]]),
              "active": np.array([[0.7, 0.4, 0.3, 0.3, 0.3], [0.8, 0.5, 0.4, 0.35, 0.3]])}
    s = summarise(curves)
    assert s["budget"] == 5 and s["stats"]["active"][0]["mean"] == pytest.approx(0.75)
    t = s["target"]
    assert t["reference_final_nmse"] == pytest.approx(0.4)
    # active's seed-mean curve 0.75, 0.45, 0.35, ...: at random's final 0.4 after 3 of 5 touches
    assert t["touches_needed"] == 3 and t["fraction"] == pytest.approx(0.6) and t["met"]
    assert t["touches_needed_per_seed"] == [2, 3]
    assert "target" not in summarise({"active": curves["active"]})  # no reference: no target check
    table = curve_table(s, "NMSE per touch")
    assert [r[0] for r in table.rows] == [1, 2, 3, 4, 5] and table.columns[0] == "Touches"
    assert table.rows[0][1:3] == [pytest.approx(0.85), pytest.approx(0.75)]  # random, active means


@pytest.mark.slow
def test_palpate_main_in_process_errors_clearly_on_a_missing_run(tmp_path, monkeypatch, capsys, restore_logging):
    """What test_cli_errors_clearly_on_a_missing_run checks of the CLI, through palpate.main
    in this process (the subprocess test is slow)."""
    from embodied_tactile.active import palpate

    monkeypatch.chdir(tmp_path)
    threads = torch.get_num_threads()  # palpate.run sets torch's threads from its config

    def status(*argv):
        monkeypatch.setattr(sys, "argv", ["palpate", f"hydra.run.dir={tmp_path / 'hydra'}", *argv])
        with pytest.raises(SystemExit) as exc:
            palpate.main()
        return exc.value.code, capsys.readouterr().err

    try:
        code, err = status(f"run={tmp_path / 'nope'}", "object=3", "budget=2")
        assert code == 2 and f"palpate: error: no such run folder: {tmp_path / 'nope'}" in err, err
        code, err = status("object=3")
        assert code == 2 and "run=<folder of a trained run> is required" in err, err
        (tmp_path / "empty").mkdir()
        code, err = status(f"run={tmp_path / 'empty'}")
        assert code == 2 and "holds no training run" in err, err
        code, err = status(f"run={tmp_path / 'empty'}", "budget=0")
        assert code == 2 and "budget must be an integer >= 1" in err, err
    finally:
        torch.set_num_threads(threads)


def _palpate(args, cwd=REPO, timeout=240):
    env = dict(os.environ, WANDB_MODE="disabled", OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "embodied_tactile.active.palpate", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow  # a palpate CLI subprocess (the same errors in this process: the test above)
def test_cli_errors_clearly_on_a_missing_run(tmp_path):
    p = _palpate([f"run={tmp_path / 'nope'}", "object=3", "budget=2"])
    assert p.returncode == 2
    assert f"palpate: error: no such run folder: {tmp_path / 'nope'}" in p.stderr


def _palpate_here(argv, tmp_path, monkeypatch, capsys) -> subprocess.CompletedProcess:
    """``python -m embodied_tactile.active.palpate <argv>`` by its main() in this process (the
    threads it sets put back afterwards): its exit status and what it printed."""
    from embodied_tactile.active import palpate

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["palpate", f"hydra.run.dir={tmp_path / 'hydra'}", *argv])
    env, threads = dict(os.environ), torch.get_num_threads()
    capsys.readouterr()
    try:
        with pytest.raises(SystemExit) as exc:
            palpate.main()
    finally:
        os.environ.clear()
        os.environ.update(env)
        torch.set_num_threads(threads)
    out = capsys.readouterr()
    return subprocess.CompletedProcess(argv, exc.value.code, out.out, out.err)


@pytest.mark.slow  # trains a tiny run (train.py's entry point in this process)
def test_cli_runs_an_episode_on_a_tiny_trained_run(tmp_path, fast_data_dir, monkeypatch, capsys, restore_logging):
    from conftest import train_in_process

    t = train_in_process("debug=fast", "modality=fsr_tb", "threads=1", f"paths.data_dir={fast_data_dir}",
                         f"hydra.run.dir={tmp_path}/run")
    assert t.returncode == 0, t.stderr[-3000:]
    p = _palpate_here([f"run={tmp_path}/run", "object=8", "budget=2", "first_action=10", "active.n_rollouts=2",
                       "active.n_y_samples=8", "n_factor_samples=8", "evaluate.policies=[active]",
                       f"out={tmp_path}/pal"], tmp_path, monkeypatch, capsys)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "touch 1/2 action 10" in p.stdout and "touch 2/2 action" in p.stdout
    assert "+-" in p.stdout and "decision latency:" in p.stdout
    assert (tmp_path / "pal" / "episode_obj08_active_s0.png").stat().st_size > 0
    bad = _palpate_here([f"run={tmp_path}/run", "object=8", "first_action=14"], tmp_path, monkeypatch, capsys)
    assert bad.returncode == 2 and "first_action=14 is not an action of the run" in bad.stderr
    assert not (tmp_path / "run" / "palpation").exists()  # refused before any calibration episode or output
