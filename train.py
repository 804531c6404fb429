"""Train a Latent Filter on one scene (modality x skin x primitive).

    python train.py                                            # embedded default (simulator)
    python train.py modality=multi_l skin=soft primitive=sliding
    python train.py -m sweep=ablation                          # the paper's 24 models
    python train.py experiment=paper                           # the paper's lr / batch / epochs

Each run folder (logs/train/runs/<time> or the multirun sub-folder named after its
overrides) holds the resolved config, checkpoints/last.ckpt and the best checkpoint,
metrics.json, split.json and provenance.json (git commit, package versions, raw data digests).
Starting again with the same folder (hydra.run.dir=...) resumes from last.ckpt; the folder
is locked while a training runs, and a restart with settings that shape the model or the
data differently is refused (embodied_tactile.runfolder). Exit codes: 0 finished, 2 bad
setting or refused start, 130 / 143 SIGINT / SIGTERM (last.ckpt saved, "interrupted"),
74 a checkpoint could not be written, 1 any other failure.
"""

from __future__ import annotations

import logging
import sys
import time

import embodied_tactile.run.threadenv  # noqa: F401  OMP_WAIT_POLICY=PASSIVE before torch loads OpenMP
import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

import embodied_tactile.run.config  # noqa: F401  registers the typed configs before Hydra composes
from embodied_tactile import cli
from embodied_tactile.run import quiet, runfolder, runtime, settings, summary
from embodied_tactile.run.jsonio import read_json, write_json

log = logging.getLogger("train")


