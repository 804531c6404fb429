"""The Latent Filter's and its training module's options, typed, with their defaults: the
one place each default is written, with its bounds (field metadata and ``RULES``, which
:func:`embodied_tactile.options.checks.check_options` reads at train.py's entry).

:class:`~.latent_filter.LatentFilter`, :class:`~.networks.HierarchicalPrior` and
:class:`~.module.LatentFilterModule` read their defaults from here; Hydra composes the same
dataclasses as structured configs (:mod:`embodied_tactile.run.config` registers them as
``model/net`` and ``model/optimizer``), so ``configs/`` names only what a scene or a recipe
changes and the command line can change any field (``model.net.prior.labels=true``).
Plain dataclasses: no torch, no Hydra.
"""

from dataclasses import asdict, dataclass, field, fields
from typing import Any, ClassVar, List, Mapping, Optional

from embodied_tactile.options.checks import Rule, at_least, bounds


@dataclass
class EncoderOptions:
    """Every encoder's (and its decoder's) convolution widths and hidden width."""

    widths: List[int] = field(default_factory=lambda: [16, 32])
    hidden: int = 128


@dataclass
class PriorOptions:
    """The hierarchical prior over y (:class:`~.networks.HierarchicalPrior`, docs/reference/model.md):
    object-level sigma at ``sigma_init`` (fixed unless ``learn_sigma``), variance floor,
    action term, the population's initial sigma, the population term's weight (None: 1 / the
    training sequences, set at the start of fit), object labels (``labels``: the paper's
    label-conditioned prior) and learnable object codes (``learn_embedding``)."""

    sigma_init: float = 0.5
    learn_sigma: bool = False
    var_floor: float = 1e-2
    action_term: bool = True
    pop_sigma_init: float = 0.5
    population_weight: Optional[float] = None
    labels: bool = False
    learn_embedding: bool = False


@dataclass
class LatentFilterOptions:
    """The network's options (:class:`~.latent_filter.LatentFilter`'s docstring says what
    each does); ``modality`` is not an option but the network's input, given beside them."""

    n_z: int = field(default=16, metadata=at_least(1))
    n_y: int = field(default=16, metadata=at_least(1))
    n_a: int = 6
    n_objects: int = 32
    encoder: EncoderOptions = field(default_factory=EncoderOptions)
    transition_hidden: int = 128
    lstm_hidden: int = 128
    min_var: float = 1e-3
    obs_sigma: float = field(default=0.1, metadata=bounds(0, lo_open=True))
    learn_obs_sigma: bool = True
    obs_sigma_min: float = field(default=1e-2, metadata=at_least(0))
    prior: PriorOptions = field(default_factory=PriorOptions)
    y_update: str = "evidence"
    y_prior_precision: float = 1.0
    y_start: str = "fixed"
    y_evidence_max: Optional[float] = 1.0
    y_evidence_range: Optional[float] = 2.0
    obs_dropout: float = field(default=0.5, metadata=bounds(0, 1, hi_open=True))
    input_standardize: bool = True

    RULES: ClassVar[tuple[Rule, ...]] = (
        ("obs_sigma", "obs_sigma_min", lambda s, m: s > m, "obs_sigma > obs_sigma_min"),)


@dataclass
class ContextOptions:
    """The context objective (docs/reference/model.md, "The context objective"): where y's context
    comes from (``trial``: another trial of the same object; ``window``: a disjoint window
    of the same trial), how many target frames are filtered before the open-loop rollout,
    whether every target frame is filtered (``refilter``, a leak control), and how many other touches (trials) of the object make up one
    context (``touches``; with ``source=trial``): their posteriors q(y | touch) are combined
    by the product rule of :func:`~.latent_filter.combine_touches`, the read-out of K touches.
    Two label-free terms, off by default (:mod:`.objectives`; both > 0: their sum):
    ``invariance``, the weight of a VICReg term between y of the context touch and y of the
    target touch; ``physical``, the weight of y of the context touch predicting the target
    touch's hand-crafted features (it needs ``data.context_features=true``; it imports the
    hand-crafted reader's bias)."""

    source: str = "trial"
    touches: int = field(default=1, metadata=at_least(1))
    initial_frames: int = field(default=3, metadata=at_least(1))
    refilter: bool = False
    invariance: float = field(default=0.0, metadata=at_least(0))
    physical: float = field(default=0.0, metadata=at_least(0))


@dataclass
class OptimizerOptions:
    """Adam and its learning rate: the CPU budget's 2e-3 (docs/reference/model.md, "CPU budget");
    ``experiment=paper`` sets the paper's 1e-5."""

    name: str = "Adam"
    lr: float = field(default=2e-3, metadata=at_least(0))


@dataclass
class ModuleOptions:
    """The LightningModule's own options (:class:`~.module.LatentFilterModule`). The run's
    weights are the moving average of the optimiser's over about 100 steps (``weight_average``
    0.99): lower on the validation trials of the default scene in 6 of 6 paired runs over the
    whole trajectory (docs/experiments/default_budget.md, "Weight averaging"); null: the
    optimiser's own weights (``experiment=paper``, the population, the pendulum, the studies)."""

    check_finite: bool = True
    lr_schedule: str = "constant"
    code_lr_scale: float = field(default=1.0, metadata=bounds(0, lo_open=True))
    weight_average: Optional[float] = field(default=0.99, metadata=bounds(0, 1, lo_open=True, hi_open=True))


def build(cls: type, given: Optional[Mapping[str, Any]], owner: str) -> Any:
    """``cls`` filled from a mapping (nested option groups included), the dataclass's
    defaults where the mapping is silent; ValueError naming ``owner`` and every unknown key."""
    given = dict(given or {})
    names = {f.name: f for f in fields(cls)}
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise ValueError(f"unknown {owner} options {unknown} (known: {sorted(names)})")
    kwargs = {}
    for name, value in given.items():
        nested = _NESTED.get((cls, name))
        kwargs[name] = build(nested, value, f"{owner} {name}") if nested and not isinstance(value, nested) else value
    return cls(**kwargs)


_NESTED = {(LatentFilterOptions, "encoder"): EncoderOptions, (LatentFilterOptions, "prior"): PriorOptions}


def defaults(cls: type) -> dict[str, Any]:
    """The dataclass's defaults as a plain dict (nested groups as dicts)."""
    return asdict(cls())


__all__ = ["EncoderOptions", "PriorOptions", "LatentFilterOptions", "ContextOptions", "OptimizerOptions",
           "ModuleOptions", "build", "defaults"]
