"""Evaluate trained Latent Filter runs: KRR alignment, NMSE tables, curves, UMAP, baselines.

    python evaluate.py                                              # the most recent run / multirun
    python evaluate.py logs/train/runs/<run>                        # one run (best checkpoint)
    python evaluate.py logs/train/runs/<run>/checkpoints/last.ckpt  # one checkpoint
    python evaluate.py logs/train/multiruns/<time>                  # every job of a sweep
    python evaluate.py logs/train/study                             # a study run in parts (sub-multiruns), merged
    python evaluate.py <run> latent=both baselines=[handcrafted,gru,mean] gru.epochs=5 out=/tmp/ev
    python evaluate.py <run> checkpoint=last umap=false

Why argparse + OmegaConf and not ``@hydra.main``: Hydra takes no positional arguments (every
command-line word must be an override), and the run folder is the one thing every call
needs. So the path is an argparse positional and the options are an OmegaConf dotlist
merged over ``configs/evaluate.yaml`` (the same ``key=value`` syntax as train.py; unknown
keys are an error).

The recipe, per run (docs/evaluation.md, "evaluate.py"):

1. reload the run's OWN config from ``config_resolved.yaml`` (never rebuilt from the
   defaults: a run trained with ``modality=fsr_tb`` evaluates as fsr_tb, with no extra
   argument); ``configs/evaluate.yaml`` holds evaluation options only;
2. relative data paths are resolved against the training cwd (``provenance.json``) when
   they do not exist relative to the current directory;
3. the DataModule is instantiated from ``cfg.data`` with ``split_file=<run>/split.json``
   (the saved split is reused; the regressor never sees the sequences it scores: trial
   names go along as ``seq_id`` and the library raises ``LeakageError`` on overlap);
4. the model class of ``cfg.model._target_`` is loaded with ``load_from_checkpoint``
   (best checkpoint by default, ``checkpoint=last`` as option) on the CPU;
5. ``collect_latents`` over ``train_eval_dataloader()`` (fit) and ``test_dataloader()``
   (scored: the held-out test trials, never used for checkpoint selection); inference time per held-out trial is measured on pre-loaded batches;
6. ``evaluate_latents`` + the baselines (hand-crafted features -> KRR, supervised GRU,
   mean predictor) on the same split; KRR history (``krr_history.jsonl``) for the
   error-vs-run-time figure; training time from ``metrics.json`` (``train_wall_s``);
7. ``write_report`` into ``<run>/evaluation`` (or ``<multirun>/evaluation``, aggregating
   every job) and the Markdown tables printed to the terminal.

A multirun folder: every sub-folder holding a ``config_resolved.yaml`` is a job (a study
folder: also every job of its sub-folders, so parts of a sweep run apart are merged); jobs
without a checkpoint are skipped with a message. DataModules are shared between jobs with
the same data config and the same saved split, and the GRU baseline is off by default for
multiruns (``baselines=[handcrafted,gru,mean]`` turns it on).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError

from embodied_tactile import quiet, summary

REPO = Path(__file__).resolve().parent
DEFAULTS = REPO / "configs" / "evaluate.yaml"
BASELINES = ("handcrafted", "gru", "mean")
MULTIRUN_BASELINES = ("handcrafted", "mean")

log = logging.getLogger("evaluate")


class EvaluationError(RuntimeError):
    """A run folder / checkpoint / option that cannot be evaluated (message names it)."""


# ----------------------------------------------------------------------------- options
def parse_options(overrides: Sequence[str] = ()) -> DictConfig:
    """``configs/evaluate.yaml`` + ``key=value`` overrides (unknown top-level keys rejected;
    ``alignment.*`` and ``gru.*`` accept any keyword of fit_alignment / GRURegressor)."""
    base = OmegaConf.load(DEFAULTS)
    OmegaConf.set_struct(base, True)
    for open_key in ("alignment", "gru"):
        OmegaConf.set_struct(base[open_key], False)
    bad = [o for o in overrides if "=" not in o]
    if bad:
        raise EvaluationError(f"options must be key=value, got {bad}")
    try:
        opts = OmegaConf.merge(base, OmegaConf.from_dotlist(list(overrides)))
    except ConfigKeyError as err:
        raise EvaluationError(f"unknown evaluation option: {err}. Known: {sorted(base.keys())}. "
                              "(The scene and model come from the run's own config and cannot be overridden.)") from err
    if opts.checkpoint not in ("best", "last"):
        raise EvaluationError(f"checkpoint must be 'best' or 'last', got {opts.checkpoint!r}")
    if opts.latent not in ("y", "z", "both"):
        raise EvaluationError(f"latent must be 'y', 'z' or 'both', got {opts.latent!r}")
    from embodied_tactile.eval.targets import TARGET_ENCODINGS

    if opts.targets is not None and opts.targets not in TARGET_ENCODINGS:
        raise EvaluationError(f"targets must be null (the run's own) or one of {list(TARGET_ENCODINGS)}, got {opts.targets!r}")
    if opts.baselines is not None:
        unknown = [b for b in opts.baselines if b not in BASELINES]
        if unknown:
            raise EvaluationError(f"unknown baseline(s) {unknown}; choose from {list(BASELINES)}")
    return opts


SELECT_ALIASES = {"modality": "modality.name", "skin": "skin.name", "primitive": "primitive.name"}


def split_overrides(overrides: Sequence[str]) -> tuple[list[str], dict[str, list[str]]]:
    """-> (evaluation options: keys of configs/evaluate.yaml, run selection: every other
    ``key=value``, e.g. ``modality=multi_l skin=hard seed=[0,1] annealing.name=dvbf``)."""
    known = set(OmegaConf.load(DEFAULTS).keys())
    options, selection = [], {}
    for o in overrides:
        key = o.split("=", 1)[0]
        if "=" not in o or key.split(".")[0] in known:
            options.append(o)
            continue
        value = OmegaConf.to_container(OmegaConf.from_dotlist([f"v={o.split('=', 1)[1]}"]))["v"]
        selection[key] = [str(v) for v in value] if isinstance(value, list) else [str(value)]
    return options, selection


def _matches(have, want: list[str]) -> bool:
    for w in want:
        if str(have) == w:
            return True
        try:
            if float(have) == float(w):
                return True
        except (TypeError, ValueError):
            pass
    return False


def select_runs(runs: list[Run], selection: dict[str, list[str]]) -> list[Run]:
    """The runs whose config matches every ``key=value`` of the selection (modality / skin /
    primitive name their ``.name``; any dotted key of config_resolved.yaml works). A selection
    picks runs; it never changes a run's scene."""
    for key, want in selection.items():
        path = SELECT_ALIASES.get(key, key)
        have = [OmegaConf.select(r.cfg, path, default=None) for r in runs]
        if all(h is None for h in have):
            raise EvaluationError(
                f"unknown evaluation option or run selector {key!r}: not an option of configs/evaluate.yaml "
                f"({sorted(OmegaConf.load(DEFAULTS).keys())}) nor a key of the runs' config_resolved.yaml")
        kept = [r for r, h in zip(runs, have) if h is not None and _matches(h, want)]
        if not kept:
            raise EvaluationError(f"no run matches {key}={','.join(want)} (the runs have {key} = "
                                  f"{sorted({str(h) for h in have})}; a selection picks runs, it never changes a run's scene)")
        runs = kept
    if selection:
        log.info("selected %d run(s) by %s", len(runs), selection)
    return runs


