"""experiments/study_power.py: the detectable difference of a comparison at more seeds."""

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location("study_power", Path(__file__).parents[2] / "experiments" / "study_power.py")
power = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(power)


def test_only_overall_comparisons_with_a_detectable_difference_are_read(tmp_path):
    table = tmp_path / "table_comparisons.csv"
    table.write_text("# comparisons: a caption\n"
                     "finding,better,worse,score,pairing,n,mean d,95% CI,detectable,paper d,verdict\n"
                     "(a),x,y,overall,paired by seed,3/3,0.1,\"[0.0, 0.2]\",0.06,,inconclusive\n"
                     "(c),x,y,stiffness,paired by seed,3/3,0.1,\"[0.0, 0.2]\",0.02,,inconclusive\n"
                     "(e),x,y,overall,unpaired (Welch),3/4,0.1,\"[0.0, 0.2]\",0.09,,inconclusive\n"
                     "(g),x,y,overall,–,0/3,,,,,not measured\n")
    comps = power.overall_comparisons(table)
    assert comps == [{"pairing": "paired by seed", "n": 3, "detectable": 0.06},
                     {"pairing": "unpaired (Welch)", "n": 3, "detectable": 0.09}]


@pytest.mark.parametrize("pairing", ["paired by seed", "unpaired (Welch)"])
def test_the_detectable_difference_is_the_measured_one_at_its_own_seeds_and_falls_with_more(pairing):
    c = {"pairing": pairing, "n": 3, "detectable": 0.0755}
    assert power.detectable_at(c, 3) == pytest.approx(0.0755)
    at = [power.detectable_at(c, n) for n in (3, 4, 5, 8, 12)]
    assert all(a > b for a, b in zip(at, at[1:]))
    assert at[-1] < 0.0755 / 2  # beyond 1 / sqrt(4): the t quantiles fall too


def test_a_paired_comparison_at_five_seeds_follows_the_t_quantiles():
    from scipy.stats import t

    c = {"pairing": "paired by seed", "n": 3, "detectable": 1.0}
    se3 = 1.0 / (t.ppf(0.975, 2) + t.ppf(0.80, 2))
    assert power.detectable_at(c, 5) == pytest.approx((t.ppf(0.975, 4) + t.ppf(0.80, 4)) * se3 * (3 / 5) ** 0.5)
