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
  The split is part of the run (:func:`check_split_file`): a split file that moves
  trials of the run's ``split.json`` or puts a trial on two sides is refused the same way.
  The length too (:func:`check_length`): fewer epochs than the checkpoint's are refused;
  the same command on a finished run raises :class:`RunFinished` (train.py: says so, exit
  0, no file touched, ``.lock`` included); more epochs continue it. The resume checkpoint
  must fit the run's model (:func:`check_checkpoint_fits`): a misfit is refused the same way.
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
from typing import Any, Mapping, Sequence

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
_created: set[str] = set()  # resolved run folders this process created (lock): discard_new may remove them


def _is_rank_zero() -> bool:
    """DDP child processes (LOCAL_RANK / RANK > 0) share rank 0's run folder and lock."""
    return all(os.environ.get(v, "0") in ("", "0") for v in ("LOCAL_RANK", "RANK", "NODE_RANK"))


def try_lock(path: str | os.PathLike, shared: bool = False) -> tuple[int | None, dict]:
    """A non-blocking ``flock`` on the file ``path`` (created when absent, unless ``shared``:
    a probe that never creates it). -> ``(fd, {})`` when taken (closing the fd releases
    it; -1 for a probe of a file that does not exist), ``(None, holder)`` when another process holds it (``holder``: what that process
    recorded in the file, :func:`write_holder`; ``{}`` when unreadable or absent)."""
    try:
        fd = os.open(path, os.O_RDONLY if shared else os.O_RDWR | os.O_CREAT, 0o644)
    except FileNotFoundError:
        if not shared:
            raise
        return -1, {}  # no lock file: nobody holds it
    try:
        fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
    except OSError as err:
        os.close(fd)
        if err.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
            raise
        try:
            holder = json.loads(Path(path).read_text() or "{}")
        except (OSError, ValueError):
            holder = {}
        return None, holder if isinstance(holder, dict) else {}
    return fd, {}


def write_holder(fd: int) -> None:
    """Record this process (pid, host, start time) in a lock file it holds."""
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                              "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}).encode(), 0)


def lock(run_dir: str | os.PathLike, record: bool = True) -> None:
    """Hold ``<run_dir>/.lock`` for the rest of this process (idempotent). RunFolderError
    naming the holder when another process holds it. ``record=False`` leaves the file's
    content (the previous holder) as it is until :func:`record_holder`: a start that is
    then refused or finds the run finished changes no byte of the folder."""
    run_dir = Path(run_dir).resolve()
    if str(run_dir) in _held or not _is_rank_zero():
        return
    if not run_dir.exists():
        _created.add(str(run_dir))
    run_dir.mkdir(parents=True, exist_ok=True)
    fd, holder = try_lock(run_dir / LOCK_FILE)
    if fd is None:
        raise RunFolderError(
            f"run folder {run_dir} is in use by another training (pid {holder.get('pid', '?')} on host "
            f"{holder.get('host', '?')}, started {holder.get('started', '?')}); wait for it to end or give "
            "another hydra.run.dir") from None
    _held[str(run_dir)] = fd
    if record:
        record_holder(run_dir)


def record_holder(run_dir: str | os.PathLike) -> None:
    """Write this process (pid, host, start time) into the lock file it holds (what a
    refused second start names)."""
    fd = _held.get(str(Path(run_dir).resolve()))
    if fd is not None:
        write_holder(fd)


def training_holder(run_dir: str | os.PathLike) -> dict | None:
    """The training that holds ``<run_dir>/.lock`` now (``{"pid", "host", "started"}``, as
    it recorded itself), or None when no process holds it. A probe: a shared lock taken and
    dropped at once (a killed training's lock is gone with its process)."""
    run_dir = Path(run_dir)
    if str(run_dir.resolve()) in _held:
        return {"pid": os.getpid(), "host": socket.gethostname(), "started": "?"}
    fd, holder = try_lock(run_dir / LOCK_FILE, shared=True)
    if fd is None:
        return {k: holder.get(k, "?") for k in ("pid", "host", "started")}
    if fd >= 0:
        os.close(fd)  # drops the probe's shared lock
    return None


