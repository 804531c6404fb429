"""A run folder belongs to one run: the lock, the resume check, one CSV row per (step, metric),
stop signals and atomic checkpoints. Each test injects one fault and asserts the exit code,
the message and what is kept on disk."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from conftest import REPO
from test_train import ENV, _csv_rows, run_train, train_cmd


def _digests(run: Path, names=("metrics.json", "config_resolved.yaml", ".hydra/config.yaml")) -> dict[str, str]:
    return {n: hashlib.sha256((run / n).read_bytes()).hexdigest() for n in names if (run / n).exists()}


@pytest.fixture(scope="module")
def finished_run(fast_data_dir, tmp_path_factory) -> Path:
    """A finished acc run of one epoch (the cheapest train.py run, in this process)."""
    run = tmp_path_factory.mktemp("owned") / "r"
    run_train(f"paths.data_dir={fast_data_dir}", f"hydra.run.dir={run}", "modality=acc", "threads=1",
              "callbacks.krr_alignment=null")
    return run


# ----------------------------------------------------------------------------- resume check
def test_config_changes_names_keys_that_shape_model_or_data():
    from embodied_tactile.run.runfolder import config_changes

    saved = {"seed": 0, "data": {"actions": [0, 5], "num_workers": 0, "split": "trial"}, "trainer": {"max_epochs": 2},
             "model": {"net": {"n_z": 16}}, "callbacks": {"krr": {"points": 8}}}
    new = {"seed": 1, "data": {"actions": [0], "num_workers": 4, "split": "object"}, "trainer": {"max_epochs": 9},
           "model": {"net": {"n_z": 16, "extra": 1}}, "callbacks": None}
    assert set(config_changes(saved, new)) == {"seed", "data.actions", "data.split", "model.net.extra"}
    assert config_changes(saved, saved) == {}
    # a config saved before the modules moved reads as today's: the same run, resumable
    old = {"model": {"_target_": "embodied_tactile.models.module.LateFusionLatentFilter"},
           "modality": {"name": "acc", "module": "embodied_tactile.models.module.LateFusionLatentFilter"}}
    assert config_changes(old, {"model": {"_target_": "embodied_tactile.model.module.LatentFilterModule"},
                                "modality": {"name": "acc"}}) == {}


def test_check_resume_refuses_other_settings_before_writing(tmp_path):
    from embodied_tactile.run.runfolder import RunFolderError, check_resume

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    cfg = OmegaConf.create({"seed": 0, "resume": True, "modality": {"name": "acc"}, "trainer": {"max_epochs": 1}})
    (run / "config_resolved.yaml").write_text(OmegaConf.to_yaml(cfg))
    check_resume(cfg, run)  # no checkpoint and no finished metrics.json: nothing to protect
    (run / "checkpoints" / "last.ckpt").write_bytes(b"x")
    check_resume(OmegaConf.merge(cfg, {"trainer": {"max_epochs": 5}}), run)  # longer: allowed
    with pytest.raises(RunFolderError, match=r"modality\.name.*'acc' -> 'fsr_t'"):
        check_resume(OmegaConf.merge(cfg, {"modality": {"name": "fsr_t"}}), run)
    with pytest.raises(RunFolderError, match="resume=false"):
        check_resume(OmegaConf.merge(cfg, {"resume": False}), run)


@pytest.mark.slow  # finished_run: a training by train.py's entry point
def test_refused_restart_with_other_modality_keeps_the_finished_run(finished_run, fast_data_dir):
    """Fault: a finished run folder re-run with another modality, actions and seed. Before:
    state_dict mismatch, exit 1, metrics.json rewritten "failed", config_resolved.yaml
    rewritten. Now: exit 2 before anything is written, the keys named."""
    before = _digests(finished_run)
    ckpts = {p.name: p.read_bytes() for p in (finished_run / "checkpoints").iterdir()}
    res = run_train(f"paths.data_dir={fast_data_dir}", f"hydra.run.dir={finished_run}", "modality=fsr_t", "seed=3",
                    "data.actions=[0,10]", "threads=1", check=False)
    assert res.returncode == 2, res.stderr[-2000:]
    err = res.stderr.strip().splitlines()[-1]
    assert err.startswith("train.py: error: run folder") and str(finished_run) in err
    for key in ("modality.name", "data.channels", "data.actions", "seed"):
        assert key in err, key
    assert "Traceback" not in res.stderr
    assert _digests(finished_run) == before
    assert {p.name: p.read_bytes() for p in (finished_run / "checkpoints").iterdir()} == ckpts
    assert json.loads((finished_run / "metrics.json").read_text())["status"] == "finished"


@pytest.mark.slow  # finished_run: a training by train.py's entry point
def test_bad_setting_in_a_finished_run_folder_keeps_its_metrics(finished_run, fast_data_dir):
    before = _digests(finished_run)
    res = run_train(f"paths.data_dir={fast_data_dir}", f"hydra.run.dir={finished_run}", "modality=acc", "data.batch_size=0",
                    check=False)
    assert res.returncode == 2 and "data.batch_size=0" in res.stderr
    assert _digests(finished_run) == before


# ----------------------------------------------------------------------------- lock
class _LockHolder:
    """Another process holding the run folder's lock (as a running training does): a fork of
    this one, which has runfolder imported already (a fresh interpreter spends seconds
    importing lightning first)."""

    def __init__(self, run: Path):
        import multiprocessing

        ctx = multiprocessing.get_context("fork")
        ready = ctx.Event()
        self.proc = ctx.Process(target=self._hold, args=(str(run), ready), daemon=True)
        self.proc.start()
        assert ready.wait(60), "the lock holder did not take the lock"
        self.pid = self.proc.pid

    @staticmethod
    def _hold(run: str, ready) -> None:
        from embodied_tactile.run import runfolder

        runfolder.lock(run)
        ready.set()
        time.sleep(120)

    def kill(self) -> None:
        self.proc.kill()

    def wait(self) -> None:
        self.proc.join()


def _hold_lock(run: Path) -> _LockHolder:
    return _LockHolder(run)


def test_lock_refuses_a_second_holder_and_frees_on_exit(tmp_path):
    from embodied_tactile.run import runfolder

    run = tmp_path / "run"
    holder = _hold_lock(run)
    try:
        with pytest.raises(runfolder.RunFolderError, match=rf"in use by another training \(pid {holder.pid} on host "):
            runfolder.lock(run)
    finally:
        holder.kill()
        holder.wait()
    runfolder.lock(run)  # the kernel released the dead holder's lock
    runfolder.release(run)


@pytest.mark.slow  # finished_run: a training by train.py's entry point
def test_second_training_in_a_running_folder_is_refused(finished_run, fast_data_dir):
    """Fault: two trainings in one run folder at once. Before: both exit 0, every step twice
    in the CSV, best-epoch003.ckpt beside best-epoch003-v1.ckpt. Now: the second exits 2
    naming the holder's pid, and writes nothing."""
    before = _digests(finished_run)
    rows = (finished_run / "csv" / "metrics.csv").read_bytes()
    holder = _hold_lock(finished_run)
    try:
        res = run_train(f"paths.data_dir={fast_data_dir}", f"hydra.run.dir={finished_run}", "modality=acc",
                        "trainer.max_epochs=3", check=False)
    finally:
        holder.kill()
        holder.wait()
    assert res.returncode == 2
    assert f"in use by another training (pid {holder.pid}" in res.stderr
    assert _digests(finished_run) == before and (finished_run / "csv" / "metrics.csv").read_bytes() == rows


