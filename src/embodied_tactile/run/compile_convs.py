"""``compile_convs``: torch.compile of the conv encoders / decoders for training steps
(docs/reference/model.md, "Speed and the CPU budget")."""

from __future__ import annotations

import importlib.metadata as md

from omegaconf import DictConfig


def configure_compile(cfg: DictConfig, model) -> int:
    """``cfg.compile_convs`` (default false): :func:`~embodied_tactile.model.networks.compile_convs`
    on the model's conv encoders / decoders (training steps on CPU only). Off by default:
    at the default budget it was measured no faster and its compilation took longer than
    a default run's training (docs/reference/model.md "Speed", ``benchmarks/bench_step_levers.py``).
    Returns the number of networks switched on."""
    if not bool(cfg.get("compile_convs", False)):
        return 0
    from ..model.networks import compile_convs

    return compile_convs(model, True)


__all__ = ["configure_compile"]