@hydra.main(version_base="1.3", config_path="configs", config_name="train")
def main(cfg: DictConfig) -> float | None:
    quiet.silence_third_party()
    run_dir = HydraConfig.get().runtime.output_dir
    try:  # one training per folder; a restart continues the same model and data (done at entry for single runs)
        runfolder.claim(cfg, run_dir)
    except runfolder.RunFolderError as err:
        cli.fail(err)
    try:  # cli.EntryCallback checked before the folder existed; values swept with -m reach only the job
        settings.check_train_config(cfg)
    except settings.SettingsError as err:
        if not runfolder.holds_run(run_dir):  # a finished run's metrics.json is never rewritten by a refused start
            write_json(f"{run_dir}/metrics.json", {"status": "failed", "error": f"bad setting: {err}", "run_dir": run_dir})
        cli.fail(err)
    stop = runfolder.StopSignals().install()  # SIGTERM / SIGINT: last.ckpt, "interrupted", exit 143 / 130
    resuming = runfolder.holds_run(run_dir)  # its config and provenance are rewritten once its data are checked
    trained_on = read_json(f"{run_dir}/provenance.json").get("raw_data") if resuming else None
    if not resuming:
        runtime.save_provenance(cfg, run_dir)
    L.seed_everything(cfg.seed, workers=True)
    threads = runtime.configure_threads(cfg)  # this training's share of the cores, again at every epoch
    log.info("torch threads: %d (threads=%s, %d training(s) on this machine)", threads.threads,
             cfg.get("threads", "auto"), threads.jobs)
    torch.set_float32_matmul_precision("high")

    datamodule: L.LightningDataModule = instantiate(cfg.data)
    model: L.LightningModule = instantiate(cfg.model)
    if runtime.configure_compile(cfg, model):
        log.info("compile_convs: the conv encoders / decoders of training steps run through torch.compile")

    callbacks = [runtime.HandOverStatistics()]  # the training split's statistics, from the data to the model
    callbacks += [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
    loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values() if c is not None]
    if not loggers:  # logger=none: Lightning refuses a LearningRateMonitor without a logger
        from lightning.pytorch.callbacks import LearningRateMonitor

        callbacks = [c for c in callbacks if not isinstance(c, LearningRateMonitor)]
    callbacks.append(stop)
    plain = runtime.use_plain_progress(cfg.plain_progress)
    if plain:
        callbacks.append(runtime.PlainProgress())
    elif cfg.trainer.get("enable_progress_bar", True):
        from lightning.pytorch.callbacks import RichProgressBar

        callbacks.append(RichProgressBar())
    callbacks.append(threads)  # re-counts the trainings on the machine at every epoch
    trainer: L.Trainer = instantiate(
        cfg.trainer, callbacks=callbacks, logger=loggers or False,
        plugins=[runfolder.AtomicCheckpointIO()],  # temporary file, fsync, rename: a *.ckpt is always whole
        enable_progress_bar=bool(cfg.trainer.get("enable_progress_bar", True)) and not plain,
    )

    ckpt_path = runtime.find_resume_checkpoint(run_dir) if cfg.resume else None
    if ckpt_path:
        log.info("resuming from %s", ckpt_path)
    runtime.continue_logs(loggers, ckpt_path)  # csv/metrics.csv continues from that step

    metrics: dict = {"status": "running", "run_dir": run_dir, "resumed_from": str(ckpt_path) if ckpt_path else None}
    t0 = time.perf_counter()
    try:
        # data preparation is timed apart from training: prepare_data is the preparation stage
        # (embodied_tactile.data.prepare: simulation, caches, trial listing), setup splits and
        # loads; the DataModule does each once, so fit() below does not repeat it
        datamodule.prepare_data()
        if resuming and trainer.global_rank == 0:  # a resume continues on the data the run was trained on
            changed = runtime.data_changes(trained_on, runtime.data_identity(getattr(datamodule, "cache_files", {})))
            if changed:
                raise runfolder.RunFolderError(
                    f"run folder {run_dir} was trained on other data: {'; '.join(changed)}; refusing to resume it "
                    "on these (give another hydra.run.dir for a new run)")
            runtime.save_provenance(cfg, run_dir)
        datamodule.setup("fit")
        metrics["data_prepare_s"] = time.perf_counter() - t0
        if trainer.global_rank == 0 and getattr(datamodule, "cache_files", None):  # evaluate.py compares with it
            runtime.record_data_identity(run_dir, datamodule.cache_files)
        t0 = time.perf_counter()
        trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path)
    except runfolder.RunFolderError as err:  # refused before anything of the run was rewritten
        cli.fail(err)
    except BaseException as err:  # any failure: the folder must not look like a finished run
        status = "interrupted" if stop.received is not None else "failed"
        metrics.update(status=status, error=str(err) or type(err).__name__, error_type=type(err).__name__,
                       train_wall_s=time.perf_counter() - t0)
        if stop.received is not None:
            metrics["stopped_by"] = stop.name
        write_json(f"{run_dir}/metrics.json", metrics)
        if isinstance(err, FloatingPointError):  # the model's non-finite-loss guard: name step and term
            log.error("training stopped: %s (last good checkpoint kept in %s/checkpoints)", err, run_dir)
        if stop.received is not None:
            log.error("%s before training began: nothing new to save; exit %d", stop.name, stop.exit_code())
            raise SystemExit(stop.exit_code()) from None
        if isinstance(err, runfolder.CheckpointWriteError):  # disk full: one line, the previous file kept
            print(f"train.py: error: {err}", file=sys.stderr)
            raise SystemExit(runfolder.EXIT_CHECKPOINT_WRITE) from None
        raise
    metrics["train_wall_s"] = time.perf_counter() - t0
    stop.defer()
    if stop.received is not None:  # stopped between steps: the state of this step is the run's last.ckpt
        last = f"{run_dir}/checkpoints/last.ckpt"
        trainer.save_checkpoint(last)
        metrics.update(status="interrupted", stopped_by=stop.name, last_checkpoint=last, step=trainer.global_step)
        write_json(f"{run_dir}/metrics.json", metrics)
        log.error("%s: stopped at step %d, %s saved; start the same command again to resume; exit %d",
                  stop.name, trainer.global_step, last, stop.exit_code())
        raise SystemExit(stop.exit_code())
    metrics["fit_metrics"] = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
    # the run's NMSE: the KRR callback's final alignment (evaluate.py's settings, final weights)
    metrics["krr_final"] = next((c.final for c in callbacks if getattr(c, "final", None)), None)

    if cfg.validate_at_end and not cfg.trainer.get("fast_dev_run"):
        # validation trials (training objects), final weights; recorded in metrics.json only, not
        # as one more csv row that would carry Lightning's post-fit epoch number
        loggers_fit, trainer.loggers = trainer.loggers, []
        try:
            val = trainer.validate(model, datamodule=datamodule, verbose=False)
        finally:
            trainer.loggers = loggers_fit
        metrics["final_val"] = {k: float(v) for k, v in (val[0] if val else {}).items()}
        log.info("validation ELBO per sequence (final weights): %.4g", metrics["final_val"].get("val/elbo", float("nan")))
    for cb in trainer.checkpoint_callbacks:  # the monitored one keeps the best, the unmonitored one last.ckpt
        key = "best_checkpoint" if getattr(cb, "monitor", None) else "last_checkpoint"
        metrics[key] = (cb.best_model_path if key == "best_checkpoint" else cb.last_model_path or cb.best_model_path) or None
    metrics["data"] = datamodule.describe() if hasattr(datamodule, "describe") else {}
    metrics["peak_rss_bytes"] = runtime.peak_rss_bytes()
    metrics["status"] = "interrupted" if trainer.interrupted or stop.received is not None else "finished"
    if trainer.global_rank == 0:
        write_json(f"{run_dir}/metrics.json", metrics)
        log.info("run folder: %s", run_dir)
        if HydraConfig.get().mode != RunMode.MULTIRUN:  # a multirun ends with cli.EntryCallback's summary
            summary.print_run_summary(run_dir, metrics)
    runfolder.release(run_dir)  # the folder is free once its run is written (a multirun's next job goes on in this process)

    for lg in loggers:  # one wandb run per multirun job
        if lg.__class__.__name__ == "WandbLogger":
            import wandb

            wandb.finish()
    if stop.received is not None:  # a signal after the training steps (final validation): still not a success
        raise SystemExit(stop.exit_code())
    return metrics.get("final_val", {}).get("val/elbo")


if __name__ == "__main__":
    cli.check_typed_overrides(sys.argv[1:])  # one line for a value of the wrong type, before Hydra merges it
    sys.exit(main())
