"""A training's share of the machine's cores: the cores available, the trainings running on
this machine (:class:`~embodied_tactile.run.threadenv.TrainingRegistry`), the share each one
takes (:func:`thread_budget`), re-counted at every epoch (:class:`ThreadShare`, which
:func:`configure_threads` starts). Threads are set by
:func:`embodied_tactile.run.threadenv.set_threads` alone."""

from __future__ import annotations

import logging
import os
from typing import Any

import lightning as L
from omegaconf import DictConfig, OmegaConf

from embodied_tactile.run.threadenv import TrainingRegistry, set_threads

log = logging.getLogger(__name__)


def available_cores() -> int:
    """CPU cores this process may run on (affinity-aware where the OS tells)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return max(1, os.cpu_count() or 1)


def concurrent_jobs(launcher_n_jobs: Any = None, processes_per_node: Any = 1, cores: int | None = None) -> int:
    """How many training processes share this machine: the joblib launcher's ``n_jobs``
    (joblib's convention: -1 = one per core, -2 = all but one, ...) times the DDP processes
    per node. Anything unset counts as 1."""
    cores = available_cores() if cores is None else int(cores)
    jobs = 1
    if launcher_n_jobs not in (None, "", 0):
        n = int(launcher_n_jobs)
        jobs = n if n > 0 else max(1, cores + 1 + n)
    try:
        procs = max(1, int(processes_per_node))
    except (TypeError, ValueError):  # devices: "auto" and the like
        procs = 1
    return max(1, jobs * procs)


def thread_budget(setting: Any, jobs: int, cores: int | None = None) -> int:
    """Threads per training: its fair share of the cores, ``max(1, cores // jobs)`` for
    ``jobs`` trainings sharing the machine, and no more than ``setting`` when that is a
    positive integer (``auto`` / null: the share alone). A setting is a ceiling, never a
    demand: two trainings at 2 threads each on 2 cores ran 4x slower than at 1 thread each
    (oversubscription), whatever threads each had been given."""
    cores = available_cores() if cores is None else int(cores)
    share = max(1, cores // max(1, int(jobs)))
    if setting in (None, "auto", "null"):
        return share
    n = int(setting)
    if n < 1:
        raise ValueError(f"threads must be a positive integer or 'auto', got {setting!r}")
    return min(n, share)


#: the registry of this process (train.py registers through :func:`configure_threads`)
REGISTRY = TrainingRegistry()


class ThreadShare(L.Callback):
    """A training's threads: its fair share of the cores among the trainings on this machine
    (:func:`thread_budget` of ``setting`` and ``max(declared jobs, live trainings)``),
    applied when built and again at every training epoch's start, so that a training
    started beside a running one takes half the cores at once and the running one gives
    them up at its next epoch. Registers this process in ``registry``."""

    def __init__(self, setting: Any = "auto", declared_jobs: int = 1, cores: int | None = None,
                 registry: TrainingRegistry | None = None) -> None:
        self.setting = setting
        self.declared_jobs = max(1, int(declared_jobs))
        self.cores = available_cores() if cores is None else int(cores)
        self.registry = REGISTRY if registry is None else registry
        self.registry.register()
        self.jobs = 1
        self.threads = 0
        self.apply()

    def decide(self) -> tuple[int, int]:
        """(trainings sharing the machine, threads for this one), from a fresh count."""
        jobs = max(self.declared_jobs, self.registry.count())
        return jobs, thread_budget(self.setting, jobs, self.cores)

    def apply(self) -> int:
        """Count again and set the threads where the share changed; the threads."""
        self.jobs, n = self.decide()
        if n != self.threads:
            if self.threads:
                log.info("threads %d -> %d (%d training(s) on this machine)", self.threads, n, self.jobs)
            self.threads = set_threads(n)
        return self.threads

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.apply()


def configure_threads(cfg: DictConfig, registry: TrainingRegistry | None = None) -> ThreadShare:
    """Threads for a train.py process from ``cfg.threads`` (``auto`` or a ceiling) and the
    trainings sharing the machine: those registered live (:class:`TrainingRegistry`), at
    least the concurrent jobs this process knows of (the Hydra launcher's n_jobs x the
    trainer's DDP devices per node). The returned :class:`ThreadShare` is a callback that
    keeps the share up to date at every epoch."""
    n_jobs = None
    try:
        from hydra.core.hydra_config import HydraConfig

        hc = HydraConfig.get()
        if hc.mode is not None and str(hc.mode).endswith("MULTIRUN"):
            n_jobs = OmegaConf.select(hc, "launcher.n_jobs", default=None)
    except (ImportError, ValueError):  # not inside a Hydra app
        pass
    trainer = cfg.get("trainer") or {}
    procs = trainer.get("devices", 1) if "ddp" in str(trainer.get("strategy", "")) else 1
    return ThreadShare(cfg.get("threads", "auto"), concurrent_jobs(n_jobs, procs), registry=registry)


__all__ = ["REGISTRY", "ThreadShare", "available_cores", "concurrent_jobs", "configure_threads", "thread_budget"]
