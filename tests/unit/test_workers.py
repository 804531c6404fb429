"""embodied_tactile.run.workers: a pool worker keeps the memory it frees (no page faults per trial)."""

import subprocess
import sys

import pytest

_FAULTS = """
import resource, sys
from embodied_tactile.run import workers
from embodied_tactile.sim.trial import simulate_trial
held = workers.hold_freed_memory() if sys.argv[1] == "held" else None
simulate_trial(4, "soft", "pressing", 6)  # the first trial: surfaces cached, the heap grows once
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for action in (2, 10):
    simulate_trial(4, "soft", "pressing", action)
print(held, (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 2)
"""


def _faults(mode: str) -> tuple[str, float]:
    out = subprocess.run([sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, check=True).stdout.split()
    return out[0], float(out[1])


def test_a_simulation_worker_keeps_freed_arrays_instead_of_faulting_their_pages_in_again():
    held, with_policy = _faults("held")
    if held != "True":
        pytest.skip("this C library has no mallopt (not glibc)")
    _, default = _faults("default")
    assert default > 2000  # a trial's temporaries mapped afresh: about 6,000-9,000 faults (AMD EPYC, 2026-12-08)
    assert with_policy < default / 20
