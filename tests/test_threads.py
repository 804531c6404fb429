"""Thread policy: one place divides the cores among concurrent jobs."""

from __future__ import annotations

import os

import pytest
import torch
from omegaconf import OmegaConf

from embodied_tactile import runtime


def test_concurrent_jobs_follows_launcher_and_ddp():
    assert runtime.concurrent_jobs(None, 1, cores=8) == 1
    assert runtime.concurrent_jobs(2, 1, cores=8) == 2
    assert runtime.concurrent_jobs(-1, 1, cores=8) == 8  # joblib: one job per core
    assert runtime.concurrent_jobs(-2, 1, cores=8) == 7  # all but one
    assert runtime.concurrent_jobs(2, 2, cores=8) == 4  # 2 launcher jobs x 2 DDP processes
    assert runtime.concurrent_jobs(None, "auto", cores=8) == 1


def test_thread_budget_divides_cores_and_respects_a_setting():
    assert runtime.thread_budget("auto", jobs=1, cores=2) == 2
    assert runtime.thread_budget("auto", jobs=2, cores=2) == 1
    assert runtime.thread_budget(None, jobs=3, cores=2) == 1  # never 0
    assert runtime.thread_budget("auto", jobs=2, cores=16) == 8
    assert runtime.thread_budget(3, jobs=2, cores=2) == 3  # an explicit setting wins
    with pytest.raises(ValueError, match="positive integer or 'auto'"):
        runtime.thread_budget(0, jobs=1)


def test_configure_threads_sets_torch_and_the_environment(monkeypatch):
    before = torch.get_num_threads()
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        monkeypatch.setenv(var, "99")
    try:
        cfg = OmegaConf.create({"threads": "auto", "trainer": {"strategy": "ddp", "devices": 2}})
        n = runtime.configure_threads(cfg)  # outside a Hydra app: no launcher; DDP: 2 processes
        assert n == max(1, runtime.available_cores() // 2)
        assert torch.get_num_threads() == n
        assert os.environ["OMP_NUM_THREADS"] == os.environ["MKL_NUM_THREADS"] == str(n)
        assert runtime.configure_threads(OmegaConf.create({"threads": 1})) == 1
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
