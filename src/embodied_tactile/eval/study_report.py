"""``docs/generated/results.md`` from an evaluated study, generated, never typed by hand.

    python train.py -m sweep=study_min hydra.sweeper.params.seed=0 hydra.sweep.dir=logs/train/study/seed0
    ...                                                              # further parts: seed1, seed2, ...
    python evaluate.py logs/train/study                             # merges the parts -> logs/train/study/evaluation
    embodied-tactile report page=results evaluation=logs/train/study/evaluation out=docs/generated/results.md

Reads ``results.json`` (written by :func:`~embodied_tactile.eval.report.write_report`) and, when
present, ``evaluation.json`` and each evaluated run's ``config_resolved.yaml`` /
``metrics.json`` / ``provenance.json`` for the budget, the commands and the wall time. Writes:

* what was run: the parts and their commands (each job's Hydra overrides), the budget, the
  wall time (training and data preparation apart), the code commit;
* the Table 2 analogue for MULTI-L: per e-Skin, object group and primitive, the mean over
  seeds with its 95 % t interval beside the paper's value (:data:`~.verdicts.PAPER_TABLE2`);
  then the same tables in the convention of the authors' public code (squared error on
  targets min-max scaled to [0, 1] over the design range, :data:`~.metrics.SCALED_MSE_DEFINITION`),
  converted run by run with the held-out targets' variance of the trial split
  (:func:`held_out_variance`), and one sentence comparing both with the paper;
* the per-cell statistics over seeds for every modality (the ``aggregate`` table);
* the paper's findings with their verdicts and every comparison behind them;
* with ``objects=<evaluation folder>``: the held-out-object runs' statistics over seeds;
  with ``extra={TITLE: <evaluation folder>}`` (one or more): any further evaluation (an ablation);
* the figures of the evaluation folder (:data:`PAGE_FIGURES`: the error over interaction time
  per modality, e-Skin, method and the best and worst parameter sets, the error against
  training time, and each cell's class-distance matrix and UMAP of seed 0), copied next to the
  page into ``figures/results/`` with the first sentence of their captions;
* what was not run: every cell of the paper's 24 (8 modality x e-Skin combinations x 3
  primitives) with fewer than the protocol's 3 seeds.
"""

from __future__ import annotations

import json
import re
import shlex
from collections import defaultdict
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..options.data import SceneOptions, SplitOptions
from ..constants import ACTIONS, FACTOR_NAMES, N_ACTIONS, OBJECT_GROUPS, PRIMITIVES
from .metrics import SCALED_MSE_DEFINITION, reference_variance, scaled_mse_from_nmse
from .results import scored_on_validation
from .tables import FACTOR_LABELS, MISSING, Table, fmt_cell, seed_stats
from .targets import DEFAULT_TARGETS, design_range, encode_factors
from .verdicts import MIN_SEEDS, PAPER_TABLE2, SCORES, SOFT_SKIN_MODALITIES

#: the paper's 8 modality x e-Skin combinations (configs/combo/); x 3 primitives = its 24 cells
PAPER_COMBOS: tuple[tuple[str, str], ...] = (*((m, "soft") for m in SOFT_SKIN_MODALITIES),
                                             ("fsr_tb", "hard"), ("multi_l", "hard"))
METHOD = "latent_filter"


#: figures of an evaluation folder's ``figures/`` that the page shows, in this order (glob patterns)
PAGE_FIGURES = ("nmse_time_by_modality.png", "nmse_time_by_skin.png", "nmse_time_by_best_worst_action.png",
                "nmse_time_by_method.png", "error_vs_runtime.png", f"distances_{METHOD}_*_seed_0.png",
                f"umap_{METHOD}_*_seed_0.png")


class StudyReportError(ValueError):
    """An evaluation folder that cannot make a study report (names the file)."""


