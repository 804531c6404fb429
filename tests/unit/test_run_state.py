"""What a run folder says is what happened: a run is ``finished`` only when its training
reached its length and its final read-out ran; a stop signal before training or in the
final read-out ends the run within seconds and says where; a checkpoint that does not fit
the run's model is refused with every file kept. In-process trainings of the tiny scene
(``composed``), each fault injected in this process."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import time
from pathlib import Path

import pytest
import torch

from test_training_inprocess import composed, composing, tiny_overrides  # noqa: F401  composed: the fixture

EVAL_FAST = ["baselines=[mean]", "figures=false", "umap=false", "alignment.cv=2", "print_tables=false"]


@pytest.fixture(autouse=True)
def _no_handlers_on_closed_streams():
    """A handler an earlier in-process run left on a stream pytest has since closed would print
    "--- Logging error ---" into this test's stderr: such handlers are dropped first."""
    import logging

    for logger in [logging.getLogger(), *logging.root.manager.loggerDict.values()]:
        for h in list(getattr(logger, "handlers", [])):
            if isinstance(h, logging.StreamHandler) and getattr(h.stream, "closed", False):
                logger.removeHandler(h)


@pytest.fixture(scope="module")
def finished_tiny(fast_data_dir, tmp_path_factory) -> Path:
    """A finished run of ``composed``'s job, trained once for the tests that start from one."""
    from embodied_tactile.run.training import train

    with composing(tmp_path_factory.mktemp("finished"), fast_data_dir) as (cfg, run):
        train(cfg, str(run))
    return run


@pytest.fixture()
def finished(composed, finished_tiny):
    """``composed`` whose run folder holds a copy of ``finished_tiny``."""
    cfg, run = composed
    shutil.copytree(finished_tiny, run)
    return cfg, run


def _every_file(run: Path) -> dict[str, str]:
    return {p.relative_to(run).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(run.rglob("*")) if p.is_file()}


def _signal_in_check(monkeypatch, which: str, hold_s: float = 8.0) -> dict:
    """The KRR callback's check ``which`` ("initial" or "final") sends SIGTERM to this process
    and then takes ``hold_s`` more seconds (a long check on a busy machine); records when."""
    from embodied_tactile.eval.callback import KRRAlignmentCallback

    seen = {"sent": None, "initial": 0, "final": 0}
    original = KRRAlignmentCallback._evaluate

    def evaluate(self, trainer, pl_module, final=False, initial=False):
        kind = "initial" if initial else "final" if final else "periodic"
        if kind in seen:
            seen[kind] += 1
        if kind == which and seen["sent"] is None:
            seen["sent"] = time.perf_counter()
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(hold_s)
        return original(self, trainer, pl_module, final=final, initial=initial)

    monkeypatch.setattr(KRRAlignmentCallback, "_evaluate", evaluate)
    return seen


@pytest.mark.slow
def test_sigterm_in_the_check_before_training_skips_it_and_the_final_readout(composed, monkeypatch):
    """Fault: SIGTERM during the KRR check before the first step. Before: the check ran to its
    end, then the final read-out, and only then exit 143 (12-26 s on a real run). Now: exit
    143 at once, neither finishes, metrics.json says interrupted in the check before training."""
    from embodied_tactile.run.training import train

    cfg, run = composed
    seen = _signal_in_check(monkeypatch, "initial")
    with pytest.raises(SystemExit) as info:
        train(cfg, str(run))
    took = time.perf_counter() - seen["sent"]
    assert info.value.code == 143
    assert took < 5.0, took
    assert seen["final"] == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["status"] == "interrupted" and metrics["final_readout"] is False
    assert metrics["stopped_by"] == "SIGTERM" and metrics["stopped_in"] == "check before training"
    assert "krr_final" not in metrics


