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
    """A finished acc run of one epoch (the cheapest train.py run)."""
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


@pytest.mark.slow  # finished_run: a train.py subprocess
def test_refused_restart_with_other_modality_keeps_the_finished_run(finished_run, fast_data_dir):
    """Fault: a finished run folder re-run with another modality, actions and seed. Before:
    state_dict mismatch, exit 1, metrics.json rewritten "failed", config_resolved.yaml
    rewritten. Now: exit 2 before anything is written, the keys named."""
    before = _digests(finished_run)
    ckpts = {p.name: p.read_bytes() for p in (finished_run / "checkpoints").iterdir()}
    res = run_train(f"paths.data_dir={fast_data_dir}", f"hydra.run.dir={finished_run}", "modality=fsr_t", "seed=3",
                    "data.actions=[0,10]", "threads=1", check=False, timeout=120)
    assert res.returncode == 2, res.stderr[-2000:]
    err = res.stderr.strip().splitlines()[-1]
    assert err.startswith("train.py: error: run folder") and str(finished_run) in err
    for key in ("modality.name", "data.channels", "data.actions", "seed"):
        assert key in err, key
    assert "Traceback" not in res.stderr
    assert _digests(finished_run) == before
    assert {p.name: p.read_bytes() for p in (finished_run / "checkpoints").iterdir()} == ckpts
    assert json.loads((finished_run / "metrics.json").read_text())["status"] == "finished"


@pytest.mark.slow  # finished_run: a train.py subprocess
def test_bad_setting_in_a_finished_run_folder_keeps_its_metrics(finished_run, fast_data_dir):
    before = _digests(finished_run)
    res = run_train(f"paths.data_dir={fast_data_dir}", f"hydra.run.dir={finished_run}", "modality=acc", "data.batch_size=0",
                    check=False, timeout=120)
    assert res.returncode == 2 and "data.batch_size=0" in res.stderr
    assert _digests(finished_run) == before


# ----------------------------------------------------------------------------- lock
def _hold_lock(run: Path) -> subprocess.Popen:
    """Another process holding the run folder's lock (as a running training does)."""
    code = ("import sys, time; from embodied_tactile.run import runfolder; runfolder.lock(sys.argv[1]); "
            "print('held', flush=True); time.sleep(120)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(run)], env={**ENV, "PYTHONPATH": str(REPO / "src")},
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


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


@pytest.mark.slow  # finished_run: a train.py subprocess
def test_second_training_in_a_running_folder_is_refused(finished_run, fast_data_dir):
    """Fault: two trainings in one run folder at once. Before: both exit 0, every step twice
    in the CSV, best-epoch003.ckpt beside best-epoch003-v1.ckpt. Now: the second exits 2
    naming the holder's pid, and writes nothing."""
    before = _digests(finished_run)
    rows = (finished_run / "csv" / "metrics.csv").read_bytes()
    holder = _hold_lock(finished_run)
    try:
        res = run_train(f"paths.data_dir={fast_data_dir}", f"hydra.run.dir={finished_run}", "modality=acc",
                        "trainer.max_epochs=3", check=False, timeout=120)
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
    from embodied_tactile.run.runtime import ResumableCSVLogger

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


@pytest.mark.slow
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


@pytest.mark.slow  # finished_run: a train.py subprocess
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


@pytest.mark.slow  # finished_run: a train.py subprocess
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
    with pytest.raises(EvaluationError, match=rf"no checkpoint in run folder {run} that can be read.*{best.name}"):
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


@pytest.mark.slow  # finished_run: a train.py subprocess
def test_copied_run_folder_never_reads_the_original_checkpoints(finished_run, tmp_path, evaluate_cli, capsys):
    """Fault: a copy of a run folder whose checkpoints were deleted. Before: exit 0, "same
    weights", the original's checkpoint read through metrics.json's absolute path. Now: the
    checkpoints are looked up inside the folder evaluated; none there: exit 2 naming it."""
    import shutil

    from embodied_tactile.eval.runs import find_checkpoint

    copy = tmp_path / "copy"
    shutil.copytree(finished_run, copy)
    assert json.loads((copy / "metrics.json").read_text())["best_checkpoint"].startswith(str(finished_run))
    assert find_checkpoint(copy, "best").parent == copy / "checkpoints"
    shutil.rmtree(copy / "checkpoints")
    assert evaluate_cli([str(copy), *EVAL_FAST]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith(f"evaluate.py: error: no checkpoint in run folder {copy} ")
    assert not (copy / "evaluation").exists()


@pytest.mark.slow  # finished_run: a train.py subprocess
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


@pytest.mark.slow
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
                    "trainer.max_epochs=2", check=False, timeout=240)
    assert res.returncode == 2, res.stderr[-2000:]
    assert res.stderr.strip().splitlines()[-1].startswith(f"train.py: error: run folder {run} was trained on other data: {raw}")
    assert _digests(run, ("metrics.json", "config_resolved.yaml", "provenance.json")) == before
    assert evaluate_cli([str(run), *EVAL_FAST, "allow_changed_data=true"]) == 0
    out = capsys.readouterr()
    ev = json.loads((run / "evaluation" / "evaluation.json").read_text())
    other = ev["runs"][0]["training_final_alignment"]["other"]
    assert other and other[0].startswith("the data changed since training") and str(raw) in other[0]
    assert "another measurement: the data changed since training" in out.out + out.err


def test_stop_signal_outside_the_training_steps_raises_and_inside_sets_should_stop():
    """SIGTERM during data preparation ends the run as interrupted (StopRequested, which
    train.py turns into exit 143); during the steps it only asks Lightning to stop."""
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
        stop.on_train_start(trainer, None)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.1)
        assert trainer.should_stop and stop.exit_code() == 130 and stop.name == "SIGINT"
    finally:
        for s, h in old.items():
            signal.signal(s, h)
