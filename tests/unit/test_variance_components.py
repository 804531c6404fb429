"""experiments/variance_components.py: the runs it plans, how lanes share them, and the seeds
a paired difference needs (no training)."""

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

_spec = importlib.util.spec_from_file_location(
    "variance_components", Path(__file__).parents[2] / "experiments" / "variance_components.py")
vc = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(vc)


def test_each_factor_changes_one_seed_and_the_main_factor_comes_before_the_further_levels():
    runs = vc.plan(["sets16"], 3)
    names = [n for _, n, _ in runs]
    assert names == ["base", "init1", "split1", "data1", "main1", "main2", "init2", "split2", "data2"]
    seeds = {n: {o.split("=")[0]: o.split("=")[1] for o in ov if o.split("=")[0] in
                 ("seed", "data.split_seed", "data.sim_seed")} for _, n, ov in runs}
    assert seeds["base"] == {"seed": "0", "data.split_seed": "0", "data.sim_seed": "0"}
    assert seeds["split2"] == {"seed": "0", "data.split_seed": "2", "data.sim_seed": "0"}
    assert seeds["data1"] == {"seed": "0", "data.split_seed": "0", "data.sim_seed": "1"}
    assert seeds["main2"] == {"seed": "2", "data.split_seed": "2", "data.sim_seed": "0"}
    assert all(o in ov for _, _, ov in runs for o in vc.DESIGNS["sets16"])


@pytest.mark.slow
def test_a_lane_claims_a_run_once_and_a_lane_that_stopped_holds_nothing(tmp_path):
    run = tmp_path / "runs" / "sets4" / "base"
    fd = vc.claim(run)
    assert fd is not None and vc.claim(run) is None  # this lane holds it now
    os.close(fd)  # the run ended
    code = ("import importlib.util, os, sys; s = importlib.util.spec_from_file_location('vc', sys.argv[1]); "
            "m = importlib.util.module_from_spec(s); s.loader.exec_module(m); "
            "from pathlib import Path; assert m.claim(Path(sys.argv[2])) is not None; os._exit(0)")
    lane = subprocess.run([sys.executable, "-c", code, _spec.origin, str(run)], capture_output=True, text=True)
    assert lane.returncode == 0, lane.stderr  # another lane took it, then stopped without letting go
    fd = vc.claim(run)
    assert fd is not None
    os.close(fd)


def test_the_seeds_a_paired_difference_needs_follow_its_spread():
    from embodied_tactile.eval.verdicts import detectable_difference

    n = vc.seeds_for(0.05, 0.03)
    assert detectable_difference(0.05 / np.sqrt(n), n - 1) <= 0.03 < detectable_difference(0.05 / np.sqrt(n - 1), n - 2)
    assert vc.seeds_for(0.005, 0.03) == 3 and vc.seeds_for(0.2, 0.03, n_max=50) is None
    assert vc.seeds_for(0.1, 0.03) > vc.seeds_for(0.05, 0.03)
