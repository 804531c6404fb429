"""A run folder belongs to one run: the lock, the resume check, stop signals, atomic checkpoints.

* :func:`claim` -- an exclusive lock on ``<run>/.lock`` (``fcntl.flock``: released by the
  kernel when the process ends, kill -9 included) held while a training runs; a second
  start in the folder is refused naming the holder's pid and host. Then, when the folder
  already holds a run (``checkpoints/*.ckpt`` or a finished / interrupted
  ``metrics.json``), the saved ``config_resolved.yaml`` is compared with the new config:
  a difference in a key outside :data:`MAY_CHANGE` (modality, actions, split, model
  options, seed, ...) is refused, naming the keys. Both refusals happen before anything is
  written and raise :class:`RunFolderError` (train.py: one line, exit 2). train.py refuses
  a resume on raw data other than the run's (``provenance.json`` ``raw_data``) the same
  way, once the preparation stage has computed their digests.
* :class:`StopSignals` -- SIGTERM / SIGINT stop the training at the next step:
  ``last.ckpt`` is saved, ``metrics.json`` says ``interrupted``, the exit status is 143 /
  130 (128 + signal number), so that a scheduler can requeue the job.
* :class:`AtomicCheckpointIO` -- a checkpoint is written to ``<name>.tmp-<pid>``, fsync-ed
  and renamed over ``<name>``: a file with a checkpoint's name is always complete; a full
  disk leaves the previous file and raises :class:`CheckpointWriteError` naming the file.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import signal
import socket
import time
from pathlib import Path
from typing import Any, Mapping

from omegaconf import DictConfig, OmegaConf

from embodied_tactile.run.settings import SettingsError

log = logging.getLogger(__name__)

#: train.py's exit status when a checkpoint cannot be written (EX_IOERR); a refused start
#: exits 2 (settings.EXIT_BAD_SETTINGS), a stop signal 128 + its number (130, 143).
EXIT_CHECKPOINT_WRITE = 74

LOCK_FILE = ".lock"

#: Keys that may differ between the saved config of a run folder and a restart of it
#: (prefixes of dotted keys): how long and where it runs, what it logs. Every other key
#: shapes the model, the data or the optimisation, and a change to it is refused.
MAY_CHANGE: tuple[str, ...] = (
    "trainer.max_epochs", "trainer.max_steps", "trainer.max_time", "trainer.enable_progress_bar",
    "trainer.accelerator", "trainer.devices", "trainer.num_nodes", "trainer.strategy",
    "trainer.log_every_n_steps", "trainer.default_root_dir",
    "threads", "plain_progress", "resume", "validate_at_end", "compile_convs", "tags", "task_name",
    "paths", "logger", "callbacks",
    "data.data_dir", "data.num_workers", "data.sim_workers", "data.preprocess_workers", "data.split_file",
    "data.allow_large_population",
)


class RunFolderError(SettingsError):
    """A start refused because the run folder belongs to another run or training."""


class CheckpointWriteError(OSError):
    """A checkpoint could not be written; the previous file of that name is unchanged."""


# ----------------------------------------------------------------------------- lock
_held: dict[str, int] = {}  # resolved run folder -> fd of its lock, for this process


def _is_rank_zero() -> bool:
    """DDP child processes (LOCAL_RANK / RANK > 0) share rank 0's run folder and lock."""
    return all(os.environ.get(v, "0") in ("", "0") for v in ("LOCAL_RANK", "RANK", "NODE_RANK"))


