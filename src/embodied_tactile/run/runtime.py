"""Run-folder plumbing shared by train.py and evaluate.py: provenance, resume, progress.

A run folder holds: ``.hydra/`` (Hydra's composed config and overrides),
``config_resolved.yaml`` (every interpolation resolved), ``checkpoints/last.ckpt`` and the
best checkpoint, ``csv/metrics.csv`` (continued across restarts: :class:`ResumableCSVLogger`),
``metrics.json``, ``split.json``, ``provenance.json`` (git commit, dirty
flag, package versions, command line) and ``git.diff`` when the tree was dirty.
"""

from __future__ import annotations

import csv
import importlib.metadata as md
import json
import logging
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import lightning as L
from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from lightning.pytorch.loggers.logger import rank_zero_experiment
from omegaconf import DictConfig, OmegaConf

from embodied_tactile.run.jsonio import write_json
from embodied_tactile.run.threadenv import TrainingRegistry, set_threads

log = logging.getLogger(__name__)

PACKAGES = (
    "embodied-tactile", "torch", "lightning", "hydra-core", "omegaconf", "torchmetrics", "librosa",
    "h5py", "numpy", "scipy", "scikit-learn", "wandb", "pyserial", "umap-learn",
)


def package_versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {}
    for name in PACKAGES:
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = None
    return out


def git_state(repo: str | os.PathLike | None = None) -> dict[str, Any]:
    """Commit, dirty flag and diff of the source tree (None where git is unavailable)."""
    repo = Path(repo or Path(__file__).resolve().parents[3])

    def git(*args: str) -> str | None:
        try:
            return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=10, check=True).stdout
        except (OSError, subprocess.SubprocessError):
            return None

    commit = git("rev-parse", "HEAD")
    diff = git("diff", "HEAD")
    return {"commit": commit.strip() if commit else None, "dirty": bool(diff), "diff": diff or ""}


