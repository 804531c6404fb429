"""The data preparation knows physics and time: unknown factors, trials shorter or longer
than the window, pose logs that stop early, damaged or copied caches, literal paths with
glob characters, and population sizes. Each test injects one fault and asserts what is
kept, skipped or refused, and that the message names file, trial and field."""

from __future__ import annotations

import logging
import shutil
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest

from conftest import tiny_scene
from embodied_tactile import constants as C
from embodied_tactile.data import rawformat as rf


def _trial(object_id: int, seconds: float, pose_seconds: float | None = None, seed: int = 0) -> rf.RawTrial:
    rng = np.random.default_rng(seed)
    n = int(round(seconds * C.FS_TACTILE))
    m = int(round((seconds if pose_seconds is None else pose_seconds) * C.FS_POSE))
    acc = rng.normal(0, 0.01, (n, 4, 4, 3)).astype(np.float32)
    acc[..., 2] += 1.0
    attrs = rf.make_attrs(object_id=object_id, skin="soft", primitive="pressing", action_index=0, repetition=0,
                          source="recorded", seed=0)
    return rf.RawTrial(t=np.arange(n) / C.FS_TACTILE, acc=acc, fsr=rng.integers(0, 4096, (n, 2, 16, 16)).astype(np.uint16),
                       pose_t=np.arange(m) / C.FS_POSE, pose=rng.normal(0, 1e-3, (m, 6)).astype(np.float32), attrs=attrs)


