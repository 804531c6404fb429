"""``docs/results.md`` from an evaluated study, generated, never typed by hand.

    python train.py -m sweep=study_min hydra.sweeper.params.seed=0 hydra.sweep.dir=logs/train/study/seed0
    ...                                                              # further parts: seed1, seed2, ...
    python evaluate.py logs/train/study                             # merges the parts -> logs/train/study/evaluation
    python -m embodied_tactile.eval.study_report logs/train/study/evaluation --out docs/results.md

Reads ``results.json`` (written by :func:`~embodied_tactile.eval.report.write_report`) and, when
present, ``evaluation.json`` and each evaluated run's ``config_resolved.yaml`` /
``metrics.json`` / ``provenance.json`` for the budget, the commands and the wall time. Writes:

* what was run: the parts and their commands (each job's Hydra overrides), the budget, the
  wall time (training and data preparation apart), the code commit;
* the Table 2 analogue for MULTI-L: per e-Skin, object group and primitive, the mean over
  seeds with its 95 % t interval beside the paper's value (:data:`~.verdicts.PAPER_TABLE2`);
* the per-cell statistics over seeds for every modality (the ``aggregate`` table);
* the paper's findings with their verdicts and every comparison behind them;
* with ``--objects <evaluation folder>``: the held-out-object runs' statistics over seeds;
  with ``--extra TITLE=<evaluation folder>`` (repeatable): any further evaluation (an ablation);
* what was not run: every cell of the paper's 24 (8 modality x e-Skin combinations x 3
  primitives) with fewer than the protocol's 3 seeds.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..constants import FACTOR_NAMES, OBJECT_GROUPS, PRIMITIVES
from .results import scored_on_validation
from .tables import FACTOR_LABELS, MISSING, Table, fmt_cell, seed_stats
from .verdicts import MIN_SEEDS, PAPER_TABLE2, SCORES, SOFT_SKIN_MODALITIES

#: the paper's 8 modality x e-Skin combinations (configs/combo/); x 3 primitives = its 24 cells
PAPER_COMBOS: tuple[tuple[str, str], ...] = (*((m, "soft") for m in SOFT_SKIN_MODALITIES),
                                             ("fsr_tb", "hard"), ("multi_l", "hard"))
METHOD = "latent_filter"


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


def table2_with_intervals(runs: Sequence[Mapping], modality: str = "multi_l") -> list[Table]:
    """One table per e-Skin: rows factor (and Overall) x object group, columns the primitives;
    a cell is 'mean [95 % CI] (paper p)' over the seeds of that (skin, primitive) cell, the
    group's held-out sequences normalised by the run's total variance (Table 2's convention)."""
    rs = _latent_runs(runs, modality)
    tables = []
    for skin in ("soft", "hard"):
        mine = [r for r in rs if r.get("skin") == skin and not r.get("axes")]
        if not mine:
            continue
        prims = [p for p in PRIMITIVES if any(r.get("primitive") == p for r in mine)]
        rows = []
        for score in SCORES:
            for g in OBJECT_GROUPS:
                row: list[Any] = [FACTOR_LABELS.get(score, "Overall"), g]
                for p in prims:
                    vals = [r.get("nmse_trajectory_by_group", {}).get(g, {}).get(score) for r in mine
                            if r.get("primitive") == p]
                    st = seed_stats([np.nan if v is None else v for v in vals])
                    paper = PAPER_TABLE2[(skin, g)][p][SCORES.index(score)]
                    row += [st["mean"], _ci(st), st["n"], paper]
                rows.append(row)
        cols = ["Factor", "group"] + [c for p in prims for c in (f"{p} mean", f"{p} 95% CI", f"{p} n", f"{p} paper")]
        cap = (f"Table 2 analogue, {modality.upper().replace('_', '-')} on the {skin} e-Skin: held-out "
               "whole-trajectory NMSE per factor and object group, the group's sequences normalised by the "
               "run's total variance (the paper's convention); mean over seeds, 95 % Student t interval "
               f"(n >= {MIN_SEEDS}, {MISSING} otherwise), n = seeds; paper = the paper's Table 2 (real e-Skin, "
               "real objects, its own budget: a reference, not a target).")
        tables.append(Table(f"table2_{modality}_{skin}", cap, cols, rows))
    return tables


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
                           c.get("data", {}).get("windows_per_trial"), c.get("data", {}).get("split"))
                          for c in cfgs}, key=str)
        for ep, bs, acts, win, wpt, split in budgets:
            lines.append(f"- Budget: {ep} epochs, batch {bs}, action indices {acts}, {wpt} windows of {win} frames "
                         f"per training trial and epoch, split `{split}`"
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


def _command_lines(files: Sequence[Mapping]) -> list[str]:
    """One `python train.py ...` line per part (runs grouped by their sweep folder), with the
    overrides the jobs of that part share and those that vary listed."""
    parts: dict[str, list[list[str]]] = defaultdict(list)
    for f in files:
        if f.get("overrides") is not None:
            parts[str(Path(f["run_dir"]).parent)].append(f["overrides"])
    lines = []
    for part, ovs in sorted(parts.items()):
        common = [o for o in ovs[0] if all(o in other for other in ovs[1:])]
        varying = sorted({o for ov in ovs for o in ov if o not in common})
        multirun = " -m" if (Path(part) / "multirun.yaml").exists() else ""
        lines.append(f"- `{part}` ({len(ovs)} jobs): `python train.py{multirun} {' '.join(common)}`"
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
    same read-out of the untrained network (its step-0 check, ``krr_history.jsonl``), whole
    trajectory and last frame, mean over seeds, and in how many seeds the trained filter is
    below its own floor on both; None when no run has both rows."""
    from ..summary import krr_history

    cells: dict[tuple, list[tuple[float, float, float, float]]] = defaultdict(list)
    for f in _run_files(blob):
        cfg = f.get("config") or {}
        rows = krr_history(f["run_dir"])
        first = next((r for r in rows if r.get("initial")), None)
        final = next((r for r in reversed(rows) if r.get("final")), None)
        if not (first and final and cfg):
            continue
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
                 "and the same alignment of the untrained network (the step-0 check), overall NMSE on the "
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


def render(blob: Mapping, source: str = "", notes: Sequence[str] = (), objects: Mapping | None = None,
           extras: Sequence[tuple[str, Mapping]] = (), out_path: str | None = "docs/results.md") -> str:
    """The results page; ``out_path`` is the ``--out`` its header names (None: printed)."""
    runs = blob["runs"]
    files = _run_files(blob)
    out = ["# Simulated study: results", "",
           "Generated by `python -m embodied_tactile.eval.study_report "
           f"{source or blob.get('_dir', '<evaluation folder>')}{f' --out {out_path}' if out_path else ''}` from that folder's "
           "`results.json` (evaluate.py's numbers); not edited by hand. Data: the project's simulator, "
           "not the paper's recordings: these numbers test the pipeline and the simulated physics, they do "
           "not re-measure the paper's robot.", "", "## What was run", ""]
    out += _command_lines(files) or ["- (no run folders readable from evaluation.json: commands not listed)"]
    out += _budget_lines(files, blob)
    out += [f"- Note: {n}" for n in notes]
    out += [f"- {blob.get('nmse_definition', '')}", ""]
    for t in table2_with_intervals(runs):
        out += ["## " + t.name.replace("_", " "), "", t.to_markdown()]
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


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Write the study's results page (Markdown) from evaluate.py's output.")
    ap.add_argument("evaluation", help="the evaluation folder evaluate.py wrote for the study (holds results.json)")
    ap.add_argument("--out", default=None, help="write here (e.g. docs/results.md); default: print")
    ap.add_argument("--objects", default=None,
                    help="an evaluation folder of held-out-object runs (data.split=object): adds their section")
    ap.add_argument("--extra", action="append", default=[], metavar="TITLE=FOLDER",
                    help="a further evaluation folder (e.g. an ablation) as a section titled TITLE; repeatable")
    ap.add_argument("--note", action="append", default=[],
                    help="a line for 'What was run' (e.g. how the parts were run); repeatable")
    args = ap.parse_args(argv)
    try:
        extras = []
        for item in args.extra:
            title, sep, folder = item.rpartition("=")
            if not sep or not title or not folder:
                raise StudyReportError(f"--extra {item!r}: expected TITLE=FOLDER")
            extras.append((title, load(folder)))
        source = " ".join([args.evaluation] + ([f"--objects {args.objects}"] if args.objects else [])
                          + [f"--extra {shlex.quote(e)}" for e in args.extra])
        text = render(load(args.evaluation), source=source, notes=args.note,
                      objects=load(args.objects) if args.objects else None, extras=extras, out_path=args.out)
    except StudyReportError as err:
        print(f"study_report: error: {err}", file=sys.stderr)
        return 2
    if args.out:
        Path(args.out).write_text(text)
        print(f"wrote {args.out}")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
