"""Loading a trained run: finding runs, choosing the checkpoint, reloading the run's own
config, data config and saved split, and collecting its latents.

``evaluate.py``, the palpation CLI (:mod:`embodied_tactile.active.load`) and the benchmarks
load runs through this module. A run folder is what ``train.py`` writes:
``config_resolved.yaml``, ``split.json``, ``checkpoints/``, ``metrics.json``,
``provenance.json``. A trial's object and factors come from its attributes (the DataModule's
trials), never from its name: a name is a label (the leakage guard's ``seq_id``).
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from omegaconf import DictConfig, OmegaConf

from embodied_tactile.run import summary
from embodied_tactile.jsonio import read_json

log = logging.getLogger(__name__)


class EvaluationError(RuntimeError):
    """A run folder / checkpoint / option that cannot be evaluated (message names it)."""


@dataclass
class Run:
    """A training run to evaluate: its folder, the checkpoint to score (None for an archived
    run, whose folder holds its scored record instead: :data:`~.records.IN_RUN`), its config."""
    run_dir: Path
    ckpt: Path | None
    cfg: DictConfig = field(repr=False)
    name: str = ""

    @property
    def record(self) -> Path | None:
        """The archived run's scored record (None for a run with its checkpoint)."""
        from .records import IN_RUN

        return self.run_dir / IN_RUN if self.ckpt is None else None


def _readable(path: Path) -> str | None:
    """None when ``path`` opens as a Lightning checkpoint, else the reason (cheap: the zip's
    directory and the pickled header, tensors memory-mapped, not read)."""
    import torch

    try:
        ck = torch.load(path, map_location="cpu", mmap=True, weights_only=False)
    except Exception as err:  # noqa: BLE001 -- torch raises many kinds on damaged files
        return f"unreadable ({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})"
    if not isinstance(ck, dict) or "state_dict" not in ck:
        return "not a Lightning checkpoint (no state_dict)"
    return None


def find_checkpoint(run_dir: Path, which: str = "best") -> Path:
    """A checkpoint of this run folder, always looked up inside ``<run_dir>/checkpoints``
    (metrics.json's ``best_checkpoint`` gives only the file name: a copied or moved folder
    never reads the original's files). best: the checkpoint whose own stored monitored
    value is best, over every checkpoint in the folder (:func:`runfolder.best_checkpoint`);
    for checkpoints without that record, the file metrics.json names, else the newest
    ``checkpoints/best*.ckpt``, else ``last.ckpt``; last: ``checkpoints/last.ckpt``. A file
    that does not open as a checkpoint (truncated, another format) is skipped with a
    warning naming it; EvaluationError naming the folder (and the skipped files) when no
    candidate is readable."""
    from embodied_tactile.run.runfolder import best_checkpoint

    ck_dir = run_dir / "checkpoints"
    last = ck_dir / "last.ckpt"
    cands: list[Path] = []
    scored = best_checkpoint(run_dir) if which == "best" else None
    if which == "best":
        if scored is not None:
            cands.append(scored[0])
        best = read_json(run_dir / "metrics.json").get("best_checkpoint")
        if best:
            cands.append(ck_dir / Path(str(best)).name)
        bests = [p for p in ck_dir.glob("best*.ckpt") if p.is_file()] if ck_dir.is_dir() else []
        cands += sorted(bests, key=lambda p: (p.stat().st_mtime, p.name), reverse=True)
    cands.append(last)
    bad: list[str] = []
    for i, cand in enumerate(dict.fromkeys(cands)):
        if not cand.is_file():
            continue
        why = _readable(cand)
        if why:
            bad.append(f"{cand}: {why}")
            log.warning("%s: %s; trying the next checkpoint", cand, why)
            continue
        if which == "best" and cand == last and (scored is None or scored[0] != last):
            log.warning("%s: no readable best checkpoint, using %s", run_dir, last)
        return cand
    have = sorted(p.name for p in ck_dir.glob("*.ckpt")) if ck_dir.is_dir() else []
    raise EvaluationError(
        f"no checkpoint ({'best or last' if which == 'best' else 'last.ckpt'}) in run folder {run_dir} that can be read "
        f"(looked in {ck_dir}; found {have or 'nothing'}{'; ' + '; '.join(bad) if bad else ''}). "
        "Did training finish or get killed before its first epoch?")


