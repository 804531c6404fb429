"""The end of `python train.py` / `python train.py -m`, and `python evaluate.py` without a
path (the most recent run under <paths.log_dir>/train)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import REPO

sys.path.insert(0, str(REPO))
import evaluate as ev  # noqa: E402  (the script's main(); its logic is in embodied_tactile.eval)

from embodied_tactile.run.summary import (latest_run, multirun_summary_lines,  # noqa: E402
                                      run_summary_lines)

ENV = {**os.environ, "WANDB_MODE": "disabled", "PYTHONUNBUFFERED": "1"}


def _row(step, overall, per):
    return {"epoch": step // 2, "step": step, "train_wall_time_s": 10.0 * step, "n_test": 8,
            "nmse": dict(zip(("spatial_frequency", "amplitude", "stiffness", "heterogeneity"), per)),
            "nmse_overall": overall}


def fake_run(d: Path, *, ckpt=True, rows=((6, 0.5, (0.4, 0.5, 0.6, 0.5)), (12, 0.1223, (0.1, 0.2, 0.0892, 0.1)))):
    d.mkdir(parents=True)
    (d / "config_resolved.yaml").write_text("seed: 0\n")
    (d / "provenance.json").write_text("{}")
    if ckpt:
        (d / "checkpoints").mkdir()
        (d / "checkpoints" / "last.ckpt").write_bytes(b"x")
    (d / "krr_history.jsonl").write_text("".join(json.dumps(_row(*r)) + "\n" for r in rows))
    m = {"status": "finished", "train_wall_s": 221.4, "data_prepare_s": 12.0,
         "best_checkpoint": str(d / "checkpoints" / "best-epoch011.ckpt") if ckpt else None}
    (d / "metrics.json").write_text(json.dumps(m))
    return d


def test_run_summary_lines(tmp_path):
    run = fake_run(tmp_path / "logs" / "train" / "runs" / "2026-01-01_00-00-00-000000")
    lines = run_summary_lines(run, cwd=tmp_path)
    text = "\n".join(lines)
    rel = "logs/train/runs/2026-01-01_00-00-00-000000"
    assert f"run finished: {rel}" in text
    # the LAST alignment of the history, overall and per factor
    assert "overall 0.1223" in text and "step 12" in text and "8 held-out sequences" in text
    assert "spatial freq. 0.1  amplitude 0.2  stiffness 0.0892  heterogeneity 0.1" in text
    assert "training time: 3 min 41 s (data preparation 12.0 s on top)" in text
    assert f"checkpoint:    {rel}/checkpoints/best-epoch011.ckpt" in text
    assert f"{rel}/{{metrics.json,krr_history.jsonl}}" in text
    assert f"{rel}/evaluation/" in text
    assert lines[-2] == f"next:          python evaluate.py {rel}"
    # outside the cwd: absolute paths, quoted for the shell
    odd = fake_run(tmp_path / "a run")
    assert run_summary_lines(odd, cwd=REPO)[-2].endswith(f"python evaluate.py '{odd}'")


PAPER_CONFIG = """seed: 0
data: {split: trial}
modality: {name: multi_l}
model: {net: {prior: {labels: true, learn_embedding: true}, y_update: direct, obs_dropout: 0.0}}
annealing: {schedule: {y_weight: 1.0}}
"""


def test_the_last_lines_say_what_the_number_means(tmp_path, monkeypatch):
    """After the run's block: the final alignment beside the untrained network (step 0) and the
    mean predictor, whole trajectory and last frame; what the split measures; the command for
    objects never touched with the number the learning curve's scores file holds for this
    recipe (mean over its seeds at 256 training objects)."""
    import embodied_tactile.run.summary as S

    initial = {**_row(0, 0.998, (1.0,) * 4), "initial": True, "nmse_last_overall": 0.988}
    final = {**_row(480, 0.1234, (0.1,) * 4), "final": True, "n_test": 32, "nmse_last_overall": 0.0987,
             "nmse_mean_predictor_overall": 1.0031}
    run = tmp_path / "run"
    run.mkdir()
    (run / "config_resolved.yaml").write_text(PAPER_CONFIG)
    (run / "krr_history.jsonl").write_text("".join(json.dumps(r) + "\n" for r in (initial, final)))
    method = "Latent Filter multi_l (labels, learned codes, y_weight 1, y direct)"
    scores = tmp_path / "scores.json"
    scores.write_text(json.dumps([{"method": method, "n_objects": 256, "seed": s, "trajectory": {"overall": w},
                                   "last_step": {"overall": l}} for s, w, l in ((0, 1.0, 0.7), (1, 1.2, 0.8))]
                                 + [{"method": method, "n_objects": 24, "seed": 0, "trajectory": {"overall": 9.0},
                                     "last_step": {"overall": 9.0}}]))
    monkeypatch.setattr(S, "POPULATION_SCORES", scores)
    lines = S.protocol_lines(run)
    text = "\n".join(lines)
    assert lines[0] == f"{method} on 32 held-out trials of the training objects (data.split=trial, the paper's protocol):"
    assert [ln.split()[-2:] for ln in lines[2:5]] == [["0.1234", "0.0987"], ["0.998", "0.988"], ["1.003", "1.003"]]
    assert "untrained" in lines[3] and "mean predictor" in lines[4]
    assert "measures recognition" in text
    assert ("Objects never touched: python train.py experiment=population; measured: " + method
            + ": whole trajectory 1.100, last frame 0.750 (2 seeds") in text and "docs/generalisation.md" in text
    # the block closes the run's summary; another split says what it measures; an unmeasured recipe says so
    assert run_summary_lines(run, cwd=tmp_path)[-len(lines) - 1:-1] == lines
    (run / "config_resolved.yaml").write_text(PAPER_CONFIG.replace("trial", "object").replace("true", "false"))
    text = "\n".join(S.protocol_lines(run))
    assert "generalisation to objects never touched" in text and "recognition" not in text
    assert "not yet measured for Latent Filter multi_l (no labels, y_weight 1, y direct)" in text


def test_run_summary_without_alignment(tmp_path):
    run = fake_run(tmp_path / "r", rows=())
    text = "\n".join(run_summary_lines(run, cwd=tmp_path))
    assert "no KRR alignment in this run" in text and "python evaluate.py r" in text


def test_multirun_summary_lines(tmp_path):
    sweep = tmp_path / "multi"
    fake_run(sweep / "modality=acc")
    fake_run(sweep / "modality=fsr_t", ckpt=False, rows=())
    (sweep / "modality=fsr_t" / "metrics.json").write_text(json.dumps({"status": "failed"}))
    lines = multirun_summary_lines(sweep, cwd=tmp_path)
    assert lines[1] == "multirun: 2 job(s), 1 finished, 1 not: multi"
    assert any(ln.split()[:3] == ["modality=acc", "finished", "0.1223"] for ln in lines)
    assert any(ln.split()[:3] == ["modality=fsr_t", "failed", "n/a"] for ln in lines)
    assert lines[-2] == "next: python evaluate.py multi"


@pytest.mark.slow  # train.py subprocess
def test_train_ends_with_the_summary(tmp_path, fast_data_dir):
    run = tmp_path / "run"
    res = subprocess.run([sys.executable, str(REPO / "train.py"), "debug=fast", "trainer.max_epochs=2",
                          f"paths.data_dir={fast_data_dir}", f"hydra.run.dir={run}"],
                         cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    out = res.stdout.strip().splitlines()
    start = out.index("run finished: run") - 1
    tail, protocol = out[start:start + 10], out[start + 10:]
    hist = [json.loads(x) for x in (run / "krr_history.jsonl").read_text().splitlines()]
    assert tail[0].startswith("-----") and tail[-1].startswith("-----")
    assert f"overall {hist[-1]['nmse_overall']:.4g}" in tail[2]
    assert tail[3].startswith("  per factor: spatial freq. ")
    assert tail[4].startswith("training time: ")
    assert tail[5].startswith("checkpoint:    run/checkpoints/")
    assert tail[-2] == "next:          python evaluate.py run"
    # then what the number means, closing the output
    assert protocol[-1].startswith("-----") and "held-out trials of the training objects" in protocol[0]
    assert protocol[2].split()[-2:] == [f"{hist[-1]['nmse_overall']:.4g}", f"{hist[-1]['nmse_last_overall']:.4g}"]
    assert "untrained" in protocol[3] and "mean predictor" in protocol[4]
    assert "measures recognition" in protocol[5] and protocol[6].startswith("Objects never touched: python train.py")


@pytest.mark.slow  # train.py -m (Hydra multirun) subprocess
def test_multirun_ends_with_its_folder_and_evaluate_command(tmp_path, fast_data_dir):
    sweep = tmp_path / "multi"
    res = subprocess.run([sys.executable, str(REPO / "train.py"), "-m", "debug=fast", "modality=acc",
                          "callbacks.krr_alignment=null", f"paths.data_dir={fast_data_dir}", f"hydra.sweep.dir={sweep}"],
                         cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    out = res.stdout.strip().splitlines()
    assert out[-2] == "next: python evaluate.py multi"
    assert "multirun: 1 job(s), 1 finished, 0 not: multi" in out
    assert not any(ln.startswith("run finished:") for ln in out)  # no per-job block in a multirun


# ----------------------------------------------------------------------------- latest run
def _age(folder: Path, t: float) -> None:
    for f in folder.rglob("*"):
        os.utime(f, (t, t))


def test_latest_run_by_start_time(tmp_path):
    train = tmp_path / "logs" / "train"
    now = time.time()
    old = fake_run(train / "runs" / "b_old")
    multi = tmp_path / "logs" / "train" / "multiruns" / "m"
    fake_run(multi / "modality=acc")
    newest_failed = fake_run(train / "runs" / "a_newest_failed", ckpt=False)
    _age(old, now - 300)
    _age(multi, now - 200)
    _age(newest_failed, now - 100)
    (old / "evaluation").mkdir()  # evaluating an old run must not make it "recent"
    folder, kind, passed = latest_run(train)
    assert (folder, kind, passed) == (multi, "multirun", [newest_failed])
    _age(old, now - 50)
    assert latest_run(train)[:2] == (old, "run")


def test_evaluate_without_path_picks_latest_and_says_so(tmp_path, monkeypatch, capsys):
    log_dir = tmp_path / "mylogs"
    run = fake_run(log_dir / "train" / "runs" / "r1")
    seen = {}
    monkeypatch.setattr(ev, "evaluate", lambda path, overrides: seen.update(path=path, overrides=overrides))
    assert ev.main([f"paths.log_dir={log_dir}", "umap=false"]) == 0
    assert seen == {"path": str(run), "overrides": ["umap=false"]}
    assert f"evaluating the most recent run under {log_dir / 'train'}: {run}" in capsys.readouterr().out


def test_evaluate_without_path_default_log_dir_from_train_config(tmp_path, monkeypatch, capsys):
    """No paths.log_dir given: the one train.py composes (configs/train.yaml: logs), relative to the cwd."""
    monkeypatch.chdir(tmp_path)
    run = fake_run(tmp_path / "logs" / "train" / "runs" / "r1")
    seen = {}
    monkeypatch.setattr(ev, "evaluate", lambda path, overrides: seen.update(path=path))
    assert ev.main([]) == 0
    assert Path(seen["path"]).resolve() == run.resolve()
    assert "logs/train/runs/r1" in capsys.readouterr().out


def test_evaluate_without_path_and_no_run_is_a_clear_error(tmp_path, capsys):
    assert ev.main([f"paths.log_dir={tmp_path}"]) == 2
    err = capsys.readouterr().err
    assert f"no trained run under {tmp_path}/train/runs or {tmp_path}/train/multiruns" in err
    fake_run(tmp_path / "train" / "runs" / "killed", ckpt=False)
    assert ev.main([f"paths.log_dir={tmp_path}"]) == 2
    assert "none with a checkpoint" in capsys.readouterr().err
