"""The evaluation side of a study: target encodings, heterogeneity as a decision,
group-table normalisation, split kind / unseen objects, verdicts on the paper's findings."""

from __future__ import annotations

import json
import warnings

import re
from pathlib import Path

import numpy as np
import pytest

from conftest import stable_seed
from embodied_tactile.constants import FACTOR_NAMES, OBJECTS
from embodied_tactile.eval import Results, nmse_trajectory



# ------------------------------------------------------------------ targets
def test_design_rank_encoding_by_hand():
    from embodied_tactile.eval.targets import encode_factors

    f = np.array([OBJECTS[o].factors() for o in (0, 4, 8, 27)])  # EF10 5mm f10, EF50 10mm f10, PLA 20mm f10, hetero
    r = encode_factors(f, "design_rank")
    np.testing.assert_allclose(r, [[0, 0, 0, 0], [0, 1, 1, 0], [0, 2, 2, 0], [0, 1, 0, 1]])
    np.testing.assert_array_equal(encode_factors(f, "physical"), f)
    f2 = f.copy()
    f2[0, 2] = np.nan
    assert np.isnan(encode_factors(f2)[0, 2])
    with pytest.raises(ValueError, match=r"stiffness.*outside the design levels"):
        encode_factors([[10.0, 5.0, 12.0, 0.0]])


def test_design_rank_resolves_the_two_silicones():
    """Swapping Ecoflex 00-10 and 00-50 everywhere costs 0.004 NMSE in log10 Pa, 0.9 in ranks."""
    from embodied_tactile.eval.targets import encode_factors

    f = np.array([OBJECTS[o].factors() for o in range(27)])
    swapped = f.copy()
    k = FACTOR_NAMES.index("stiffness")
    ef10, ef50 = f[0, k], f[3, k]
    swapped[f[:, k] == ef10, k], swapped[f[:, k] == ef50, k] = ef50, ef10
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # heterogeneity is constant among objects 0..26
        phys = nmse_trajectory(f, swapped[:, None, :])[k]
        rank = nmse_trajectory(encode_factors(f), encode_factors(swapped)[:, None, :])[k]
    # by hand: 18 of 27 objects off by one level; levels equally often, so the variance is that of 3 values
    assert rank == pytest.approx(18 * 1.0 / (27 * np.var([0, 1, 2])))
    assert phys == pytest.approx(18 * (ef50 - ef10) ** 2 / (27 * np.var([ef10, ef50, f[6, k]])))
    assert phys < 0.01 and rank > 0.8


# ------------------------------------------------------------------ heterogeneity as a decision
def test_balanced_accuracy_and_auc_by_hand():
    from sklearn.metrics import roc_auc_score

    from embodied_tactile.eval.metrics import balanced_accuracy, roc_auc

    y, s = np.array([0, 0, 1, 1]), np.array([0.1, 0.6, 0.4, 0.9])
    assert roc_auc(y, s) == pytest.approx(0.75)  # 3 of the 4 (pos, neg) pairs ordered
    assert balanced_accuracy(y, s) == pytest.approx(0.5)  # TPR 1/2, TNR 1/2
    assert roc_auc([0, 1], [0.5, 0.5]) == pytest.approx(0.5)  # a tie counts one half
    y2 = np.array([0, 0, 0, 0, 0, 1]); s2 = np.array([0.0, 0.2, 0.7, 0.1, 0.1, 0.6])
    assert balanced_accuracy(y2, s2) == pytest.approx(0.5 * (1.0 + 4 / 5))
    assert roc_auc(y2, s2) == pytest.approx(roc_auc_score(y2, s2)) == pytest.approx(4 / 5)
    assert np.isnan(roc_auc([1, 1], [0.2, 0.3])) and np.isnan(balanced_accuracy([0, 0], [0.2, 0.3]))
    # labels (n, 1) against every frame (n, T): each frame a sample
    assert roc_auc(np.array([[0], [1]]), np.array([[0.1, 0.9], [0.5, 0.6]])) == pytest.approx(0.5)  # 2 of 4 pairs