def discard_new(run_dir: str | os.PathLike) -> bool:
    """Remove ``run_dir`` whole when this process created it (:func:`lock`) and it holds no
    run: a start refused before training leaves nothing behind (Hydra's ``.hydra/`` and log
    included). False (nothing removed) for a folder that existed before, e.g. a multirun
    job's, which Hydra creates and whose reason the sweep's table reads."""
    import shutil

    key = str(Path(run_dir).resolve())
    if key not in _created or holds_run(run_dir):
        return False
    release(run_dir)
    shutil.rmtree(key, ignore_errors=True)
    _created.discard(key)
    return True


def refuse(run_dir: str | os.PathLike, err: Exception, resuming: bool) -> None:
    """A start refused before training (a bad setting, a dead channel, another run's split
    or data): one line and exit 2 (:func:`~embodied_tactile.run.settings.fail`). A new run's
    folder is removed when this process created it (:func:`discard_new`), else it gets
    ``metrics.json`` ``failed`` with the reason (a multirun job); a folder that holds a run
    is left byte-identical."""
    from embodied_tactile.jsonio import write_json
    from embodied_tactile.run.settings import fail

    if not resuming and not discard_new(run_dir):
        write_json(Path(run_dir) / "metrics.json", {"status": "failed", "error": str(err)})
    fail(err)


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
    from embodied_tactile.model.compat import ADDED_CONFIG_KEYS, DROPPED_CONFIG_KEYS, current_target

    def today(flat: dict) -> dict:  # a config saved before a module moved or a key was added reads as today's
        return {k: current_target(v) if k.endswith("_target_") and isinstance(v, str) else v
                for k, v in {**ADDED_CONFIG_KEYS, **flat}.items() if k not in DROPPED_CONFIG_KEYS}

    a, b = today(_flatten(saved)), today(_flatten(new))
    missing = "<absent>"
    return {k: (a.get(k, missing), b.get(k, missing)) for k in sorted(set(a) | set(b))
            if not _may_change(k) and a.get(k, missing) != b.get(k, missing)}


def holds_run(run_dir: str | os.PathLike) -> bool:
    """The folder holds a run's results: a checkpoint, or a finished / interrupted metrics.json."""
    run_dir = Path(run_dir)
    if any(p.is_file() for p in (run_dir / "checkpoints").glob("*.ckpt")):
        return True
    return run_status(run_dir) in ("finished", "interrupted")


def run_status(run_dir: str | os.PathLike) -> str | None:
    """The ``status`` its ``metrics.json`` records, or None (no file, or not one that says)."""
    try:
        return json.loads((Path(run_dir) / "metrics.json").read_text()).get("status")
    except (OSError, ValueError, AttributeError):
        return None


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


# ----------------------------------------------------------------------------- split
SPLIT_SIDES = ("train", "val", "test")


def read_split(path: str | os.PathLike) -> dict[str, list[str]]:
    """The trial names per side of a split file (``train`` / ``val`` / ``test``; a file of
    before the validation side has ``train`` / ``val``, read as train / test).
    RunFolderError naming the file when it is not a split file."""
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
        if not isinstance(raw, Mapping) or not all(isinstance(raw.get(k, []), list) for k in SPLIT_SIDES):
            raise ValueError("no lists of trial names under train / val / test")
    except (OSError, ValueError) as err:
        raise RunFolderError(f"{path}: not a split file ({type(err).__name__}: {err})") from None
    if "test" not in raw:
        raw = {"train": raw.get("train", []), "val": [], "test": raw.get("val", [])}
    return {k: [str(n) for n in raw.get(k, [])] for k in SPLIT_SIDES}


def _sides(split: Mapping[str, Sequence[str]]) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for side in SPLIT_SIDES:
        for name in split.get(side, []):
            out.setdefault(name, []).append(side)
    return out


def _shown(items: Sequence[str], n: int = 5) -> str:
    return "; ".join(items[:n]) + (f"; ... ({len(items)} in all)" if len(items) > n else "")


def split_overlap(split: Mapping[str, Sequence[str]]) -> list[str]:
    """``"<trial> (train and test)"`` for each trial a split puts on more than one side."""
    return [f"{name} ({' and '.join(sides)})" for name, sides in sorted(_sides(split).items()) if len(sides) > 1]


