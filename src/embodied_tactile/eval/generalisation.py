"""The learning curve of generalisation: held-out-object NMSE against the number of training objects.

    embodied-tactile report page=generalisation 'roots=[<root>,...]' out=docs/generated

``<root>``: folders holding population runs (``experiment=population``, any depth), each
evaluated by ``evaluate.py`` (``<run>/evaluation/results.json``), or a scores file written by
an earlier report (``generalisation_scores.json``): parts run apart merge, a later root's
score replacing an earlier one's for the same method, size and seed. Every method of every run
becomes a point: the Latent Filter of the run's modality and recipe (:func:`recipe`), the same
filter untrained (evaluate.py's ``untrained`` reader: the same architecture and seed at step 0,
the same read-out: the floor) and the baselines evaluate.py scored on the same split
(hand-crafted features + KRR, the supervised conv + GRU, the mean predictor). A baseline scored
by two runs with the same modality, size and seed is counted once. Cells are averaged over
seeds with a 95 % t interval; a cell with one seed has no interval. Scores of different
read-outs (``alignment.readout``) are refused in one page.

Writes ``<out>/generalisation.md``, ``<out>/generalisation_scores.json`` (every score, for the
next merge), ``<out>/figures/generalisation_curve.png`` (log x axis) and
``<out>/figures/generalisation_over_time.png`` (each reader's NMSE over interaction time):
generated, never edited.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from ..constants import FACTOR_NAMES
from ..jsonio import write_json
from ..run.summary import recipe
from .results import scored_on_validation

_BASELINE_NAMES = {"handcrafted_krr": "hand-crafted + KRR", "gru": "supervised conv + GRU", "mean": "mean predictor"}


def _method_label(method: str, modality: str, recipe_: str, params: Mapping[str, Any] | None = None) -> str:
    """The row name of a method; the GRU's says whether its inputs were standardised
    (``params["gru"]["input_standardize"]``, as evaluate.py's results carry it)."""
    if method == "latent_filter":
        return f"Latent Filter {modality} ({recipe_})"
    if method == "untrained":
        return f"Latent Filter {modality} ({recipe_}){UNTRAINED}"
    if method == "mean":
        return "mean predictor"
    if method == "hybrid_krr":
        return f"hand-crafted + y of Latent Filter {modality} ({recipe_}), KRR"
    if method == "gru":
        std = bool(((params or {}).get("gru") or {}).get("input_standardize", False))
        return f"{_BASELINE_NAMES[method]} ({modality}, {'standardised' if std else 'raw'} inputs)"
    return f"{_BASELINE_NAMES.get(method, method)} ({modality})"


UNTRAINED = ", untrained"
#: the read-out of results written before ``alignment.readout`` existed
PAPER_READOUT = "final_segment"


def collect(roots: Iterable[str | Path]) -> list[dict[str, Any]]:
    """One row per (method, labelled training objects, seed, unlabelled training objects):
    ``{method, n_objects, n_unlabelled, seed, trajectory, last_step, run_dir, commit, targets}``
    from every evaluated population run under ``roots``; ``trajectory`` / ``last_step``:
    ``{factor: NMSE, "overall": mean over factors}`` over every frame / at the last frame; a
    later root's row replaces an earlier one's."""
    rows: dict[tuple, dict[str, Any]] = {}
    for root in roots:
        rows.update(_collect_root(Path(root)))
    kinds = {r.get("readout", PAPER_READOUT): r["run_dir"] for r in rows.values()}
    if len(kinds) > 1:
        raise ValueError("the scores mix read-outs (" + ", ".join(f"{k}: {v}" for k, v in sorted(kinds.items()))
                         + "): evaluate every run with one alignment.readout")
    return sorted(rows.values(), key=lambda r: (r["method"], r["n_objects"], r["n_unlabelled"], r["seed"]))


def _key(row: Mapping[str, Any]) -> tuple[str, int, int, int]:
    return row["method"], int(row["n_objects"]), int(row["seed"]), int(row["n_unlabelled"])


def _collect_root(root: Path) -> dict[tuple, dict[str, Any]]:
    """The rows of one root (a folder of runs, or a scores file); within a folder the first
    run's score of a baseline stands for the others scored on the same size and seed."""
    from omegaconf import OmegaConf

    rows: dict[tuple, dict[str, Any]] = {}
    if root.is_file():
        try:
            for r in json.loads(root.read_text()):
                r = {**r, "n_unlabelled": int(r.get("n_unlabelled", 0))}  # files written before the unlabelled axis
                rows[_key(r)] = r
        except (ValueError, TypeError, KeyError) as e:
            raise ValueError(f"{root}: not a scores file written by the generalisation report ({type(e).__name__}: {e})") from None
        return rows
    for res_path in sorted(root.rglob("evaluation/results.json")):
        run_dir = res_path.parent.parent
        cfg_path = run_dir / "config_resolved.yaml"
        if not cfg_path.exists():
            continue
        cfg = OmegaConf.load(cfg_path)
        if cfg.data.get("objects") != "population" or cfg.data.get("split") != "object":
            continue
        prov = run_dir / "provenance.json"
        commit = json.loads(prov.read_text()).get("git_commit", "unknown") if prov.exists() else "unknown"
        n, seed, modality = int(cfg.data.n_objects), int(cfg.seed), str(cfg.modality.name)
        unlabelled = int(cfg.data.get("n_unlabelled_objects") or 0)  # trained on without labels, never read out
        if unlabelled:  # the page's own axis, not a part of the row's name: one row over N
            OmegaConf.update(cfg, "data.n_unlabelled_objects", 0)
        recipe_ = recipe(cfg)
        runs = json.loads(res_path.read_text())["runs"]
        val = scored_on_validation(runs)
        if val:
            raise ValueError(f"{res_path}: {', '.join(val)} scored on the validation side (evaluate.py held_out=val); "
                             "the learning curve reads the test objects only")
        readout = next((((r.get("params") or {}).get("alignment") or {}).get("readout") for r in runs
                        if r["method"] == "latent_filter"), None) or PAPER_READOUT
        for r in runs:
            key = (_method_label(r["method"], modality, recipe_, r.get("params")), n, seed, unlabelled)
            if key not in rows:
                rows[key] = {"method": key[0], "n_objects": n, "n_unlabelled": unlabelled, "seed": seed,
                             "run_dir": str(run_dir),
                             "commit": commit, "targets": r.get("targets"), "readout": readout,
                             "trajectory": {**r["nmse_trajectory"], "overall": float(r["nmse_trajectory_overall"])},
                             "last_step": {**r["nmse_last_step"], "overall": float(r["nmse_last_step_overall"])}}
                if r.get("nmse_curve_overall"):
                    rows[key]["curve"] = [float(v) for v in r["nmse_curve_overall"]]
    return rows


def mean_interval(values: Sequence[float]) -> tuple[float, float, float]:
    """(mean, lower, upper) of a 95 % t interval; NaN bounds for fewer than 2 values."""
    v = np.asarray([x for x in values if math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return math.nan, math.nan, math.nan
    m = float(v.mean())
    if v.size < 2:
        return m, math.nan, math.nan
    from scipy.stats import t

    h = float(t.ppf(0.975, v.size - 1) * v.std(ddof=1) / math.sqrt(v.size))
    return m, m - h, m + h


def aggregate(rows: Sequence[Mapping[str, Any]], score: str = "overall",
              readout: str = "trajectory") -> dict[str, dict[int, dict[str, Any]]]:
    """method -> n_objects -> {mean, lo, hi, seeds} of ``score`` ('overall' or a factor name)
    of ``readout`` ('trajectory' or 'last_step')."""
    cells: dict[str, dict[int, list[tuple[int, float]]]] = {}
    for r in rows:
        v = r[readout][score]
        cells.setdefault(r["method"], {}).setdefault(r["n_objects"], []).append((r["seed"], float(v)))
    out: dict[str, dict[int, dict[str, Any]]] = {}
    for m, by_n in cells.items():
        for n, vals in by_n.items():
            mean, lo, hi = mean_interval([v for _, v in vals])
            out.setdefault(m, {})[n] = {"mean": mean, "lo": lo, "hi": hi, "seeds": sorted(s for s, _ in vals)}
    return out


def _cell(c: Mapping[str, Any] | None) -> str:
    if c is None:
        return "not run"
    s = f"{c['mean']:.3f}"
    if math.isfinite(c["lo"]):
        s += f" [{c['lo']:.3f}, {c['hi']:.3f}]"
    return s + f" ({len(c['seeds'])})"


def table(agg: Mapping[str, Mapping[int, Mapping[str, Any]]], sizes: Sequence[int]) -> list[str]:
    lines = ["| method | " + " | ".join(str(n) for n in sizes) + " |", "|---" * (len(sizes) + 1) + "|"]
    for m in sorted(agg, key=_method_order):
        lines.append(f"| {m} | " + " | ".join(_cell(agg[m].get(n)) for n in sizes) + " |")
    return lines


def _method_order(m: str) -> tuple[int, str]:
    return (0 if m.startswith("Latent Filter") else 2 if m == "mean predictor" else 1, m)


READOUTS = (("trajectory", "whole trajectory"), ("last_step", "last step"))


def over_time(rows: Sequence[Mapping[str, Any]]) -> dict[str, dict[int, dict[str, Any]]]:
    """method -> n_objects -> the NMSE over interaction time (mean over factors) of the rows
    that carry a curve: ``curve`` the mean over seeds per frame; ``first`` (frame 1) and
    ``peak`` (its highest frame) as (mean, lower, upper) over seeds; ``below_half`` per seed
    the first frame (1-based) at or below 0.5, None where none is; ``seeds``."""
    cells: dict[str, dict[int, list[np.ndarray]]] = {}
    for r in rows:
        if r.get("curve"):
            cells.setdefault(r["method"], {}).setdefault(r["n_objects"], []).append(np.asarray(r["curve"], float))
    out: dict[str, dict[int, dict[str, Any]]] = {}
    for m, by_n in cells.items():
        for n, curves in by_n.items():
            stack = np.stack([c[:min(len(c) for c in curves)] for c in curves])
            below = [int(np.flatnonzero(c <= 0.5)[0]) + 1 if (c <= 0.5).any() else None for c in stack]
            out.setdefault(m, {})[n] = {"curve": stack.mean(0), "first": mean_interval(stack[:, 0]),
                                       "peak": mean_interval(stack.max(1)), "below_half": below,
                                       "seeds": len(stack)}
    return out


def _interval(mli: tuple[float, float, float]) -> str:
    m, lo, hi = mli
    return f"{m:.3f}" + (f" [{lo:.3f}, {hi:.3f}]" if math.isfinite(lo) else "")


def time_table(curves: Mapping[str, Mapping[int, Mapping[str, Any]]]) -> list[str]:
    lines = ["| method | training objects | seeds | frame 1 | highest frame | first frame <= 0.5, per seed |",
             "|---|---|---|---|---|---|"]
    for m in sorted(curves, key=_method_order):
        for n in sorted(curves[m]):
            c = curves[m][n]
            below = ", ".join("never" if b is None else str(b) for b in c["below_half"])
            lines.append(f"| {m} | {n} | {c['seeds']} | {_interval(c['first'])} | {_interval(c['peak'])} | {below} |")
    return lines


def _style(m: str) -> str:
    return "--" if m == "mean predictor" else ":" if m.endswith(UNTRAINED) else "-"


def time_figure(curves: Mapping[str, Mapping[int, Mapping[str, Any]]], path: Path) -> None:
    """Each reader's NMSE over interaction time (mean over seeds), one panel per size, one
    colour per reader across panels, the legend below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = sorted(curves, key=_method_order)
    colour = {m: f"C{i % 10}" for i, m in enumerate(methods)}
    sizes = sorted({n for by_n in curves.values() for n in by_n})
    fig, axes = plt.subplots(1, len(sizes), figsize=(4.6 * len(sizes), 4.0 + 0.22 * len(methods)), sharey=True,
                             squeeze=False)
    for ax, n in zip(axes[0], sizes):
        for m in methods:
            if n in curves[m]:
                c = curves[m][n]["curve"]
                ax.plot(np.arange(1, len(c) + 1), c, _style(m), lw=1.2, color=colour[m], label=m)
        ax.axhline(1.0, color="0.6", lw=0.8)
        ax.set_title(f"{n} training objects", fontsize=9)
        ax.set_xlabel("frame (interaction time)")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("NMSE, held-out objects (mean over factors)")
    handles = [plt.Line2D([], [], linestyle=_style(m), color=colour[m]) for m in methods]
    fig.legend(handles, methods, loc="lower center", fontsize=6, ncol=1, frameon=False)
    fig.tight_layout(rect=(0, 0.05 * len(methods) / 2, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def figure(rows: Sequence[Mapping[str, Any]], path: Path, sizes: Sequence[int]) -> None:
    """Mean over factors against training objects (log x), one panel per read-out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter, NullFormatter

    fig, axes = plt.subplots(1, len(READOUTS), figsize=(11.0, 4.4), sharey=True)
    for ax, (readout, title) in zip(axes, READOUTS):
        agg = aggregate(rows, readout=readout)
        for m in sorted(agg, key=_method_order):
            ns = sorted(agg[m])
            mean = np.array([agg[m][n]["mean"] for n in ns])
            lo = np.array([agg[m][n]["lo"] for n in ns])
            hi = np.array([agg[m][n]["hi"] for n in ns])
            line, = ax.plot(ns, mean, _style(m), marker="o", label=m)
            ok = np.isfinite(lo)
            if ok.any():
                ax.fill_between(np.array(ns)[ok], lo[ok], hi[ok], color=line.get_color(), alpha=0.15)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(list(sizes))
        ax.set_yticks([0.1, 0.2, 0.3, 0.5, 0.7, 1.0, 2.0, 5.0])
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_major_formatter(FormatStrFormatter("%g"))
            axis.set_minor_formatter(NullFormatter())
        ax.set_title(f"held-out objects, {title}", fontsize=9)
        ax.set_xlabel("training objects")
        ax.axhline(1.0, color="0.6", lw=0.8)
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("NMSE (mean over factors, log scale)")
    axes[-1].legend(fontsize=6)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _readout_sentence(rows: Sequence[Mapping[str, Any]]) -> str:
    kind = next((r.get("readout", PAPER_READOUT) for r in rows), PAPER_READOUT)
    if kind == "per_time":
        return ("Read-out (`alignment.readout=per_time`, docs/reference/evaluation.md): one probe per span of "
                "interaction time, fitted on the training objects' frames of that span, its hyper-parameters "
                "cross-validated by object on every frame of the span.")
    return ("Read-out (`alignment.readout=final_segment`, the paper's protocol, docs/reference/evaluation.md): one "
            "alignment fitted on the final tenth of every training trial, applied to every frame.")


def write_page(rows: Sequence[Mapping[str, Any]], out: str | Path, *, command: str,
               sizes: Sequence[int] = (24, 64, 128, 256, 512)) -> Path:
    """docs page + figure from ``collect`` rows. Returns the page's path."""
    out = Path(out)
    every, rows = rows, [r for r in rows if not r["n_unlabelled"]]
    figure(rows, out / "figures" / "generalisation_curve.png", sizes)
    commits = sorted({r["commit"][:7] if len(r["commit"]) == 40 else r["commit"] for r in rows})
    lines = [
        "# Generalisation to objects never touched",
        "",
        f"Generated by `{command}` on {_dt.date.today().isoformat()} from {len(rows)} scores "
        f"(runs at commit(s) {', '.join(commits) or 'none'}). Do not edit: regenerate.",
        "",
        "Held-out-object NMSE (0 = perfect, 1 = the training mean) of the population "
        "scene (`experiment=population`: soft e-Skin, pressing at 4 and 8 mm, 0.6 Hz; docs/reference/simulator.md, "
        "\"Object population\") against the number of training objects. Every size is scored on the same "
        "64 test objects and picks checkpoints on the same 32 validation objects; the population and "
        "the simulated noise are those of population_seed 0 and sim_seed 0, the seeds vary the model's "
        "initialisation and training windows. Targets: physical units (1/m, mm, log10 Pa, 0/1), "
        "standardised by the alignment. " + _readout_sentence(rows) + " Two numbers per reader: over the "
        "whole trajectory (every frame, the project's main NMSE; frames before the first contact count) and "
        "at the last frame (the estimate after the whole trial); the curve between them is in \"Over "
        "interaction time\". Each cell: mean over seeds [95 % t interval] (number of seeds); 'not run' cells "
        "were not run. The baselines train on the same training split at the Latent Filter's optimiser-step "
        "budget (480 steps of 16 windows). 'untrained' rows: the same filter at step 0 (its random "
        "initialisation, the run's seed), read by the same read-out: the floor a trained filter's read-out is "
        "to be compared with.",
        "",
        "What the signals allow on the same population (a kernel reader on physical summary features): "
        "docs/experiments/signal_content.md. The paper's 32 objects under the object split: "
        "docs/experiments/archive/study_held_out_objects.md. The runs: `python train.py experiment=population "
        "data.n_objects=N seed=S threads=1` (or the sweep, configs/sweep/generalisation.yaml), then `python "
        "evaluate.py <run> baselines=[handcrafted,untrained,mean]` per run (`gru` adds the supervised conv + "
        "GRU: `gru.epochs=16 gru.max_batches_per_epoch=30`). The GRU at other budgets: "
        "docs/experiments/population_readers.md.",
        "",
        "![learning curve](figures/generalisation_curve.png)",
        "",
    ]
    for readout, title in READOUTS:
        lines += [f"## Mean over factors, {title}", "", *table(aggregate(rows, readout=readout), sizes), ""]
    lines += unlabelled_section(every)
    curves = over_time(rows)
    if curves:
        time_figure(curves, out / "figures" / "generalisation_over_time.png")
        lines += ["## Over interaction time", "",
                  "NMSE (mean over factors) frame by frame, each reader with its own read-out over the whole "
                  "trial. Frame 1 is one observation, taken at the press's deepest point (docs/reference/simulator.md, "
                  "\"Primitives\"): a reader that takes no evidence from it reads 1 there.",
                  "", "![over interaction time](figures/generalisation_over_time.png)", "", *time_table(curves), ""]
    for f in FACTOR_NAMES:
        for readout, title in READOUTS:
            lines += [f"## {f}, {title}", "", *table(aggregate(rows, f, readout), sizes), ""]
    head = " | ".join(FACTOR_NAMES)
    lines += ["## Scores (whole trajectory; last step)", "",
              f"| method | training objects | unlabelled | seed | overall | {head} | overall (last) | {head} (last) |",
              "|---" * (5 + 2 * len(FACTOR_NAMES) + 1) + "|"]
    for r in every:
        cells = [f"{r[ro][k]:.3f}" for ro in ("trajectory", "last_step") for k in ("overall", *FACTOR_NAMES)]
        lines.append(f"| {r['method']} | {r['n_objects']} | {r['n_unlabelled']} | {r['seed']} | " + " | ".join(cells) + " |")
    page = out / "generalisation.md"
    page.write_text("\n".join(lines) + "\n")
    write_json(out / "generalisation_scores.json", list(every), indent=1)
    return page


def unlabelled_section(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The curve over unlabelled objects: for each labelled count that runs with unlabelled
    objects were trained at, every reader against N = labelled + unlabelled training objects
    (the read-out fitted on the labelled ones at every N); no lines when there are none."""
    lines: list[str] = []
    for labelled in sorted({r["n_objects"] for r in rows if r["n_unlabelled"]}):
        at = [{**r, "n_objects": labelled + r["n_unlabelled"]} for r in rows if r["n_objects"] == labelled]
        sizes = sorted({r["n_objects"] for r in at})
        lines += [f"## Unlabelled objects: {labelled} labelled, N training objects in all", "",
                  f"The filter trained on N objects, the {labelled} labelled ones and N - {labelled} more that carry "
                  f"no labels (`data.n_unlabelled_objects`); every reader's read-out is fitted on the {labelled} "
                  "labelled training objects and scored on the same test objects at every N. The hand-crafted "
                  "reader and the mean predictor see no unlabelled object: their values at each N are scored "
                  "again in that N's evaluation, and stay the same.", ""]
        for readout, title in READOUTS:
            lines += [f"### Mean over factors, {title}", "", *table(aggregate(at, readout=readout), sizes), ""]
    return lines
