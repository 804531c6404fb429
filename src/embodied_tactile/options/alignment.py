"""The alignment's options: one default per option (no heavy imports, so the typed configs
can register it).

The training's final alignment (``configs/train.yaml`` ``alignment``, handed to
:class:`~embodied_tactile.eval.callback.KRRAlignmentCallback`) and ``python evaluate.py <run>``
(which reads the run's own ``alignment`` from its config_resolved.yaml, then applies
``alignment.*`` overrides) use these options, so the two numbers are one measurement.

Read-outs (``readout``; docs/reference/evaluation.md, "The read-out over time"):

* ``per_time`` -- a probe per interaction time: the trial is cut into spans
  (:func:`~embodied_tactile.eval.krr.time_spans`: frame 0 alone, edges growing geometrically
  so that spans are short where the posterior moves fastest, none longer than a
  ``time_bins``-th of the trial, the final tenth last) and each span gets its own alignment,
  fitted on the training latents of that span (``frames_per_sequence`` frames of every
  training sequence, the span's last frame included), its ``alpha`` and ``gamma``
  cross-validated on every frame of the span of the held-out folds' sequences. A frame is
  read by the probe of its span, so every latent is read by a regressor fitted on latents of
  the same time; where the latents carry no evidence yet, the cross-validation picks the
  most regularised fit, which reads the training targets' mean. The last span is the
  paper's final tenth: the last-frame number is the paper protocol's.
* ``final_segment`` -- the paper's protocol: one alignment fitted on the final segment
  (``final_segment``, a fraction of T or a frame count) of every training sequence, applied
  to every frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any, Dict, List, Optional

from .checks import SettingsError, at_least, bounds, check_options, one_of

#: ``alpha`` grid: reaches 100, where the fit on standardised targets is close to their mean
DEFAULT_ALPHAS = (1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0)
#: ``gamma`` grid, multiples of 1/d on standardised inputs
DEFAULT_GAMMAS = (0.1, 0.3, 1.0, 3.0)
#: what a periodic check of the training changes in the run's alignment (cheaper: the checks
#: trace the curve; the final alignment and evaluate.py use the run's own): fewer rows and
#: folds, a smaller Nystroem map and grid
CHECK_ALIGNMENT = {"frames_per_sequence": 2, "cv": 3, "nystroem_threshold": 1024, "n_components": 256,
                   "alphas": [1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0], "gammas": [0.3, 1.0, 3.0]}
READOUTS = ("per_time", "final_segment")
CV_GROUPINGS = ("auto", "sequence", "object")
#: what the alignment reads (eval.latents.LATENT_KEYS) and the factors' encodings it scores
#: (eval.targets: the catalogue's design levels, or physical units for populations)
LATENTS = ("y", "z", "both")
TARGET_ENCODINGS = ("design_rank", "physical")


@dataclass
class AlignmentOptions:
    """``alignment``: the latent -> factor read-out (RBF kernel ridge regression). Built and
    checked once, where it enters (:func:`alignment_options`); the read-out's functions take it
    typed and do not check it again."""

    readout: str = field(default="per_time", metadata=one_of(*READOUTS))  # per_time | final_segment (the paper's protocol)
    time_bins: int = field(default=10, metadata=at_least(1))  # per_time: no span longer than 1/time_bins of the trial (eval.krr.time_spans)
    final_segment: float = field(default=0.1, metadata=bounds(0, lo_open=True))  # final_segment: the fitted tail (fraction of T, or frames if > 1)
    frames_per_sequence: int = field(default=4, metadata=at_least(1))  # rows per training sequence (per span for per_time)
    cv: int = field(default=5, metadata=at_least(2))  # grouped folds of the grid search
    groups: str = field(default="auto", metadata=one_of(*CV_GROUPINGS))  # CV folds: auto (by object on an object split) | sequence | object
    alphas: List[float] = field(default_factory=lambda: list(DEFAULT_ALPHAS))
    gammas: List[float] = field(default_factory=lambda: list(DEFAULT_GAMMAS))
    nystroem_threshold: int = field(default=2000, metadata=at_least(1))  # above this many rows: Nystroem features + ridge
    n_components: int = field(default=500, metadata=at_least(1))
    seed: int = 0
    n_threads: Optional[int] = field(default=1, metadata=at_least(1))  # BLAS threads of the fit (1: much faster on a loaded small machine)


@dataclass
class AlignmentCheckOptions:
    """``callbacks.krr_alignment``: the KRR callback's own settings
    (:class:`~embodied_tactile.eval.callback.KRRAlignmentCallback`): when it checks the
    alignment during training and how cheaply. A row at t = 0 (``initial``), then ``points``
    checks spread over ``max_epochs``, the last on the final weights (then the final
    alignment: the run's ``alignment`` as it is, on every sequence and frame, as evaluate.py
    reads it), or one every ``every_n_epochs`` epochs; the periodic checks change only what ``checks`` names
    (:data:`CHECK_ALIGNMENT`, then ``checks`` over it), on at most ``max_train_sequences``
    training sequences and every ``val_frame_stride``-th held-out frame."""

    every_n_epochs: Optional[int] = field(default=None, metadata=at_least(0))  # an int checks every N epochs instead of `points`
    points: int = field(default=8, metadata=at_least(1))
    initial: bool = True
    infer_batch_size: int = field(default=128, metadata=at_least(1))  # sequences per latent-inference batch
    latent: str = field(default="y", metadata=one_of(*LATENTS))
    max_train_sequences: Optional[int] = 512
    val_frame_stride: int = 2
    checks: Optional[Dict[str, Any]] = None  # alignment options of the periodic checks


def alignment_options(*layers) -> AlignmentOptions:
    """The typed alignment: :class:`AlignmentOptions`' defaults updated by each layer in order
    (a mapping, a config node or an :class:`AlignmentOptions`; None skipped), checked by the one checker
    (:func:`~embodied_tactile.options.checks.check_options`, the fields' metadata): an unknown
    key or a value of the wrong type or range raises :class:`SettingsError` naming
    ``alignment.<key>``. The entry points build it (the KRR callback from the run's
    ``alignment``, evaluate.py from the run's own with its overrides); what reads it below
    takes it as it is."""
    known = {f.name for f in fields(AlignmentOptions)}
    merged = asdict(AlignmentOptions())
    for layer in layers:
        if layer is None:
            continue
        if isinstance(layer, AlignmentOptions):
            layer = asdict(layer)
        else:
            from omegaconf import OmegaConf

            layer = OmegaConf.to_container(layer, resolve=True) if OmegaConf.is_config(layer) else dict(layer)
        unknown = sorted(set(layer) - known)
        if unknown:
            raise SettingsError(f"unknown alignment option(s) {unknown}; known: {sorted(known)}")
        merged.update(layer)
    check_options(AlignmentOptions, merged, "alignment")
    merged["alphas"], merged["gammas"] = [float(a) for a in merged["alphas"]], [float(g) for g in merged["gammas"]]
    return AlignmentOptions(**merged)


__all__ = ["AlignmentCheckOptions", "AlignmentOptions", "CHECK_ALIGNMENT", "CV_GROUPINGS", "DEFAULT_ALPHAS", "DEFAULT_GAMMAS", "LATENTS",
           "READOUTS", "TARGET_ENCODINGS", "alignment_options"]
