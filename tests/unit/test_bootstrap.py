"""The test sample's own noise: the bootstrap of the Overall NMSE over held-out objects."""

from __future__ import annotations

import numpy as np
import pytest

from embodied_tactile.eval.metrics import bootstrap_overall, nmse_over_time, nmse_trajectory, overall


def _sample(n_objects: int, per_object: int, noise: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    f = np.repeat(rng.normal(size=(n_objects, 4)), per_object, axis=0)
    pred = f[:, None, :] + noise * rng.normal(size=(len(f), 6, 4))
    return f, pred, np.repeat(np.arange(n_objects), per_object)


def test_a_perfect_reader_has_no_sampling_noise_and_the_draws_repeat_with_the_seed():
    f, _, g = _sample(16, 4, 0.0)
    b = bootstrap_overall(f, np.repeat(f[:, None, :], 5, axis=1), g, n_boot=50)
    assert b.shape == (50, 2) and np.all(b == 0)
    f, p, g = _sample(16, 4, 0.5)
    assert np.array_equal(bootstrap_overall(f, p, g, n_boot=30, seed=3), bootstrap_overall(f, p, g, n_boot=30, seed=3))
    assert not np.array_equal(bootstrap_overall(f, p, g, n_boot=30, seed=3), bootstrap_overall(f, p, g, n_boot=30, seed=4))


@pytest.mark.slow
def test_the_resamples_centre_on_the_full_sets_value_and_narrow_with_more_objects():
    f, p, g = _sample(32, 4, 0.5)
    b = bootstrap_overall(f, p, g, n_boot=400)
    whole, last = overall(nmse_trajectory(f, p)), overall(nmse_over_time(f, p)[-1])
    assert abs(np.median(b[:, 0]) - whole) < 0.03 and abs(np.median(b[:, 1]) - last) < 0.05
    f4, p4, g4 = _sample(128, 4, 0.5)
    assert bootstrap_overall(f4, p4, g4, n_boot=400)[:, 0].std() < 0.7 * b[:, 0].std()


@pytest.mark.slow
def test_objects_as_units_are_wider_than_sequences_when_an_objects_errors_agree():
    rng = np.random.default_rng(1)
    f = np.repeat(rng.normal(size=(24, 4)), 4, axis=0)
    shared = np.repeat(rng.normal(size=(24, 1, 4)), 4, axis=0)  # one error per object, on every touch
    p = f[:, None, :] + 0.6 * shared + 0.05 * rng.normal(size=(len(f), 6, 4))
    by_object = bootstrap_overall(f, p, np.repeat(np.arange(24), 4), n_boot=400)[:, 0].std()
    by_sequence = bootstrap_overall(f, p, np.arange(len(f)), n_boot=400)[:, 0].std()
    assert by_object > 1.4 * by_sequence


def test_the_closing_block_states_the_interval_of_the_final_read_out():
    from embodied_tactile.run.summary import nmse_lines

    row = {"step": 960, "n_test": 128, "nmse_overall": 0.0812, "nmse_last_overall": 0.0481,
           "nmse": {"spatial_frequency": 0.1}, "bootstrap_objects": {"resamples": 1000, "overall_ci95": [0.061, 0.104],
                                                                    "last_overall_ci95": [0.031, 0.069]}}
    lines = nmse_lines(row)
    assert "overall 0.0812" in lines[0]
    assert lines[-1] == ("  95 % interval over resampled test objects (the test sample's own noise; another seed adds "
                         "its own): whole [0.061, 0.104], last frame 0.0481 [0.031, 0.069]")
    assert not any("interval" in ln for ln in nmse_lines({k: v for k, v in row.items() if k != "bootstrap_objects"}))
