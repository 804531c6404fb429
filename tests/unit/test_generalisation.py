"""The learning-curve page: collected from evaluated population runs, aggregated over seeds."""

from __future__ import annotations

import json

import pytest
from omegaconf import OmegaConf

from embodied_tactile.constants import FACTOR_NAMES
from embodied_tactile.eval import generalisation as G
from embodied_tactile.run.summary import recipe


def _run(root, n, seed, lf, labels=True, objects="population", gru_std=None, held_out=None, readout=None,
         curve=None, unlabelled=None):
    d = root / f"n{n}_s{seed}_{labels}" / ("" if unlabelled is None else f"u{unlabelled}")
    (d / "evaluation").mkdir(parents=True)
    cfg = {"seed": seed, "modality": {"name": "multi_l"}, "model": {"net": {"prior": {"labels": labels}}},
           "data": {"objects": objects, "split": "object", "n_objects": n}}
    if unlabelled is not None:  # configs saved before the option existed have no key
        cfg["data"]["n_unlabelled_objects"] = unlabelled
    OmegaConf.save(OmegaConf.create(cfg), d / "config_resolved.yaml")
    (d / "provenance.json").write_text(json.dumps({"git_commit": "abcdef0123"}))
    runs = [{"method": m, "nmse_trajectory": {f: v for f in FACTOR_NAMES}, "nmse_trajectory_overall": v,
             "nmse_last_step": {f: v / 2 for f in FACTOR_NAMES}, "nmse_last_step_overall": v / 2,
             "targets": "physical"} for m, v in (("latent_filter", lf), ("untrained", 1.05), ("gru", 0.5),
                                                  ("mean", 1.0))]
    if curve is not None:  # evaluate.py's NMSE per frame, mean over factors
        for r, c in zip(runs, curve):
            r["nmse_curve_overall"] = c
    if gru_std is not None:  # evaluate.py's results carry the GRU's settings
        runs[2]["params"] = {"gru": {"input_standardize": gru_std}}
    if held_out is not None:  # evaluate.py's held_out option, as its results carry it
        runs[0]["params"] = {"held_out": held_out}
    if readout is not None:  # the run's alignment, as evaluate.py's results carry it
        runs[0].setdefault("params", {})["alignment"] = {"readout": readout}
    (d / "evaluation" / "results.json").write_text(json.dumps({"runs": runs}))


@pytest.mark.slow
def test_curve_page_aggregates_seeds_and_names_missing_cells(tmp_path):
    root = tmp_path / "runs"
    for seed, lf in ((0, 0.8), (1, 0.9), (2, 1.0)):
        _run(root, 24, seed, lf)
    _run(root, 24, 0, 0.95, labels=False)
    _run(root, 256, 0, 0.4, gru_std=True)
    _run(root, 64, 0, 0.1, objects=None)  # not a population run: left out
    rows = G.collect([root])
    methods = {r["method"] for r in rows}
    assert methods == {"Latent Filter multi_l (labels)", "Latent Filter multi_l (no labels)",
                       "Latent Filter multi_l (labels), untrained", "Latent Filter multi_l (no labels), untrained",
                       "supervised conv + GRU (multi_l, raw inputs)", "supervised conv + GRU (multi_l, standardised inputs)",
                       "mean predictor"}
    gru = {r["method"]: r["n_objects"] for r in rows if "GRU" in r["method"]}
    assert gru == {"supervised conv + GRU (multi_l, raw inputs)": 24,
                   "supervised conv + GRU (multi_l, standardised inputs)": 256}
    # the GRU and mean of the labels=false run duplicate the labels=true run's: counted once
    assert sum(1 for r in rows if r["method"] == "mean predictor" and r["n_objects"] == 24) == 3
    agg = G.aggregate(rows)
    cell = agg["Latent Filter multi_l (labels)"][24]
    assert cell["mean"] == pytest.approx(0.9) and cell["seeds"] == [0, 1, 2]
    assert cell["lo"] < 0.9 < cell["hi"] and cell["hi"] - cell["lo"] == pytest.approx(2 * 4.303 * 0.1 / 3**0.5, rel=1e-3)
    single = agg["Latent Filter multi_l (labels)"][256]
    assert single["mean"] == pytest.approx(0.4) and single["lo"] != single["lo"]  # one seed: no interval
    assert agg["Latent Filter multi_l (labels), untrained"][24]["mean"] == pytest.approx(1.05)
    last = G.aggregate(rows, "overall", "last_step")
    assert last["Latent Filter multi_l (labels)"][24]["mean"] == pytest.approx(0.45)
    assert last["Latent Filter multi_l (labels), untrained"][24]["mean"] == pytest.approx(0.525)
    page = G.write_page(rows, tmp_path / "docs", command="test")
    text = page.read_text()
    assert "0.900 [" in text and "0.450 [" in text and "not run" in text and "abcdef0" in text
    assert "## Mean over factors, last step" in text
    assert (tmp_path / "docs" / "figures" / "generalisation_curve.png").stat().st_size > 1000
    assert 64 not in {r["n_objects"] for r in rows}


