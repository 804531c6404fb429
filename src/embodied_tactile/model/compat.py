"""What lets configs and checkpoints of earlier versions load, in one place, out of the
model's hot path: options that were measured, rejected and removed; the values of options a
saved config did not name; the parameter names of the layout before the fusion code moved
into :mod:`.fusion`; the LightningModule classes and module paths that saved configs name.
Plain Python: no torch."""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
from typing import Any, Mapping

#: options that were measured, rejected and removed (docs/reference/model.md, "Removed options"),
#: with the value that meant "off": a saved config holding the off value still loads
REMOVED_OPTIONS = {"obs_dropout_span": 1, "elbo_samples": 1, "overshoot": 1, "overshoot_weight": None,
                   "free_bits_z": 0.0, "free_bits_y": 0.0, "y_input": "sample", "y_static": False,
                   "transition_form": "mlp", "obs_sigma_shape": "channel"}

#: the values a saved config that does not name an option was trained with (the option did
#: not exist, or was not saved, when that config was written): today's defaults differ
UNSAVED_OPTIONS = {"input_standardize": False, "y_update": "direct", "y_evidence_max": None,
                   "y_evidence_range": None, "obs_dropout": 0.0}
UNSAVED_PRIOR_OPTIONS = {"labels": True}
#: the LightningModule's options that a checkpoint's hyper-parameters do not name, with the
#: value it was trained with (written before the option existed): today's default differs
UNSAVED_MODULE_OPTIONS = {"weight_average": None}
#: context-objective options that were measured, rejected and removed, with their off value
#: (random_length: docs/experiments/context_objective.md; filter_weight:
#: docs/experiments/population_budget.md)
REMOVED_CONTEXT_OPTIONS = {"random_length": False, "filter_weight": 0.0}


def upgrade_net_config(config: Mapping[str, Any]) -> dict[str, Any]:
    """A saved network config (a checkpoint's ``net``) as today's constructor arguments: a
    removed option (:data:`REMOVED_OPTIONS`) at its off value is dropped, any other value of
    it is a ValueError that names it; an option the config does not name takes the value
    networks were trained with before it was saved (:data:`UNSAVED_OPTIONS`), not today's
    default."""
    config = {**UNSAVED_OPTIONS, **config, "prior": {**UNSAVED_PRIOR_OPTIONS, **(config.get("prior") or {})}}
    return _drop_removed(config, REMOVED_OPTIONS, "docs/reference/model.md, 'Removed options'")


def upgrade_context_config(context: Mapping[str, Any]) -> dict[str, Any]:
    """A saved context-objective config (a checkpoint's ``context``) as today's options: a
    removed option (:data:`REMOVED_CONTEXT_OPTIONS`) at its off value is dropped, any other
    value of it is a ValueError that names it."""
    return _drop_removed(dict(context), REMOVED_CONTEXT_OPTIONS,
                         "docs/experiments/context_objective.md, docs/experiments/population_budget.md")


def _drop_removed(config: dict[str, Any], removed: Mapping[str, Any], where: str) -> dict[str, Any]:
    for name, off in removed.items():
        if name in config:
            value = config.pop(name)
            if off is not None and value != off:
                raise ValueError(f"this network was trained with {name}={value!r}, an option that was measured, "
                                 f"rejected and removed ({where}); only {off!r} loads")
    return config


def upgrade_state_dict(state: Mapping[str, Any], late: bool) -> dict[str, Any]:
    """Checkpoints written before the fusion code moved into :mod:`.fusion` (commit 3c3e49b)
    hold the same weights under ``model.encoders.<pathway>.*`` / ``model.decoders.<pathway>.*``;
    they are renamed to this layout (``model.observation.encoder.*`` for early fusion,
    ``model.observation.encoders.<pathway>.*`` for late fusion). Any other key is kept."""

    def rename(key: str) -> str:
        for part in ("encoders", "decoders"):
            prefix = f"model.{part}."
            if key.startswith(prefix):
                pathway, rest = key[len(prefix):].split(".", 1)
                return f"model.observation.{part}.{pathway}.{rest}" if late else f"model.observation.{part[:-1]}.{rest}"
        return key

    return {rename(k): v for k, v in state.items()}


