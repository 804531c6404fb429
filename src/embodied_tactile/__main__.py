"""``embodied-tactile COMMAND [ARGS...]``: the project's one command (also ``python -m embodied_tactile``).

Each subcommand calls its entry point's ``main(argv)`` in this process with the remaining
arguments and exits with the status it returns; every one takes Hydra ``key=value`` overrides
over the configs (evaluate's after the run folders). ``embodied-tactile COMMAND --help``
prints that entry point's own help. The configs are the checkout's ``configs/`` or, in an
installed wheel, the copy built into the package (:func:`embodied_tactile.paths.config_dir`).
"""

from __future__ import annotations

import embodied_tactile.run.threadenv  # noqa: F401  OpenMP's spin count before torch loads it

import importlib
import sys
from pathlib import Path
from typing import Sequence

#: subcommand -> (``module:function``, its ``main(argv) -> int``; one line for ``--help``)
COMMANDS = {
    "train": ("embodied_tactile.cli:train_main", "train a Latent Filter on one scene, or a sweep with -m (Hydra key=value over configs/train.yaml)"),
    "evaluate": ("embodied_tactile.eval.command:main", "evaluate trained runs: NMSE of the KRR read-out and the baselines (RUN... key=value)"),
    "simulate": ("embodied_tactile.sim.simulate:main", "simulate raw e-Skin trials into one HDF5 file (key=value)"),
    "prepare": ("embodied_tactile.run.prepare_cli:main", "prepare a scene's data: simulate missing trials, build the caches (train's key=value)"),
    "record": ("embodied_tactile.hardware.record:main", "record e-Skin trials from a serial port (Hydra key=value over configs/record.yaml)"),
    "emulate": ("embodied_tactile.hardware.emulate:main", "fake e-Skin on a pseudo-terminal, for the recorder (Hydra key=value over configs/emulate.yaml)"),
    "palpate": ("embodied_tactile.active.palpate:main", "closed-loop active palpation with a trained run (Hydra key=value over configs/palpate.yaml)"),
    "report": ("embodied_tactile.pages:main", "regenerate the pages under docs/generated/, page=all|results|generalisation|active (Hydra key=value over configs/report.yaml)"),
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: embodied-tactile COMMAND [ARGS...]", "", "commands:"]
    lines += [f"  {name:<{width}}  {line}" for name, (_, line) in COMMANDS.items()]
    lines += ["", "embodied-tactile COMMAND --help prints the command's own options."]
    return "\n".join(lines)


def missing_configs() -> str | None:
    """One line saying what to do when no config folder is found, else None."""
    from embodied_tactile.paths import CONFIG_ENV, config_dir

    if Path(config_dir()).is_dir():
        return None
    return (f"no configs found at {config_dir()}: install from the project's checkout (pip install -e .), "
            f"or set {CONFIG_ENV}=<checkout>/configs")


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the subcommand ``argv[0]`` with the remaining arguments -> its exit status; 2 for
    an unknown or missing subcommand, or when no configs are found."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage(), file=sys.stdout if args else sys.stderr)
        return 0 if args else 2
    name, rest = args[0], args[1:]
    if name not in COMMANDS:
        print(f"embodied-tactile: error: unknown command {name!r}\n\n{usage()}", file=sys.stderr)
        return 2
    problem = missing_configs()
    if problem is not None:
        print(f"embodied-tactile: error: {problem}", file=sys.stderr)
        return 2
    module, _, function = COMMANDS[name][0].partition(":")
    entry = getattr(importlib.import_module(module), function)
    from embodied_tactile.cli import exit_status

    try:
        return entry(rest) or 0
    except SystemExit as exc:  # the Hydra commands end with sys.exit(status)
        return exit_status(exc)


def console() -> None:
    """The ``embodied-tactile`` script: :func:`main` on the command line, then the process's
    end (:func:`embodied_tactile.cli.process_exit`: quick after a stop signal)."""
    from embodied_tactile.cli import process_exit

    process_exit(main())


if __name__ == "__main__":
    console()
