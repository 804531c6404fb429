"""The typed part of the Hydra configuration: the Latent Filter's options
(:mod:`embodied_tactile.model.options`) as structured configs, and the one resolver.

Registered on import (idempotent), so that every entry point that composes ``configs/``
(train.py, evaluate.py, ``python -m embodied_tactile.run.prepare_cli``, the tests) imports this
module first:

* ``model: schema`` (:class:`ModelNode`): the LightningModule's options
  (:class:`~embodied_tactile.model.options.ModuleOptions`), the network ``net``
  (:class:`~embodied_tactile.model.options.LatentFilterOptions` with ``_target_`` and
  ``modality``), the optimizer (Adam as a partial with the learning rate of
  :class:`~embodied_tactile.model.options.OptimizerOptions`) and the context objective's
  options (:class:`~embodied_tactile.model.options.ContextOptions`, null unless a recipe
  sets them). configs/model/latent_filter.yaml composes it and names only what depends on
  the scene.
* ``data: schema`` (:class:`DataNode`): the data's scene, split and loader options
  (:mod:`embodied_tactile.options.data`), flat; configs/data/*.yaml compose it.
* ``data: pendulum_schema`` (:class:`PendulumNode`): the pendulum scene's data
  (:class:`~embodied_tactile.options.data.PendulumOptions`); configs/data/pendulum.yaml composes it.
* ``alignment: schema`` (:class:`~embodied_tactile.options.alignment.AlignmentOptions`): the
  latent -> factor read-out, shared by the training's final alignment and evaluate.py.
* ``callbacks/krr_alignment: schema`` (:class:`AlignmentCallbackNode`): the KRR callback's
  own settings (:class:`~embodied_tactile.options.alignment.AlignmentCheckOptions`);
  configs/callbacks/default.yaml composes it.
* ``emulate_schema`` / ``report_schema``: the whole config of ``embodied-tactile emulate``
  (:class:`~embodied_tactile.options.emulation.EmulationOptions`) and ``report``
  (:class:`~embodied_tactile.options.report.ReportOptions`); configs/emulate.yaml and
  configs/report.yaml compose them.
* ``${prior_rows:objects,n_test,n_val,n_train}``: rows of the prior's object-code table.

:func:`compose` is the one way the package composes ``configs/`` itself (outside an entry point).
"""

from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Any, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, OmegaConf

from embodied_tactile.options.alignment import TARGET_ENCODINGS, AlignmentCheckOptions, AlignmentOptions
from embodied_tactile.options.checks import one_of
from embodied_tactile.options.data import DataOptions, PendulumOptions
from embodied_tactile.options.emulation import EmulationOptions
from embodied_tactile.options.report import ReportOptions
from embodied_tactile.model.options import ContextOptions, LatentFilterOptions, ModuleOptions, OptimizerOptions
from embodied_tactile.paths import config_dir


@dataclass
class LatentFilterNode(LatentFilterOptions):
    """``model.net``: what Hydra instantiates into a :class:`~embodied_tactile.model.LatentFilter`."""

    _target_: str = "embodied_tactile.model.latent_filter.LatentFilter"
    modality: Any = MISSING


@dataclass
class OptimizerNode:
    """``model.optimizer``: ``torch.optim.<name>(params, lr=...)`` built by the module."""

    _target_: str = f"torch.optim.{OptimizerOptions.name}"
    _partial_: bool = True
    lr: float = field(default=OptimizerOptions.lr,
                      metadata=next(f.metadata for f in fields(OptimizerOptions) if f.name == "lr"))


@dataclass
class ModelNode(ModuleOptions):
    """``model``: the LightningModule (:class:`~embodied_tactile.model.module.LatentFilterModule`)."""

    _target_: str = MISSING
    net: LatentFilterNode = field(default_factory=LatentFilterNode)
    annealing: Any = MISSING
    optimizer: OptimizerNode = field(default_factory=OptimizerNode)
    context: Optional[ContextOptions] = None


@dataclass
class DataNode(DataOptions):
    """``data``: what Hydra instantiates into a :class:`~embodied_tactile.data.datamodule.TactileDataModule`
    (its flat keys sorted into scene, split and loader by ``from_config``)."""

    _target_: str = "embodied_tactile.data.datamodule.TactileDataModule.from_config"


