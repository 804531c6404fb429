"""train.py end to end: run folder, resume after SIGKILL, multirun, DDP, the ablation grid,
and the non-finite-loss guard, on the tiny debug scene. train.py's entry point runs in this
process (conftest.train_in_process) unless a test needs a process of its own (killed, DDP,
the joblib launcher); ``one_run`` is the train.py subprocess the other runs are checked against."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from conftest import REPO, train_in_process

ENV = {**os.environ, "WANDB_MODE": "disabled", "PYTHONUNBUFFERED": "1"}


def train_cmd(*overrides: str) -> list[str]:
    flags = [o for o in overrides if o.startswith("-")]
    return [sys.executable, str(REPO / "train.py"), *flags, "debug=fast", *[o for o in overrides if not o.startswith("-")]]


def run_train(*overrides: str, check: bool = True) -> subprocess.CompletedProcess:
    """``train.py debug=fast <overrides>`` in this process: its exit status and output."""
    res = train_in_process(*train_cmd(*overrides)[2:])
    if check and res.returncode != 0:
        raise AssertionError(f"train.py failed ({res.returncode}):\n{res.stdout[-3000:]}\n{res.stderr[-5000:]}")
    return res


def run_train_subprocess(*overrides: str, timeout: int = 300) -> subprocess.CompletedProcess:
    """``train.py debug=fast <overrides>`` in a fresh interpreter; a failure raises."""
    res = subprocess.run(train_cmd(*overrides), cwd=REPO, env=ENV, capture_output=True, text=True, timeout=timeout)
    if res.returncode != 0:
        raise AssertionError(f"train.py failed ({res.returncode}):\n{res.stdout[-3000:]}\n{res.stderr[-5000:]}")
    return res


@pytest.fixture(scope="module")
def data_dir(fast_data_dir) -> Path:
    return fast_data_dir


@pytest.fixture(scope="module")
def one_run(train_py_run) -> Path:
    """The session's train.py subprocess run (debug=fast, 2 epochs; conftest.train_py_run)."""
    return train_py_run[0]


@pytest.mark.slow  # one_run: a train.py subprocess
def test_run_folder_contents(one_run):
    for name in ("config_resolved.yaml", ".hydra/config.yaml", "metrics.json", "split.json", "provenance.json",
                 "checkpoints/last.ckpt", "csv/metrics.csv", "krr_history.jsonl"):
        assert (one_run / name).exists(), name
    assert list((one_run / "checkpoints").glob("best-*.ckpt"))
    metrics = json.loads((one_run / "metrics.json").read_text())
    assert metrics["status"] == "finished"
    assert np.isfinite(metrics["final_val"]["val/elbo"])
    assert metrics["peak_rss_bytes"] > 0 and metrics["train_wall_s"] > 0
    prov = json.loads((one_run / "provenance.json").read_text())
    assert prov["packages"]["torch"] and prov["packages"]["lightning"]
    assert "git_commit" in prov
    assert prov["cpu"]["cores"] >= 1 and prov["cpu"]["torch_capability"]
    split = json.loads((one_run / "split.json").read_text())
    assert split["train"] and split["val"] and not set(split["train"]) & set(split["val"])
    history = [json.loads(line) for line in (one_run / "krr_history.jsonl").read_text().splitlines()]
    assert history and "train_wall_time_s" in history[-1]
    # error against run time starts at t = 0 (the untrained network, with its floor read by the
    # run's read-out); 2 epochs, points: 8 -> a check after each epoch, then the final alignment
    assert history[0]["initial"] and history[0]["train_wall_time_s"] == 0.0 and history[0]["epoch"] == -1
    assert history[0]["floor"]["alignment"]["readout"] == history[-1]["alignment"]["readout"]
    assert [(h["epoch"], h["final"]) for h in history] == [(-1, False), (0, False), (1, False), (1, True)]


