"""How a training shows its progress: plain lines under launchers and without a terminal
(:class:`PlainProgress`), Lightning's progress bar otherwise (:func:`use_plain_progress`)."""

from __future__ import annotations

import logging
import sys
import time

import lightning as L

log = logging.getLogger(__name__)


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


__all__ = ["PlainProgress", "use_plain_progress"]
