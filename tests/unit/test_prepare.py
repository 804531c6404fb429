"""The data preparation stage (embodied_tactile.data.prepare, embodied-tactile prepare):
simulate, lock, build caches, list trials; the DataModule only splits and serves what it
prepared."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import pytest

from conftest import TINY_ACTIONS, TINY_OBJECTS, tiny_datamodule, tiny_scene

N_TINY = len(TINY_OBJECTS) * len(TINY_ACTIONS) * 2


def _prepare_cli(tmp_path, data_dir, *overrides):
    cmd = [sys.executable, "-m", "embodied_tactile.run.prepare_cli", f"paths.data_dir={data_dir}", "modality=acc",
           f"data.objects=[{','.join(map(str, TINY_OBJECTS))}]", f"data.actions=[{','.join(map(str, TINY_ACTIONS))}]",
           "data.repetitions=2", "data.sim_workers=1", "data.preprocess_workers=1", *overrides]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.slow  # a prepare CLI subprocess (the command's one; the tests below run its main in this process)
def test_cli_prepares_the_tiny_scene_and_a_second_call_is_a_cache_hit(tiny_data_dir, tmp_path, capsys):
    d = tmp_path / "data"
    shutil.copytree(tiny_data_dir / "raw", d / "raw")
    first = _prepare_cli(tmp_path, d)
    assert first.returncode == 0, first.stderr[-3000:]
    out = first.stdout
    assert f"trials: {N_TINY} usable, 0 skipped, 0 incomplete left out" in out, out
    assert "simulated: 0 new trial(s)" in out  # the copied raw file holds every trial
    built = dict(re.findall(r"^  (\w+): (\S+) \(built\)$", out, re.M))
    assert sorted(built) == ["acc", "actions"], out  # acc-only: no fsr cache
    assert all(os.path.exists(p) for p in built.values())
    from embodied_tactile.run import prepare_cli as prepare

    capsys.readouterr()
    assert prepare.main(_prepare_args(d)) == 0  # the second call: the command's main in this process
    second = capsys.readouterr().out
    assert f"trials: {N_TINY} usable, 0 skipped" in second
    hits = dict(re.findall(r"^  (\w+): (\S+) \(cache hit\)$", second, re.M))
    assert hits == built, second


@pytest.mark.slow
def test_cli_simulates_missing_trials_and_reports_skipped_ones(tiny_data_dir, tmp_path, capsys):
    """Trials absent from the raw file are simulated; a bad one is listed with its reason (the
    command's main in this process)."""
    import h5py

    from embodied_tactile.data import rawformat as rf
    from embodied_tactile.run import prepare_cli as prepare

    d = tmp_path / "data"
    shutil.copytree(tiny_data_dir / "raw", d / "raw")
    raw = d / "raw" / "soft_pressing.h5"
    good, _ = rf.scan_raw(raw, validate_data=False)
    names = sorted(g.name for g in good)
    with h5py.File(raw, "a") as f:
        del f["trials"][names[0]]  # missing: simulated again
        f["trials"][names[1]]["tactile/acc"][3, 0, 0, 0] = float("nan")  # bad: skipped, named
    capsys.readouterr()
    assert prepare.main(_prepare_args(d, "+data.preprocess.n_frames=30")) == 0
    out = capsys.readouterr().out
    assert "simulated: 1 new trial(s)" in out
    assert f"trials: {N_TINY - 1} usable, 1 skipped" in out
    assert re.search(rf"skipped \S*{raw.name} / {names[1]} \(\S+\): .*tactile/acc", out), out


def test_datamodule_after_the_stage_does_no_simulation(tiny_prepared, monkeypatch):
    """With the prepared scene attached, prepare_data / setup neither simulate nor build
    caches; without it, prepare_data runs the stage (so the patch below does bite)."""
    import embodied_tactile.data.cache as cache
    import embodied_tactile.sim as sim

    def fail(*a, **k):
        raise AssertionError("simulated / built a cache after the preparation stage")

    monkeypatch.setattr(sim, "generate_dataset", fail)
    monkeypatch.setattr(cache, "build_cache", fail)
    d = tiny_prepared.scene.data_dir
    dm = tiny_datamodule(d, ["acc"])
    dm.attach(tiny_prepared)
    dm.prepare_data()
    dm.setup()
    served = {t.name for s in (dm.train_set, dm.val_set, dm.test_set) for t in s.trials}
    assert served == {t.name for t in tiny_prepared.trials} and len(served) == N_TINY
    assert next(iter(dm.train_dataloader()))["obs"].shape[2] == 1
    assert dm.cache_files == tiny_prepared.cache_files
    with pytest.raises(AssertionError, match="after the preparation stage"):
        tiny_datamodule(d, ["acc"]).prepare_data()
    with pytest.raises(ValueError, match="not this DataModule's scene"):
        tiny_datamodule(d, ["acc", "fsr_t"]).attach(tiny_prepared)


def test_setup_without_prepare_data_finds_the_caches_and_never_simulates(tiny_prepared, monkeypatch):
    """A DDP rank whose rank 0 ran prepare_data: setup finds the caches, simulates nothing."""
    import embodied_tactile.sim as sim

    def fail(*a, **k):
        raise AssertionError("setup simulated")

    monkeypatch.setattr(sim, "generate_dataset", fail)
    dm = tiny_datamodule(tiny_prepared.scene.data_dir, ["acc"])
    dm.setup()
    assert dm.cache_files == tiny_prepared.cache_files and dm.prepared.cache_built == []
    assert len(dm.train_set) + len(dm.val_set) + len(dm.test_set) == N_TINY


def test_scene_from_a_data_config_ignores_split_and_loader_keys(tmp_path):
    from embodied_tactile.data.prepare import Scene

    scene = tiny_scene(tmp_path)
    cfg = {**{k: getattr(scene, k) for k in ("data_dir", "source", "skin", "primitive", "channels", "objects",
                                              "actions", "repetitions", "sim_workers", "preprocess_workers")},
           "_target_": "x", "split": "object", "batch_size": 3, "split_file": "s.json", "raw_files": None}
    assert Scene.from_config(cfg) == scene
    with pytest.raises(ValueError, match="unknown observation channel"):
        tiny_scene(tmp_path, channels=("gyro",))


def test_each_simulator_seed_has_its_own_raw_file(tmp_path):
    """The study varies the simulated dataset with the seed: one raw file per simulator seed,
    seed 0 keeping the plain name (trial names do not hold the seed)."""
    from embodied_tactile.data.prepare import Scene

    assert Scene.from_config(data_dir=str(tmp_path)).raw_paths == [tmp_path / "raw" / "soft_pressing.h5"]
    assert Scene.from_config(data_dir=str(tmp_path), skin="hard", primitive="sliding", sim_seed=2).raw_paths == [
        tmp_path / "raw" / "hard_sliding_sim2.h5"]


# ----------------------------------------------------------------------------- the entry point in this process
# (the first CLI test above starts it in a subprocess and is marked slow; these keep its logic in -m "not slow")
def _prepare_args(data_dir, *overrides):
    return [f"paths.data_dir={data_dir}", "modality=acc", f"data.objects=[{','.join(map(str, TINY_OBJECTS))}]",
            f"data.actions=[{','.join(map(str, TINY_ACTIONS))}]", "data.repetitions=2", "data.sim_workers=1",
            "data.preprocess_workers=1", *overrides]


@pytest.mark.slow
def test_main_in_process_lists_a_prepared_scene_as_cache_hits(tiny_data_dir, tmp_path, capsys):
    from embodied_tactile.run import prepare_cli as prepare

    d = tmp_path / "data"
    shutil.copytree(tiny_data_dir, d)  # raw file and caches of the tiny scene
    assert prepare.main(_prepare_args(d)) == 0
    out = capsys.readouterr().out
    assert f"trials: {N_TINY} usable, 0 skipped, 0 incomplete left out" in out, out
    assert "simulated: 0 new trial(s)" in out
    hits = dict(re.findall(r"^  (\w+): (\S+) \(cache hit\)$", out, re.M))
    assert sorted(hits) == ["acc", "actions"] and all(p.startswith(str(d)) for p in hits.values()), out
    assert prepare.main(["--help"]) == 0 and "embodied-tactile prepare" in capsys.readouterr().out


@pytest.mark.parametrize("override, needle", [("skin=bogus", "skin=bogus: no such option"), ("data=recorded", "raw_files")])
def test_main_in_process_bad_setting_is_one_line_exit_2(tmp_path, capsys, override, needle):
    from embodied_tactile.run import prepare_cli as prepare

    assert prepare.main(_prepare_args(tmp_path / "data", override)) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("prepare: error: ") and needle in err, err
    assert not (tmp_path / "data").exists()  # nothing prepared


def test_a_trial_whose_attributes_disagree_with_its_file_is_named_and_skipped(tiny_prepared, tmp_path, caplog):
    """Fault: one trial of the soft/pressing set says skin=hard. Before: dropped without a
    word, ``skipped`` empty. Now: a warning names the file, the trial and the attribute, and
    it is counted in ``skipped``; trials of a file that records another scene stay silent."""
    import logging
    import shutil

    import h5py

    from embodied_tactile.data.prepare import list_trials

    scene = tiny_prepared.scene
    caches = {}
    for fld, path in tiny_prepared.cache_files.items():
        caches[fld] = str(tmp_path / os.path.basename(path))
        shutil.copy(path, caches[fld])
    first = tiny_prepared.trials[0].name
    other = tmp_path / "hard_sliding.h5"  # the trials of another scene's file: not this scene's to name
    for path in caches.values():
        with h5py.File(path, "a") as f:
            f["trials"][first].attrs["skin"] = "hard"
            for name in list(f["trials"])[1:3]:
                if name != first:
                    f.copy(f["trials"][name], f["trials"], name=f"{name}_elsewhere")
                    g = f["trials"][f"{name}_elsewhere"]
                    g.attrs.update(skin="hard", primitive="sliding", source_file=str(other))
    with caplog.at_level(logging.WARNING):
        refs, skipped, _ = list_trials(scene, caches)
    assert first not in {r.name for r in refs} and len(refs) == len(tiny_prepared.trials) - 1
    assert [(s["trial"], s["field"]) for s in skipped] == [(first, "attrs/skin")]
    assert "disagree with its file" in skipped[0]["problem"]
    lines = [r.getMessage() for r in caplog.records if first in r.getMessage()]
    assert lines and "skin=hard primitive=pressing in a recording set of soft/pressing" in lines[0]
    assert not any("_elsewhere" in r.getMessage() for r in caplog.records)


@pytest.mark.slow  # preprocesses the tiny scene's three fields and simulates one trial
def test_keep_raw_false_deletes_the_raw_file_and_its_record_finds_the_caches(tiny_data_dir, tmp_path, caplog):
    """keep_raw=false: every field is cached, the raw file is deleted and a record beside it
    finds the caches again, for another modality too, with the same per-trial digests (a
    run's data identity) and nothing simulated; a scene the record does not cover simulates
    its raw file again; a recording cannot be deleted."""
    import json

    from embodied_tactile.data.prepare import dropped_record_path, prepare_scene
    from embodied_tactile.run.provenance import data_identity

    d = tmp_path / "data"
    shutil.copytree(tiny_data_dir / "raw", d / "raw")
    kept = prepare_scene(tiny_scene(d, channels=("acc",)))  # keep_raw: true, the default
    raw = d / "raw" / "soft_pressing.h5"
    size = raw.stat().st_size
    first = prepare_scene(tiny_scene(d, channels=("acc",), keep_raw=False))
    assert not raw.exists() and first.raw_dropped and len(first.trials) == N_TINY
    record = json.loads(dropped_record_path(raw).read_text())
    assert record["raw_bytes"] == size and len(record["trials"]) == N_TINY
    assert sorted(record["fields"]) == ["acc", "actions", "fsr"]  # every field, before the raw file went
    assert first.cache_files == kept.cache_files and sorted(first.cache_files) == ["acc", "actions"]
    assert first.trial_digests == kept.trial_digests
    for channels in (("acc",), ("fsr_t", "fsr_b")):  # the record finds them whatever keep_raw says now
        again = prepare_scene(tiny_scene(d, channels=channels))
        assert not raw.exists() and again.simulated == 0 and again.raw_dropped and len(again.trials) == N_TINY
    assert data_identity(again.cache_files, again.trial_digests)["fsr"]["trials"] == record["fields"]["fsr"]["trial_digests"]
    same = prepare_scene(tiny_scene(d, channels=("acc",)))
    assert data_identity(same.cache_files, same.trial_digests) == data_identity(kept.cache_files, kept.trial_digests)
    # a trial the record does not list: the raw file is simulated again (the record goes with it)
    caplog.set_level("WARNING")
    more = prepare_scene(tiny_scene(d, channels=("acc",), objects=[TINY_OBJECTS[0]], actions=[5], repetitions=1))
    assert more.simulated == 1 and raw.exists() and not dropped_record_path(raw).exists()
    assert "the scene asks for 1 trial(s) it does not list" in caplog.text
    with pytest.raises(ValueError, match="keep_raw=false needs the simulator"):
        tiny_scene(d, source="recorded", raw_files=[str(raw)], keep_raw=False)
