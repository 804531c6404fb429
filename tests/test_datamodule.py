"""DataModule: batch shapes and dtypes per modality, split, acc-only reads no FSR data."""

from __future__ import annotations

import json
import pickle

import h5py
import numpy as np
import pytest
import torch

from embodied_tactile.data.datamodule import TrialRef, fields_for_channels, stratified_split
from embodied_tactile.io import rawformat as rf

from conftest import TINY_ACTIONS, TINY_OBJECTS, tiny_datamodule

MODALITIES = {
    "acc": ["acc"],
    "fsr_t": ["fsr_t"],
    "fsr_b": ["fsr_b"],
    "fsr_tb": ["fsr_t", "fsr_b"],
    "multi_e": ["acc", "fsr_t", "fsr_b"],
    "multi_l": ["acc", "fsr_t", "fsr_b"],
}


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


def test_split_is_stratified_stable_and_saved(tiny_data_dir, tmp_path):
    dm = tiny_datamodule(tiny_data_dir, ["fsr_t"], split_file=str(tmp_path / "split.json"))
    dm.prepare_data()
    dm.setup()
    train = {t.name for t in dm.train_set.trials}
    val = {t.name for t in dm.val_set.trials}
    assert not train & val
    assert len(train) + len(val) == len(TINY_OBJECTS) * len(TINY_ACTIONS) * 2
    assert len(val) == len(TINY_OBJECTS)  # round(0.25 * 4) per object
    for obj in TINY_OBJECTS:  # every object on both sides
        assert any(t.object_id == obj for t in dm.train_set.trials)
        assert any(t.object_id == obj for t in dm.val_set.trials)
    saved = json.loads((tmp_path / "split.json").read_text())
    assert set(saved["val"]) == val and saved["source"] == "simulated"
    dm2 = tiny_datamodule(tiny_data_dir, ["fsr_t"])
    dm2.prepare_data()
    dm2.setup()
    assert {t.name for t in dm2.val_set.trials} == val  # same seed, same split


def test_split_independent_of_listing_order():
    refs = [TrialRef(f"obj{o:02d}_a{a:02d}", o, a, "soft", "pressing", (0, 0, 0, 0)) for o in range(5) for a in range(8)]
    tr1, va1 = stratified_split(refs, 0.25, seed=3)
    tr2, va2 = stratified_split(list(reversed(refs)), 0.25, seed=3)
    assert va1 == va2 and tr1 == tr2
    _, va3 = stratified_split(refs, 0.25, seed=4)
    assert va3 != va1
    with pytest.raises(ValueError, match="val_fraction"):
        stratified_split(refs, 1.0, seed=0)


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
    assert len(dm.train_set) + len(dm.val_set) == len(TINY_OBJECTS) * len(TINY_ACTIONS) * 2
    assert opened, "the spy saw no dataset access"
    assert not [n for n in opened if "fsr" in n]
    assert "fsr" not in dm.cache_files


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
    names = {t.name for t in dm.train_set.trials + dm.val_set.trials}
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
