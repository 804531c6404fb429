"""The run folder's lifecycle around one training: :class:`RunFolderLifecycle`, the context
manager inside which :func:`embodied_tactile.run.training.train` instantiates and fits.

In order: the folder is claimed (its lock; a restart continues the same run: settings, split,
length and checkpoint checked, :func:`~embodied_tactile.run.runfolder.claim`), the settings
checked, the stop signals installed (SIGINT / SIGTERM: ``last.ckpt`` after the step under way,
exit 130 / 143), a new run's provenance written; then the data are prepared and checked
against the run's (a resume continues on the data and split it was trained on), the folder's
``metrics.json`` says ``running``, the fit runs from the checkpoint it resumes; at the end
``metrics.json`` holds the outcome and the folder is released. A failure leaves the folder
saying so: a refused start is one line and exit 2 with nothing of the run rewritten; a stop
signal or any other failure writes ``metrics.json`` ``interrupted`` / ``failed`` (a checkpoint
that could not be written: exit 74). docs/reference/guarantees.md lists what this keeps.
"""

from __future__ import annotations

import logging
import sys
import time
from typing import Any, Sequence

from omegaconf import DictConfig

from embodied_tactile.data.datamodule import ConstantChannelError
from embodied_tactile.run import provenance, resume, runfolder, settings, summary
from embodied_tactile.jsonio import read_json, write_json

log = logging.getLogger("train")


