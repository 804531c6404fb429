"""The LightningModule of the Latent Filter, for every modality (uni-modal, early and late fusion)."""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator, Mapping
from dataclasses import asdict
from typing import Any, Callable, Optional

import lightning as L
import torch
from torch import Tensor

from .annealing import AnnealingSchedule, build_schedule, check_finite
from .compat import RENAMED_CLASSES, UNSAVED_MODULE_OPTIONS, upgrade_context_config, upgrade_state_dict
from .fusion import LateFusion
from .latent_filter import LatentFilter, to_plain
from .objectives import FeatureHead, feature_count, invariance_terms, physical_term
from .options import ContextOptions, ModuleOptions, OptimizerOptions, build, defaults

_DEFAULT = ModuleOptions()
LR_SCHEDULES = ("constant", "cosine")


def _optimizer_spec(optimizer: Any) -> Optional[dict[str, Any]]:
    """Checkpoint-safe description of an optimizer factory (None if not describable)."""
    if optimizer is None:
        return None
    if isinstance(optimizer, Mapping):
        return dict(to_plain(optimizer))
    if isinstance(optimizer, functools.partial) and getattr(torch.optim, optimizer.func.__name__, None) is optimizer.func:
        kw = to_plain(dict(optimizer.keywords))
        if all(isinstance(v, (int, float, bool, str, list, tuple, type(None))) for v in kw.values()) and not optimizer.args:
            return {"name": optimizer.func.__name__, **kw}
    return None


def _optimizer_factory(optimizer: Any) -> Callable:
    if optimizer is None:
        optimizer = defaults(OptimizerOptions)
    if callable(optimizer):
        return optimizer
    if isinstance(optimizer, Mapping):
        spec = dict(to_plain(optimizer))
        name = spec.pop("name")
        cls = getattr(torch.optim, name, None)
        if cls is None:
            raise ValueError(f"unknown torch.optim optimizer {name!r}")
        return functools.partial(cls, **spec)
    raise TypeError(f"optimizer must be a callable (functools.partial) or a mapping, got {type(optimizer).__name__}")


def _trial_label(batch: Mapping[str, Any], row: int) -> str:
    """``trial 'name' (object_id 8, action_index 10)``, or ``batch row 3 (...)`` for a batch
    without ``trial`` names."""
    trials = batch.get("trial")
    label = f"trial {trials[row]!r}" if trials is not None else f"batch row {row}"
    ids = [f"{k} {int(batch[k][row])}" for k in ("object_id", "action_index") if k in batch]
    return f"{label} ({', '.join(ids)})" if ids else label


def nonfinite_inputs(batch: Mapping[str, Any], max_frames: int = 8) -> list[str]:
    """Where a batch's ``obs`` / ``actions`` are NaN or infinite: one entry per trial and
    field, e.g. ``"trial 'x' (object_id 8, action_index 10) obs frame 37"``. Frames count
    from the start of the trial's preprocessed sequence (``first_frame`` of a crop added);
    empty when every value is finite."""
    first = batch.get("first_frame")
    found = []
    for key in ("obs", "actions"):
        x = batch.get(key)
        if not isinstance(x, Tensor) or not x.is_floating_point() or bool(torch.isfinite(x.detach().sum())):
            continue  # a finite sum: every value finite (one pass; 4 for isfinite().all())
        bad = ~torch.isfinite(x.detach()).flatten(2).all(-1)  # (B, T)
        for row in bad.any(1).nonzero().flatten().tolist():
            frames = bad[row].nonzero().flatten()
            if first is not None:
                frames = frames + int(first[row])
            shown = ", ".join(str(f) for f in frames[:max_frames].tolist())
            more = f" ... ({len(frames)} frames)" if len(frames) > max_frames else ""
            found.append(f"{_trial_label(batch, row)} {key} frame{'s' if len(frames) > 1 else ''} {shown}{more}")
    return found


CONTEXT_SOURCES = ("trial", "window")


