"""Resuming a run in its folder: the newest readable checkpoint (an unreadable one renamed
``<name>.unreadable``) and ``csv/metrics.csv`` continued from the checkpoint's step, the rows a
killed training logged after it set aside in ``csv/metrics.discarded.csv``
(:class:`ResumableCSVLogger`)."""

from __future__ import annotations

import csv
import logging
import os
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from lightning.pytorch.loggers.logger import rank_zero_experiment

log = logging.getLogger(__name__)


def read_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Load a Lightning checkpoint on the CPU; ``ValueError(path: reason)`` when it cannot be
    read or lacks what a resume needs (``state_dict``, ``global_step``)."""
    import torch

    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # torch raises RuntimeError, EOFError, UnpicklingError, ... on damaged files
        raise ValueError(f"{path}: unreadable checkpoint ({type(err).__name__}: {err})") from err
    missing = [k for k in ("state_dict", "global_step") if not isinstance(ckpt, Mapping) or k not in ckpt]
    if missing:
        raise ValueError(f"{path}: not a Lightning checkpoint (missing {missing})")
    return dict(ckpt)


def _set_aside(path: Path) -> Path:
    """Rename an unreadable checkpoint to ``<name>.unreadable`` (``-1``, ``-2``... when taken):
    kept for inspection, out of the way of Lightning's ``last.ckpt``."""
    target = path.with_name(path.name + ".unreadable")
    n = 0
    while target.exists():
        n += 1
        target = path.with_name(f"{path.name}.unreadable-{n}")
    path.rename(target)
    return target


def find_resume_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    """The checkpoint a restart in ``run_dir`` continues from: ``checkpoints/last.ckpt``, or,
    when that is unreadable, the newest readable ``checkpoints/*.ckpt`` (by modification
    time). Each unreadable file is named in a warning and, on rank 0, renamed to
    ``<name>.unreadable`` (never deleted), so that the new ``last.ckpt`` takes its place.
    None (start fresh, with a warning when checkpoints existed) if none is readable."""
    from lightning.pytorch.utilities import rank_zero_only

    folder = Path(run_dir) / "checkpoints"
    found = [p for p in folder.glob("*.ckpt") if p.is_file()]
    found.sort(key=lambda p: (p.name != "last.ckpt", -p.stat().st_mtime, p.name))
    for path in found:
        try:
            read_checkpoint(path)
        except ValueError as err:
            kept = f"; kept as {_set_aside(path).name}" if rank_zero_only.rank == 0 else ""
            log.warning("cannot resume from %s%s; trying the next checkpoint", err, kept)
            continue
        if path.name != "last.ckpt":
            log.warning("resuming from %s, the newest readable checkpoint in %s", path, folder)
        return path
    if found:
        log.warning("no readable checkpoint in %s (%s): training starts from scratch", folder,
                    ", ".join(p.name for p in found))
    return None


def _read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        return list(reader.fieldnames or []), list(reader)


def _write_csv(path: Path, keys: Sequence[str], rows: Sequence[Mapping[str, Any]]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(keys))
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)


def _row_step(row: Mapping[str, str]) -> float:
    try:
        return float(row.get("step") or "nan")
    except ValueError:
        return float("nan")


