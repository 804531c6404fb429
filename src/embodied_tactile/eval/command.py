"""evaluate.py's command line: the run folder (or checkpoint, multirun, study folder) as a
positional argument, evaluation options as ``key=value`` over ``configs/evaluate.yaml``
(:func:`embodied_tactile.eval.pipeline.evaluate` does the work and is what tests and
notebooks call in-process); evaluate.py's docstring says why argparse and not
``@hydra.main``."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Sequence

from embodied_tactile.eval.pipeline import evaluate
from embodied_tactile.eval.runs import EvaluationError, latest_target
from embodied_tactile.run import quiet


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="evaluate.py",  # = embodied-tactile evaluate; its errors read "evaluate.py: error: ..." either way
        description="Evaluate a training run folder, a checkpoint file or a multirun folder "
                    "(options: key=value over configs/evaluate.yaml).",
        epilog="e.g. python evaluate.py logs/train/runs/<run> latent=both baselines=[handcrafted,mean] umap=false")
    ap.add_argument("path", nargs="?", default=None,
                    help="run folder | checkpoint (.ckpt) | multirun folder; default: the most recent run or "
                         "multirun under <paths.log_dir>/train (paths.log_dir=... picks another log folder)")
    ap.add_argument("overrides", nargs="*", help="evaluation options, key=value (see configs/evaluate.yaml)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    quiet.silence_third_party()
    overrides = list(args.overrides)
    if args.path is not None and "=" in args.path and "/" not in args.path.split("=", 1)[0] \
            and not Path(args.path).exists():  # an option (key=value), not a path
        overrides.insert(0, args.path)
        args.path = None
    log_dirs = [o.split("=", 1)[1] for o in overrides if o.startswith("paths.log_dir=")]
    overrides = [o for o in overrides if not o.startswith("paths.log_dir=")]
    try:
        if args.path is None:
            args.path = str(latest_target(log_dirs[-1] if log_dirs else None))
        evaluate(args.path, overrides)
    except EvaluationError as err:
        print(f"evaluate.py: error: {err}", file=sys.stderr)
        return 2
    return 0


__all__ = ["main"]