def _agreement_line(c: dict) -> str:
    """One line: evaluate.py's NMSE beside the training's final alignment, and why they differ."""
    if c.get("training_nmse_overall") is None:
        return f"NMSE {c['evaluate_nmse_overall']:.4g} (no training-time final alignment to compare: {c['reasons'][0]})"
    head = (f"NMSE {c['evaluate_nmse_overall']:.4g} here, {c['training_nmse_overall']:.4g} in the training's final "
            f"alignment (metrics.json krr_final, epoch {c.get('training_epoch')}), difference {c['difference']:+.2g}")
    return head + ("; same weights, settings and sequences" if not c["reasons"] else "; differs because: "
                   + "; ".join(c["reasons"]))


# ----------------------------------------------------------------------------- discovery
@dataclass
class Run:
    run_dir: Path
    ckpt: Path
    cfg: DictConfig = field(repr=False)
    name: str = ""


def find_checkpoint(run_dir: Path, which: str = "best") -> Path:
    """best: ``metrics.json`` best_checkpoint, else the newest ``checkpoints/best*.ckpt``;
    last (or no best): ``checkpoints/last.ckpt``. Raises EvaluationError naming the folder."""
    ck_dir = run_dir / "checkpoints"
    last = ck_dir / "last.ckpt"
    if which == "best":
        mpath = run_dir / "metrics.json"
        if mpath.exists():
            try:
                best = json.loads(mpath.read_text()).get("best_checkpoint")
            except ValueError:
                best = None
            if best:
                p = Path(best)
                cand = p if p.exists() else ck_dir / p.name  # the run folder may have moved
                if cand.exists():
                    return cand
        bests = sorted(ck_dir.glob("best*.ckpt"), key=lambda p: (p.stat().st_mtime, p.name))
        if bests:
            return bests[-1]
        if last.exists():
            log.warning("%s: no best checkpoint, using %s", run_dir, last)
            return last
    elif last.exists():
        return last
    have = sorted(p.name for p in ck_dir.glob("*.ckpt")) if ck_dir.is_dir() else []
    raise EvaluationError(
        f"no {'checkpoint' if which == 'best' else 'last.ckpt'} in run folder {run_dir} "
        f"(looked in {ck_dir}; found {have or 'nothing'}). Did training finish or get killed before its first epoch?")


