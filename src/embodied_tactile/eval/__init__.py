"""Evaluation: NMSE, KRR latent->factor alignment, baselines, tables, figures, callback.

Works on arrays only (no files, no model internals). The recipe for evaluate.py::

    from embodied_tactile.eval import evaluate_latents, evaluate_handcrafted, evaluate_mean, write_report
    res, align = evaluate_latents(train, test, latent="y", modality=..., skin=..., primitive=...)
    write_report([res, ...], out_dir, source="simulated")

See docs/reference/evaluation.md.
"""

from .krr import Alignment, LeakageError, assert_disjoint, final_segment_rows, fit_alignment
from .metrics import NMSE_DEFINITION, NMSEUndefinedWarning, nmse, nmse_over_time, nmse_trajectory, overall
from .results import Results, evaluate_latents, select_latents

__all__ = [
    "Alignment", "LeakageError", "NMSE_DEFINITION", "NMSEUndefinedWarning", "Results", "assert_disjoint",
    "evaluate_latents", "final_segment_rows", "fit_alignment", "nmse", "nmse_over_time", "nmse_trajectory",
    "overall", "select_latents",
    # lazily imported (matplotlib / torch / lightning):
    "evaluate_handcrafted", "evaluate_gru", "evaluate_mean", "GRURegressor", "MeanPredictor",
    "handcrafted_features", "write_report", "KRRAlignmentCallback", "collect_latents",
]

_LAZY = {
    "evaluate_handcrafted": "baselines", "evaluate_gru": "baselines", "evaluate_mean": "baselines",
    "GRURegressor": "baselines", "MeanPredictor": "baselines", "handcrafted_features": "baselines",
    "write_report": "report", "KRRAlignmentCallback": "callback",
    "collect_latents": "callback",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(name)
