"""eval/records.py: a run's scored results as one portable file (no pickle)."""

import numpy as np
import pytest

from embodied_tactile.eval.records import RecordError, read_fingerprint, read_record, write_record
from embodied_tactile.eval.results import Results


def _scored():
    rng = np.random.default_rng(0)
    res = Results(pred=rng.normal(size=(3, 5, 4)), factors=rng.normal(size=(3, 4)), object_id=np.array([0, 1, 2]),
                  action_index=np.array([4, 5, 6]), modality="acc", skin="soft", primitive="pressing",
                  latents_last=rng.normal(size=(3, 2)).astype(np.float32), seq_id=np.array(["a", "b", "c"]),
                  params={"train_time_s": float("nan"), "n": np.int64(3), "grid": np.array([0.1, 1.0])}, seed=2,
                  axes={"annealing.name": "dvbf"})
    history = [{"step": 0, "nmse": 0.9}, {"step": 10, "nmse": np.float32(0.5), "final": True}]
    info = {"run_dir": "/x/run", "timings": {"total_s": 1.5}, "split": {"kind": "trial", "unseen_objects": False},
            "data_changed": [], "n_test": 3}
    return [res], history, info


def test_a_record_reads_back_what_was_written_and_a_compact_one_its_predictions_to_float16(tmp_path):
    scored = _scored()
    path = write_record(tmp_path / "r.npz", scored, {"code": "abc", "options": "def", "baselines": ["mean"]})
    (results, history, info), fp = read_record(path)
    assert fp == {"code": "abc", "options": "def", "baselines": ["mean"]} == read_fingerprint(path)
    r = results[0]
    assert np.array_equal(r.pred, scored[0][0].pred)  # to the last digit
    small = write_record(tmp_path / "small.npz", _scored(), fp, compact=True)
    pred = read_record(small)[0][0][0].pred
    assert pred.dtype == np.float64 and not np.array_equal(pred, r.pred)
    np.testing.assert_allclose(pred, r.pred, rtol=0, atol=1e-3 * r.pred.std())  # float16 of the standardised values
    assert small.stat().st_size < path.stat().st_size


def test_a_compact_record_keeps_nan_and_constant_factors():
    """NaN (a factor with no ground truth, a frame with no prediction) stays NaN; a constant
    factor (the mean predictor) and an all-NaN one read back as they were."""
    from embodied_tactile.eval.records import _quantized, _unpack

    rng = np.random.default_rng(1)
    value = rng.normal(1e4, 50.0, size=(4, 6, 4))
    value[0, 0, 0], value[:, :, 1], value[:, :, 3] = np.nan, 7.5, np.nan
    arrays: dict = {}
    back = _unpack(_quantized(value, arrays, "p"), arrays)
    assert arrays["p"].dtype == np.float16
    assert np.array_equal(np.isnan(back), np.isnan(value))
    assert np.all(back[:, :, 1] == 7.5)
    np.testing.assert_allclose(back[:, :, [0, 2]], value[:, :, [0, 2]], rtol=0, atol=50.0 * 2e-3)


def test_a_damaged_record_or_another_format_is_named(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(RecordError, match="bad.npz: not a scored record"):
        read_record(bad)
    np.savez(tmp_path / "other.npz", x=np.zeros(2))
    with pytest.raises(RecordError, match="other.npz: not a scored record"):
        read_fingerprint(tmp_path / "other.npz")
