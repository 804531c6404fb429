"""Physics and learning apart; a scene imports only what it uses.

Each check runs in a fresh interpreter so that modules imported by other tests do not
hide an unwanted import.
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
    "embodied_tactile.data.prepare_cli": ["torch", "lightning"],
    # the recorder's command starts in a fraction of a second (a second recorder on a busy port
    # is refused while the first one records); the typed configs need no torch
    "embodied_tactile.hardware.record": ["torch", "lightning", "librosa"],
    "embodied_tactile.run.config": ["torch", "lightning"],
    # (librosa is not checked here: lightning -> torchmetrics.functional.audio imports it
    # whenever it is installed, which is outside this project's control.)
    "embodied_tactile.model.latent_filter": ["h5py"],
    "embodied_tactile.model.module": ["h5py"],
}


@pytest.mark.parametrize("module", sorted(CASES))
def test_module_does_not_import(module):
    banned = CASES[module]
    code = (
        f"import sys, importlib; importlib.import_module({module!r}); "
        f"bad = [m for m in {banned!r} if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, f"{module} imports {res.stdout.strip()} {res.stderr[-2000:]}"