@dataclass
class PendulumNode(PendulumOptions):
    """``data`` of the pendulum scene (configs/data/pendulum.yaml): what Hydra instantiates
    into a :class:`~embodied_tactile.data.pendulum_module.PendulumDataModule`."""

    _target_: str = "embodied_tactile.data.pendulum_module.PendulumDataModule"


@dataclass
class AlignmentCallbackNode(AlignmentCheckOptions):
    """``callbacks.krr_alignment``: what Hydra instantiates into a
    :class:`~embodied_tactile.eval.callback.KRRAlignmentCallback`, with the run's ``alignment``
    (its final alignment is the run's number) and ``targets``."""

    _target_: str = "embodied_tactile.eval.callback.KRRAlignmentCallback"
    alignment: Any = "${alignment}"
    targets: str = field(default="${targets}", metadata=one_of(*TARGET_ENCODINGS))


def prior_rows(objects: Any, n_test: int, n_val: int, n_train: int) -> int:
    """Rows of the prior's object-code table for a scene (``${prior_rows:...}`` in
    configs/model/latent_filter.yaml): the catalogue's 32, or every population id."""
    from embodied_tactile.constants import N_OBJECTS, POPULATION_ID_BASE

    if objects == "population":
        return POPULATION_ID_BASE + int(n_test) + int(n_val) + int(n_train)
    return N_OBJECTS


#: longest folder name made from overrides (file systems allow 255 bytes)
MAX_DIRNAME = 200


def folder_name(text: Any) -> str:
    """One folder name from a text such as Hydra's ``override_dirname``
    (``${folder_name:...}`` in configs/train.yaml): never a path separator (``%`` -> ``%25``,
    ``/`` -> ``%2F``, the OS's own separators likewise), never ``.`` / ``..``, and at most
    :data:`MAX_DIRNAME` bytes (longer: cut, with a digest of the whole so names stay unique)."""
    import hashlib
    import os

    name = str(text).replace("%", "%25").replace("/", "%2F")
    for sep in {os.sep, os.altsep} - {None, "/"}:
        name = name.replace(sep, "%" + format(ord(sep), "02X"))
    if name in ("", ".", ".."):
        name = name.replace(".", "%2E") or "_"
    if len(name.encode()) > MAX_DIRNAME:
        digest = hashlib.sha1(name.encode()).hexdigest()[:12]
        name = name.encode()[: MAX_DIRNAME - 13].decode(errors="ignore") + "-" + digest
    return name


def register() -> None:
    """Store the structured configs and the resolvers (a second call changes nothing)."""
    cs = ConfigStore.instance()
    cs.store(group="model", name="schema", node=ModelNode)
    cs.store(group="alignment", name="schema", node=AlignmentOptions)
    cs.store(group="data", name="schema", node=DataNode)
    cs.store(group="data", name="pendulum_schema", node=PendulumNode)
    cs.store(group="callbacks/krr_alignment", name="schema", node=AlignmentCallbackNode)
    cs.store(name="emulate_schema", node=EmulationOptions)
    cs.store(name="report_schema", node=ReportOptions)
    if not OmegaConf.has_resolver("prior_rows"):
        OmegaConf.register_new_resolver("prior_rows", prior_rows)
    if not OmegaConf.has_resolver("folder_name"):
        OmegaConf.register_new_resolver("folder_name", folder_name)


register()


def compose(overrides: Sequence[str] = (), config_name: str = "train", return_hydra_config: bool = False) -> Any:
    """``configs/<config_name>.yaml`` composed with ``overrides`` as its entry point composes
    it, in this process whether or not a Hydra app runs in it (``embodied-tactile report``,
    a test): Hydra's global state is set aside while composing and put back after."""
    from hydra import compose as hydra_compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.singleton import Singleton

    outer = Singleton._instances.pop(GlobalHydra, None)
    try:
        with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
            return hydra_compose(config_name=config_name, overrides=list(overrides),
                                 return_hydra_config=return_hydra_config)
    finally:
        Singleton._instances.pop(GlobalHydra, None)
        if outer is not None:
            Singleton._instances[GlobalHydra] = outer


__all__ = ["AlignmentCallbackNode", "DataNode", "PendulumNode", "LatentFilterNode", "ModelNode", "OptimizerNode", "compose", "config_dir", "folder_name", "prior_rows", "register"]