def load_module(run: Run):
    """The run's LightningModule (class from ``cfg.model._target_``) from its checkpoint, on
    the CPU, in eval mode. A checkpoint whose weights do not fit this code's network (written
    by an older model layout) is an :class:`EvaluationError` naming the file, the commit that
    wrote it and the first mismatching key."""
    from hydra.utils import get_class

    cls = get_class(str(run.cfg.model._target_))
    try:
        model = cls.load_from_checkpoint(str(run.ckpt), map_location="cpu")
    except RuntimeError as err:
        if "state_dict" not in str(err):
            raise
        keys = re.findall(r'"([^"]+)"', str(err))
        commit = _read_json(run.run_dir / "provenance.json").get("git_commit") or "unknown"
        raise EvaluationError(
            f"{run.ckpt}: its weights do not fit this code's {cls.__name__} (first mismatching key "
            f"{keys[0] if keys else '?'}): it was written by commit {commit[:12]}, whose network layout differs; "
            "evaluate it with that commit's code or retrain") from None
    model.eval()
    return model


def load_run(run_dir: Path, which: str, ckpt: Path | None = None) -> Run:
    cpath = run_dir / "config_resolved.yaml"
    if not cpath.exists():
        raise EvaluationError(f"{run_dir} is not a training run folder: no config_resolved.yaml "
                              "(give a run folder made by train.py, one of its checkpoints, or a multirun folder)")
    cfg = OmegaConf.load(cpath)
    return Run(run_dir=run_dir, ckpt=ckpt or find_checkpoint(run_dir, which), cfg=cfg, name=run_dir.name)


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
        return "run", [load_run(target.resolve().parent.parent, which, ckpt=target.resolve())], []
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
def _training_cwd(run_dir: Path) -> Path | None:
    p = run_dir / "provenance.json"
    try:
        cwd = json.loads(p.read_text()).get("cwd")
    except (OSError, ValueError):
        return None
    return Path(cwd) if cwd else None


