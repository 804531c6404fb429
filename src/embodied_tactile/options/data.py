"""The data's options, typed, with their one default each (no heavy imports, so the typed
configs can register them): what scene is prepared, how it is split, how it is served.

``configs/data/*.yaml`` keeps them flat (``data.batch_size``, ``data.split``, ``data.skin``):
:class:`DataOptions` is the three groups in one node, which
:meth:`TactileDataModule.from_config <embodied_tactile.data.datamodule.TactileDataModule.from_config>`
sorts back into the groups :class:`~embodied_tactile.data.datamodule.TactileDataModule` takes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any, ClassVar, Dict, List, Mapping, Optional, get_args, get_type_hints

from .checks import Rule, at_least, bounds
from .simulation import SimulationOptions


@dataclass
class SceneOptions:
    """What to prepare (:class:`embodied_tactile.data.prepare.Scene`): the keys that decide
    which trials exist and how they are preprocessed (bounds: the fields' metadata,
    :mod:`embodied_tactile.options.checks`)."""

    data_dir: str = "data"
    source: str = "simulated"             # simulated (the built-in simulator) | recorded (raw_files)
    raw_files: Optional[List[str]] = None  # recorded: paths or glob patterns
    skin: str = "soft"
    primitive: str = "pressing"
    channels: List[str] = field(default_factory=lambda: ["acc", "fsr_t", "fsr_b"])
    objects: Any = None                   # null = all 32 wave objects; a list of ids; population (docs/reference/simulator.md)
    n_objects: int = field(default=256, metadata=at_least(1))  # population: training objects (validation and test objects come on top)
    n_val_objects: int = field(default=32, metadata=at_least(1))  # population: validation objects (checkpoint selection)
    n_test_objects: int = field(default=64, metadata=at_least(1))  # population: test objects (evaluation only)
    population_seed: int = field(default=0, metadata=at_least(0))  # population: which objects are drawn
    n_unlabelled_objects: int = field(default=0, metadata=at_least(0))  # population: objects after the training objects, trained on without property labels (NaN factors)
    actions: Optional[List[int]] = None   # null = all 16 parameter sets (the default scene: 512 trials, 128 held out); a list of indices of the action table
    repetitions: int = field(default=SimulationOptions.repetitions, metadata=at_least(1))
    sim_seed: int = SimulationOptions.seed
    sim_workers: int = field(default=SimulationOptions.workers, metadata=at_least(1))
    preprocess: Dict[str, Any] = field(default_factory=dict)  # PreprocessConfig overrides (docs/reference/preprocessing.md)
    preprocess_workers: int = field(default=2, metadata=at_least(1))
    strict: bool = False                  # true: a bad raw trial is fatal instead of skipped
    include_incomplete: bool = False      # true: also use interrupted recordings (complete=False)
    allow_large_population: bool = False  # true: prepare a population of more than 10,000 trials
    keep_raw: bool = True                 # simulated: false deletes the raw file once every field is cached (a record beside it finds the caches; regenerated from the seed when needed)


@dataclass
class SplitOptions:
    """How the prepared trials are split (:func:`embodied_tactile.data.datamodule.split_trials`)."""

    split: str = "trial"          # trial: the paper's split (recognition) | object: train / validation / test objects disjoint
    test_fraction: float = field(default=0.25, metadata=bounds(0, 1, lo_open=True, hi_open=True))  # held-out test share (of trials; of objects for split=object): evaluation only
    val_fraction: float = field(default=0.125, metadata=bounds(0, 1, hi_open=True))  # validation share (from training objects; of objects for split=object)
    split_seed: int = 0
    split_file: Optional[str] = None  # where the split is saved (JSON); reused if it exists and matches

    RULES: ClassVar[tuple[Rule, ...]] = (
        ("test_fraction", "val_fraction", lambda t, v: t + v < 1, "test_fraction + val_fraction < 1"),)


@dataclass
class LoaderOptions:
    """How the split is served. The defaults are the CPU budget of ``python train.py``: each
    epoch 480 random 50-frame windows (1.7 s, one pressing cycle) drawn over the training
    trials, in batches of 16: 30 optimiser steps an epoch whatever the number of trials
    (docs/experiments/default_budget.md, docs/experiments/variance_components.md); held-out
    data and the KRR alignment always use whole trials. ``experiment=paper``: batch 48, whole
    trials."""

    batch_size: int = field(default=16, metadata=at_least(1))
    num_workers: int = field(default=0, metadata=at_least(0))
    seq_len: Optional[int] = field(default=None, metadata=at_least(1))  # null = the full trial
    train_window: Optional[int] = field(default=50, metadata=at_least(2))  # training crops of this many frames (null = whole trials; >= 2: the recursion needs a transition)
    windows_per_trial: Optional[int] = field(default=None, metadata=at_least(1))  # random crops per training trial and epoch (instead of windows_per_epoch, then null)
    windows_per_epoch: Optional[int] = field(default=480, metadata=at_least(1))  # random crops per epoch, drawn over the training trials
    context: Optional[str] = None            # the context objective's pairing: null | trial | window
    context_touches: int = 1                 # context=trial: other trials of the object per context
    context_features: bool = False           # serve target_features, the target crop's standardised hand-crafted features (model.context.physical)
    pin_memory: bool = False


@dataclass
class DataOptions(LoaderOptions, SplitOptions, SceneOptions):
    """``data``: the three groups flat, as ``configs/data/*.yaml`` and saved run configs hold them."""


@dataclass
class PendulumOptions:
    """``data`` of the pendulum scene (``data=pendulum``,
    :class:`~embodied_tactile.data.pendulum_module.PendulumDataModule`): the sequences
    :func:`embodied_tactile.data.pendulum.generate` draws for it. Training: ``n_train``
    sequences per system of the 8 training systems (data seed ``seed``); validation (the
    checkpoints' ELBO): ``n_val`` per system (``seed + 3000``); test (the KRR read-out):
    ``n_test`` per system (``seed + 1000``); unseen systems (``UNSEEN_SYSTEMS``, a second
    held-out set): ``n_test`` per system (``seed + 2000``)."""

    seed: int = field(default=0, metadata=at_least(0))
    channels: List[str] = field(default_factory=lambda: ["fsr_t"])  # the modality's one image channel (a label)
    n_train: int = field(default=128, metadata=at_least(1))  # training sequences per system
    n_val: int = field(default=2, metadata=at_least(1))      # validation sequences per system
    n_test: int = field(default=8, metadata=at_least(1))     # held-out sequences per system (and per unseen system)
    n_steps: int = field(default=60, metadata=at_least(2))   # frames per sequence (50 ms each)
    batch_size: int = field(default=16, metadata=at_least(1))
    context: Optional[str] = None  # the context objective's pairing: null | trial (another sequence of the system)


GROUPS = (SceneOptions, SplitOptions, LoaderOptions)


def group_options(flat: Mapping[str, Any]) -> tuple[SceneOptions, SplitOptions, LoaderOptions]:
    """Flat data keys (a ``data`` config; ``_target_`` ignored) -> the three groups, each
    key's default where ``flat`` is silent; TypeError naming an unknown key."""
    given = {k: v for k, v in flat.items() if k != "_target_"}
    names = [{f.name for f in fields(cls)} for cls in GROUPS]
    unknown = sorted(set(given) - set().union(*names))
    if unknown:
        raise TypeError(f"unknown data option(s) {unknown}")
    return tuple(cls(**{k: v for k, v in given.items() if k in n}) for cls, n in zip(GROUPS, names))  # type: ignore[return-value]


def scene_defaults() -> dict[str, Any]:
    """:class:`SceneOptions`'s defaults as a dict."""
    return asdict(SceneOptions())


#: scene options whose null is a value of its own (raw_files: none; objects: all 32; actions: all 16)
NULLABLE_SCENE_KEYS = frozenset(name for name, hint in get_type_hints(SceneOptions).items()
                                if type(None) in get_args(hint))


def scene_values(given: Mapping[str, Any]) -> dict[str, Any]:
    """The :class:`SceneOptions` keys of a data config: the default where ``given`` is silent,
    or null for an option whose null means nothing (:data:`NULLABLE_SCENE_KEYS` keep theirs)."""
    return {k: given[k] if k in given and (given[k] is not None or k in NULLABLE_SCENE_KEYS) else v
            for k, v in scene_defaults().items()}


__all__ = ["DataOptions", "GROUPS", "LoaderOptions", "PendulumOptions", "SceneOptions", "SplitOptions", "NULLABLE_SCENE_KEYS", "group_options", "scene_defaults",
           "scene_values"]
