"""Trial identity across raw files (docs/reference/data_format.md, "Trial identity"): a trial is one
group of one file, all its fields come from that group, and nothing is mixed or dropped
without a stated reason."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from embodied_tactile.data.cache import build_cache, cache_info, list_cached
from embodied_tactile.data.datamodule import TactileDataModule
from embodied_tactile.data.prepare import list_trials
from embodied_tactile.data import rawformat as rf

FAST = {"n_frames": 30}  # 1 s of each 10 s trial: the identity rules do not depend on T


def _copy_trials(src, dst, names, rename=None):
    """Copy trial groups of ``src`` into a new raw file ``dst`` (optionally renaming them)."""
    rename = rename or {}
    with h5py.File(src, "r") as fi, h5py.File(dst, "a") as fo:
        fo.attrs["format"] = rf.FORMAT_NAME
        fo.attrs["format_version"] = rf.FORMAT_VERSION
        trials = fo.require_group("trials")
        for n in names:
            fi.copy(fi["trials"][n], trials, name=rename.get(n, n))
    return dst


@pytest.fixture()
def names(tiny_data_dir):
    good, _ = rf.scan_raw(tiny_data_dir / "raw" / "soft_pressing.h5", validate_data=False)
    return [g.name for g in good]


def _recorded(tmp_path, files, channels=("acc", "fsr_t"), **kw):
    return TactileDataModule.from_config(
        data_dir=str(tmp_path / "data"), source="recorded", raw_files=[str(f) for f in files], skin="soft",
        primitive="pressing", channels=list(channels), preprocess=FAST, preprocess_workers=1, batch_size=2,
        actions=None, train_window=None, windows_per_trial=1, windows_per_epoch=None, **kw,  # every recorded trial, whole
    )


def _set_layer(ds: h5py.Dataset, layer: int, value: float) -> None:
    """``ds[:, layer] = value`` as one read and one whole write (h5py writes a strided
    selection of a compressed dataset chunk by chunk: about 4 s a trial)."""
    data = ds[()]
    data[:, layer] = value
    ds[...] = data


def _refs(dm):
    """Every trial the DataModule serves, whatever the split."""
    sets = (getattr(dm, k, None) for k in ("train_set", "val_set", "test_set"))
    return [t for s in sets if s is not None for t in s.trials]


def _used(dm):
    return {t.name for t in _refs(dm)}


def test_duplicate_trial_in_two_files_is_an_error_naming_both(tiny_data_dir, names, tmp_path):
    """The chimeric trial: the first copy is bad in fsr only. Before, the acc cache took the
    trial from file A and the fsr cache from file B, and the stitched trial was trained on."""
    raw = tiny_data_dir / "raw" / "soft_pressing.h5"
    x = names[0]
    a = _copy_trials(raw, tmp_path / "a.h5", [x, names[1]])
    b = _copy_trials(raw, tmp_path / "b.h5", [x, names[2]])
    with h5py.File(a, "a") as f:
        f["trials"][x]["tactile/fsr"][3, 0, 0, 0] = 5000  # out of the 12-bit range
    dm = _recorded(tmp_path, [a, b])
    with pytest.raises(rf.TrialFormatError, match="duplicate") as info:
        dm.prepare_data()
    msg = str(info.value)
    assert x in msg and str(a) in msg and str(b) in msg
    # the cache builder refuses it too, strict or not, and whatever the fields
    for fields in (("acc",), ("fsr", "actions")):
        with pytest.raises(rf.TrialFormatError, match="duplicate"):
            build_cache([a, b], tmp_path / "cache2", fields=fields, workers=1, cfg=_cfg())


def test_trial_bad_in_one_field_is_skipped_whole(tiny_data_dir, names, tmp_path):
    raw = tiny_data_dir / "raw" / "soft_pressing.h5"
    a = _copy_trials(raw, tmp_path / "a.h5", names[:4])
    bad = names[1]
    with h5py.File(a, "a") as f:
        f["trials"][bad]["tactile/fsr"][3, 0, 0, 0] = 5000
    dm = _recorded(tmp_path, [a])
    dm.prepare_data()
    dm.setup()
    assert bad not in _used(dm) and _used(dm) == set(names[:4]) - {bad}
    assert [(e["trial"], e["field"]) for e in dm.skipped] == [(bad, "fsr")]
    assert "tactile/fsr" in dm.skipped[0]["problem"] and dm.skipped[0]["file"] == str(a)


@pytest.mark.parametrize("declared", [350.0, 1400.0])
def test_trial_bad_in_every_field_is_counted_once(tiny_data_dir, names, tmp_path, caplog, declared):
    """A declared rate its timestamps contradict (either direction) breaks the clock every
    field reads: each cache lists the trial, the DataModule skips and counts it once."""
    raw = tiny_data_dir / "raw" / "soft_pressing.h5"
    a = _copy_trials(raw, tmp_path / "a.h5", names[:4])
    bad = names[2]
    with h5py.File(a, "a") as f:
        f["trials"][bad].attrs["fs_tactile"] = declared
    dm = _recorded(tmp_path, [a])
    with caplog.at_level("INFO"):
        dm.prepare_data()
        dm.setup()
    assert _used(dm) == set(names[:4]) - {bad}
    assert len(dm.skipped) == 1 and dm.skipped[0]["trial"] == bad and dm.skipped[0]["file"] == str(a)
    assert set(dm.skipped[0]["field"].split(", ")) == {"acc", "fsr", "actions"}
    assert "tactile/t" in dm.skipped[0]["problem"] and f"fs_tactile declares {declared:g} Hz" in dm.skipped[0]["problem"]
    assert "skipped 1 bad trial(s)" in caplog.text


@pytest.mark.slow
@pytest.mark.parametrize("dataset, layer", [("tactile/fsr", 1), ("tactile/acc", None)])
def test_a_dead_channel_in_one_trial_is_skipped_naming_file_trial_and_layer(tiny_data_dir, names, tmp_path, caplog,
                                                                            dataset, layer):
    """Fault: one trial of four reads one value in a channel (its bottom FSR layer at 512
    counts, or every accelerometer at 0 g: a layer dead in that recording only). Before: the
    trial was trained on with no word. Now: the preparation skips it with a warning naming
    file, trial and channel, and lists it in ``skipped`` (field: the raw dataset and layer);
    a scene that does not read the dead channel keeps the trial."""
    raw = tiny_data_dir / "raw" / "soft_pressing.h5"
    a = _copy_trials(raw, tmp_path / "a.h5", names[:4])
    bad = names[1]
    with h5py.File(a, "a") as f:
        if layer is None:
            ds = f["trials"][bad][dataset]
            ds[...] = np.zeros(ds.shape, ds.dtype)  # a whole array: h5py broadcasts a scalar chunk by chunk
        else:
            _set_layer(f["trials"][bad][dataset], layer, 512)
    channel = "fsr_b" if layer is not None else "acc"
    dm = _recorded(tmp_path, [a], channels=("acc", "fsr_t", "fsr_b"))
    with caplog.at_level("WARNING"):
        dm.prepare_data()
        dm.setup()
    assert _used(dm) == set(names[:4]) - {bad}
    field = dataset + ("" if layer is None else f" layer {layer}")
    assert [(e["file"], e["trial"], e["field"]) for e in dm.skipped] == [(str(a), bad, field)]
    assert dm.skipped[0]["problem"].startswith(f"channel {channel} (")
    assert "reads one value" in dm.skipped[0]["problem"] and "3 other trial(s) of the scene vary" in dm.skipped[0]["problem"]
    warned = [r.getMessage() for r in caplog.records if r.getMessage().startswith("skipping")]
    assert len(warned) == 1 and str(a) in warned[0] and f"channel {channel} (" in warned[0]
    assert "1 skipped" in dm.prepared.summary()
    if layer is not None:  # a scene without the dead layer (top layer only) keeps the trial
        kept = _recorded(tmp_path, [a], channels=("fsr_t",))
        kept.prepare_data()
        kept.setup()
        assert _used(kept) == set(names[:4]) and kept.skipped == []


@pytest.mark.slow
def test_a_channel_dead_in_every_trial_is_still_refused_whole(tiny_data_dir, names, tmp_path):
    """The same dead layer in every trial is no trial's fault: nothing is skipped, and the
    training set-up refuses the channel (ConstantChannelError), as before."""
    from embodied_tactile.data.datamodule import ConstantChannelError

    raw = tiny_data_dir / "raw" / "soft_pressing.h5"
    a = _copy_trials(raw, tmp_path / "a.h5", names[:4])
    with h5py.File(a, "a") as f:
        for n in names[:4]:
            _set_layer(f["trials"][n]["tactile/fsr"], 1, 512)
    dm = _recorded(tmp_path, [a], channels=("fsr_t", "fsr_b"))
    dm.prepare_data()
    assert dm.skipped == [] and len(dm.prepared.trials) == 4
    with pytest.raises(ConstantChannelError, match=r"^channel fsr_b \(layer 1 of cached field fsr"):
        dm.setup("fit")


def test_fields_of_one_trial_from_different_files_are_refused(tiny_data_dir, names, tmp_path):
    """The preparation stage's trial listing checks that every cached field of a trial came
    from the same raw file (a guard behind the cache builder's duplicate check)."""
    raw = tiny_data_dir / "raw" / "soft_pressing.h5"
    a = _copy_trials(raw, tmp_path / "a.h5", names[:2])
    b = _copy_trials(raw, tmp_path / "b.h5", names[:2])
    acc = build_cache([a], tmp_path / "cache", fields=("acc",), workers=1, cfg=_cfg())
    rest = build_cache([b], tmp_path / "cache", fields=("fsr", "actions"), workers=1, cfg=_cfg())
    dm = _recorded(tmp_path, [a])
    mixed = {"acc": str(acc["acc"]), "fsr": str(rest["fsr"]), "actions": str(rest["actions"])}
    with pytest.raises(RuntimeError, match="different raw files") as info:
        list_trials(dm.scene, mixed)
    assert str(a) in str(info.value) and str(b) in str(info.value)


def _cfg():
    from embodied_tactile.data.preprocess import PreprocessConfig

    return PreprocessConfig(**FAST)


def test_renamed_group_is_cached_under_its_group_name(tiny_data_dir, names, tmp_path, caplog):
    """A group renamed to resolve a duplicate (its name no longer matches its attributes)
    used to pass validation and then vanish from the cache without a word."""
    raw = tiny_data_dir / "raw" / "soft_pressing.h5"
    x = names[0]
    a = _copy_trials(raw, tmp_path / "a.h5", [x, names[1]])
    b = _copy_trials(raw, tmp_path / "b.h5", [x, names[2]], rename={x: f"{x}_session2"})
    paths = build_cache([a, b], tmp_path / "cache", cfg=_cfg(), fields=("acc", "actions"), workers=1)
    for fld, p in paths.items():
        cached = dict(list_cached(p))
        assert set(cached) == {x, f"{x}_session2", names[1], names[2]}, fld
        assert cached[f"{x}_session2"]["source_file"] == str(b) and cached[x]["source_file"] == str(a)
        assert cache_info(p)["skipped"] == []
    dm = _recorded(tmp_path, [a, b], channels=["acc"])
    dm.prepare_data()
    dm.setup()
    assert _used(dm) == {x, f"{x}_session2", names[1], names[2]}
    # the renamed copy keeps what its attributes say it is
    ref = next(t for t in _refs(dm) if t.name == f"{x}_session2")
    assert rf.trial_name({"skin": ref.skin, "primitive": ref.primitive, "object_id": ref.object_id,
                          "action_index": ref.action_index, "repetition": int(x[-2:])}) == x


def test_raw_trial_name_is_its_group(tiny_data_dir, names, tmp_path):
    raw = tiny_data_dir / "raw" / "soft_pressing.h5"
    a = _copy_trials(raw, tmp_path / "a.h5", [names[0]], rename={names[0]: "renamed"})
    tr = rf.read_trial(a, "renamed", fields=["acc"])
    assert tr.name == "renamed" and tr.group == "renamed"
    assert rf.trial_name(tr.attrs) == names[0]
    fresh = rf.RawTrial(t=tr.t, acc=tr.acc, fsr=np.zeros(0), pose_t=np.zeros(0), pose=np.zeros(0), attrs=tr.attrs)
    assert fresh.name == names[0]  # a trial not read from a file is named by its attributes


def test_trial_absent_from_one_cache_without_reason_is_reported(tiny_data_dir, names, tmp_path, caplog):
    raw = tiny_data_dir / "raw" / "soft_pressing.h5"
    a = _copy_trials(raw, tmp_path / "a.h5", names[:4])
    dm = _recorded(tmp_path, [a], channels=["acc"])
    dm.prepare_data()
    with h5py.File(dm.cache_files["actions"], "a") as f:  # a damaged cache: one trial gone, no reason listed
        del f["trials"][names[2]]
    dm = _recorded(tmp_path, [a], channels=["acc"])  # the next preparation finds the damaged cache
    dm.prepare_data()
    dm.setup()
    assert _used(dm) == set(names[:4]) - {names[2]}
    assert [(e["file"], e["trial"], e["field"]) for e in dm.skipped] == [(str(a), names[2], "actions")]
    assert "absent from the cache" in dm.skipped[0]["problem"] and names[2] in caplog.text


@pytest.mark.slow  # trains a tiny run (train.py's entry point in this process)
def test_evaluation_takes_each_trials_object_from_its_attributes_not_its_name(tiny_data_dir, names, tmp_path):
    """A group named ``obj05_...`` that holds object 0, and one named ``session2_trial7``:
    both train as their attributes say, and evaluate.py scores them as the same objects
    (before, the first was listed as test object 5 and the second stopped evaluate.py)."""
    import json

    from conftest import train_in_process

    from embodied_tactile.eval import pipeline

    raw = tiny_data_dir / "raw" / "soft_pressing.h5"
    with h5py.File(raw, "r") as f:
        obj = {n: int(f["trials"][n].attrs["object_id"]) for n in names}
    liar = next(n for n in names if obj[n] == 0)
    free = next(n for n in names if obj[n] == 8)
    rename = {liar: "obj05_soft_pressing_a00_r00", free: "session2_trial7"}
    data = _copy_trials(raw, tmp_path / "renamed.h5", names, rename=rename)
    run = tmp_path / "run"
    p = train_in_process("debug=fast", "data=recorded", f"data.raw_files=[{data}]", "data.objects=null",
                         "data.actions=null", f"paths.data_dir={tmp_path / 'data'}", f"hydra.run.dir={run}")
    assert p.returncode == 0, p.stderr[-3000:]
    out = pipeline.evaluate(run, ["alignment.cv=2", "baselines=[mean]", "umap=false", "figures=false"])
    split = json.loads((run / "split.json").read_text())
    truth = {rename.get(n, n): obj[n] for n in names}
    info = out["runs"][0]["split"]
    for side in ("train", "test"):
        assert info[f"{side}_objects"] == sorted({truth[n] for n in split[side]}), side
    assert 5 not in info["train_objects"] + info["test_objects"]
    assert {"obj05_soft_pressing_a00_r00", "session2_trial7"} <= set(split["train"] + split["val"] + split["test"])
    res = json.loads((run / "evaluation" / "results.json").read_text())
    lf = next(r for r in res["runs"] if r["method"] == "latent_filter")
    assert set(lf["nmse_trajectory_by_group"]) <= {"soft", "hard", "heterogeneous"}
    assert lf["n_test"] == len(split["test"])


@pytest.mark.slow
def test_data_identity_is_per_trial_of_the_run(tiny_data_dir, names, tmp_path):
    """Faults: a trial the run never used is added to its raw file; then one of the run's
    trials changes. Before: the identity was one digest per raw file, so the added trial
    refused the run's resume and evaluation ("its trials or their acc data changed") and a
    change named only the file. Now: the identity is one digest per trial of the run: the
    added trial changes nothing, the changed trial is named, a removed one too."""
    from embodied_tactile.data.cache import build_cache
    from embodied_tactile.run.provenance import data_changes, data_identity

    raw = _copy_trials(tiny_data_dir / "raw" / "soft_pressing.h5", tmp_path / "raw.h5", names[:3])
    run_trials = names[:3]

    def identity(trials=None):
        digests: dict = {}
        files = build_cache([raw], tmp_path / "cache", fields=("acc",), workers=1, trial_digests=digests)
        return data_identity(files, digests, trials)

    trained = identity(run_trials)
    assert sorted(trained["acc"]["trials"]) == sorted(run_trials)
    _copy_trials(tiny_data_dir / "raw" / "soft_pressing.h5", raw, [names[3]])  # a trial the run never used
    now = identity()
    assert now["acc"]["digests"] != trained["acc"]["digests"]  # the file's digest moved ...
    assert data_changes(trained, now) == []  # ... the run's trials did not
    with h5py.File(raw, "a") as f:  # one accelerometer sample of one of the run's trials
        f["trials"][names[1]]["tactile/acc"][0, 0, 0, 0] *= 0.5
    changed = data_changes(trained, identity())
    assert len(changed) == 1 and changed[0].startswith(f"trial {names[1]}: its acc data or attributes changed since training")
    assert str(raw) in changed[0]
    with h5py.File(raw, "a") as f:
        del f["trials"][names[2]]
    assert any(c.startswith(f"trial {names[2]}: not in the data now") for c in data_changes(trained, identity()))
    old = {"acc": {k: v for k, v in trained["acc"].items() if k != "trials"}}  # a run recorded per file
    assert data_changes(old, identity())[0].startswith(f"{raw}: its trials or their acc data changed")