def run_state(run: Run, allow_running: bool = False) -> dict:
    """The state of the training behind a run folder, as an evaluation reports it:
    ``status`` -- ``training`` while a process holds the folder's lock, else metrics.json's
    ``finished`` / ``interrupted`` / ``failed``, or ``killed`` when it says ``running`` (or
    is absent) and no process holds the folder; ``reason`` (the error, the stop signal,
    whether the final read-out was done), ``checkpoint`` (the file evaluated, relative to the
    folder), its ``epoch`` and ``step``, and ``line``: what evaluate.py prints first when the
    run is not finished. EvaluationError for a run being trained unless ``allow_running``."""
    from embodied_tactile.run.runfolder import checkpoint_progress, in_folder, training_holder

    epochs, step = None, None
    if run.ckpt is not None:  # an archived run has its record, no checkpoint to read progress from
        try:
            import torch

            epochs, step = checkpoint_progress(torch.load(str(run.ckpt), map_location="cpu", mmap=True,
                                                          weights_only=False))
        except Exception:  # noqa: BLE001 -- find_checkpoint opened it already; say '?' rather than fail here
            pass
    ckpt = in_folder(run.run_dir, run.ckpt) if run.ckpt is not None else f"{run.record.name} (archived: no checkpoint)"
    used = f"checkpoint {ckpt} (epoch(s) {epochs if epochs is not None else '?'}, step {step if step is not None else '?'})"
    holder = training_holder(run.run_dir)
    metrics = read_json(run.run_dir / "metrics.json")
    state: dict[str, Any] = {"checkpoint": ckpt, "epochs": epochs, "step": step}
    if holder is not None:
        who = f"pid {holder['pid']} on host {holder['host']}, started {holder['started']}"
        if not allow_running:
            raise EvaluationError(f"run folder {run.run_dir} is being trained ({who}): its checkpoints are still "
                                  "changing; wait for it to end, or allow_running=true evaluates one as it is now")
        state.update(status="training", reason=who,
                     line=f"evaluate.py: run {run.run_dir} is being trained ({who}); allow_running=true: evaluating "
                          f"{used} as it is now")
        return state
    status = metrics.get("status")
    if status in ("finished", "interrupted", "failed"):
        reason = {"interrupted": f"stopped by {metrics.get('stopped_by') or 'a signal'}",
                  "failed": str(metrics.get("error") or "error not recorded")}.get(status, "")
        if status == "interrupted" and "final_readout" in metrics:
            reason += f", final read-out {'done' if metrics['final_readout'] else 'not done'}"
    else:
        status, reason = "killed", ("metrics.json says running but no process holds the folder" if status == "running"
                                    else "no metrics.json and no process holds the folder")
    state.update(status=status, reason=reason)
    if status != "finished":
        state["line"] = f"evaluate.py: run {run.run_dir} is {status} ({reason}); evaluating {used}"
    return state


def load_module(run: Run):
    """The run's LightningModule (class from ``cfg.model._target_``) from its checkpoint, on
    the CPU, in eval mode. A checkpoint whose weights do not fit this code's network (written
    by an older model layout) is an :class:`EvaluationError` naming the file, the commit that
    wrote it and the first mismatching key."""
    from hydra.utils import get_class

    cls = get_class(str(run.cfg.model._target_))
    try:
        model = cls.load_from_checkpoint(str(run.ckpt), map_location="cpu")
    except Exception as err:  # noqa: BLE001 -- one line naming the file, whatever torch / Lightning raise
        if not (isinstance(err, RuntimeError) and "state_dict" in str(err)):
            first = str(err).splitlines()[0] if str(err) else ""
            raise EvaluationError(f"{run.ckpt}: cannot load as the run's {cls.__name__} "
                                  f"({type(err).__name__}: {first})") from None
        keys = re.findall(r'"([^"]+)"', str(err))
        commit = read_json(run.run_dir / "provenance.json").get("git_commit") or "unknown"
        raise EvaluationError(
            f"{run.ckpt}: its weights do not fit this code's {cls.__name__} (first mismatching key "
            f"{keys[0] if keys else '?'}): it was written by commit {commit[:12]}, whose network layout differs; "
            "evaluate it with that commit's code or retrain") from None
    model.eval()
    return model


def untrained_module(run: Run, trained):
    """The run's network as its training started: built from the run's config under the run's
    seed (as train.py builds it), with the trained module's input statistics (data, not
    learning) copied in, in eval mode: the floor every read-out of the run is compared with."""
    import lightning as L
    from hydra.utils import instantiate

    L.seed_everything(int(run.cfg.seed), workers=True, verbose=False)
    model = instantiate(run.cfg.model)
    stats = {n: b for n, b in trained.named_buffers() if n.rsplit(".", 1)[-1].startswith("input_")}
    for name, buf in model.named_buffers():
        if name in stats:
            buf.copy_(stats[name])
    model.eval()
    return model


