"""Which settings can work: the checks that stop train.py at the entry with one line naming
the key and the value.

:func:`check_train_config` checks the composed train config against its typed options, each
value by its field's type and bounds (:func:`embodied_tactile.options.checks.check_options`;
the bounds are the fields' metadata): train.yaml's own keys and the Lightning Trainer's
(:mod:`embodied_tactile.options.run`), the data, the model, the alignment and the KRR
callback's settings; :func:`check_paths` makes sure the data and log folders can be created
and written. Both raise :class:`SettingsError`; :class:`embodied_tactile.cli.EntryCallback`
runs them before Hydra creates the run folder and exits with status :data:`EXIT_BAD_SETTINGS`.
``train.py`` runs the check again per job (values swept with ``-m``).
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from embodied_tactile.options.alignment import AlignmentOptions
from embodied_tactile.options.checks import SettingsError, check_options
from embodied_tactile.options.data import DataOptions, PendulumOptions, scene_defaults, scene_values
from embodied_tactile.options.run import RunKeys, TrainerKeys
from embodied_tactile.run.config import AlignmentCallbackNode, ModelNode, PendulumNode

EXIT_BAD_SETTINGS = 2

#: (config node, its typed options); a node absent from a config (e.g. callbacks=none) is not checked
SECTIONS: tuple[tuple[str, type], ...] = (
    ("", RunKeys),
    ("trainer", TrainerKeys),
    ("data", DataOptions),
    ("model", ModelNode),
    ("alignment", AlignmentOptions),
    ("callbacks.krr_alignment", AlignmentCallbackNode),
)


class Exit(SystemExit):
    """SystemExit carrying its one-line message (a multirun job records it as its reason)."""

    def __init__(self, code: int, message: str = "") -> None:
        super().__init__(code)
        self.message = message


def fail(err: Exception, prog: str = "train.py") -> None:
    """The one line ``<prog>: error: <err>`` and exit status :data:`EXIT_BAD_SETTINGS`."""
    print(f"{prog}: error: {err}", file=sys.stderr)
    raise Exit(EXIT_BAD_SETTINGS, str(err))


def config_value(cfg: DictConfig, key: str) -> tuple[bool, Any]:
    """(present, value) with interpolations resolved where they can be (a value that only
    resolves inside a Hydra job, e.g. ``${hydra:...}``, is reported absent)."""
    node: Any = cfg
    for part in key.split("."):
        if not isinstance(node, DictConfig) or part not in node:
            return False, None
        try:
            node = node[part]
        except Exception:  # unresolvable outside the job
            return False, None
    if isinstance(node, DictConfig):
        return False, None
    if OmegaConf.is_config(node):
        node = OmegaConf.to_container(node, resolve=True)
    return True, node


def check_train_config(cfg: DictConfig) -> None:
    """Raise SettingsError for the first value of :data:`SECTIONS` of the wrong type or
    range (or that breaks a bound between two options), then for a population too large."""
    for key, options in SECTIONS:
        node = OmegaConf.select(cfg, key, default=None, throw_on_resolution_failure=False) if key else cfg
        if key == "data" and isinstance(node, DictConfig) and node.get("_target_") == PendulumNode._target_:
            options = PendulumOptions  # the pendulum scene's data (experiment=pendulum)
        if isinstance(node, DictConfig):
            check_options(options, node, key)
    _check_threads(cfg)
    _check_design(cfg)
    _check_population(cfg)
    _check_context_features(cfg)


def _check_context_features(cfg: DictConfig) -> None:
    """``model.context.physical`` > 0 reads the targets ``data.context_features`` serves:
    SettingsError naming both keys when the data would not serve them."""
    present, weight = config_value(cfg, "model.context.physical")
    if present and weight is not None and float(weight) > 0:
        served, features = config_value(cfg, "data.context_features")
        if not (served and features):
            raise SettingsError(f"model.context.physical={weight} needs data.context_features=true (the targets of the "
                                "physical term; configs/recipe/context_physical.yaml sets both)")


def _check_design(cfg: DictConfig) -> None:
    """A simulated scene of the catalogue's objects must be one the simulator can make and the
    split can honour: ``data.actions`` are distinct parameter sets of the action table, every
    object has at least two trials on the trial split, and the held-out share is the one asked
    for (the split caps it at all but one trial per object, and an object split must keep
    every factor level among its training objects). SettingsError naming the key otherwise."""
    present, source = config_value(cfg, "data.source")
    if not present or source != "simulated":
        return
    from embodied_tactile import constants as C

    scene = scene_defaults()

    def get(name: str) -> Any:
        present, value = config_value(cfg, f"data.{name}")
        return value if present else scene.get(name)

    actions = get("actions")
    if actions is not None:
        bad = [a for a in actions if not isinstance(a, int) or isinstance(a, bool) or not 0 <= a < C.N_ACTIONS]
        if bad or not actions:
            raise SettingsError(f"data.actions={actions}: parameter sets are integers 0..{C.N_ACTIONS - 1} of the "
                                "action table (null = all 16)" + (f"; {bad} are not" if bad else ""))
        if len(set(actions)) != len(actions):
            raise SettingsError(f"data.actions={actions}: a parameter set is named twice")
    objects = get("objects")
    if objects is not None and not (isinstance(objects, list) and all(isinstance(o, int) for o in objects)):
        return  # a population: its roles are fixed by sim.population
    split, test_fraction, val_fraction = get("split"), get("test_fraction"), get("val_fraction")
    if not isinstance(test_fraction, (int, float)) or not isinstance(val_fraction, (int, float)):
        return  # typed checks name these
    per_object = (C.N_ACTIONS if actions is None else len(actions)) * int(get("repetitions"))
    if split == "trial":
        if per_object < 2:
            raise SettingsError(f"data.actions={actions} x data.repetitions={get('repetitions')} give one trial per "
                                "object: the trial split holds out other touches of training objects and needs at "
                                "least two")
        if round(test_fraction * per_object) > per_object - 1:
            raise SettingsError(f"data.test_fraction={test_fraction}: with {per_object} trials per object an object "
                                f"would keep no training trial; at most {(per_object - 1) / per_object:.3g}")
    elif split == "object":
        from embodied_tactile.data.datamodule import split_trials  # lightning: only for an object split
        from embodied_tactile.data.prepare import catalogue_trials

        try:
            listed = [t for t in catalogue_trials(actions, 1) if objects is None or t.object_id in objects]
            train, _, _ = split_trials(listed, by="object", test_fraction=test_fraction,
                                       val_fraction=val_fraction, seed=int(get("split_seed") or 0))
        except ValueError as err:
            raise SettingsError(f"data.test_fraction={test_fraction}, data.val_fraction={val_fraction}: {err}") from None
        for k, name in enumerate(C.FACTOR_NAMES):
            levels = {round(t.factors[k], 6) for t in listed}
            kept = {round(t.factors[k], 6) for t in train}
            if levels - kept:
                raise SettingsError(f"data.test_fraction={test_fraction}, data.val_fraction={val_fraction}: the object "
                                    f"split leaves no training object with {name} = {sorted(levels - kept)}")


def _check_threads(cfg: DictConfig) -> None:
    """``threads``: ``auto`` (or null) or a ceiling >= 1 (:func:`~embodied_tactile.run.threads.thread_budget`)."""
    present, v = config_value(cfg, "threads")
    if not present or v is None or v == "auto":
        return
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise SettingsError(f"threads={v!r} ({type(v).__name__}): expected auto or an integer >= 1")


def _check_population(cfg: DictConfig) -> None:
    """A population scene larger than ``prepare.POPULATION_MAX_TRIALS`` trials needs
    ``data.allow_large_population=true``: SettingsError with its disk and time estimate."""
    present, objects = config_value(cfg, "data.objects")
    if not present or objects != "population":
        return
    from embodied_tactile import constants as C
    from embodied_tactile.data.prepare import check_population_size, fields_for_channels

    given = {}
    for name in scene_defaults():
        present, value = config_value(cfg, f"data.{name}")
        if present:
            given[name] = value
    scene = scene_values(given)  # a key the config does not hold: the data module's default

    def get(name: str) -> Any:
        return scene[name]

    actions = get("actions")
    try:
        check_population_size(int(get("n_objects")), int(get("n_val_objects")), int(get("n_test_objects")),
                              C.N_ACTIONS if actions is None else len(actions), int(get("repetitions")),
                              fields_for_channels(get("channels")), int(get("sim_workers")),
                              bool(get("allow_large_population")), int(get("n_unlabelled_objects")))
    except ValueError as err:
        raise SettingsError(str(err)) from None


def check_writable_dir(key: str, value: Any) -> Path:
    """Create the folder if needed and write a probe file of one block into it (synced: a
    full disk fails as a read-only folder does); SettingsError naming the key, the path and
    the OS reason otherwise."""
    if value is None or str(value) == "":
        raise SettingsError(f"{key} is empty: give a folder")
    p = Path(str(value)).expanduser()
    try:
        if p.exists() and not p.is_dir():
            raise SettingsError(f"{key}={value}: exists and is not a folder")
        p.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=p) as probe:  # a block written and synced: a full disk fails here
            probe.write(b"\0" * 4096)
            probe.flush()
            os.fsync(probe.fileno())
    except OSError as err:
        raise SettingsError(f"{key}={value}: cannot create or write this folder ({err.strerror or err})") from None
    return p


def check_paths(cfg: DictConfig, *, run_dir_key: str | None = None) -> None:
    """paths.data_dir, paths.log_dir (and the run / sweep folder's parent when given)."""
    for key in ("paths.data_dir", "paths.log_dir"):
        present, v = config_value(cfg, key)
        if present:
            check_writable_dir(key, v)
    if run_dir_key:
        present, v = config_value(cfg, run_dir_key)
        if present and v:
            check_writable_dir(run_dir_key, Path(str(v)).parent)


def check_sweep_folder(cfg: DictConfig) -> None:
    """A sweep folder holds one multirun: Hydra rewrites its ``multirun.yaml`` at every start,
    so a multirun whose overrides or sweep parameters differ from the ones recorded there would
    overwrite another part's record (and put its jobs beside that part's). SettingsError naming
    ``hydra.sweep.dir`` then; the same multirun again (a resume) passes, also from another machine
    whose ``paths.*`` differ (where the data and logs lie is not a setting of the runs; each job's
    data is checked against its own record when it resumes)."""
    present, folder = config_value(cfg, "hydra.sweep.dir")
    if not present or not folder or not (Path(str(folder)) / "multirun.yaml").is_file():
        return
    try:
        earlier = OmegaConf.load(Path(str(folder)) / "multirun.yaml")
    except Exception:  # noqa: BLE001 -- an unreadable record is not ours to judge: Hydra rewrites it
        return

    def what(c: DictConfig) -> tuple[list, Any]:
        task = OmegaConf.select(c, "hydra.overrides.task", default=[])
        params = OmegaConf.select(c, "hydra.sweeper.params", default=None)
        task = OmegaConf.to_container(task) if task is not None else []
        return (sorted(t for t in task if not str(t).lstrip("+~").startswith("paths.")),
                OmegaConf.to_container(params) if params is not None else None)

    (task0, params0), (task1, params1) = what(earlier), what(cfg)
    if task0 != task1 or params0 != params1:
        shown = " ".join(task0) if task0 != task1 else f"sweeper params {params0}"
        raise SettingsError(f"hydra.sweep.dir={folder}: holds another multirun ({shown}); give each part of a study "
                            f"a folder of its own (hydra.sweep.dir={folder}/<part>) and evaluate.py merges them")


__all__ = ["EXIT_BAD_SETTINGS", "Exit", "SECTIONS", "fail", "SettingsError", "check_sweep_folder", "check_train_config", "check_paths",
           "check_writable_dir"]
