"""experiments/touches.py: the K-touch posteriors each object's read-out row is built from."""

import importlib.util
from pathlib import Path

import numpy as np
import torch

_spec = importlib.util.spec_from_file_location("touches", Path(__file__).parents[2] / "experiments" / "touches.py")
touches = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(touches)


def _split():
    """Object 7 touched three times, object 9 once; prior N(0, 1) per dimension."""
    y_last = torch.tensor([[1.0, 0.0], [3.0, 0.0], [5.0, 0.0], [-2.0, 4.0]])
    y_var = torch.full((4, 2), 0.5)
    factors = np.array([[0.1, 0.2], [0.1, 0.2], [0.1, 0.2], [0.9, 0.8]])
    return {"object_id": np.array([7, 7, 7, 9]), "y_last": y_last, "y_var_last": y_var, "factors": factors}


def test_k_touches_combine_k_of_each_objects_trials_and_skip_objects_with_fewer():
    prior = (torch.zeros(2), torch.ones(2))
    m1, f1, ids1 = touches.combined(_split(), 1, prior, np.random.default_rng(0))
    assert ids1.tolist() == [7, 9]
    assert m1[1].tolist() == [-2.0, 4.0]  # K = 1: the touch's own posterior (tighter than the prior)
    assert m1[0][0] in (1.0, 3.0, 5.0)
    np.testing.assert_array_equal(f1, [[0.1, 0.2], [0.9, 0.8]])

    m2, _, ids2 = touches.combined(_split(), 2, prior, np.random.default_rng(0))
    assert ids2.tolist() == [7]  # object 9 has one trial: skipped at K = 2
    # two touches of evidence 1/0.5 - 1 = 1 each over the prior's 1: precision 3, mean 2 (m_a + m_b) / 3
    assert m2[0][0] * 1.5 in (4.0, 6.0, 8.0)

    m3, _, _ = touches.combined(_split(), 3, prior, np.random.default_rng(1))
    np.testing.assert_allclose(m3[0], [2 * (1 + 3 + 5) / 4, 0.0])  # every trial: the order does not matter
    empty, _, ids4 = touches.combined(_split(), 4, prior, np.random.default_rng(0))
    assert empty.shape == (0, 0) and ids4.size == 0


def test_the_summary_gives_each_network_its_mean_and_interval_over_runs():
    rows = [{"network": "trained", "K=1": v} for v in (0.5, 0.6, 0.7)] + [{"network": "untrained", "K=1": 0.8}] * 3
    text = touches.summary(rows, [1])
    assert "| trained | 3 | 0.600 [0.352, 0.848] |" in text  # t(0.975, 2) = 4.303, sd 0.1
    assert "| untrained | 3 | 0.800 [0.800, 0.800] |" in text