def split_moves(saved: Mapping[str, Sequence[str]], new: Mapping[str, Sequence[str]]) -> list[str]:
    """``"<trial>: train -> test"`` for each trial whose side differs between two splits
    (``absent`` where a split does not name it). [] when they are the same."""
    a, b = _sides(saved), _sides(new)
    return [f"{name}: {'+'.join(a.get(name, ['absent']))} -> {'+'.join(b.get(name, ['absent']))}"
            for name in sorted(set(a) | set(b)) if sorted(a.get(name, [])) != sorted(b.get(name, []))]


def check_split_file(cfg: DictConfig, run_dir: str | os.PathLike) -> None:
    """The split is part of a run's identity. RunFolderError when the split file the run
    would read (``data.split_file``, when it exists) puts a trial on two sides (a test
    trial trained on), or, for a folder that holds a run, when it differs from the run's
    own ``split.json``: the message names the trials that move."""
    path = OmegaConf.select(cfg, "data.split_file", default=None)
    if not path or not Path(str(path)).is_file() or not _is_rank_zero():
        return
    split = read_split(path)
    both = split_overlap(split)
    if both:
        raise RunFolderError(f"split file {path} puts {len(both)} trial(s) on two sides: {_shown(both)}; a test "
                             "trial is never trained on: fix the file or give another data.split_file")
    own = Path(run_dir) / "split.json"
    if holds_run(run_dir) and own.is_file() and Path(str(path)).resolve() != own.resolve():
        check_same_split(run_dir, split, f"split file {path}")


def check_same_split(run_dir: str | os.PathLike, split: Mapping[str, Sequence[str]], what: str) -> None:
    """RunFolderError naming the trials that move when ``split`` is not the run's own
    ``split.json`` (nothing to compare when the run has none)."""
    own = Path(run_dir) / "split.json"
    if not own.is_file():
        return
    moves = split_moves(read_split(own), split)
    if moves:
        raise RunFolderError(
            f"run folder {run_dir} was trained on the split in {own}; {what} moves {len(moves)} trial(s): "
            f"{_shown(moves)}; refusing to resume it on another split (give another hydra.run.dir for a new run)")


def served_split(datamodule: Any) -> dict[str, list[str]] | None:
    """The trial names a DataModule serves per side (after ``setup``); None when it does
    not list its trials."""
    sets = {side: getattr(datamodule, f"{side}_set", None) for side in SPLIT_SIDES}
    if any(not hasattr(ds, "trials") for ds in sets.values()):
        return None
    return {side: [str(t.name) for t in ds.trials] for side, ds in sets.items()}


def keep_split(run_dir: str | os.PathLike, datamodule: Any, resuming: bool) -> None:
    """After the DataModule's ``setup``: RunFolderError when its split puts a trial on two
    sides, or, for a resume, when it moves trials of the run's own ``split.json`` (naming
    them). A new run whose ``data.split_file`` lies outside the folder gets a copy as its
    ``split.json``: the folder always holds the split it was trained on."""
    split = served_split(datamodule)
    if split is None:
        return
    source = getattr(datamodule, "split_file", None)
    both = split_overlap(split)
    if both:
        raise RunFolderError(f"split {source or '(drawn)'} puts {len(both)} trial(s) on two sides: {_shown(both)}; "
                             "a test trial is never trained on")
    own = Path(run_dir) / "split.json"
    if resuming:
        check_same_split(run_dir, split, f"the split this start would train on ({source or 'drawn anew'})")
    elif source and Path(source).is_file() and Path(source).resolve() != own.resolve():
        from embodied_tactile.jsonio import write_json

        write_json(own, json.loads(Path(source).read_text()), indent=1)


# ----------------------------------------------------------------------------- length
#: an archived run folder's scored record, which stands in for its checkpoints
#: (embodied_tactile.eval.records): the folder is finished, and evaluate.py merges the record
ARCHIVED_RECORD = "scored.npz"


class RunFinished(Exception):
    """The folder holds a finished run that this start would not lengthen: nothing to do
    (train.py says so and exits 0, every file as it was)."""