@pytest.mark.slow
def test_run_stopped_in_its_final_readout_resumes_at_its_length_into_the_readout(composed, monkeypatch):
    """Fault: SIGTERM during the final read-out, then the same command again (max_epochs equal
    to the epochs trained). Before: the resumed run trained nothing, ran no read-out, and said
    "finished" with final_readout false and krr_final null. Now: the stop is prompt and saves
    the last step; the resume runs the final read-out on those weights and only then says
    finished."""
    from embodied_tactile.run.training import train

    cfg, run = composed
    seen = _signal_in_check(monkeypatch, "final")
    with pytest.raises(SystemExit) as info:
        train(cfg, str(run))
    assert info.value.code == 143 and time.perf_counter() - seen["sent"] < 5.0
    stopped = json.loads((run / "metrics.json").read_text())
    assert stopped["status"] == "interrupted" and stopped["stopped_in"] == "final read-out"
    assert stopped["final_readout"] is False and stopped["last_checkpoint"] == "checkpoints/last.ckpt"
    ck = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ck["global_step"] == stopped["step"] > 0

    monkeypatch.undo()
    train(cfg, str(run))  # the same length: nothing to train, the read-out to make
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["status"] == "finished" and metrics["final_readout"] is True
    assert metrics["krr_final"]["final"] is True and metrics["krr_final"]["step"] == stopped["step"]
    assert metrics["krr_final"]["epoch"] >= 0  # the final weights' read-out, not the step-0 check


def test_run_outcome_is_finished_only_with_its_length_and_readout():
    from types import SimpleNamespace

    from embodied_tactile.run.runfolder import StopSignals, run_outcome

    class Reader:
        run_on_train_end = True

        def __init__(self, final):
            self.final = final

        def ensure_final(self, trainer, pl_module):  # pragma: no cover - not called here
            pass

    done = SimpleNamespace(fit_loop=SimpleNamespace(done=True), interrupted=False)
    cut = SimpleNamespace(fit_loop=SimpleNamespace(done=False), interrupted=False)
    assert run_outcome(done, [Reader({"nmse_overall": 0.5})], StopSignals()) == ("finished", True)
    assert run_outcome(done, [Reader(None)], StopSignals()) == ("interrupted", False)
    assert run_outcome(done, [], StopSignals()) == ("finished", False)  # no read-out configured
    assert run_outcome(cut, [Reader({"nmse_overall": 0.5})], StopSignals())[0] == "interrupted"


def _misfit(run: Path) -> None:
    """Every checkpoint of ``run`` as if copied from a run of another modality: one more input
    channel in the first 4-D encoder weight, the modality named in its hyperparameters."""
    for path in (run / "checkpoints").glob("*.ckpt"):
        ck = torch.load(path, map_location="cpu", weights_only=False)
        key = next(k for k, v in ck["state_dict"].items() if "encoder" in k and v.ndim == 4)
        w = ck["state_dict"][key]
        ck["state_dict"][key] = torch.zeros(w.shape[0], w.shape[1] + 1, *w.shape[2:])
        ck["hyper_parameters"]["net"]["modality"] = {"name": "acc_fsr_t", "channels": ["acc", "fsr_t"]}
        torch.save(ck, path)