def load_run(run_dir: Path, which: str, ckpt: Path | None = None) -> Run:
    cpath = run_dir / "config_resolved.yaml"
    if not cpath.exists():
        raise EvaluationError(f"{run_dir} is not a training run folder: no config_resolved.yaml "
                              "(give a run folder made by train.py, one of its checkpoints, or a multirun folder)")
    cfg = OmegaConf.load(cpath)
    from .records import IN_RUN

    if ckpt is None and (run_dir / IN_RUN).is_file() and not (run_dir / "checkpoints").is_dir():
        return Run(run_dir=run_dir, ckpt=None, cfg=cfg, name=run_dir.name)  # archived: its record stands in
    run = Run(run_dir=run_dir, ckpt=ckpt or find_checkpoint(run_dir, which), cfg=cfg, name=run_dir.name)
    check_fits(run)
    return run


def check_fits(run: Run) -> None:
    """EvaluationError naming the checkpoint and the mismatch (modality, shapes:
    :func:`~embodied_tactile.run.runfolder.checkpoint_misfit`) when its weights do not fit the
    model the run's config builds: a checkpoint copied from another run is refused before
    any data are prepared (a folder of runs skips it and scores the others)."""
    import torch
    from hydra.utils import instantiate

    from embodied_tactile.run.runfolder import checkpoint_misfit

    if OmegaConf.select(run.cfg, "model._target_", default=None) is None:
        return
    with torch.random.fork_rng():  # building the model draws its initial weights: the caller's stream stays
        model = instantiate(run.cfg.model)
    misfit = checkpoint_misfit(model, torch.load(run.ckpt, map_location="cpu", mmap=True, weights_only=False))
    if misfit:
        raise EvaluationError(f"{run.ckpt}: does not fit the model of its run {run.run_dir} ({misfit}); "
                              "not evaluated")


def job_dirs(folder: Path) -> list[Path]:
    """The training jobs under a multirun folder (its sub-folders holding a
    ``config_resolved.yaml``) or under a study folder whose sub-folders are multiruns run as
    separate parts (e.g. one per seed or primitive: ``hydra.sweep.dir=<study>/<part>``); both
    levels are searched, so ``evaluate.py <study>`` merges the parts."""
    jobs = []
    for d in sorted((p for p in folder.iterdir() if p.is_dir()), key=lambda p: p.name):
        if (d / "config_resolved.yaml").exists():
            jobs.append(d)
        else:
            jobs += sorted((j for j in d.iterdir() if j.is_dir() and (j / "config_resolved.yaml").exists()),
                           key=lambda j: j.name)
    return jobs


def discover(target: Path, which: str) -> tuple[str, list[Run], list[tuple[Path, str]]]:
    """-> (kind 'run' | 'multirun', runs, skipped (folder, reason))."""
    target = Path(target)
    if not target.exists():
        raise EvaluationError(f"no such file or folder: {target}")
    if target.is_file():
        if target.suffix != ".ckpt":
            raise EvaluationError(f"{target} is a file but not a checkpoint (*.ckpt)")
        why = _readable(target)
        if why:
            raise EvaluationError(f"{target}: {why}")
        target = Path(os.path.abspath(target))  # absolute, symlinks not followed: the folder given is the run
        return "run", [load_run(target.parent.parent, which, ckpt=target)], []
    if (target / "config_resolved.yaml").exists():
        return "run", [load_run(target, which)], []
    jobs = job_dirs(target)
    if not jobs:
        raise EvaluationError(f"{target} holds no training run: no config_resolved.yaml in it nor in its "
                              "sub-folders (expected a run folder, a checkpoint or a multirun folder)")
    runs, skipped = [], []
    for d in jobs:
        try:
            runs.append(load_run(d, which))
            runs[-1].name = d.relative_to(target).as_posix()  # 'seed1/3' for a job of a study part
        except EvaluationError as err:
            skipped.append((d, str(err)))
            log.warning("skipping %s", err)
    if not runs:
        raise EvaluationError(f"multirun folder {target}: none of its {len(jobs)} job(s) has a checkpoint; "
                              + "; ".join(r for _, r in skipped[:3]))
    return "multirun", runs, skipped


# ----------------------------------------------------------------------------- data
def training_cwd(run_dir: Path) -> Path | None:
    """The working directory train.py ran in (``provenance.json``), or None."""
    cwd = read_json(run_dir / "provenance.json").get("cwd")
    return Path(cwd) if cwd else None


