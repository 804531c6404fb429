"""Lightning callback: KRR alignment of the latents every N training epochs (and at the end).

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
``trainer.log_dir`` (or ``default_root_dir``).

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
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..constants import FACTOR_NAMES
from .krr import assert_disjoint, fit_alignment
from .targets import DEFAULT_TARGETS, TARGET_ENCODINGS, encode_split
from .metrics import nmse_over_time, nmse_trajectory, overall
from .results import select_latents

try:  # lightning is a dependency of the package, but keep the eval core importable without it
    from lightning.pytorch.callbacks import Callback
except ImportError:  # pragma: no cover
    Callback = object  # type: ignore[misc,assignment]

log = logging.getLogger(__name__)

LATENT_KEYS = {"y": ("y_mean",), "z": ("z_mean",), "both": ("z_mean", "y_mean")}


def _to_device(batch, device):
    import torch

    if isinstance(batch, torch.Tensor):
        return batch.to(device)
    if isinstance(batch, Mapping):
        return {k: _to_device(v, device) for k, v in batch.items()}
    if isinstance(batch, (list, tuple)):
        return type(batch)(_to_device(v, device) for v in batch)
    return batch


def collect_latents(pl_module, loader, *, latent: str = "y", max_sequences: int | None = None) -> dict[str, np.ndarray]:
    """Run ``pl_module.infer_latents`` over ``loader`` -> split dict for
    :func:`~embodied_tactile.eval.results.evaluate_latents`: ``"z"`` / ``"y"`` (n, T, d) from
    ``z_mean`` / ``y_mean`` (those the module returns; the ones ``latent`` needs are required),
    ``factors``, ``object_id``, ``action_index`` and ``seq_id`` when batches carry it.
    Usable outside the callback (evaluate.py)."""
    import torch

    need = LATENT_KEYS[latent]
    lat: dict[str, list] = {"z": [], "y": []}
    fac, obj, act, ids = [], [], [], []
    n = 0
    was_training = pl_module.training
    pl_module.eval()
    try:
        with torch.no_grad():
            for batch in loader:
                batch = _to_device(batch, pl_module.device)
                out = pl_module.infer_latents(batch)
                missing = [k for k in need if k not in out]
                if missing:
                    raise KeyError(f"infer_latents returned {sorted(out)}; latent={latent!r} needs {list(need)}")
                take = len(batch["factors"]) if max_sequences is None else min(len(batch["factors"]), max_sequences - n)
                for k in ("z", "y"):
                    if f"{k}_mean" in out:
                        lat[k].append(out[f"{k}_mean"][:take].float().cpu().numpy())
                fac.append(batch["factors"][:take].float().cpu().numpy())
                obj.append(batch["object_id"][:take].cpu().numpy())
                act.append(batch["action_index"][:take].cpu().numpy())
                if "seq_id" in batch:
                    sid = batch["seq_id"][:take]
                    ids.append(np.asarray(sid.cpu() if hasattr(sid, "cpu") else sid))
                n += take
                if max_sequences is not None and n >= max_sequences:
                    break
    finally:
        pl_module.train(was_training)
    res = {k: np.concatenate(v) for k, v in lat.items() if v}
    res.update({"factors": np.concatenate(fac), "object_id": np.concatenate(obj), "action_index": np.concatenate(act)})
    if ids:
        res["seq_id"] = np.concatenate(ids)
    return res


class KRRAlignmentCallback(Callback):
    """See module docstring. Defaults aim at <= 10 % of training time: evaluation every
    ``every_n_epochs`` epochs on at most ``max_train_sequences`` training sequences,
    ``frames_per_sequence`` final-segment frames each, Nystroem above ``nystroem_threshold``
    rows, held-out frames subsampled by ``val_frame_stride``."""

    def __init__(self, every_n_epochs: int = 10, latent: str = "y", max_train_sequences: int | None = 512,
                 max_val_sequences: int | None = None, val_frame_stride: int = 2, final_segment: float | int = 0.1,
                 frames_per_sequence: int = 2, cv: int = 3, nystroem_threshold: int = 1024, n_components: int = 256,
                 alphas=(1e-3, 1e-2, 1e-1, 1.0), gammas=(0.3, 1.0, 3.0), run_on_train_end: bool = True,
                 history_name: str = "krr_history.jsonl", seed: int = 0, n_threads: int | None = None,
                 final_alignment: Mapping[str, Any] | None = None, targets: str = DEFAULT_TARGETS):
        if latent not in LATENT_KEYS:
            raise ValueError(f"latent must be one of {sorted(LATENT_KEYS)}, got {latent!r}")
        if targets not in TARGET_ENCODINGS:
            raise ValueError(f"targets must be one of {TARGET_ENCODINGS}, got {targets!r}")
        self.targets = targets  # the factors' encoding (eval.targets), as evaluate.py's `targets`
        self.every_n_epochs = int(every_n_epochs)
        self.latent = latent
        self.max_train_sequences = max_train_sequences
        self.max_val_sequences = max_val_sequences
        self.val_frame_stride = max(1, int(val_frame_stride))
        self.align_kw = dict(final_segment=final_segment, frames_per_sequence=frames_per_sequence, cv=cv,
                             nystroem_threshold=nystroem_threshold, n_components=n_components,
                             alphas=tuple(alphas), gammas=tuple(gammas), seed=seed, n_threads=n_threads)
        # the final alignment: evaluate.py's recipe (fit_alignment defaults unless given)
        self.final_kw = dict(final_alignment or {})
        self.final_kw.setdefault("n_threads", n_threads)
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
        if self.every_n_epochs > 0 and (trainer.current_epoch + 1) % self.every_n_epochs == 0:
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

    # ------------------------------------------------------------------ work
    def _loaders(self, trainer):
        dm = trainer.datamodule
        if dm is None:
            raise RuntimeError("KRRAlignmentCallback needs trainer.datamodule (pass datamodule= to fit)")
        train = dm.train_eval_dataloader() if hasattr(dm, "train_eval_dataloader") else dm.train_dataloader()
        held_out = dm.test_dataloader() if hasattr(dm, "test_set") else dm.val_dataloader()
        return train, held_out

    def _evaluate(self, trainer, pl_module, final: bool = False) -> dict[str, float]:
        t0 = time.perf_counter()
        if self._t_start is None:
            self._t_start = t0
        train_wall = self._elapsed_before + (t0 - self._t_start) - self._cb_before - self._cb_time
        train_loader, val_loader = self._loaders(trainer)
        max_train, max_val, stride = (None, None, 1) if final else (
            self.max_train_sequences, self.max_val_sequences, self.val_frame_stride)
        align_kw = self.final_kw if final else self.align_kw
        tr = collect_latents(pl_module, train_loader, latent=self.latent, max_sequences=max_train)
        te = collect_latents(pl_module, val_loader, latent=self.latent, max_sequences=max_val)
        assert_disjoint(tr.get("seq_id"), te.get("seq_id"))
        tr, te = encode_split(tr, self.targets), encode_split(te, self.targets)
        t_inf = time.perf_counter()
        align = fit_alignment(select_latents(tr, self.latent), tr["factors"], ids=tr.get("seq_id"), **align_kw)
        x_te = select_latents(te, self.latent)[:, ::-1][:, ::stride][:, ::-1]  # keep the last frame
        pred = align.predict(x_te, ids=te.get("seq_id"))
        curve = nmse_over_time(te["factors"], pred)  # (T', 4)
        per_factor = nmse_trajectory(te["factors"], pred)  # == mean of the curve over frames
        cb = time.perf_counter() - t0
        self._cb_time += cb
        cb_total = self._cb_before + self._cb_time
        total = self._elapsed_before + time.perf_counter() - self._t_start
        metrics = {f"krr/nmse_{f}": float(v) for f, v in zip(FACTOR_NAMES, per_factor)}
        metrics.update({
            "krr/nmse_overall": overall(per_factor),
            "krr/nmse_last_overall": overall(curve[-1]),
            "krr/train_wall_time_s": float(train_wall),
            "krr/callback_time_s": float(cb),
            "krr/callback_fraction": float(cb_total / total) if total > 0 else 0.0,
        })
        row = {
            # at train end Lightning has already counted the last epoch: report the epoch trained last
            "epoch": max(0, int(trainer.current_epoch) - 1) if final else int(trainer.current_epoch),
            "step": int(trainer.global_step),
            "train_wall_time_s": float(train_wall), "callback_time_s": float(cb),
            "callback_infer_s": float(t_inf - t0), "callback_krr_s": float(cb - (t_inf - t0)),
            "callback_time_total_s": float(cb_total), "callback_fraction": metrics["krr/callback_fraction"],
            "nmse": {f: _fin(v) for f, v in zip(FACTOR_NAMES, per_factor)},
            "nmse_overall": _fin(metrics["krr/nmse_overall"]), "nmse_last": {f: _fin(v) for f, v in zip(FACTOR_NAMES, curve[-1])},
            "nmse_last_overall": _fin(metrics["krr/nmse_last_overall"]),
            "n_train": int(len(tr["factors"])), "n_test": int(len(te["factors"])), "latent": self.latent,
            "val_frame_stride": stride, "final": bool(final), "targets": self.targets,
            "alignment": {k: align.params[k] for k in ("method", "alpha", "gamma", "n_train_rows", "fit_time_s",
                                                       "final_segment", "frames_per_sequence", "cv_folds", "seed")},
        }
        if final:
            row["alignment_settings"] = {k: v for k, v in align_kw.items() if k != "n_threads"}
            self.final = row
        self.history.append(row)
        if trainer.is_global_zero:
            path = self.history_path(trainer)
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(path, "a") as fh:
                fh.write(json.dumps(row) + "\n")
        log.info("KRR alignment %sepoch %d: nmse_overall=%.4f (callback %.2fs, %.1f%% of elapsed)",
                 "(final weights, evaluate.py settings) " if final else "(periodic check) ", row["epoch"],
                 metrics["krr/nmse_overall"], cb, 100 * metrics["krr/callback_fraction"])
        return metrics

    def history_path(self, trainer) -> Path:
        """``<run folder>/krr_history.jsonl``: the trainer's root dir (the Hydra run folder),
        so evaluate.py finds it whatever loggers were configured."""
        return Path(trainer.default_root_dir) / self.history_name

    @staticmethod
    def _log_to_loggers(trainer, metrics: Mapping[str, Any]) -> None:
        for lg in trainer.loggers:
            lg.log_metrics(dict(metrics), step=trainer.global_step)


def _fin(v) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None