@pytest.mark.slow  # one_run: a train.py subprocess
def test_checkpoint_round_trip(one_run):
    from omegaconf import OmegaConf
    from hydra.utils import get_class

    cfg = OmegaConf.load(one_run / "config_resolved.yaml")
    cls = get_class(cfg.model._target_)
    model = cls.load_from_checkpoint(one_run / "checkpoints" / "last.ckpt", map_location="cpu")
    model.eval()
    torch.manual_seed(0)
    batch = {"obs": torch.rand(2, 5, 3, 28, 28), "actions": torch.zeros(2, 5, 6)}
    a = model.infer_latents(batch)
    b = cls.load_from_checkpoint(one_run / "checkpoints" / "last.ckpt", map_location="cpu").eval().infer_latents(batch)
    torch.testing.assert_close(a["y_mean"], b["y_mean"])
    assert a["y_mean"].shape == (2, 5, 16)


@pytest.mark.slow  # one_run: a train.py subprocess
def test_same_seed_same_weights_and_alignment(one_run, data_dir, tmp_path):
    """A run repeated with the same seed on the same data trains the same weights and scores
    the same held-out NMSE: two runs of one command differ only where the code changed (here
    the train.py subprocess and the same command in this process)."""
    again = tmp_path / "again"
    run_train(f"paths.data_dir={data_dir}", f"hydra.run.dir={again}", "trainer.max_epochs=2")
    a = torch.load(one_run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)["state_dict"]
    b = torch.load(again / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)["state_dict"]
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    final = [json.loads((r / "krr_history.jsonl").read_text().splitlines()[-1]) for r in (one_run, again)]
    assert final[0]["nmse"] == final[1]["nmse"]


@pytest.mark.slow  # one_run: a train.py subprocess
def test_checks_during_training_leave_the_weights_as_they_are(one_run, data_dir, tmp_path):
    """The KRR checks only read: a run checked once, on its final weights, with no row at
    t = 0 trains the same weights as the default's checks at t = 0 and over the epochs. Before,
    each check's loaders drew their seeds from torch's generator and moved the training's."""
    fewer = tmp_path / "fewer"
    run_train(f"paths.data_dir={data_dir}", f"hydra.run.dir={fewer}", "trainer.max_epochs=2",
              "callbacks.krr_alignment.initial=false", "callbacks.krr_alignment.points=1")
    rows = [json.loads(line) for line in (one_run / "krr_history.jsonl").read_text().splitlines()]
    assert rows[0]["epoch"] == -1 and len(rows) > len((fewer / "krr_history.jsonl").read_text().splitlines())
    a = torch.load(one_run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)["state_dict"]
    b = torch.load(fewer / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)["state_dict"]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)


def _ckpt_epoch(path: Path) -> int:
    return int(torch.load(path, map_location="cpu", weights_only=False)["epoch"])


