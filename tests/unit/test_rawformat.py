"""The raw trial format: round trip, and every validation error names file, trial and field."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest

from embodied_tactile import constants as C
from embodied_tactile.data import rawformat as rf


def make_trial(object_id=3, action_index=5, repetition=0, n=700, m=100, seed=0) -> rf.RawTrial:
    rng = np.random.default_rng(seed)
    attrs = rf.make_attrs(
        object_id=object_id, skin="soft", primitive="sliding", action_index=action_index,
        repetition=repetition, source="simulated", seed=seed,
    )
    acc = rng.normal(0, 0.01, (n, 4, 4, 3)).astype(np.float32)
    acc[..., 2] += 1.0
    return rf.RawTrial(
        t=np.arange(n) / C.FS_TACTILE,
        acc=acc,
        fsr=rng.integers(0, 4096, (n, 2, 16, 16)).astype(np.uint16),
        pose_t=np.arange(m) / C.FS_POSE,
        pose=rng.normal(0, 1e-3, (m, 6)).astype(np.float32),
        attrs=attrs,
    )


@pytest.fixture()
def three_trials(tmp_path):
    path = tmp_path / "raw.h5"
    trials = [make_trial(object_id=k, seed=k) for k in (0, 1, 2)]
    for tr in trials:
        rf.write_trial(path, tr)
    return path, trials


def test_round_trip(three_trials):
    path, trials = three_trials
    good, errors = rf.scan_raw(path)
    assert errors == [] and len(good) == 3
    for tr in trials:
        back = rf.read_trial(path, tr.name)
        for fld in ("t", "acc", "fsr", "pose_t", "pose"):
            np.testing.assert_array_equal(getattr(back, fld), getattr(tr, fld))
            assert getattr(back, fld).dtype == getattr(tr, fld).dtype
        assert back.attrs["object_id"] == tr.attrs["object_id"]
        assert back.attrs["skin"] == "soft" and back.attrs["source"] == "simulated"
        np.testing.assert_array_equal(back.attrs["action_params"], C.ACTIONS["sliding"][5].as_array())
        assert json.loads(back.attrs["action_param_names"]) == list(C.ACTION_PARAM_NAMES["sliding"])
        np.testing.assert_array_equal(back.factors, C.OBJECTS[tr.attrs["object_id"]].factors())
    with h5py.File(path) as f:
        assert f.attrs["format"] == rf.FORMAT_NAME


def test_read_only_requested_fields(three_trials):
    path, trials = three_trials
    back = rf.read_trial(path, trials[0].name, fields=["acc"])
    assert back.acc.shape == (700, 4, 4, 3) and back.fsr.size == 0 and back.pose.size == 0
    assert back.t.shape == (700,)  # the tactile clock comes with acc


def _corrupt(path, name, fn):
    with h5py.File(path, "a") as f:
        fn(f["trials"][name])


CORRUPTIONS = {
    "nan": (lambda g: g["tactile/acc"].__setitem__((5, 0, 0, 0), np.nan), "tactile/acc", "non-finite"),
    "wrong_shape": (
        lambda g: (g.__delitem__("tactile/fsr"), g.create_dataset("tactile/fsr", data=np.zeros((700, 2, 16, 15), np.uint16))),
        "tactile/fsr",
        "shape",
    ),
    "missing_attr": (lambda g: g.attrs.__delitem__("primitive"), "attrs/primitive", "missing"),
    "non_monotonic": (lambda g: g["tactile/t"].__setitem__(10, 0.0), "tactile/t", "strictly increasing"),
    "truncated_dataset": (
        lambda g: (g.__delitem__("tactile/acc"), g.create_dataset("tactile/acc", data=np.zeros((500, 4, 4, 3), np.float32))),
        "tactile/acc",
        "truncated",
    ),
    "missing_dataset": (lambda g: g.__delitem__("pose/ee"), "pose/ee", "missing"),
    "wrong_dtype": (
        lambda g: (g.__delitem__("tactile/fsr"), g.create_dataset("tactile/fsr", data=np.zeros((700, 2, 16, 16), np.int32))),
        "tactile/fsr",
        "dtype",
    ),
    "bad_primitive": (lambda g: g.attrs.__setitem__("primitive", "poking"), "attrs/primitive", "must be one of"),
    "out_of_range_fsr": (lambda g: g["tactile/fsr"].__setitem__((0, 0, 0, 0), 5000), "tactile/fsr", "12-bit"),
    "lost_at_out_of_range": (lambda g: g.create_dataset("tactile/lost_at", data=np.array([3, 701])), "tactile/lost_at", "outside 0..700"),
    "lost_at_decreasing": (lambda g: g.create_dataset("tactile/lost_at", data=np.array([5, 3])), "tactile/lost_at", "decrease"),
    "lost_at_dtype": (lambda g: g.create_dataset("tactile/lost_at", data=np.array([1.0, 2.0])), "tactile/lost_at", "dtype"),
    "lost_at_shape": (lambda g: g.create_dataset("tactile/lost_at", data=np.zeros((2, 1), np.int64)), "tactile/lost_at", "shape"),
    # a declared rate that disagrees with the timestamps, each direction
    "rate_data_slower": (lambda g: g["tactile/t"].__setitem__(slice(None), np.arange(700) / 350.0), "tactile/t", "show 350 Hz"),
    "rate_declared_higher": (lambda g: g.attrs.__setitem__("fs_tactile", 1400.0), "tactile/t", "declares 1400 Hz"),
    "rate_declared_lower": (lambda g: g.attrs.__setitem__("fs_tactile", 350.0), "tactile/t", "declares 350 Hz"),
    "pose_rate_declared_lower": (lambda g: g.attrs.__setitem__("fs_pose", 50.0), "pose/t", "attrs/fs_pose declares 50 Hz"),
    # continuity: a clock jumping forward with no lost packet recorded; a pose log with a hole
    "gap_without_lost_packet": (lambda g: g["tactile/t"].__setitem__(slice(400, None), g["tactile/t"][400:] + 1.0),
                                "tactile/t", "1 gap(s) longer than 0.5 s; the first 1 s before sample 400"),
    "pose_log_gap": (lambda g: g["pose/t"].__setitem__(slice(50, None), g["pose/t"][50:] + 0.6),
                     "pose/t", "1 gap(s) longer than 0.5 s; the first 0.61 s before sample 50"),
    # physical attributes outside their documented ranges (NaN, "unknown", is allowed)
    "amplitude_huge": (lambda g: g.attrs.__setitem__("amplitude", 1e9), "attrs/amplitude", "outside the documented range [0, 100]"),
    "spatial_frequency_inf": (lambda g: g.attrs.__setitem__("spatial_frequency", np.inf), "attrs/spatial_frequency", "outside the documented range"),
    "heterogeneity_half": (lambda g: g.attrs.__setitem__("heterogeneity", 0.5), "attrs/heterogeneity", "must be 0 or 1"),
    "object_id_negative": (lambda g: g.attrs.__setitem__("object_id", -5), "attrs/object_id", "must be >= 0, got -5"),
    "stiffness_negative": (lambda g: g.attrs.__setitem__("stiffness", -1.0), "attrs/stiffness", "outside the documented range [2, 11]"),
    "fs_tactile_inf": (lambda g: g.attrs.__setitem__("fs_tactile", np.inf), "attrs/fs_tactile", "must be finite"),
}


@pytest.mark.parametrize("kind", sorted(CORRUPTIONS))
def test_validation_error_names_file_trial_field_and_others_load(three_trials, kind, caplog):
    path, trials = three_trials
    fn, field, words = CORRUPTIONS[kind]
    bad = trials[1].name
    _corrupt(path, bad, fn)
    good, errors = rf.scan_raw(path)
    assert sorted(i.name for i in good) == sorted([trials[0].name, trials[2].name])
    assert len(errors) == 1
    err = errors[0]
    assert (err.file, err.trial, err.field) == (str(path), bad, field)
    msg = str(err)
    assert str(path) in msg and bad in msg and field in msg and words in msg
    assert bad in caplog.text  # reported, not silent
    with pytest.raises(rf.TrialFormatError, match=field.replace("/", "/")):
        rf.scan_raw(path, strict=True)


def test_rate_check_tolerates_jitter_and_losses(tmp_path):
    tr = make_trial()
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.5, 1.5, 700)) / C.FS_TACTILE  # +-50 % jitter around the declared step
    t[300:] += 0.05  # 35 lost packets in one gap
    tr.t = t
    tr.attrs["fs_tactile"] = C.FS_TACTILE / (1 + 0.75 * rf.RATE_TOLERANCE)  # a board a little off
    rf.write_trial(tmp_path / "ok.h5", tr)
    good, errors = rf.scan_raw(tmp_path / "ok.h5")
    assert [g.name for g in good] == [tr.name] and not errors
    tr.attrs["fs_tactile"] = C.FS_TACTILE / 2  # twice the steps: beyond the widened quartiles
    with pytest.raises(rf.TrialFormatError, match="tactile/t.*fs_tactile declares"):
        rf.write_trial(tmp_path / "off.h5", tr)


def test_modality_subset_validation_ignores_other_fields(three_trials):
    """An acc-only reader validates (and opens) only acc: a corrupt FSR does not exclude the trial."""
    path, trials = three_trials
    _corrupt(path, trials[1].name, lambda g: g["tactile/fsr"].__setitem__((0, 0, 0, 0), 5000))
    good, errors = rf.scan_raw(path, fields=["acc"])
    assert len(good) == 3 and errors == []


def test_truncated_file_is_reported_and_other_files_load(three_trials, tmp_path):
    path, trials = three_trials
    other = tmp_path / "other.h5"
    shutil.copy(path, other)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])
    good, errors = rf.scan_raw([path, other])
    assert len(good) == 3 and all(i.file == str(other) for i in good)
    assert len(errors) >= 1 and errors[0].file == str(path)
    assert str(path) in str(errors[0])


def test_write_refuses_invalid_trial(tmp_path):
    tr = make_trial()
    tr.acc[0, 0, 0, 0] = np.inf
    with pytest.raises(rf.TrialFormatError, match="tactile/acc"):
        rf.write_trial(tmp_path / "x.h5", tr)
    assert not (tmp_path / "x.h5").exists() or rf.scan_raw(tmp_path / "x.h5")[0] == []


def test_incremental_writer_interrupted_stays_readable(tmp_path):
    path = tmp_path / "rec.h5"
    tr = make_trial()
    attrs = dict(tr.attrs, source="recorded")
    w = rf.IncrementalTrialWriter(path, attrs)
    for k in range(0, 350, 50):
        w.append("t", tr.t[k : k + 50])
        w.append("acc", tr.acc[k : k + 50])
        w.append("fsr", tr.fsr[k : k + 50])
    w.append("pose_t", tr.pose_t[:50])
    w.append("pose", tr.pose[:50])
    w.flush()
    # Simulate a crash: the handle is never closed; a reader opens the file meanwhile.
    good, errors = rf.scan_raw(path)
    assert errors == [] and len(good) == 1
    assert good[0].attrs["complete"] is False or good[0].attrs["complete"] == 0
    back = rf.read_trial(path, good[0].name)
    assert back.acc.shape[0] == 350
    np.testing.assert_array_equal(back.fsr, tr.fsr[:350])
    w.close(complete=True)
    assert rf.scan_raw(path)[0][0].attrs["complete"]


def test_format_error_pickles():
    import pickle

    err = rf.TrialFormatError("f.h5", "obj00", "tactile/acc", "bad")
    back = pickle.loads(pickle.dumps(err))
    assert (back.file, back.trial, back.field, back.problem) == ("f.h5", "obj00", "tactile/acc", "bad")
    assert str(back) == str(err)


def test_lost_packet_positions_round_trip_and_are_optional(tmp_path):
    """``tactile/lost_at``: where each lost packet was (the index of the sample after the gap);
    written incrementally, validated on read, absent in files written before it existed."""
    path = tmp_path / "rec.h5"
    tr = make_trial()
    w = rf.IncrementalTrialWriter(path, dict(tr.attrs, source="recorded"))
    w.append("t", tr.t[:300])
    w.append("acc", tr.acc[:300])
    w.append("fsr", tr.fsr[:300])
    w.append("lost_at", np.array([0, 120, 120]))
    w.append("pose_t", tr.pose_t)
    w.append("pose", tr.pose)
    w.flush()
    back = rf.read_trial(path, w.name)  # mid-recording
    np.testing.assert_array_equal(back.lost_at, [0, 120, 120])
    w.append("t", tr.t[300:])
    w.append("acc", tr.acc[300:])
    w.append("fsr", tr.fsr[300:])
    w.append("lost_at", np.array([700]))  # lost after the last sample
    w.close(complete=True)
    back = rf.read_trial(path, w.name)
    assert back.lost_at.dtype == np.int64 and back.baseline_lost_at is None
    np.testing.assert_array_equal(back.lost_at, [0, 120, 120, 700])
    with h5py.File(path) as f:
        assert "baseline" not in f["trials"][w.name]  # no baseline recorded: none written
    # write_trial / validate_arrays take it too, and refuse a bad one
    copy = rf.RawTrial(**{**back.__dict__, "group": None})
    rf.write_trial(tmp_path / "copy.h5", copy)
    np.testing.assert_array_equal(rf.read_trial(tmp_path / "copy.h5", copy.name).lost_at, back.lost_at)
    copy.lost_at = np.array([800])
    with pytest.raises(rf.TrialFormatError, match="tactile/lost_at.*outside 0..700"):
        rf.write_trial(tmp_path / "bad.h5", copy)
    # an old file (no lost_at) reads as before
    rf.write_trial(tmp_path / "old.h5", make_trial())
    assert rf.read_trial(tmp_path / "old.h5", make_trial().name).lost_at is None
    assert rf.scan_raw(tmp_path / "old.h5")[1] == []


def test_scan_refuses_a_trial_name_in_two_files(tmp_path):
    a, b, c = tmp_path / "a.h5", tmp_path / "b.h5", tmp_path / "c.h5"
    rf.write_trial(a, make_trial(object_id=1))
    rf.write_trial(b, make_trial(object_id=1, seed=5))
    rf.write_trial(c, make_trial(object_id=2))
    assert len(rf.scan_raw([a, c])[0]) == 2
    assert len(rf.scan_raw([a, str(a), tmp_path / "." / "a.h5"])[0]) == 1  # the same file named thrice
    for strict in (False, True):
        with pytest.raises(rf.TrialFormatError, match="duplicate trial") as info:
            rf.scan_raw([a, c, b], strict=strict)
        assert str(a) in str(info.value) and str(b) in str(info.value) and make_trial(object_id=1).name in str(info.value)


def test_new_files_use_blosc_and_gzip_files_stay_readable(tmp_path, monkeypatch):
    """New raw files store Blosc-LZ4 (HDF5 filter 32001); a file written before the switch
    (gzip-1 + shuffle) reads back bit-identical, also mixed with a Blosc trial in one file,
    and caches build from both."""
    from embodied_tactile.data.cache import build_cache, load_cached
    from embodied_tactile.data.preprocess import preprocess_trial

    old, new = make_trial(object_id=0, seed=0), make_trial(object_id=1, seed=1)
    path = tmp_path / "mixed.h5"
    monkeypatch.setattr(rf, "_COMPRESSION", {"compression": "gzip", "compression_opts": 1, "shuffle": True})
    rf.write_trial(path, old)
    monkeypatch.undo()
    rf.write_trial(path, new)
    with h5py.File(path) as f:
        g_old, g_new = f["trials"][old.name], f["trials"][new.name]
        assert g_old["tactile/fsr"].compression == "gzip"
        assert "32001" in g_new["tactile/fsr"]._filters and "32001" in g_new["tactile/acc"]._filters
    for tr in (old, new):
        back = rf.read_trial(path, tr.name)
        for fld in ("t", "acc", "fsr", "pose_t", "pose"):
            np.testing.assert_array_equal(getattr(back, fld), getattr(tr, fld))
    from embodied_tactile.data.preprocess import PreprocessConfig

    cfg = PreprocessConfig(n_frames=30)  # the trials' 1 s
    paths = build_cache([path], tmp_path / "cache", cfg, fields=("acc",), workers=1)
    for tr in (old, new):
        np.testing.assert_allclose(load_cached(paths["acc"], tr.name, "acc"), preprocess_trial(tr, cfg, fields=("acc",))["acc"], atol=1e-6)


def test_unknown_factor_nan_passes_the_validator(three_trials):
    path, trials = three_trials
    _corrupt(path, trials[1].name, lambda g: g.attrs.__setitem__("stiffness", np.nan))
    good, errors = rf.scan_raw(path, strict=True)
    assert len(good) == 3 and not errors


def test_a_gap_is_accepted_where_a_lost_packet_is_recorded(tmp_path):
    """A 0.6 s step in the tactile clock: a TrialFormatError naming the sample unless
    tactile/lost_at records a lost packet at the sample after it (the recorder's timeouts);
    a step within max(MAX_GAP_S, GAP_STEPS / fs) needs nothing. (10 s of samples: the gap
    is within the missing share a trial may have, MAX_MISSING_SHARE.)"""
    tr = make_trial(n=7000, m=1070)  # the pose log covers the longer clock
    t = tr.t.copy()
    t[400:] += 0.6
    path = tmp_path / "raw.h5"
    with pytest.raises(rf.TrialFormatError, match=r"tactile/t.*0\.601 s before sample 400 \(0\.57 s -> 1\.17143 s\), with no lost packet recorded "
                                                  r"there \(tactile/lost_at\)"):
        rf.write_trial(path, rf.RawTrial(**{**tr.__dict__, "t": t}))
    rf.write_trial(path, rf.RawTrial(**{**tr.__dict__, "t": t, "lost_at": np.array([400])}))
    assert rf.scan_raw(path, strict=True)[0][0].name == tr.name
    t = tr.t.copy()
    t[400:] += rf.gap_limit(C.FS_TACTILE) * 0.9
    rf.write_trial(tmp_path / "small.h5", rf.RawTrial(**{**tr.__dict__, "t": t}))
    assert rf.gap_limit(10.0) == 1.0 and rf.gap_limit(1000.0) == rf.MAX_GAP_S


def test_a_trial_missing_more_than_the_documented_share_is_skipped_naming_it(tmp_path, caplog):
    """Fault: a 3 s hole in a 10 s trial whose lost packets are listed (tactile/lost_at), and
    a trial with a fifth of its samples dropped evenly (garbage answers). Before: both
    passed scan_raw and were resampled over the hole. Now: each is skipped with a warning
    naming the file, the trial and the share missing; a trial within MAX_MISSING_SHARE loads."""
    import logging

    rng = np.random.default_rng(3)
    hole = make_trial(n=7000, m=1070, repetition=0)
    keep = (hole.t < 2.0) | (hole.t >= 5.0)
    first = int(np.argmax(~keep))
    hole = rf.RawTrial(**{**hole.__dict__, "t": hole.t[keep], "acc": hole.acc[keep], "fsr": hole.fsr[keep],
                          "lost_at": np.full(int((~keep).sum()), first, dtype=np.int64)})
    sparse = make_trial(n=7000, m=1070, repetition=1)
    kept = np.sort(rng.choice(7000, 5600, replace=False))
    kept[0], kept[-1] = 0, 6999
    sparse = rf.RawTrial(**{**sparse.__dict__, "t": sparse.t[kept], "acc": sparse.acc[kept], "fsr": sparse.fsr[kept]})
    fine = make_trial(n=7000, m=1070, repetition=2)
    kept = np.sort(rng.choice(7000, 6650, replace=False))  # 5 % missing
    kept[0], kept[-1] = 0, 6999
    fine = rf.RawTrial(**{**fine.__dict__, "t": fine.t[kept], "acc": fine.acc[kept], "fsr": fine.fsr[kept]})
    path = tmp_path / "raw.h5"
    with pytest.raises(rf.TrialFormatError, match=r"30\.0% of the samples of the trial missing .*largest gap 3 s at 2 s"):
        rf.write_trial(path, hole)
    names = {}
    for label, tr, fields in (("hole", hole, ("t", "acc", "fsr", "lost_at")), ("sparse", sparse, ("t", "acc", "fsr"))):
        w = rf.IncrementalTrialWriter(path, tr.attrs)  # as the recorder stores it: no check on writing
        for fld in fields:
            w.append(fld, getattr(tr, fld))
        w.close(complete=True)
        names[label] = w.name
    names["fine"] = rf.write_trial(path, fine)
    with caplog.at_level(logging.WARNING):
        good, errors = rf.scan_raw(path, fields=["t", "acc"])
    assert [g.name for g in good] == [names["fine"]]
    assert sorted(e.trial for e in errors) == sorted([names["hole"], names["sparse"]])
    lines = [r.getMessage() for r in caplog.records if "skipping bad trial" in r.getMessage()]
    assert any(str(path) in ln and names["hole"] in ln and "30.0% of the samples" in ln for ln in lines), lines
    assert any(names["sparse"] in ln and "20.0% of the samples" in ln for ln in lines), lines
