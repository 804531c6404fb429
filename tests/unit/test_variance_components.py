"""experiments/variance_components.py: the runs it plans, how lanes share them, and the seeds
a paired difference needs (no training)."""

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

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


def test_a_lane_claims_a_run_once_and_takes_over_a_dead_lanes_claim(tmp_path):
    run = tmp_path / "runs" / "sets4" / "base"
    assert vc.claim(run) and not vc.claim(run)  # this process holds it now
    mark = run.with_name("base.claimed")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    mark.write_text(dead.stdout.strip())  # a lane that has exited
    assert vc.claim(run) and mark.read_text() == str(os.getpid())


def test_the_seeds_a_paired_difference_needs_follow_its_spread():
    from embodied_tactile.eval.verdicts import detectable_difference

    n = vc.seeds_for(0.05, 0.03)
    assert detectable_difference(0.05 / np.sqrt(n), n - 1) <= 0.03 < detectable_difference(0.05 / np.sqrt(n - 1), n - 2)
    assert vc.seeds_for(0.005, 0.03) == 3 and vc.seeds_for(0.2, 0.03, n_max=50) is None
    assert vc.seeds_for(0.1, 0.03) > vc.seeds_for(0.05, 0.03)