# ----------------------------------------------------------------------------- factors
def test_a_factor_unknown_everywhere_leaves_only_that_factor_out_of_the_alignment():
    """Fault: stiffness NaN in every trial (the format allows NaN for unknown). Before: the
    alignment dropped every row (a NaN in one factor dropped the row) and failed, exit 1.
    Now: the other three factors are aligned on every sequence, stiffness is predicted NaN."""
    from embodied_tactile.eval.krr import fit_alignment

    rng = np.random.default_rng(0)
    lat = rng.normal(size=(24, 8, 3))
    fac = np.stack([lat[:, -1, 0], lat[:, -1, 1] * 2, np.full(24, np.nan), (lat[:, -1, 2] > 0).astype(float)], axis=1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        align = fit_alignment(lat, fac, cv=2, ids=[f"s{i}" for i in range(24)])
    assert any("known on 0 sequence(s)" in str(w.message) for w in caught)
    pred = align.predict(lat[:4], ids=[f"t{i}" for i in range(4)])
    assert pred.shape == (4, 8, 4) and np.isnan(pred[..., 2]).all() and np.isfinite(pred[..., [0, 1, 3]]).all()
    # a factor unknown on some sequences: the other factors keep those sequences
    fac2 = np.nan_to_num(fac, nan=5.0)
    fac2[:6, 1] = np.nan
    align2 = fit_alignment(lat, fac2, cv=2)
    parts = {tuple(p["factor_columns"]): p["n_train_sequences"] for p in align2.params["parts"]}
    assert parts == {(0, 2, 3): 24, (1,): 18}


# ----------------------------------------------------------------------------- time
def test_short_long_and_pose_short_trials(tmp_path, caplog):
    """Faults: a 0.05 s trial, a 4 s trial and a pose log covering 0.3 s of a 1 s window.
    Before: the short trial became frames repeating its last sample, the long one was cut
    silently, the actions stayed constant after the pose log ended. Now: the short trial
    and the pose-short trial are skipped, naming file, trial and field; the long one is
    cut to the window with a warning naming it; the normal one is cached."""
    from embodied_tactile.data.cache import build_cache, cache_info
    from embodied_tactile.data.preprocess import PreprocessConfig

    raw = tmp_path / "raw.h5"
    for oid, secs, pose in ((0, 1.0, None), (1, 0.05, None), (2, 4.0, None), (3, 1.0, 0.3)):
        rf.write_trial(raw, _trial(oid, secs, pose, seed=oid))
    cfg = PreprocessConfig(n_frames=30)  # a 1 s window
    with caplog.at_level(logging.WARNING):
        files = build_cache([raw], tmp_path / "cache", cfg, fields=("acc", "actions"), workers=1)
    with h5py.File(files["acc"]) as f:  # the pose-short trial's acc is fine; training skips it whole (actions)
        assert sorted(f["trials"]) == ["obj00_soft_pressing_a00_r00", "obj02_soft_pressing_a00_r00",
                                       "obj03_soft_pressing_a00_r00"]
    with h5py.File(files["actions"]) as f:
        assert sorted(f["trials"]) == ["obj00_soft_pressing_a00_r00", "obj02_soft_pressing_a00_r00"]
    skipped = {(e["trial"], e["field"]): e for e in cache_info(files["actions"])["skipped"]}
    short = skipped[("obj01_soft_pressing_a00_r00", "actions")]
    assert short["file"] == str(raw) and "tactile/t: the recording covers 0.05 s, the scene's window is 1 s" in short["problem"]
    assert "pose/t: the pose log covers 0 .. 0.29 s of the tactile span 0 .. 1 s" in skipped[("obj03_soft_pressing_a00_r00", "actions")]["problem"]
    assert ("obj01_soft_pressing_a00_r00", "acc") in {(e["trial"], e["field"]) for e in cache_info(files["acc"])["skipped"]}
    assert f"{raw}: 1 trial(s) longer than the scene's 1 s window are cut to it: obj02_soft_pressing_a00_r00 (4 s)" in caplog.text
    assert f"skipping {raw} / obj01_soft_pressing_a00_r00 for acc: tactile/t" in caplog.text


# ----------------------------------------------------------------------------- caches
@pytest.fixture()
def data_copy(tiny_data_dir, tmp_path) -> Path:
    d = tmp_path / "data"
    shutil.copytree(tiny_data_dir, d)
    return d


def _arrays(path) -> dict[str, np.ndarray]:
    with h5py.File(path) as f:
        return {f"{n}/{k}": ds[()] for n, g in f["trials"].items() for k, ds in g.items()}


@pytest.mark.slow
def test_finite_garbage_in_a_cache_chunk_is_detected_and_rebuilt(data_copy, caplog):
    """Fault: finite garbage written into a cached array. Before: not detected, every run
    died with "non-finite loss". Now: the checksum fails, the file is set aside (kept) and
    the field rebuilt from the raw file, equal to the original."""
    from embodied_tactile.data.prepare import prepare_scene

    scene = tiny_scene(data_copy, sim_workers=1)
    first = prepare_scene(scene)
    acc = Path(first.cache_files["acc"])
    good = _arrays(acc)
    name = sorted(good)[3].split("/")[0]
    with h5py.File(acc, "a") as f:
        f["trials"][name]["acc"][0, 0, 0] = 1e6
    with caplog.at_level(logging.WARNING):
        again = prepare_scene(scene)
    assert f"{acc}: 1 cached array(s) fail their checksum (e.g. {name}/acc)" in caplog.text
    assert again.cache_files["acc"] == str(acc)
    rebuilt = _arrays(acc)
    assert rebuilt.keys() == good.keys() and all(np.array_equal(rebuilt[k], good[k]) for k in good)
    assert _arrays(acc.with_name(acc.name + ".corrupt"))[f"{name}/acc"][0, 0, 0] == 1e6


@pytest.mark.slow
def test_copied_data_folder_with_a_deleted_cache_file(data_copy):
    """Fault: a data folder copied elsewhere and one of its cache files deleted. Before:
    "cached fields ... come from different raw files" traceback. Now: the missing field is
    rebuilt, the copied one reused, the same trials listed."""
    from embodied_tactile.data.prepare import prepare_scene

    scene = tiny_scene(data_copy, sim_workers=1)
    before = prepare_scene(scene)
    moved = data_copy.parent / "moved"
    shutil.copytree(data_copy, moved)
    (moved / "cache" / Path(before.cache_files["actions"]).name).unlink()
    after = prepare_scene(tiny_scene(moved, sim_workers=1))
    assert [t.name for t in after.trials] == [t.name for t in before.trials]
    assert after.cache_built == ["actions"] and after.simulated == 0


# ----------------------------------------------------------------------------- paths, size
def test_literal_raw_path_with_glob_characters_is_found(tiny_data_dir, tmp_path):
    """Fault: a raw file in a folder named 'x [1]' given literally in data.raw_files.
    Before: "matches no file" (read as a glob pattern). Now: the existing file is used."""
    from embodied_tactile.data.prepare import Scene

    folder = tmp_path / "x [1]"
    folder.mkdir()
    raw = folder / "rec*.h5"
    shutil.copy(tiny_data_dir / "raw" / "soft_pressing.h5", raw)
    scene = Scene.from_config(data_dir=str(tmp_path), source="recorded", raw_files=(str(raw),), channels=("acc",))
    assert scene.raw_paths == [raw]
    with pytest.raises(FileNotFoundError, match=r"pattern .*x \[1\]/nothing\*\.h5.* matches no file"):
        Scene.from_config(data_dir=str(tmp_path), source="recorded", raw_files=(str(folder / "nothing*.h5"),)).raw_paths


def test_large_population_needs_the_flag_and_shows_its_estimate(tmp_path):
    """Fault: experiment=population data.n_objects=200000. Before: started writing 600,288
    trials with no estimate. Now: refused (exit 2 at train.py's entry) with trials, disk
    and time; data.allow_large_population=true lets it through."""
    from omegaconf import OmegaConf

    from embodied_tactile.data.prepare import Scene
    from embodied_tactile.run.settings import SettingsError, check_train_config

    kw = dict(data_dir=str(tmp_path), objects="population", n_objects=200000, actions=(6, 14), channels=("acc",))
    with pytest.raises(ValueError, match=r"400,192 trials .* more than the 10,000 allowed without "
                                         r"data.allow_large_population=true; preparing it takes about 1,737 GB"):
        Scene.from_config(**kw)
    Scene.from_config(**kw, allow_large_population=True)
    Scene.from_config(**{**kw, "n_objects": 256})
    cfg = OmegaConf.create({"data": {"objects": "population", "n_objects": 200000, "n_val_objects": 32,
                                     "n_test_objects": 64, "actions": [6, 14], "channels": ["acc"], "sim_workers": 2}})
    with pytest.raises(SettingsError, match=r"data.n_objects=200000: the population scene has 400,192 trials"):
        check_train_config(cfg)
    cfg.data.allow_large_population = True
    check_train_config(cfg)


def test_constant_statistics_name_the_channel_and_files(tiny_data_dir):
    """The check itself, on the tiny scene's acc data with its training statistics replaced
    by a constant and by a non-finite channel."""
    import numpy as np

    from conftest import tiny_datamodule
    from embodied_tactile.data.datamodule import ConstantChannelError
    from embodied_tactile.data.statistics import DataStatistics

    dm = tiny_datamodule(tiny_data_dir, ["acc"])
    dm.prepare_data()
    dm.setup("test")
    for mean, std, what in ((3.0, 0.0, "constant"), (float("nan"), float("nan"), "not finite")):
        with pytest.raises(ConstantChannelError, match=rf"^channel acc \(cached field acc, raw dataset tactile/acc\) of "
                                                        rf"the modality's channels \['acc'\] is {what} over the \d+ "
                                                        rf"training trials .* in raw file\(s\) {dm.raw_paths[0]}"):
            dm._check_statistics(DataStatistics(np.array([mean]), np.array([std]), 6))
    dm._check_statistics(DataStatistics(np.array([0.0]), np.array([1.0]), 6))


@pytest.mark.slow
def test_a_constant_channel_is_named_with_its_layer_modality_and_file(tiny_data_dir, tmp_path):
    """Fault: the bottom FSR layer reads one value in every trial (a dead layer). Before:
    ValueError "input stats must be finite with std > 0, got mean [..], std [.., 0.0]" from
    inside Lightning's fit, a traceback naming no channel, layer or file. Now: the data
    module's set-up raises ConstantChannelError naming the channel, its layer, cached field,
    raw dataset, the modality's channels and the raw file."""
    import shutil

    import h5py

    from conftest import tiny_datamodule
    from embodied_tactile.data.datamodule import ConstantChannelError

    data = tmp_path / "data"
    shutil.copytree(tiny_data_dir / "raw", data / "raw")
    raw = data / "raw" / "soft_pressing.h5"
    with h5py.File(raw, "a") as f:
        for g in f["trials"].values():
            fsr = g["tactile/fsr"][()]  # whole: h5py writes a strided selection element by element
            fsr[:, 1] = 512
            g["tactile/fsr"][...] = fsr
    dm = tiny_datamodule(data, ["fsr_t", "fsr_b"])
    dm.prepare_data()
    with pytest.raises(ConstantChannelError) as err:
        dm.setup("fit")
    msg = str(err.value)
    assert msg.startswith("channel fsr_b (layer 1 of cached field fsr, raw dataset tactile/fsr) of the modality's "
                          "channels ['fsr_t', 'fsr_b'] is constant over the ")
    assert str(raw) in msg and dm.statistics is None


@pytest.mark.slow
def test_stale_temporary_files_of_a_killed_preparation_are_removed(tiny_data_dir, tmp_path, caplog):
    """Fault: a cache build killed (kill -9) before its rename, leaving <field>-<key>.h5.tmp-<pid>-<id>
    in the cache folder. Before: the file stayed for good (hundreds of MB per field on the
    recorded data). Now: the next preparation removes each one last written before its own
    process started, naming it; a newer one (another build's, under the lock) stays."""
    import os
    import shutil
    import time

    from conftest import tiny_scene
    from embodied_tactile.data.prepare import prepare_scene, process_start_time

    data = tmp_path / "data"
    shutil.copytree(tiny_data_dir / "raw", data / "raw")
    (data / "cache").mkdir()
    stale = data / "cache" / "acc-0123456789abcdef.h5.tmp-4242-deadbeef"
    stale.write_bytes(b"half a cache")
    then = process_start_time() - 60
    os.utime(stale, (then, then))
    fresh = data / "cache" / "fsr-0123456789abcdef.h5.tmp-4243-cafef00d"
    fresh.write_bytes(b"being written")
    assert fresh.stat().st_mtime > process_start_time() and time.time() > process_start_time()
    with caplog.at_level("WARNING"):
        prepared = prepare_scene(tiny_scene(data, sim_workers=1))
    assert not stale.exists() and fresh.exists()
    assert f"removed {stale}" in caplog.text
    assert prepared.trials


@pytest.mark.slow
def test_damaged_cache_copies_do_not_pile_up(data_copy):
    """Fault: a cache file fails its checksum three times. Before: three .corrupt-N copies,
    each as large as the cache (128 MB on the recorded data), kept for good. Now: once each
    rebuild succeeds, the newest damaged copy is kept for inspection and the older ones go."""
    from embodied_tactile.data.prepare import prepare_scene

    scene = tiny_scene(data_copy, sim_workers=1)
    acc = Path(prepare_scene(scene).cache_files["acc"])
    name = sorted(_arrays(acc))[0].split("/")[0]
    for value in (1e6, 2e6, 3e6):
        with h5py.File(acc, "a") as f:
            f["trials"][name]["acc"][0, 0, 0] = value
        prepare_scene(scene)
    copies = sorted(acc.parent.glob(acc.name + ".corrupt*"))
    assert len(copies) == 1, copies
    assert _arrays(copies[0])[f"{name}/acc"][0, 0, 0] == 3e6  # the newest damage
    assert _arrays(acc)[f"{name}/acc"][0, 0, 0] not in (1e6, 2e6, 3e6)
