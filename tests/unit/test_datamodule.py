"""DataModule: batch shapes and dtypes per modality, split, acc-only reads no FSR data."""

from __future__ import annotations

import json
import pickle

import h5py
import numpy as np
import pytest
import torch

from embodied_tactile.data.datamodule import TrialRef, fields_for_channels, split_trials
from embodied_tactile.data import rawformat as rf

from conftest import TINY_ACTIONS, TINY_OBJECTS, tiny_datamodule

MODALITIES = {
    "acc": ["acc"],
    "fsr_t": ["fsr_t"],
    "fsr_b": ["fsr_b"],
    "fsr_tb": ["fsr_t", "fsr_b"],
    "multi_e": ["acc", "fsr_t", "fsr_b"],
    "multi_l": ["acc", "fsr_t", "fsr_b"],
}


@pytest.mark.slow
@pytest.mark.parametrize("modality", sorted(MODALITIES))
def test_batch_shapes_and_dtypes(tiny_data_dir, modality, tmp_path):
    channels = MODALITIES[modality]
    dm = tiny_datamodule(tiny_data_dir, channels, split_file=str(tmp_path / "split.json"))
    dm.prepare_data()
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    B = batch["obs"].shape[0]
    assert batch["obs"].shape == (B, 300, len(channels), 28, 28) and batch["obs"].dtype == torch.float32
    assert batch["actions"].shape == (B, 300, 6) and batch["actions"].dtype == torch.float32
    assert batch["object_id"].shape == (B,) and batch["object_id"].dtype == torch.int64
    assert batch["factors"].shape == (B, 4) and batch["factors"].dtype == torch.float32
    assert batch["action_index"].dtype == torch.int64
    assert torch.isfinite(batch["obs"]).all() and torch.isfinite(batch["actions"]).all()
    # channel selection: fsr_b is the bottom layer of the cached fsr field
    if modality == "fsr_b":
        name = dm.train_set.trials[0].name
        with h5py.File(dm.cache_files["fsr"]) as f:
            np.testing.assert_array_equal(dm.train_set[0]["obs"][:, 0].numpy(), f["trials"][name]["fsr"][:, 1])


@pytest.mark.slow
def test_training_windows_are_random_crops_and_evaluation_sees_whole_trials(tiny_data_dir, tmp_path):
    dm = tiny_datamodule(tiny_data_dir, ["fsr_t", "fsr_b"], split_file=str(tmp_path / "split.json"),
                         train_window=40, windows_per_trial=3)
    dm.prepare_data()
    dm.setup("fit")
    n = len(dm.train_set)
    assert len(dm.train_dataloader().dataset) == 3 * n
    torch.manual_seed(0)
    starts = set()
    for i in range(3 * n):
        item = dm.train_dataloader().dataset[i]
        full = dm.train_set[i % n]
        assert item["obs"].shape == (40, 2, 28, 28) and item["actions"].shape == (40, 6)
        assert int(item["object_id"]) == int(full["object_id"])
        # the crop is a contiguous block of the whole trial, observations and actions aligned
        hits = [s for s in range(300 - 40 + 1) if torch.equal(full["actions"][s:s + 40], item["actions"])
                and torch.equal(full["obs"][s:s + 40], item["obs"])]
        assert hits
        starts.add(hits[0])
    assert len(starts) > 1  # offsets are drawn, not fixed
    for loader in (dm.train_eval_dataloader(), dm.val_dataloader()):
        assert next(iter(loader))["obs"].shape[1] == 300
    with pytest.raises(ValueError, match="train window must be >= 2"):
        bad = tiny_datamodule(tiny_data_dir, ["fsr_t"], split_file=str(tmp_path / "s2.json"), train_window=1)
        bad.prepare_data()
        bad.setup("fit")