def _resolve_path(value: str, train_cwd: Path | None) -> str:
    """Relative path: as is when it exists from here, else relative to the training cwd."""
    p = Path(value)
    if p.is_absolute() or train_cwd is None:
        return value
    globby = any(ch in value for ch in "*?[")
    here = bool(list(Path().glob(value))) if globby else p.exists()
    if here:
        return value
    there = train_cwd / p
    return str(there) if (bool(list(train_cwd.glob(value))) if globby else there.exists()) else value


def data_config(run: Run, opts: DictConfig) -> dict:
    """The run's cfg.data with the saved split, loader options and resolved paths."""
    data = OmegaConf.to_container(run.cfg.data, resolve=True)
    split = run.run_dir / "split.json"
    if not split.exists():
        raise EvaluationError(f"{run.run_dir} has no split.json: the training/held-out split of this run is unknown, "
                              "so the alignment could be fitted on scored sequences; refusing to evaluate")
    train_cwd = _training_cwd(run.run_dir)
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

    def get(self, data: dict):
        from hydra.utils import instantiate

        k = self.key(data)
        if k in self._dms:
            self.hits += 1
            return k, self._dms[k]
        self.clear()  # free the previous scene before loading the next one
        dm = instantiate(OmegaConf.create(data), _convert_="all")
        dm.prepare_data()
        dm.setup("fit")
        self._dms[k] = dm
        return k, dm

    def clear(self) -> None:
        import gc

        self._dms.clear()
        self._batches.clear()
        gc.collect()

    def batches(self, k: str, dm, which: str) -> list:
        if (k, which) not in self._batches:
            loader = dm.train_eval_dataloader() if which == "train" else dm.test_dataloader()
            self._batches[(k, which)] = list(loader)
        return self._batches[(k, which)]


# ----------------------------------------------------------------------------- one run
def _names(dm, which: str) -> list[str]:
    ds = dm.train_set if which == "train" else dm.test_set
    return [t.name for t in ds.trials]


def collect_split(model, batches: list, names: list[str], latent: str) -> tuple[dict, float]:
    """collect_latents over pre-loaded batches (so the timing is inference only) + the
    observations / actions the baselines need + trial names as seq_id."""
    import numpy as np
    import torch

    from embodied_tactile.eval.callback import collect_latents

    t0 = time.perf_counter()
    split = collect_latents(model, batches, latent=latent)
    dt = time.perf_counter() - t0
    split["obs"] = torch.cat([b["obs"] for b in batches]).numpy()
    split["actions"] = torch.cat([b["actions"] for b in batches]).numpy()
    if len(names) != len(split["factors"]):
        raise EvaluationError(f"{len(names)} trial names but {len(split['factors'])} sequences served")
    split["seq_id"] = np.asarray(names)
    return split, dt