def _checkpoint_header(path: Path) -> dict | None:
    """A checkpoint's small entries (tensors memory-mapped, not read); None when unreadable."""
    import torch

    try:
        ck = torch.load(path, map_location="cpu", mmap=True, weights_only=False)
    except Exception:  # noqa: BLE001 -- a damaged file: find_resume_checkpoint names it
        return None
    return ck if isinstance(ck, dict) and "global_step" in ck else None


def checkpoint_progress(ck: Mapping[str, Any]) -> tuple[int, int]:
    """(epochs trained, global step) of a Lightning checkpoint: the fit loop's processed
    epochs (a checkpoint of the end of epoch e holds e + 1), else ``epoch + 1``. A checkpoint
    saved after an epoch's last batch but before the loop counted the epoch (the validation
    at the epoch's end saves ``last.ckpt`` there) holds that epoch as started and not processed,
    with its batch loop at the last batch: Lightning resumes it as done, and so is it counted
    here (before, a finished run whose last epoch ended in a validation read one epoch short,
    and the same command resumed it into a second final read-out)."""
    try:
        loop = ck["loops"]["fit_loop"]
        progress = loop["epoch_progress"]["current"]
        epochs = int(progress["processed"])
        if int(progress["started"]) == epochs + 1 and loop.get("epoch_loop.batch_progress", {}).get("is_last_batch"):
            epochs += 1
    except (KeyError, TypeError, ValueError):
        epochs = int(ck.get("epoch", -1)) + 1
    return epochs, int(ck.get("global_step", 0))


def resume_candidate(run_dir: str | os.PathLike) -> tuple[Path, dict] | None:
    """The checkpoint a restart would continue from (:func:`~embodied_tactile.run.resume.find_resume_checkpoint`'s
    order: ``last.ckpt``, else the newest readable) and its header, without renaming anything."""
    folder = Path(run_dir) / "checkpoints"
    found = [p for p in folder.glob("*.ckpt") if p.is_file()]
    found.sort(key=lambda p: (p.name != "last.ckpt", -p.stat().st_mtime, p.name))
    for path in found:
        ck = _checkpoint_header(path)
        if ck is not None:
            return path, ck
    return None


def _limit(cfg: DictConfig, key: str) -> int | None:
    v = OmegaConf.select(cfg, key, default=None)
    return None if v is None or int(v) < 0 else int(v)


def check_length(cfg: DictConfig, run_dir: str | os.PathLike) -> None:
    """A run is never shortened nor rewritten by a start that adds nothing.
    RunFolderError when ``trainer.max_epochs`` (or ``max_steps``) is below what the
    folder's resume checkpoint has trained; :class:`RunFinished` when the folder's run is
    finished (``metrics.json``) and this start asks for exactly what it trained. More
    epochs continue the run."""
    run_dir = Path(run_dir)
    if not _is_rank_zero() or not holds_run(run_dir):
        return
    found = resume_candidate(run_dir)
    if found is None:
        if (run_dir / ARCHIVED_RECORD).is_file() and run_status(run_dir) == "finished":
            raise RunFinished(f"run folder {run_dir} is finished and archived (its scored record {ARCHIVED_RECORD}, no "
                              "checkpoint): nothing to train and nothing rewritten")
        return
    path, ck = found
    epochs, step = checkpoint_progress(ck)
    max_epochs, max_steps = _limit(cfg, "trainer.max_epochs"), _limit(cfg, "trainer.max_steps")
    for key, asked, done, unit in (("max_epochs", max_epochs, epochs, "epoch(s)"), ("max_steps", max_steps, step, "step(s)")):
        if asked is not None and asked < done:
            raise RunFolderError(
                f"run folder {run_dir} holds a run trained for {done} {unit} ({path.name}: epoch(s) {epochs}, step "
                f"{step}); trainer.{key}={asked} asks for fewer and a run is never shortened: give trainer.{key} >= "
                f"{done} to continue it, or another hydra.run.dir for a new run")
    if run_status(run_dir) == "finished" and (max_epochs == epochs or (max_epochs is None and max_steps == step)):
        raise RunFinished(
            f"run folder {run_dir} is finished ({epochs} epoch(s), step {step}): nothing to train and nothing "
            f"rewritten; give trainer.max_epochs > {epochs} to continue it, or evaluate it: "
            f"python evaluate.py {run_dir}")