def save_provenance(cfg: DictConfig, run_dir: str | os.PathLike) -> None:
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config_resolved.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    git = git_state()
    if git["diff"]:
        (run_dir / "git.diff").write_text(git["diff"])
    write_json(
        run_dir / "provenance.json",
        {
            "git_commit": git["commit"],
            "git_dirty": git["dirty"],
            "packages": package_versions(),
            "python": sys.version,
            "platform": platform.platform(),
            "argv": sys.argv,
            "cwd": os.getcwd(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        },
    )


def data_identity(cache_files: Mapping[str, str | os.PathLike],
                  trial_digests: Mapping[str, Mapping[str, str]] | None = None,
                  trials: Sequence[str] | None = None) -> dict[str, Any]:
    """What the run's data were: per field, the raw files and the digests of their stored
    bytes and trial attributes that the preparation stage computed when it built or found
    the cache (its root attrs ``sources`` / ``source_digests``; nothing is hashed again),
    and, given the preparation's ``trial_digests``, ``trials``: ``{trial: digest}`` of each
    of ``trials`` (all when None), so that a change is named per trial and trials the run
    never used do not count."""
    from embodied_tactile.data.cache import cache_info

    out: dict[str, Any] = {}
    for field, path in sorted(cache_files.items()):
        info = cache_info(path)
        out[field] = {"raw_files": [str(p) for p in info.get("sources", [])],
                      "digests": list(info.get("source_digests", []))}
        if trial_digests and field in trial_digests:
            per = trial_digests[field]
            out[field]["trials"] = {n: per[n] for n in sorted(per if trials is None else trials) if n in per}
    return out


def trial_digests(datamodule: Any) -> dict[str, dict[str, str]] | None:
    """The preparation stage's per-trial digests of a DataModule (None when it has none)."""
    prepared = getattr(datamodule, "prepared", None)
    return getattr(prepared, "trial_digests", None) or None


def data_changes(saved: Mapping[str, Any] | None, now: Mapping[str, Any]) -> list[str]:
    """How the data differ from those a run was trained on (``provenance.json``
    ``raw_data`` against :func:`data_identity` now): with per-trial digests on both sides,
    one line per trial of the run that is gone or whose data or attributes changed (other
    trials of the raw files do not count); else one line per raw file and field whose
    digest differs, a field missing, or a different number of raw files. [] when the same."""
    if not saved:
        return []
    out = []
    for field in sorted(set(saved) | set(now)):
        a, b = saved.get(field), now.get(field)
        if a is None or b is None:
            out.append(f"field {field}: {'not prepared now' if b is None else 'not in the training data'}")
            continue
        if "trials" in a and "trials" in b:
            for name, da in sorted(a["trials"].items()):
                db = b["trials"].get(name)
                if db is None:
                    out.append(f"trial {name}: not in the data now ({', '.join(b['raw_files'])})")
                elif db != da:
                    out.append(f"trial {name}: its {field} data or attributes changed since training "
                               f"(digest {da[:12]} -> {db[:12]}; {', '.join(b['raw_files'])})")
            continue
        if len(a["digests"]) != len(b["digests"]):
            out.append(f"field {field}: {len(a['digests'])} raw file(s) at training, {len(b['digests'])} now "
                       f"({', '.join(b['raw_files'])})")
            continue
        for i, (da, db) in enumerate(zip(a["digests"], b["digests"])):
            if da != db:
                path = b["raw_files"][i] if i < len(b["raw_files"]) else "?"
                out.append(f"{path}: its trials or their {field} data changed since training (digest {da[:12]} -> {db[:12]})")
    return out


def record_data_identity(run_dir: str | os.PathLike, cache_files: Mapping[str, str | os.PathLike],
                         trial_digests: Mapping[str, Mapping[str, str]] | None = None,
                         trials: Sequence[str] | None = None) -> None:
    """Add :func:`data_identity` (per trial of ``trials``, the run's split, when the
    preparation's ``trial_digests`` are given) to ``provenance.json`` as ``raw_data``."""
    path = Path(run_dir) / "provenance.json"
    prov = json.loads(path.read_text()) if path.is_file() else {}
    prov["raw_data"] = data_identity(cache_files, trial_digests, trials)
    write_json(path, prov)


def peak_rss_bytes() -> int:
    """Peak resident memory of this process and its finished children (Linux: KiB units)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return int(max(own, children) * 1024)


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


def use_plain_progress(setting: str | bool) -> bool:
    """Plain log lines under launchers (multirun) or without a terminal; bars otherwise."""
    if isinstance(setting, bool):
        return setting
    if setting != "auto":
        return str(setting).lower() in ("1", "true", "yes", "plain")
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
            return True
    except (ImportError, ValueError):
        pass
    return not sys.stdout.isatty()


class HandOverStatistics(L.Callback):
    """Hands the DataModule's training statistics (``datamodule.statistics``, computed in its
    ``setup("fit")``) to the module (``use_data_statistics``) at the start of fit, after a
    resumed run's checkpoint is restored and before the first step: the data owns its
    statistics, the model never reaches for the DataModule. A module without
    ``use_data_statistics`` or a DataModule without statistics is left as it is."""

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        statistics = getattr(trainer.datamodule, "statistics", None)
        if statistics is not None and hasattr(pl_module, "use_data_statistics"):
            pl_module.use_data_statistics(statistics)


class PlainProgress(L.Callback):
    """One log line per epoch with the logged losses and the elapsed wall time."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.global_rank != 0:
            return
        m = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
        keys = [k for k in ("train/loss", "train/nll", "train/kl_z", "train/kl_y", "val/elbo", "krr/nmse_overall") if k in m]
        body = "  ".join(f"{k}={m[k]:.4g}" for k in keys)
        log.info("epoch %d/%d  step %d  %s  (%.0f s)", trainer.current_epoch + 1, trainer.max_epochs, trainer.global_step, body, time.perf_counter() - self.t0)