# ----------------------------------------------------------------------------- CSV
def test_resumed_csv_one_row_per_step_and_metric_when_lightning_saves_after_each_log(tmp_path):
    """Fault: kill -9 after the checkpoint at step 4 while the next epoch had logged its
    learning rate and first loss at step 4. Lightning saves the CSV after every log call, so
    the resumed run's rows at step 4 arrive in separate saves; before, only the first save's
    metric was deduplicated and train/loss at step 4 appeared twice."""
    from embodied_tactile.run.resume import ResumableCSVLogger

    folder = tmp_path / "csv"
    folder.mkdir()
    with open(folder / "metrics.csv", "w") as fh:
        fh.write("epoch,lr,step,train/loss,val/elbo\n"
                 "0,,3,5.0,\n0,,4,,-9.0\n,0.1,4,,\n1,,4,4.0,\n")  # val before the checkpoint; lr, loss after it
    lg = ResumableCSVLogger(tmp_path, name="csv", version="", resume_step=4)
    for metrics in ({"lr": 0.1}, {"train/loss": 3.5, "epoch": 1}, {"train/loss": 3.0, "epoch": 1}):
        step = 5 if metrics.get("train/loss") == 3.0 else 4
        lg.log_metrics(metrics, step=step)
        lg.save()
    rows = _csv_rows(folder / "metrics.csv")
    pairs = [(r["step"], k) for r in rows for k in ("lr", "train/loss", "val/elbo") if r[k]]
    assert len(pairs) == len(set(pairs)), pairs
    assert [(r["step"], r["lr"], r["train/loss"], r["val/elbo"]) for r in rows] == [
        ("3", "", "5.0", ""), ("4", "", "", "-9.0"), ("4", "0.1", "", ""), ("4", "", "3.5", ""), ("5", "", "3.0", "")]
    assert [(r["step"], r["lr"], r["train/loss"]) for r in _csv_rows(folder / "metrics.discarded.csv")] == [
        ("4", "0.1", ""), ("4", "", "4.0")]