class RunFolderLifecycle:
    """``with RunFolderLifecycle(cfg, run_dir) as run:`` one training's run folder, from its
    claim to its ``metrics.json``: :meth:`prepare` (data, resume checkpoint, ``running``),
    :meth:`fit`, :meth:`finish`. ``run.finished``: the folder already holds the finished run
    (a multirun job; a single run stops at entry), nothing to train. ``run.stop``: the stop
    signals' callback, first of the trainer's; ``run.checkpoints``: the folder's checkpoint
    callback (each checkpoint's monitored value and the run's fit time up to it)."""

    def __init__(self, cfg: DictConfig, run_dir: str) -> None:
        self.cfg, self.run_dir = cfg, str(run_dir)
        self.finished = False
        self.stop: runfolder.StopSignals | None = None
        self.resuming = False
        self.ckpt_path: str | None = None
        self.metrics: dict | None = None  # from prepare(): what metrics.json says of the run
        self._fitting = False  # prepare() to the fit's end: a failure there is the folder's to record
        self._t0 = 0.0
        self.checkpoints = runfolder.FolderCheckpoints()

    def __enter__(self) -> "RunFolderLifecycle":
        cfg, run_dir = self.cfg, self.run_dir
        try:  # one training per folder; a restart continues the same model and data (done at entry for single runs)
            runfolder.claim(cfg, run_dir)
        except runfolder.RunFolderError as err:
            settings.fail(err)
        except runfolder.RunFinished as done:
            print(f"train.py: {done}", flush=True)  # not logged: the job's train.log stays as it was
            self.finished = True
            return self
        try:  # cli.EntryCallback checked before the folder existed; values swept with -m reach only the job
            settings.check_train_config(cfg)
        except settings.SettingsError as err:  # a folder holding a run is never rewritten by a refused start
            runfolder.refuse(run_dir, err, runfolder.holds_run(run_dir))
        # SIGTERM / SIGINT: last.ckpt after the step under way (no validation nor KRR check after it), exit 143 / 130
        self.stop = runfolder.StopSignals(last_path=f"{run_dir}/checkpoints/last.ckpt").install()
        # a resumed run's config and provenance are rewritten once its data are checked (prepare)
        self.resuming = runfolder.holds_run(run_dir)
        self._trained_on = read_json(f"{run_dir}/provenance.json").get("raw_data") if self.resuming else None
        if not self.resuming:
            provenance.save_provenance(cfg, run_dir)
        return self

    def prepare(self, datamodule: Any, trainer: Any, loggers: Sequence[Any]) -> None:
        """The checkpoint the fit resumes from (the CSV log continues from its step), the data
        prepared and checked against the run's, the split kept, ``metrics.json`` ``running``."""
        cfg, run_dir = self.cfg, self.run_dir
        self.ckpt_path = resume.find_resume_checkpoint(run_dir) if cfg.resume else None
        if self.ckpt_path:
            log.info("resuming from %s", self.ckpt_path)
        resume.continue_logs(loggers, self.ckpt_path)  # csv/metrics.csv continues from that step
        # paths relative to the run folder: a moved or copied folder names its own files
        self.metrics = {"status": "running", "resumed_from": runfolder.in_folder(run_dir, self.ckpt_path)}
        self._fitting, self._t0 = True, time.perf_counter()
        rank0 = trainer.global_rank == 0
        # data preparation is timed apart from training: prepare_data is the preparation stage
        # (embodied_tactile.data.prepare: simulation, caches, trial listing), setup splits and
        # loads; the DataModule does each once, so fit() does not repeat it
        datamodule.prepare_data()
        if self.resuming and rank0:  # a resume continues on the data the run was trained on
            changed = provenance.data_changes(self._trained_on, provenance.data_identity(
                getattr(datamodule, "cache_files", {}), provenance.trial_digests(datamodule)))
            if changed:
                raise runfolder.RunFolderError(
                    f"run folder {run_dir} was trained on other data: {'; '.join(changed)}; refusing to resume it "
                    "on these (give another hydra.run.dir for a new run)")
        datamodule.setup("fit")
        if rank0:  # the split is the run's: a resume on another is refused, naming the trials
            runfolder.keep_split(run_dir, datamodule, self.resuming)
        if self.resuming and rank0:
            provenance.save_provenance(cfg, run_dir)
        self.metrics["data_prepare_s"] = time.perf_counter() - self._t0
        if rank0 and getattr(datamodule, "cache_files", None):  # evaluate.py compares with it
            split = runfolder.served_split(datamodule)  # per trial of the run's split: others may change freely
            provenance.record_data_identity(run_dir, datamodule.cache_files, provenance.trial_digests(datamodule),
                                            [n for side in (split or {}).values() for n in side] if split else None)
        if rank0:  # from here the folder's run changes: a kill -9 leaves "running" (evaluate.py: killed)
            write_json(f"{run_dir}/metrics.json", self.metrics)

    def fit(self, trainer: Any, model: Any, datamodule: Any, callbacks: Sequence[Any]) -> None:
        """``trainer.fit`` from the resume checkpoint, then the callbacks' final read-out where
        the fit did not run it; a stop between steps saves ``last.ckpt`` and exits 130 / 143."""
        stop, run_dir = self.stop, self.run_dir
        self._t0 = time.perf_counter()
        trainer.fit(model, datamodule=datamodule, ckpt_path=self.ckpt_path)
        runfolder.finish_fit(trainer, model, callbacks, stop)  # a run resumed at its own length: its final read-out
        self._fitting = False
        self.metrics.update(self._wall_times())
        stop.defer()
        if stop.received is not None:  # stopped between steps: the state of this step is the run's last.ckpt
            last = f"{run_dir}/checkpoints/last.ckpt"
            trainer.save_checkpoint(last)
            self.metrics.update(status="interrupted", stopped_by=stop.name, stopped_in=stop.phase,
                                last_checkpoint=runfolder.in_folder(run_dir, last), step=trainer.global_step,
                                final_readout=any(getattr(c, "final", None) for c in callbacks))
            write_json(f"{run_dir}/metrics.json", self.metrics)
            log.error("%s: stopped at step %d, %s saved; start the same command again to resume; exit %d",
                      stop.name, trainer.global_step, last, stop.exit_code())
            raise SystemExit(stop.exit_code())
        self.metrics["fit_metrics"] = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
        # the run's NMSE: the KRR callback's final alignment (evaluate.py's settings, final weights)
        self.metrics["krr_final"] = next((c.final for c in callbacks if getattr(c, "final", None)), None)

    def _wall_times(self) -> dict[str, float | None]:
        """``train_wall_s``: the run's fit time over all its starts (this start's, plus the
        earlier starts' up to the checkpoint it resumed from: the time of steps done again
        after a crash is not counted twice); ``train_wall_s_this_start``: this process's.
        A resume from a checkpoint that did not record its time: ``train_wall_s`` None."""
        this, earlier = time.perf_counter() - self._t0, self.checkpoints.earlier_wall_s
        return {"train_wall_s": None if earlier is None else earlier + this, "train_wall_s_this_start": this}

    def finish(self, trainer: Any, datamodule: Any, callbacks: Sequence[Any], final_val: dict | None,
               in_multirun: bool) -> None:
        """``metrics.json`` of the fitted run (its checkpoints, data, memory and outcome), the
        closing summary (a multirun's comes at its end), the folder released."""
        metrics, run_dir = self.metrics, self.run_dir
        if final_val is not None:
            metrics["final_val"] = final_val
        for cb in trainer.checkpoint_callbacks:  # the monitored one keeps the best, the unmonitored one last.ckpt
            key = "best_checkpoint" if getattr(cb, "monitor", None) else "last_checkpoint"
            path = cb.best_model_path if key == "best_checkpoint" else cb.last_model_path or cb.best_model_path
            path = path or None
            metrics[key] = runfolder.in_folder(run_dir, path)
        best = runfolder.best_checkpoint(run_dir)  # over every checkpoint in the folder, by the value each one stores
        if best is not None:
            metrics["best_checkpoint"] = runfolder.in_folder(run_dir, best[0])
            metrics["best_value"] = {best[1]["key"]: best[1]["value"]}
        metrics["data"] = datamodule.describe() if hasattr(datamodule, "describe") else {}
        metrics["peak_rss_bytes"] = provenance.peak_rss_bytes()
        # finished: its length reached and its final KRR alignment (callbacks.krr_alignment) made
        metrics["status"], metrics["final_readout"] = runfolder.run_outcome(trainer, callbacks, self.stop)
        if trainer.global_rank == 0:
            write_json(f"{run_dir}/metrics.json", metrics)
            log.info("run folder: %s", run_dir)
            if not in_multirun:  # a multirun ends with cli.EntryCallback's summary
                summary.print_run_summary(run_dir, metrics)
        runfolder.release(run_dir)  # free once its run is written: a multirun's next job goes on in this process

    def __exit__(self, kind: type | None, err: BaseException | None, tb: Any) -> None:
        """A failure between :meth:`prepare` and the fit's end: refused (one line, exit 2,
        nothing of the run rewritten), or ``metrics.json`` ``interrupted`` / ``failed``."""
        if err is None or not self._fitting:
            return
        self._fitting = False
        run_dir, stop, metrics = self.run_dir, self.stop, self.metrics
        if isinstance(err, (runfolder.RunFolderError, ConstantChannelError)):  # refused before the run was rewritten
            runfolder.refuse(run_dir, err, self.resuming)  # a dead channel: one line naming channel, layer, files
        stop.settle()  # a signal in the final read-out: last.ckpt holds the last step's weights
        status = "interrupted" if stop.received is not None else "failed"
        metrics.update(status=status, error=str(err) or type(err).__name__, error_type=type(err).__name__,
                       **self._wall_times())
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


__all__ = ["RunFolderLifecycle"]