def _report(tmp_path, monkeypatch, root) -> int:
    """``embodied-tactile report page=generalisation roots=[root] out=<tmp>/docs``'s exit status."""
    from embodied_tactile import pages

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as info:
        pages.main(["page=generalisation", f"roots=[{root}]", f"out={tmp_path / 'docs'}"])
    return info.value.code


def test_cli_refuses_a_folder_without_population_runs(tmp_path, capsys, monkeypatch, restore_logging):
    assert _report(tmp_path, monkeypatch, tmp_path) == 2
    assert capsys.readouterr().err.startswith("report: error: no evaluated population runs")


def test_recipe_names_the_settings_that_tell_recipes_apart():
    cfg = OmegaConf.create({"model": {"net": {"prior": {"labels": False}, "y_update": "evidence", "obs_dropout": 0.5}},
                            "annealing": {"schedule": {"y_weight": 1.0}}})
    assert recipe(cfg) == "no labels, y_weight 1, y evidence, dropout 0.5"
    cfg.model.net.obs_dropout = 0.0
    cfg.model.net.prior.labels = True
    assert recipe(cfg) == "labels, y_weight 1, y evidence"
    cfg.model.net.prior.learn_embedding = True  # the paper's recipe: the object codes learn
    assert recipe(cfg) == "labels, learned codes, y_weight 1, y evidence"
    ctx = OmegaConf.create({"model": {"net": {"prior": {"labels": False}, "y_update": "evidence", "y_start": "population"},
                                      "context": {"source": "trial", "refilter": False}},
                            "annealing": {"schedule": {"y_weight": 1.0}}})
    assert recipe(ctx) == "context objective (trial), no labels, y_weight 1, y evidence, y from the population"
    ctx.model.lr_schedule = "cosine"
    ctx.model.context.touches = 3
    assert recipe(ctx) == ("context objective (trial, 3 touches), no labels, y_weight 1, y evidence, "
                           "y from the population, cosine schedule")


@pytest.mark.slow
def test_parts_merge_through_the_scores_file_and_a_later_root_replaces_a_score(tmp_path):
    first, second = tmp_path / "part1", tmp_path / "part2"
    _run(first, 24, 0, 0.8)
    _run(first, 256, 0, 0.6)
    G.write_page(G.collect([first]), tmp_path / "docs", command="test")
    scores = tmp_path / "docs" / "generalisation_scores.json"
    _run(second, 256, 0, 0.4)  # seed 0 at 256 run again
    _run(second, 256, 1, 0.5)
    rows = G.collect([scores, second])
    agg = G.aggregate(rows)["Latent Filter multi_l (labels)"]
    assert agg[24]["mean"] == pytest.approx(0.8)  # only in the scores file: kept
    assert agg[256]["seeds"] == [0, 1] and agg[256]["mean"] == pytest.approx(0.45)  # 0.6 replaced by 0.4
    assert G.collect([scores]) == G.collect([first])  # the file holds every score as collected


def test_a_file_that_is_not_a_scores_file_is_named(tmp_path, capsys, monkeypatch, restore_logging):
    bad = tmp_path / "results.json"
    bad.write_text(json.dumps({"runs": []}))
    assert _report(tmp_path, monkeypatch, bad) == 2
    assert "results.json: not a scores file" in capsys.readouterr().err


def test_validation_side_scores_are_refused_with_the_file_named(tmp_path, capsys, monkeypatch, restore_logging):
    _run(tmp_path / "runs", 24, 0, 0.8, held_out="test")
    assert len(G.collect([tmp_path / "runs"])) == 4
    _run(tmp_path / "val", 24, 1, 0.8, held_out="val")
    assert _report(tmp_path, monkeypatch, tmp_path / "val") == 2
    err = capsys.readouterr().err
    assert "n24_s1_True/evaluation/results.json: latent_filter scored on the validation side" in err