def check_context(context: Optional[Mapping[str, Any]]) -> Optional[dict[str, Any]]:
    """The context objective's settings as a plain dict (None: the filtering ELBO):
    :class:`~.options.ContextOptions` filled from ``context``, ``source`` in
    :data:`CONTEXT_SOURCES`, ``initial_frames`` >= 1."""
    if context is None:
        return None
    out = asdict(build(ContextOptions, upgrade_context_config(to_plain(context)), "context"))
    if out["source"] not in CONTEXT_SOURCES:
        raise ValueError(f"context.source must be one of {CONTEXT_SOURCES}, got {out['source']!r}")
    if int(out["initial_frames"]) < 1:
        raise ValueError(f"context.initial_frames must be >= 1, got {out['initial_frames']}")
    if int(out["touches"]) < 1 or (int(out["touches"]) > 1 and out["source"] != "trial"):
        raise ValueError(f"context.touches must be 1, or > 1 with source=trial, got {out['touches']} "
                         f"with source={out['source']!r}")
    for key in ("invariance", "physical"):
        if not float(out[key]) >= 0.0:
            raise ValueError(f"context.{key} must be a weight >= 0 (0: off), got {out[key]}")
    if float(out["invariance"]) > 0 and int(out["touches"]) > 1:
        raise ValueError("context.invariance compares y of one context touch with y of the target: it needs touches=1")
    return out


