"""``write_report``: every table (md / csv / tex), every figure (png) and one JSON with every
number, from a list of :class:`~embodied_tactile.eval.results.Results`."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .figures import (best_worst_action_curves, class_distances, curves_by, physical_factors, plot_distance_matrix,
                      plot_error_vs_runtime, plot_nmse_curves, plot_umap, readable, seed_curves_by, write_captions)
from .metrics import NMSE_DEFINITION, overall
from ..jsonio import to_jsonable
from .results import Results
from .tables import (MISSING, RUNTIME_DEFINITION, caption_note, runtime_points, split_sizes, table_actions,
                     table_aggregate, table_groups, table_heterogeneity, table_runtime, table_summary)
from .verdicts import verdict_tables


def _safe(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", s)


def _title(r: Results) -> str:
    """'MULTI-L, soft skin, pressing' (+ other axes / replicate): a figure title, not a key."""
    extra = "".join(f", {k}={v}" for k, v in sorted(r.axes.items())) + (f" ({r.replicate})" if r.replicate else "")
    return f"{readable(r.method)}, {readable(r.modality)}, {r.skin} skin, {r.primitive}{extra}"


def write_report(
    results: Sequence[Results],
    out_dir,
    *,
    source: str | None = None,
    split_sizes_: Mapping | None = None,
    histories: Mapping[str, Sequence[Mapping]] | None = None,
    method: str = "latent_filter",
    figures: bool = True,
    umap: bool = True,
    distance_mode: str = "pairwise",
    run_states: Mapping[str, Mapping] | None = None,
) -> dict:
    """Write tables, figures and ``results.json`` under ``out_dir``; return {kind: [paths]}.

    ``source``: 'simulated' | 'recorded' (overrides every Results.source when given).
    ``split_sizes_``: extra split bookkeeping stored in the JSON (the per-run n_train / n_test
    are always taken from the Results). ``run_states``: run folder -> the state of its
    training (:func:`~embodied_tactile.eval.runs.run_state`: status, checkpoint). ``histories``: label -> rows of krr_history.jsonl
    (error vs run time figure). ``method``: whose rows go into Tables 1 / 2 (None = all).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results = list(results)
    if source is not None:
        for r in results:
            r.source = source
    written: dict[str, list[str]] = {"tables": [], "figures": [], "json": []}
    main = [r for r in results if method is None or r.method == method] or results
    table_method = method if main is not results else None
    tables = [table_actions(results, method=table_method), table_groups(results, method=table_method),
              table_groups(results, method=table_method, norm="group"),
              table_summary(results), table_aggregate(results), table_heterogeneity(results), table_runtime(results)]
    verdicts = verdict_tables(results, method=method or "latent_filter")
    if any(v not in (MISSING, "not measured") for v in (r[-1] for r in verdicts[1].rows)):
        tables += verdicts  # the paper's findings with verdicts, once any comparison is measured
    for t in tables:
        for ext, text in (("md", t.to_markdown()), ("csv", t.to_csv()), ("tex", t.to_latex())):
            p = out / f"table_{t.name}.{ext}"
            p.write_text(text)
            written["tables"].append(str(p))
    note = caption_note(results)
    curves: dict[str, dict] = {}
    if figures and results:
        figs = out / "figures"
        soft = [r for r in main if r.skin == "soft"] or main
        bands = {"modality": seed_curves_by(soft, "modality"), "skin": seed_curves_by(main, "skin")}
        sets = {
            "modality": curves_by(soft, "modality"),
            "skin": curves_by(main, "skin"),
            "method": curves_by(results, "method"),
            "best_worst_action": best_worst_action_curves(main),
        }
        for name, cv in sets.items():
            if cv:
                by = "best and worst action set per primitive" if name == "best_worst_action" else name
                p = plot_nmse_curves(cv, figs / f"nmse_time_by_{name}.png",  # definitions: figures/captions.md
                                     title=f"Held-out NMSE vs interaction time, by {by}", bands=bands.get(name))
                written["figures"].append(str(p))
                curves[name] = {k: v for k, v in cv.items()}
        for r in main:
            if r.latents_last is None or len(r.latents_last) < 2:
                continue
            tag = _safe(r.label)
            if umap:
                # coloured by the trials' factor levels in physical units (the legend's unit), not by
                # the alignment's target encoding (design_rank would label every level 0 / 1 / 2)
                written["figures"].append(str(plot_umap(r.latents_last, physical_factors(r),
                                                        figs / f"umap_{tag}.png",
                                                        title=f"UMAP of last-step latents: {_title(r)}")))
            cls, dist = class_distances(r.latents_last, r.object_id, mode=distance_mode)
            written["figures"].append(str(plot_distance_matrix(cls, dist, figs / f"distances_{tag}.png",
                                                               title=f"Class distances ({distance_mode}): {_title(r)}")))
            curves.setdefault("distances", {})[r.label] = {"classes": cls, "distance": dist}
        # every method's marker comes from the runtime table's points (one NMSE source: evaluate.py,
        # one time base: RUNTIME_DEFINITION); the training-time KRR checks are drawn as lines
        points = {p["label"]: (p["train_time_s"], p["nmse_overall"]) for p in runtime_points(results)
                  if np.isfinite(p["train_time_s"]) and np.isfinite(p["nmse_overall"])}
        if histories or points:
            written["figures"].append(str(plot_error_vs_runtime(histories or {}, figs / "error_vs_runtime.png",
                                                                title="Held-out NMSE vs training time",
                                                                baselines=points)))
        written["captions"] = [str(write_captions(written["figures"], note, figs / "captions.md",
                                                          distance_mode=distance_mode))]
    blob = {
        "nmse_definition": NMSE_DEFINITION,
        "caption_note": note,
        "split_sizes": split_sizes(results),
        "split_sizes_extra": split_sizes_ or {},
        "sources": sorted({r.source for r in results}),
        "runs": [r.summary() for r in results],
        "curves_per_run": {r.label: r.curve() for r in results},
        "figure_curves": curves,
        "tables": [t.to_json() for t in tables],
        "histories": histories or {},
        "runtime_points": runtime_points(results),
        "runtime_definition": RUNTIME_DEFINITION,
        "run_states": {k: {a: b for a, b in v.items() if a != "line"} for k, v in (run_states or {}).items()},
    }
    p = out / "results.json"
    p.write_text(json.dumps(to_jsonable(blob, nan_to_none=True), indent=1, allow_nan=False))
    written["json"].append(str(p))
    return written


