"""Physics and learning apart; a scene imports only what it uses.

The checks run in fresh interpreters so that modules imported by other tests do not hide an
unwanted import. One interpreter checks several modules in turn: after each import the modules
it must not bring are still absent, so each module brought none of them (the imports before it
brought none either), exactly what a fresh interpreter per module shows. The strictest bans go
first; modules whose bans another module's imports may break (h5py) get an interpreter of their own.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

CASES = {
    # module imported -> modules that must stay out of sys.modules
    "embodied_tactile.sim": ["torch", "lightning", "librosa"],
    "embodied_tactile.sim.simulate": ["torch", "lightning", "librosa"],
    "embodied_tactile.data.rawformat": ["torch", "lightning", "librosa"],
    "embodied_tactile.hardware.recorder": ["torch", "lightning", "librosa"],
    "embodied_tactile.data.preprocess": ["torch", "lightning"],
    "embodied_tactile.data.prepare": ["torch", "lightning"],  # the preparation stage: files only
    "embodied_tactile.data.pendulum": ["torch", "lightning", "librosa", "h5py"],  # the pendulum's data: numpy
    "embodied_tactile.run.prepare_cli": ["torch", "lightning"],
    # the recorder's command starts in a fraction of a second (a second recorder on a busy port
    # is refused while the first one records); the typed configs need no torch
    "embodied_tactile.hardware.record": ["torch", "lightning", "librosa"],
    "embodied_tactile.run.config": ["torch", "lightning"],
    # (librosa is not checked here: lightning -> torchmetrics.functional.audio imports it
    # whenever it is installed, which is outside this project's control.)
    "embodied_tactile.model.latent_filter": ["h5py"],
    "embodied_tactile.model.module": ["h5py"],
}


def _interpreters() -> list[list[str]]:
    """The modules of CASES in checking order, one list per interpreter: modules in order of
    decreasing bans, each following the previous one's interpreter while its bans are a
    subset of everything checked absent there."""
    groups: list[list[str]] = []
    for module in sorted(CASES, key=lambda m: (-len(CASES[m]), m)):
        if groups and set(CASES[module]) <= set(CASES[groups[-1][-1]]):
            groups[-1].append(module)
        else:
            groups.append([module])
    return groups


def _check(modules: list[str]) -> subprocess.Popen:
    """A fresh interpreter importing ``modules`` in turn, exit 1 at the first banned import."""
    code = (
        "import sys, importlib\n"
        f"for module, banned in {[(m, CASES[m]) for m in modules]!r}:\n"
        "    importlib.import_module(module)\n"
        "    bad = [m for m in banned if m in sys.modules]\n"
        "    if bad:\n"
        "        print(module, 'imports', bad); sys.exit(1)\n"
    )
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.fixture(scope="module")
def checked() -> dict[str, tuple[int, str]]:
    """Every interpreter's outcome (first module -> (exit status, output)), started at once."""
    procs = {ms[0]: _check(ms) for ms in _interpreters()}
    out = {}
    for first, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=180)
        out[first] = (proc.returncode, f"{stdout.strip()} {stderr[-2000:]}")
    return out


@pytest.mark.slow  # fresh interpreters importing torch and Lightning
@pytest.mark.parametrize("modules", _interpreters(), ids=lambda ms: ms[0])
def test_modules_do_not_import(modules, checked):
    status, output = checked[modules[0]]
    assert status == 0, output


def test_every_case_is_checked():
    assert sorted(m for ms in _interpreters() for m in ms) == sorted(CASES)