class LatentFilterModule(L.LightningModule):
    """Latent Filter training module for any modality (``fusion`` single|early|late): the
    network builds the observation model (:mod:`.fusion`) from its modality.

    Args (Hydra-instantiable; see docs/reference/model.md and configs/model/latent_filter.yaml):
        net: the :class:`~.latent_filter.LatentFilter` (Hydra builds it from ``model.net``
            and injects it), or its ``config()`` mapping (how ``load_from_checkpoint``
            rebuilds it). Its constructor arguments are defined there only and stored here
            once, as the ``net`` hyperparameter.
        annealing: an :class:`AnnealingSchedule`, a name, or ``{name, **kwargs}``
            (None -> plain ELBO). Stored in the hyperparameters as its ``config()``.
        optimizer: ``functools.partial(torch.optim.X, **kw)`` (Hydra ``_partial_: true``)
            or ``{name: "Adam", lr: ...}``; None -> :class:`~.options.OptimizerOptions`. Stored as
            ``{name, **kw}`` when it is a torch.optim partial with plain keywords.
        check_finite: raise FloatingPointError on non-finite inputs (naming trial and frame)
            or a non-finite loss (naming the terms and the batch's trials), in training and
            validation / test steps.
        lr_schedule: ``"constant"`` (the optimizer's lr throughout) or ``"cosine"`` (the lr
            falls from its value to 0 along a half cosine over the run's optimiser steps,
            ``trainer.estimated_stepping_batches``; docs/reference/model.md, "Learning-rate schedule").
        code_lr_scale: the prior's object codes (``prior.embedding``) train in a parameter
            group of their own at this multiple of the optimizer's lr (1 = one group, the
            default; docs/reference/model.md, "Fixed object codes").
        context: None (default: the filtering ELBO, :meth:`LatentFilter.elbo_terms`) or
            ``{source, initial_frames, refilter}``: the context objective
            (:meth:`LatentFilter.context_terms`, ``recipe=context``, docs/reference/model.md "The
            context objective"). ``source`` (``trial`` | ``window``) names the DataModule's
            pairing (configs/data reads it from here); ``initial_frames`` target frames are
            filtered before the open-loop rollout; ``refilter`` filters every target frame.
            ``invariance`` / ``physical`` (0: off): the weights of the label-free terms
            (:meth:`auxiliary_terms`, :mod:`.objectives`) added to the training loss; with
            ``physical`` > 0 the module holds ``feature_head``.
        weight_average: None (default) or a decay d in (0, 1): an exponential moving average
            of the network's parameters, updated after every optimiser step with decay
            min(d, (1 + n) / (10 + n)) at the n-th update (:class:`WeightAverage`). The
            run's weights are then the average: the KRR checks and the final alignment read
            it (:meth:`averaged_weights`), so does the validation loop in fit (the held-out
            ELBO and the checkpoint chosen by it), every checkpoint's ``state_dict`` holds it
            (the weights the optimiser moves are kept beside it, for resuming), and after fit
            the network holds it (docs/reference/model.md, "Weight averaging").

    Logs: train/loss (annealed, with the weighted label-free terms), train/nll, train/kl_z,
    train/kl_y, train/entropy, train/elbo, anneal/*, train/invariance (train/variance,
    train/covariance) and train/physical where their weights are > 0; val/loss, val/elbo (per sequence, higher is better),
    val/nll, val/kl_z, val/kl_y (and test/* likewise).
    """

    def __init__(self, net: LatentFilter | Mapping[str, Any], annealing: Any = None, optimizer: Any = None,
                 check_finite: bool = _DEFAULT.check_finite, lr_schedule: str = _DEFAULT.lr_schedule,
                 code_lr_scale: float = _DEFAULT.code_lr_scale, context: Optional[Mapping[str, Any]] = None,
                 weight_average: Optional[float] = _DEFAULT.weight_average) -> None:
        super().__init__()
        context = check_context(context)
        if lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, got {lr_schedule!r}")
        if not code_lr_scale > 0:
            raise ValueError(f"code_lr_scale must be > 0, got {code_lr_scale}")
        if weight_average is not None and not 0.0 < float(weight_average) < 1.0:
            raise ValueError(f"weight_average must be a decay in (0, 1) or None, got {weight_average}")
        if not isinstance(net, LatentFilter):
            if not isinstance(net, Mapping):
                raise TypeError(f"{type(self).__name__}: net must be a LatentFilter or its config mapping, "
                                f"got {type(net).__name__}")
            net = LatentFilter.from_config(net)
        schedule = build_schedule(annealing)
        self._optimizer = _optimizer_factory(optimizer)
        self.check_finite = bool(check_finite)
        self.lr_schedule = lr_schedule
        self.code_lr_scale = float(code_lr_scale)
        # saved once: the network's own constructor arguments, the schedule and the optimizer
        self.save_hyperparameters({"net": net.config(), "annealing": schedule.config(),
                                   "optimizer": _optimizer_spec(optimizer), "check_finite": bool(check_finite),
                                   "lr_schedule": lr_schedule, "code_lr_scale": float(code_lr_scale),
                                   "context": context,
                                   "weight_average": None if weight_average is None else float(weight_average)})
        self.context = context
        self.model = net
        self.annealing: AnnealingSchedule = schedule
        self.average = None if weight_average is None else WeightAverage(float(weight_average))
        #: context.physical > 0: y of the context touch -> the target touch's hand-crafted features
        self.feature_head = (FeatureHead(net.n_y, net.n_a, feature_count(net.modality["channels"]))
                             if context is not None and float(context["physical"]) > 0 else None)

    # ------------------------------------------------------------------ API
    def forward(self, obs: Tensor, actions: Tensor, sample: bool = False) -> dict[str, Tensor]:
        return self.model(obs, actions, sample=sample)

    def infer_latents(self, batch: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """z_mean, z_var (B, T, n_z), y_mean, y_var (B, T, n_y): eval mode, no sampling,
        no object label needed."""
        return self.model.infer_latents(batch)

    def filter_step(self, obs_t: Tensor, action_t: Tensor, prev_action: Optional[Tensor] = None,
                    state: Optional[dict[str, Tensor]] = None, sample: bool = False):
        """See :meth:`LatentFilter.filter_step`."""
        return self.model.filter_step(obs_t, action_t, prev_action, state, sample)

    # ------------------------------------------------------------------ Lightning
    def _terms(self, batch: Mapping[str, Tensor], keep_out: bool = False) -> dict[str, Tensor]:
        if self.context is None:
            terms = self.model.elbo_terms(batch, sample=True)
        elif "context_obs" not in batch:
            raise ValueError("the context objective needs batches with context_obs / context_actions: "
                             "a TactileDataModule with context=trial|window (configs/recipe/context.yaml)")
        else:
            terms = self.model.context_terms(batch, self.context["initial_frames"], self.context["refilter"],
                                             sample=True)
        out = terms.pop("out")
        if keep_out:
            terms["out"] = out
        return terms

    def auxiliary_terms(self, batch: Mapping[str, Any], out: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """The context objective's label-free terms (:mod:`.objectives`), unweighted, from
        the context touch's q(y) (``out``, :meth:`LatentFilter.context_terms`) and the
        target touch of ``batch``: ``invariance`` (VICReg total, with its ``variance`` and
        ``covariance`` parts) between the posterior means of y from the two touches, and
        ``physical`` (the feature head's error on ``batch["target_features"]``). Empty when
        both weights are 0. Neither reads ``factors`` or ``object_id``."""
        found: dict[str, Tensor] = {}
        if self.context is None:
            return found
        if float(self.context["invariance"]) > 0:
            y_b, _ = self.model.context_posterior(batch["obs"], batch["actions"])
            vic = invariance_terms(out["y_mean"], y_b)
            found.update(invariance=vic["total"], variance=vic["variance"], covariance=vic["covariance"])
        if self.feature_head is not None:
            if "target_features" not in batch:
                raise ValueError("model.context.physical > 0 needs batches with target_features: "
                                 "data.context_features=true (configs/recipe/context_physical.yaml)")
            pred = self.feature_head(out["y_mean"], batch["actions"])
            found["physical"] = physical_term(pred, batch["target_features"])
        return found

    def _with_auxiliary(self, batch: Mapping[str, Any], terms: dict[str, Tensor], loss: Tensor
                        ) -> tuple[Tensor, dict[str, Tensor]]:
        """The loss with the weighted label-free terms added, and those terms."""
        aux = self.auxiliary_terms(batch, terms.pop("out"))
        for key in ("invariance", "physical"):
            if key in aux:
                loss = loss + float(self.context[key]) * aux[key]
        return loss, aux

    def _check_inputs(self, batch: Mapping[str, Any], stage: str, batch_idx: int) -> None:
        bad = nonfinite_inputs(batch) if self.check_finite else []
        if bad:
            raise FloatingPointError(f"non-finite input at step {self.global_step} ({stage} batch {batch_idx}): "
                                     + "; ".join(bad))

    def _check_loss(self, batch: Mapping[str, Any], stage: str, batch_idx: int, terms: Mapping[str, Tensor],
                    loss: Tensor) -> None:
        if not self.check_finite:
            return
        try:
            check_finite(self.global_step, {k: terms[k] for k in ("nll", "kl_z", "kl_y", "entropy")}, loss)
        except FloatingPointError as err:  # the inputs were finite (_check_inputs): name the batch
            rows = ", ".join(_trial_label(batch, r) for r in range(batch["obs"].shape[0]))
            raise FloatingPointError(f"{err} ({stage} batch {batch_idx}, finite inputs of {rows})") from None

    def training_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> Tensor:
        self._check_inputs(batch, "train", batch_idx)
        terms = self._terms(batch, keep_out=True)
        loss, logs = self.annealing(self.global_step, {k: v for k, v in terms.items() if k != "out"})
        loss, aux = self._with_auxiliary(batch, terms, loss)
        self._check_loss(batch, "train", batch_idx, terms, loss)
        bs = batch["obs"].shape[0]
        self.log("train/loss", loss, prog_bar=True, batch_size=bs)
        for k, v in aux.items():
            self.log(f"train/{k}", v.detach(), batch_size=bs)
        for k in ("nll", "kl_z", "kl_y", "pop", "entropy"):
            self.log(f"train/{k}", terms[k].detach(), batch_size=bs)
        self.log("train/elbo", -(terms["nll"] + terms["kl_z"] + terms["kl_y"]).detach(), batch_size=bs)
        for k, v in logs.items():
            self.log(k, float(v), batch_size=bs)
        return loss

    def _eval_step(self, batch: Mapping[str, Tensor], prefix: str, batch_idx: int = 0) -> Tensor:
        self._check_inputs(batch, prefix, batch_idx)
        terms = self._terms(batch)
        loss, _ = self.annealing(self.global_step, terms)  # eval mode: no schedule state change
        self._check_loss(batch, prefix, batch_idx, terms, loss)
        bs = batch["obs"].shape[0]
        elbo = -(terms["nll"] + terms["kl_z"] + terms["kl_y"])
        self.log(f"{prefix}/loss", loss, batch_size=bs, sync_dist=True)
        self.log(f"{prefix}/elbo", elbo, prog_bar=True, batch_size=bs, sync_dist=True)
        for k in ("nll", "kl_z", "kl_y"):
            self.log(f"{prefix}/{k}", terms[k], batch_size=bs, sync_dist=True)
        return loss

    def validation_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> Tensor:
        return self._eval_step(batch, "val", batch_idx)

    def test_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> Tensor:
        return self._eval_step(batch, "test", batch_idx)

    def use_data_statistics(self, statistics: Any) -> None:
        """What the network needs from its training data, handed over by the data side
        (:class:`embodied_tactile.run.handover.HandOverStatistics` at the start of fit; any object
        with ``channel_mean``, ``channel_std`` (C,) and ``n_train_sequences``): the encoders'
        input statistics (``input_standardize``) and the prior's population weight,
        1 / (training sequences) per sequence, unless the config fixes it. Input statistics a
        network already holds (a trained network fitted further, a resumed run's restored
        checkpoint) stay."""
        if self.model.input_standardize and not bool(self.model.input_stats_set):
            self.model.set_input_stats(statistics.channel_mean, statistics.channel_std)
        if (self.hparams["net"].get("prior") or {}).get("population_weight") is None and statistics.n_train_sequences:
            self.model.prior.population_weight = 1.0 / int(statistics.n_train_sequences)

    # ------------------------------------------------------------------ weight averaging
    @property
    def averaging(self) -> bool:
        """Whether an average is kept now (``weight_average``, in fit)."""
        return self.average is not None and self.average.started

    @contextlib.contextmanager
    def averaged_weights(self) -> Iterator[None]:
        """The network holds the averaged weights inside the block (``weight_average``; the
        weights the optimiser moves outside it); a no-op without averaging."""
        if not self.averaging:
            yield
            return
        self.average.swap(self)
        try:
            yield
        finally:
            self.average.swap(self)

    def on_fit_start(self) -> None:
        if self.model.input_standardize and not bool(self.model.input_stats_set):
            raise ValueError("input_standardize (the default) needs the training set's channel statistics: fit with a "
                             "TactileDataModule and the HandOverStatistics callback (embodied_tactile.run.handover; "
                             "train.py adds it), or build the network with input_standardize=False")
        if self.average is not None:
            self.average.start(self)  # a resumed run's checkpoint held the average: the optimiser's weights return

    def optimizer_step(self, *args: Any, **kwargs: Any) -> None:
        super().optimizer_step(*args, **kwargs)
        if self.average is not None:  # before any on_train_batch_end: a checkpoint saved there has this step
            self.average.update(self)

    def on_validation_epoch_start(self) -> None:
        if self.averaging:  # in fit: the held-out ELBO of the run's weights
            self.average.swap(self)

    def on_validation_epoch_end(self) -> None:
        if self.averaging:
            self.average.swap(self)

    def on_train_end(self) -> None:
        if self.averaging:
            self.average.swap(self)  # the run's weights from here on: validate_at_end, the caller
            self.average.stop()

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        if self.averaging:
            self.average.save(checkpoint)

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Checkpoints of earlier layouts load (:func:`~.compat.upgrade_state_dict`); a
        weight-averaged run's checkpoint loads its average (the optimiser's weights are kept
        for :meth:`on_fit_start` of a resumed fit)."""
        checkpoint["state_dict"] = upgrade_state_dict(checkpoint.get("state_dict") or {},
                                                      late=isinstance(self.model.observation, LateFusion))
        saved = checkpoint.get("hyper_parameters") or {}
        if "weight_average" not in saved and UNSAVED_MODULE_OPTIONS["weight_average"] is None:
            self.average = None  # written before the option existed: trained without an average
            self.hparams["weight_average"] = None
        if self.average is not None:
            self.average.load(checkpoint)

    def configure_optimizers(self):
        if getattr(self, "_trainer", None) is not None:  # schedule lengths given as a fraction of the run's steps
            self.annealing.set_total_steps(self.trainer.estimated_stepping_batches)
        if self.code_lr_scale == 1.0:
            optimizer = self._optimizer(self.parameters())
        else:  # the object codes in a group of their own, at code_lr_scale x the optimizer's lr
            codes = self.model.prior.embedding.weight
            optimizer = self._optimizer([{"params": [p for p in self.parameters() if p is not codes]},
                                         {"params": [codes]}])
            optimizer.param_groups[1]["lr"] = optimizer.param_groups[0]["lr"] * self.code_lr_scale
        if self.lr_schedule == "constant" or getattr(self, "_trainer", None) is None:
            return optimizer
        total = max(1, int(self.trainer.estimated_stepping_batches))
        cosine = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=total, eta_min=0.0)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": cosine, "interval": "step"}}


class WeightAverage:
    """An exponential moving average of a module's parameters (float32, on their device).

    After the n-th optimiser step (n = 1, 2, ...) every averaged tensor moves toward the
    parameter by (1 - d_n), d_n = min(decay, (1 + n) / (10 + n)): early updates forget the
    initialisation fast, later ones average over about 1 / (1 - decay) steps. The average
    starts as a copy of the parameters (:meth:`start`), so before any update it equals them.
    Buffers are not averaged (input statistics and the prior's record of seen objects are
    the network's own).
    """

    KEY = "weight_average"  # the checkpoint entry: decay, updates and the optimiser's weights

    def __init__(self, decay: float) -> None:
        self.decay = float(decay)
        self.updates = 0
        self.tensors: Optional[dict[str, Tensor]] = None
        self._resume: Optional[dict[str, Any]] = None

    @property
    def started(self) -> bool:
        return self.tensors is not None

    def start(self, module: torch.nn.Module) -> None:
        """Begin averaging ``module``'s parameters; after a checkpoint of an averaged run
        (:meth:`load`) the module holds the average, which is kept, and the optimiser's
        weights are put back."""
        params = dict(module.named_parameters())
        self.tensors = {k: p.detach().clone() for k, p in params.items()}
        state, self._resume = self._resume, None
        self.updates = 0 if state is None else int(state["updates"])
        if state is not None:
            with torch.no_grad():
                for k, p in params.items():
                    p.copy_(state["weights"][k])

    def stop(self) -> None:
        self.tensors = None

    @torch.no_grad()
    def update(self, module: torch.nn.Module) -> None:
        if self.tensors is None:
            self.start(module)
        self.updates += 1
        d = min(self.decay, (1.0 + self.updates) / (10.0 + self.updates))
        for k, p in module.named_parameters():
            self.tensors[k].lerp_(p.detach(), 1.0 - d)

    @torch.no_grad()
    def swap(self, module: torch.nn.Module) -> None:
        """Exchange the module's parameters with the average (twice: back as before)."""
        for k, p in module.named_parameters():
            held = p.detach().clone()
            p.copy_(self.tensors[k])
            self.tensors[k] = held

    def save(self, checkpoint: dict[str, Any]) -> None:
        """The checkpoint's ``state_dict`` gets the average; the optimiser's weights go
        under :attr:`KEY`."""
        state = checkpoint["state_dict"]
        weights = {k: state[k] for k in self.tensors}
        state.update({k: v.detach().clone() for k, v in self.tensors.items()})
        checkpoint[self.KEY] = {"decay": self.decay, "updates": self.updates, "weights": weights}

    def load(self, checkpoint: Mapping[str, Any]) -> None:
        """Keep a checkpoint's optimiser weights for the :meth:`start` of a resumed fit."""
        self._resume = checkpoint.get(self.KEY)


def __getattr__(name: str) -> Any:
    """The class names of earlier versions (:data:`~.compat.RENAMED_CLASSES`), which the
    ``_target_`` of saved configs names."""
    if name in RENAMED_CLASSES:
        return globals()[RENAMED_CLASSES[name]]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
