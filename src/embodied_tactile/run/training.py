"""train.py's recipe as functions that tests, notebooks and experiment scripts call
in-process: :func:`compose` (train.py's config with overrides, for a given run folder),
:func:`train` (one training in a run folder) and :func:`run_job` (train.py's Hydra job: a
multirun job's failure is recorded in its folder and the sweep goes on). train.py's docstring says what a
run folder holds and what each exit status means."""

from __future__ import annotations

import logging
import sys
import time

import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig

from embodied_tactile.data.datamodule import ConstantChannelError
from embodied_tactile.run import quiet, runfolder, runtime, settings, summary
from embodied_tactile.run.jsonio import read_json, write_json

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
    from hydra import compose as hydra_compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import open_dict

    import embodied_tactile.run.config  # noqa: F401  registers the typed configs
    from embodied_tactile.run.paths import config_dir

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        cfg = hydra_compose(config_name="train", return_hydra_config=True,
                            overrides=[*overrides, f"hydra.run.dir={run_dir}"])
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(run_dir)
    HydraConfig.instance().set_config(cfg)
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg


def train(cfg: DictConfig, run_dir: str | None = None) -> float | None:
    """One training in ``run_dir`` (default: the Hydra job's output folder), train.py's recipe
    top to bottom -> the final validation ELBO (None when nothing was trained)."""
    if run_dir is None:
        run_dir = HydraConfig.get().runtime.output_dir
    try:  # one training per folder; a restart continues the same model and data (done at entry for single runs)
        runfolder.claim(cfg, run_dir)
    except runfolder.RunFolderError as err:
        settings.fail(err)
    except runfolder.RunFinished as done:  # a multirun job (a single run stops at entry): nothing to train
        print(f"train.py: {done}", flush=True)  # not logged: the job's train.log stays as it was
        return None
    try:  # cli.EntryCallback checked before the folder existed; values swept with -m reach only the job
        settings.check_train_config(cfg)
    except settings.SettingsError as err:  # a folder holding a run is never rewritten by a refused start
        runfolder.refuse(run_dir, err, runfolder.holds_run(run_dir))
    # SIGTERM / SIGINT: last.ckpt after the step under way (no validation nor KRR check after it), "interrupted", exit 143 / 130
    stop = runfolder.StopSignals(last_path=f"{run_dir}/checkpoints/last.ckpt").install()
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
    callbacks.append(runfolder.FolderCheckpoints())  # each checkpoint stores its own val/elbo; a moved folder resumes as it was
    callbacks += [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
    loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values() if c is not None]
    if not loggers:  # logger=none: Lightning refuses a LearningRateMonitor without a logger
        from lightning.pytorch.callbacks import LearningRateMonitor

        callbacks = [c for c in callbacks if not isinstance(c, LearningRateMonitor)]
    callbacks.insert(0, stop)  # its hooks first: a stop is saved before any other callback's work
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

    # paths relative to the run folder: a moved or copied folder names its own files
    metrics: dict = {"status": "running", "resumed_from": runfolder.in_folder(run_dir, ckpt_path)}
    t0 = time.perf_counter()
    try:
        # data preparation is timed apart from training: prepare_data is the preparation stage
        # (embodied_tactile.data.prepare: simulation, caches, trial listing), setup splits and
        # loads; the DataModule does each once, so fit() below does not repeat it
        datamodule.prepare_data()
        if resuming and trainer.global_rank == 0:  # a resume continues on the data the run was trained on
            changed = runtime.data_changes(trained_on, runtime.data_identity(
                getattr(datamodule, "cache_files", {}), runtime.trial_digests(datamodule)))
            if changed:
                raise runfolder.RunFolderError(
                    f"run folder {run_dir} was trained on other data: {'; '.join(changed)}; refusing to resume it "
                    "on these (give another hydra.run.dir for a new run)")
        datamodule.setup("fit")
        if trainer.global_rank == 0:  # the split is the run's: a resume on another is refused, naming the trials
            runfolder.keep_split(run_dir, datamodule, resuming)
        if resuming and trainer.global_rank == 0:
            runtime.save_provenance(cfg, run_dir)
        metrics["data_prepare_s"] = time.perf_counter() - t0
        if trainer.global_rank == 0 and getattr(datamodule, "cache_files", None):  # evaluate.py compares with it
            split = runfolder.served_split(datamodule)  # per trial of the run's split: others may change freely
            runtime.record_data_identity(run_dir, datamodule.cache_files, runtime.trial_digests(datamodule),
                                         [n for side in (split or {}).values() for n in side] if split else None)
        if trainer.global_rank == 0:  # from here the folder's run changes: a kill -9 leaves "running" (evaluate.py: killed)
            write_json(f"{run_dir}/metrics.json", metrics)
        t0 = time.perf_counter()
        trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path)
        runfolder.finish_fit(trainer, model, callbacks, stop)  # a run resumed at its own length: its final read-out
    except (runfolder.RunFolderError, ConstantChannelError) as err:  # refused before anything of the run was rewritten
        runfolder.refuse(run_dir, err, resuming)  # a dead channel: one line naming channel, layer, files
    except BaseException as err:  # any failure: the folder must not look like a finished run
        stop.settle()  # a signal in the final read-out: last.ckpt holds the last step's weights
        status = "interrupted" if stop.received is not None else "failed"
        metrics.update(status=status, error=str(err) or type(err).__name__, error_type=type(err).__name__,
                       train_wall_s=time.perf_counter() - t0)
        if stop.received is not None:
            metrics.update(stopped_by=stop.name, stopped_in=stop.phase, final_readout=False)
        if stop.saved is not None:
            metrics.update(last_checkpoint=runfolder.in_folder(run_dir, stop.saved), step=stop.step)
        write_json(f"{run_dir}/metrics.json", metrics)
        if isinstance(err, FloatingPointError):  # the model's non-finite-loss guard: name step and term
            log.error("training stopped: %s (last good checkpoint kept in %s/checkpoints)", err, run_dir)
        if stop.saved is not None:
            log.error("%s (%s): stopped after the optimiser step of step %d, %s saved (no validation, KRR check or "
                      "final read-out after the signal); start the same command again to resume; exit %d", stop.name,
                      stop.phase, stop.step, stop.saved, stop.exit_code())
            raise SystemExit(stop.exit_code()) from None
        if stop.received is not None:
            log.error("%s (%s): no training step of this start to save; exit %d", stop.name, stop.phase,
                      stop.exit_code())
            raise SystemExit(stop.exit_code()) from None
        if isinstance(err, runfolder.CheckpointWriteError):  # disk full: one line, the previous file kept
            print(f"train.py: error: {err}", file=sys.stderr)
            raise settings.Exit(runfolder.EXIT_CHECKPOINT_WRITE, str(err)) from None
        raise
    metrics["train_wall_s"] = time.perf_counter() - t0
    stop.defer()
    if stop.received is not None:  # stopped between steps: the state of this step is the run's last.ckpt
        last = f"{run_dir}/checkpoints/last.ckpt"
        trainer.save_checkpoint(last)
        metrics.update(status="interrupted", stopped_by=stop.name, stopped_in=stop.phase,
                       last_checkpoint=runfolder.in_folder(run_dir, last),
                       step=trainer.global_step, final_readout=any(getattr(c, "final", None) for c in callbacks))
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
        path = (cb.best_model_path if key == "best_checkpoint" else cb.last_model_path or cb.best_model_path) or None
        metrics[key] = runfolder.in_folder(run_dir, path)
    best = runfolder.best_checkpoint(run_dir)  # over every checkpoint in the folder, by the value each one stores
    if best is not None:
        metrics["best_checkpoint"] = runfolder.in_folder(run_dir, best[0])
        metrics["best_value"] = {best[1]["key"]: best[1]["value"]}
    metrics["data"] = datamodule.describe() if hasattr(datamodule, "describe") else {}
    metrics["peak_rss_bytes"] = runtime.peak_rss_bytes()
    # finished: its length reached and its final KRR alignment (callbacks.krr_alignment) made
    metrics["status"], metrics["final_readout"] = runfolder.run_outcome(trainer, callbacks, stop)
    if trainer.global_rank == 0:
        write_json(f"{run_dir}/metrics.json", metrics)
        log.info("run folder: %s", run_dir)
        if not _in_multirun():  # a multirun ends with cli.EntryCallback's summary
            summary.print_run_summary(run_dir, metrics)
    runfolder.release(run_dir)  # the folder is free once its run is written (a multirun's next job goes on in this process)

    for lg in loggers:  # one wandb run per multirun job
        if lg.__class__.__name__ == "WandbLogger":
            import wandb

            wandb.finish()
    if stop.received is not None:  # a signal after the training steps (final validation): still not a success
        raise SystemExit(stop.exit_code())
    return metrics.get("final_val", {}).get("val/elbo")


__all__ = ["compose", "run_job", "train"]