# ----------------------------------------------------------------------------- threads
def available_cores() -> int:
    """CPU cores this process may run on (affinity-aware where the OS tells)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return max(1, os.cpu_count() or 1)


def concurrent_jobs(launcher_n_jobs: Any = None, processes_per_node: Any = 1, cores: int | None = None) -> int:
    """How many training processes share this machine: the joblib launcher's ``n_jobs``
    (joblib's convention: -1 = one per core, -2 = all but one, ...) times the DDP processes
    per node. Anything unset counts as 1."""
    cores = available_cores() if cores is None else int(cores)
    jobs = 1
    if launcher_n_jobs not in (None, "", 0):
        n = int(launcher_n_jobs)
        jobs = n if n > 0 else max(1, cores + 1 + n)
    try:
        procs = max(1, int(processes_per_node))
    except (TypeError, ValueError):  # devices: "auto" and the like
        procs = 1
    return max(1, jobs * procs)


def thread_budget(setting: Any, jobs: int, cores: int | None = None) -> int:
    """Threads per training: its fair share of the cores, ``max(1, cores // jobs)`` for
    ``jobs`` trainings sharing the machine, and no more than ``setting`` when that is a
    positive integer (``auto`` / null: the share alone). A setting is a ceiling, never a
    demand: two trainings at 2 threads each on 2 cores ran 4x slower than at 1 thread each
    (oversubscription), whatever threads each had been given."""
    cores = available_cores() if cores is None else int(cores)
    share = max(1, cores // max(1, int(jobs)))
    if setting in (None, "auto", "null"):
        return share
    n = int(setting)
    if n < 1:
        raise ValueError(f"threads must be a positive integer or 'auto', got {setting!r}")
    return min(n, share)


#: the registry of this process (train.py registers through :func:`configure_threads`)
REGISTRY = TrainingRegistry()


class ThreadShare(L.Callback):
    """A training's threads: its fair share of the cores among the trainings on this machine
    (:func:`thread_budget` of ``setting`` and ``max(declared jobs, live trainings)``),
    applied when built and again at every training epoch's start, so that a training
    started beside a running one takes half the cores at once and the running one gives
    them up at its next epoch. Registers this process in ``registry``."""

    def __init__(self, setting: Any = "auto", declared_jobs: int = 1, cores: int | None = None,
                 registry: TrainingRegistry | None = None) -> None:
        self.setting = setting
        self.declared_jobs = max(1, int(declared_jobs))
        self.cores = available_cores() if cores is None else int(cores)
        self.registry = REGISTRY if registry is None else registry
        self.registry.register()
        self.jobs = 1
        self.threads = 0
        self.apply()

    def decide(self) -> tuple[int, int]:
        """(trainings sharing the machine, threads for this one), from a fresh count."""
        jobs = max(self.declared_jobs, self.registry.count())
        return jobs, thread_budget(self.setting, jobs, self.cores)

    def apply(self) -> int:
        """Count again and set the threads where the share changed; the threads."""
        self.jobs, n = self.decide()
        if n != self.threads:
            if self.threads:
                log.info("threads %d -> %d (%d training(s) on this machine)", self.threads, n, self.jobs)
            self.threads = set_threads(n)
        return self.threads

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.apply()


def configure_threads(cfg: DictConfig, registry: TrainingRegistry | None = None) -> ThreadShare:
    """Threads for a train.py process from ``cfg.threads`` (``auto`` or a ceiling) and the
    trainings sharing the machine: those registered live (:class:`TrainingRegistry`), at
    least the concurrent jobs this process knows of (the Hydra launcher's n_jobs x the
    trainer's DDP devices per node). The returned :class:`ThreadShare` is a callback that
    keeps the share up to date at every epoch."""
    n_jobs = None
    try:
        from hydra.core.hydra_config import HydraConfig

        hc = HydraConfig.get()
        if hc.mode is not None and str(hc.mode).endswith("MULTIRUN"):
            n_jobs = OmegaConf.select(hc, "launcher.n_jobs", default=None)
    except (ImportError, ValueError):  # not inside a Hydra app
        pass
    trainer = cfg.get("trainer") or {}
    procs = trainer.get("devices", 1) if "ddp" in str(trainer.get("strategy", "")) else 1
    return ThreadShare(cfg.get("threads", "auto"), concurrent_jobs(n_jobs, procs), registry=registry)


def configure_compile(cfg: DictConfig, model) -> int:
    """``cfg.compile_convs`` (default false): :func:`~embodied_tactile.model.networks.compile_convs`
    on the model's conv encoders / decoders (training steps on CPU only). Off by default:
    at the default budget it was measured no faster and its compilation took longer than
    a default run's training (docs/reference/model.md "Speed", ``benchmarks/bench_step_levers.py``).
    Returns the number of networks switched on."""
    if not bool(cfg.get("compile_convs", False)):
        return 0
    from ..model.networks import compile_convs

    return compile_convs(model, True)