def evaluate_run(run: Run, opts: DictConfig, cache: DataCache, baselines: Sequence[str]) -> tuple[list, list[dict], dict]:
    """-> (Results of every method, krr history rows, info dict)."""
    from embodied_tactile.eval import evaluate_latents
    from embodied_tactile.eval.baselines import evaluate_gru, evaluate_handcrafted, evaluate_mean
    from embodied_tactile.modality import Modality
    from embodied_tactile.eval.figures import read_history
    from embodied_tactile.eval.targets import DEFAULT_TARGETS, encode_split

    t_run = time.perf_counter()
    cfg = run.cfg
    targets = str(opts.targets if opts.targets is not None else cfg.get("targets", DEFAULT_TARGETS))
    modality, skin, primitive = str(cfg.modality.name), str(cfg.skin.name), str(cfg.primitive.name)
    data = data_config(run, opts)
    source = str(data.get("source", "simulated"))
    channels = list(Modality.from_config(cfg.modality).channels)  # the run's own modality, defined once
    if list(data["channels"]) != channels:
        raise EvaluationError(f"{run.run_dir}: data channels {list(data['channels'])} differ from the run's "
                              f"modality {modality} channels {channels}; the config was edited by hand")
    key, dm = cache.get(data)
    t_data = time.perf_counter()

    model = load_module(run)
    tr, _ = collect_split(model, cache.batches(key, dm, "train"), _names(dm, "train"), opts.latent)
    te, infer_s = collect_split(model, cache.batches(key, dm, "test"), _names(dm, "test"), opts.latent)
    tr, te = encode_split(tr, targets), encode_split(te, targets)  # every method: one encoding
    t_inf = time.perf_counter()
    split = run_split(run, data["split_file"])

    metrics = _read_json(run.run_dir / "metrics.json")
    hist_path = run.run_dir / "krr_history.jsonl"
    history = read_history(hist_path) if hist_path.exists() else []
    # one time base for every method: training wall time without data preparation and without
    # evaluation (the last krr_history row: training minus the KRR checks; else train_wall_s)
    train_s = history[-1].get("train_wall_time_s") if history else metrics.get("train_wall_s")
    final_row = metrics.get("krr_final") or next((h for h in reversed(history) if h.get("final")), None)
    meta = dict(modality=modality, skin=skin, primitive=primitive, source=source)
    align = OmegaConf.to_container(opts.alignment, resolve=True)
    params = {"train_time_s": float("nan") if train_s is None else float(train_s),
              "inference_s_per_sequence": infer_s / max(1, len(te["factors"])),
              "inference_s_total_val": infer_s,
              "train_time_source": "krr_history.jsonl (training minus KRR checks)" if history
              else "metrics.json train_wall_s", "data_prepare_s": metrics.get("data_prepare_s"),
              "checkpoint": str(run.ckpt), "run_dir": str(run.run_dir)}
    res, _ = evaluate_latents(tr, te, latent=opts.latent, alignment=align, params=params, split=split["kind"], **meta)
    results = [res]
    timings = {"data_s": t_data - t_run, "load_and_infer_s": t_inf - t_data}
    for b in baselines:
        t0 = time.perf_counter()
        if b == "handcrafted":
            results.append(evaluate_handcrafted(tr, te, channels, alignment=align, split=split["kind"], **meta))
        elif b == "gru":
            gru = OmegaConf.to_container(opts.gru, resolve=True)
            if gru.get("arch") == "latent_filter":  # the run's own modality, defined once
                gru["modality"] = OmegaConf.to_container(cfg.modality, resolve=True)
            results.append(evaluate_gru(tr, te, gru=gru, **meta))
        elif b == "mean":
            results.append(evaluate_mean(tr, te, n_frames=te["obs"].shape[1], **meta))
        timings[f"{b}_s"] = time.perf_counter() - t0
    for r in results:
        r.params.setdefault("run_dir", str(run.run_dir))
        r.targets, r.split, r.unseen_objects = targets, split["kind"], split["unseen_objects"]
    timings["total_s"] = time.perf_counter() - t_run
    info = {"run_dir": str(run.run_dir), "checkpoint": str(run.ckpt), "modality": modality, "skin": skin,
            "primitive": primitive, "source": source, "channels": channels, "latent": opts.latent,
            "n_train": int(len(tr["factors"])), "n_test": int(len(te["factors"])),
            "n_frames": int(te["obs"].shape[1]), "train_wall_s": train_s, "timings": timings,
            "baselines": list(baselines), "data_prepare_s": metrics.get("data_prepare_s"), "targets": targets,
            "split": split,
            "training_final_alignment": compare_with_training(res, final_row, run.ckpt, align, opts.latent,
                                                              targets, split["kind"])}
    del model
    return results, history, info


