"""Lightning callback: KRR alignment of the latents before training, at ``points`` times
spread over the run (or every N training epochs), and at the end.

Each evaluation (i) runs ``pl_module.infer_latents(batch)`` (no grad, eval mode) over the
datamodule's non-shuffled training loader (``train_eval_dataloader()`` when the datamodule
has it, else ``train_dataloader()``) up to ``max_train_sequences`` and over
``test_dataloader()`` (the held-out test trials, which never steer checkpoint selection;
``val_dataloader()`` for a datamodule without a test set); (ii) fits :func:`fit_alignment` on the training
latents' final segments only; (iii) scores every ``val_frame_stride``-th frame of the
held-out sequences with :func:`nmse`. It logs ``krr/nmse_<factor>``, ``krr/nmse_overall``
(whole trajectory, mean over factors), ``krr/nmse_last_overall`` (last frame),
``krr/train_wall_time_s`` (training wall time since ``on_train_start`` minus this callback's
own time; both continue across a resume, through the callback's ``state_dict`` in the
checkpoint), ``krr/callback_time_s`` and ``krr/callback_fraction`` (callback time / total
elapsed) to every logger, and appends one JSON line to ``krr_history.jsonl`` in
``trainer.log_dir`` (or ``default_root_dir``); each line also holds the mean predictor's NMSE
on the same held-out frames (``nmse_mean_predictor``: the training targets' mean).

The final alignment (``on_train_end``, always run unless ``run_on_train_end=False``) is the
run's number: it uses evaluate.py's settings (``final_alignment``; default: the defaults of
:func:`fit_alignment`, the same as ``configs/evaluate.yaml`` ``alignment``), every training
sequence and every held-out frame, on the final weights, so ``python evaluate.py <run>``
(``checkpoint=last``, the default) reproduces it. Its row in ``krr_history.jsonl`` carries
``"final": true`` and its settings; :attr:`final` holds it (train.py writes it to
``metrics.json``). The periodic checks are cheaper (``frames_per_sequence``, ``cv``, grids,
``val_frame_stride``, ``max_train_sequences``): they trace the curve, they are not the result.
A ``krr/*`` value shows in ``trainer.callback_metrics`` (hence in the per-epoch progress
lines) only in the epoch it was computed.

The step-0 row also holds ``floor``: the untrained network read by the final alignment's
read-out (every sequence and frame, the run's ``alignment``), the same read-out as the run's
number, which the closing block and the study's floor table set beside it.

When it runs (error against run time): with ``initial`` a row at t = 0 (``on_train_start``
of a run that does not resume; ``"epoch": -1``), then either every ``every_n_epochs`` epochs
or, with ``every_n_epochs=None``, at ``points`` epochs spread evenly over ``max_epochs``
(:func:`check_epochs`), the last after the last epoch, then the final alignment: a run's
curve has ``points`` periodic rows whatever its length (fewer when it has fewer epochs than
points). The last periodic check reads the final weights with the checks' own read-out, so
the curve ends on the same measurement it started with: the final alignment reads the same
weights 1.1-1.5x lower (docs/experiments/default_budget.md, 2026-11-27), and a curve that
ended on it would fall at its last point whatever the training did.
The periodic checks read their inputs once: the training and held-out sequences are fixed
for the run, so the first check keeps them (CPU tensors, the keys ``collect_latents`` reads)
and every later check only runs the latent inference, in batches of ``infer_batch_size``
sequences (one recursion loop per batch instead of one per loader batch).
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, ContextManager, Mapping, Sequence

import numpy as np

from .krr import alignment_kwargs, assert_disjoint, fit_alignment, resolve_cv_grouping
from ..options.alignment import CHECK_ALIGNMENT, AlignmentCheckOptions, AlignmentOptions, alignment_options
from .latents import (cache_batches, collect_latents, collect_split_latents, count_sequences,
                      factor_names, rebatch, split_at)
from .targets import DEFAULT_TARGETS, encode_split
from .metrics import bootstrap_overall, nmse_over_time, nmse_trajectory, overall
from .results import select_latents

try:  # lightning is a dependency of the package, but keep the eval core importable without it
    from lightning.pytorch.callbacks import Callback
except ImportError:  # pragma: no cover
    Callback = object  # type: ignore[misc,assignment]

log = logging.getLogger(__name__)

_OPTIONS = AlignmentCheckOptions  # the callback's defaults


def check_epochs(max_epochs: int, points: int) -> list[int]:
    """0-based epochs after which a run of ``max_epochs`` epochs runs a periodic check so
    that its ``points`` checks are spread evenly: epoch counts ``round(k * max_epochs /
    points)``, k = 1 .. points, without duplicates; the last is the last epoch."""
    if points < 1:
        raise ValueError(f"KRRAlignmentCallback points must be >= 1, got {points}")
    if max_epochs < 1:
        return []
    counts = {max(1, round(k * max_epochs / points)) for k in range(1, points + 1)}
    return sorted(c - 1 for c in counts if c <= max_epochs)


class KRRAlignmentCallback(Callback):
    """See module docstring. Defaults aim at <= 10 % of training time: a check at t = 0
    (``initial``) and ``points`` checks over the run (``every_n_epochs=None``; an int
    checks every that many epochs instead), each on at most ``max_train_sequences`` training
    sequences, ``frames_per_sequence`` final-segment frames each, Nystroem above
    ``nystroem_threshold`` rows, held-out frames subsampled by ``val_frame_stride``; inputs
    read once and inferred ``infer_batch_size`` sequences at a time."""

    def __init__(self, every_n_epochs: int | None = _OPTIONS.every_n_epochs, latent: str = _OPTIONS.latent,
                 max_train_sequences: int | None = _OPTIONS.max_train_sequences,
                 max_val_sequences: int | None = None, val_frame_stride: int = _OPTIONS.val_frame_stride,
                 alignment: Mapping[str, Any] | None = None, checks: Mapping[str, Any] | None = _OPTIONS.checks,
                 run_on_train_end: bool = True, history_name: str = "krr_history.jsonl",
                 targets: str = DEFAULT_TARGETS, points: int = _OPTIONS.points, initial: bool = _OPTIONS.initial,
                 infer_batch_size: int = _OPTIONS.infer_batch_size):
        # train.py checks these settings at its entry (run.settings: AlignmentCallbackNode's fields)
        self.targets = targets  # the factors' encoding (eval.targets), as evaluate.py's `targets`
        self.every_n_epochs = None if every_n_epochs is None else int(every_n_epochs)
        self.points, self.initial, self.infer_batch_size = int(points), bool(initial), int(infer_batch_size)
        # inputs kept between checks (per fit): merged batches of both splits, the number of
        # training sequences, whether both splits are whole; None until the first check
        self._inputs: tuple[list[dict], int, bool] | None = None
        self.latent = latent
        self.max_train_sequences = max_train_sequences
        self.max_val_sequences = max_val_sequences
        self.val_frame_stride = max(1, int(val_frame_stride))
        # the final alignment is the run's `alignment` (evaluate.py reads the same from the run's config);
        # the periodic checks change only what CHECK_ALIGNMENT / `checks` name
        self.final_kw = alignment_options(alignment)
        self.align_kw = alignment_options(self.final_kw, CHECK_ALIGNMENT, checks)
        self.run_on_train_end = run_on_train_end
        self.history_name = history_name
        self.final: dict | None = None
        self._t_start: float | None = None
        self._cb_time = 0.0
        self._elapsed_before = 0.0  # wall / callback time of the runs this one resumes (state_dict)
        self._cb_before = 0.0
        self.history: list[dict] = []

    # ------------------------------------------------------------------ hooks
    def on_train_start(self, trainer, pl_module) -> None:
        self._t_start = time.perf_counter()
        self._cb_time = 0.0
        self._inputs = None
        if self.initial and trainer.global_step == 0 and self._elapsed_before == 0.0:
            metrics = self._evaluate(trainer, pl_module, initial=True)  # t = 0: the untrained network
            if metrics:
                self._log_to_loggers(trainer, metrics)

    def due(self, trainer) -> bool:
        """Whether the epoch that just ended (``trainer.current_epoch``) gets a periodic check."""
        epoch = int(trainer.current_epoch)
        if self.every_n_epochs is not None:
            return self.every_n_epochs > 0 and (epoch + 1) % self.every_n_epochs == 0
        max_epochs = trainer.max_epochs
        if max_epochs is None or max_epochs < 1:  # open-ended run: no length to spread points over
            return (epoch + 1) % 10 == 0
        return epoch in check_epochs(int(max_epochs), self.points)

    def state_dict(self) -> dict[str, float]:
        """Elapsed wall time and callback time so far, so that a resumed run continues them."""
        elapsed = 0.0 if self._t_start is None else time.perf_counter() - self._t_start
        return {"elapsed_s": self._elapsed_before + elapsed, "callback_time_s": self._cb_before + self._cb_time}

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        self._elapsed_before = float(state_dict["elapsed_s"])
        self._cb_before = float(state_dict["callback_time_s"])

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        # a krr/* value belongs to the epoch that computed it: never re-show it in later epochs
        for store in (trainer.callback_metrics, trainer.progress_bar_metrics):
            for k in [k for k in store if k.startswith("krr/")]:
                del store[k]

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        if self.due(trainer):
            metrics = self._evaluate(trainer, pl_module)
            if metrics:
                for k, v in metrics.items():
                    pl_module.log(k, v, on_step=False, on_epoch=True, logger=False, prog_bar=(k == "krr/nmse_overall"))
                self._log_to_loggers(trainer, metrics)

    def on_train_end(self, trainer, pl_module) -> None:
        if self.run_on_train_end:
            metrics = self._evaluate(trainer, pl_module, final=True)
            if metrics:
                import torch

                self._log_to_loggers(trainer, metrics)
                # the final alignment replaces any earlier krr/* value (metrics.json's fit_metrics)
                trainer.callback_metrics.update({k: torch.tensor(v) for k, v in metrics.items()})

    def ensure_final(self, trainer, pl_module) -> None:
        """The final alignment when the fit did not run it: a run resumed at its own length
        (Lightning's fit loop is done before it starts and calls neither ``on_train_start``
        nor ``on_train_end``) reads its restored final weights here, so that its result is
        the final read-out, never an earlier check."""
        if self.final is None and self.run_on_train_end:
            self.on_train_end(trainer, pl_module)

    # ------------------------------------------------------------------ work
    def _loaders(self, trainer):
        dm = trainer.datamodule
        if dm is None:
            raise RuntimeError("KRRAlignmentCallback needs trainer.datamodule (pass datamodule= to fit)")
        train = dm.train_eval_dataloader() if hasattr(dm, "train_eval_dataloader") else dm.train_dataloader()
        held_out = dm.test_dataloader() if hasattr(dm, "test_set") else dm.val_dataloader()
        return train, held_out

    def _latents(self, trainer, pl_module, final: bool) -> tuple[dict, dict]:
        """Latents of the training and held-out sequences.

        The first check of a fit reads both splits once (at most ``max_train_sequences`` /
        ``max_val_sequences``) and keeps them merged into batches of up to
        ``infer_batch_size`` sequences, training sequences first (the default scene's
        80 + 32 in one batch of 112); every check infers that list in ONE pass, so the
        recursion's Python loop runs over the T frames once instead of once per split batch,
        and the merge is not redone per check. Sequences are filtered independently (eval
        mode, no sampling): a sequence's latents do not depend on its batch-mates (tested).
        The final alignment of a run whose cache holds only part of a split reads both
        splits whole from their loaders and merges them the same way
        (:func:`collect_split_latents`, as evaluate.py does)."""
        with averaged(pl_module):  # the run's weights: the average where the module keeps one
            loaders = self._loaders(trainer)
            if self._inputs is None:
                train, train_whole = cache_batches(loaders[0], self.max_train_sequences)
                held, held_whole = cache_batches(loaders[1], self.max_val_sequences)
                self._inputs = (rebatch(train + held, self.infer_batch_size), count_sequences(train), train_whole and held_whole)
            batches, n_train, whole = self._inputs
            if final and not whole:  # both splits whole, inferred as evaluate.py infers them
                return collect_split_latents(pl_module, cache_batches(loaders[0], None)[0],
                                             cache_batches(loaders[1], None)[0], latent=self.latent,
                                             batch_size=self.infer_batch_size)
            # the same batches collect_split_latents would merge, merged once per fit
            return split_at(collect_latents(pl_module, batches, latent=self.latent), n_train)

    def _evaluate(self, trainer, pl_module, final: bool = False, initial: bool = False) -> dict[str, float]:
        """One check (:meth:`_check`) that leaves the global random states as it found them:
        its loaders draw their seeds from torch's generator, so without this a run's weights
        would depend on when and how often it is checked."""
        import random

        import torch

        states = random.getstate(), np.random.get_state()
        with torch.random.fork_rng(devices=list(range(torch.cuda.device_count()))):
            try:
                return self._check(trainer, pl_module, final=final, initial=initial)
            finally:
                random.setstate(states[0])
                np.random.set_state(states[1])

    def _check(self, trainer, pl_module, final: bool = False, initial: bool = False) -> dict[str, float]:
        import torch

        t0 = time.perf_counter()
        if self._t_start is None:
            self._t_start = t0
        train_wall = 0.0 if initial else self._elapsed_before + (t0 - self._t_start) - self._cb_before - self._cb_time
        stride = 1 if final else self.val_frame_stride
        base_kw = self.final_kw if final else self.align_kw
        latents = self._latents(trainer, pl_module, final)
        names = factor_names(trainer.datamodule)
        t_inf = time.perf_counter()
        split = str(getattr(trainer.datamodule, "split", "trial"))
        tr, te, align, curve, per_factor, pred = self._score(*latents, base_kw, split, stride)
        floor = None
        if initial:  # the untrained network read by the final alignment's read-out: the run's floor
            whole = latents if self._inputs[2] else self._latents(trainer, pl_module, True)
            _, _, f_align, f_curve, f_per, _ = self._score(*whole, self.final_kw, split, 1)
            floor = {**_nmse_fields(names, f_per, f_curve[-1]),
                     "alignment": {k: f_align.params.get(k) for k in ("readout", "method", "alpha", "gamma")}}
        # the mean predictor: the training targets' mean at every frame (the same at every frame,
        # so its whole-trajectory and last-frame NMSE are one number)
        with np.errstate(invalid="ignore"):
            train_mean = np.nanmean(np.asarray(tr["factors"], dtype=np.float64), axis=0)
        per_factor_mean = nmse_trajectory(te["factors"], np.broadcast_to(train_mean, (len(te["factors"]), 1, len(names))))
        cb = time.perf_counter() - t0
        self._cb_time += cb
        cb_total = self._cb_before + self._cb_time
        total = self._elapsed_before + time.perf_counter() - self._t_start
        metrics = {f"krr/nmse_{f}": float(v) for f, v in zip(names, per_factor)}
        metrics.update({
            "krr/nmse_overall": overall(per_factor),
            "krr/nmse_last_overall": overall(curve[-1]),
            "krr/train_wall_time_s": float(train_wall),
            "krr/callback_time_s": float(cb),
            "krr/callback_fraction": float(cb_total / total) if total > 0 else 0.0,
        })
        row = {
            # at train end Lightning has already counted the last epoch: report the epoch trained last
            # before training (t = 0) no epoch has been trained: -1
            "epoch": -1 if initial else max(0, int(trainer.current_epoch) - 1) if final else int(trainer.current_epoch),
            "step": int(trainer.global_step),
            "train_wall_time_s": float(train_wall), "callback_time_s": float(cb),
            "callback_infer_s": float(t_inf - t0), "callback_krr_s": float(cb - (t_inf - t0)),
            "callback_time_total_s": float(cb_total), "callback_fraction": metrics["krr/callback_fraction"],
            **_nmse_fields(names, per_factor, curve[-1]),
            "nmse_mean_predictor": {f: _fin(v) for f, v in zip(names, per_factor_mean)},
            "nmse_mean_predictor_overall": _fin(overall(per_factor_mean)),
            "n_train": int(len(tr["factors"])), "n_test": int(len(te["factors"])), "latent": self.latent,
            "val_frame_stride": stride, "final": bool(final), "initial": bool(initial), "targets": self.targets,
            "torch_threads": int(torch.get_num_threads()),  # float32 inference depends on it: evaluate.py reuses it
            "alignment": {k: align.params.get(k) for k in ("readout", "time_bins", "method", "alpha", "gamma",
                                                           "n_train_rows", "fit_time_s", "final_segment",
                                                           "frames_per_sequence", "cv_folds", "seed")},
            "alignment_settings": {**{k: v for k, v in asdict(base_kw).items() if k != "n_threads"},
                                   "groups": resolve_cv_grouping(self.final_kw.groups, split)},
        }
        if floor is not None:
            row["floor"] = floor
        if final:  # the test sample's own noise around the run's number: objects resampled
            row["bootstrap_objects"] = _interval_fields(bootstrap_overall(te["factors"], pred, te["object_id"],
                                                                          n_boot=BOOTSTRAP_RESAMPLES))
            self.final = row
        self.history.append(row)
        if trainer.is_global_zero:
            path = self.history_path(trainer)
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(path, "a") as fh:
                fh.write(json.dumps(row) + "\n")
        log.info("KRR alignment %sepoch %d: nmse_overall=%.4f (callback %.2fs, %.1f%% of elapsed)",
                 "(final weights, evaluate.py settings) " if final else "(before training) " if initial else "(periodic check) ",
                 row["epoch"],
                 metrics["krr/nmse_overall"], cb, 100 * metrics["krr/callback_fraction"])
        return metrics

    def _score(self, tr: dict, te: dict, base_kw: AlignmentOptions, split: str, stride: int):
        """Fit the alignment ``base_kw`` on the training latents ``tr`` and read the held-out
        ``te``: (tr, te with encoded targets, the fitted alignment, the NMSE curve over the
        scored frames (T', K), the NMSE per factor over the trajectory, the predictions of the
        scored frames (n, T', K)). Every frame is read
        (a per-time read-out reads a frame by its place in the trial); every ``stride``-th is
        scored, the last one kept."""
        assert_disjoint(tr.get("seq_id"), te.get("seq_id"))
        tr, te = encode_split(tr, self.targets), encode_split(te, self.targets)
        align_kw = alignment_kwargs(base_kw, split, tr.get("object_id"))
        align = fit_alignment(select_latents(tr, self.latent), tr["factors"], ids=tr.get("seq_id"), **align_kw)
        pred = align.predict(select_latents(te, self.latent), ids=te.get("seq_id"))[:, ::-1][:, ::stride][:, ::-1]
        curve = nmse_over_time(te["factors"], pred)  # (T', K)
        return tr, te, align, curve, nmse_trajectory(te["factors"], pred), pred  # per factor == the curve's mean

    def history_path(self, trainer) -> Path:
        """``<run folder>/krr_history.jsonl``: the trainer's root dir (the Hydra run folder),
        so evaluate.py finds it whatever loggers were configured."""
        return Path(trainer.default_root_dir) / self.history_name

    @staticmethod
    def _log_to_loggers(trainer, metrics: Mapping[str, Any]) -> None:
        for lg in trainer.loggers:
            lg.log_metrics(dict(metrics), step=trainer.global_step)


def averaged(pl_module) -> ContextManager[None]:
    """The module's averaged weights for a check (``weight_average``); its own otherwise."""
    hold = getattr(pl_module, "averaged_weights", None)
    return hold() if hold is not None else contextlib.nullcontext()


def _nmse_fields(names: Sequence[str], per_factor, last) -> dict[str, Any]:
    """A row's NMSE fields: per factor and their mean over the trajectory (``per_factor``) and
    at the last scored frame (``last``), non-finite values as None."""
    return {"nmse": {f: _fin(v) for f, v in zip(names, per_factor)}, "nmse_overall": _fin(overall(per_factor)),
            "nmse_last": {f: _fin(v) for f, v in zip(names, last)}, "nmse_last_overall": _fin(overall(last))}


#: resamples of the held-out objects behind the final row's interval (about a second at 128 sequences)
BOOTSTRAP_RESAMPLES = 1000


def _interval_fields(draws: np.ndarray) -> dict[str, Any]:
    """Percentile 95 % intervals of bootstrap draws (n, 2: whole trajectory, last frame)."""
    with np.errstate(invalid="ignore"):
        lo, hi = np.nanpercentile(draws, [2.5, 97.5], axis=0)
    return {"resamples": int(len(draws)), "overall_ci95": [_fin(lo[0]), _fin(hi[0])],
            "last_overall_ci95": [_fin(lo[1]), _fin(hi[1])]}


def _fin(v) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None