def _resolve_path(value: str, train_cwd: Path | None) -> str:
    """A relative path of the run's config means what it meant to train.py: relative to the
    training cwd when it exists there (a folder of the same name here is another data set),
    else as is from here."""
    p = Path(value)
    if p.is_absolute() or train_cwd is None:
        return value
    globby = any(ch in value for ch in "*?[")
    there = train_cwd / p
    return str(there) if (bool(list(train_cwd.glob(value))) if globby else there.exists()) else value


def data_config(run: Run, opts: DictConfig) -> dict:
    """The run's cfg.data with the saved split, loader options and resolved paths."""
    from embodied_tactile.run.summary import OWN_READERS

    modality = OmegaConf.select(run.cfg, "modality.name", default=None)
    if modality in OWN_READERS:
        raise EvaluationError(f"{run.run_dir} is a {modality} run, which evaluate.py does not score (its baselines are "
                              f"the tactile scenes'): {OWN_READERS[modality][2].format(run=run.run_dir)}")
    data = OmegaConf.to_container(run.cfg.data, resolve=True)
    split = run.run_dir / "split.json"
    if not split.exists():
        raise EvaluationError(f"{run.run_dir} has no split.json: the training/held-out split of this run is unknown, "
                              "so the alignment could be fitted on scored sequences; refusing to evaluate")
    try:
        side = json.loads(split.read_text())
        if not isinstance(side, dict) or not isinstance(side.get("test"), list):
            raise ValueError("no list of test trials")
    except (OSError, ValueError) as err:
        raise EvaluationError(f"{split}: not a split file written by train.py ({type(err).__name__}: {err})") from None
    from embodied_tactile.run.runfolder import split_overlap

    both = split_overlap(side)
    if both:
        raise EvaluationError(f"{split} puts {len(both)} trial(s) on two sides ({'; '.join(both[:5])}): its scores "
                              "would include trials the run was trained on; refusing to evaluate")
    train_cwd = training_cwd(run.run_dir)
    data["data_dir"] = _resolve_path(str(data.get("data_dir", "data")), train_cwd)
    if not Path(data["data_dir"]).exists():
        log.warning("%s: data folder %s not found (training cwd %s); the DataModule will %s", run.run_dir,
                    data["data_dir"], train_cwd, "re-simulate the scene" if data.get("source") == "simulated"
                    else "fail unless raw_files are found")
    if data.get("raw_files"):
        data["raw_files"] = [_resolve_path(str(f), train_cwd) for f in data["raw_files"]]
    data["split_file"] = str(split)
    if opts.data.batch_size:
        data["batch_size"] = int(opts.data.batch_size)
    data["num_workers"] = int(opts.data.num_workers)
    return data


class DataCache:
    """The prepared DataModule (and its loaded batches) of the current (data config, saved
    split). Only the latest one is kept: runs are evaluated grouped by data key, so a sweep
    streams through its scenes and memory does not grow with the number of runs."""

    def __init__(self) -> None:
        self._dms: dict[str, Any] = {}
        self._batches: dict[tuple[str, str], list] = {}
        self.hits = 0

    @staticmethod
    def key(data: dict) -> str:
        split = json.loads(Path(data["split_file"]).read_text())
        d = {k: v for k, v in data.items() if k != "split_file"}
        return json.dumps([d, split.get("train"), split.get("val"), split.get("test")], sort_keys=True, default=str)

    def get(self, data: dict, check=None):
        """``(key, DataModule)``; ``check(dm)``, when given, runs after the preparation stage
        and before the saved split is loaded (it sees the caches, e.g. to compare the data
        with the training's), also on a reused DataModule."""
        from embodied_tactile.data.datamodule import TactileDataModule

        k = self.key(data)
        if k in self._dms:
            self.hits += 1
            if check is not None:
                check(self._dms[k])
            return k, self._dms[k]
        self.clear()  # free the previous scene before loading the next one
        dm = TactileDataModule.from_config(data)  # a saved config of any version (its _target_ ignored)
        dm.prepare_data()
        if check is not None:
            check(dm)
        dm.setup("test")  # the split and its datasets; no training statistics
        self._dms[k] = dm
        return k, dm

    def clear(self) -> None:
        import gc

        self._dms.clear()
        self._batches.clear()
        gc.collect()

    def batches(self, k: str, dm, which: str) -> list:
        if (k, which) not in self._batches:
            loader = {"train": dm.train_eval_dataloader, "val": dm.val_eval_dataloader, "test": dm.test_dataloader}[which]()
            self._batches[(k, which)] = list(loader)
        return self._batches[(k, which)]