def _hand_run(pred_het_last=None):
    """4 soft + 4 hard + 2 heterogeneous objects, 2 frames, known predictions."""
    obj = np.array([0, 1, 3, 4, 2, 6, 7, 8, 27, 28])  # hard: EF10 20 mm + three PLA
    f = np.array([OBJECTS[o].factors() for o in obj])
    rng = np.random.default_rng(0)
    pred = f[:, None, :] + rng.normal(scale=0.3, size=(len(obj), 2, 4)) * f.std(axis=0)
    if pred_het_last is not None:
        pred[:, -1, 3] = pred_het_last
    return Results(pred=pred, factors=f, object_id=obj, action_index=np.zeros(len(obj), int), seed=0,
                   primitive="pressing")


def test_objects_outside_the_catalogue_are_grouped_as_population_with_their_own_factors():
    """Objects with ids beyond the 32-object catalogue (their factors from their trials):
    the group tables put them in 'population', the catalogue groups are unchanged."""
    r = _hand_run()
    extra = Results(pred=np.concatenate([r.pred, r.pred[:2] * 1.1]), factors=np.concatenate([r.factors, r.factors[:2] + 1]),
                    object_id=np.concatenate([r.object_id, [32, 40]]), action_index=np.zeros(r.n_test + 2, int),
                    seed=0, primitive="pressing")
    assert list(extra.group[-2:]) == ["population", "population"]
    groups = extra.group_summary()
    assert groups["population"]["n"] == 2
    assert {g: groups[g]["n"] for g in ("soft", "hard", "heterogeneous")} == \
        {g: v["n"] for g, v in r.group_summary().items()}


def test_heterogeneity_scores_on_a_run():
    r = _hand_run(pred_het_last=[0.0, 0.1, 0.2, 0.3, 0.4, 0.6, 0.0, 0.0, 0.9, 0.45])
    h = r.heterogeneity_scores()
    assert (h["n_pos"], h["n_neg"]) == (2, 8)
    assert h["balanced_accuracy_last"] == pytest.approx(0.5 * (0.5 + 7 / 8))
    assert h["roc_auc_last"] == pytest.approx((8 + 7) / 16)  # 0.9 beats all 8, 0.45 beats 7
    assert r.summary()["heterogeneity_classification"]["roc_auc_last"] == pytest.approx(15 / 16)


def test_group_tables_state_and_apply_their_variance():
    from embodied_tactile.eval.tables import table_groups

    r = _hand_run()
    total, own = table_groups([r], method=None), table_groups([r], method=None, norm="group")
    assert total.name == "environmentshape" and own.name == "environmentshape_groupvar"
    assert "ALL held-out sequences" in total.caption and "group's OWN" in own.caption
    col = total.columns.index("hard:pressing")
    m = r.group == "hard"
    err = ((r.factors[m][:, None, :] - r.pred[m]) ** 2).mean(axis=(0, 1))
    by_total = err / r.factors.var(axis=0)
    var_g = r.factors[m].var(axis=0)
    by_own = np.where(var_g > 0, err / np.where(var_g > 0, var_g, 1.0), np.nan)
    assert np.isfinite(by_own).sum() == 2  # amplitude, stiffness vary in this hard group; frequency, heterogeneity not
    for k, name in enumerate(FACTOR_NAMES):
        row_t = next(x for x in total.rows if x[2] == name)
        row_o = next(x for x in own.rows if x[2] == name)
        assert row_t[col] == pytest.approx(by_total[k])
        if np.isnan(by_own[k]):  # constant inside the group: undefined, printed as '–'
            assert np.isnan(row_o[col])
        else:
            assert row_o[col] == pytest.approx(by_own[k])
    assert "nan" not in own.to_markdown().lower()