@pytest.mark.slow
def test_curves_over_time_are_tabled_and_drawn_and_read_outs_do_not_mix(tmp_path):
    """Rows carry evaluate.py's per-frame curve: the page tables frame 1, the highest frame
    and the first frame at or below 0.5 per seed, and draws the curves; a root evaluated with
    another alignment.readout is refused, naming both."""
    import numpy as np

    root = tmp_path / "runs"
    frames = np.arange(1, 301)
    for seed in (0, 1):
        lf = list(np.minimum(1.0, 1.0 - 0.6 * (frames - 1) / 299 * (1 + 0.1 * seed)))
        flat = [1.0] * 300
        _run(root, 256, seed, 0.6, readout="per_time", curve=[lf, [1.02] * 300, flat, flat])
    rows = G.collect([root])
    assert {r["readout"] for r in rows} == {"per_time"}
    cells = G.over_time(rows)
    lf = cells["Latent Filter multi_l (labels)"][256]
    assert lf["seeds"] == 2 and lf["first"][0] == pytest.approx(1.0) and lf["peak"][0] == pytest.approx(1.0)
    assert lf["below_half"] == [251, 228]  # 1 - 0.6 (f - 1) / 299 (1 + 0.1 s) <= 0.5
    assert cells["Latent Filter multi_l (labels), untrained"][256]["below_half"] == [None, None]
    text = G.write_page(rows, tmp_path / "docs", command="test").read_text()
    assert "## Over interaction time" in text and "| 251, 228 |" in text and "never, never" in text
    assert "alignment.readout=per_time" in text
    assert (tmp_path / "docs" / "figures" / "generalisation_over_time.png").stat().st_size > 1000
    _run(tmp_path / "old", 24, 0, 0.8)  # results from before alignment.readout: the paper's final tenth
    with pytest.raises(ValueError, match="mix read-outs.*final_segment.*per_time"):
        G.collect([root, tmp_path / "old"])


@pytest.mark.slow
def test_the_hybrid_reader_is_a_row_of_its_own_per_recipe(tmp_path):
    """evaluate.py's hybrid_krr (KRR on [hand-crafted features, y]) is its own row beside the
    Latent Filter's, named by the run's recipe, aggregated over seeds like it."""
    root = tmp_path / "runs"
    for seed, lf in ((0, 0.8), (1, 0.9)):
        for labels in (True, False):
            _run(root, 24, seed, lf, labels=labels)
            res = root / f"n24_s{seed}_{labels}" / "evaluation" / "results.json"
            runs = json.loads(res.read_text())["runs"]
            runs.append({**runs[0], "method": "hybrid_krr", "nmse_trajectory_overall": lf / 4,
                         "nmse_last_step_overall": lf / 8})
            res.write_text(json.dumps({"runs": runs}))
    rows = G.collect([root])
    agg = G.aggregate(rows)
    for labels in ("labels", "no labels"):
        hybrid = agg[f"hand-crafted + y of Latent Filter multi_l ({labels}), KRR"][24]
        assert hybrid["mean"] == pytest.approx(0.85 / 4) and hybrid["seeds"] == [0, 1]
        assert agg[f"Latent Filter multi_l ({labels})"][24]["mean"] == pytest.approx(0.85)
    text = G.write_page(rows, tmp_path / "docs", command="test").read_text()
    assert "| hand-crafted + y of Latent Filter multi_l (labels), KRR |" in text


def test_runs_with_unlabelled_objects_are_a_curve_of_their_own_and_replace_no_score(tmp_path):
    """A run trained on 256 labelled and 768 unlabelled objects is read out on the same 256: it
    is the point N = 1,024 of the unlabelled curve, beside the 256-object runs (which it must not
    replace), and stays out of the curve over labelled objects."""
    root = tmp_path / "runs"
    for seed, lf in ((0, 0.6), (1, 0.7)):
        _run(root, 256, seed, lf)
    _run(root, 256, 0, 0.4, unlabelled=768)
    _run(tmp_path / "again", 256, 1, 0.5, unlabelled=0)  # the option given at 0: the same run as without it
    rows = G.collect([root, tmp_path / "again"])
    lf = {(r["n_objects"], r["n_unlabelled"], r["seed"]): r["trajectory"]["overall"] for r in rows
          if r["method"] == "Latent Filter multi_l (labels)"}
    assert lf == {(256, 0, 0): 0.6, (256, 0, 1): 0.5, (256, 768, 0): 0.4}
    text = G.write_page(rows, tmp_path / "docs", command="test").read_text()
    labelled_curve = text.split("## Mean over factors, whole trajectory")[1].split("##")[0]
    assert "| Latent Filter multi_l (labels) |" in labelled_curve and "0.550 [" in labelled_curve
    unl = text.split("## Unlabelled objects: 256 labelled, N training objects in all")[1].split("### Mean over factors, last step")[0]
    assert "| method | 256 | 1024 |" in unl
    assert "| Latent Filter multi_l (labels) | 0.550 [" in unl and "| 0.400 (1) |" in unl
    assert "| mean predictor | 1.000 [1.000, 1.000] (2) | 1.000 (1) |" in unl
    # the scores file keeps the axis: read back, the same rows
    assert G.collect([tmp_path / "docs" / "generalisation_scores.json"]) == rows
