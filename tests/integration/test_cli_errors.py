"""Bad settings at the entry of train.py: one line naming key / path and value, exit 2, no
traceback, no run folder; a run that fails later is marked failed; the third-party message
filter (quiet.py) drops the known messages and keeps the project's own."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest


def train_here(tmp_path: Path, capsys, *overrides: str) -> subprocess.CompletedProcess:
    """``train.py debug=fast paths.log_dir=<tmp_path>/logs <overrides>`` by train.py's entry
    point (cli.train_main) in this process: its exit status and what it printed."""
    from embodied_tactile.cli import train_main

    flags = [o for o in overrides if o.startswith("-")]
    args = [*flags, "debug=fast", f"paths.log_dir={tmp_path / 'logs'}", *[o for o in overrides if not o.startswith("-")]]
    capsys.readouterr()
    code = train_main(args)
    out = capsys.readouterr()
    return subprocess.CompletedProcess(args, code, out.out, out.err)


def _one_line_exit_2(res: subprocess.CompletedProcess, *needles: str) -> str:
    assert res.returncode == 2, (res.returncode, res.stdout[-2000:], res.stderr[-3000:])
    err = res.stderr.strip()
    assert "Traceback" not in res.stderr + res.stdout
    assert len(err.splitlines()) == 1, err
    assert err.startswith("train.py: error: ")
    for n in needles:
        assert n in err, (n, err)
    return err


def test_typed_check_covers_the_optional_context_group(capsys):
    """model.context.* is None unless a recipe sets it: its keys are still checked by type,
    and a right value passes (it used to stop train.py with an AssertionError)."""
    from embodied_tactile.cli import check_typed_overrides

    check_typed_overrides(["recipe=context", "model.context.source=window", "model.context.refilter=true",
                           "model.net.y_start=fixed"])
    with pytest.raises(SystemExit) as info:
        check_typed_overrides(["model.context.initial_frames=many"])
    assert info.value.code == 2
    assert "model.context.initial_frames='many' (str): expected an integer" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize("override, needle", [
    ("targets=si", "callbacks.krr_alignment.targets='si' (str): expected one of design_rank, physical"),
    ("callbacks.krr_alignment.latent=w", "callbacks.krr_alignment.latent='w' (str): expected one of y, z, both"),
    ("callbacks.krr_alignment.points=0", "callbacks.krr_alignment.points=0 (int): expected an integer >= 1"),
])
def test_the_krr_callbacks_settings_are_refused_at_the_entry(tmp_path, capsys, override, needle):
    """The KRR callback takes its settings as train.py's entry checked them (its fields'
    metadata, run.config.AlignmentCallbackNode): a value it cannot use stops train.py there,
    before any folder is made."""
    _one_line_exit_2(train_here(tmp_path, capsys, override), needle)
    assert not (tmp_path / "logs").exists()


@pytest.mark.slow
@pytest.mark.parametrize("override, needles", [
    ("trainer.max_epochs=abc", ("trainer.max_epochs='abc'", "integer")),
    ("data.batch_size=0", ("data.batch_size=0", ">= 1")),
    ("model.optimizer.lr=fast", ("model.optimizer.lr='fast'", "number")),
    ("data.train_window=1", ("data.train_window=1", ">= 2")),
    ("modality=mutli_l", ("modality=mutli_l: no such option", "multi_l")),  # Hydra's own errors: exit 1 before
    ("trainer.max_epoch=3", ("trainer.max_epoch=3: no such key", "+trainer.max_epoch=")),
    ("threads=0", ("threads=0 (int): expected auto or an integer >= 1",)),  # a traceback and a folder before
])
def test_wrongly_typed_setting_names_key_and_value(tmp_path, capsys, restore_logging, override, needles):
    res = train_here(tmp_path, capsys, f"paths.data_dir={tmp_path / 'data'}", override)
    _one_line_exit_2(res, *needles)
    runs = tmp_path / "logs" / "train" / "runs"
    assert not (runs.exists() and any(runs.iterdir())), "a bad setting must not leave a run folder"


@pytest.mark.slow
def test_log_dir_that_cannot_be_created(tmp_path, capsys, restore_logging):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    res = train_here(tmp_path, capsys, f"paths.data_dir={tmp_path / 'data'}", f"paths.log_dir={blocker}/logs")
    _one_line_exit_2(res, f"paths.log_dir={blocker}/logs", "cannot create or write")


@pytest.mark.slow
def test_data_dir_that_is_a_file(tmp_path, capsys, restore_logging):
    blocker = tmp_path / "data.txt"
    blocker.write_text("not a folder")
    res = train_here(tmp_path, capsys, f"paths.data_dir={blocker}")
    _one_line_exit_2(res, f"paths.data_dir={blocker}", "not a folder")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_unwritable_data_dir(tmp_path, capsys, restore_logging):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        res = train_here(tmp_path, capsys, f"paths.data_dir={ro}")
    finally:
        ro.chmod(0o700)
    _one_line_exit_2(res, f"paths.data_dir={ro}")


@pytest.mark.slow  # a Hydra multirun of two jobs in this process (~16 s with the first Lightning import)
def test_swept_bad_value_fails_its_job_and_the_sweep_says_so(tmp_path, capsys, restore_logging):
    """A value swept with -m reaches only the job: train.py checks again there and marks the
    job folder failed; the other jobs still run, the sweep's table names each refused job
    with its reason, exit 1."""
    sweep = tmp_path / "multi"
    res = train_here(tmp_path, capsys, "-m", f"paths.data_dir={tmp_path / 'data'}", "trainer.max_epochs=abc",
                     f"hydra.sweep.dir={sweep}")
    _one_line_exit_2(res, "trainer.max_epochs='abc'")  # caught before the sweep starts
    res = train_here(tmp_path, capsys, "-m", f"paths.data_dir={tmp_path / 'data'}", "seed=x,y",
                     f"hydra.sweep.dir={sweep}")
    assert res.returncode == 1 and "Traceback" not in res.stderr
    assert "train.py: error: seed='x' (str): expected an integer" in res.stderr
    assert "train.py: error: seed='y' (str): expected an integer" in res.stderr  # the second job ran too
    rows = [ln.split(None, 2) for ln in res.stdout.splitlines() if ln.strip().startswith("seed=")]
    assert [(r[0], r[1]) for r in rows] == [("seed=x", "refused"), ("seed=y", "refused")]
    assert all("expected an integer" in r[2] for r in rows)
    job = json.loads((sweep / "seed=x" / "metrics.json").read_text())
    assert job["status"] == "failed" and "seed='x'" in job["error"]
    assert not (sweep / "seed=x" / "config_resolved.yaml").exists()


@pytest.mark.slow
def test_failed_run_is_marked_failed(tmp_path, capsys, restore_logging):
    res = train_here(tmp_path, capsys, f"paths.data_dir={tmp_path / 'data'}", "data=recorded",
                     f"data.raw_files=[{tmp_path / 'missing.h5'}]")
    assert res.returncode != 0
    (run,) = (tmp_path / "logs" / "train" / "runs").iterdir()
    m = json.loads((run / "metrics.json").read_text())
    assert m["status"] == "failed" and "missing.h5" in m["error"] and m["error_type"] == "FileNotFoundError"


def test_settings_spec_unit():
    from omegaconf import OmegaConf

    from embodied_tactile.options.checks import Spec
    from embodied_tactile.run.settings import SettingsError, check_train_config

    assert not Spec(("int",)).accepts(True)  # a bool is not an epoch count
    assert Spec(("float",), lo=0).accepts(3) and not Spec(("float",)).accepts(float("nan"))
    assert Spec(("int",), nullable=True).accepts(None) and not Spec(("int",)).accepts(None)
    pacing = Spec(("str",), choices=("fifo", "grid"))  # a closed set (options.checks.one_of)
    assert pacing.accepts("grid") and not pacing.accepts("burst") and pacing.describe() == "one of fifo, grid"
    check_train_config(OmegaConf.create({"trainer": {"max_epochs": 3}, "callbacks": None}))
    with pytest.raises(SettingsError, match=r"trainer.limit_val_batches=-1 \(int\): expected an integer or a number >= 0"):
        check_train_config(OmegaConf.create({"trainer": {"limit_val_batches": -1}}))
    # open bounds, and bounds between two keys, as the data module and the model enforce them
    assert Spec(("float",), lo=0, hi=1, hi_open=True).accepts(0.0) and not Spec(("float",), lo=0, hi=1, hi_open=True).accepts(1.0)
    for bad, match in [({"data": {"test_fraction": 0}}, r"data.test_fraction=0 \(int\): expected a number in \(0, 1\)"),
                       ({"data": {"test_fraction": 0.25, "val_fraction": 0.75}}, "test_fraction \+ val_fraction < 1"),
                       ({"model": {"net": {"obs_dropout": 1.0}}}, r"model.net.obs_dropout=1.0 .* in \[0, 1\)"),
                       ({"model": {"net": {"obs_sigma": 0.01, "obs_sigma_min": 0.01}}}, "obs_sigma > obs_sigma_min"),
                       ({"model": {"code_lr_scale": 0}}, r"model.code_lr_scale=0 .* > 0")]:
        with pytest.raises(SettingsError, match=match):
            check_train_config(OmegaConf.create(bad))
    check_train_config(OmegaConf.create({"data": {"test_fraction": 0.25, "val_fraction": 0.125, "train_window": 2}}))
    # the alignment's and the KRR callback's bounds are their options' too
    for bad, match in [({"alignment": {"time_bins": 0}}, r"alignment.time_bins=0 \(int\): expected an integer >= 1"),
                       ({"alignment": {"readout": "per_frame"}}, "alignment.readout='per_frame' .* one of per_time, final_segment"),
                       ({"alignment": {"groups": "objects"}}, "alignment.groups='objects' .* one of auto, sequence, object"),
                       ({"callbacks": {"krr_alignment": {"points": 0}}}, r"callbacks.krr_alignment.points=0 .* >= 1"),
                       ({"callbacks": {"krr_alignment": {"latent": "w"}}}, "callbacks.krr_alignment.latent='w' .* one of y, z, both"),
                       ({"callbacks": {"krr_alignment": {"every_n_epochs": "x"}}}, "an integer >= 0 or null"),
                       ({"seed": 1.5}, r"seed=1.5 \(float\): expected an integer"),
                       # the budget is the experiment's: trainer groups leave it ??? (~experiment)
                       ({"trainer": {"max_epochs": "???"}}, r"trainer.max_epochs has no value \(\?\?\? in its config\)")]:
        with pytest.raises(SettingsError, match=match):
            check_train_config(OmegaConf.create(bad))


def test_wrongly_typed_data_override_is_one_line(capsys):
    """data.* and alignment.* overrides are checked by their options' types as model.* are:
    one line, exit 2, before Hydra merges them; keys the options do not declare are Hydra's."""
    from embodied_tactile.cli import check_typed_overrides

    check_typed_overrides(["data=recorded", "data.raw_files=[a.h5]", "data.seq_len=null", "+data.extra=1",
                           "alignment.readout=final_segment"])
    for arg, line in [("data.batch_size=many", "data.batch_size='many' (str): expected an integer >= 1"),
                      ("data.seq_len=x", "data.seq_len='x' (str): expected an integer >= 1 or null"),
                      ("data.batch_size=4,x", "data.batch_size='x' (str): expected an integer >= 1"),
                      ("alignment.cv=x", "alignment.cv='x' (str): expected an integer >= 2")]:
        with pytest.raises(SystemExit) as info:
            check_typed_overrides([arg])
        assert info.value.code == 2
        err = capsys.readouterr().err.strip()
        assert err == f"train.py: error: {line}", err
    check_typed_overrides(["experiment=pendulum", "data=pendulum"])  # the scene with its own data: composes
    with pytest.raises(SystemExit) as info:
        check_typed_overrides(["data=pendulum"])  # without the scene: the tactile modality and model
    assert info.value.code == 2
    assert capsys.readouterr().err.strip().endswith("python train.py experiment=pendulum")


