"""The end of `python train.py` / `python train.py -m`, and `python evaluate.py` without a
path (the most recent run under <paths.log_dir>/train)."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import pytest

from conftest import REPO, train_in_process

sys.path.insert(0, str(REPO))
import evaluate as ev  # noqa: E402
from embodied_tactile.eval import pipeline  # noqa: E402  (what evaluate.py's main calls, imported when it runs: patched there)

from embodied_tactile.run.summary import (latest_run, multirun_summary_lines,  # noqa: E402
                                      run_summary_lines)


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
         "best_checkpoint": str(d / "checkpoints" / "best-epoch011.ckpt") if ckpt else None,
         "last_checkpoint": str(d / "checkpoints" / "last.ckpt") if ckpt else None}
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
    assert "training time: 3 min 41 s (data preparation 12.0 s on top)\n" in text + "\n"  # no CPU recorded: none named
    (run / "provenance.json").write_text(json.dumps({"cpu": {"model": "AMD EPYC", "cores": 2}}))
    m = {**json.loads((run / "metrics.json").read_text()), "krr_final": {"torch_threads": 1}}
    assert ("training time: 3 min 41 s (data preparation 12.0 s on top), on AMD EPYC, 1 torch thread"
            in run_summary_lines(run, m, cwd=tmp_path))
    # threads=auto re-counts the threads each epoch: every count the checks ran at, in order
    rows = [{**_row(6, 0.5, (0.4, 0.5, 0.6, 0.5)), "torch_threads": 2}, {**_row(12, 0.2, (0.2,) * 4), "torch_threads": 2},
            {**_row(18, 0.1223, (0.1, 0.2, 0.0892, 0.1)), "torch_threads": 1}]
    (run / "krr_history.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert ("training time: 3 min 41 s (data preparation 12.0 s on top), on AMD EPYC, 2 then 1 torch threads "
            "(1 from step 18)" in run_summary_lines(run, m, cwd=tmp_path))
    m2 = {**m, "krr_final": {"torch_threads": 2}}
    assert any(line.endswith("2 then 1 then 2 torch threads (1 from step 18, 2 in the final read-out)")
               for line in run_summary_lines(run, m2, cwd=tmp_path))
    (run / "krr_history.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows[:2]))
    assert any(line.endswith("on AMD EPYC, 2 then 1 torch threads (1 in the final read-out)")
               for line in run_summary_lines(run, m, cwd=tmp_path))
    (run / "krr_history.jsonl").write_text("".join(json.dumps(_row(*r)) + "\n" for r in ((6, 0.5, (0.4, 0.5, 0.6, 0.5)), (12, 0.1223, (0.1, 0.2, 0.0892, 0.1)))))
    # the final weights (the read-out printed above, evaluate.py's default), the best named beside them
    assert f"checkpoint:    {rel}/checkpoints/last.ckpt (lowest validation loss: best-epoch011.ckpt)" in text
    assert f"{rel}/{{metrics.json,krr_history.jsonl}}" in text
    assert f"{rel}/evaluation/" in text
    assert lines[-2] == f"next:          python evaluate.py {rel}"
    # outside the cwd: absolute paths, quoted for the shell
    odd = fake_run(tmp_path / "a run")
    assert run_summary_lines(odd, cwd=REPO)[-2].endswith(f"python evaluate.py '{odd}'")



def test_checks_line_compares_the_last_three_checks_like_with_like(tmp_path):
    """The closing block's checks line: the last three periodic checks (not the step-0 row, not
    the final alignment, whose read-out differs) and their spread, (max - min) / min."""
    from embodied_tactile.run.summary import check_spread

    per = (0.3, 0.3, 0.3, 0.3)
    rows = [(0, 0.99, per), (6, 0.5, per), (8, 0.4, per), (10, 0.44, per), (12, 0.42, per), (12, 0.3, per)]
    run = fake_run(tmp_path / "run", rows=rows)
    hist = [json.loads(ln) for ln in (run / "krr_history.jsonl").read_text().splitlines()]
    hist[0]["initial"], hist[-1]["final"] = True, True
    (run / "krr_history.jsonl").write_text("".join(json.dumps(r) + "\n" for r in hist))
    checks, spread = check_spread(hist)
    assert [r["step"] for r in checks] == [8, 10, 12] and spread == pytest.approx(0.1)
    line = next(ln for ln in run_summary_lines(run, cwd=tmp_path) if ln.startswith("checks:"))
    assert "steps 8, 10, 12" in line and "0.4, 0.44, 0.42" in line and "spread 10 %" in line
    assert "moving average" not in line
    (run / "config_resolved.yaml").write_text("model: {weight_average: 0.99}\n")  # the checks read the average
    line = next(ln for ln in run_summary_lines(run, cwd=tmp_path) if ln.startswith("checks:"))
    assert line.endswith("(the checks' cheaper read-out, of the weights' moving average (decay 0.99))")
    assert check_spread(hist[:3]) is None  # one periodic check only: nothing to compare
    # fewer than three checks: no line
    assert not any(ln.startswith("checks:") for ln in run_summary_lines(fake_run(tmp_path / "short"), cwd=tmp_path))

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
    row = {"side": "test", "population_default": True}
    scores.write_text(json.dumps(
        [{**row, "reader": "latent_filter", "seed": s, "whole": w, "last": l} for s, w, l in ((0, 1.0, 0.7), (1, 1.2, 0.8))]
        + [{**row, "reader": "untrained", "seed": 0, "whole": 0.9, "last": 0.85}]
        + [{**row, "reader": "latent_filter", "side": "val", "seed": 0, "whole": 9.0, "last": 9.0},
           {**row, "reader": "latent_filter", "population_default": False, "seed": 0, "whole": 9.0, "last": 9.0}]))
    monkeypatch.setattr(S, "POPULATION_SCORES", scores)
    lines = S.protocol_lines(run)
    text = "\n".join(lines)
    assert lines[0] == f"{method} on 32 held-out trials of the training objects (data.split=trial, the paper's protocol):"
    assert [ln.split()[-2:] for ln in lines[2:5]] == [["0.1234", "0.0987"], ["0.998", "0.988"], ["1.003", "1.003"]]
    assert "untrained" in lines[3] and "mean predictor" in lines[4]
    assert "measures recognition" in text
    # a step-0 row with its floor (the final alignment's read-out of the untrained network): the floor
    floored = {**initial, "floor": {"nmse_overall": 0.977, "nmse_last_overall": 0.966}}
    (run / "krr_history.jsonl").write_text("".join(json.dumps(r) + "\n" for r in (floored, final)))
    assert S.protocol_lines(run)[3].split()[-2:] == ["0.977", "0.966"]
    (run / "krr_history.jsonl").write_text("".join(json.dumps(r) + "\n" for r in (initial, final)))
    assert ("Objects never touched: python train.py experiment=population; measured: the population default: "
            "whole trajectory 1.100, last frame 0.750 (2 seed(s), 64 test objects; untrained 0.900 / 0.850)") in text
    assert "docs/experiments/label_free_objectives.md" in text
    # the block closes the run's summary; another split says what it measures; an unmeasured recipe says so
    assert run_summary_lines(run, cwd=tmp_path)[-len(lines) - 1:-1] == lines
    (run / "config_resolved.yaml").write_text(PAPER_CONFIG.replace("trial", "object").replace("true", "false"))
    text = "\n".join(S.protocol_lines(run))
    assert "generalisation to objects never touched" in text and "recognition" not in text
    monkeypatch.setattr(S, "POPULATION_SCORES", tmp_path / "absent.json")
    assert "the population default: not yet measured" in "\n".join(S.protocol_lines(run))


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


def test_multirun_table_names_each_failed_job_its_overrides_and_reason(tmp_path):
    """A sweep's table: one row per job Hydra started, finished or not (a job refused before
    its config was saved included), the overrides that tell it apart, its status and why."""
    from embodied_tactile.run.summary import multirun_rows, record_outcome

    sweep = tmp_path / "multi"
    for name, batch in (("data.batch_size=4", 4), ("data.batch_size=0", 0)):
        (sweep / name / ".hydra").mkdir(parents=True)
        (sweep / name / ".hydra" / "overrides.yaml").write_text(f"- modality=acc\n- data.batch_size={batch}\n")
    (sweep / "data.batch_size=4" / "metrics.json").write_text(json.dumps({"status": "finished", "train_wall_s": 3.0}))
    record_outcome(sweep / "data.batch_size=4", "finished")
    record_outcome(sweep / "data.batch_size=0", "refused", "data.batch_size=0 (int): expected an integer >= 1")
    rows = multirun_rows(sweep)
    assert [(r["job"], r["overrides"], r["status"], r["reason"]) for r in rows] == [
        ("data.batch_size=0", ["data.batch_size=0"], "refused", "data.batch_size=0 (int): expected an integer >= 1"),
        ("data.batch_size=4", ["data.batch_size=4"], "finished", "")]
    lines = multirun_summary_lines(sweep, cwd=tmp_path)
    assert lines[1] == "multirun: 2 job(s), 1 finished, 1 not: multi"
    assert lines[2].split() == ["job", "status", "NMSE", "(last", "KRR)", "training", "time", "overrides", "reason"]
    assert lines[3].split()[:2] == ["data.batch_size=0", "refused"]
    assert lines[3].endswith("data.batch_size=0  data.batch_size=0 (int): expected an integer >= 1")


def test_folder_names_from_overrides_hold_no_path_separator():
    """Fault: an override value holding "/" or "..". Before: its multirun job folder was
    nested (tags=[x/y,../z] made <sweep>/...tags=[x/y,../z] a path two levels deep, ".."
    climbing out of it). Now: one folder per job, "/" written %2F, unique and short."""
    from embodied_tactile.run.config import MAX_DIRNAME, folder_name
    from hydra import compose, initialize_config_dir

    assert folder_name("modality=acc,tags=[x/y,../z]") == "modality=acc,tags=[x%2Fy,..%2Fz]"
    assert folder_name("a=50%/x") == "a=50%25%2Fx" and folder_name("a=50%2Fx") != folder_name("a=50%/x")
    assert folder_name("..") == "%2E%2E" and folder_name("") == "_"
    long_a, long_b = folder_name("x=" + "a" * 400), folder_name("x=" + "a" * 399 + "b")
    assert len(long_a.encode()) <= MAX_DIRNAME and long_a != long_b and "/" not in long_a
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose(config_name="train", return_hydra_config=True)
    from omegaconf import OmegaConf

    assert OmegaConf.to_container(cfg.hydra.sweep)["subdir"] == "${folder_name:${hydra:job.override_dirname}}"


@pytest.mark.slow  # train.py -m: two jobs (its entry point in this process)
def test_a_failed_job_does_not_stop_the_sweep_and_the_table_says_why(tmp_path, fast_data_dir):
    """Fault: one job of a sweep with a bad swept value. Before: its SystemExit ended the
    sweep (the next jobs never ran), exit 2, no table. Now: every job runs, the table names
    the failed job, its overrides, status and reason, exit 1."""
    sweep = tmp_path / "sweep"
    res = train_in_process("-m", "debug=fast", f"paths.data_dir={fast_data_dir}", f"hydra.sweep.dir={sweep}",
                           "modality=acc", "threads=1", "callbacks.krr_alignment=null", "data.batch_size=0,4",
                           cwd=tmp_path)
    assert res.returncode == 1, res.stderr[-3000:]
    out = res.stdout.splitlines()
    bad = next(ln for ln in out if ln.strip().startswith("callbacks.krr_alignment=null,data.batch_size=0"))
    assert bad.split()[1] == "refused" and bad.endswith("data.batch_size=0  data.batch_size=0 (int): expected an integer >= 1")
    good = next(ln for ln in out if ln.strip().startswith("callbacks.krr_alignment=null,data.batch_size=4"))
    assert good.split()[1] == "finished"
    assert json.loads((sweep / "callbacks.krr_alignment=null,data.batch_size=4,modality=acc,threads=1" / "metrics.json")
                      .read_text())["status"] == "finished"


@pytest.mark.slow  # train_py_run: the session's train.py subprocess (debug=fast, 2 epochs, run folder "run")
def test_train_ends_with_the_summary(train_py_run):
    run, res = train_py_run
    out = res.stdout.strip().splitlines()
    start = out.index("run finished: run") - 1
    tail, protocol = out[start:start + 11], out[start + 11:]
    hist = [json.loads(x) for x in (run / "krr_history.jsonl").read_text().splitlines()]
    assert tail[0].startswith("-----") and tail[-1].startswith("-----")
    assert f"overall {hist[-1]['nmse_overall']:.4g}" in tail[2]
    assert tail[3].startswith("  per factor: spatial freq. ")
    assert tail[4].startswith("  95 % interval over resampled test objects")
    assert tail[5].startswith("training time: ")
    assert tail[6].startswith("checkpoint:    run/checkpoints/")
    assert tail[-2] == "next:          python evaluate.py run"
    # then what the number means, closing the output
    assert protocol[-1].startswith("-----") and "held-out trials of the training objects" in protocol[0]
    assert protocol[2].split()[-2:] == [f"{hist[-1]['nmse_overall']:.4g}", f"{hist[-1]['nmse_last_overall']:.4g}"]
    assert "untrained" in protocol[3] and "mean predictor" in protocol[4]
    assert "measures recognition" in protocol[5] and protocol[6].startswith("Objects never touched: python train.py")


@pytest.mark.slow  # train.py -m (Hydra multirun; its entry point in this process)
def test_multirun_ends_with_its_folder_and_evaluate_command(tmp_path, fast_data_dir):
    sweep = tmp_path / "multi"
    res = train_in_process("-m", "debug=fast", "modality=acc", "callbacks.krr_alignment=null",
                           f"paths.data_dir={fast_data_dir}", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
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
    monkeypatch.setattr(pipeline, "evaluate", lambda path, overrides: seen.update(path=path, overrides=overrides))
    assert ev.main([f"paths.log_dir={log_dir}", "umap=false"]) == 0
    assert seen == {"path": str(run), "overrides": ["umap=false"]}
    assert f"evaluating the most recent run under {log_dir / 'train'}: {run}" in capsys.readouterr().out


def test_evaluate_without_path_default_log_dir_from_train_config(tmp_path, monkeypatch, capsys):
    """No paths.log_dir given: the one train.py composes (configs/train.yaml: logs), relative to the cwd."""
    monkeypatch.chdir(tmp_path)
    run = fake_run(tmp_path / "logs" / "train" / "runs" / "r1")
    seen = {}
    monkeypatch.setattr(pipeline, "evaluate", lambda path, overrides: seen.update(path=path))
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