# ----------------------------------------------------------------------------- one run
def trials(dm, which: str) -> list:
    """The trials the DataModule serves on one side ('train' | 'val' | 'test'), in loader order."""
    ds = {"train": dm.train_set, "val": getattr(dm, "val_set", None), "test": dm.test_set}[which]
    return list(ds.trials) if ds is not None else []


def trial_names(dm, which: str) -> list[str]:
    """The names (labels) of the trials one side serves, in loader order."""
    return [t.name for t in trials(dm, which)]


def trial_objects(dm) -> dict[str, int]:
    """Trial name -> object id, from the trials' attributes, over every side the DataModule serves."""
    return {t.name: int(t.object_id) for side in ("train", "val", "test") for t in trials(dm, side)}


def collect_split(model, batches: list, names: list[str], latent: str) -> tuple[dict, float]:
    """collect_latents over pre-loaded batches (so the timing is inference only) + the
    observations / actions the baselines need + trial names as seq_id."""
    from embodied_tactile.eval.latents import collect_latents

    t0 = time.perf_counter()
    split = collect_latents(model, batches, latent=latent)
    return _with_inputs(split, batches, names), time.perf_counter() - t0


def collect_splits(model, train: tuple[list, list[str]], held: tuple[list, list[str]], latent: str,
                   batch_size: int) -> tuple[dict, dict, float]:
    """:func:`collect_split` of the training and the held-out side (each ``(batches,
    names)``), inferred together as the training's final read-out infers them
    (:func:`~embodied_tactile.eval.latents.collect_split_latents`, ``batch_size`` sequences a
    batch: the run's ``callbacks.krr_alignment.infer_batch_size``), so evaluate.py reads the
    same latents to the bit -> (training split, held-out split, inference seconds per held-out
    share of the sequences)."""
    from embodied_tactile.eval.latents import collect_split_latents

    t0 = time.perf_counter()
    tr, te = collect_split_latents(model, train[0], held[0], latent=latent, batch_size=batch_size)
    dt = time.perf_counter() - t0
    n_tr, n_te = len(tr["factors"]), len(te["factors"])
    return (_with_inputs(tr, *train), _with_inputs(te, *held), dt * n_te / max(1, n_tr + n_te))


def _with_inputs(split: dict, batches: list, names: list[str]) -> dict:
    """A split's latents with the observations / actions the baselines need and the trial
    names as seq_id."""
    import numpy as np
    import torch

    split["obs"] = torch.cat([b["obs"] for b in batches]).numpy()
    split["actions"] = torch.cat([b["actions"] for b in batches]).numpy()
    if len(names) != len(split["factors"]):
        raise EvaluationError(f"{len(names)} trial names but {len(split['factors'])} sequences served")
    split["seq_id"] = np.asarray(names)
    return split


def run_split(run: Run, split_file: str, objects: Mapping[str, int]) -> dict:
    """The run's split from its ``split.json``: kind ('trial' | 'object'), sizes, object ids per
    side (``objects``: trial name -> object id from the trials' attributes, :func:`trial_objects`)
    and ``unseen_objects`` (no held-out object has a trial in training or validation). An object
    split whose held-out objects were seen in training is an error (its numbers would not
    measure generalisation to unseen objects)."""
    from embodied_tactile.eval.results import split_report

    try:
        rep = split_report(json.loads(Path(split_file).read_text()), objects)
    except (OSError, ValueError) as err:
        raise EvaluationError(f"{run.run_dir}: cannot read the split {split_file}: {err}") from err
    if rep["kind"] == "object" and not rep["unseen_objects"]:
        raise EvaluationError(f"{run.run_dir}: split.json ({split_file}) is an object split but held-out object(s) "
                              f"{rep['seen_test_objects']} have trials in training or validation")
    return rep


def train_log_dir() -> str:
    """``paths.log_dir`` as train.py composes it (configs/train.yaml + configs/local/)."""
    from embodied_tactile.run.config import compose

    return str(compose().paths.log_dir)


def latest_target(log_dir: str | None = None) -> Path:
    """The most recent run or multirun (with a checkpoint) under ``<log_dir>/train``; says
    which one on stdout. EvaluationError when there is none."""
    train_dir = Path(log_dir or train_log_dir()) / "train"
    try:
        folder, kind, passed = summary.latest_run(train_dir)
    except FileNotFoundError as err:
        raise EvaluationError(str(err)) from None
    print(summary.picked_message(folder, kind, passed, train_dir), flush=True)
    return folder