@pytest.mark.slow  # trains with train.py in a subprocess (killed), then resumes in this process
def test_resume_after_sigkill(data_dir, tmp_path):
    run = tmp_path / "run"
    overrides = (f"paths.data_dir={data_dir}", f"hydra.run.dir={run}", "trainer.max_epochs=40", "callbacks.krr_alignment=null")
    proc = subprocess.Popen(train_cmd(*overrides), cwd=REPO, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    last = run / "checkpoints" / "last.ckpt"
    deadline = time.time() + 240
    try:
        while time.time() < deadline:
            if last.exists() and _ckpt_epoch(last) >= 2:
                break
            if proc.poll() is not None:
                pytest.fail("training ended before it could be killed")
            time.sleep(0.5)
        else:
            pytest.fail("no checkpoint of epoch >= 2 appeared")
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    killed_at = _ckpt_epoch(last)  # 0-based index of the last finished epoch
    killed = torch.load(last, map_location="cpu", weights_only=False)
    step_at_kill, wall_at_kill = int(killed["global_step"]), killed["fit_wall_s"]
    res = run_train(*overrides[:-2], "trainer.max_epochs=" + str(killed_at + 3), "callbacks.krr_alignment=null")
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["resumed_from"] and metrics["resumed_from"].endswith("last.ckpt")
    # its training time counts the killed start up to its checkpoint, and this start
    assert wall_at_kill > 0 and metrics["train_wall_s_this_start"] > 0
    assert metrics["train_wall_s"] == pytest.approx(wall_at_kill + metrics["train_wall_s_this_start"])
    assert "resuming from" in res.stderr + res.stdout
    # it continued after the last finished epoch: exactly 2 more epochs, none repeated
    steps_per_epoch = step_at_kill // (killed_at + 1)
    assert steps_per_epoch >= 1
    assert _ckpt_epoch(last) == killed_at + 2
    assert int(torch.load(last, map_location="cpu", weights_only=False)["global_step"]) == step_at_kill + 2 * steps_per_epoch
    csv = (run / "csv" / "metrics.csv").read_text().splitlines()
    assert len(csv) > 1
    pairs = [(r["step"], k) for r in _csv_rows(run / "csv" / "metrics.csv") for k, v in r.items()
             if v and k not in ("step", "epoch")]
    assert len(pairs) == len(set(pairs)), "a (step, metric) pair appears twice after the resume"


def _csv_rows(path: Path) -> list[dict]:
    import csv

    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow  # trains with train.py's entry point (in this process)
def test_resume_continues_csv_history_and_krr_wall_time(data_dir, tmp_path):
    """Train 2 epochs, restart in the same folder up to 4: csv/metrics.csv holds the rows of
    all 4 epochs, and krr_history.jsonl's training wall time keeps increasing."""
    run = tmp_path / "run"
    base = (f"paths.data_dir={data_dir}", f"hydra.run.dir={run}", "modality=acc", "callbacks.krr_alignment.every_n_epochs=1")
    run_train(*base, "trainer.max_epochs=2")
    rows_before = _csv_rows(run / "csv" / "metrics.csv")
    run_train(*base, "trainer.max_epochs=4")
    rows = _csv_rows(run / "csv" / "metrics.csv")
    assert rows[: len(rows_before)] == rows_before  # the earlier rows, unchanged, first
    epochs = {int(float(r["epoch"])) for r in rows if r.get("epoch")}
    assert epochs == {0, 1, 2, 3}
    train_epochs = sorted(int(float(r["epoch"])) for r in rows if r.get("train/loss"))
    assert train_epochs == [0, 0, 1, 1, 2, 2, 3, 3]  # debug=fast: 2 steps an epoch, none repeated
    assert not (run / "csv" / "metrics.discarded.csv").exists()
    history = [json.loads(line) for line in (run / "krr_history.jsonl").read_text().splitlines()]
    assert [h["epoch"] for h in history if not h["final"]] == [-1, 0, 1, 2, 3]  # one t = 0 row: the resume adds none
    # the training clock continues across the resume; a session's closing ("final") alignment
    # is taken after its last checkpoint, so the resumed session's clock starts before it
    during = [h for h in history if not h["final"]]
    wall = [h["train_wall_time_s"] for h in during]
    assert all(b > a for a, b in zip(wall, wall[1:])), wall
    cb_total = [h["callback_time_total_s"] for h in during]
    assert all(b > a for a, b in zip(cb_total, cb_total[1:])), cb_total
    assert history[-1]["final"] and history[-1]["train_wall_time_s"] >= wall[-1]


def test_resumable_csv_logger_moves_rows_of_discarded_training(tmp_path):
    """Rows logged after the checkpoint a run resumes from (training lost to a kill) move to
    metrics.discarded.csv; a fresh start moves them all; nothing is deleted."""
    from embodied_tactile.run.resume import ResumableCSVLogger

    folder = tmp_path / "csv"
    folder.mkdir()
    rows = [{"epoch": str(s // 2), "step": str(s), "train/loss": str(10.0 - s)} for s in range(6)]
    with open(folder / "metrics.csv", "w") as fh:
        fh.write("epoch,step,train/loss\n" + "".join(f"{r['epoch']},{r['step']},{r['train/loss']}\n" for r in rows))
    lg = ResumableCSVLogger(tmp_path, name="csv", version="", resume_step=3)
    lg.log_metrics({"train/loss": 0.5, "val/elbo": -1.0}, step=4)
    lg.save()
    kept = _csv_rows(folder / "metrics.csv")
    assert [r["step"] for r in kept] == ["0", "1", "2", "3", "4"]
    assert kept[:4] == [{**r, "val/elbo": ""} for r in rows[:4]] and kept[4]["val/elbo"] == "-1.0"
    assert [r["step"] for r in _csv_rows(folder / "metrics.discarded.csv")] == ["4", "5"]

    fresh = ResumableCSVLogger(tmp_path, name="csv", version="", resume_step=None)
    fresh.log_metrics({"train/loss": 7.0}, step=0)
    fresh.save()
    assert [r["train/loss"] for r in _csv_rows(folder / "metrics.csv")] == ["7.0"]
    assert [r["step"] for r in _csv_rows(folder / "metrics.discarded.csv")] == ["4", "5", "0", "1", "2", "3", "4"]


def test_resumed_csv_holds_one_row_per_step_and_metric(tmp_path):
    """A run killed after its checkpoint at step 3 had logged step 3's training row: the
    resumed run logs step 3 again and the file keeps one row of it (the new one); the row of
    other metrics at step 3 (logged before the checkpoint) stays."""
    from embodied_tactile.run.resume import ResumableCSVLogger

    folder = tmp_path / "csv"
    folder.mkdir()
    with open(folder / "metrics.csv", "w") as fh:
        fh.write("epoch,krr/nmse,step,train/loss\n" + "".join(f"{s // 2},,{s},{10.0 - s}\n" for s in range(4))
                 + ",0.9,3,\n")
    lg = ResumableCSVLogger(tmp_path, name="csv", version="", resume_step=3)
    lg.log_metrics({"train/loss": 0.5, "epoch": 1}, step=3)
    lg.log_metrics({"train/loss": 0.4, "epoch": 2}, step=4)
    lg.save()
    rows = _csv_rows(folder / "metrics.csv")
    assert [(r["step"], r["train/loss"], r["krr/nmse"]) for r in rows] == [
        ("0", "10.0", ""), ("1", "9.0", ""), ("2", "8.0", ""), ("3", "", "0.9"), ("3", "0.5", ""), ("4", "0.4", "")]
    assert [(r["step"], r["train/loss"]) for r in _csv_rows(folder / "metrics.discarded.csv")] == [("3", "7.0")]
    lg.log_metrics({"train/loss": 0.3}, step=5)  # later saves leave the run's own rows alone
    lg.save()
    assert [r["step"] for r in _csv_rows(folder / "metrics.csv")] == ["0", "1", "2", "3", "3", "4", "5"]


def _fake_checkpoint(path: Path, step: int, mtime: float) -> None:
    torch.save({"state_dict": {}, "global_step": step, "epoch": step}, path)
    os.utime(path, (mtime, mtime))


def test_find_resume_checkpoint_skips_unreadable_files(tmp_path, caplog):
    from embodied_tactile.run.resume import find_resume_checkpoint

    ck = tmp_path / "checkpoints"
    ck.mkdir()
    assert find_resume_checkpoint(tmp_path) is None
    _fake_checkpoint(ck / "best-epoch000.ckpt", 1, 1000.0)
    _fake_checkpoint(ck / "best-epoch001.ckpt", 2, 2000.0)
    _fake_checkpoint(ck / "last.ckpt", 3, 1500.0)
    assert find_resume_checkpoint(tmp_path) == ck / "last.ckpt"  # last.ckpt first when readable
    data = (ck / "last.ckpt").read_bytes()
    (ck / "last.ckpt").write_bytes(data[: len(data) // 2])  # truncated
    (ck / "best-epoch001.ckpt").write_bytes(b"garbage" * 10)
    with caplog.at_level("WARNING", logger="embodied_tactile.run.resume"):
        assert find_resume_checkpoint(tmp_path) == ck / "best-epoch000.ckpt"
    text = caplog.text
    assert str(ck / "last.ckpt") in text and str(ck / "best-epoch001.ckpt") in text
    # the bad files are set aside, not deleted, so that Lightning writes a fresh last.ckpt
    assert (ck / "last.ckpt.unreadable").read_bytes() == data[: len(data) // 2]
    assert (ck / "best-epoch001.ckpt.unreadable").read_bytes() == b"garbage" * 10
    assert sorted(p.name for p in ck.glob("*.ckpt")) == ["best-epoch000.ckpt"]
    torch.save({"weights": 1}, ck / "best-epoch000.ckpt")  # readable, but not a Lightning checkpoint
    (ck / "last.ckpt").write_bytes(b"")  # a second bad last.ckpt does not overwrite the first
    caplog.clear()
    with caplog.at_level("WARNING", logger="embodied_tactile.run.resume"):
        assert find_resume_checkpoint(tmp_path) is None
    assert "not a Lightning checkpoint" in caplog.text and "starts from scratch" in caplog.text
    assert (ck / "last.ckpt.unreadable-1").read_bytes() == b""
    assert (ck / "last.ckpt.unreadable").read_bytes() == data[: len(data) // 2]


@pytest.mark.slow  # trains with train.py's entry point (in this process)
def test_corrupt_last_checkpoint_falls_back_or_starts_fresh(one_run, data_dir, tmp_path):
    """A truncated last.ckpt: the restart continues from the newest readable checkpoint and
    names the bad file; with no readable checkpoint it starts afresh, never crashes."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(one_run, run)
    last = run / "checkpoints" / "last.ckpt"
    best = run / "checkpoints" / "epoch001.ckpt"  # an older good checkpoint (the run's best may be absent)
    shutil.copy2(last, best)
    last.write_bytes(last.read_bytes()[:1000])
    overrides = (f"paths.data_dir={data_dir}", f"hydra.run.dir={run}", "callbacks.krr_alignment=null")
    res = run_train(*overrides, "trainer.max_epochs=3")
    out = res.stdout + res.stderr
    assert f"cannot resume from {last}" in out
    assert len((run / "checkpoints" / "last.ckpt.unreadable").read_bytes()) == 1000  # kept aside
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["status"] == "finished" and metrics["resumed_from"] == "checkpoints/epoch001.ckpt"
    assert _ckpt_epoch(last) == _ckpt_epoch(best) + 1  # one more epoch after the good one, into last.ckpt
    step_best = int(torch.load(best, map_location="cpu", weights_only=False)["global_step"])

    corrupted = list((run / "checkpoints").glob("*.ckpt"))
    for p in corrupted:
        p.write_bytes(b"\0" * 64)
    res = run_train(*overrides, "trainer.max_epochs=1")
    out = res.stdout + res.stderr
    assert f"cannot resume from {last}" in out and "starts from scratch" in out
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["status"] == "finished" and metrics["resumed_from"] is None
    assert int(torch.load(last, map_location="cpu", weights_only=False)["global_step"]) == step_best // 2  # 1 of 2 epochs
    # every bad file kept: the truncated last.ckpt set aside before, and each one corrupted here
    assert len(list((run / "checkpoints").glob("*.unreadable*"))) == 1 + len(corrupted)


@pytest.mark.slow  # train.py -m (Hydra multirun, in this process)
def test_multirun_two_modalities(data_dir, tmp_path):
    # logger=none as well: the default callbacks include a LearningRateMonitor, which
    # Lightning refuses without a logger; train.py must drop it
    sweep = tmp_path / "multi"
    run_train("-m", "modality=acc,fsr_t", "logger=none", f"paths.data_dir={data_dir}", f"hydra.sweep.dir={sweep}")
    subdirs = sorted(p.name for p in sweep.iterdir() if p.is_dir())
    names = ["logger=none,modality=acc", "logger=none,modality=fsr_t"]
    assert subdirs == names
    for name in names:
        m = json.loads((sweep / name / "metrics.json").read_text())
        assert m["status"] == "finished"
        assert m["data"]["channels"] == [name.split("=")[-1]]


@pytest.mark.slow  # train.py with DDP (two processes)
def test_ddp_two_cpu_processes(data_dir, tmp_path):
    run = tmp_path / "ddp"
    res = run_train_subprocess("trainer=ddp", f"paths.data_dir={data_dir}", f"hydra.run.dir={run}", "callbacks.krr_alignment=null",
                               timeout=400)
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["status"] == "finished" and np.isfinite(metrics["final_val"]["val/elbo"])
    assert "world_size=2" in res.stdout + res.stderr or "distributed_backend=gloo" in res.stdout + res.stderr


@pytest.mark.slow  # trains with train.py's entry point (in this process)
def test_nonfinite_loss_stops_and_keeps_last_checkpoint(data_dir, tmp_path):
    """Overflowing (finite) inputs make the loss non-finite: the run stops, names step and
    term, and last.ckpt from the previous epoch survives unchanged."""
    import shutil

    d = tmp_path / "data"
    shutil.copytree(data_dir, d)
    run = tmp_path / "run"
    base = (f"paths.data_dir={d}", f"hydra.run.dir={run}", "modality=acc", "callbacks.krr_alignment=null")
    run_train(*base, "trainer.max_epochs=1")
    last = run / "checkpoints" / "last.ckpt"
    before = last.read_bytes()
    from embodied_tactile.data.cache import _crc

    # overflowing inputs with valid checksums (not a damaged cache), not constant (a constant
    # channel is refused before training: ConstantChannelError)
    for cache in (d / "cache").glob("acc-*.h5"):
        with h5py.File(cache, "a") as f:
            for g in f["trials"].values():
                g["acc"][...] = g["acc"][()] * 1e30 + 1e30
                g["acc"].attrs["crc32"] = _crc(g["acc"][()])
    res = run_train(*base, "trainer.max_epochs=3", check=False)
    assert res.returncode != 0
    out = res.stdout + res.stderr
    assert "non-finite loss at step" in out and "nll=" in out
    assert "(train batch 0, finite inputs of trial 'obj" in out  # the batch's trials, named
    assert last.read_bytes() == before
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["status"] == "failed" and "non-finite" in metrics["error"]


@pytest.mark.slow  # train.py -m with the joblib launcher
def test_joblib_launcher_parallel_jobs_share_a_fresh_data_dir(tmp_path):
    """Two sweep jobs in parallel (joblib) on an empty data folder: both prepare the same raw
    file; the data-folder lock serialises that, and both runs finish."""
    sweep = tmp_path / "multi"
    run_train_subprocess("-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "modality=acc,fsr_t",
                         "trainer.max_epochs=1", f"paths.data_dir={tmp_path / 'data'}", f"hydra.sweep.dir={sweep}",
                         "callbacks.krr_alignment=null", timeout=400)
    for name in ("modality=acc", "modality=fsr_t"):
        (job,) = [p for p in sweep.iterdir() if name in p.name.split(",")]  # folder named after its overrides
        assert json.loads((job / "metrics.json").read_text())["status"] == "finished"


@pytest.mark.slow  # trains with train.py's entry point (in this process)
def test_last_checkpoint_follows_every_epoch_even_when_validation_worsens(data_dir, tmp_path):
    """last.ckpt is the last epoch's state whatever val/elbo did (Lightning 2.6's save_last
    refreshes it only together with a best checkpoint), so a resume never repeats epochs."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    run = tmp_path / "run"
    run_train(f"paths.data_dir={data_dir}", f"hydra.run.dir={run}", "trainer.max_epochs=4", "callbacks.krr_alignment=null")
    best = [p for p in (run / "checkpoints").glob("best-*.ckpt")]
    assert len(best) == 1 and _ckpt_epoch(run / "checkpoints" / "last.ckpt") == 3
    # force a best checkpoint that the next epochs cannot beat: last.ckpt must still move on
    ck = torch.load(best[0], map_location="cpu", weights_only=False)
    for key, state in ck["callbacks"].items():
        if key.startswith("ModelCheckpoint") and "'monitor': 'val/elbo'" in key:
            state["best_model_score"] = torch.tensor(1e30)
            state["best_k_models"] = {k: torch.tensor(1e30) for k in state["best_k_models"]}
    last = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    last["callbacks"] = ck["callbacks"] | {k: v for k, v in last["callbacks"].items() if "'monitor': None" in k}
    torch.save(last, run / "checkpoints" / "last.ckpt")
    run_train(f"paths.data_dir={data_dir}", f"hydra.run.dir={run}", "trainer.max_epochs=6", "callbacks.krr_alignment=null")
    assert _ckpt_epoch(run / "checkpoints" / "last.ckpt") == 5
    assert ModelCheckpoint  # the class whose save_last behaviour this guards against
