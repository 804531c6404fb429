"""Run-folder plumbing shared by train.py and evaluate.py: provenance, resume, progress.

A run folder holds: ``.hydra/`` (Hydra's composed config and overrides),
``config_resolved.yaml`` (every interpolation resolved), ``checkpoints/last.ckpt`` and the
best checkpoint, ``metrics.json``, ``split.json``, ``provenance.json`` (git commit, dirty
flag, package versions, command line) and ``git.diff`` when the tree was dirty.
"""

from __future__ import annotations

import importlib.metadata as md
import json
import logging
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Mapping

import lightning as L
from omegaconf import DictConfig, OmegaConf

from embodied_tactile.jsonio import write_json

log = logging.getLogger(__name__)

PACKAGES = (
    "embodied-tactile", "torch", "lightning", "hydra-core", "omegaconf", "torchmetrics", "librosa",
    "h5py", "numpy", "scipy", "scikit-learn", "wandb", "pyserial", "umap-learn",
)


def package_versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {}
    for name in PACKAGES:
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = None
    return out


def git_state(repo: str | os.PathLike | None = None) -> dict[str, Any]:
    """Commit, dirty flag and diff of the source tree (None where git is unavailable)."""
    repo = Path(repo or Path(__file__).resolve().parents[2])

    def git(*args: str) -> str | None:
        try:
            return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=10, check=True).stdout
        except (OSError, subprocess.SubprocessError):
            return None

    commit = git("rev-parse", "HEAD")
    diff = git("diff", "HEAD")
    return {"commit": commit.strip() if commit else None, "dirty": bool(diff), "diff": diff or ""}


def save_provenance(cfg: DictConfig, run_dir: str | os.PathLike) -> None:
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config_resolved.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    git = git_state()
    if git["diff"]:
        (run_dir / "git.diff").write_text(git["diff"])
    write_json(
        run_dir / "provenance.json",
        {
            "git_commit": git["commit"],
            "git_dirty": git["dirty"],
            "packages": package_versions(),
            "python": sys.version,
            "platform": platform.platform(),
            "argv": sys.argv,
            "cwd": os.getcwd(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        },
    )


def peak_rss_bytes() -> int:
    """Peak resident memory of this process and its finished children (Linux: KiB units)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return int(max(own, children) * 1024)


def find_resume_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    last = Path(run_dir) / "checkpoints" / "last.ckpt"
    return last if last.exists() else None


def use_plain_progress(setting: str | bool) -> bool:
    """Plain log lines under launchers (multirun) or without a terminal; bars otherwise."""
    if isinstance(setting, bool):
        return setting
    if setting != "auto":
        return str(setting).lower() in ("1", "true", "yes", "plain")
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
            return True
    except (ImportError, ValueError):
        pass
    return not sys.stdout.isatty()


class PlainProgress(L.Callback):
    """One log line per epoch with the logged losses and the elapsed wall time."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.global_rank != 0:
            return
        m = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
        keys = [k for k in ("train/loss", "train/nll", "train/kl_z", "train/kl_y", "val/elbo", "krr/nmse_overall") if k in m]
        body = "  ".join(f"{k}={m[k]:.4g}" for k in keys)
        log.info("epoch %d/%d  step %d  %s  (%.0f s)", trainer.current_epoch + 1, trainer.max_epochs, trainer.global_step, body, time.perf_counter() - self.t0)