def checkpoint_misfit(model: Any, checkpoint: Mapping[str, Any]) -> str | None:
    """How a checkpoint's weights do not fit ``model`` (a LightningModule built from the
    run's config), in one phrase: the modality the checkpoint was trained on where it differs,
    the number of tensors of another shape (the first named, both shapes), missing and
    unexpected keys; None when every tensor fits. Checkpoints of earlier layouts are read
    as the model reads them (its ``on_load_checkpoint`` renames)."""
    from embodied_tactile.model.compat import upgrade_state_dict

    state = dict(checkpoint.get("state_dict") or {})
    observation = getattr(getattr(model, "model", None), "observation", None)
    if observation is not None:
        from embodied_tactile.model.fusion import LateFusion

        state = upgrade_state_dict(state, late=isinstance(observation, LateFusion))
    own = model.state_dict()
    shapes = [f"{k}: checkpoint {list(v.shape)}, model {list(own[k].shape)}" for k, v in state.items()
              if k in own and hasattr(v, "shape") and tuple(v.shape) != tuple(own[k].shape)]
    missing, unexpected = sorted(set(own) - set(state)), sorted(set(state) - set(own))
    if not (shapes or missing or unexpected):
        return None
    parts = []
    ck_mod = ((checkpoint.get("hyper_parameters") or {}).get("net") or {}).get("modality") or {}
    own_mod = (getattr(model, "hparams", {}).get("net") or {}).get("modality") or {}
    if ck_mod.get("name") != own_mod.get("name") or ck_mod.get("channels") != own_mod.get("channels"):
        parts.append(f"modality {ck_mod.get('name', '?')} {list(ck_mod.get('channels') or [])} in the checkpoint, "
                     f"{own_mod.get('name', '?')} {list(own_mod.get('channels') or [])} in the run")
    if shapes:
        parts.append(f"{len(shapes)} tensor(s) of another shape (first {shapes[0]})")
    if missing:
        parts.append(f"{len(missing)} missing (first {missing[0]})")
    if unexpected:
        parts.append(f"{len(unexpected)} unexpected (first {unexpected[0]})")
    return "; ".join(parts)


def check_checkpoint_fits(cfg: DictConfig, run_dir: str | os.PathLike) -> None:
    """RunFolderError naming the file and the mismatch (:func:`checkpoint_misfit`) when the
    checkpoint a resume would continue from does not fit the model the run's config builds
    (e.g. a ``last.ckpt`` copied from a run of another modality): refused before a file is
    written, where loading it in ``fit`` would fail after ``metrics.json`` was rewritten."""
    if not _is_rank_zero() or not bool(cfg.get("resume", True)) or not holds_run(run_dir):
        return
    found = resume_candidate(run_dir)
    if found is None or OmegaConf.select(cfg, "model._target_", default=None) is None:
        return
    from hydra.utils import instantiate

    path, ck = found
    misfit = checkpoint_misfit(instantiate(cfg.model), ck)
    if misfit:
        raise RunFolderError(f"{path}: does not fit this run's model ({misfit}); refusing to resume from it, every "
                             "file kept (remove or replace that checkpoint, or give another hydra.run.dir)")