# ----------------------------------------------------------------------------- stop signals
def _start_and_wait_for_epoch(overrides: tuple[str, ...], last: Path, epoch: int = 1) -> subprocess.Popen:
    proc = subprocess.Popen(train_cmd(*overrides), cwd=REPO, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    deadline = time.time() + 240
    while time.time() < deadline:
        try:
            if last.exists() and int(torch.load(last, map_location="cpu", weights_only=False)["epoch"]) >= epoch:
                return proc
        except Exception:  # noqa: BLE001 -- read while being replaced
            pass
        if proc.poll() is not None:
            pytest.fail("training ended before the signal:\n" + proc.stdout.read()[-3000:])
        time.sleep(0.3)
    proc.kill()
    pytest.fail(f"no checkpoint of epoch >= {epoch} appeared")


@pytest.mark.slow  # a train.py subprocess stopped by the signal
@pytest.mark.parametrize("sig,code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_stop_signal_saves_last_checkpoint_and_exits_nonzero(fast_data_dir, tmp_path, sig, code):
    """Fault: SIGTERM (a cluster's pre-emption) or SIGINT during training. Before: exit 0,
    metrics.json "failed", no checkpoint of the step reached. Now: last.ckpt of the step the
    run stopped at, metrics.json "interrupted", exit 128 + signal; the same command resumes."""
    run = tmp_path / "run"
    overrides = (f"paths.data_dir={fast_data_dir}", f"hydra.run.dir={run}", "modality=acc", "threads=1",
                 "trainer.max_epochs=200", "callbacks.krr_alignment=null")
    last = run / "checkpoints" / "last.ckpt"
    proc = _start_and_wait_for_epoch(overrides, last)
    proc.send_signal(sig)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == code, out[-3000:]
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["status"] == "interrupted" and metrics["stopped_by"] == signal.Signals(sig).name
    assert metrics["final_readout"] is False and metrics["last_checkpoint"] == "checkpoints/last.ckpt"
    ck = torch.load(last, map_location="cpu", weights_only=False)
    assert ck["global_step"] == metrics["step"] > 0
    assert not list((run / "checkpoints").glob("*.tmp*"))
    if sig == signal.SIGTERM:  # requeued: the same folder continues from that step
        res = run_train(*overrides[:-2], f"trainer.max_epochs={ck['epoch'] + 2}", "callbacks.krr_alignment=null")
        assert "resuming from" in res.stdout + res.stderr
        after = json.loads((run / "metrics.json").read_text())
        assert after["status"] == "finished" and after["resumed_from"].endswith("last.ckpt")


# ----------------------------------------------------------------------------- checkpoints
def test_atomic_checkpoint_write_error_keeps_the_previous_file(tmp_path, monkeypatch):
    from embodied_tactile.run import runfolder

    io = runfolder.AtomicCheckpointIO()
    path = tmp_path / "checkpoints" / "last.ckpt"
    io.save_checkpoint({"state_dict": {"w": torch.ones(3)}, "global_step": 1}, path)
    before = path.read_bytes()

    def full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(runfolder.os, "fsync", full)
    with pytest.raises(runfolder.CheckpointWriteError, match=rf"cannot write checkpoint {path}: No space left on device"):
        io.save_checkpoint({"state_dict": {"w": torch.zeros(3)}, "global_step": 2}, path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.ckpt"]  # no partial file beside it


def _file_size_limit(limit: int):
    def pre() -> None:  # a disk that fills up: writes past `limit` bytes fail with EFBIG
        import resource

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return pre


@pytest.mark.slow  # finished_run, and a train.py subprocess under a file size limit
def test_full_disk_leaves_previous_checkpoints_and_one_line(finished_run, fast_data_dir, tmp_path):
    """Fault: the disk fills while a checkpoint is written. Before: OSError traceback and a
    truncated best-epoch001.ckpt that evaluation and resume then picked. Now: exit 74, one
    line naming the file, the earlier checkpoints bit for bit, no partial file."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    ck = run / "checkpoints"
    before = {p.name: p.read_bytes() for p in ck.iterdir()}
    limit = min(len(b) for b in before.values()) // 2
    res = subprocess.run(train_cmd(f"paths.data_dir={fast_data_dir}", f"hydra.run.dir={run}", "modality=acc", "threads=1",
                                   "callbacks.krr_alignment=null", "trainer.max_epochs=2"),
                         cwd=REPO, env=ENV, capture_output=True, text=True, timeout=240, preexec_fn=_file_size_limit(limit))
    assert res.returncode == 74, res.stderr[-3000:]
    last_line = res.stderr.strip().splitlines()[-1]
    assert last_line.startswith(f"train.py: error: cannot write checkpoint {ck}/") and "File too large" in last_line
    assert "Traceback" not in res.stderr
    assert {p.name: p.read_bytes() for p in ck.iterdir()} == before
    from embodied_tactile.eval.runs import find_checkpoint

    assert find_checkpoint(run, "best").read_bytes() in before.values()


@pytest.mark.slow  # finished_run: a training by train.py's entry point
def test_evaluation_skips_a_truncated_checkpoint(finished_run, tmp_path, caplog):
    import shutil

    from embodied_tactile.eval.runs import EvaluationError, find_checkpoint

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    (best,) = (run / "checkpoints").glob("best-*.ckpt")
    best.write_bytes(best.read_bytes()[:5000])
    with caplog.at_level("WARNING"):
        assert find_checkpoint(run, "best") == run / "checkpoints" / "last.ckpt"
    assert str(best) in caplog.text
    (run / "checkpoints" / "last.ckpt").write_bytes(b"\0" * 100)
    with pytest.raises(EvaluationError, match=rf"no checkpoint \(best or last\) in run folder {run} that can be read.*{best.name}"):
        find_checkpoint(run, "best")


# ----------------------------------------------------------------------------- evaluation
@pytest.fixture()
def evaluate_cli():
    sys.path.insert(0, str(REPO))
    import logging

    import evaluate

    def run(argv):
        # a handler an earlier in-process run left on a stream pytest has since closed would
        # print "--- Logging error ---" into this test's stderr: drop such handlers first
        for logger in [logging.getLogger(), *logging.root.manager.loggerDict.values()]:
            for h in list(getattr(logger, "handlers", [])):
                if isinstance(h, logging.StreamHandler) and getattr(h.stream, "closed", False):
                    logger.removeHandler(h)
        return evaluate.main(argv)

    return run


EVAL_FAST = ["baselines=[mean]", "figures=false", "umap=false", "alignment.cv=2", "print_tables=false"]


@pytest.mark.slow  # finished_run: a training by train.py's entry point
def test_copied_run_folder_never_reads_the_original_checkpoints(finished_run, tmp_path, evaluate_cli, capsys):
    """Fault: a copy of a run folder whose checkpoints were deleted. Before: exit 0, "same
    weights", the original's checkpoint read through metrics.json's absolute path. Now: the
    checkpoints are looked up inside the folder evaluated; none there: exit 2 naming it."""
    import shutil

    from embodied_tactile.eval.runs import find_checkpoint

    copy = tmp_path / "copy"
    shutil.copytree(finished_run, copy)
    assert json.loads((copy / "metrics.json").read_text())["best_checkpoint"].startswith("checkpoints/")
    assert find_checkpoint(copy, "best").parent == copy / "checkpoints"
    shutil.rmtree(copy / "checkpoints")
    assert evaluate_cli([str(copy), *EVAL_FAST]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith(f"evaluate.py: error: no checkpoint (last.ckpt) in run folder {copy} ")
    assert not (copy / "evaluation").exists()


@pytest.mark.slow  # finished_run: a training by train.py's entry point
def test_unreadable_split_and_checkpoints_are_one_line_errors(finished_run, tmp_path, evaluate_cli, capsys):
    """Faults: split.json that is not JSON; a truncated checkpoint given by path; a
    checkpoint of another model. Before: tracebacks. Now: exit 2, one line naming the file."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    (run / "split.json").write_text("{not json")
    assert evaluate_cli([str(run), *EVAL_FAST]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{run / 'split.json'}: not a split file" in err
    shutil.copy2(finished_run / "split.json", run / "split.json")

    last = run / "checkpoints" / "last.ckpt"
    truncated = run / "checkpoints" / "cut.ckpt"
    truncated.write_bytes(last.read_bytes()[:4000])
    assert evaluate_cli([str(truncated), *EVAL_FAST]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"evaluate.py: error: {truncated}: unreadable")

    other = run / "checkpoints" / "other.ckpt"
    torch.save({"state_dict": {"linear.weight": torch.zeros(2, 2)}, "global_step": 1, "epoch": 0,
                "hyper_parameters": {"hidden": 3}}, other)
    assert evaluate_cli([str(other), *EVAL_FAST]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(other) in err


@pytest.mark.slow  # trainings by train.py's entry point
def test_changed_raw_data_is_refused_or_named_at_evaluation(fast_data_dir, tmp_path, evaluate_cli, capsys):
    """Fault: the raw data changed after training. Before: exit 0, "same weights, settings
    and sequences". Now: exit 2 naming the raw file and field; a resume on them exit 2 too;
    allow_changed_data=true scores it and names the change in place of "same sequences"."""
    import shutil

    import h5py

    data = tmp_path / "data"
    shutil.copytree(fast_data_dir / "raw", data / "raw")
    run = tmp_path / "run"
    run_train(f"paths.data_dir={data}", f"hydra.run.dir={run}", "modality=acc", "threads=1")
    prov = json.loads((run / "provenance.json").read_text())
    assert set(prov["raw_data"]) == {"acc", "actions"}
    raw = data / "raw" / "soft_pressing.h5"
    with h5py.File(raw, "a") as f:  # one accelerometer sample of one trial
        g = next(iter(f["trials"].values()))
        path = g.visit(lambda n: n if isinstance(g[n], h5py.Dataset) and "acc" in n else None)
        g[path][0] = g[path][0] * 0.5
    assert evaluate_cli([str(run), *EVAL_FAST]) == 2
    err = capsys.readouterr().err
    assert "the data differ from those it was trained on" in err and str(raw) in err and "acc" in err
    # a resume on the changed data is refused too, the run's files as they were
    before = _digests(run, ("metrics.json", "config_resolved.yaml", "provenance.json"))
    res = run_train(f"paths.data_dir={data}", f"hydra.run.dir={run}", "modality=acc", "threads=1",
                    "trainer.max_epochs=2", check=False)
    assert res.returncode == 2, res.stderr[-2000:]
    last = res.stderr.strip().splitlines()[-1]  # named per trial of the run, with its raw file
    assert last.startswith(f"train.py: error: run folder {run} was trained on other data: trial obj") and str(raw) in last
    assert "its acc data or attributes changed since training" in last
    assert _digests(run, ("metrics.json", "config_resolved.yaml", "provenance.json")) == before
    assert evaluate_cli([str(run), *EVAL_FAST, "allow_changed_data=true"]) == 0
    out = capsys.readouterr()
    ev = json.loads((run / "evaluation" / "evaluation.json").read_text())
    other = ev["runs"][0]["training_final_alignment"]["other"]
    assert other and other[0].startswith("the data changed since training") and str(raw) in other[0]
    assert "another measurement: the data changed since training" in out.out + out.err


def test_stop_signal_outside_the_training_steps_raises_and_inside_sets_should_stop():
    """SIGTERM during data preparation or the check before the first step ends the run as
    interrupted (StopRequested, which train.py turns into exit 143); during the steps it only
    asks Lightning to stop."""
    from types import SimpleNamespace

    from embodied_tactile.run.runfolder import StopRequested, StopSignals

    old = {s: signal.getsignal(s) for s in StopSignals.SIGNALS}
    try:
        stop = StopSignals().install()
        with pytest.raises(StopRequested, match="stopped by SIGTERM"):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
        assert stop.exit_code() == 143
        stop = StopSignals().install()
        trainer = SimpleNamespace(should_stop=False)
        stop.on_train_start(trainer, None)  # the check before the first step: abandoned at once
        with pytest.raises(StopRequested, match="stopped by SIGTERM"):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
        assert stop.phase == "check before training"
        stop = StopSignals().install()
        stop.on_train_start(trainer, None)
        stop.on_train_batch_start(trainer, None, None, 0)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.1)
        assert trainer.should_stop and stop.exit_code() == 130 and stop.name == "SIGINT" and stop.phase == "training"
    finally:
        for s, h in old.items():
            signal.signal(s, h)


# ----------------------------------------------------------------------------- a finished run is never rewritten
def _fake_run(run: Path, *, epochs: int, steps: int, status: str = "finished", split: dict | None = None,
              monitored: dict[str, float | None] | None = None) -> OmegaConf:
    """A run folder as train.py leaves it (config, metrics.json, split.json, last.ckpt of
    ``epochs`` epochs, a lock file naming an earlier holder), without training: its config."""
    cfg = OmegaConf.create({"seed": 0, "resume": True, "modality": {"name": "acc"},
                            "trainer": {"max_epochs": epochs, "max_steps": -1},
                            "data": {"split_file": str(run / "split.json")}})
    (run / "checkpoints").mkdir(parents=True)
    (run / "config_resolved.yaml").write_text(OmegaConf.to_yaml(cfg))
    (run / "metrics.json").write_text(json.dumps({"status": status, "best_checkpoint": "checkpoints/best-epoch000.ckpt"}))
    (run / "split.json").write_text(json.dumps(split or {"train": ["a", "b"], "val": ["c"], "test": ["d"]}))
    (run / ".lock").write_text('{"pid": 1, "host": "earlier", "started": "then"}')
    for name, value in (monitored or {"last.ckpt": None}).items():
        torch.save({"state_dict": {}, "global_step": steps, "epoch": epochs - 1,
                    "loops": {"fit_loop": {"epoch_progress": {"current": {"processed": epochs}}}},
                    "monitored": {"key": "val/elbo", "mode": "max", "value": value, "step": steps}},
                   run / "checkpoints" / name)
    return cfg


def _every_file(run: Path) -> dict[str, bytes]:
    return {p.relative_to(run).as_posix(): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


def test_claim_of_a_finished_run_says_finished_refuses_fewer_epochs_and_continues_more(tmp_path):
    """Faults: the same command again on a finished run; then fewer epochs than its
    checkpoint's. Before: both trained (Lightning found nothing to do) and rewrote
    metrics.json, provenance.json and train.log, exit 0. Now: RunFinished (train.py: exit 0)
    and RunFolderError (exit 2), every byte of the folder as it was, the lock file included;
    more epochs are claimed and continue."""
    from embodied_tactile.run import runfolder

    run = tmp_path / "run"
    cfg = _fake_run(run, epochs=2, steps=8)
    before = _every_file(run)
    with pytest.raises(runfolder.RunFinished, match=rf"run folder {run} is finished \(2 epoch\(s\), step 8\)"):
        runfolder.claim(cfg, run)
    assert _every_file(run) == before
    with pytest.raises(runfolder.RunFolderError, match=r"trained for 2 epoch\(s\).*trainer.max_epochs=1 asks for fewer"):
        runfolder.claim(OmegaConf.merge(cfg, {"trainer": {"max_epochs": 1}}), run)
    assert _every_file(run) == before
    runfolder.claim(OmegaConf.merge(cfg, {"trainer": {"max_epochs": 3}}), run)  # more: claimed, the lock names us
    try:
        assert json.loads((run / ".lock").read_text())["pid"] == os.getpid()
    finally:
        runfolder.release(run)
    interrupted = tmp_path / "interrupted"  # stopped inside its last epoch: the same command resumes it
    runfolder.claim(_fake_run(interrupted, epochs=2, steps=7, status="interrupted"), interrupted)
    runfolder.release(interrupted)


@pytest.mark.slow  # finished_run and trainings by train.py's entry point
def test_same_command_on_a_finished_run_rewrites_nothing(finished_run, fast_data_dir, tmp_path):
    """The same command on a finished run: one line saying so, exit 0, every file of the
    folder bit for bit (.hydra/, train.log and .lock included). Fewer epochs: exit 2, one
    line, nothing written. More epochs: the run continues from its last.ckpt."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    args = (f"paths.data_dir={fast_data_dir}", f"hydra.run.dir={run}", "modality=acc", "threads=1",
            "callbacks.krr_alignment=null")
    before = _every_file(run)
    res = run_train(*args)
    assert res.stdout.strip().splitlines()[-1].startswith(f"train.py: run folder {run} is finished (1 epoch(s)")
    assert _every_file(run) == before
    res = run_train(*args, "trainer.max_epochs=0", check=False)
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr[-2000:]
    assert res.stderr.startswith(f"train.py: error: run folder {run} holds a run trained for 1 epoch(s)")
    assert _every_file(run) == before
    run_train(*args, "trainer.max_epochs=2")
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["status"] == "finished" and metrics["resumed_from"] == "checkpoints/last.ckpt"
    assert int(torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)["epoch"]) == 1


# ----------------------------------------------------------------------------- the split is part of the run
def test_split_file_with_a_test_trial_in_training_is_refused_at_start(tmp_path):
    """Fault: data.split_file names a trial both in train and in test. Before: the run
    trained on a trial it was scored on. Now: RunFolderError (exit 2) before anything is
    written, naming the trial and its sides."""
    from embodied_tactile.run import runfolder

    split = tmp_path / "split.json"
    split.write_text(json.dumps({"train": ["a", "b"], "val": ["c"], "test": ["d", "b"]}))
    run = tmp_path / "new"
    cfg = OmegaConf.create({"seed": 0, "trainer": {"max_epochs": 1}, "data": {"split_file": str(split)}})
    with pytest.raises(runfolder.RunFolderError, match=rf"split file {split} puts 1 trial\(s\) on two sides: b \(train and test\)"):
        runfolder.claim(cfg, run)
    assert not run.exists()  # the folder the claim made for its lock is gone again: nothing written


def test_resume_on_another_split_is_refused_naming_the_trials_that_move(tmp_path):
    """Fault: a resume given another split file (data.split_file may name any file). Before:
    the run continued training on its former test trials. Now: RunFolderError naming each
    trial that moves and its sides, the run's files as they were; a DataModule whose split
    differs from split.json after setup is refused the same way."""
    from types import SimpleNamespace

    from embodied_tactile.run import runfolder

    run = tmp_path / "run"
    cfg = _fake_run(run, epochs=1, steps=2, status="interrupted")
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"train": ["a", "d"], "val": ["c"], "test": ["b"]}))
    before = _every_file(run)
    with pytest.raises(runfolder.RunFolderError, match=r"moves 2 trial\(s\): b: train -> test; d: test -> train"):
        runfolder.claim(OmegaConf.merge(cfg, {"trainer": {"max_epochs": 2}, "data": {"split_file": str(other)}}), run)
    assert _every_file(run) == before

    def dm(**sides):
        return SimpleNamespace(split_file=None, **{f"{k}_set": SimpleNamespace(trials=[SimpleNamespace(name=n) for n in v])
                                                   for k, v in sides.items()})

    runfolder.keep_split(run, dm(train=["a", "b"], val=["c"], test=["d"]), resuming=True)  # the same: fine
    with pytest.raises(runfolder.RunFolderError, match=r"moves 1 trial\(s\): e: absent -> test"):
        runfolder.keep_split(run, dm(train=["a", "b"], val=["c"], test=["d", "e"]), resuming=True)
    with pytest.raises(runfolder.RunFolderError, match=r"a \(train and val\)"):
        runfolder.keep_split(tmp_path / "fresh", dm(train=["a"], val=["a"], test=["d"]), resuming=False)


def test_new_run_with_an_outside_split_file_keeps_a_copy(tmp_path):
    from types import SimpleNamespace

    from embodied_tactile.run import runfolder

    outside = tmp_path / "mine.json"
    outside.write_text(json.dumps({"train": ["a"], "val": [], "test": ["d"]}))
    run = tmp_path / "run"
    run.mkdir()
    dm = SimpleNamespace(split_file=str(outside), train_set=SimpleNamespace(trials=[SimpleNamespace(name="a")]),
                         val_set=SimpleNamespace(trials=[]), test_set=SimpleNamespace(trials=[SimpleNamespace(name="d")]))
    runfolder.keep_split(run, dm, resuming=False)
    assert json.loads((run / "split.json").read_text()) == json.loads(outside.read_text())


# ----------------------------------------------------------------------------- a run folder knows where it is
def test_best_is_chosen_over_every_checkpoint_by_its_stored_value(tmp_path, caplog):
    """Fault: metrics.json names a best checkpoint (and a best-*.ckpt is the newest) whose
    val/elbo is worse than another file's in the folder, e.g. after a resume in a moved
    folder wrote a new "best". Before: the named / newest file was evaluated. Now: the file
    whose own stored value is best, whatever its name; without stored values, the names."""
    from embodied_tactile.run import runfolder
    from embodied_tactile.eval.runs import find_checkpoint

    run = tmp_path / "run"
    _fake_run(run, epochs=3, steps=6, monitored={"best-epoch000.ckpt": -5.0, "epoch001.ckpt": -1.0,
                                                 "best-epoch002.ckpt": -3.0, "last.ckpt": None})
    os.utime(run / "checkpoints" / "best-epoch002.ckpt", (time.time() + 10, time.time() + 10))
    (run / "checkpoints" / "broken.ckpt").write_bytes(b"\0" * 50)
    path, rec = runfolder.best_checkpoint(run)
    assert path.name == "epoch001.ckpt" and rec["value"] == -1.0 and rec["key"] == "val/elbo"
    assert find_checkpoint(run, "best").name == "epoch001.ckpt"
    assert find_checkpoint(run, "last").name == "last.ckpt"
    old = tmp_path / "old"  # checkpoints written before the stored value: metrics.json's name, then the newest best*
    _fake_run(old, epochs=1, steps=2, monitored={"best-epoch000.ckpt": None, "last.ckpt": None})
    assert runfolder.best_checkpoint(old) is None and find_checkpoint(old, "best").name == "best-epoch000.ckpt"


def test_checkpoint_states_of_a_moved_folder_point_into_it():
    """Fault: a run folder moved before its resume. Before: Lightning dropped the monitored
    callback's best score (its saved dirpath differs) and wrote a worse "best" beside the
    real one. Now: the states are moved onto the folder's checkpoints/ before they load."""
    from types import SimpleNamespace

    from embodied_tactile.run.runfolder import FolderCheckpoints

    cb = SimpleNamespace(state_key="MC{val}", dirpath="/new/run/checkpoints")
    saved = {"dirpath": "/old/run/checkpoints", "best_model_path": "/old/run/checkpoints/best-epoch001.ckpt",
             "best_k_models": {"/old/run/checkpoints/best-epoch001.ckpt": -1.0}, "kth_value": -1.0,
             "last_model_path": "", "other": "/old/run/checkpoints-not/x"}
    ck = {"callbacks": {"MC{val}": saved}}
    FolderCheckpoints().on_load_checkpoint(SimpleNamespace(checkpoint_callbacks=[cb]), None, ck)
    assert ck["callbacks"]["MC{val}"] == {
        "dirpath": "/new/run/checkpoints", "best_model_path": "/new/run/checkpoints/best-epoch001.ckpt",
        "best_k_models": {"/new/run/checkpoints/best-epoch001.ckpt": -1.0}, "kth_value": -1.0,
        "last_model_path": "", "other": "/old/run/checkpoints-not/x"}


@pytest.mark.slow  # finished_run, a training by train.py's entry point and an evaluation
def test_moved_run_folder_resumes_and_evaluates_as_the_original(finished_run, fast_data_dir, tmp_path, evaluate_cli,
                                                                 capsys):
    """Fault: a run folder moved, then resumed and evaluated. Before: metrics.json named the
    old folder's files, the resume wrote a second "best" (Lightning's best score dropped).
    Now: metrics.json's paths are relative to the folder, one best file, and evaluation
    reads the moved folder's own files."""
    import shutil

    first = tmp_path / "first"
    shutil.copytree(finished_run, first)
    metrics = json.loads((first / "metrics.json").read_text())
    assert metrics["best_checkpoint"].startswith("checkpoints/best-") and metrics["last_checkpoint"] == "checkpoints/last.ckpt"
    moved = tmp_path / "elsewhere" / "moved"
    moved.parent.mkdir()
    shutil.move(first, moved)
    res = run_train(f"paths.data_dir={fast_data_dir}", f"hydra.run.dir={moved}", "modality=acc", "threads=1",
                    "callbacks.krr_alignment=null", "trainer.max_epochs=2")
    assert "dirpath has changed" not in res.stdout + res.stderr
    metrics = json.loads((moved / "metrics.json").read_text())
    assert metrics["status"] == "finished" and metrics["resumed_from"] == "checkpoints/last.ckpt"
    assert len(list((moved / "checkpoints").glob("best-*.ckpt"))) == 1
    from embodied_tactile.run.runfolder import best_checkpoint

    assert (moved / metrics["best_checkpoint"]) == best_checkpoint(moved)[0]
    assert evaluate_cli([str(moved), *EVAL_FAST, "checkpoint=best"]) == 0
    ev = json.loads((moved / "evaluation-best" / "evaluation.json").read_text())
    assert ev["runs"][0]["checkpoint"] == str(best_checkpoint(moved)[0])


# ----------------------------------------------------------------------------- an evaluation owns its output
def test_evaluation_output_is_owned_and_published_whole(tmp_path):
    """Faults: two evaluations into one folder; an evaluation that fails half way; a killed
    one's leftovers. Before: both wrote into <run>/evaluation (tables of one, results.json
    of the other), a failure left half a folder mixed with the previous one. Now: the second
    is refused naming the holder; a failure leaves the previous folder bit for bit; a
    published folder holds only what its evaluation wrote; a stale temporary folder goes."""
    from embodied_tactile.eval.pipeline import OwnedOutput
    from embodied_tactile.eval.runs import EvaluationError

    out = tmp_path / "run" / "evaluation"
    out.mkdir(parents=True)
    (out / "results.json").write_text("previous")
    (out / "table_old.md").write_text("previous")
    stale = tmp_path / "run" / ".evaluation.tmp-999999"
    stale.mkdir()
    first = OwnedOutput(out)
    with first as tmp:
        assert not stale.exists() and tmp.parent == out.parent and tmp != out
        with pytest.raises(EvaluationError, match=rf"{out} is being written by another evaluation \(pid {os.getpid()}"):
            with OwnedOutput(out):
                pass
        (tmp / "results.json").write_text("half")
        assert (out / "results.json").read_text() == "previous"  # a reader sees the previous evaluation until the end
    assert sorted(p.name for p in out.iterdir()) == ["results.json", "table_old.md"]  # not published: kept
    assert (out / "results.json").read_text() == "previous"
    with pytest.raises(RuntimeError):
        with OwnedOutput(out) as tmp:
            (tmp / "results.json").write_text("half")
            raise RuntimeError("failed half way")
    assert (out / "results.json").read_text() == "previous"
    second = OwnedOutput(out)
    with second as tmp:
        (tmp / "results.json").write_text("new")
        second.publish()
    assert sorted(p.name for p in out.iterdir()) == ["results.json"] and (out / "results.json").read_text() == "new"
    assert sorted(p.name for p in out.parent.iterdir()) == [".evaluation.lock", "evaluation"]
    mine = tmp_path / "mine"  # out= naming a folder of other files: never replaced
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    with pytest.raises(EvaluationError, match=rf"{mine} holds files an evaluation does not write \(notes.txt\)"):
        with OwnedOutput(mine):
            pass
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]


@pytest.mark.slow  # finished_run: a training by train.py's entry point, then evaluations
def test_evaluation_knows_the_runs_state(finished_run, tmp_path, evaluate_cli, capsys):
    """Faults: evaluating a run while its training holds the folder; evaluating an
    interrupted run. Before: both exit 0 and read like a finished run's numbers. Now: the
    first is refused (exit 2, one line naming the training's pid) unless allow_running=true,
    whose first printed line names the checkpoint used; an interrupted run is evaluated with
    its status in the first printed line and in results.json."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    holder = _hold_lock(run)
    try:
        assert evaluate_cli([str(run), *EVAL_FAST]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith(f"evaluate.py: error: run folder {run} is being trained (pid {holder.pid}")
        assert not (run / "evaluation").exists()
        assert evaluate_cli([str(run), *EVAL_FAST, "allow_running=true"]) == 0
        first = capsys.readouterr().out.splitlines()[0]
        assert first.startswith(f"evaluate.py: run {run} is being trained (pid {holder.pid}")
        assert "evaluating checkpoint checkpoints/last.ckpt (epoch(s) 1, step " in first  # the default: the final weights
        states = json.loads((run / "evaluation" / "results.json").read_text())["run_states"]
        assert states[str(run)]["status"] == "training"
    finally:
        holder.kill()
        holder.wait()
    metrics = json.loads((run / "metrics.json").read_text())
    (run / "metrics.json").write_text(json.dumps({**metrics, "status": "interrupted", "stopped_by": "SIGTERM"}))
    assert evaluate_cli([str(run), *EVAL_FAST]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith(f"evaluate.py: run {run} is interrupted (stopped by SIGTERM, final read-out not done); "
                            "evaluating checkpoint ")
    for name in ("results.json", "evaluation.json"):
        blob = json.loads((run / "evaluation" / name).read_text())
        state = blob["run_states"][str(run)] if name == "results.json" else blob["runs"][0]["run_state"]
        assert state["status"] == "interrupted" and state["checkpoint"].startswith("checkpoints/")
    (run / "metrics.json").write_text(json.dumps({**metrics, "status": "running"}))  # killed -9 during training
    assert evaluate_cli([str(run), *EVAL_FAST]) == 0
    assert capsys.readouterr().out.splitlines()[0].startswith(f"evaluate.py: run {run} is killed (metrics.json says running")


def test_stop_saves_after_the_step_under_way_before_any_validation_or_check(tmp_path):
    """Fault: SIGTERM in the middle of a training step, with a validation and an epoch-end
    check (as the KRR callback's) due after that step. Before: Lightning finished the step,
    then ran the validation, the epoch-end check and the final read-out (minutes of KRR on a
    real run) before last.ckpt was saved. Now: the step under way finishes, last.ckpt holds
    its weights, and the fit ends with StopRequested: no validation, check or read-out."""
    import lightning as L

    from embodied_tactile.run.runfolder import StopRequested, StopSignals

    class Tiny(L.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            self.lin = torch.nn.Linear(2, 1)

        def training_step(self, batch, batch_idx):
            if self.current_epoch == 0 and batch_idx == 2:
                os.kill(os.getpid(), signal.SIGTERM)  # arrives during the step
            return self.lin(batch[0]).pow(2).mean()

        def validation_step(self, batch, batch_idx):
            self.log("val/elbo", -self.lin(batch[0]).pow(2).mean())

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

    class Watch(L.Callback):  # what the KRR callback does at these hooks
        def __init__(self) -> None:
            self.calls: list[str] = []

        def on_validation_start(self, trainer, pl_module):
            self.calls.append("validation")

        def on_train_epoch_end(self, trainer, pl_module):
            self.calls.append("epoch check")

        def on_train_end(self, trainer, pl_module):
            self.calls.append("final read-out")

    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(20, 2)), batch_size=2)
    old = {s: signal.getsignal(s) for s in StopSignals.SIGNALS}
    last = tmp_path / "checkpoints" / "last.ckpt"
    stop, watch = StopSignals(last_path=last).install(), Watch()
    model = Tiny()
    trainer = L.Trainer(max_epochs=3, limit_train_batches=5, limit_val_batches=1, num_sanity_val_steps=0,
                        callbacks=[stop, watch], logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, accelerator="cpu")
    try:
        with pytest.raises(StopRequested, match="stopped by SIGTERM"):
            trainer.fit(model, data, data)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    assert watch.calls == []
    assert stop.saved == str(last) and stop.step == 3 and stop.exit_code() == 143
    ck = torch.load(last, map_location="cpu", weights_only=False)
    assert ck["global_step"] == 3  # the step under way (the third) finished and is in last.ckpt
    assert torch.equal(ck["state_dict"]["lin.weight"], model.lin.weight.detach())


def test_stop_at_an_epochs_end_after_the_stop_hook_skips_the_final_readout(tmp_path):
    """Fault: SIGTERM while a later callback works at an epoch's end (a checkpoint save, after
    the stop callback's own epoch-end hook). Before: Lightning's should_stop ended the fit
    quietly and the final read-out ran (minutes of KRR on a real run) before the process
    could exit. Now: the stop callback's on_train_end, first of the callbacks', saves
    last.ckpt and ends the fit with StopRequested: no read-out."""
    import lightning as L

    from embodied_tactile.run.runfolder import StopRequested, StopSignals

    class Tiny(L.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            self.lin = torch.nn.Linear(2, 1)

        def training_step(self, batch, batch_idx):
            return self.lin(batch[0]).pow(2).mean()

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

    class Late(L.Callback):  # after StopSignals in the list: the signal comes after its epoch-end hook
        def __init__(self) -> None:
            self.calls: list[str] = []

        def on_train_epoch_end(self, trainer, pl_module):
            self.calls.append(f"epoch {trainer.current_epoch} end")
            if trainer.current_epoch == 0:
                os.kill(os.getpid(), signal.SIGTERM)

        def on_train_end(self, trainer, pl_module):
            self.calls.append("final read-out")

    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(8, 2)), batch_size=2)
    old = {s: signal.getsignal(s) for s in StopSignals.SIGNALS}
    last = tmp_path / "checkpoints" / "last.ckpt"
    stop, late = StopSignals(last_path=last).install(), Late()
    trainer = L.Trainer(max_epochs=3, limit_train_batches=4, limit_val_batches=0, num_sanity_val_steps=0,
                        callbacks=[stop, late], logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, accelerator="cpu")
    try:
        with pytest.raises(StopRequested, match="stopped by SIGTERM"):
            trainer.fit(Tiny(), data)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    assert late.calls == ["epoch 0 end"]
    assert stop.phase == "training" and stop.saved == str(last) and stop.step == 4
    assert torch.load(last, map_location="cpu", weights_only=False)["global_step"] == 4


def test_evaluation_refuses_a_split_with_a_trial_on_two_sides(tmp_path):
    """Fault: a run's split.json edited so that a test trial is also a training trial.
    Before: evaluated, its scores including a trial the alignment was fitted on. Now:
    EvaluationError (exit 2) naming the file and the trial."""
    from embodied_tactile.eval.pipeline import parse_options
    from embodied_tactile.eval.runs import EvaluationError, Run, data_config

    run = tmp_path / "run"
    run.mkdir()
    (run / "split.json").write_text(json.dumps({"train": ["a", "b"], "val": [], "test": ["b", "c"]}))
    r = Run(run_dir=run, ckpt=run / "checkpoints" / "last.ckpt",
            cfg=OmegaConf.create({"data": {"data_dir": str(tmp_path), "source": "simulated"}}))
    with pytest.raises(EvaluationError, match=rf"{run / 'split.json'} puts 1 trial\(s\) on two sides \(b \(train and test\)\)"):
        data_config(r, parse_options([]))
