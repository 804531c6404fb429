"""train.py's recipe in this process: :func:`embodied_tactile.run.training.train` on a config
composed from ``configs/`` with tiny shapes, its run folder in ``tmp_path``, and evaluate's
in-process :func:`~embodied_tactile.eval.pipeline.evaluate` on that folder."""

from __future__ import annotations

import contextlib
import json
import math
import signal

import pytest


def tiny_overrides(data_dir, log_dir) -> list[str]:
    """The overrides of :func:`composed`'s job (its run folder aside)."""
    return ["debug=fast", "modality=acc", "threads=1", "seed=0", "plain_progress=true", "logger=csv",
            "callbacks.krr_alignment.points=1", f"paths.data_dir={data_dir}", f"paths.log_dir={log_dir}"]


@contextlib.contextmanager
def composing(folder, data_dir):
    """(job config of the tiny scene, run folder ``<folder>/run``), as :func:`composed` makes it."""
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig

    from embodied_tactile.run.training import compose

    run = folder / "run"
    cfg = compose(tiny_overrides(data_dir, folder / "logs"), str(run))
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield cfg, run
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
        HydraConfig.instance().cfg = None
        GlobalHydra.instance().clear()


@pytest.fixture()
def composed(tmp_path, fast_data_dir):
    """A job config of the tiny scene (debug=fast, acc only, one thread), its
    ``${hydra:runtime.output_dir}`` the run folder in tmp_path; Hydra's and the signal
    handlers' state put back afterwards."""
    with composing(tmp_path, fast_data_dir) as job:
        yield job


@pytest.mark.slow
def test_train_in_process_and_evaluate_reproduces_its_nmse(composed, capsys):
    """One training in this process finishes, prints its summary and records a finite NMSE;
    evaluate on its folder (the final weights, the run's own alignment) gives the same number
    to 1e-9."""
    from embodied_tactile.eval.pipeline import evaluate
    from embodied_tactile.run.training import train

    cfg, run = composed
    elbo = train(cfg, str(run))
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["status"] == "finished" and metrics["final_readout"]
    assert elbo is not None and math.isfinite(elbo) and elbo == metrics["final_val"]["val/elbo"]
    nmse = metrics["krr_final"]["nmse_overall"]
    assert math.isfinite(nmse) and 0 < nmse < 2
    assert (run / "checkpoints" / "last.ckpt").is_file() and (run / "config_resolved.yaml").is_file()
    assert "run finished:" in capsys.readouterr().out

    out = evaluate(run, ["print_tables=false", "baselines=[mean]", "figures=false", "umap=false"])
    check = out["runs"][0]["training_final_alignment"]
    assert check["other"] == [], check
    assert check["evaluate_nmse_overall"] == pytest.approx(nmse, abs=1e-9)


def test_a_bad_setting_stops_train_before_the_data(composed, capsys):
    """train(cfg) checks the settings itself (a value swept with -m reaches only the job): one
    line naming the key, exit 2; the folder this start created is gone again (a multirun
    job's folder, made by Hydra, is marked failed with that reason instead)."""
    from embodied_tactile.run.training import train

    cfg, run = composed
    cfg.data.batch_size = 0
    with pytest.raises(SystemExit) as info:
        train(cfg, str(run))
    assert info.value.code == 2
    assert capsys.readouterr().err.strip() == "train.py: error: data.batch_size=0 (int): expected an integer >= 1"
    assert not run.exists()


@pytest.mark.slow
def test_train_in_process_on_the_pendulum_scene(tmp_path):
    """experiment=pendulum (configs/data/pendulum.yaml) through train(cfg) with tiny shapes: the
    run finishes, its final KRR read-out of the systems' (w0, d) is a finite NMSE in metrics.json,
    and its checkpoints are there."""
    from hydra.core.hydra_config import HydraConfig

    from embodied_tactile.run.training import compose, train

    run = tmp_path / "run"
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        cfg = compose(["experiment=pendulum", "threads=1", "seed=0", "plain_progress=true", "logger=none",
                       "data.n_train=2", "data.n_test=1", "data.n_steps=12", "data.batch_size=4", "trainer.max_epochs=2",
                       "model.net.encoder.widths=[2,2]", "model.net.encoder.hidden=8", "model.net.transition_hidden=8",
                       "model.net.lstm_hidden=8", "callbacks.krr_alignment.points=1",
                       f"paths.log_dir={tmp_path / 'logs'}", f"paths.data_dir={tmp_path / 'data'}"], str(run))
        train(cfg, str(run))
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
        HydraConfig.instance().cfg = None
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["status"] == "finished" and metrics["final_readout"]
    final = metrics["krr_final"]
    assert set(final["nmse"]) == {"natural_frequency", "damping"} and final["n_test"] == 8
    assert math.isfinite(final["nmse_overall"]) and final["targets"] == "physical"
    assert metrics["data"]["scene"] == "pendulum" and (run / "checkpoints" / "last.ckpt").is_file()
