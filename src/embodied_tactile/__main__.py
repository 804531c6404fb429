"""``embodied-tactile COMMAND [ARGS...]``: the project's one command (also ``python -m embodied_tactile``).

Each subcommand hands its arguments unchanged to the entry point it names; every one takes
Hydra ``key=value`` overrides over ``configs/`` (evaluate's after the run folders).
``embodied-tactile COMMAND --help`` prints that entry point's own help.
"""

from __future__ import annotations

import os
import runpy
import sys
from pathlib import Path
from typing import Sequence

#: the repository's top-level scripts (train.py, evaluate.py); the package runs from its checkout
REPO = Path(__file__).resolve().parents[2]

#: subcommand -> (top-level script or module run as ``__main__``, one line for ``--help``)
COMMANDS = {
    "train": ("train.py", "train a Latent Filter on one scene, or a sweep with -m (Hydra key=value over configs/train.yaml)"),
    "evaluate": ("evaluate.py", "evaluate trained runs: NMSE of the KRR read-out and the baselines (RUN... key=value)"),
    "simulate": ("embodied_tactile.sim.simulate", "simulate raw e-Skin trials into one HDF5 file (key=value)"),
    "prepare": ("embodied_tactile.data.prepare_cli", "prepare a scene's data: simulate missing trials, build the caches (train's key=value)"),
    "record": ("embodied_tactile.hardware.record", "record e-Skin trials from a serial port (Hydra key=value over configs/record.yaml)"),
    "emulate": ("embodied_tactile.hardware.emulate", "fake e-Skin on a pseudo-terminal, for the recorder (Hydra key=value over configs/emulate.yaml)"),
    "palpate": ("embodied_tactile.active.palpate", "closed-loop active palpation with a trained run (Hydra key=value over configs/palpate.yaml)"),
    "report": ("embodied_tactile.eval.pages", "regenerate the pages under docs/generated/, page=all|results|generalisation|active (Hydra key=value over configs/report.yaml)"),
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: embodied-tactile COMMAND [ARGS...]", "", "commands:"]
    lines += [f"  {name:<{width}}  {line}" for name, (_, line) in COMMANDS.items()]
    lines += ["", "embodied-tactile COMMAND --help prints the command's own options."]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the subcommand ``argv[0]`` with the remaining arguments; exit status 2 for an
    unknown or missing subcommand."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage(), file=sys.stdout if args else sys.stderr)
        return 0 if args else 2
    name, rest = args[0], args[1:]
    if name not in COMMANDS:
        print(f"embodied-tactile: error: unknown command {name!r}\n\n{usage()}", file=sys.stderr)
        return 2
    target = COMMANDS[name][0]
    if target.endswith(".py"):
        script = REPO / target
        if not script.is_file():
            print(f"embodied-tactile: error: {script} not found (the commands run from the project's checkout)",
                  file=sys.stderr)
            return 2
        # the script as `python <script> ARGS`: Hydra names the job and its launchers re-run it from the script
        os.execv(sys.executable, [sys.executable, str(script), *rest])
    sys.argv = [sys.argv[0], *rest]
    runpy.run_module(target, run_name="__main__", alter_sys=True)  # as `python -m <module> ARGS`
    return 0


if __name__ == "__main__":
    sys.exit(main())