def lock(run_dir: str | os.PathLike) -> None:
    """Hold ``<run_dir>/.lock`` for the rest of this process (idempotent). RunFolderError
    naming the holder when another process holds it."""
    run_dir = Path(run_dir).resolve()
    if str(run_dir) in _held or not _is_rank_zero():
        return
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        os.close(fd)
        if err.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
            raise
        try:
            holder = json.loads(path.read_text() or "{}")
        except (OSError, ValueError):
            holder = {}
        raise RunFolderError(
            f"run folder {run_dir} is in use by another training (pid {holder.get('pid', '?')} on host "
            f"{holder.get('host', '?')}, started {holder.get('started', '?')}); wait for it to end or give "
            "another hydra.run.dir") from None
    os.ftruncate(fd, 0)
    os.write(fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                             "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}).encode())
    _held[str(run_dir)] = fd


def release(run_dir: str | os.PathLike) -> None:
    """Drop this process's lock on ``run_dir`` (the file stays; the kernel lock goes)."""
    fd = _held.pop(str(Path(run_dir).resolve()), None)
    if fd is not None:
        os.close(fd)


# ----------------------------------------------------------------------------- resume check
def _flatten(node: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(node, Mapping):
        out: dict[str, Any] = {}
        for k, v in node.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out or {prefix[:-1]: {}}
    return {prefix[:-1]: node}


def _may_change(key: str) -> bool:
    return any(key == p or key.startswith(p + ".") for p in MAY_CHANGE)


def config_changes(saved: Mapping[str, Any], new: Mapping[str, Any]) -> dict[str, tuple[Any, Any]]:
    """``{dotted key: (saved value, new value)}`` of the keys outside :data:`MAY_CHANGE`
    whose values differ (a key present on one side only counts, with ``<absent>``)."""
    a, b = _flatten(saved), _flatten(new)
    missing = "<absent>"
    return {k: (a.get(k, missing), b.get(k, missing)) for k in sorted(set(a) | set(b))
            if not _may_change(k) and a.get(k, missing) != b.get(k, missing)}


def holds_run(run_dir: str | os.PathLike) -> bool:
    """The folder holds a run's results: a checkpoint, or a finished / interrupted metrics.json."""
    run_dir = Path(run_dir)
    if any(p.is_file() for p in (run_dir / "checkpoints").glob("*.ckpt")):
        return True
    try:
        status = json.loads((run_dir / "metrics.json").read_text()).get("status")
    except (OSError, ValueError, AttributeError):
        return False
    return status in ("finished", "interrupted")


def task_config(cfg: DictConfig) -> dict:
    """The resolved config without Hydra's own node (what config_resolved.yaml holds)."""
    data = OmegaConf.to_container(cfg, resolve=True)
    data.pop("hydra", None)
    return data


def check_resume(cfg: DictConfig, run_dir: str | os.PathLike) -> None:
    """RunFolderError when ``run_dir`` holds a run whose saved config differs from ``cfg``
    in a key that shapes the model or the data, or when ``resume=false`` would start a new
    training over it."""
    run_dir = Path(run_dir)
    saved_path = run_dir / "config_resolved.yaml"
    if not _is_rank_zero() or not holds_run(run_dir):
        return
    if not bool(cfg.get("resume", True)):
        raise RunFolderError(f"run folder {run_dir} holds a run and resume=false would train a new one over it; "
                             "give another hydra.run.dir")
    if not saved_path.is_file():
        return  # a run of before config_resolved.yaml: nothing to compare
    try:
        saved = OmegaConf.to_container(OmegaConf.load(saved_path), resolve=False)
    except Exception as err:  # noqa: BLE001 -- a damaged yaml: refuse, naming it
        raise RunFolderError(f"{saved_path}: unreadable ({type(err).__name__}: {err}); cannot check that "
                             "this start continues the same run") from None
    changed = config_changes(saved, task_config(cfg))
    if changed:
        shown = "; ".join(f"{k}: {a!r} -> {b!r}" for k, (a, b) in list(changed.items())[:4])
        raise RunFolderError(
            f"run folder {run_dir} holds a run trained with other settings; refusing to resume it with other "
            f"values of {', '.join(changed)} (saved -> now: {shown}{'; ...' if len(changed) > 4 else ''}); "
            "a resume may change only how long and where it runs (trainer.max_epochs, threads, paths, logger, "
            "callbacks, ...): give another hydra.run.dir for a new run")


def claim(cfg: DictConfig, run_dir: str | os.PathLike) -> None:
    """Lock the run folder, then check that this start may continue what it holds; remove
    the temporary files of checkpoint writes that a killed process left (the lock says no
    writer is alive)."""
    lock(run_dir)
    check_resume(cfg, run_dir)
    if _is_rank_zero():
        for tmp in (Path(run_dir) / "checkpoints").glob("*.ckpt.tmp-*"):
            log.warning("removing %s: a checkpoint write that did not finish", tmp)
            tmp.unlink(missing_ok=True)


def claim_at_entry(config: DictConfig) -> None:
    """:func:`claim` from Hydra's ``on_run_start`` (before Hydra writes ``.hydra/`` or the
    log): the run folder is ``hydra.run.dir``; ``hydra.runtime.output_dir`` is set to it
    (run_job sets the same value later) so that the config resolves."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import open_dict, read_write

    run_dir = OmegaConf.select(config, "hydra.run.dir")
    if not run_dir:
        return
    with read_write(config.hydra.runtime), open_dict(config.hydra.runtime):
        config.hydra.runtime.output_dir = os.path.abspath(str(run_dir))
    HydraConfig.instance().set_config(config)
    claim(config, run_dir)


# ----------------------------------------------------------------------------- stop signals
try:
    from lightning.pytorch import Callback as _Callback
except ImportError:  # pragma: no cover
    _Callback = object  # type: ignore[misc,assignment]


class StopRequested(BaseException):
    """SIGTERM / SIGINT outside the training steps (data preparation, set-up)."""

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        super().__init__(f"stopped by {signal.Signals(signum).name}")


class StopSignals(_Callback):
    """SIGTERM / SIGINT stop a training cleanly. :meth:`install` at the start of train.py;
    as a Lightning callback it takes the signals over from Lightning's own SIGTERM handler
    (which raises out of the loop without a checkpoint) between ``on_train_start`` and
    ``on_train_end``: there a signal sets ``trainer.should_stop`` and the step under way
    finishes; outside it (data preparation, set-up) the signal raises
    :class:`StopRequested`. A second signal ends the process at once with the default
    action. :meth:`exit_code` is 128 + the signal number (130 SIGINT, 143 SIGTERM)."""

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self) -> None:
        self.received: int | None = None
        self._trainer = None
        self._deferred = False

    def install(self) -> "StopSignals":
        for sig in self.SIGNALS:
            signal.signal(sig, self._handle)
        return self

    def restore(self) -> None:
        for sig in self.SIGNALS:
            signal.signal(sig, signal.SIG_DFL if sig == signal.SIGTERM else signal.default_int_handler)

    def on_train_start(self, trainer, pl_module) -> None:
        self._trainer = trainer
        self.install()  # over Lightning's SIGTERM handler (Lightning restores ours at teardown)
        if self.received is not None:
            trainer.should_stop = True

    def on_train_end(self, trainer, pl_module) -> None:
        self._trainer = None

    def defer(self) -> None:
        """From now on a signal is only recorded (after fit: the run's own checkpoints are
        written; what is left is its final validation and metrics.json)."""
        self._deferred = True

    def _handle(self, signum: int, frame) -> None:
        if self.received is not None:  # asked twice: stop now
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        self.received = signum
        if self._deferred:
            return
        if self._trainer is None:
            raise StopRequested(signum)
        self._trainer.should_stop = True
        log.warning("%s received: stopping after the current step; last.ckpt is saved", signal.Signals(signum).name)

    @property
    def name(self) -> str | None:
        return signal.Signals(self.received).name if self.received is not None else None

    def exit_code(self) -> int | None:
        return None if self.received is None else 128 + int(self.received)


# ----------------------------------------------------------------------------- checkpoints
try:
    from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO as _TorchIO
except ImportError:  # pragma: no cover
    _TorchIO = object  # type: ignore[misc,assignment]


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class AtomicCheckpointIO(_TorchIO):
    """Lightning's torch checkpoint IO written atomically: ``<path>.tmp-<pid>``, flush,
    fsync, ``os.replace`` onto ``path``, fsync of the folder. On a write error the temporary
    file is removed, the previous ``path`` is untouched and :class:`CheckpointWriteError`
    names the file and the OS reason."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any | None = None) -> None:
        import io

        import torch

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
        buf = io.BytesIO()  # serialised first (as Lightning's own writer does): a write error is a plain OSError
        torch.save(checkpoint, buf)
        try:
            with open(tmp, "wb") as fh:
                fh.write(buf.getbuffer())
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except OSError as err:
            try:
                tmp.unlink()
            except OSError:
                pass
            raise CheckpointWriteError(
                f"cannot write checkpoint {path}: {err.strerror or err} ({len(buf.getbuffer()) / 1e6:.1f} MB; no "
                "partial file left, the run's earlier checkpoints are kept)") from err
        _fsync_dir(path.parent)
