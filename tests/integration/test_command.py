"""The one command: ``embodied-tactile --help`` lists every subcommand, and each subcommand's
``--help`` reaches its entry point (a subprocess each, as a user types it)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from embodied_tactile.__main__ import COMMANDS

#: a line of each entry point's own help
OWN_HELP = {"train": "train is powered by Hydra", "evaluate": "usage: evaluate.py", "simulate": "Simulate raw e-Skin trials",
            "prepare": "Prepare a scene's data", "record": "powered by Hydra", "emulate": "faults.disconnect_after_*",
            "palpate": "powered by Hydra", "report": "paper_units: null"}


def command(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "embodied_tactile", *args], capture_output=True, text=True, timeout=180)


def test_help_lists_one_line_per_subcommand():
    res = command("--help")
    assert res.returncode == 0, res.stderr
    listed = [line.split()[0] for line in res.stdout.splitlines() if line.startswith("  ")]
    assert listed == list(COMMANDS) == list(OWN_HELP)


def test_unknown_or_missing_subcommand_exits_2():
    assert command("fly").returncode == 2
    assert command().returncode == 2


@pytest.fixture(scope="module")
def helps() -> dict[str, subprocess.CompletedProcess]:
    """``embodied-tactile NAME --help`` of every subcommand, the subprocesses started at once so
    that they share the cores instead of queueing."""
    procs = {name: subprocess.Popen([sys.executable, "-m", "embodied_tactile", name, "--help"],
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for name in COMMANDS}
    done = {}
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=300)
        done[name] = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    return done


@pytest.mark.slow  # eight interpreters importing torch and Lightning: ~10 s on 2 quiet cores
@pytest.mark.parametrize("name", list(COMMANDS))
def test_subcommand_help(name, helps):
    res = helps[name]
    assert res.returncode == 0, res.stderr[-2000:]
    assert OWN_HELP[name] in res.stdout, res.stdout[:2000]