@pytest.mark.slow
def test_split_is_stratified_stable_and_saved(tiny_data_dir, tmp_path):
    dm = tiny_datamodule(tiny_data_dir, ["fsr_t"], split_file=str(tmp_path / "split.json"))
    dm.prepare_data()
    dm.setup()
    train = {t.name for t in dm.train_set.trials}
    val = {t.name for t in dm.val_set.trials}
    test = {t.name for t in dm.test_set.trials}
    assert not train & val and not train & test and not val & test
    assert len(train) + len(val) + len(test) == len(TINY_OBJECTS) * len(TINY_ACTIONS) * 2
    assert len(test) == len(TINY_OBJECTS)  # round(0.25 * 4) per object
    assert len(val) == 2  # round(0.125 * 16)
    for obj in TINY_OBJECTS:  # every object on the training and test sides
        assert any(t.object_id == obj for t in dm.train_set.trials)
        assert any(t.object_id == obj for t in dm.test_set.trials)
    train_objects = {t.object_id for t in dm.train_set.trials}
    assert {t.object_id for t in dm.val_set.trials} <= train_objects  # validation: training objects only
    saved = json.loads((tmp_path / "split.json").read_text())
    assert set(saved["val"]) == val and set(saved["test"]) == test and saved["source"] == "simulated"
    assert saved["split"] == "trial"
    dm2 = tiny_datamodule(tiny_data_dir, ["fsr_t"])
    dm2.prepare_data()
    dm2.setup()
    assert {t.name for t in dm2.test_set.trials} == test  # same seed, same split
    assert {t.name for t in dm2.val_set.trials} == val
    # the test loader serves the test trials, the validation loader the validation trials
    assert sum(len(b["object_id"]) for b in dm.test_dataloader()) == len(test)
    assert sum(len(b["object_id"]) for b in dm.val_dataloader()) == len(val)


def _refs(n_objects=5, n_actions=8):
    from embodied_tactile.constants import OBJECTS

    return [TrialRef(f"obj{o:02d}_a{a:02d}", o, a, "soft", "pressing", tuple(OBJECTS[o].factors()))
            for o in range(n_objects) for a in range(n_actions)]


def test_split_independent_of_listing_order():
    refs = _refs()
    s1 = split_trials(refs, test_fraction=0.25, seed=3)
    s2 = split_trials(list(reversed(refs)), test_fraction=0.25, seed=3)
    assert s1 == s2
    s3 = split_trials(refs, test_fraction=0.25, seed=4)
    assert s3[2] != s1[2]
    with pytest.raises(ValueError, match="test_fraction"):
        split_trials(refs, test_fraction=1.0, seed=0)
    with pytest.raises(ValueError, match="split must be one of"):
        split_trials(refs, by="person")


@pytest.mark.parametrize("by", ["trial", "object"])
def test_split_partitions_and_validation_objects(by):
    refs = _refs(32, 4)
    for seed in range(5):
        train, val, test = split_trials(refs, by=by, test_fraction=0.25, val_fraction=0.125, seed=seed)
        names = [t.name for t in train + val + test]
        assert sorted(names) == sorted(r.name for r in refs) and len(set(names)) == len(names)
        assert len(val) == 16
        train_objects, val_objects = {t.object_id for t in train}, {t.object_id for t in val}
        if by == "trial":  # validation trials of training objects
            assert val_objects <= train_objects
            assert len(test) == 32 and {t.object_id for t in test} == set(range(32))
        else:  # 4 whole validation objects, apart from training and test objects
            assert len(val_objects) == 4 and not val_objects & train_objects
            assert not val_objects & {t.object_id for t in test}


def test_object_split_never_puts_one_object_on_both_sides():
    from embodied_tactile.constants import OBJECTS

    refs = _refs(32, 4)
    for seed in range(20):
        train, val, test = split_trials(refs, by="object", test_fraction=0.25, seed=seed)
        seen = {t.object_id for t in train + val}
        held = {t.object_id for t in test}
        assert held and not seen & held
        assert len(held) == 8 and len(test) == 32  # 8 whole objects x 4 trials
        for k in range(4):  # stratified: every factor level keeps most of its objects in training
            levels = [OBJECTS[o].factors()[k] for o in range(32)]
            for lv in set(levels):
                n = sum(1 for v in levels if v == lv)
                n_held = sum(1 for o in held if OBJECTS[o].factors()[k] == lv)
                assert n_held <= int(np.ceil(0.25 * n)), (seed, k, lv, n_held, n)
    # a different seed holds out different objects
    assert {t.object_id for t in split_trials(refs, by="object", seed=0)[2]} != \
        {t.object_id for t in split_trials(refs, by="object", seed=1)[2]}


