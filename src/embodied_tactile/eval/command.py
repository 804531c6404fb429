"""evaluate.py's command line: the run folder (or checkpoint, multirun, study folder) as a
positional argument, evaluation options as ``key=value`` over ``configs/evaluate.yaml``
(:func:`embodied_tactile.eval.pipeline.evaluate` does the work and is what tests and
notebooks call in-process); evaluate.py's docstring says why argparse and not
``@hydra.main``. Exit status: 0 evaluated, 2 refused (one line: a bad option or path, a run
that cannot be scored, an output folder that cannot be written), 130 / 143 SIGINT / SIGTERM
in any phase (nothing written; :class:`~embodied_tactile.run.runfolder.StopSignals`)."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path
from typing import Sequence


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
    args = ap.parse_args(argv)  # --help ends here, before torch and Lightning are imported
    from embodied_tactile.eval.pipeline import evaluate
    from embodied_tactile.eval.runs import EvaluationError, latest_target
    from embodied_tactile.run import quiet
    from embodied_tactile.run.runfolder import StopSignals

    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    quiet.silence_third_party()
    overrides = list(args.overrides)
    if args.path is not None and "=" in args.path and "/" not in args.path.split("=", 1)[0] \
            and not Path(args.path).exists():  # an option (key=value), not a path
        overrides.insert(0, args.path)
        args.path = None
    log_dirs = [o.split("=", 1)[1] for o in overrides if o.startswith("paths.log_dir=")]
    overrides = [o for o in overrides if not o.startswith("paths.log_dir=")]
    stop, handlers = StopSignals(), {s: signal.getsignal(s) for s in StopSignals.SIGNALS}
    stop.install()  # SIGINT / SIGTERM: StopRequested at once, in every phase
    try:
        if args.path is None:
            args.path = str(latest_target(log_dirs[-1] if log_dirs else None))
        evaluate(args.path, overrides)
    except BaseException as err:  # noqa: BLE001 -- a stop, whatever a library made of it, is the stop
        if stop.received is not None:
            print(f"evaluate.py: stopped by {stop.name}: nothing written (an earlier evaluation in that folder is "
                  "kept as it was)", file=sys.stderr)
            return stop.exit_code()
        if isinstance(err, EvaluationError):
            print(f"evaluate.py: error: {err}", file=sys.stderr)
            return 2
        raise
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
    return 0


__all__ = ["main"]