#: LightningModule classes of earlier versions -> today's (the fusion-specific subclasses
#: differed only in the observation model they accepted, which the modality decides)
RENAMED_CLASSES = {"EarlyFusionLatentFilter": "LatentFilterModule", "LateFusionLatentFilter": "LatentFilterModule"}

#: module paths that saved configs (``_target_`` of the model, its network, annealing schedule
#: and logger) and checkpoints of the earlier layout name -> where that code is now; a
#: submodule follows its package (``embodied_tactile.models.module`` -> ``embodied_tactile.model.module``).
#: The run plumbing's ``runtime`` module was split by concern; of it, saved configs name only the
#: CSV logger (``logger._target_``), now in ``run.resume``
MOVED_MODULES = {"embodied_tactile.models": "embodied_tactile.model",
                 "embodied_tactile.runtime": "embodied_tactile.run.resume",
                 "embodied_tactile.run.runtime": "embodied_tactile.run.resume"}


def moved_to(name: str) -> str | None:
    """Today's path of a module that :data:`MOVED_MODULES` moved, or None."""
    for old, new in MOVED_MODULES.items():
        if name == old or name.startswith(old + "."):
            return new + name[len(old):]
    return None


#: config keys that saved configs hold and today's configs no longer write (the modality
#: named its LightningModule before one class served every modality)
DROPPED_CONFIG_KEYS = ("modality.module", "model.net.modality.module", "model.context.filter_weight")


#: config keys that today's configs write and earlier saved configs lack, with the value
#: those runs had (the typed data options made ``pin_memory`` a key of ``data``; the windows
#: and the weight average are options added after the first runs, whose defaults are now the
#: default scene's)
ADDED_CONFIG_KEYS = {"data.pin_memory": False, "data.train_window": None, "data.windows_per_trial": 1,
                     "data.windows_per_epoch": None, "model.weight_average": None}

#: ``_target_`` strings that saved configs hold -> today's (the DataModule is built from its
#: flat config keys by ``from_config``, its constructor taking the grouped options)
RETARGETED = {"embodied_tactile.data.datamodule.TactileDataModule":
              "embodied_tactile.data.datamodule.TactileDataModule.from_config"}


def current_target(target: str) -> str:
    """Today's spelling of a saved ``_target_`` (``embodied_tactile.models.module.
    LateFusionLatentFilter`` -> ``embodied_tactile.model.module.LatentFilterModule``); any
    other string unchanged. For comparing a saved config with today's."""
    if target in RETARGETED:
        return RETARGETED[target]
    module, _, name = target.rpartition(".")
    new = moved_to(module)
    if new is None:
        return target
    if new == "embodied_tactile.model.module":
        name = RENAMED_CLASSES.get(name, name)
    return f"{new}.{name}"


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports a moved module under its old path as the same module object, so that
    ``hydra.utils.get_class`` / ``instantiate`` of an old ``_target_`` and unpickling an old
    checkpoint find today's classes."""

    def find_spec(self, name, path=None, target=None):
        new = moved_to(name)
        if new is None:
            return None
        return importlib.util.spec_from_loader(name, self, is_package=hasattr(importlib.import_module(new), "__path__"))

    def create_module(self, spec):
        module = importlib.import_module(moved_to(spec.name))
        spec.loader_state = module.__spec__
        return module

    def exec_module(self, module):
        module.__spec__ = module.__spec__.loader_state  # the import system set the old path's spec


def install_moved_modules() -> None:
    """Lets the old paths of :data:`MOVED_MODULES` import (once per interpreter)."""
    if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
        sys.meta_path.insert(0, _MovedModules())  # before the path finder, which would load a second copy