@pytest.mark.slow
def test_legacy_split_file_reads_val_as_test(tiny_data_dir, tmp_path, caplog):
    dm = tiny_datamodule(tiny_data_dir, ["fsr_t"], split_file=str(tmp_path / "split.json"))
    dm.prepare_data()
    dm.setup()
    legacy = {"train": [t.name for t in dm.train_set.trials + dm.val_set.trials],
              "val": [t.name for t in dm.test_set.trials]}
    (tmp_path / "legacy.json").write_text(json.dumps(legacy))
    old = tiny_datamodule(tiny_data_dir, ["fsr_t"], split_file=str(tmp_path / "legacy.json"))
    old.prepare_data()
    with caplog.at_level("WARNING"):
        old.setup()
    assert {t.name for t in old.test_set.trials} == set(legacy["val"])
    assert len(old.val_set) == 0
    assert "predates the train/val/test split" in caplog.text


@pytest.mark.slow
def test_acc_only_never_reads_fsr(tiny_data_dir, tmp_path, monkeypatch):
    """The acc-only pipeline works on raw files whose FSR datasets are gone, and the spy sees
    no FSR dataset opened in this process (cache building, listing and batches)."""
    import shutil

    d = tmp_path / "data"
    shutil.copytree(tiny_data_dir / "raw", d / "raw")
    raw = d / "raw" / "soft_pressing.h5"
    with h5py.File(raw, "a") as f:
        for g in f["trials"].values():
            del g["tactile/fsr"]
    opened: list[str] = []
    orig = h5py.Group.__getitem__

    def spy(self, key):
        obj = orig(self, key)
        if isinstance(obj, h5py.Dataset):
            opened.append(obj.name)
        return obj

    monkeypatch.setattr(h5py.Group, "__getitem__", spy)
    dm = tiny_datamodule(d, ["acc"])
    dm.prepare_data()
    dm.setup()
    batch = next(iter(dm.train_dataloader()))
    assert batch["obs"].shape[2] == 1
    assert len(dm.train_set) + len(dm.val_set) + len(dm.test_set) == len(TINY_OBJECTS) * len(TINY_ACTIONS) * 2
    assert opened, "the spy saw no dataset access"
    assert not [n for n in opened if "fsr" in n]
    assert "fsr" not in dm.cache_files


@pytest.mark.slow
def test_dataset_pickles_without_handle(tiny_data_dir):
    dm = tiny_datamodule(tiny_data_dir, ["acc", "fsr_t"])
    dm.prepare_data()
    dm.setup()
    ds = dm.train_set
    _ = ds[0]  # opens the handles
    assert ds._handles is not None
    clone = pickle.loads(pickle.dumps(ds))
    assert clone._handles is None
    torch.testing.assert_close(clone[0]["obs"], ds[0]["obs"])


@pytest.mark.slow
def test_bad_trial_is_skipped_and_named(tiny_data_dir, tmp_path, caplog):
    import shutil

    d = tmp_path / "data"
    shutil.copytree(tiny_data_dir / "raw", d / "raw")
    raw = d / "raw" / "soft_pressing.h5"
    good, _ = rf.scan_raw(raw)
    bad = good[0].name
    with h5py.File(raw, "a") as f:
        f["trials"][bad]["tactile/acc"][3, 0, 0, 0] = np.nan
    dm = tiny_datamodule(d, ["acc"])
    dm.prepare_data()
    dm.setup()
    names = {t.name for t in dm.train_set.trials + dm.val_set.trials + dm.test_set.trials}
    assert bad not in names and len(names) == len(good) - 1
    assert bad in caplog.text and "tactile/acc" in caplog.text
    assert [e["trial"] for e in dm.skipped] == [bad]  # reported once, not once per cached field
    strict = tiny_datamodule(tmp_path / "strict", ["acc"], strict=True)
    shutil.copytree(d / "raw", tmp_path / "strict" / "raw")
    with pytest.raises(rf.TrialFormatError, match=bad):
        strict.prepare_data()