def run_split(run: Run, split_file: str) -> dict:
    """The run's split from its ``split.json``: kind ('trial' | 'object'), sizes, object ids per
    side and ``unseen_objects`` (no held-out object has a trial in training or validation).
    An object split whose held-out objects were seen in training is an error (its numbers
    would not measure generalisation to unseen objects)."""
    from embodied_tactile.eval.results import split_report

    try:
        rep = split_report(json.loads(Path(split_file).read_text()))
    except (OSError, ValueError) as err:
        raise EvaluationError(f"{run.run_dir}: cannot read the split {split_file}: {err}") from err
    if rep["kind"] == "object" and not rep["unseen_objects"]:
        raise EvaluationError(f"{run.run_dir}: split.json ({split_file}) is an object split but held-out object(s) "
                              f"{rep['seen_test_objects']} have trials in training or validation")
    return rep


def compare_with_training(res, final_row: dict | None, ckpt: Path, align: dict, latent: str,
                          targets: str = "design_rank", split_kind: str = "trial") -> dict:
    """evaluate.py's NMSE against the training's final KRR alignment (krr_final of metrics.json /
    the ``final`` row of krr_history.jsonl): both numbers, the difference and, when they are
    not the same measurement, why (other weights, other alignment settings, other sequences)."""
    import inspect

    from embodied_tactile.eval.krr import fit_alignment, resolve_cv_grouping

    ours = float(res.summary()["nmse_trajectory_overall"])
    if not final_row or final_row.get("nmse_overall") is None:
        return {"evaluate_nmse_overall": ours, "training_nmse_overall": None,
                "reasons": ["the run has no final KRR alignment (callback off, or trained before it existed)"]}
    defaults = {k: p.default for k, p in inspect.signature(fit_alignment).parameters.items()
                if p.default is not inspect.Parameter.empty and k not in ("ids", "groups", "n_threads")}
    theirs_kw = {**defaults, **{k: v for k, v in (final_row.get("alignment_settings") or {}).items() if k in defaults}}
    ours_kw = {**defaults, **{k: v for k, v in align.items() if k in defaults}}
    norm = lambda v: list(v) if isinstance(v, (list, tuple)) else v  # noqa: E731
    reasons = []
    try:
        import torch

        step = int(torch.load(str(ckpt), map_location="cpu", mmap=True, weights_only=False).get("global_step", -1))
    except Exception:  # noqa: BLE001 -- a checkpoint without a step: say so below
        step = -1
    if step != int(final_row.get("step", -2)):
        reasons.append(f"other weights: {ckpt.name} (step {step}) against the final weights (step "
                       f"{final_row.get('step')}); checkpoint=last evaluates the final weights")
    diff = {k: (theirs_kw[k], ours_kw[k]) for k in defaults if norm(theirs_kw[k]) != norm(ours_kw[k])}
    if "alignment_settings" not in final_row:
        reasons.append("the training's last check used the callback's periodic settings")
    elif diff:
        reasons.append("alignment settings (training, evaluate.py): "
                       + ", ".join(f"{k}=({a}, {b})" for k, (a, b) in diff.items()))
    theirs_groups = (final_row.get("alignment_settings") or {}).get("groups", "sequence")
    ours_groups = resolve_cv_grouping(align.get("groups", "auto"), split_kind)
    if "alignment_settings" in final_row and theirs_groups != ours_groups:
        reasons.append(f"CV folds grouped by {theirs_groups} in training, by {ours_groups} here")
    if final_row.get("val_frame_stride", 1) != 1:
        reasons.append(f"training scored every {final_row['val_frame_stride']}th frame")
    if final_row.get("latent", latent) != latent:
        reasons.append(f"latent {final_row.get('latent')} against {latent}")
    if final_row.get("targets", "physical") != targets:  # rows written before targets existed: physical units
        reasons.append(f"targets {final_row.get('targets', 'physical')} (training) against {targets}")
    if (final_row.get("n_train"), final_row.get("n_test")) != (res.n_train, res.n_test):
        reasons.append(f"sequences: training {final_row.get('n_train')} fit / {final_row.get('n_test')} scored, "
                       f"evaluate.py {res.n_train} / {res.n_test}")
    theirs = float(final_row["nmse_overall"])
    if "alignment_settings" in final_row and "alphas" not in final_row["alignment_settings"] and abs(ours - theirs) > 1e-9:
        reasons.append("the training's alpha grid is not recorded (runs written before the grid reached 100 used "
                       "1e-4 .. 1; evaluate.py now searches 1e-4 .. 100)")
    return {"evaluate_nmse_overall": ours, "training_nmse_overall": theirs, "difference": ours - theirs,
            "training_epoch": final_row.get("epoch"), "reasons": reasons}