@pytest.mark.slow
def test_a_checkpoint_of_another_model_is_refused_and_every_file_kept(finished, capsys, tmp_path):
    """Fault: a finished run whose checkpoints come from another modality, resumed for more
    epochs, then evaluated alone and in a folder beside a good run. Before: the resume failed
    with a traceback (exit 1) and rewrote metrics.json "failed"; evaluate failed with a
    traceback and a folder of runs stopped at that run. Now: exit 2 with one line naming the
    file and the mismatch, every file byte-identical; the folder's other run is scored and
    the misfit named as skipped."""
    from embodied_tactile.eval.command import main as evaluate_main
    from embodied_tactile.run.training import compose, train

    cfg, run = finished
    folder = tmp_path / "sweep"
    good, bad = folder / "0", folder / "1"
    shutil.copytree(run, good)
    shutil.move(str(run), bad)
    _misfit(bad)
    before = _every_file(bad)
    capsys.readouterr()

    longer = compose(tiny_overrides(cfg.paths.data_dir, cfg.paths.log_dir) + ["trainer.max_epochs=2"], str(bad))
    with pytest.raises(SystemExit) as info:
        train(longer, str(bad))
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("train.py: error: ") and "last.ckpt" in err[0]
    assert "modality acc_fsr_t" in err[0] and "of another shape" in err[0]
    assert _every_file(bad) == before

    assert evaluate_main([str(bad), *EVAL_FAST]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("evaluate.py: error: ") and "does not fit the model" in err[-1]
    assert "modality acc_fsr_t" in err[-1] and "Traceback" not in "\n".join(err)

    assert evaluate_main([str(folder), *EVAL_FAST]) == 0
    out = capsys.readouterr().out
    assert f"SKIPPED {bad}" in out and "does not fit" in out
    assert "evaluated 1 run(s) (1 skipped)" in out
    assert _every_file(bad) == before


@pytest.mark.slow
def test_a_dead_channel_refuses_a_new_run_and_leaves_no_folder(composed, monkeypatch, capsys):
    """Fault: every training frame of the modality's channel reads one value (a dead layer).
    Before: exit 2 with one line, but the run folder stayed behind (metrics.json "failed",
    config_resolved.yaml, provenance.json). Now: the same line, and no folder."""
    import numpy as np

    from embodied_tactile.data.statistics import DataStatistics
    from embodied_tactile.run.training import train

    cfg, run = composed
    real = DataStatistics.of.__func__

    def dead(cls, batches, n):
        st = real(cls, batches, n)
        return cls(st.channel_mean, np.zeros_like(st.channel_std), st.n_train_sequences)

    monkeypatch.setattr(DataStatistics, "of", classmethod(dead))
    with pytest.raises(SystemExit) as info:
        train(cfg, str(run))
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("train.py: error: channel acc ") and "is constant" in err[0]
    assert not run.exists()


@pytest.mark.parametrize("threads", [0, -2, "many"])
def test_threads_below_one_is_a_bad_setting(threads):
    """Fault: threads=0. Before: a traceback from thread_budget (exit 1) after the run folder
    was written. Now: the entry's check names it."""
    from omegaconf import OmegaConf

    from embodied_tactile.run.settings import SettingsError, check_train_config

    with pytest.raises(SettingsError, match=rf"^threads={threads!r} \(\w+\): expected auto or an integer >= 1$"):
        check_train_config(OmegaConf.create({"threads": threads}))
    for ok in ("auto", 1, 4, None):
        check_train_config(OmegaConf.create({"threads": ok}))


@pytest.mark.slow
@pytest.mark.parametrize("args, needles", [
    (["modality=mutli_l"], ("modality=mutli_l: no such option", "multi_l")),
    (["trainer.max_epoch=3"], ("trainer.max_epoch=3: no such key", "+trainer.max_epoch=")),
    (["-m", "modality=acc,mutli_l"], ("modality=mutli_l: no such option",)),
])
def test_hydra_composition_errors_are_one_line_exit_2(args, needles, capsys):
    """Fault: a mistyped group option or key. Before: Hydra's several-line report and exit 1.
    Now: train.py's entry check prints one line, exit 2, before Hydra makes a folder."""
    from embodied_tactile.run.overrides import check_composes

    with pytest.raises(SystemExit) as info:
        check_composes(args)
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("train.py: error: ")
    for n in needles:
        assert n in err[0], (n, err)
    check_composes(["modality=acc", "trainer.max_epochs=3", "-m", "seed=1,2"])  # a command that composes


# ----------------------------------------------------------------------------- evaluate: one line, nothing written
@pytest.fixture(scope="module")
def evaluated_tiny(finished_tiny, tmp_path_factory) -> Path:
    """A copy of ``finished_tiny`` with one evaluation of it (``<run>/evaluation``)."""
    from embodied_tactile.eval.command import main as evaluate_main

    run = tmp_path_factory.mktemp("evaluated") / "run"
    shutil.copytree(finished_tiny, run)
    handler = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a fresh evaluate.py process
    try:
        assert evaluate_main([str(run), *EVAL_FAST]) == 0
    finally:
        signal.signal(signal.SIGINT, handler)
    return run


@pytest.fixture()
def evaluated_run(composed, evaluated_tiny):
    """A finished run of the tiny scene with one evaluation of it (a copy of ``evaluated_tiny``)."""
    run = composed[1]
    shutil.copytree(evaluated_tiny, run)
    signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a fresh evaluate.py process
    return run


def _evaluate(*argv: str):
    """evaluate.py's main in this process -> its exit status, or what escaped it."""
    from embodied_tactile.eval.command import main as evaluate_main

    try:
        return evaluate_main(list(argv))
    except KeyboardInterrupt:
        return "KeyboardInterrupt escaped"
    except Exception as err:  # noqa: BLE001 -- the fault shows as what escaped
        return f"{type(err).__name__} escaped"


def _interrupt_at(monkeypatch, target, name: str, sig=signal.SIGINT) -> None:
    original = getattr(target, name)

    def stopped(*a, **k):
        os.kill(os.getpid(), sig)
        time.sleep(3)
        return original(*a, **k)

    monkeypatch.setattr(target, name, stopped)


@pytest.mark.slow
def test_ctrl_c_in_evaluate_exits_130_in_every_phase(evaluated_run, monkeypatch, capsys):
    """Fault: Ctrl-C while evaluate finds the runs, prepares the data, or writes the report.
    Before: a KeyboardInterrupt traceback out of main (exit 130 or 1 by phase). Now: one line,
    exit 130, the earlier evaluation byte-identical and no temporary folder left."""
    from embodied_tactile.eval import pipeline, report, runs

    before = _every_file(evaluated_run / "evaluation")
    for phase, target in (("discover", (pipeline, "discover")), ("data", (runs.DataCache, "get")),
                          ("report", (report, "write_report"))):
        with monkeypatch.context() as patch:
            _interrupt_at(patch, *target)
            patch.setattr(pipeline, "_reused", lambda out, key: None)  # scored afresh: its data are prepared
            capsys.readouterr()
            assert _evaluate(str(evaluated_run), *EVAL_FAST) == 130, phase
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("evaluate.py: stopped by SIGINT: nothing written"), (phase, err[-3:])
        assert "Traceback" not in "\n".join(err), phase
        assert _every_file(evaluated_run / "evaluation") == before, phase
        assert not list(evaluated_run.glob(".evaluation.tmp-*")), phase


@pytest.mark.slow
def test_evaluate_on_a_full_or_read_only_folder_is_one_line(evaluated_run, monkeypatch, capsys):
    """Fault: the disk fills while the report is written (Errno 28 from PIL); the run folder
    is read-only. Before: tracebacks, exit 1. Now: one line naming the folder and the OS
    reason, exit 2, the earlier evaluation kept."""
    import errno
    import tempfile

    from embodied_tactile.eval import report

    before = _every_file(evaluated_run / "evaluation")
    real = report.write_report

    def full(results, out, **kw):
        (Path(out) / "table_partial.md").write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device", str(Path(out) / "figures" / "nmse.png"))

    monkeypatch.setattr(report, "write_report", full)
    capsys.readouterr()
    assert _evaluate(str(evaluated_run), *EVAL_FAST) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"evaluate.py: error: cannot write the evaluation into "
                                               f"{evaluated_run / 'evaluation'}: No space left on device")
    assert _every_file(evaluated_run / "evaluation") == before
    assert not list(evaluated_run.glob(".evaluation.tmp-*"))

    monkeypatch.setattr(report, "write_report", real)

    def read_only(*a, **k):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "TemporaryFile", read_only)  # the probe of a folder on a read-only mount
    assert _evaluate(str(evaluated_run), *EVAL_FAST, "out=" + str(evaluated_run / "again")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot write the evaluation into" in err[0] and "Read-only file system" in err[0]
    assert not (evaluated_run / "again").exists()


# ----------------------------------------------------------------------------- sweeps
@pytest.mark.slow
def test_a_finished_job_run_again_leaves_every_file_unchanged_train_log_included(finished, capsys):
    """Fault: the same multirun again on a finished sweep: each job's train() finds its run
    finished. Before: one line appended to each job's train.log (the README promises every
    file unchanged). Now: it says so on stdout and no byte of the folder changes."""
    import logging

    from embodied_tactile.run.training import train

    cfg, run = finished
    handler = logging.FileHandler(run / "train.log")  # as Hydra's job logging: the root logger into the job's log
    root = logging.getLogger()
    root.addHandler(handler)
    old_level = root.level
    root.setLevel(logging.INFO)
    try:
        before = _every_file(run)
        capsys.readouterr()
        assert train(cfg, str(run)) is None
        handler.flush()
        assert _every_file(run) == before
        assert "is finished" in capsys.readouterr().out
    finally:
        root.removeHandler(handler)
        root.setLevel(old_level)
        handler.close()


def test_a_sweep_over_recording_sets_is_one_job_per_set():
    """Fault: ``-m 'data.raw_files=[a.h5,b.h5],[c*.h5]'`` (two recording sets). Before: refused
    ("expected a list or null") however it was quoted. Now: the typed check passes each list
    and Hydra's sweeper makes one job per set."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from embodied_tactile.cli import check_typed_overrides

    args = ["data.source=recorded", "data.raw_files=[rec/soft_a.h5,rec/soft_b.h5],[rec/hard/*.h5]", "seed=0,1"]
    check_typed_overrides(["-m", *args])
    jobs = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(args), None)[0]
    assert sorted({j[1] for j in jobs}) == ["data.raw_files=[rec/hard/*.h5]", "data.raw_files=[rec/soft_a.h5,rec/soft_b.h5]"]
    assert len(jobs) == 4
    with pytest.raises(SystemExit):  # a set that is not a list is still refused, naming it
        check_typed_overrides(["-m", "data.raw_files=[rec/a.h5],3"])


def test_a_full_output_folder_is_refused_at_the_entry(tmp_path, monkeypatch):
    """Fault: the disk of the log folder is full. Before: the entry's probe created an empty
    file, which a full disk allows, and the run failed later with a traceback. Now: the probe
    writes and syncs a block, and a full disk is one line naming the key and the reason."""
    import errno

    from embodied_tactile.run import settings

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(settings.os, "fsync", full)
    with pytest.raises(settings.SettingsError, match=r"^paths.log_dir=.*: cannot create or write this folder "
                                                     r"\(No space left on device\)$"):
        settings.check_writable_dir("paths.log_dir", tmp_path / "logs")


def _progress(started: int, processed: int, is_last_batch: bool, step: int) -> dict:
    """A checkpoint's header as Lightning writes it (only the fit loop's counters)."""
    epochs = {"ready": started, "started": started, "processed": processed, "completed": processed}
    return {"epoch": started - 1, "global_step": step,
            "loops": {"fit_loop": {"epoch_progress": {"total": dict(epochs), "current": dict(epochs)},
                                   "epoch_loop.batch_progress": {"is_last_batch": is_last_batch}}}}


def test_a_checkpoint_saved_by_the_last_epochs_validation_counts_that_epoch(tmp_path):
    """A study run's last.ckpt, saved by the validation that ends its 32nd and last epoch,
    holds the epoch as started and not processed, its batch loop at the last batch (the
    counters of a real one). It counts 32 epochs, so the same command on the finished run
    trains and rewrites nothing; a checkpoint saved mid-epoch still counts the epochs before."""
    from omegaconf import OmegaConf

    from embodied_tactile.run.runfolder import RunFinished, check_length, checkpoint_progress

    assert checkpoint_progress(_progress(32, 31, True, 960)) == (32, 960)
    assert checkpoint_progress(_progress(32, 31, False, 950)) == (31, 950)  # stopped inside epoch 32
    assert checkpoint_progress(_progress(32, 32, True, 960)) == (32, 960)  # saved after the epoch was counted
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    torch.save(_progress(32, 31, True, 960), run / "checkpoints" / "last.ckpt")
    (run / "metrics.json").write_text(json.dumps({"status": "finished"}))
    with pytest.raises(RunFinished, match=r"is finished \(32 epoch\(s\), step 960\)"):
        check_length(OmegaConf.create({"trainer": {"max_epochs": 32}}), run)
    check_length(OmegaConf.create({"trainer": {"max_epochs": 33}}), run)  # more epochs: it continues