def claim(cfg: DictConfig, run_dir: str | os.PathLike) -> None:
    """Lock the run folder, then check that this start may continue what it holds
    (:func:`check_resume`, :func:`check_split_file`, :func:`check_length`); only then
    record this process in the lock file and remove the temporary files of checkpoint
    writes that a killed process left (the lock says no writer is alive). A refused start
    (RunFolderError) or a finished run (:class:`RunFinished`) leaves every file as it was."""
    lock(run_dir, record=False)
    try:
        check_resume(cfg, run_dir)
        check_split_file(cfg, run_dir)
        check_length(cfg, run_dir)
        check_checkpoint_fits(cfg, run_dir)
    except (RunFolderError, RunFinished):
        release(run_dir)
        discard_new(run_dir)  # a folder made only to be refused goes again
        raise
    record_holder(run_dir)
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
    """SIGTERM / SIGINT stop a training within seconds, in every phase. :meth:`install` at
    the start of train.py; as a Lightning callback (first in the trainer's list, so that its
    hooks run before any other callback's) it takes the signals over from Lightning's own
    SIGTERM handler (which raises out of the loop without a checkpoint). While the training
    steps run (from the first ``on_train_batch_start`` to ``on_train_end``) a signal is
    recorded and the optimiser step under way finishes; at the next hook (the end of that
    step, or the start of a validation, of an epoch's end or of the next step) ``last_path``
    (``last.ckpt``) is saved and :class:`StopRequested` ends the fit: no validation, KRR check
    or final read-out runs after a signal (a periodic KRR check already under way ends
    first). In every other phase -- data preparation and set-up, the check before the first
    step (the KRR callback's step-0 check), the final read-out after the last step -- the
    signal raises :class:`StopRequested` at once: the check or read-out under way is
    abandoned. :attr:`phase` says where the signal found the run (:data:`PHASES`); after the
    last step, :meth:`settle` saves ``last_path`` (the weights of that step). A second signal
    ends the process at once with the default action. :meth:`exit_code` is 128 + the signal
    number (130 SIGINT, 143 SIGTERM); :attr:`saved` / :attr:`step` say what was saved."""

    #: where a run can be when the signal comes (metrics.json ``stopped_in``)
    PHASES = ("set-up", "check before training", "training", "final read-out")
    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self, last_path: str | os.PathLike | None = None) -> None:
        self.received: int | None = None
        self.last_path = last_path
        self.saved: str | None = None  # the checkpoint written on the stop
        self.step: int | None = None
        self._trainer = None
        self._deferred = False
        self._phase = "set-up"  # the phase now (PHASES); :attr:`phase` keeps the one the signal came in
        self.phase: str | None = None
        self._ended = None  # the trainer whose steps are all done (on_train_end), for settle()

    def install(self) -> "StopSignals":
        for sig in self.SIGNALS:
            signal.signal(sig, self._handle)
        return self

    def restore(self) -> None:
        for sig in self.SIGNALS:
            signal.signal(sig, signal.SIG_DFL if sig == signal.SIGTERM else signal.default_int_handler)

    def enter(self, phase: str) -> None:
        """The run is in ``phase`` (:data:`PHASES`) from now on; its first entry is logged
        (``phase: <name>``), so that the log says where a run was when it stopped."""
        if phase != self._phase:
            self._phase = phase
            log.info("phase: %s", phase)

    def on_train_start(self, trainer, pl_module) -> None:
        self.install()  # over Lightning's SIGTERM handler (Lightning restores ours at teardown)
        self.enter("check before training")  # until the first step: a signal raises at once
        if self.received is not None:
            raise StopRequested(self.received)

    def on_train_end(self, trainer, pl_module) -> None:  # first of the callbacks: before the final read-out
        self._trainer = None
        self._ended = trainer
        # a signal after the last hook of the steps that stops (during an epoch's end: the
        # checkpoints' saves) ended the fit through should_stop: saved and stopped here, no read-out
        self._stop_now(trainer)
        self.enter("final read-out")

    def _stop_now(self, trainer) -> None:
        """After a signal: save ``last_path`` as the weights are now, and end the fit."""
        if self.received is None or self._deferred:
            return
        if self.last_path is not None and self.saved is None:
            trainer.save_checkpoint(str(self.last_path))
            self.saved, self.step = str(self.last_path), int(trainer.global_step)
        raise StopRequested(self.received)

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self._trainer = trainer
        self.enter("training")
        self._stop_now(trainer)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:  # after the optimiser step
        self._stop_now(trainer)

    def on_validation_start(self, trainer, pl_module) -> None:
        if not trainer.sanity_checking and self._trainer is not None:
            self._stop_now(trainer)

    def on_validation_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0) -> None:
        if not trainer.sanity_checking and self._trainer is not None:
            self._stop_now(trainer)

    def on_validation_end(self, trainer, pl_module) -> None:
        if not trainer.sanity_checking and self._trainer is not None:
            self._stop_now(trainer)

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        self._stop_now(trainer)

    def defer(self) -> None:
        """From now on a signal is only recorded (after fit: the run's own checkpoints are
        written; what is left is its final validation and metrics.json)."""
        self._deferred = True

    def settle(self) -> None:
        """After :class:`StopRequested` in the final read-out: save ``last_path`` with the
        weights of the last step (nothing to save when the signal came before the first)."""
        if self.received is not None and self.saved is None and self._ended is not None and self.last_path:
            self._ended.save_checkpoint(str(self.last_path))
            self.saved, self.step = str(self.last_path), int(self._ended.global_step)

    def _handle(self, signum: int, frame) -> None:
        if self.received is not None:  # asked twice: stop now
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        self.received, self.phase = signum, self._phase
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


