"""Thread policy: one place divides the cores among the trainings that share the machine."""

from __future__ import annotations

import ast
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from embodied_tactile.run import threadenv, threads
from embodied_tactile.run.threadenv import TrainingRegistry

REPO = Path(__file__).resolve().parents[2]


def test_concurrent_jobs_follows_launcher_and_ddp():
    assert threads.concurrent_jobs(None, 1, cores=8) == 1
    assert threads.concurrent_jobs(2, 1, cores=8) == 2
    assert threads.concurrent_jobs(-1, 1, cores=8) == 8  # joblib: one job per core
    assert threads.concurrent_jobs(-2, 1, cores=8) == 7  # all but one
    assert threads.concurrent_jobs(2, 2, cores=8) == 4  # 2 launcher jobs x 2 DDP processes
    assert threads.concurrent_jobs(None, "auto", cores=8) == 1


def test_thread_budget_divides_cores_and_a_setting_is_a_ceiling():
    assert threads.thread_budget("auto", jobs=1, cores=2) == 2
    assert threads.thread_budget("auto", jobs=2, cores=2) == 1
    assert threads.thread_budget(None, jobs=3, cores=2) == 1  # never 0
    assert threads.thread_budget("auto", jobs=2, cores=16) == 8
    assert threads.thread_budget("auto", jobs=3, cores=16) == 5
    assert threads.thread_budget(3, jobs=1, cores=16) == 3  # fewer than the share: kept
    assert threads.thread_budget(3, jobs=2, cores=2) == 1  # more than the share: the share
    assert threads.thread_budget(2, jobs=1, cores=2) == 2
    with pytest.raises(ValueError, match="positive integer or 'auto'"):
        threads.thread_budget(0, jobs=1)


def test_configure_threads_sets_torch_and_the_environment(monkeypatch, tmp_path):
    before = torch.get_num_threads()
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        monkeypatch.setenv(var, "99")
    try:
        cfg = OmegaConf.create({"threads": "auto", "trainer": {"strategy": "ddp", "devices": 2}})
        share = threads.configure_threads(cfg, TrainingRegistry(tmp_path / "a"))  # no launcher; DDP: 2
        assert share.jobs == 2 and share.threads == max(1, threads.available_cores() // 2)
        assert torch.get_num_threads() == share.threads
        assert os.environ["OMP_NUM_THREADS"] == os.environ["MKL_NUM_THREADS"] == str(share.threads)
        assert threads.configure_threads(OmegaConf.create({"threads": 1}), TrainingRegistry(tmp_path / "b")).threads == 1
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


HOLDER = textwrap.dedent("""
    import sys, time
    from embodied_tactile.run.threadenv import TrainingRegistry
    TrainingRegistry(sys.argv[1]).register()
    print("registered", flush=True)
    time.sleep(60)
""")


def _holders(folder: Path, n: int = 1) -> list[subprocess.Popen]:
    """Other 'trainings': ``n`` processes that register in ``folder`` and wait (started together)."""
    ps = [subprocess.Popen([sys.executable, "-c", HOLDER, str(folder)], stdout=subprocess.PIPE, text=True,
                           env={**os.environ, "PYTHONPATH": str(REPO / "src")}) for _ in range(n)]
    for p in ps:
        assert p.stdout.readline().strip() == "registered"
    return ps


def test_registry_counts_live_trainings_and_forgets_killed_ones(tmp_path):
    reg = TrainingRegistry(tmp_path)
    assert reg.count() == 0
    reg.register()
    reg.register()  # once per process
    assert reg.count() == 1
    others = _holders(tmp_path, 2)
    try:
        assert reg.count() == 3
        others[0].send_signal(signal.SIGKILL)  # no clean-up: the lock goes with the process
        others[0].wait()
        assert reg.count() == 2
        assert len(list(tmp_path.glob("*.live"))) == 2  # the killed one's file removed by the count
    finally:
        for p in others:
            p.kill()
            p.wait()
    assert reg.count() == 1
    reg.release()
    assert reg.count() == 0 and not list(tmp_path.iterdir())


def test_thread_share_takes_its_share_and_gives_cores_up_at_the_next_epoch(tmp_path):
    before = torch.get_num_threads()
    try:
        share = threads.ThreadShare("auto", cores=2, registry=TrainingRegistry(tmp_path))
        assert (share.jobs, share.threads, torch.get_num_threads()) == (1, 2, 2)  # alone: every core
        other, = _holders(tmp_path)  # a second training starts beside it
        try:
            assert share.threads == 2  # unchanged until the next epoch starts
            share.on_train_epoch_start(None, None)
            assert (share.jobs, share.threads, torch.get_num_threads()) == (2, 1, 1)
            third = threads.ThreadShare(2, cores=2, registry=TrainingRegistry(tmp_path))
            assert (third.jobs, third.threads) == (3, 1)  # threads=2 given: still 1 of the 2 cores
            third.registry.release()
        finally:
            other.kill()
            other.wait()
        share.on_train_epoch_start(None, None)
        assert (share.jobs, share.threads) == (1, 2)  # alone again
        three = threads.ThreadShare("auto", cores=6, declared_jobs=3, registry=TrainingRegistry(tmp_path / "x"))
        assert (three.jobs, three.threads) == (3, 2)  # a launcher's 3 jobs count before they register
    finally:
        torch.set_num_threads(before)


def test_openmp_spin_count_is_set_before_torch_loads(tmp_path):
    code = ("import os, sys, embodied_tactile.run.threadenv; "
            "print('torch' in sys.modules, os.environ.get('GOMP_SPINCOUNT'), os.environ.get('OMP_WAIT_POLICY'))")
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env["PYTHONPATH"] = str(REPO / "src")

    def run(**extra: str) -> list[str]:
        return subprocess.run([sys.executable, "-c", code], env={**env, **extra}, capture_output=True, text=True,
                              check=True).stdout.split()

    assert run() == ["False", threadenv.SPIN_COUNT, "None"]
    assert run(OMP_WAIT_POLICY="PASSIVE") == ["False", "None", "PASSIVE"]  # the user's settings are kept
    assert run(GOMP_SPINCOUNT="0") == ["False", "0", "None"]
    # train.py imports it before anything that loads torch (hydra, lightning, torch, the package's modules)
    imports = [n for n in ast.parse((REPO / "train.py").read_text()).body if isinstance(n, (ast.Import, ast.ImportFrom))]
    names = [a.name if isinstance(n, ast.Import) else n.module for n in imports for a in n.names]
    first = next(i for i, name in enumerate(names) if name not in ("__future__", "logging", "sys", "time"))
    assert names[first] == "embodied_tactile.run.threadenv"
