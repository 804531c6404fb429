"""train.py's recipe as functions that tests, notebooks and experiment scripts call
in-process: :func:`compose` (train.py's config with overrides, for a given run folder),
:func:`train` (one training in a run folder) and :func:`run_job` (train.py's Hydra job: a
multirun job's failure is recorded in its folder and the sweep goes on). train.py's docstring says what a
run folder holds and what each exit status means."""

from __future__ import annotations

import logging

import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig

from embodied_tactile.run import quiet, runfolder, summary
from embodied_tactile.run.compile_convs import configure_compile
from embodied_tactile.run.handover import HandOverStatistics
from embodied_tactile.jsonio import read_json
from embodied_tactile.run.lifecycle import RunFolderLifecycle
from embodied_tactile.run.progress import PlainProgress, use_plain_progress
from embodied_tactile.run.threads import configure_threads

log = logging.getLogger("train")


def _in_multirun() -> bool:
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def run_job(cfg: DictConfig) -> float | None:
    """train.py's Hydra job: :func:`train` in the job's output folder; a multirun job's failure is
    recorded and the sweep goes on."""
    quiet.silence_third_party()
    run_dir = HydraConfig.get().runtime.output_dir
    if not _in_multirun():
        return train(cfg, run_dir)
    # a multirun job: a failure is recorded (<job>/.hydra/outcome.json) and the sweep goes on; it ends
    # with a table of every job's status and reason, exit 1 when one did not finish (cli.EntryCallback)
    try:
        result = train(cfg, run_dir)
    except SystemExit as done:
        if done.code in (0, None):
            return None
        if done.code in (130, 143):  # a stop signal stops the sweep (exit 128 + signal: a scheduler requeues it)
            summary.record_outcome(run_dir, "interrupted", f"stopped by {'SIGINT' if done.code == 130 else 'SIGTERM'}")
            raise
        summary.record_outcome(run_dir, "refused" if done.code == 2 else "failed",
                               getattr(done, "message", "") or f"exit {done.code}")
        return None
    except Exception as err:  # noqa: BLE001 -- its traceback in the job's log, its reason in the table
        log.exception("job failed: %s", run_dir)
        summary.record_outcome(run_dir, "failed", f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}")
        return None
    finally:
        runfolder.release(run_dir)  # the next job goes on in this process
    status = read_json(f"{run_dir}/metrics.json").get("status", "unknown")
    summary.record_outcome(run_dir, status, "" if status == "finished" else read_json(f"{run_dir}/metrics.json").get("error", ""))
    return result


def compose(overrides: list[str], run_dir: str) -> DictConfig:
    """configs/train.yaml composed with ``overrides`` as train.py would for a run in
    ``run_dir`` (``${hydra:runtime.output_dir}`` resolves to it: this process's Hydra state
    is set to the job's), without the ``hydra`` node: :func:`train`'s ``cfg``."""
    from omegaconf import open_dict

    from embodied_tactile.run.config import compose as compose_config

    cfg = compose_config([*overrides, f"hydra.run.dir={run_dir}"], return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(run_dir)
    HydraConfig.instance().set_config(cfg)
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg


def train(cfg: DictConfig, run_dir: str | None = None) -> float | None:
    """One training in ``run_dir`` (default: the Hydra job's output folder), train.py's recipe
    top to bottom: instantiate, fit, final read-out -> the final validation ELBO (None when
    nothing was trained). The run folder's lifecycle around it (lock, settings, stop signals,
    provenance, resume, metrics.json) is :class:`~embodied_tactile.run.lifecycle.RunFolderLifecycle`'s."""
    run_dir = run_dir if run_dir is not None else HydraConfig.get().runtime.output_dir
    with RunFolderLifecycle(cfg, run_dir) as run:
        if run.finished:  # a multirun job whose run is finished (a single run stops at entry): nothing to train
            return None
        L.seed_everything(cfg.seed, workers=True)
        share = configure_threads(cfg)  # this training's share of the cores, again at every epoch
        log.info("torch threads: %d (threads=%s, %d training(s) on this machine)", share.threads,
                 cfg.get("threads", "auto"), share.jobs)
        torch.set_float32_matmul_precision("high")

        datamodule: L.LightningDataModule = instantiate(cfg.data)
        model: L.LightningModule = instantiate(cfg.model)
        if configure_compile(cfg, model):
            log.info("compile_convs: the conv encoders / decoders of training steps run through torch.compile")
        configured = [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
        loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values() if c is not None]
        plain = use_plain_progress(cfg.plain_progress)
        callbacks = [run.stop,  # its hooks first: a stop is saved before any other callback's work
                     HandOverStatistics(),  # the training split's statistics, from the data to the model
                     run.checkpoints,  # each checkpoint stores its own val/elbo and the run's fit time
                     *usable_with(configured, loggers), *progress_callbacks(cfg, plain),
                     share]  # re-counts the trainings on the machine at every epoch
        trainer: L.Trainer = instantiate(
            cfg.trainer, callbacks=callbacks, logger=loggers or False,
            plugins=[runfolder.AtomicCheckpointIO()],  # temporary file, fsync, rename: a *.ckpt is always whole
            enable_progress_bar=bool(cfg.trainer.get("enable_progress_bar", True)) and not plain)

        run.prepare(datamodule, trainer, loggers)
        run.fit(trainer, model, datamodule, callbacks)
        final_val = validate_final_weights(cfg, trainer, model, datamodule)
        run.finish(trainer, datamodule, callbacks, final_val, in_multirun=_in_multirun())
    for lg in loggers:  # one wandb run per multirun job
        if lg.__class__.__name__ == "WandbLogger":
            import wandb

            wandb.finish()
    if run.stop.received is not None:  # a signal after the training steps (final validation): still not a success
        raise SystemExit(run.stop.exit_code())
    return (final_val or {}).get("val/elbo")


def usable_with(callbacks: list, loggers: list) -> list:
    """The config's callbacks that run with these loggers: without a logger (``logger=none``)
    no LearningRateMonitor, which Lightning refuses then."""
    if loggers:
        return callbacks
    from lightning.pytorch.callbacks import LearningRateMonitor

    return [c for c in callbacks if not isinstance(c, LearningRateMonitor)]


def progress_callbacks(cfg: DictConfig, plain: bool) -> list:
    """Plain progress lines, or Lightning's rich progress bar where the trainer shows one."""
    if plain:
        return [PlainProgress()]
    if cfg.trainer.get("enable_progress_bar", True):
        from lightning.pytorch.callbacks import RichProgressBar

        return [RichProgressBar()]
    return []


def validate_final_weights(cfg: DictConfig, trainer: L.Trainer, model: L.LightningModule,
                           datamodule: L.LightningDataModule) -> dict | None:
    """The held-out ELBO of the final weights on the validation trials (``validate_at_end``;
    None without it): recorded in metrics.json only, not as one more csv row that would carry
    Lightning's post-fit epoch number."""
    if not cfg.validate_at_end or cfg.trainer.get("fast_dev_run"):
        return None
    loggers_fit, trainer.loggers = trainer.loggers, []
    try:
        val = trainer.validate(model, datamodule=datamodule, verbose=False)
    finally:
        trainer.loggers = loggers_fit
    final_val = {k: float(v) for k, v in (val[0] if val else {}).items()}
    log.info("validation ELBO per sequence (final weights): %.4g", final_val.get("val/elbo", float("nan")))
    return final_val


__all__ = ["compose", "progress_callbacks", "run_job", "train", "usable_with", "validate_final_weights"]