def finish_fit(trainer, pl_module, callbacks: Sequence[Any], stop: StopSignals) -> None:
    """After ``trainer.fit`` returned: the callbacks' final read-out where the fit did not run
    it (``ensure_final``: a run resumed at its own length, which Lightning does not train),
    a stop signal raising :class:`StopRequested` at once while it runs."""
    if trainer.interrupted or stop.received is not None:
        return
    stop.enter("final read-out")
    for cb in callbacks:
        if hasattr(cb, "ensure_final"):
            cb.ensure_final(trainer, pl_module)


def run_outcome(trainer, callbacks: Sequence[Any], stop: StopSignals) -> tuple[str, bool]:
    """(metrics.json ``status``, ``final_readout``) of a fit that returned: ``finished`` only
    when the training reached its length (Lightning's fit loop is done, no stop asked) and
    the final read-out ran (where a callback makes one: ``final``); ``interrupted`` else."""
    readers = [cb for cb in callbacks if hasattr(cb, "ensure_final") and getattr(cb, "run_on_train_end", True)]
    readout = bool(readers) and all(getattr(cb, "final", None) for cb in readers)
    done = bool(trainer.fit_loop.done) and not trainer.interrupted and stop.received is None
    return ("finished" if done and (readout or not readers) else "interrupted"), readout


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


# ----------------------------------------------------------------------------- best checkpoint
#: the entry of a checkpoint that holds the monitored value of its own weights
MONITORED = "monitored"
#: the entry of a checkpoint that holds the fit time (s) of every start up to it
FIT_WALL_S = "fit_wall_s"


class FolderCheckpoints(_Callback):
    """Checkpoints that belong to their folder, wherever it is.

    Every checkpoint carries the fit time of the run up to it, over all its starts
    (``checkpoint["fit_wall_s"]``: a resumed run's metrics.json ``train_wall_s`` counts the
    earlier starts too), and the monitored value of the weights it holds:
    ``checkpoint["monitored"] = {"key", "mode", "value", "step"}`` (key and mode of the
    trainer's monitored ModelCheckpoint, e.g. ``val/elbo`` / ``max``). ``value`` is None
    when these weights were not validated (a stop between validations), so "best" is
    decided by the files themselves (:func:`best_checkpoint`), not by one callback's memory
    of where it wrote them. On resume, the ModelCheckpoint states saved under another
    folder (the run folder was moved or copied) are moved onto this folder's
    ``checkpoints/``, so that the monitored callback keeps its best score and files
    (Lightning drops them when the saved ``dirpath`` differs, and then writes a "best"
    that is worse than the one already there)."""

    def __init__(self) -> None:
        self._validated: tuple[int, dict[str, float]] | None = None
        self.earlier_wall_s: float | None = 0.0  # fit time of the starts before this one; None: not recorded
        self._fit_t0: float | None = None

    def on_fit_start(self, trainer, pl_module) -> None:
        self._fit_t0 = time.perf_counter()

    def wall_s(self) -> float | None:
        """Fit time of the run so far: the earlier starts up to the checkpoint this start
        resumed from, plus this start's (None when that checkpoint did not record its own)."""
        if self.earlier_wall_s is None or self._fit_t0 is None:
            return None
        return self.earlier_wall_s + time.perf_counter() - self._fit_t0

    def on_validation_end(self, trainer, pl_module) -> None:  # before the checkpoint callbacks (Lightning runs them last)
        if trainer.sanity_checking:
            return
        self._validated = (int(trainer.global_step), {k: float(v) for k, v in trainer.callback_metrics.items()
                                                       if getattr(v, "numel", lambda: 0)() == 1})

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        checkpoint[FIT_WALL_S] = self.wall_s()
        mon = next((cb for cb in trainer.checkpoint_callbacks if getattr(cb, "monitor", None)), None)
        if mon is None:
            return
        value = None
        if self._validated is not None and self._validated[0] == int(trainer.global_step):
            value = self._validated[1].get(mon.monitor)
        checkpoint[MONITORED] = {"key": mon.monitor, "mode": mon.mode, "value": value, "step": int(trainer.global_step)}

    def on_load_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:  # before the callbacks' load_state_dict
        self.earlier_wall_s = checkpoint.get(FIT_WALL_S)
        states = checkpoint.get("callbacks") or {}
        for cb in trainer.checkpoint_callbacks:
            st = states.get(getattr(cb, "state_key", None))
            old, new = (st or {}).get("dirpath"), getattr(cb, "dirpath", None)
            if not old or not new or os.path.abspath(old) == os.path.abspath(new):
                continue
            states[cb.state_key] = _moved(st, str(old), str(new))
            log.info("checkpoints saved in %s now in %s: the run folder was moved or copied", old, new)


