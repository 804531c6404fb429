"""experiments/population_objectives.py: the runs it plans and its selection rule, on
hand-made scores (no training)."""

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "population_objectives", Path(__file__).parents[2] / "experiments" / "population_objectives.py")
po = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(po)


def test_plan_counts_the_labelled_and_the_unlabelled_objects():
    runs = po.plan(["context", "both"], [256, 1024], [0, 1, 2], 256)
    assert len(runs) == 2 * 2 * 3
    obj, n, seed, overrides = runs[-1]
    assert (obj, n, seed) == ("both", 1024, 2)
    assert "recipe=context_both" in overrides and "data.n_objects=256" in overrides
    assert "data.n_unlabelled_objects=768" in overrides and "experiment=population" in overrides
    assert "data.n_unlabelled_objects=0" in runs[0][3]
    with pytest.raises(SystemExit, match="below"):
        po.plan(["context"], [128], [0], 256)


def _rows(context, other, name="invariance", n=256):
    return ([{"objective": "context", "n": n, "seed": s, "side": "val", "reader": "latent_filter", "last": v,
              "whole": v} for s, v in enumerate(context)]
            + [{"objective": name, "n": n, "seed": s, "side": "val", "reader": "latent_filter", "last": v,
                "whole": v} for s, v in enumerate(other)])


def test_an_objective_is_adopted_only_if_lower_in_every_seed_by_more_than_the_seed_sd():
    context = [0.50, 0.52, 0.54]  # sd 0.02
    assert po.verdict(_rows(context, [0.45, 0.47, 0.49]), 256, ["context", "invariance"])[0] == "invariance"
    # lower in every seed, by 0.01 < sd
    assert po.verdict(_rows(context, [0.49, 0.51, 0.53]), 256, ["context", "invariance"])[0] == "context"
    # far lower on average, higher in one seed
    assert po.verdict(_rows(context, [0.30, 0.30, 0.55]), 256, ["context", "invariance"])[0] == "context"
    # two pass: the lower mean is adopted; the test side is never read
    rows = _rows(context, [0.45, 0.47, 0.49]) + _rows(context, [0.40, 0.42, 0.44], "physical")[3:]
    rows += [{**r, "side": "test", "last": 0.0} for r in _rows(context, [0.9, 0.9, 0.9], "both")]
    chosen, notes = po.verdict(rows, 256, ["context", "invariance", "physical", "both"])
    assert chosen == "physical" and any("both: 0 of 3 seeds" in n for n in notes)


def test_a_weight_other_than_the_recipes_names_its_runs():
    runs = po.plan(["context", "invariance", "both"], [256], [0], 256, weight=1000.0)
    assert [r[0] for r in runs] == ["context", "invariance-w1000", "both-w1000"]
    assert "model.context.invariance=1000.0" in runs[1][3] and "model.context.physical=1000.0" not in runs[1][3]
    assert {"model.context.invariance=1000.0", "model.context.physical=1000.0"} <= set(runs[2][3])
    assert not any("model.context" in o for o in runs[0][3])


def test_the_default_objectives_rows_at_the_labelled_size_are_marked_the_population_default(tmp_path):
    """scores() marks the rows of the population default as configured (its recipe in
    configs/experiment/population.yaml, at N = the labelled objects), which the main job's
    closing line quotes (run.summary.population_scores)."""
    import json

    from omegaconf import OmegaConf

    recipe = next(d["override /recipe"] for d in OmegaConf.load(Path(po.REPO) / "configs" / "experiment" /
                                                                  "population.yaml").defaults
                  if "override /recipe" in d)
    assert po.OBJECTIVES[po.DEFAULT_OBJECTIVE] == [f"recipe={recipe}"]
    for obj, n in [("context", 256), ("context", 1024), ("invariance", 256)]:
        folder = po.run_dir(tmp_path, obj, n, 0) / po.SIDES["test"]
        folder.mkdir(parents=True)
        (folder / "results.json").write_text(json.dumps({"runs": [
            {"method": "latent_filter", "nmse_last_step_overall": 0.5, "nmse_trajectory_overall": 0.6}]}))
    rows = po.scores(tmp_path, ["context", "invariance"], [256, 1024], [0], 256)
    assert {(r["objective"], r["n"]): r["population_default"] for r in rows} == {
        ("context", 256): True, ("context", 1024): False, ("invariance", 256): False}

    from embodied_tactile.run import summary

    (tmp_path / "rows.json").write_text(json.dumps(rows))
    assert summary.population_scores(tmp_path / "rows.json") == {"latent_filter": (0.6, 0.5, 1)}
