"""A bad design request (a parameter set that does not exist, one trial per object on the trial
split, a held-out share the split cannot honour, an object split that leaves a factor level
without training objects) stops train.py at the entry: one line naming the key, exit 2,
nothing written."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from conftest import REPO
from embodied_tactile.options.checks import SettingsError
from embodied_tactile.run.settings import check_train_config


def data(**kw):
    base = {"source": "simulated", "objects": None, "actions": [2, 6, 10, 14], "repetitions": 1, "split": "trial",
            "test_fraction": 0.25, "val_fraction": 0.125, "split_seed": 0}
    return OmegaConf.create({"data": {**base, **kw}})


@pytest.mark.parametrize("kw, needles", [
    ({"actions": [2, 16]}, ("data.actions=[2, 16]", "0..15", "[16]")),
    ({"actions": [-1]}, ("data.actions=[-1]",)),
    ({"actions": [3, 3]}, ("data.actions=[3, 3]", "twice")),
    ({"actions": []}, ("data.actions=[]",)),
    ({"actions": [6], "repetitions": 1}, ("data.actions=[6]", "data.repetitions=1", "one trial per object")),
    ({"test_fraction": 0.9, "val_fraction": 0.05}, ("data.test_fraction=0.9", "4 trials per object", "at most 0.75")),
    ({"split": "object", "test_fraction": 0.8, "val_fraction": 0.1}, ("data.test_fraction=0.8", "no training object")),
    ({"split": "object", "objects": [0, 8, 17, 27], "actions": [0, 5, 10]}, ("object split", "no training object")),
])
def test_a_design_the_split_or_the_simulator_cannot_honour_names_its_key(kw, needles):
    from embodied_tactile.run.settings import _check_design

    with pytest.raises(SettingsError) as info:
        _check_design(data(**kw))
    for n in needles:
        assert n in str(info.value), (n, str(info.value))


@pytest.mark.parametrize("kw", [
    {},                                                   # the default scene
    {"actions": None, "repetitions": 5},                  # the paper's design
    {"actions": None, "test_fraction": 0.9, "val_fraction": 0.05},  # 16 trials per object: 14 held out, 2 kept
    {"split": "object"},                                  # the held-out-objects protocol on the catalogue
    {"objects": "population", "split": "object", "actions": [6]},  # a population: roles fixed elsewhere
    {"source": "recorded", "actions": [6]},               # recordings: the trials that exist decide
])
def test_a_design_that_works_passes(kw):
    from embodied_tactile.run.settings import _check_design

    _check_design(data(**kw))


def test_the_check_runs_with_the_typed_checks_of_train_py():
    with pytest.raises(SettingsError, match=r"data.actions=\[16\]"):
        check_train_config(data(actions=[16]))


@pytest.mark.slow
def test_train_py_refuses_a_bad_design_in_one_line_and_writes_nothing(tmp_path):
    """train.py's entry point in this process, started in tmp_path."""
    from conftest import train_in_process

    res = train_in_process("debug=fast", "data.actions=[0,5,16]", f"paths.log_dir={tmp_path / 'logs'}",
                           f"paths.data_dir={tmp_path / 'data'}", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert res.returncode == 2, res.stderr[-2000:]
    assert res.stderr.strip().splitlines() == [
        "train.py: error: data.actions=[0, 5, 16]: parameter sets are integers 0..15 of the action table "
        "(null = all 16); [16] are not"]
    assert not (tmp_path / "run").exists() and not any((tmp_path / "data").rglob("*.h5"))


def _multirun(task: list[str], params: dict | None) -> "OmegaConf":
    return OmegaConf.create({"hydra": {"overrides": {"task": task}, "sweeper": {"params": params}}})


def test_a_study_part_into_another_parts_sweep_folder_is_refused_and_a_resume_passes(tmp_path):
    from embodied_tactile.run.settings import check_sweep_folder

    folder = tmp_path / "study"
    part = _multirun(["primitive=pressing", "seed=0,1,2"], {"combo": "acc_soft,multi_l_soft"})
    check_sweep_folder(OmegaConf.merge(part, {"hydra": {"sweep": {"dir": str(folder)}}}))  # no record yet
    folder.mkdir()
    OmegaConf.save(part, folder / "multirun.yaml")
    before = (folder / "multirun.yaml").read_bytes()
    same = OmegaConf.merge(part, {"hydra": {"sweep": {"dir": str(folder)}}})
    check_sweep_folder(same)  # the same multirun again: a resume
    moved = OmegaConf.merge(_multirun(["primitive=pressing", "seed=0,1,2", "paths.data_dir=/elsewhere/data"],
                                      {"combo": "acc_soft,multi_l_soft"}), {"hydra": {"sweep": {"dir": str(folder)}}})
    check_sweep_folder(moved)  # a resume on another machine, whose data lie elsewhere
    other = OmegaConf.merge(_multirun(["primitive=sliding", "seed=0,1,2"], {"combo": "acc_soft,multi_l_soft"}),
                            {"hydra": {"sweep": {"dir": str(folder)}}})
    with pytest.raises(SettingsError, match=r"hydra.sweep.dir=.*study: holds another multirun \(primitive=pressing"):
        check_sweep_folder(other)
    wider = OmegaConf.merge(_multirun(["primitive=pressing", "seed=0,1,2"], {"combo": "acc_soft"}),
                            {"hydra": {"sweep": {"dir": str(folder)}}})
    with pytest.raises(SettingsError, match="sweeper params"):
        check_sweep_folder(wider)
    assert (folder / "multirun.yaml").read_bytes() == before


def test_the_paper_design_scene_has_the_papers_trials_and_holds_out_a_quarter(tmp_path):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from embodied_tactile.data.datamodule import split_trials
    from embodied_tactile.data.prepare import catalogue_trials

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["experiment=paper_design", f"paths.log_dir={tmp_path}"])
    d = cfg.data
    assert d.actions is None and d.repetitions == 5 and d.test_fraction == 0.25 and d.keep_raw is False
    assert (d.batch_size, d.train_window, d.windows_per_epoch, cfg.trainer.max_epochs) == (16, 50, 480, 32)
    trials = catalogue_trials(None, d.repetitions)
    train, val, test = split_trials(trials, test_fraction=d.test_fraction, val_fraction=d.val_fraction)
    assert (len(trials), len(test)) == (2560, 640)
    held = {(t.object_id, t.action_index) for t in test}
    assert len({t.object_id for t in test}) == 32 and len({t.action_index for t in test}) == 16
    assert {(t.object_id, t.action_index) for t in train} | held >= held