# ----------------------------------------------------------------------------- quiet.py
def test_known_third_party_warnings_are_silenced_project_warnings_kept():
    from embodied_tactile.run.quiet import silence_third_party

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        silence_third_party()
        warnings.warn("`isinstance(treespec, LeafSpec)` is deprecated, use `isinstance(treespec, TreeSpec) and "
                      "treespec.is_leaf()` instead.", FutureWarning)
        warnings.warn("n_jobs value -1 overridden to 1 by setting random_state. Use no seed for parallelism.",
                      UserWarning)
        warnings.warn("The 'train_dataloader' does not have many workers which may be a bottleneck.", UserWarning)
        warnings.warn("embodied_tactile: 3 trials skipped (bad FSR field)", UserWarning)
        warnings.warn("some other torch deprecation", FutureWarning)
    assert [str(w.message) for w in seen] == ["embodied_tactile: 3 trials skipped (bad FSR field)",
                                              "some other torch deprecation"]


def test_real_pytree_warning_is_silenced():
    """The filter matches Lightning's real message (not a copy that could drift); UMAP's is
    checked where the suite fits its one real UMAP (tests/unit/test_eval.py)."""
    from embodied_tactile.run.quiet import silence_third_party
    from lightning.pytorch.utilities._pytree import _tree_flatten

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        silence_third_party()
        _tree_flatten(1.0)  # builds torch's deprecated LeafSpec inside Lightning
    assert not [w for w in seen if "LeafSpec" in str(w.message)], [str(w.message) for w in seen]
    with warnings.catch_warnings(record=True) as unfiltered:  # the same call warns without the filters
        warnings.simplefilter("always")
        _tree_flatten(1.0)
    assert [w for w in unfiltered if "LeafSpec" in str(w.message)], [str(w.message) for w in unfiltered]