class _ContinuedExperimentWriter(ExperimentWriter):
    """Lightning's CSV writer deletes an existing ``metrics.csv``; this one continues it.

    Rows logged at a step <= ``resume_step`` (the global step of the checkpoint the run
    continues from) stay; later rows (training that a resume after a kill discards, or every
    row when the run starts afresh: ``resume_step=None``) move to ``metrics.discarded.csv``
    in the same folder, so the file never mixes two trainings and nothing is deleted. Rows
    at ``resume_step`` itself holding a metric that the resumed run logs again move there
    too (:meth:`save`)."""

    DISCARDED_FILE = "metrics.discarded.csv"

    def __init__(self, log_dir: str, resume_step: int | None) -> None:
        self.resume_step = resume_step
        self._old_at_resume = 0  # rows at resume_step kept from before this run (set by _check_log_dir_exists)
        super().__init__(log_dir=log_dir)

    def _discard(self, path: Path, keys: Sequence[str], dropped: Sequence[Mapping[str, str]], why: str) -> None:
        old = path.with_name(self.DISCARDED_FILE)
        old_keys, old_rows = _read_csv(old) if old.is_file() else ([], [])
        _write_csv(old, sorted(set(old_keys) | set(keys)), [*old_rows, *dropped])
        log.warning("%s: %d row(s) %s moved to %s", path, len(dropped), why, old)

    def save(self) -> None:
        """A kept row at the resume step (written before this run started) holding a metric
        that this run logs again at that step (training after the checkpoint was written:
        the next epoch's first step, its learning rate) moves to ``metrics.discarded.csv``
        before the new rows are written, at whichever save they come: one row per step and
        metric. (Lightning saves after every ``log_metrics`` call.)"""
        path = Path(self.metrics_file_path)
        if self._old_at_resume and self.metrics and path.is_file():
            again = {k for m in self.metrics if m.get("step") == self.resume_step
                     for k, v in m.items() if v is not None} - {"step", "epoch"}
            if again:
                keys, rows = _read_csv(path)
                seen, keep, dropped = 0, [], []
                for r in rows:
                    if _row_step(r) == self.resume_step and seen < self._old_at_resume:
                        seen += 1
                        if again & {k for k, v in r.items() if v not in ("", None)}:
                            dropped.append(r)
                            continue
                    keep.append(r)
                if dropped:
                    self._discard(path, keys, dropped, f"at step {self.resume_step} that this run logs again")
                    _write_csv(path, keys, keep)
                    self._old_at_resume -= len(dropped)
        super().save()

    def _check_log_dir_exists(self) -> None:  # called by the base __init__ instead of deleting
        path = Path(self.metrics_file_path)
        if not path.is_file():
            return
        keys, rows = _read_csv(path)
        if self.resume_step is None:
            kept, dropped = [], rows
        else:
            kept = [r for r in rows if not _row_step(r) > self.resume_step]
            dropped = [r for r in rows if _row_step(r) > self.resume_step]
        if dropped:
            self._discard(path, keys, dropped, f"logged after step {self.resume_step} (training this run does not continue)")
        if kept:
            if dropped:
                _write_csv(path, keys, kept)
            self.metrics_keys = sorted(keys)
            self._old_at_resume = sum(_row_step(r) == self.resume_step for r in kept)
        else:
            path.unlink()  # its rows are in metrics.discarded.csv


class ResumableCSVLogger(CSVLogger):
    """:class:`~lightning.pytorch.loggers.CSVLogger` whose ``metrics.csv`` continues across
    restarts in one run folder (Lightning's deletes it). Set ``resume_step`` before
    ``fit`` (:func:`continue_logs` does): rows up to that global step are kept, later ones
    move to ``metrics.discarded.csv`` (see :class:`_ContinuedExperimentWriter`)."""

    def __init__(self, *args: Any, resume_step: int | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.resume_step = resume_step

    @property
    @rank_zero_experiment
    def experiment(self) -> ExperimentWriter:
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = _ContinuedExperimentWriter(self.log_dir, self.resume_step)
        return self._experiment


def continue_logs(loggers: Sequence[Any], ckpt_path: str | os.PathLike | None) -> None:
    """Tell each :class:`ResumableCSVLogger` the global step the run continues from
    (None: a fresh start)."""
    step = None
    if ckpt_path is not None:
        import torch

        step = int(torch.load(ckpt_path, map_location="cpu", weights_only=False, mmap=True)["global_step"])
    for lg in loggers:
        if isinstance(lg, ResumableCSVLogger):
            lg.resume_step = step


__all__ = ["ResumableCSVLogger", "continue_logs", "find_resume_checkpoint", "read_checkpoint"]
