"""``--remedy NAME=VALUE`` options of the pendulum benchmarks: parsed to LatentFilter keywords
(docs/reference/model.md, "Options"); ``prior.X`` names go into the ``prior`` mapping."""

from __future__ import annotations

import argparse


def boolean(text: str) -> bool:
    """``true`` / ``false`` (any case) -> bool; anything else is a ValueError."""
    if text.lower() not in ("true", "false"):
        raise ValueError(text)
    return text.lower() == "true"


#: --remedy NAME -> its value type; prior.X -> prior={X: ...}
REMEDIES = {"obs_dropout": float, "y_update": str, "y_start": str, "y_evidence_max": float, "y_evidence_range": float,
            "prior.labels": boolean, "prior.learn_embedding": boolean, "prior.learn_sigma": boolean}


def remedy_kwargs(remedies) -> dict:
    """(NAME, value) pairs -> LatentFilter keywords; ``prior.X`` names go into ``prior``."""
    kwargs: dict = {}
    for name, value in remedies:
        head, _, key = name.partition(".")
        if key:
            kwargs.setdefault(head, {})[key] = value
        else:
            kwargs[name] = value
    return kwargs


def parse_remedy(text: str) -> tuple[str, float | int | str]:
    """``NAME=VALUE`` -> (NAME, typed value); an unknown name or a bad value is an ArgumentTypeError."""
    name, _, value = text.partition("=")
    if name not in REMEDIES or not value:
        raise argparse.ArgumentTypeError(f"--remedy {text!r}: expected NAME=VALUE with NAME in {sorted(REMEDIES)}")
    try:
        return name, REMEDIES[name](value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--remedy {text!r}: {value!r} is not a {REMEDIES[name].__name__}") from None