def test_litlogger_tip_dropped_other_lightning_info_kept(caplog):
    from embodied_tactile.run.quiet import silence_third_party
    from lightning.pytorch.utilities.rank_zero import rank_zero_info

    silence_third_party()
    with caplog.at_level(logging.INFO):
        rank_zero_info("💡 Tip: For seamless cloud logging and experiment tracking, try installing "
                       "[litlogger](https://pypi.org/project/litlogger/) to enable LitLogger")
        rank_zero_info("GPU available: False, used: False")
    text = caplog.text
    assert "litlogger" not in text and "GPU available" in text


@pytest.mark.slow  # train_py_run: the session's train.py subprocess
def test_default_train_run_prints_none_of_the_known_messages(train_py_run):
    res = train_py_run[1]
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    for noise in ("litlogger", "LeafSpec", "litmodels"):
        assert noise not in out, noise


@pytest.mark.slow
def test_hydra_command_exit_statuses(tmp_path, monkeypatch, capsys):
    """The one wrapper of the Hydra commands (record, palpate): run's status, a listed error
    as one line and 2, a bad override 2, ``--cfg job`` and ``--help`` 0."""
    from embodied_tactile.cli import hydra_command

    monkeypatch.chdir(tmp_path)
    seen = []

    def run(cfg):
        seen.append(cfg.port)
        if cfg.port == "bad":
            raise KeyError("no such thing")
        return 3

    main = hydra_command("record", run, "prog", errors=(KeyError,))

    def status(*argv):
        monkeypatch.setattr(sys, "argv", ["prog", f"hydra.run.dir={tmp_path / 'run'}", *argv])
        with pytest.raises(SystemExit) as exc:
            main()
        return exc.value.code

    assert status("port=loop://") == 3 and seen == ["loop://"]
    assert status("port=bad") == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == "prog: error: 'no such thing'"
    assert status("no_such_key=1") == 2
    assert status("--cfg", "job") == 0 and status("--help") == 0
    assert seen == ["loop://", "bad"]


@pytest.mark.parametrize("command", ["record", "palpate", "prepare"])
@pytest.mark.parametrize("override, needles", [
    ("modality=mutli_l", ("modality=mutli_l: no such",)),
    ("trainer.max_epoch=3", ("trainer.max_epoch=3: no such key", "+trainer.max_epoch=")),
])
def test_every_hydra_entry_refuses_a_mistyped_option_or_key_in_one_line(tmp_path, monkeypatch, capsys,
                                                                         restore_logging, command, override, needles):
    """Fault: a mistyped group option or key given to a Hydra command other than train
    (``embodied-tactile record|palpate|prepare``). Before: Hydra's several-line report (record,
    palpate) or its first line alone (prepare: "Could not override 'trainer.max_epoch'."). Now:
    train's check (run.overrides.check_composes) before Hydra runs: one line ``<command>: error: ...``
    naming the override, exit 2, nothing written in the working folder."""
    from embodied_tactile.__main__ import main

    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert main([command, override]) == 2
    out = capsys.readouterr()
    err = out.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"{command}: error: "), err
    for n in needles:
        assert n in err[0], (n, err)
    assert "Traceback" not in out.out + out.err and list(tmp_path.iterdir()) == []