def _moved(state: Any, old: str, new: str) -> Any:
    """``state`` with each path under ``old`` (strings and dict keys) put under ``new``."""
    def move(v: Any) -> Any:
        if isinstance(v, str) and (v == old or v.startswith(old.rstrip("/") + "/")):
            return new + v[len(old):]
        return v
    if isinstance(state, Mapping):
        return {move(k): _moved(v, old, new) for k, v in state.items()}
    return move(state)


def monitored(ck: Mapping[str, Any]) -> dict | None:
    """A checkpoint's :data:`MONITORED` record when it holds a finite value, else None."""
    rec = ck.get(MONITORED) if isinstance(ck, Mapping) else None
    if not isinstance(rec, Mapping) or rec.get("value") is None or rec.get("mode") not in ("min", "max"):
        return None
    value = float(rec["value"])
    return dict(rec, value=value) if value == value and abs(value) != float("inf") else None


def best_checkpoint(run_dir: str | os.PathLike) -> tuple[Path, dict] | None:
    """The checkpoint of ``<run_dir>/checkpoints`` whose stored monitored value is best
    (its own mode; a tie goes to the later step, then to a file other than ``last.ckpt``), over every readable ``*.ckpt`` in the
    folder whatever its name; with its record. None when no checkpoint stores a value
    (runs written before the record: :func:`embodied_tactile.eval.runs.find_checkpoint`
    falls back to the names)."""
    scored = []
    for path in sorted(p for p in (Path(run_dir) / "checkpoints").glob("*.ckpt") if p.is_file()):
        ck = _checkpoint_header(path)
        if ck is None:
            log.warning("%s: not a readable Lightning checkpoint; left out of the choice of the best", path)
            continue
        rec = monitored(ck)
        if rec is not None:
            scored.append((path, rec))
    if not scored:
        return None
    keys = {(r["key"], r["mode"]) for _, r in scored}
    if len(keys) > 1:
        log.warning("%s: checkpoints monitor different values %s; ranking by %s", run_dir, sorted(keys), scored[-1][1]["key"])
        scored = [(p, r) for p, r in scored if (r["key"], r["mode"]) == (scored[-1][1]["key"], scored[-1][1]["mode"])]
    sign = 1.0 if scored[0][1]["mode"] == "max" else -1.0
    # a tie goes to the later step, then to a file that a continued training does not overwrite
    return max(scored, key=lambda pr: (sign * pr[1]["value"], pr[1].get("step", 0), pr[0].name != "last.ckpt", pr[0].name))


def in_folder(run_dir: str | os.PathLike, path: str | os.PathLike | None) -> str | None:
    """``path`` relative to the run folder (what metrics.json stores: a moved or copied
    folder names its own files); as given when it lies outside."""
    if not path:
        return None
    try:
        return Path(os.path.abspath(path)).relative_to(Path(os.path.abspath(run_dir))).as_posix()
    except ValueError:
        return str(path)
