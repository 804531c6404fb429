"""evaluate.py end to end on tiny trained runs (debug=fast, trained by train.py's entry point
in this process): one run trained with a non-default modality (fsr_tb) from another working
directory with a relative data_dir, and a two-job multirun (acc, fsr_t) sharing the data
folder; evaluate.py itself runs once as a subprocess, as a user starts it."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

import evaluate as cli  # noqa: E402  (the script: main())
from embodied_tactile.eval import pipeline as ev  # noqa: E402
from embodied_tactile.eval import runs  # noqa: E402
from embodied_tactile.options.alignment import alignment_options  # noqa: E402

# every test uses `trained`: three trainings (a run and a two-job multirun)
pytestmark = pytest.mark.slow

FAST = ["print_tables=false", "alignment.cv=2"]


def _train(args, cwd, log):
    """``python train.py <args>`` started in ``cwd``, by its entry point in this process."""
    from conftest import train_in_process

    p = train_in_process(*args, cwd=cwd)
    log.write_text(p.stdout + p.stderr)
    assert p.returncode == 0, p.stderr[-3000:]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """run: modality=fsr_tb, seed 3, trained in <tmp> with the RELATIVE data_dir 'data' (evaluation
    from the repo must find it through provenance.json's cwd); multi: modality=acc,fsr_t."""
    tmp = tmp_path_factory.mktemp("evaluate")
    _train(["debug=fast", "modality=fsr_tb", "seed=3", "paths.data_dir=data", f"hydra.run.dir={tmp}/run"], tmp,
           tmp / "run.log")
    _train(["-m", "debug=fast", "modality=acc,fsr_t", f"paths.data_dir={tmp}/data", f"hydra.sweep.dir={tmp}/multi"],
           REPO, tmp / "multi.log")
    return tmp


def _finite_tree(obj, path="") -> list[str]:
    bad = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            bad += _finite_tree(v, f"{path}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            bad += _finite_tree(v, f"{path}[{i}]")
    elif isinstance(obj, float) and not math.isfinite(obj):
        bad.append(path)
    return bad


def test_run_cli_writes_everything_as_trained_modality(trained):
    run = trained / "run"
    env = dict(os.environ, WANDB_MODE="disabled")
    p = subprocess.run([sys.executable, str(REPO / "evaluate.py"), str(run), "gru.epochs=2", "alignment.cv=2", "umap=false"],
                       cwd=REPO, env=env, capture_output=True, text=True, timeout=240)
    assert p.returncode == 0, f"rc={p.returncode}\nSTDOUT:\n{p.stdout[-2000:]}\nSTDERR:\n{p.stderr[-6000:]}"
    out = run / "evaluation"
    for name in ("action_config", "environmentshape", "summary", "runtime"):
        for ext in ("md", "csv", "tex"):
            assert (out / f"table_{name}.{ext}").stat().st_size > 0
        assert f"**{name}.**" not in p.stdout  # tables go to files; the terminal gets what was measured
    printed = p.stdout.strip().splitlines()
    assert len(printed) <= 40, p.stdout
    assert "split trial: held-out trials of training objects: recognition" in p.stdout  # the paper's split, named
    for method in ("Latent Filter", "hand-crafted KRR", "GRU", "mean"):  # NMSE per factor beside the baselines
        assert any(line.startswith(f"| {method} |") for line in printed), p.stdout
    assert "| method | spatial_frequency | amplitude | stiffness | heterogeneity | overall | last frame |" in p.stdout
    figs = {f.name for f in (out / "figures").glob("*.png")}
    for f in ("nmse_time_by_modality.png", "nmse_time_by_skin.png", "nmse_time_by_method.png",
              "nmse_time_by_best_worst_action.png", "error_vs_runtime.png",
              "distances_latent_filter_fsr_tb_soft_pressing.png"):
        assert f in figs, sorted(figs)
    assert not [f for f in figs if f.startswith("umap_")], sorted(figs)  # umap=false (UMAP: tests/unit/test_eval.py)
    res = json.loads((out / "results.json").read_text())
    # the run's own modality, no argument given
    assert {r["modality"] for r in res["runs"]} == {"fsr_tb"}
    assert {r["method"] for r in res["runs"]} == {"latent_filter", "untrained", "handcrafted_krr", "hybrid_krr", "gru", "mean"}
    assert "| latent_filter | fsr_tb | soft | pressing |" in (out / "table_summary.md").read_text()
    # the saved split is reused: sizes equal split.json
    split = json.loads((run / "split.json").read_text())
    for r in res["runs"]:
        assert (r["n_train"], r["n_test"]) == (len(split["train"]), len(split["test"]))
        assert math.isfinite(r["nmse_trajectory_overall"]) and math.isfinite(r["nmse_last_step_overall"])
        assert all(math.isfinite(v) for v in r["nmse_trajectory"].values())
    lf = next(r for r in res["runs"] if r["method"] == "latent_filter")
    gru = next(r for r in res["runs"] if r["method"] == "gru")
    assert gru["params"]["gru"]["seed"] == 3  # gru.seed null: the run's seed
    assert lf["params"]["train_time_s"] > 0 and lf["params"]["inference_s_per_sequence"] > 0
    assert res["histories"], "krr_history.jsonl rows missing"
    # every table states the NMSE definition, the split sizes and the data source
    for t in res["tables"]:
        assert res["nmse_definition"] in t["caption"]
        assert f"{len(split['train'])} train / {len(split['test'])} held-out" in t["caption"]
        assert "Data source: simulated" in t["caption"]
    assert not _finite_tree(res["runs"]), _finite_tree(res["runs"])
    info = json.loads((out / "evaluation.json").read_text())["runs"][0]
    assert info["channels"] == ["fsr_t", "fsr_b"] and info["modality"] == "fsr_tb"
    assert Path(info["checkpoint"]).name == "last.ckpt"  # the final weights, whose read-out the training printed


def test_saved_split_reused_and_leakage_guard(trained):
    from embodied_tactile.eval import LeakageError, evaluate_latents

    run = trained / "run"
    opts = ev.parse_options(FAST)
    _, (r,), _ = runs.discover(run, "best")
    cache = runs.DataCache()
    key, dm = cache.get(runs.data_config(r, opts))
    split = json.loads((run / "split.json").read_text())
    assert runs.trial_names(dm, "train") == split["train"] and runs.trial_names(dm, "test") == split["test"]
    from hydra.utils import get_class

    model = get_class(str(r.cfg.model._target_)).load_from_checkpoint(str(r.ckpt), map_location="cpu")
    tr, _ = runs.collect_split(model, cache.batches(key, dm, "train"), runs.trial_names(dm, "train"), "y")
    te, _ = runs.collect_split(model, cache.batches(key, dm, "test"), runs.trial_names(dm, "test"), "y")
    assert not set(tr["seq_id"]) & set(te["seq_id"])  # scored ids disjoint from fitted ids
    assert tr["obs"].shape[2] == 2  # fsr_tb: two channels, from the run's config
    with pytest.raises(LeakageError):  # scoring a fitted sequence is refused
        evaluate_latents(tr, {k: v[:2] for k, v in tr.items()}, latent="y", alignment=alignment_options({"cv": 2}))


def test_checkpoint_path(trained, tmp_path):
    ckpt = trained / "run" / "checkpoints" / "last.ckpt"
    out = ev.evaluate(ckpt, [*FAST, f"out={tmp_path}/ev", "baselines=[mean]", "umap=false", "figures=false"])
    assert Path(out["runs"][0]["checkpoint"]) == ckpt.resolve()
    assert out["runs"][0]["modality"] == "fsr_tb"
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert {r["method"] for r in res["runs"]} == {"latent_filter", "mean"}


def test_validation_side_scores_the_validation_trials_apart_from_the_test_report(trained):
    run = trained / "run"
    out = ev.evaluate(run, [*FAST, "held_out=val", "baselines=[mean]", "umap=false", "figures=false"])
    split = json.loads((run / "split.json").read_text())
    assert Path(out["out"]) == run / "evaluation-val"
    info = out["runs"][0]
    assert info["held_out"] == "val" and info["n_test"] == len(split["val"]) != len(split["test"])
    assert "the val side" in info["training_final_alignment"]["other"]  # the training scored the test side
    res = json.loads((run / "evaluation-val" / "results.json").read_text())
    assert {r["params"]["held_out"] for r in res["runs"]} == {"val"}
    assert "validation side" in res["caption_note"]
    with pytest.raises(ev.EvaluationError, match="held_out"):
        ev.parse_options(["held_out=train"])


def test_multirun_aggregate_and_skip(trained, capsys):
    multi = trained / "multi"
    broken = multi / "modality=broken"  # a job killed before its first checkpoint
    broken.mkdir(exist_ok=True)
    shutil.copy(multi / "modality=acc" / "config_resolved.yaml", broken / "config_resolved.yaml")
    out = ev.evaluate(multi, [*FAST, "umap=false"])
    printed = capsys.readouterr().out
    assert Path(out["out"]) == multi / "evaluation"
    assert len(out["runs"]) == 2 and {i["modality"] for i in out["runs"]} == {"acc", "fsr_t"}
    assert "SKIPPED" in printed and "modality=broken" in printed
    assert len(out["skipped"]) == 1 and "no checkpoint" in out["skipped"][0]["reason"]
    res = json.loads((multi / "evaluation" / "results.json").read_text())
    lf = [r for r in res["runs"] if r["method"] == "latent_filter"]
    assert {r["modality"] for r in lf} == {"acc", "fsr_t"}
    assert {r["method"] for r in res["runs"]} == {"latent_filter", "untrained", "handcrafted_krr", "hybrid_krr", "mean"}  # no GRU by default
    assert all(math.isfinite(r["nmse_trajectory_overall"]) for r in res["runs"])
    assert set(res["histories"]) == {"acc/soft/pressing", "fsr_t/soft/pressing"}
    curves = res["figure_curves"]["modality"]
    assert {"acc", "fsr_t"} <= set(curves) and np.isfinite(np.asarray(curves["acc"], float)).all()
    for name in ("action_config", "environmentshape", "summary", "runtime"):
        assert (multi / "evaluation" / f"table_{name}.tex").exists()
    assert (multi / "evaluation" / "figures" / "error_vs_runtime.png").exists()
    assert (multi / "evaluation" / "figures" / "distances_latent_filter_acc_soft_pressing.png").exists()
    shutil.rmtree(broken)


def test_study_parts_are_merged(trained, tmp_path):
    """A study run in parts (one multirun folder each, under one study folder) evaluates as one."""
    study = tmp_path / "study"
    for part, job in (("seed0", "modality=acc"), ("seed1", "modality=fsr_t")):
        shutil.copytree(trained / "multi" / job, study / part / job)
    (study / "evaluation" / "figures").mkdir(parents=True)  # an earlier report is not a job
    assert [d.relative_to(study).as_posix() for d in runs.job_dirs(study)] == ["seed0/modality=acc",
                                                                              "seed1/modality=fsr_t"]
    out = ev.evaluate(study, [*FAST, "baselines=[mean]", "umap=false", "figures=false"])
    assert Path(out["out"]) == study / "evaluation"
    assert sorted(i["modality"] for i in out["runs"]) == ["acc", "fsr_t"]
    res = json.loads((study / "evaluation" / "results.json").read_text())
    assert {r["modality"] for r in res["runs"] if r["method"] == "latent_filter"} == {"acc", "fsr_t"}


def test_a_study_evaluated_again_reuses_the_runs_scored_before_and_scores_the_rest(trained, tmp_path):
    """A study that grows part by part: evaluating it again scores only the new runs; the
    reused run's numbers are those of its first scoring; an option that decides the numbers,
    or a changed checkpoint, scores a run again."""
    study, fast = tmp_path / "study", [*FAST, "baselines=[mean]", "umap=false", "figures=false"]
    shutil.copytree(trained / "multi" / "modality=acc", study / "part0" / "modality=acc")
    first = ev.evaluate(study, fast)
    assert json.loads((study / "evaluation" / "evaluation.json").read_text())["runs_reused"] == 0
    nmse = lambda: {r["modality"]: r["nmse_trajectory_overall"]  # noqa: E731
                    for r in json.loads((study / "evaluation" / "results.json").read_text())["runs"]
                    if r["method"] == "latent_filter"}
    acc_first = nmse()["acc"]
    shutil.copytree(trained / "multi" / "modality=fsr_t", study / "part1" / "modality=fsr_t")
    ev.evaluate(study, fast)
    assert json.loads((study / "evaluation" / "evaluation.json").read_text())["runs_reused"] == 1
    assert nmse()["acc"] == acc_first and set(nmse()) == {"acc", "fsr_t"}
    assert len(list((study / "evaluation" / ev.PER_RUN).glob("*.npz"))) == 2
    ev.evaluate(study, [*fast, "alignment.cv=3"])
    assert json.loads((study / "evaluation" / "evaluation.json").read_text())["runs_reused"] == 0
    ckpt = study / "part0" / "modality=acc" / "checkpoints" / "last.ckpt"
    import torch

    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    state["note"] = "saved again"  # other bytes, same weights: not the checkpoint scored before
    torch.save(state, ckpt)
    ev.evaluate(study, [*fast, "alignment.cv=3"])
    assert json.loads((study / "evaluation" / "evaluation.json").read_text())["runs_reused"] == 1
    assert first["out"] == str(study / "evaluation")


def test_archived_runs_travel_without_checkpoints_and_merge_with_new_ones(trained, tmp_path):
    """A study's scored runs archived (small files + record, no checkpoint), restored into
    another machine's study folder: the lanes take them as finished, the evaluation merges them
    with a new run, each with the numbers of its first scoring; other options refuse them by
    name (their checkpoint is not there to score again)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("study_grid", Path(__file__).parents[2] / "experiments" / "study_grid.py")
    grid = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(grid)
    from embodied_tactile.eval.records import IN_RUN, archive_runs, restore_runs
    from embodied_tactile.run.runfolder import RunFinished, check_length

    fast = [*FAST, "baselines=[mean]", "umap=false", "figures=false"]
    first, archive = tmp_path / "first", tmp_path / "archive"
    shutil.copytree(trained / "multi" / "modality=acc", first / "part0" / "modality=acc")
    ev.evaluate(first, fast)
    scored = json.loads((first / "evaluation" / "results.json").read_text())["runs"]
    assert [p.relative_to(archive).as_posix() for p in archive_runs(first / "evaluation", first, archive)] == [
        "part0/modality=acc"]
    job = archive / "part0" / "modality=acc"
    assert (job / IN_RUN).is_file() and not (job / "checkpoints").exists() and (job / ".hydra" / "overrides.yaml").is_file()
    assert archive_runs(first / "evaluation", first, archive) == []  # archived once

    study = tmp_path / "study"  # the next machine: the archive restored, a new run beside it
    assert restore_runs(archive, study) == [study / "part0" / "modality=acc"]
    assert restore_runs(archive, study) == []
    restored = study / "part0" / "modality=acc"
    with pytest.raises(RunFinished, match="archived"):
        check_length(OmegaConf.load(restored / "config_resolved.yaml"), restored)
    assert grid.finished_seeds(study / "part0") == [int(OmegaConf.load(restored / "config_resolved.yaml").seed)]
    shutil.copytree(trained / "multi" / "modality=fsr_t", study / "part1" / "modality=fsr_t")
    out = ev.evaluate(study, fast)
    assert json.loads((study / "evaluation" / "evaluation.json").read_text())["runs_reused"] == 1
    merged = json.loads((study / "evaluation" / "results.json").read_text())["runs"]
    assert {r["modality"] for r in merged if r["method"] == "latent_filter"} == {"acc", "fsr_t"}
    pick = lambda rows: {r["method"]: r["nmse_trajectory_overall"] for r in rows if r["modality"] == "acc"}  # noqa: E731
    assert pick(merged) == pytest.approx(pick(scored), rel=1e-4)  # its predictions kept in float16
    assert {Path(i["run_dir"]) for i in out["runs"]} == {restored, study / "part1" / "modality=fsr_t"}

    out = ev.evaluate(study, [*fast, "alignment.cv=3"])  # other scoring options: the archived run is named, not merged
    assert [i["modality"] for i in out["runs"]] == ["fsr_t"]
    assert len(out["skipped"]) == 1 and "scored with other options" in out["skipped"][0]["reason"]
    assert IN_RUN in out["skipped"][0]["reason"] and "commit" in out["skipped"][0]["reason"]


def test_a_study_with_a_run_in_training_scores_the_others_and_names_it(trained, tmp_path):
    """A study evaluated while its lanes still train, one lane stopped: the run being trained
    and the interrupted one are skipped and named (a run folder given alone is refused, or
    scored with its state: tests/integration/test_run_folder.py)."""
    from embodied_tactile.run.runfolder import LOCK_FILE, try_lock, write_holder

    study = tmp_path / "study"
    for part, job in (("part0", "modality=acc"), ("part1", "modality=fsr_t")):
        shutil.copytree(trained / "multi" / job, study / part / job)
    shutil.copytree(trained / "multi" / "modality=acc", study / "part2" / "modality=acc")
    stopped = study / "part2" / "modality=acc"  # a lane stopped by a signal: resumable, not finished
    metrics = json.loads((stopped / "metrics.json").read_text())
    (stopped / "metrics.json").write_text(json.dumps({**metrics, "status": "interrupted", "stopped_by": "SIGTERM"}))
    busy = study / "part1" / "modality=fsr_t"
    fd, _ = try_lock(busy / LOCK_FILE)  # a lane's training holds the folder
    write_holder(fd)
    try:
        out = ev.evaluate(study, [*FAST, "baselines=[mean]", "umap=false", "figures=false"])
        assert [i["run_dir"] for i in out["runs"]] == [str(study / "part0" / "modality=acc")]
        reasons = {s["run_dir"]: s["reason"] for s in out["skipped"]}
        assert set(reasons) == {str(busy), str(stopped)}
        assert "is being trained" in reasons[str(busy)]
        assert "is interrupted (stopped by SIGTERM" in reasons[str(stopped)] and "not finished" in reasons[str(stopped)]
    finally:
        os.close(fd)


def test_checkpoint_of_an_older_network_layout_is_a_clear_error(trained, tmp_path, capsys):
    import torch

    run = tmp_path / "old_layout"
    shutil.copytree(trained / "run", run, ignore=shutil.ignore_patterns("evaluation*"))
    ckpt = sorted((run / "checkpoints").glob("*.ckpt"))[0]
    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    state["state_dict"] = {k.replace("model.observation.", "model.encoders_v0."): v
                           for k, v in state["state_dict"].items()}
    torch.save(state, ckpt)
    assert cli.main([str(ckpt), "baselines=[mean]", "figures=false"]) == 2
    err = capsys.readouterr().err
    assert "does not fit the model of its run" in err and str(run / "checkpoints") in err and "not evaluated" in err
    assert "model.observation." in err and "model.encoders_v0." in err  # the first missing and unexpected keys


def test_folder_without_checkpoint_is_a_clear_error(trained, tmp_path, capsys):
    empty = tmp_path / "no_ckpt_run"
    empty.mkdir()
    shutil.copy(trained / "run" / "config_resolved.yaml", empty / "config_resolved.yaml")
    assert cli.main([str(empty)]) == 2
    err = capsys.readouterr().err
    assert "no checkpoint" in err and str(empty) in err
    assert cli.main([str(tmp_path / "nowhere")]) == 2
    assert "no such file or folder" in capsys.readouterr().err
    # the scene is not an evaluation option: modality= SELECTS runs (this one is fsr_tb), never overrides
    assert cli.main([str(trained / "run"), "modality=acc"]) == 2
    err = capsys.readouterr().err
    assert "no run matches modality=acc" in err and "fsr_tb" in err and "never changes a run's scene" in err
    assert cli.main([str(trained / "run"), "no_such_key=1"]) == 2
    assert "unknown evaluation option" in capsys.readouterr().err


def test_select_runs_by_any_axis(trained, capsys):
    multi = trained / "multi"
    out = ev.evaluate(multi, [*FAST, "modality=acc", "umap=false", "figures=false", "baselines=[mean]"])
    assert [i["modality"] for i in out["runs"]] == ["acc"]
    assert Path(out["out"]).name == "evaluation-modality=acc"  # the whole sweep's report is left alone
    out = ev.evaluate(multi, [*FAST, "modality=[acc,fsr_t]", "skin=soft", "seed=0", "figures=false", "baselines=[mean]"])
    assert sorted(i["modality"] for i in out["runs"]) == ["acc", "fsr_t"]
    with pytest.raises(ev.EvaluationError, match="no run matches skin=hard"):
        ev.evaluate(multi, [*FAST, "skin=hard"])


def test_train_then_evaluate_final_numbers_match(trained, capsys):
    """One run, one number: the training's final KRR alignment (metrics.json krr_final, the
    last krr_history.jsonl row, the last log line) and evaluate.py with its default alignment
    on the final weights agree; with other settings the output says why and by how much."""
    run = trained / "run"
    metrics = json.loads((run / "metrics.json").read_text())
    final = metrics["krr_final"]
    assert final["final"] and final["val_frame_stride"] == 1
    hist = [json.loads(line) for line in (run / "krr_history.jsonl").read_text().splitlines()]
    assert hist[-1]["nmse_overall"] == final["nmse_overall"]
    assert "KRR alignment (final weights, evaluate.py settings)" in (trained / "run.log").read_text()
    # data preparation is timed apart from training
    assert metrics["data_prepare_s"] > 0 and metrics["train_wall_s"] > 0
    out = ev.evaluate(run, ["print_tables=false", "baselines=[mean]", "figures=false"])  # default: the final weights
    c = out["runs"][0]["training_final_alignment"]
    assert c["other"] == [], c
    # the same weights, latents inferred in the same batches (eval.latents.collect_split_latents)
    # and the same read-out: one number (5.8e-05 apart when evaluate.py inferred per loader batch)
    assert c["evaluate_nmse_overall"] == pytest.approx(final["nmse_overall"], abs=1e-9)
    printed = capsys.readouterr().out
    assert "printed by the training (difference" in printed
    res = json.loads((Path(out["out"]) / "results.json").read_text())
    lf = next(r for r in res["runs"] if r["method"] == "latent_filter")
    assert lf["nmse_trajectory_overall"] == pytest.approx(final["nmse_overall"], abs=1e-9)
    # one time base: the runtime table's Latent Filter time is the history's, without data preparation
    assert lf["params"]["train_time_s"] == pytest.approx(hist[-1]["train_wall_time_s"])
    assert lf["params"]["data_prepare_s"] == pytest.approx(metrics["data_prepare_s"])
    # another read-out: said
    out = ev.evaluate(run, ["print_tables=false", "alignment.cv=2", "alignment.frames_per_sequence=2",
                            "baselines=[mean]", "figures=false", f"out={trained}/ev_cv2"])
    c = out["runs"][0]["training_final_alignment"]
    assert c["other"] == ["read-out {'cv': 2, 'frames_per_sequence': 2}"], c
    assert "another measurement: read-out" in capsys.readouterr().out