# ------------------------------------------------------------------ split kind, unseen objects
def _trial_refs():
    from embodied_tactile.data.datamodule import TrialRef

    return [TrialRef(f"obj{o:02d}_soft_pressing_a{a:02d}_r00", o, a, "soft", "pressing", tuple(OBJECTS[o].factors()))
            for o in range(32) for a in (2, 6, 10, 14)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_object_split_reports_unseen_objects(seed):
    from embodied_tactile.data.datamodule import split_trials
    from embodied_tactile.eval.results import split_report

    refs = _trial_refs()
    for by, unseen in (("object", True), ("trial", False)):
        tr, va, te = split_trials(refs, by=by, seed=seed)
        rep = split_report({"split": by, "train": [t.name for t in tr], "val": [t.name for t in va],
                            "test": [t.name for t in te]}, {t.name: t.object_id for t in refs})
        assert rep["kind"] == by and rep["unseen_objects"] is unseen
        if by == "object":  # no object has trials on both sides
            assert rep["seen_test_objects"] == [] and not set(rep["test_objects"]) & set(rep["train_objects"])
            assert sorted(rep["test_objects"]) == sorted({t.object_id for t in te})


def test_evaluate_refuses_an_object_split_with_seen_objects_and_captions_say_the_kind(tmp_path):
    from embodied_tactile.eval import runs
    from embodied_tactile.eval.tables import caption_note

    bad = {"split": "object", "train": ["obj01_soft_pressing_a02_r00", "obj02_soft_pressing_a02_r00"], "val": [],
           "test": ["obj02_soft_pressing_a06_r00"]}
    objects = {"obj01_soft_pressing_a02_r00": 1, "obj02_soft_pressing_a02_r00": 2, "obj02_soft_pressing_a06_r00": 2,
               "obj03_soft_pressing_a06_r00": 3}  # from the trials' attributes
    (tmp_path / "split.json").write_text(json.dumps(bad))
    run = runs.Run(run_dir=tmp_path, ckpt=tmp_path / "x.ckpt", cfg=None, name="r")
    with pytest.raises(runs.EvaluationError, match=r"object split.*\[2\]"):
        runs.run_split(run, str(tmp_path / "split.json"), objects)
    bad["test"] = ["obj03_soft_pressing_a06_r00"]
    (tmp_path / "split.json").write_text(json.dumps(bad))
    rep = runs.run_split(run, str(tmp_path / "split.json"), objects)
    assert rep["unseen_objects"] is True and rep["test_objects"] == [3]
    r = _hand_run()
    r.split, r.unseen_objects, r.targets = "object", True, "design_rank"
    note = caption_note([r])
    assert "Split kind: object (whole objects held out" in note and "never in training" in note
    assert "Targets: design_rank" in note


# ------------------------------------------------------------------ verdicts
def _run(modality, skin, primitive, seed, err, *, n=64, t=3, het_err=None):
    """A Results with prediction error err (x the factor's std), fixed held-out set per seed."""
    rng = np.random.default_rng([seed, stable_seed(f"{modality}/{skin}/{primitive}", 997)])
    obj = np.arange(n) % 32
    f = np.array([OBJECTS[o].factors() for o in obj])
    sd = f.std(axis=0)
    scale = np.full(n, err)
    if het_err is not None:
        scale[np.isin(obj, (27, 28, 29, 30, 31))] = het_err
    pred = f[:, None, :] + scale[:, None, None] * sd * rng.normal(size=(n, t, 4))
    return Results(pred=pred, factors=f, object_id=obj, action_index=np.full(n, seed % 16), modality=modality,
                   skin=skin, primitive=primitive, seed=seed, n_train=96)


def _claim(rows, letter, words=""):
    return next(r for r in rows if r["finding"] == letter and words in r["claim"])


def test_verdicts_read_reproduced_contradicted_and_inconclusive():
    from embodied_tactile.eval.verdicts import evaluate_findings, run_score, summarise, verdict_tables

    seeds = range(4)
    rs = ([_run("multi_l", "soft", "pressing", s, 0.2) for s in seeds]      # (b) late beats early: reproduced
          + [_run("multi_e", "soft", "pressing", s, 0.6) for s in seeds]
          + [_run("fsr_tb", "soft", "pressing", s, 0.9) for s in seeds]      # (c) fsr_tb worse than fsr_t: contradicted
          + [_run("fsr_t", "soft", "pressing", s, 0.3) for s in seeds]
          + [_run("fsr_b", "soft", "pressing", s, 0.3) for s in seeds]
          + [_run("acc", "soft", "pressing", s, 0.6) for s in seeds])
    comps = evaluate_findings(rs)
    b = next(c for c in comps if c.finding == "b" and c.better.primitive == "pressing")
    d = np.array([run_score(e, "overall") - run_score(l, "overall") for l, e in zip(rs[0:4], rs[4:8])])
    from scipy.stats import t as student_t

    h = student_t.ppf(0.975, 3) * d.std(ddof=1) / 2
    assert b.stats["pairing"] == "paired by seed" and b.stats["n"] == 4
    assert b.stats["mean"] == pytest.approx(d.mean()) and b.stats["ci95_low"] == pytest.approx(d.mean() - h)
    assert b.verdict == "reproduced"
    rows = summarise(comps)
    assert _claim(rows, "b")["verdict"] == "reproduced"
    assert _claim(rows, "c", "stiffness")["verdict"] == "contradicted"
    assert _claim(rows, "f")["verdict"] == "not measured"  # no multi_l run on another primitive
    # (a): multi_e (0.6) against acc (0.6) is a tie -> inconclusive; nothing contradicts multi_l -> claim inconclusive
    a_tie = next(c for c in comps if c.finding == "a" and c.better.modality == "multi_e" and c.worse.modality == "acc"
                 and c.better.primitive == "pressing")
    assert a_tie.verdict == "inconclusive" and a_tie.stats["ci95_low"] < 0 < a_tie.stats["ci95_high"]
    assert _claim(rows, "a")["verdict"] == "contradicted"  # multi_e loses to fsr_t (0.3): one contradiction is enough
    findings, table = verdict_tables(rs)
    assert len(findings.rows) == len(rows) and {"reproduced", "contradicted", "inconclusive"} <= {r[2] for r in findings.rows}
    assert "nan" not in table.to_markdown().lower()


def test_verdicts_unpaired_skins_and_fewer_than_three_seeds():
    from embodied_tactile.eval.verdicts import difference, evaluate_findings, run_score

    rs = ([_run("multi_l", "soft", p, s, 0.2, het_err=1.5) for p in ("pressing", "precession") for s in range(3)]
          + [_run("multi_l", "hard", "pressing", s + 10, 0.2, het_err=0.3) for s in range(3)])
    comps = evaluate_findings(rs)
    e = next(c for c in comps if c.finding == "e" and c.better.group == "heterogeneous" and c.better.primitive == "pressing")
    assert e.stats["pairing"] == "unpaired (Welch)" and e.verdict == "contradicted"  # hard skin better here
    d = next(c for c in comps if c.finding == "d" and c.better.skin == "soft" and c.better.primitive == "pressing")
    assert d.stats["pairing"] == "paired by seed" and d.verdict == "reproduced"  # within a run
    two = difference(rs[:2], rs[3:5], lambda r: run_score(r, "overall"), lambda r: run_score(r, "overall"))
    assert two["n"] == 2 and two["verdict"] == "inconclusive" and np.isnan(two["ci95_low"])


def _sets_run(primitive, seed, err_of_set, *, per_set=8, t=30, slow_of_set=None):
    """multi_l soft with per_set held-out trials of each of the 16 parameter sets; the error of
    set a is err_of_set(a) x the factor's std at the last frames, slow_of_set(a) times it early on."""
    from embodied_tactile.constants import ACTIONS

    rng = np.random.default_rng([seed, 11])
    act = np.repeat(np.arange(16), per_set)
    obj = np.arange(len(act)) % 32
    f = np.array([OBJECTS[o].factors() for o in obj])
    sd = f.std(axis=0)
    err = np.array([err_of_set(ACTIONS[primitive][a].params) for a in act])
    slow = np.ones(len(act)) if slow_of_set is None else np.array([slow_of_set(ACTIONS[primitive][a].params) for a in act])
    decay = 1.0 + (slow[:, None] - 1.0) * np.exp(-np.arange(t) / 5.0)[None, :]  # early error x slow, then err
    pred = f[:, None, :] + (err[:, None] * decay)[:, :, None] * sd * rng.normal(size=(len(act), t, 4))
    return Results(pred=pred, factors=f, object_id=obj, action_index=act, modality="multi_l", skin="soft",
                   primitive=primitive, seed=seed, n_train=96)


def test_the_parameter_set_findings_read_the_runs_trials_by_set():
    """(g) 0.6 Hz best, (h) deeper better, (i) pressing's sets change convergence more than the
    final error, (j) the sets matter more in sliding than in pressing: read from each run's
    held-out trials grouped by parameter set, paired within the run."""
    from embodied_tactile.eval.verdicts import evaluate_findings, summarise

    def press(p):  # every set converges to the same error, some much later
        return 0.2

    def press_slow(p):
        return 1.0 + 6.0 * (p["omega_z_hz"] == 0.2)

    def slide(p):  # 0.6 Hz and the longest stroke best; the sets differ a lot
        return 0.15 + 1.5 * abs(p["omega_xy_gamma_hz"] - 0.6) + 0.1 * (8.0 - p["A_xy_mm"])

    rs = ([_sets_run("pressing", s, press, slow_of_set=press_slow) for s in range(3)]
          + [_sets_run("sliding", s, slide) for s in range(3)])
    rows = summarise(comps := evaluate_findings(rs))
    g = [c for c in comps if c.finding == "g" and c.better.primitive == "sliding"]
    assert len(g) == 2 and all(c.verdict == "reproduced" and c.stats["pairing"] == "paired by seed" for c in g)
    assert next(c for c in comps if c.finding == "h" and c.better.primitive == "sliding").verdict == "reproduced"
    assert next(c for c in comps if c.finding == "h" and c.better.primitive == "pressing").verdict == "inconclusive"
    assert _claim(rows, "i")["verdict"] == "reproduced"
    j = next(c for c in comps if c.finding == "j" and c.worse.primitive == "sliding")
    assert j.verdict == "reproduced"
    assert next(c for c in comps if c.finding == "j" and c.worse.primitive == "precession").verdict == "not measured"
    flat = [_sets_run("sliding", s, lambda p: 0.3) for s in range(3)]  # no set better than another
    assert all(c.verdict == "inconclusive" for c in evaluate_findings(flat) if c.finding in "gh"
               and c.better.primitive == "sliding")


def test_paper_best_primitive_from_table2():
    from embodied_tactile.eval.verdicts import paper_all_objects, paper_best_primitive

    # stiffness, soft e-Skin: pressing (12*0.032 + 15*0.112 + 5*0.023) / 32 = 0.0681 is the lowest
    assert paper_all_objects("soft", "pressing", "stiffness") == pytest.approx((12 * 0.032 + 15 * 0.112 + 5 * 0.023) / 32)
    assert paper_best_primitive("stiffness") == "pressing" and paper_best_primitive("heterogeneity") == "precession"


def test_design_rank_accepts_float32_factors():
    """The DataModule serves factors as float32: 4.7403626 must still be Ecoflex 00-10's level."""
    from embodied_tactile.eval.targets import encode_factors

    f = np.array([OBJECTS[o].factors() for o in (0, 4, 8)], dtype=np.float32)
    np.testing.assert_allclose(encode_factors(f)[:, 2], [0, 1, 2], atol=1e-5)


# ------------------------------------------------------------------ docs/generated/results.md generator
def test_group_summary_uses_the_runs_total_variance():
    r = _run("multi_l", "soft", "pressing", 0, 0.3)
    g = r.summary()["nmse_trajectory_by_group"]
    assert set(g) == {"soft", "hard", "heterogeneous"}
    for name, row in g.items():
        by_hand = r.subset_nmse(r.group == name)  # the run's reference variance, not the group's
        np.testing.assert_allclose([row[f] for f in FACTOR_NAMES], by_hand)
        assert row["overall"] == pytest.approx(float(np.mean(by_hand)))
        assert row["n"] == int((r.group == name).sum())


@pytest.mark.slow
def test_study_report_table2_intervals_verdicts_and_what_was_not_run(tmp_path):
    from scipy.stats import t as student_t

    from embodied_tactile.eval.report import write_report
    from embodied_tactile.eval.study_report import load, render, write_results

    rs = ([_run("multi_l", "soft", "pressing", s, 0.2) for s in range(3)]
          + [_run("multi_e", "soft", "pressing", s, 0.6) for s in range(3)]
          + [_run("fsr_t", "soft", "pressing", s, 0.3) for s in range(2)])
    write_report(rs, tmp_path / "evaluation", figures=False)
    text = render(load(tmp_path / "evaluation"))
    # the Table 2 cell soft skin / soft objects / pressing / Overall: mean and t interval over the 3 seeds
    vals = np.array([r.summary()["nmse_trajectory_by_group"]["soft"]["overall"] for r in rs[:3]])
    h = student_t.ppf(0.975, 2) * vals.std(ddof=1) / np.sqrt(3)
    row = next(ln for ln in text.splitlines() if ln.startswith("| Overall | soft |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert float(cells[2]) == pytest.approx(vals.mean(), abs=1e-4)
    assert cells[3] == f"[{vals.mean() - h:.3f}, {vals.mean() + h:.3f}]"
    assert cells[4] == "3" and float(cells[5]) == pytest.approx(0.017)  # the paper's soft/soft/pressing overall
    # (b) late beats early: measured on 3 paired seeds -> a verdict row
    assert "## The paper's findings and their verdicts" in text and "reproduced" in text
    # not run: 24 cells minus multi_l and multi_e soft pressing (3 seeds each); fsr_t has only 2 seeds
    not_run = text.split("## What was not run", 1)[1]
    assert "(22 of 24)" in not_run
    assert "| fsr_t | soft | pressing | 2 | 0,1 |" in not_run
    assert "| multi_l | soft | pressing |" not in not_run
    out = tmp_path / "results.md"
    assert write_results(str(tmp_path / "evaluation"), out=str(out)) == out.read_text()
    assert out.read_text() == render(load(tmp_path / "evaluation"), out_path=str(out))
    assert (f"Generated by `embodied-tactile report page=results evaluation={tmp_path / 'evaluation'} out={out}` "
            "from that folder's") in out.read_text()  # the header names the command that wrote it
    assert out.read_text().replace(f"out={out}`", "out=docs/generated/results.md`") == text
    # the command writes the same page (it composes the default scene inside its own Hydra app)
    from embodied_tactile import pages

    with pytest.raises(SystemExit) as exc:
        pages.main(["page=results", f"evaluation={tmp_path / 'evaluation'}", "notes=[parts ran on two commits]",
                    f"out={out}"])
    assert exc.value.code == 0
    assert out.read_text().replace("- Note: parts ran on two commits\n", "") == write_results(
        str(tmp_path / "evaluation"), out=str(tmp_path / "again.md")).replace("again.md", "results.md")
    assert "- Note: parts ran on two commits" in out.read_text()


@pytest.mark.slow
def test_results_page_shows_the_evaluations_figures_copied_beside_it(tmp_path):
    """The page links the evaluation's figures (over interaction time, distances of seed 0), copied
    next to it with their captions' first sentence; a figure of an earlier page does not linger."""
    from embodied_tactile.eval.report import write_report
    from embodied_tactile.eval.study_report import write_results

    rs = [_run("multi_l", "soft", "pressing", s, 0.2) for s in range(3)]
    write_report(rs, tmp_path / "evaluation", umap=False)
    for seed in (0, 1):  # these runs carry no latents: matrices as evaluate.py names them
        (tmp_path / "evaluation" / "figures" / f"distances_latent_filter_multi_l_soft_pressing_seed_{seed}.png").write_bytes(b"m")
    stale = tmp_path / "docs" / "figures" / "results" / "nmse_time_by_old.png"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"old")
    out = tmp_path / "docs" / "results.md"
    text = write_results(str(tmp_path / "evaluation"), out=str(out))
    figures = text.split("## Figures", 1)[1].split("\n## ", 1)[0]
    links = re.findall(r"!\[[^]]*\]\(([^)]+)\)", figures)
    assert links[0] == "figures/results/nmse_time_by_modality.png"
    assert "figures/results/distances_latent_filter_multi_l_soft_pressing_seed_0.png" in links
    assert not any("seed_1" in link for link in links)  # one matrix per cell
    for link in links:
        assert (out.parent / link).read_bytes() == (tmp_path / "evaluation" / "figures" / Path(link).name).read_bytes()
    assert "*nmse_time_by_modality.png*: Held-out NMSE per frame against interaction time (s), by modality;" in figures
    assert not stale.exists()


def test_study_report_table1_gives_each_parameter_sets_nmse_with_its_interval_over_seeds(tmp_path):
    from scipy.stats import t as student_t

    from embodied_tactile.eval.report import write_report
    from embodied_tactile.eval.study_report import load, render

    rs = [_sets_run("sliding", s, lambda p: 0.1 + p["omega_xy_gamma_hz"]) for s in range(3)]
    write_report(rs, tmp_path / "evaluation", figures=False)
    text = render(load(tmp_path / "evaluation"))
    assert "## table1 multi l soft" in text
    m = rs[0].action_index == 2  # set 3: A_xy 2 mm at 0.6 Hz
    vals = np.array([rs[i].summary()["nmse_by_action"]["3"]["trajectory"] for i in range(3)])
    assert vals[0] == pytest.approx(float(np.mean(rs[0].subset_nmse(m))))
    h = student_t.ppf(0.975, 2) * vals.std(ddof=1) / np.sqrt(3)
    row = next(ln for ln in text.splitlines() if ln.startswith("| 3 |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "A_xy_mm=2, A_gamma_deg=3, omega_xy_gamma_hz=0.6"
    assert float(cells[2]) == pytest.approx(vals.mean(), abs=1e-4)
    assert cells[3] == f"[{vals.mean() - h:.3f}, {vals.mean() + h:.3f}]" and cells[6] == "3 x 8"


@pytest.mark.slow
def test_study_report_objects_section_takes_object_split_runs_only(tmp_path):
    from embodied_tactile.eval.report import write_report
    from embodied_tactile.eval.study_report import StudyReportError, load, render, write_results

    main_runs = [_run("multi_l", "soft", "pressing", s, 0.2) for s in range(3)]
    obj_runs = [_run("multi_l", "soft", "pressing", s, 0.9) for s in range(3)]
    for r in obj_runs:
        r.split, r.unseen_objects = "object", True
    write_report(main_runs, tmp_path / "study", figures=False)
    write_report(obj_runs, tmp_path / "objects", figures=False)
    text = render(load(tmp_path / "study"), objects=load(tmp_path / "objects"))
    section = text.split("## Objects never touched in training", 1)[1].split("## What was not run", 1)[0]
    vals = [r.summary()["nmse_trajectory_overall"] for r in obj_runs]
    row = next(ln for ln in section.splitlines() if ln.startswith("| latent_filter |"))
    assert f"{np.mean(vals):.4f}" in row and "| 3 |" in row
    with pytest.raises(StudyReportError, match="object-split runs with unseen held-out objects only"):
        render(load(tmp_path / "study"), objects=load(tmp_path / "study"))
    out = tmp_path / "r.md"
    write_results(str(tmp_path / "study"), objects=str(tmp_path / "objects"), out=str(out))
    written = out.read_text()  # the same page, its head naming the whole command
    assert written.split("## What was run", 1)[1] == text.split("## What was run", 1)[1]
    assert f"report page=results evaluation={tmp_path / 'study'} objects={tmp_path / 'objects'} out={out}`" in written
    write_results(str(tmp_path / "study"), extras=[("Prior ablation", str(tmp_path / "objects"))], out=str(out))
    assert "## Prior ablation" in out.read_text() and f"{np.mean(vals):.4f}" in out.read_text()
    assert f"""'extra=["Prior ablation={tmp_path / 'objects'}"]'""" in out.read_text()


def test_study_report_names_a_missing_results_file(tmp_path, capsys, monkeypatch, restore_logging):
    from embodied_tactile import pages

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        pages.main(["page=results", f"evaluation={tmp_path}"])
    assert exc.value.code == 2
    assert capsys.readouterr().err.splitlines() == [
        f"report: error: {tmp_path / 'results.json'} does not exist: run `python evaluate.py <study folder>` first"]


def test_study_report_refuses_validation_side_scores(tmp_path):
    from embodied_tactile.eval.report import write_report
    from embodied_tactile.eval.study_report import StudyReportError, load

    runs = [_run("multi_l", "soft", "pressing", s, 0.2) for s in range(3)]
    runs[1].params["held_out"] = "val"
    write_report(runs, tmp_path / "evaluation", figures=False)
    with pytest.raises(StudyReportError, match=r"results\.json: latent_filter scored on the validation side"):
        load(tmp_path / "evaluation")


def test_study_report_puts_each_cells_untrained_floor_beside_the_trained_filter(tmp_path):
    """The floor table reads every evaluated run's krr_history.jsonl: the final alignment
    beside the step-0 check, whole trajectory and last frame, mean over seeds, and counts the
    seeds below the floor on both read-outs."""
    import json

    from embodied_tactile.eval.study_report import floor_table

    runs = []
    for seed, (final, first) in enumerate([((0.2, 0.1), (0.9, 0.8)), ((0.4, 0.3), (0.9, 0.8)), ((0.95, 0.5), (0.9, 0.8))]):
        d = tmp_path / f"run{seed}"
        d.mkdir()
        (d / "config_resolved.yaml").write_text("modality: {name: multi_l}\nskin: {name: soft}\nprimitive: {name: pressing}\n")
        rows = [{"initial": True, "nmse_overall": first[0], "nmse_last_overall": first[1]},
                {"nmse_overall": 0.5, "nmse_last_overall": 0.5},
                {"final": True, "nmse_overall": final[0], "nmse_last_overall": final[1]}]
        (d / "krr_history.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
        runs.append({"run_dir": str(d), "seed": seed})
    (tmp_path / "untrained_only").mkdir()  # a run without a final row is left out
    runs.append({"run_dir": str(tmp_path / "untrained_only"), "seed": 9})
    table = floor_table({"_evaluation": {"runs": runs}})
    assert len(table.rows) == 1
    cell, n, trained_w, untrained_w, trained_l, untrained_l, below = (table.rows[0][:3], *table.rows[0][3:])
    assert cell == ["multi_l", "soft", "pressing"] and n == 3
    assert trained_w == pytest.approx((0.2 + 0.4 + 0.95) / 3) and untrained_w == pytest.approx(0.9)
    assert trained_l == pytest.approx(0.3) and untrained_l == pytest.approx(0.8)
    assert below == "2 of 3"  # seed 2 is above its floor on the whole trajectory
    assert floor_table({"_evaluation": {"runs": runs[3:]}}) is None


def test_the_pages_commands_name_parts_of_the_study_not_the_machines_folders(tmp_path):
    from embodied_tactile.eval.study_report import _command_lines

    study = tmp_path / "somewhere" / "study"
    files = []
    for part in ("multi_l_soft_pressing", "acc_soft_pressing"):
        (study / part).mkdir(parents=True)
        (study / part / "multirun.yaml").write_text("{}")
        for seed in (0, 1):
            files.append({"run_dir": study / part / f"seed={seed}",
                          "overrides": [f"combo={part.rsplit('_', 1)[0]}", f"seed={seed}", "sweep=study",
                                        f"paths.data_dir={tmp_path}/data"]})
    lines = _command_lines(files)
    assert lines[1] == ("- `multi_l_soft_pressing` (2 jobs): `python train.py -m combo=multi_l_soft sweep=study "
                        "paths.data_dir=<data_dir> hydra.sweep.dir=<study>/multi_l_soft_pressing`, varying: "
                        "`seed=0`, `seed=1`")
    assert not any(str(tmp_path) in ln for ln in lines)