def _read_json(p: Path) -> dict:
    try:
        return json.loads(p.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise StudyReportError(f"{p}: cannot read ({err})") from None


def load(eval_dir: str | Path) -> dict:
    """The evaluation's ``results.json`` (required) and ``evaluation.json`` (optional)."""
    d = Path(eval_dir)
    res = d / "results.json"
    if not res.exists():
        raise StudyReportError(f"{res} does not exist: run `python evaluate.py <study folder>` first")
    blob = _read_json(res)
    if "runs" not in blob or "tables" not in blob:
        raise StudyReportError(f"{res}: not an evaluate.py results.json (no 'runs' / 'tables')")
    val = scored_on_validation(blob["runs"])
    if val:
        raise StudyReportError(f"{res}: {', '.join(val)} scored on the validation side (evaluate.py held_out=val); "
                               "the study report reads the test side only")
    ev = d / "evaluation.json"
    blob["_evaluation"] = _read_json(ev) if ev.exists() else {}
    blob["_dir"] = str(d)
    return blob


def _ci(st: Mapping[str, float]) -> str:
    if not (np.isfinite(st["ci95_low"]) and np.isfinite(st["ci95_high"])):
        return MISSING
    return f"[{fmt_cell(st['ci95_low'], 3)}, {fmt_cell(st['ci95_high'], 3)}]"


def _latent_runs(runs: Sequence[Mapping], modality: str | None = None) -> list[Mapping]:
    return [r for r in runs if r.get("method") == METHOD and (modality is None or r.get("modality") == modality)]


def held_out_variance(targets: str = DEFAULT_TARGETS, *, actions: Sequence[int] | None = None,
                      repetitions: int = SceneOptions.repetitions, test_fraction: float = SplitOptions.test_fraction,
                      seed: int = 0) -> tuple[np.ndarray, int]:
    """(per-factor variance, number) of the held-out test targets of the catalogue's trial
    split, rebuilt with the data module's own :func:`~embodied_tactile.data.datamodule.split_trials`
    over the 32 wave objects x ``actions`` (None: all 16) x ``repetitions``: the reference
    variance each run's NMSE divides by (:func:`~.metrics.reference_variance` of the held-out
    targets in ``targets`` encoding). The split holds out ``round(test_fraction * n)`` of each
    object's n trials, so which objects are held out, and the variance, do not depend on the
    seed or on the trials' names (the seed picks which of an object's trials)."""
    from ..data.datamodule import split_trials
    from ..data.prepare import catalogue_trials

    _, _, test = split_trials(catalogue_trials(actions, repetitions), by="trial", test_fraction=test_fraction, seed=seed)
    return reference_variance(encode_factors([t.factors for t in test], targets)), len(test)


def _scene(data: Mapping) -> dict:
    return {"actions": data.get("actions"), "repetitions": data.get("repetitions", SceneOptions.repetitions),
            "test_fraction": data.get("test_fraction", SplitOptions.test_fraction)}


def _default_scene() -> dict:
    """The scene of ``python train.py`` with no overrides (configs/train.yaml composed)."""
    from omegaconf import OmegaConf

    from ..run.config import compose

    cfg = compose()
    return _scene({k: OmegaConf.to_container(cfg.data, resolve=False).get(k)
                   for k in ("actions", "repetitions", "test_fraction")})


def _scene_candidates(files: Sequence[Mapping]) -> list[dict]:
    """The (actions, repetitions, test_fraction) of the evaluated runs' configs, then the
    embedded default's: where a run's trial split can be rebuilt from."""
    out: list[dict] = []
    for cand in [_scene((f.get("config") or {}).get("data", {})) for f in files] + [_default_scene()]:
        if cand not in out:
            out.append(cand)
    return out


def run_variance(run: Mapping, scenes: Sequence[Mapping]) -> np.ndarray | None:
    """The per-factor variance a run's NMSE divided by, rebuilt (:func:`held_out_variance`)
    from the first of ``scenes`` whose trial split holds out as many trials as the run scored;
    None where it cannot be rebuilt (not the simulated catalogue's trial split, or no scene
    matches the run's held-out count)."""
    if run.get("split") != "trial" or run.get("source", "simulated") != "simulated":
        return None
    for scene in scenes:
        var, n = held_out_variance(run.get("targets") or DEFAULT_TARGETS, seed=int(run.get("seed") or 0), **scene)
        if n == run.get("n_test"):
            return var
    return None


def run_paper_units(run: Mapping, scenes: Sequence[Mapping]) -> dict | None:
    """A run's ``nmse_trajectory_by_group`` in the code's convention (:data:`~.metrics.SCALED_MSE_DEFINITION`):
    per group, each factor's NMSE x var_k / r_k^2 and their mean as ``overall``, with the
    run's own held-out variance (:func:`run_variance`); None where that cannot be rebuilt."""
    var = run_variance(run, scenes)
    if var is None:
        return None
    rng = design_range(run.get("targets") or DEFAULT_TARGETS)
    out = {}
    for g, row in (run.get("nmse_trajectory_by_group") or {}).items():
        nm = np.array([np.nan if row.get(k) is None else row[k] for k in FACTOR_NAMES], dtype=np.float64)
        sc = scaled_mse_from_nmse(nm, var, rng)
        fin = sc[np.isfinite(sc)]
        out[g] = {**dict(zip(FACTOR_NAMES, sc.tolist())), "overall": float(fin.mean()) if fin.size else np.nan}
    return out


def table2_with_intervals(runs: Sequence[Mapping], modality: str = "multi_l", scenes: Sequence[Mapping] | None = None
                          ) -> list[Table]:
    """One table per e-Skin: rows factor (and Overall) x object group, columns the primitives;
    a cell is 'mean [95 % CI] (paper p)' over the seeds of that (skin, primitive) cell, the
    group's held-out sequences normalised by the run's total variance (Table 2's convention).
    With ``scenes`` (:func:`_scene_candidates`): the same tables in the convention of the
    authors' public code (:func:`run_paper_units`); a run whose variance cannot be rebuilt
    counts as not measured there."""
    rs = _latent_runs(runs, modality)
    tables = []
    for skin in ("soft", "hard"):
        mine = [r for r in rs if r.get("skin") == skin and not r.get("axes")]
        if not mine:
            continue
        scores = {id(r): (r.get("nmse_trajectory_by_group") if scenes is None else run_paper_units(r, scenes)) or {}
                  for r in mine}
        prims = [p for p in PRIMITIVES if any(r.get("primitive") == p for r in mine)]
        rows = []
        for score in SCORES:
            for g in OBJECT_GROUPS:
                row: list[Any] = [FACTOR_LABELS.get(score, "Overall"), g]
                for p in prims:
                    vals = [scores[id(r)].get(g, {}).get(score) for r in mine if r.get("primitive") == p]
                    st = seed_stats([np.nan if v is None else v for v in vals])
                    paper = PAPER_TABLE2[(skin, g)][p][SCORES.index(score)]
                    row += [st["mean"], _ci(st), st["n"], paper]
                rows.append(row)
        cols = ["Factor", "group"] + [c for p in prims for c in (f"{p} mean", f"{p} 95% CI", f"{p} n", f"{p} paper")]
        name = modality.upper().replace('_', '-')
        if scenes is None:
            what = ("NMSE per factor and object group, the group's sequences normalised by the run's total variance "
                    "(the paper's convention)")
            paper = "the paper's Table 2 (real e-Skin, real objects, its own budget: a reference, not a target)"
        else:
            what = ("squared error on targets min-max scaled to [0, 1] per factor over the design range (no division "
                    "by the variance), per factor and object group, from the same predictions as the NMSE table")
            paper = "the paper's Table 2 as printed (its \"NMSE\", not defined further)"
        where = "" if scenes is None else ", in the convention of the authors' public code"
        cap = (f"Table 2 analogue, {name} on the {skin} e-Skin{where}: held-out whole-trajectory {what}; mean over "
               f"seeds, 95 % Student t interval (n >= {MIN_SEEDS}, {MISSING} otherwise), n = seeds; paper = {paper}.")
        tables.append(Table(f"table2_{modality}_{skin}" + ("" if scenes is None else "_code_convention"), cap, cols, rows))
    return tables


def table1_with_intervals(runs: Sequence[Mapping], modality: str = "multi_l", skin: str = "soft") -> Table | None:
    """Table 1 analogue: per parameter set (action index 1-16) and primitive, the set's
    parameters and its held-out whole-trajectory and last-frame overall NMSE, 'mean [95 % CI]'
    over the seeds of the cell (each run: its own trials of that set, the run's total
    variance). None when no run of the cell reports its sets."""
    rs = [r for r in _latent_runs(runs, modality) if r.get("skin") == skin and not r.get("axes")
          and r.get("nmse_by_action")]
    prims = [p for p in PRIMITIVES if any(r.get("primitive") == p for r in rs)]
    if not prims:
        return None
    rows = []
    for a in range(N_ACTIONS):
        row: list[Any] = [a + 1]
        for p in prims:
            sets = [r["nmse_by_action"].get(str(a + 1)) for r in rs if r.get("primitive") == p]
            whole = seed_stats([np.nan if v is None else v["trajectory"] for v in sets])
            last = seed_stats([np.nan if v is None else v["last"] for v in sets])
            params = ", ".join(f"{k}={v:g}" for k, v in ACTIONS[p][a].params.items())
            trials = sorted({v["n"] for v in sets if v is not None})
            row += [params, whole["mean"], _ci(whole), last["mean"], _ci(last),
                    f"{whole['n']} x {'/'.join(map(str, trials)) or MISSING}"]
        rows.append(row)
    cols = ["set"] + [c for p in prims for c in (f"{p} parameters", f"{p} whole", f"{p} whole 95% CI", f"{p} last",
                                                   f"{p} last 95% CI", f"{p} seeds x trials")]
    cap = (f"Table 1 analogue, {modality.upper().replace('_', '-')} on the {skin} e-Skin: held-out overall NMSE of each "
           f"parameter set's trials (whole trajectory, last frame; the run's total variance), mean over seeds, 95 % "
           f"Student t interval over seeds (n >= {MIN_SEEDS}, {MISSING} otherwise); seeds x held-out trials of the "
           "set per run.")
    return Table(f"table1_{modality}_{skin}", cap, cols, rows)


def _factor_pairs(tables: Sequence[Table]) -> list[tuple[float, float]]:
    """(ours, paper) of every measured factor cell (not Overall) of Table 2 analogue tables."""
    out = []
    for t in tables:
        for row in t.rows:
            if row[0] == "Overall":
                continue
            for i in range(2, len(row), 4):
                ours, paper = row[i], row[i + 3]
                if isinstance(ours, (int, float)) and np.isfinite(ours) and paper:
                    out.append((float(ours), float(paper)))
    return out


def like_for_like(nmse_tables: Sequence[Table], code_tables: Sequence[Table]) -> str:
    """One sentence: how far the study's factor cells are from the paper's, in both units
    (the paper's Overall is read at the last frame, ours over the trajectory: left out)."""
    a, b = _factor_pairs(nmse_tables), _factor_pairs(code_tables)
    if not a or not b:
        return "Like for like: no factor cell measured in both units."

    def spread(pairs: list[tuple[float, float]]) -> str:
        r = np.array([o / p for o, p in pairs])
        return (f"a median {np.median(r):.2g}x the paper's (range {r.min():.2g}x to {r.max():.2g}x; "
                f"below the paper's in {int(np.sum(r < 1))} of {len(r)})")

    return (f"Like for like: over the {len(a)} factor x object group x e-Skin x primitive cells of MULTI-L measured "
            f"here (the paper's Overall, read at the last frame, left out), the simulated study's whole-trajectory "
            f"error is {spread(a)} if the paper's Table 2 is an NMSE as defined here, and {spread(b)} if it is the "
            "authors' code's squared error on [0, 1]-scaled targets.")


def paper_units_section(nmse_tables: Sequence[Table], code_tables: Sequence[Table], var: np.ndarray,
                        targets: str, source: str) -> list[str]:
    """The section of the code-convention tables: the definition, the variance used, the
    tables and the like-for-like sentence."""
    rng = design_range(targets)
    factors = ", ".join(f"{FACTOR_LABELS.get(k, k)} {v:.4g} / {r:.4g}^2 = {v / r ** 2:.4g}"
                        for k, v, r in zip(FACTOR_NAMES, var, rng))
    out = ["## Table 2 in the convention of the authors' public code", "",
           f"{SCALED_MSE_DEFINITION} The paper's own definition is not stated beyond \"NMSE\": its Table 2 may be "
           "either; the authors' public code for the same model family reports this one.", "",
           f"Converted {source}. The held-out targets' variance per factor is that of the trial split's test "
           f"trials ({targets} targets; the split holds out the same share of every object's trials, so the same "
           f"objects at every seed), and var_k / r_k^2: {factors}.", "",
           like_for_like(nmse_tables, code_tables), ""]
    for t in code_tables:
        out += ["### " + t.name.replace("_", " "), "", t.to_markdown()]
    return out


PAPER_UNITS_HEADING = "## Table 2 in the convention of the authors' public code"


def _parse_cell(v: str) -> Any:
    v = v.strip()
    if v == MISSING:
        return np.nan
    try:
        return int(v) if v.isdigit() else float(v)
    except ValueError:
        return v


def page_table2(text: str) -> list[Table]:
    """The NMSE Table 2 analogue tables (``**table2_<modality>_<skin>.**``) of a results page."""
    tables = []
    for block in re.split(r"\n(?=\*\*table2_)", text)[1:]:
        lines = block.splitlines()
        m = re.match(r"\*\*(table2_[a-z_]+?)\.\*\* (.*)", lines[0])
        if not m or m.group(1).endswith("_code_convention"):
            continue
        start = next(i for i, ln in enumerate(lines) if ln.startswith("|"))
        end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
        rows = lines[start:end]
        cols = [c.strip() for c in rows[0].strip("|").split("|")]
        body = [[_parse_cell(c) for c in r.strip("|").split("|")] for r in rows[2:]]
        tables.append(Table(m.group(1), m.group(2), cols, body))
    return tables


def page_scene(text: str) -> tuple[dict, int, str]:
    """(scene, held-out trials per run, targets) that a results page states: its budget line's
    action indices, its split line's test count and its captions' target encoding."""
    acts = re.search(r"action indices \[([0-9, ]+)\]", text)
    split = re.search(r"held-out test trials per run\): (\d+) / (\d+) in every run", text)
    targets = re.search(r"Targets: (\w+) \(", text)
    if not (acts and split and targets):
        raise StudyReportError("the page names no single budget (action indices), held-out count or targets")
    return ({"actions": [int(a) for a in acts.group(1).split(",")], "repetitions": SceneOptions.repetitions,
             "test_fraction": SplitOptions.test_fraction},
            int(split.group(2)), targets.group(1))


def convert_page_table(t: Table, var: np.ndarray, rng: np.ndarray) -> Table:
    """A page's NMSE Table 2 analogue in the code's convention: each factor row's means and
    interval bounds x var_k / r_k^2 (linear: exact for the mean and the t interval over
    seeds); Overall = the mean of the group's converted factor means (its interval needs
    the per-seed values, which a page does not carry: not given)."""
    c = dict(zip((FACTOR_LABELS.get(k, k) for k in FACTOR_NAMES), var / rng ** 2))
    rows = []
    for row in t.rows:
        new = list(row)
        if row[0] in c:
            for i in range(2, len(row), 4):
                new[i] = row[i] * c[row[0]]
                ci = re.match(r"\[(\S+), (\S+)\]", str(row[i + 1]))
                new[i + 1] = (f"[{fmt_cell(float(ci.group(1)) * c[row[0]], 3)}, {fmt_cell(float(ci.group(2)) * c[row[0]], 3)}]"
                              if ci else MISSING)
        else:  # Overall
            factor_rows = [r for r in rows if r[1] == row[1] and r[0] in c]
            for i in range(2, len(row), 4):
                new[i] = float(np.nanmean([r[i] for r in factor_rows]))
                new[i + 1] = MISSING
                new[i + 2] = min(r[i + 2] for r in factor_rows)
        rows.append(new)
    skin = t.name.rsplit("_", 1)[1]
    cap = (f"Table 2 analogue, MULTI-L on the {skin} e-Skin, in the convention of the authors' public code: the "
           "NMSE table above x var_k / r_k^2 per factor (mean and 95 % interval over seeds scale exactly); Overall = "
           "mean of the converted factors (its interval is not given: the page holds no per-seed values); "
           "paper = the paper's Table 2 as printed (its \"NMSE\", not defined further).")
    return Table(t.name + "_code_convention", cap, t.columns, rows)


def add_paper_units(text: str, page: str = "docs/generated/results.md") -> str:
    """A results page with its Table 2 analogues also in the code's convention (a section
    after them, replacing an earlier one), converted from the page's own NMSE tables with the
    held-out variance of the trial split it states (:func:`page_scene`): for a page whose
    evaluation folder (results.json) is gone; :func:`render` converts run by run."""
    nmse_tables = page_table2(text)
    if not nmse_tables:
        raise StudyReportError(f"{page}: no Table 2 analogue table to convert")
    scene, n_test, targets = page_scene(text)
    var, n = held_out_variance(targets, **scene)
    if n != n_test:
        raise StudyReportError(f"{page}: its trial split holds out {n_test} trials, the rebuilt one {n}")
    code_tables = [convert_page_table(t, var, design_range(targets)) for t in nmse_tables]
    section = paper_units_section(
        nmse_tables, code_tables, var, targets,
        f"from this page's NMSE tables by `embodied-tactile report page=results paper_units={page}` "
        "(the evaluation folder's results.json was not at hand)")
    head, sep, rest = text.partition(PAPER_UNITS_HEADING)
    if sep:  # replace the earlier section: up to the next '## ' heading
        nxt = re.search(r"^## ", rest, flags=re.M)
        rest = rest[nxt.start():] if nxt else ""
    else:  # after the last Table 2 analogue section
        last = [m.start() for m in re.finditer(r"^## table2 ", text, flags=re.M)][-1]
        nxt = re.search(r"^## ", text[last + 3:], flags=re.M)
        cut = last + 3 + nxt.start() if nxt else len(text)
        head, rest = text[:cut], text[cut:]
    return head.rstrip("\n") + "\n\n" + "\n".join(section).rstrip() + "\n\n" + rest.lstrip("\n")


def coverage(runs: Sequence[Mapping]) -> tuple[list[list], list[list]]:
    """(measured, missing): per paper cell (modality, skin, primitive), the seeds of its
    Latent Filter runs; missing = cells with fewer than the protocol's 3 seeds."""
    seeds: dict[tuple, list] = defaultdict(list)
    for r in _latent_runs(runs):
        seeds[(r.get("modality"), r.get("skin"), r.get("primitive"))].append(r.get("seed"))
    measured, missing = [], []
    for m, s in PAPER_COMBOS:
        for p in PRIMITIVES:
            got = sorted(x for x in seeds.get((m, s, p), []) if x is not None)
            row = [m, s, p, len(got), ",".join(str(x) for x in got) or MISSING]
            if got:
                measured.append(row)
            if len(got) < MIN_SEEDS:
                missing.append(row)
    return measured, missing


def _run_files(blob: Mapping) -> list[dict]:
    """Per evaluated run: its folder, config (budget keys), metrics and provenance, as far as they exist."""
    out = []
    for info in blob.get("_evaluation", {}).get("runs", []):
        d = Path(info.get("run_dir", ""))
        entry: dict[str, Any] = {"run_dir": d, "seed": info.get("seed")}
        for key, name in (("metrics", "metrics.json"), ("provenance", "provenance.json")):
            p = d / name
            entry[key] = _read_json(p) if p.exists() else {}
        ov = d / ".hydra" / "overrides.yaml"
        entry["overrides"] = ([ln[2:].strip() for ln in ov.read_text().splitlines() if ln.startswith("- ")]
                              if ov.exists() else None)
        cfg = d / "config_resolved.yaml"
        if cfg.exists():
            from omegaconf import OmegaConf

            entry["config"] = OmegaConf.to_container(OmegaConf.load(cfg), resolve=False)
        out.append(entry)
    return out


def _budget_lines(files: Sequence[Mapping], blob: Mapping) -> list[str]:
    lines = []
    cfgs = [f["config"] for f in files if f.get("config")]
    if cfgs:
        budgets = sorted({(c.get("trainer", {}).get("max_epochs"), c.get("data", {}).get("batch_size"),
                           str(c.get("data", {}).get("actions")), c.get("data", {}).get("train_window"),
                           c.get("data", {}).get("windows_per_trial"), c.get("data", {}).get("windows_per_epoch"),
                           c.get("data", {}).get("split"))
                          for c in cfgs}, key=str)
        for ep, bs, acts, win, wpt, wpe, split in budgets:
            sets = "all 16 parameter sets" if acts == "None" else f"action indices {acts}"
            windows = (f"{wpt} windows of {win} frames per training trial and epoch" if wpt is not None
                       else f"{wpe} windows of {win} frames per epoch" if wpe is not None
                       else f"whole trials")
            lines.append(f"- Budget: {ep} epochs, batch {bs}, {sets}, {windows}, split `{split}`"
                         + (" (every run)." if len(budgets) == 1 else "."))
    sizes = sorted({(r.get("n_train"), r.get("n_test")) for r in _latent_runs(blob["runs"])}, key=str)
    if sizes:
        lines.append("- Split (training / held-out test trials per run): "
                     + ", ".join(f"{a} / {b}" for a, b in sizes) + (" in every run." if len(sizes) == 1 else "."))
    train = [f["metrics"].get("train_wall_s") for f in files if f["metrics"].get("train_wall_s") is not None]
    prep = [f["metrics"].get("data_prepare_s") for f in files if f["metrics"].get("data_prepare_s") is not None]
    if train:
        lines.append(f"- Wall time: training {sum(train) / 3600:.2f} h summed over {len(train)} runs "
                     f"(per run {np.min(train):.0f} to {np.max(train):.0f} s, median {np.median(train):.0f} s); "
                     f"data preparation {sum(prep):.0f} s summed (simulation and caching, once per skin x primitive).")
    ev = blob.get("_evaluation", {}).get("timings", {})
    if ev:
        lines.append(f"- evaluate.py: {ev.get('evaluate_s', 0) + ev.get('report_s', 0):.0f} s.")
    commits = sorted({str(f["provenance"].get("git_commit") or "")[:12] for f in files} - {""})
    dirty = sum(bool(f["provenance"].get("git_dirty")) for f in files)
    if commits:
        lines.append(f"- Code commit(s) of the runs: {', '.join(commits)}"
                     + (f" ({dirty} run(s) with uncommitted changes: their git.diff is in the run folder)." if dirty else "."))
    return lines


def _portable(override: str) -> str:
    """A ``paths.*`` override with its machine's folder replaced by the key's name
    (``paths.data_dir=<data_dir>``): a page names commands, not where a machine keeps files."""
    key, _, value = override.partition("=")
    return f"{key}=<{key.rsplit('.', 1)[-1]}>" if key.startswith("paths.") and value else override


def _command_lines(files: Sequence[Mapping]) -> list[str]:
    """One `python train.py ...` line per part (runs grouped by their sweep folder, named
    relative to the study folder that holds them), with the overrides the jobs of that part
    share and those that vary listed."""
    parts: dict[str, list[list[str]]] = defaultdict(list)
    for f in files:
        if f.get("overrides") is not None:
            parts[str(Path(f["run_dir"]).parent)].append(f["overrides"])
    import os

    study = Path(os.path.commonpath(list(parts))) if parts else Path()
    if len(parts) == 1:
        study = study.parent
    lines = []
    for part, ovs in sorted(parts.items()):
        ovs = [[_portable(o) for o in ov] for ov in ovs]
        common = [o for o in ovs[0] if all(o in other for other in ovs[1:])]
        varying = sorted({o for ov in ovs for o in ov if o not in common})
        name = Path(part).relative_to(study).as_posix()
        multirun = " -m" if (Path(part) / "multirun.yaml").exists() else ""
        where = f" hydra.sweep.dir=<study>/{name}" if multirun else f" hydra.run.dir=<study>/{name}"
        lines.append(f"- `{name}` ({len(ovs)} jobs): `python train.py{multirun} {' '.join(common)}{where}`"
                     + (f", varying: {', '.join(f'`{v}`' for v in varying)}" if varying else ""))
    return lines


def _json_table(blob: Mapping, name: str) -> Table | None:
    for t in blob.get("tables", []):
        if t.get("name") == name:
            rows = [[MISSING if v is None else v for v in r] for r in t["rows"]]
            return Table(name, t.get("caption", ""), list(t["columns"]), rows)
    return None


def floor_table(blob: Mapping) -> Table | None:
    """Per cell (modality, e-Skin, primitive): the training's final KRR alignment beside the
    same read-out of the untrained network (the step-0 row's ``floor``,
    ``krr_history.jsonl``), whole trajectory and last frame, mean over seeds, and in how
    many seeds the trained filter is below its own floor on both; None when no run has both
    rows."""
    from ..run.summary import krr_history, untrained_floor

    cells: dict[tuple, list[tuple[float, float, float, float]]] = defaultdict(list)
    for f in _run_files(blob):
        cfg = f.get("config") or {}
        rows = krr_history(f["run_dir"])
        first = next((r for r in rows if r.get("initial")), None)
        final = next((r for r in reversed(rows) if r.get("final")), None)
        if not (first and final and cfg):
            continue
        first = untrained_floor(first)
        key = tuple(str((cfg.get(k) or {}).get("name")) for k in ("modality", "skin", "primitive"))
        cells[key].append(tuple(float(r.get(k, np.nan)) for r, k in ((final, "nmse_overall"), (first, "nmse_overall"),
                                                                     (final, "nmse_last_overall"),
                                                                     (first, "nmse_last_overall"))))
    if not cells:
        return None
    rows = []
    for key in sorted(cells):
        v = np.asarray(cells[key])
        below = int(np.sum((v[:, 0] < v[:, 1]) & (v[:, 2] < v[:, 3])))
        rows.append([*key, len(v), *(float(np.mean(v[:, i])) for i in range(4)), f"{below} of {len(v)}"])
    return Table("untrained_floor", "The trained filter beside its own floor: the training's final KRR alignment "
                 "and the same alignment of the untrained network (the step-0 row's floor), overall NMSE on the "
                 "held-out test trials, mean over seeds; 'below floor' counts the seeds in which the trained "
                 "filter is below the untrained one on both read-outs.",
                 ["modality", "skin", "primitive", "n seeds", "trained whole", "untrained whole", "trained last",
                  "untrained last", "below floor"], rows)


def objects_section(blob: Mapping) -> list[str]:
    """'Objects never touched in training': the commands and the per-configuration statistics
    over seeds (evaluate.py's ``aggregate`` table) of an evaluation of held-out-object runs
    (``data.split=object``); every Latent Filter run in it must be an object split with unseen
    held-out objects."""
    bad = sorted({str(r.get("split")) for r in _latent_runs(blob["runs"]) if r.get("split") != "object"
                  or not r.get("unseen_objects")})
    if bad:
        raise StudyReportError(f"{blob.get('_dir')}: the held-out-object section takes object-split runs with "
                               f"unseen held-out objects only; found split kind(s) {bad}")
    return extra_section(blob, "Objects never touched in training (`data.split=object`)",
                         "Whole objects held out (stratified over factor levels); the alignment's hyper-parameters "
                         "chosen on folds grouped by object (alignment.groups=auto); unseen objects get the "
                         "hierarchical prior's population marginal.")


def extra_section(blob: Mapping, title: str, text: str = "") -> list[str]:
    """A section for a further evaluation (an ablation, the held-out objects): its commands,
    budget and per-configuration statistics over seeds (evaluate.py's ``aggregate`` table)."""
    out = [f"## {title}", "", f"Generated from `{blob.get('_dir')}/results.json`. {text}".rstrip(), ""]
    files = _run_files(blob)
    out += _command_lines(files) or ["- (no run folders readable from evaluation.json: commands not listed)"]
    out += _budget_lines(files, blob) + [""]
    agg = _json_table(blob, "aggregate")
    out += [agg.to_markdown()] if agg is not None else ["No aggregate table in that evaluation.", ""]
    return out


def override(key: str, value: Any) -> str:
    """``key=value`` as a shell word of a Hydra command line (a string quoted unless plain)."""
    def text(v: Any) -> str:
        if isinstance(v, (list, tuple)):
            return "[" + ",".join(map(text, v)) + "]"
        if v is None:
            return "null"
        if re.fullmatch(r"[\w/.:@%+-]+", str(v)) and not re.fullmatch(r"[-+0-9.e]+|true|false|null", str(v)):
            return str(v)
        return '"' + str(v).replace('"', '\\"') + '"'
    return shlex.quote(f"{key}={text(value)}")


def results_command(evaluation: str, objects: str | None = None, extras: Sequence[tuple[str, str]] = (),
                    out: str | None = None) -> str:
    """The command that writes a results page (its header names it, :func:`render`)."""
    words = ["embodied-tactile report page=results", override("evaluation", str(evaluation))]
    words += [override("objects", str(objects))] if objects else []
    words += [override("extra", [f"{t}={f}" for t, f in extras])] if extras else []
    return " ".join(words + ([override("out", str(out))] if out else []))


def write_results(evaluation: str, objects: str | None = None, extras: Sequence[tuple[str, str]] = (),
                  notes: Sequence[str] = (), out: str | None = None) -> str:
    """The results page of the evaluation folder ``evaluation`` (with the held-out-object runs
    of ``objects`` and each (title, folder) of ``extras`` as sections, ``notes`` under "What
    was run"), written to ``out`` when given; returns the page. :class:`StudyReportError`
    names a folder that cannot be read."""
    figures = copy_figures(Path(evaluation) / "figures", Path(out).parent / "figures" / "results") if out else []
    text = render(load(evaluation), command=results_command(evaluation, objects, extras, out), notes=notes,
                  objects=load(objects) if objects else None,
                  extras=[(title, load(folder)) for title, folder in extras], out_path=out,
                  figures=[(str(Path("figures") / "results" / f.name), caption) for f, caption in figures])
    if out:
        Path(out).write_text(text)
    return text


def copy_figures(source: Path, target: Path) -> list[tuple[Path, str]]:
    """The :data:`PAGE_FIGURES` of ``source`` (an evaluation's ``figures/``) copied into
    ``target``, which is emptied first (a figure of an earlier evaluation does not linger):
    (copied file, the first sentence of its caption in ``captions.md``)."""
    import shutil

    captions = {}
    if (source / "captions.md").is_file():
        for m in re.finditer(r"^\*\*(.+?)\*\*: (.+?\.)(?: |$)", (source / "captions.md").read_text(), re.M):
            captions[m.group(1)] = m.group(2)
    found = [f for pattern in PAGE_FIGURES for f in sorted(source.glob(pattern))]
    if target.is_dir():
        shutil.rmtree(target)
    if found:
        target.mkdir(parents=True)
    for f in found:
        shutil.copyfile(f, target / f.name)
    return [(target / f.name, captions.get(f.name, "")) for f in found]


def render(blob: Mapping, command: str = "", notes: Sequence[str] = (), objects: Mapping | None = None,
           extras: Sequence[tuple[str, Mapping]] = (), out_path: str | None = "docs/generated/results.md",
           figures: Sequence[tuple[str, str]] = ()) -> str:
    """The results page; its header names ``command`` (default: the command that writes the
    page of ``blob`` alone to ``out_path``; None: printed); ``figures``: (path relative to the
    page, caption) of each figure shown."""
    runs = blob["runs"]
    files = _run_files(blob)
    out = ["# Simulated study: results", "",
           f"Generated by `{command or results_command(blob.get('_dir', '<evaluation folder>'), out=out_path)}` from that folder's "
           "`results.json` (evaluate.py's numbers); not edited by hand. Data: the project's simulator, "
           "not the paper's recordings: these numbers test the pipeline and the simulated physics, they do "
           "not re-measure the paper's robot.", "", "## What was run", ""]
    out += _command_lines(files) or ["- (no run folders readable from evaluation.json: commands not listed)"]
    out += _budget_lines(files, blob)
    out += [f"- Note: {n}" for n in notes]
    out += [f"- {blob.get('nmse_definition', '')}", ""]
    nmse_tables = table2_with_intervals(runs)
    for t in nmse_tables:
        out += ["## " + t.name.replace("_", " "), "", t.to_markdown()]
    scenes = _scene_candidates(files)
    code_tables = table2_with_intervals(runs, scenes=scenes)
    if nmse_tables and _factor_pairs(code_tables):
        r0 = next(r for r in _latent_runs(runs) if run_variance(r, scenes) is not None)
        out += paper_units_section(nmse_tables, code_tables, run_variance(r0, scenes), r0.get("targets") or DEFAULT_TARGETS,
                                   "run by run from each run's NMSE, then averaged over seeds")
    table1 = table1_with_intervals(runs)
    if table1 is not None:
        out += ["## " + table1.name.replace("_", " "), "", table1.to_markdown()]
    agg = _json_table(blob, "aggregate")
    if agg is not None:
        out += ["## Every cell (all methods), statistics over seeds", "", agg.to_markdown()]
    floor = floor_table(blob)
    if floor is not None:
        out += ["## The untrained floor per cell", "", floor.to_markdown()]
    for name, head in (("findings", "The paper's findings and their verdicts"), ("comparisons", "Comparisons")):
        t = _json_table(blob, name)
        out += [f"## {head}", ""]
        out += [t.to_markdown()] if t is not None else [
            "Not measured: no comparison of the findings had runs on both sides in this evaluation.", ""]
    if figures:
        out += ["## Figures", ""]
        for path, caption in figures:
            out += [f"![{Path(path).stem}]({path})", "", f"*{Path(path).name}*: {caption}", ""]
    if objects is not None:
        out += objects_section(objects)
    for title, extra in extras:
        out += extra_section(extra, title)
    measured, missing = coverage(runs)
    out += ["## What was not run", "",
            f"Cells of the paper's 24 (8 modality x e-Skin combinations x 3 primitives) with fewer than "
            f"{MIN_SEEDS} seeds of the Latent Filter ({len(missing)} of {len(PAPER_COMBOS) * len(PRIMITIVES)}):", ""]
    out += [Table("not_run", "modality, e-Skin, primitive, seeds run.", ["modality", "skin", "primitive", "n seeds", "seeds"],
                  missing).to_markdown()] if missing else ["None: every cell has at least 3 seeds.", ""]
    return "\n".join(out).rstrip() + "\n"