def _read_json(p: Path) -> dict:
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return {}


# ----------------------------------------------------------------------------- main
def evaluate(target: str | os.PathLike, overrides: Sequence[str] = ()) -> dict:
    """Evaluate a run / checkpoint / multirun; return {"out": folder, "runs": [info...],
    "skipped": [...], "written": write_report's dict}. Raises EvaluationError."""
    overrides, selection = split_overrides(overrides)
    opts = parse_options(overrides)
    if opts.torch_threads:
        from embodied_tactile.runtime import set_threads

        set_threads(int(opts.torch_threads))
    kind, runs, skipped = discover(Path(target), opts.checkpoint)
    runs = select_runs(runs, selection)
    baselines = list(opts.baselines) if opts.baselines is not None else list(
        BASELINES if kind == "run" else MULTIRUN_BASELINES)
    root = runs[0].run_dir if kind == "run" else Path(target)
    if opts.out:
        out = Path(opts.out)
    elif Path(target).is_file():  # one checkpoint file: keep its report apart from the run's default one
        out = root / f"evaluation-{runs[0].ckpt.stem}"
    else:
        out = root / ("evaluation" if opts.checkpoint == "best" else f"evaluation-{opts.checkpoint}")
    if selection and not opts.out:  # a selection never overwrites the whole sweep's report
        out = out.with_name(out.name + "-" + ",".join(f"{k}={'+'.join(v)}" for k, v in selection.items()))

    from embodied_tactile.eval import write_report
    from embodied_tactile.eval.results import config_axes
    from embodied_tactile.runtime import peak_rss_bytes

    t0 = time.perf_counter()
    cache = DataCache()
    # every configuration axis that differs between the runs (beyond modality / skin / primitive;
    # the seed is the replicate axis): tables group by all of them and average over seeds only
    axes = config_axes([OmegaConf.to_container(r.cfg, resolve=True) for r in runs], [r.name for r in runs])
    from collections import Counter

    cells = Counter((_cell(r), tuple(sorted(a.items()))) for r, a in zip(runs, axes))
    # stream: runs sharing a data config one after the other, one DataModule in memory at a time
    data_keys = [DataCache.key(data_config(r, opts)) for r in runs]
    order = sorted(range(len(runs)), key=lambda i: (data_keys.index(data_keys[i]), i))
    per_run: dict[int, tuple] = {}
    for n, i in enumerate(order):
        run = runs[i]
        log.info("[%d/%d] %s (%s)", n + 1, len(runs), run.run_dir, run.ckpt.name)
        results, history, info = evaluate_run(run, opts, cache, baselines)
        seed = run.cfg.get("seed")
        cell = (_cell(run), tuple(sorted(axes[i].items())))
        for r in results:
            r.seed, r.axes = (None if seed is None else int(seed)), dict(axes[i])
            if cells[cell] > 1:  # replicates of one configuration: tell them apart by seed (or folder)
                same = [runs[j].cfg.get("seed") for j in range(len(runs)) if (_cell(runs[j]), tuple(sorted(axes[j].items()))) == cell]
                r.replicate = f"seed={seed}" if same.count(seed) == 1 else run.name
        label = results[0].label.split("/", 1)[1]
        info["axes"], info["seed"] = dict(axes[i]), seed
        per_run[i] = (results, history, info, label)
        cmp_ = info["training_final_alignment"]
        log.info("    %s: NMSE overall %.4g (%d train / %d held-out, %.1f s)", label,
                 results[0].summary()["nmse_trajectory_overall"], info["n_train"], info["n_test"],
                 info["timings"]["total_s"])
        log.info("    %s", _agreement_line(cmp_))
    cache.clear()
    all_results, histories, infos = [], {}, []
    for i in range(len(runs)):
        results, history, info, label = per_run.pop(i)
        if history:
            histories[label] = history
        all_results.extend(results)
        infos.append(info)
    t_eval = time.perf_counter()
    sources = sorted({i["source"] for i in infos})
    split_extra = {i["run_dir"]: {"n_train": i["n_train"], "n_test": i["n_test"], "split_file": str(Path(i["run_dir"]) / "split.json")}
                   for i in infos}
    written = write_report(all_results, out, source=sources[0] if len(sources) == 1 else None,
                           split_sizes_=split_extra, histories=histories or None,
                           figures=bool(opts.figures), umap=bool(opts.umap), distance_mode=str(opts.distance_mode))
    t_rep = time.perf_counter()
    summary = {"kind": kind, "target": str(target), "out": str(out), "options": OmegaConf.to_container(opts),
               "baselines": baselines, "runs": infos,
               "skipped": [{"run_dir": str(d), "reason": r} for d, r in skipped],
               "selection": selection, "datamodule_reuse": cache.hits,
               "timings": {"evaluate_s": t_eval - t0, "report_s": t_rep - t_eval},
               "peak_rss_bytes": peak_rss_bytes()}
    (out / "evaluation.json").write_text(json.dumps(summary, indent=1, default=str))
    if opts.print_tables:
        for p in written["tables"]:
            if p.endswith(".md"):
                print(Path(p).read_text())
    for i in infos:
        print(f"{Path(i['run_dir']).name}: {_agreement_line(i['training_final_alignment'])}")
    for d, r in skipped:
        print(f"SKIPPED {d}: {r}")
    print(f"evaluated {len(infos)} run(s) ({len(skipped)} skipped) in {t_rep - t0:.1f} s -> {out}")
    return {"out": str(out), "runs": infos, "skipped": summary["skipped"], "written": written}