def test_fields_for_channels():
    assert fields_for_channels(["acc"]) == ["acc", "actions"]
    assert fields_for_channels(["fsr_t", "fsr_b"]) == ["fsr", "actions"]
    with pytest.raises(ValueError, match="unknown observation channel"):
        fields_for_channels(["gyro"])


def _served(dm):
    """Names of every trial the DataModule serves, whatever the split."""
    sets = (getattr(dm, k, None) for k in ("train_set", "val_set", "test_set"))
    return {t.name for s in sets if s is not None for t in s.trials}


def _recorded_dm(raw_files, **kw):
    from embodied_tactile.data.datamodule import TactileDataModule

    return TactileDataModule.from_config(source="recorded", raw_files=raw_files, skin="soft", primitive="pressing",
                                         channels=["acc"], **{"actions": None, **kw})  # every recorded trial


def test_raw_file_patterns_absolute_home_and_relative(tmp_path, monkeypatch):
    sess = tmp_path / "home" / "rec"
    sess.mkdir(parents=True)
    files = [sess / f"s{k}.h5" for k in (2, 0, 1)]
    for p in files:
        p.write_bytes(b"")
    (sess / "notes.txt").write_text("")
    want = sorted(p.resolve() for p in files)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    for pattern in (f"{sess}/*.h5", "~/rec/*.h5", "home/rec/s?.h5", "home/*/s[0-9].h5"):
        assert [p.resolve() for p in _recorded_dm([pattern]).raw_paths] == want, pattern
    # literal paths (absolute, ~ or relative) too; a file named twice is used once, first place kept
    got = _recorded_dm(["~/rec/s0.h5", str(sess / "s0.h5"), "home/rec/s0.h5", f"{sess}/*.h5"]).raw_paths
    assert [p.resolve() for p in got] == [(sess / n).resolve() for n in ("s0.h5", "s1.h5", "s2.h5")]
    assert all(p.is_absolute() for p in got)


@pytest.mark.parametrize("pattern", ["/nonexistent-dir-xyz/*.h5", "~/nothing-here-*.h5", "nothing/*.h5"])
def test_raw_file_pattern_matching_nothing_is_an_error_naming_it(tmp_path, monkeypatch, pattern):
    good = tmp_path / "a.h5"
    good.write_bytes(b"")
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(FileNotFoundError, match="matches no file") as info:
        _recorded_dm([str(good), pattern]).raw_paths
    assert pattern in str(info.value)
    with pytest.raises(FileNotFoundError, match="missing.h5"):
        _recorded_dm([str(tmp_path / "missing.h5")]).raw_paths


@pytest.mark.slow
def test_incomplete_recordings_excluded_unless_asked(tiny_data_dir, tmp_path, caplog):
    import logging
    import shutil

    d = tmp_path / "data"
    shutil.copytree(tiny_data_dir / "raw", d / "raw")
    raw = d / "raw" / "soft_pressing.h5"
    good, _ = rf.scan_raw(raw, validate_data=False)
    cut = sorted(g.name for g in good)[:3]
    with h5py.File(raw, "a") as f:
        for n in cut:
            f["trials"][n].attrs["complete"] = False
        f["trials"][sorted(g.name for g in good)[3]].attrs["complete"] = True
    caplog.set_level(logging.INFO)
    dm = tiny_datamodule(d, ["acc"], source="recorded", raw_files=[str(raw)])
    dm.prepare_data()
    dm.setup()
    used = _served(dm)
    assert used == {g.name for g in good} - set(cut)
    assert "excluded 3 incomplete" in caplog.text and "include_incomplete" in caplog.text
    assert dm.describe()["excluded_incomplete"] == 3
    dm2 = tiny_datamodule(d, ["acc"], source="recorded", raw_files=[str(raw)], include_incomplete=True)
    dm2.prepare_data()
    dm2.setup()
    assert _served(dm2) == {g.name for g in good}
    assert dm2.describe()["excluded_incomplete"] == 0