def train_log_dir() -> str:
    """``paths.log_dir`` as train.py composes it (configs/train.yaml + configs/local/)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        return str(compose(config_name="train").paths.log_dir)


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


def _cell(run: Run) -> tuple:
    c = run.cfg
    return (str(c.modality.name), str(c.skin.name), str(c.primitive.name))


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description="Evaluate a training run folder, a checkpoint file or a multirun folder "
                    "(options: key=value over configs/evaluate.yaml).",
        epilog="e.g. python evaluate.py logs/train/runs/<run> latent=both baselines=[handcrafted,mean] umap=false")
    ap.add_argument("path", nargs="?", default=None,
                    help="run folder | checkpoint (.ckpt) | multirun folder; default: the most recent run or "
                         "multirun under <paths.log_dir>/train (paths.log_dir=... picks another log folder)")
    ap.add_argument("overrides", nargs="*", help="evaluation options, key=value (see configs/evaluate.yaml)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    quiet.silence_third_party()
    overrides = list(args.overrides)
    if args.path is not None and "=" in args.path and "/" not in args.path.split("=", 1)[0] \
            and not Path(args.path).exists():  # an option (key=value), not a path
        overrides.insert(0, args.path)
        args.path = None
    log_dirs = [o.split("=", 1)[1] for o in overrides if o.startswith("paths.log_dir=")]
    overrides = [o for o in overrides if not o.startswith("paths.log_dir=")]
    try:
        if args.path is None:
            args.path = str(latest_target(log_dirs[-1] if log_dirs else None))
        evaluate(args.path, overrides)
    except EvaluationError as err:
        print(f"evaluate.py: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
