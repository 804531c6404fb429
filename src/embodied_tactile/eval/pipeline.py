"""evaluate.py's pipeline: options, run selection, one run's evaluation (the Latent Filter's
KRR alignment beside the baselines on the same split), the agreement with the training's
final alignment, the report and the terminal summary.

Per run (docs/reference/evaluation.md): the run's own config and saved split (:mod:`.runs`), latents
over the training split (fit) and the held-out test split (scored), :func:`evaluate_latents`
and the baselines, :func:`write_report` into ``<run>/evaluation`` (a multirun's or study's
folder: every job, aggregated). The terminal gets what was measured: per run the NMSE per
factor beside the baselines, for a study the findings with at least one measured comparison;
every table is in the output folder.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import time
from collections import Counter
from pathlib import Path
from typing import Sequence

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, ValidationError

from embodied_tactile.constants import FACTOR_NAMES
from embodied_tactile.eval.runs import (DataCache, EvaluationError, Run, collect_splits, data_config, discover,
                                        load_module, run_split, run_state, trial_names, trial_objects,
                                        untrained_module)
from embodied_tactile.eval.results import SPLIT_KINDS
from embodied_tactile.jsonio import read_json
from embodied_tactile.options.alignment import AlignmentOptions, alignment_options
from embodied_tactile.options.checks import SettingsError, check_options
from embodied_tactile.options.evaluation import BASELINES, EvaluationOptions
from embodied_tactile.paths import config_dir

MULTIRUN_BASELINES = tuple(b for b in BASELINES if b != "gru")
SELECT_ALIASES = {"modality": "modality.name", "skin": "skin.name", "primitive": "primitive.name"}

log = logging.getLogger("evaluate")


def defaults_file() -> Path:
    """``configs/evaluate.yaml``: evaluation options only (never the scene or the model)."""
    return Path(config_dir()) / "evaluate.yaml"


# ----------------------------------------------------------------------------- options
def evaluation_keys() -> list[str]:
    """evaluate.py's option names (:class:`~embodied_tactile.options.evaluation.EvaluationOptions`)."""
    from dataclasses import fields

    return [f.name for f in fields(EvaluationOptions)]


def parse_options(overrides: Sequence[str] = ()) -> DictConfig:
    """:class:`~embodied_tactile.options.evaluation.EvaluationOptions` + ``configs/evaluate.yaml``
    + ``key=value`` overrides (unknown top-level keys rejected;
    ``alignment.*`` takes the keys of :class:`~embodied_tactile.options.alignment.AlignmentOptions`,
    ``gru.*`` any keyword of GRURegressor)."""
    base = OmegaConf.merge(OmegaConf.structured(EvaluationOptions), OmegaConf.load(defaults_file()))
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
    except ValidationError as err:  # a value of the wrong type: one line naming the key
        raise EvaluationError(f"{err.full_key}={err.msg.split(chr(39))[1] if chr(39) in err.msg else '?'}: "
                              f"{err.msg.splitlines()[0]}") from None
    try:  # each value by its field's type and choices (options.evaluation)
        check_options(EvaluationOptions, opts, "")
    except SettingsError as err:
        raise EvaluationError(str(err)) from None
    try:  # the overrides alone: the run's own alignment is layered under them per run
        alignment_options(OmegaConf.to_container(opts.alignment, resolve=True))
    except ValueError as err:
        raise EvaluationError(str(err)) from None
    return opts


def split_overrides(overrides: Sequence[str]) -> tuple[list[str], dict[str, list[str]]]:
    """-> (evaluation options: keys of configs/evaluate.yaml, run selection: every other
    ``key=value``, e.g. ``modality=multi_l skin=hard seed=[0,1] annealing.name=dvbf``)."""
    known = set(evaluation_keys())
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
                f"({sorted(evaluation_keys())}) nor a key of the runs' config_resolved.yaml")
        kept = [r for r, h in zip(runs, have) if h is not None and _matches(h, want)]
        if not kept:
            raise EvaluationError(f"no run matches {key}={','.join(want)} (the runs have {key} = "
                                  f"{sorted({str(h) for h in have})}; a selection picks runs, it never changes a run's scene)")
        runs = kept
    if selection:
        log.info("selected %d run(s) by %s", len(runs), selection)
    return runs



def agreement_line(c: dict) -> str:
    """One line: evaluate.py's NMSE beside the number the training printed."""
    if c.get("training_nmse_overall") is None:
        return f"NMSE {c['evaluate_nmse_overall']:.4g} ({c['other'][0]})"
    head = f"NMSE {c['evaluate_nmse_overall']:.4g} here, {c['training_nmse_overall']:.4g} printed by the training"
    return head + (f" (difference {c['difference']:+.1e})" if not c["other"] else
                   " (another measurement: " + "; ".join(c["other"]) + ")")


# ----------------------------------------------------------------------------- one run
def run_targets(cfg: DictConfig, opts: DictConfig) -> str:
    """The target encoding to score: ``opts.targets``, or (null) the run's own ``targets``
    (train.py's; design_rank for runs that predate it)."""
    from embodied_tactile.eval.targets import DEFAULT_TARGETS

    return str(opts.targets if opts.targets is not None else cfg.get("targets", DEFAULT_TARGETS))


def run_alignment(cfg: DictConfig, opts: DictConfig) -> AlignmentOptions:
    """The alignment to score with: the run's own ``alignment`` (the one its final check used;
    the current defaults for a run that predates it) with ``opts.alignment``'s overrides,
    built and checked here, once per run."""

    own = OmegaConf.to_container(cfg.alignment, resolve=True) if cfg.get("alignment") is not None else None
    try:
        return alignment_options(own, OmegaConf.to_container(opts.alignment, resolve=True))
    except ValueError as err:
        raise EvaluationError(str(err)) from None


def evaluate_run(run: Run, opts: DictConfig, cache: DataCache, baselines: Sequence[str]) -> tuple[list, list[dict], dict]:
    """-> (Results of every method, krr history rows, info dict)."""
    from embodied_tactile.eval.latents import INFER_BATCH_SIZE
    from embodied_tactile.eval.results import evaluate_latents
    from embodied_tactile.eval.baselines import evaluate_gru, evaluate_handcrafted, evaluate_hybrid, evaluate_mean
    from embodied_tactile.data.modality import Modality
    from embodied_tactile.eval.figures import read_history
    from embodied_tactile.eval.targets import encode_split
    from embodied_tactile.run.provenance import data_changes, data_identity, trial_digests
    from embodied_tactile.run.threadenv import set_threads

    t_run = time.perf_counter()
    cfg = run.cfg
    modality, skin, primitive = str(cfg.modality.name), str(cfg.skin.name), str(cfg.primitive.name)
    data = data_config(run, opts)
    source = str(data.get("source", "simulated"))
    channels = list(Modality.from_config(cfg.modality).channels)  # the run's own modality, defined once
    if list(data["channels"]) != channels:
        raise EvaluationError(f"{run.run_dir}: data channels {list(data['channels'])} differ from the run's "
                              f"modality {modality} channels {channels}; the config was edited by hand")
    data_changed: list[str] = []

    def same_data(dm) -> None:  # the raw data's digests now against those recorded at training
        data_changed[:] = data_changes(read_json(run.run_dir / "provenance.json").get("raw_data"),
                                       data_identity(dm.cache_files, trial_digests(dm)))
        if data_changed and not opts.allow_changed_data:
            raise EvaluationError(f"{run.run_dir}: the data differ from those it was trained on: "
                                  f"{'; '.join(data_changed)}; the run's numbers would not be reproduced "
                                  "(allow_changed_data=true scores it anyway, and says so)")

    try:
        key, dm = cache.get(data, check=same_data)
    except EvaluationError:
        raise
    except (RuntimeError, ValueError, OSError) as err:  # e.g. split.json names trials the data no longer hold
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise EvaluationError(f"{run.run_dir}: cannot prepare its data: {first}") from None
    t_data = time.perf_counter()

    metrics = read_json(run.run_dir / "metrics.json")
    if not opts.torch_threads:  # float32 latents differ in their last bits between thread counts
        set_threads(int((metrics.get("krr_final") or {}).get("torch_threads") or 1))
    model = load_module(run)
    sides = ((cache.batches(key, dm, "train"), trial_names(dm, "train")),
             (cache.batches(key, dm, opts.held_out), trial_names(dm, opts.held_out)))
    infer_batch = int(OmegaConf.select(cfg, "callbacks.krr_alignment.infer_batch_size", default=None)
                      or INFER_BATCH_SIZE)  # the training's final read-out's batches: the same latents
    tr, te, infer_s = collect_splits(model, *sides, opts.latent, infer_batch)
    te["factors_physical"] = te["factors"]  # the trials' own factors, for figure legends
    targets = run_targets(cfg, opts)
    tr, te = encode_split(tr, targets), encode_split(te, targets)  # every method: one encoding
    t_inf = time.perf_counter()
    split = run_split(run, data["split_file"], trial_objects(dm))

    hist_path = run.run_dir / "krr_history.jsonl"
    history = read_history(hist_path) if hist_path.exists() else []
    # one time base for every method: training wall time without data preparation and without
    # evaluation (the last krr_history row: training minus the KRR checks; else train_wall_s)
    train_s = history[-1].get("train_wall_time_s") if history else metrics.get("train_wall_s")
    final_row = metrics.get("krr_final") or next((h for h in reversed(history) if h.get("final")), None)
    meta = dict(modality=modality, skin=skin, primitive=primitive, source=source)
    align = run_alignment(cfg, opts)
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
        if b == "untrained":  # the same network and read-out at step 0: the floor
            floor = untrained_module(run, model)
            tr0, te0, _ = collect_splits(floor, *sides, opts.latent, infer_batch)
            del floor
            tr0, te0 = encode_split(tr0, targets), encode_split(te0, targets)
            results.append(evaluate_latents(tr0, te0, latent=opts.latent, method="untrained", alignment=align,
                                            split=split["kind"], **meta)[0])
        elif b == "handcrafted":
            results.append(evaluate_handcrafted(tr, te, channels, alignment=align, split=split["kind"],
                                                handcrafted=OmegaConf.to_container(opts.handcrafted)
                                                if opts.get("handcrafted") is not None else None, **meta))
        elif b == "hybrid":  # the same read-out on [hand-crafted features, the run's latents]
            results.append(evaluate_hybrid(tr, te, channels, latent=opts.latent, alignment=align, split=split["kind"],
                                           handcrafted=OmegaConf.to_container(opts.handcrafted)
                                           if opts.get("handcrafted") is not None else None, **meta))
        elif b == "gru":
            gru = OmegaConf.to_container(opts.gru, resolve=True)
            if gru.get("seed") is None:  # the run's seed: a baseline's spread over seeds is measured, not assumed 0
                gru["seed"] = int(cfg.seed)
            if gru.get("arch") == "latent_filter":  # the run's own modality, defined once
                gru["modality"] = OmegaConf.to_container(cfg.modality, resolve=True)
            results.append(evaluate_gru(tr, te, gru=gru, **meta))
        elif b == "mean":
            results.append(evaluate_mean(tr, te, n_frames=te["obs"].shape[1], **meta))
        timings[f"{b}_s"] = time.perf_counter() - t0
    for r in results:
        r.params.setdefault("run_dir", str(run.run_dir))
        r.targets, r.split, r.unseen_objects = targets, split["kind"], split["unseen_objects"]
        r.params["held_out"] = opts.held_out
    timings["total_s"] = time.perf_counter() - t_run
    info = {"run_dir": str(run.run_dir), "checkpoint": str(run.ckpt), "modality": modality, "skin": skin,
            "primitive": primitive, "source": source, "channels": channels, "latent": opts.latent,
            "n_train": int(len(tr["factors"])), "n_test": int(len(te["factors"])),
            "n_frames": int(te["obs"].shape[1]), "train_wall_s": train_s, "timings": timings,
            "baselines": list(baselines), "data_prepare_s": metrics.get("data_prepare_s"), "targets": targets,
            "split": split, "held_out": opts.held_out,
            "data_changed": data_changed,
            "training_final_alignment": compare_with_training(
                res, final_row, run.ckpt, OmegaConf.to_container(opts.alignment, resolve=True), opts.latent,
                targets, opts.held_out)}
    if data_changed:
        info["training_final_alignment"]["other"].insert(0, "the data changed since training: " + "; ".join(data_changed))
    del model
    return results, history, info



def compare_with_training(res, final_row: dict | None, ckpt: Path, overrides: dict, latent: str,
                          targets: str, held_out: str = "test") -> dict:
    """evaluate.py's NMSE beside the number the training printed (its final read-out,
    metrics.json ``krr_final``). Both read the run's own ``alignment`` on every training and
    held-out sequence, so they are one measurement unless evaluate.py was asked for other
    weights (``checkpoint=best`` when the best is not the last), another read-out
    (``alignment.*``), ``latent``, ``targets`` or held-out side: ``other`` names which."""
    ours = float(res.summary()["nmse_trajectory_overall"])
    if not final_row or final_row.get("nmse_overall") is None:
        return {"evaluate_nmse_overall": ours, "training_nmse_overall": None, "other": ["no final read-out in training"]}
    try:
        import torch

        step = int(torch.load(str(ckpt), map_location="cpu", mmap=True, weights_only=False).get("global_step", -1))
    except Exception:  # noqa: BLE001 -- a checkpoint without a step is not the final weights
        step = -1
    other = [what for what, differs in (
        (f"weights of step {step} ({ckpt.name}; the training read step {final_row.get('step')})",
         step != int(final_row.get("step", -2))),
        (f"read-out {overrides}", bool(overrides)), (f"latent {latent}", final_row.get("latent", latent) != latent),
        (f"targets {targets}", final_row.get("targets", targets) != targets),
        (f"the {held_out} side", held_out != "test")) if differs]
    theirs = float(final_row["nmse_overall"])
    return {"evaluate_nmse_overall": ours, "training_nmse_overall": theirs, "difference": ours - theirs,
            "other": other}


# ----------------------------------------------------------------------------- all runs
def output_folder(target: Path, runs: list[Run], kind: str, opts: DictConfig, selection: dict) -> Path:
    """``out=`` if given; else ``<run>/evaluation`` (``evaluation-best`` for checkpoint=best,
    ``evaluation-<ckpt>`` for one checkpoint file), ``<multirun>/evaluation`` for a sweep;
    a selection gets its own folder so it never overwrites the whole sweep's report."""
    if opts.out:
        return Path(opts.out)
    root = runs[0].run_dir if kind == "run" else target
    if target.is_file():
        out = root / f"evaluation-{runs[0].ckpt.stem}"
    else:
        out = root / ("evaluation" if opts.checkpoint == "last" else f"evaluation-{opts.checkpoint}")
    if opts.held_out == "val":  # never where the test report lives
        out = out.with_name(out.name + "-val")
    if selection:
        out = out.with_name(out.name + "-" + ",".join(f"{k}={'+'.join(v)}" for k, v in selection.items()))
    return out


def _written_by_evaluation(path: Path) -> bool:
    """What an evaluation writes in its output folder (:func:`write_report`, evaluation.json,
    the per-run results it reuses: :data:`PER_RUN`)."""
    return (path.name in ("results.json", "evaluation.json") or (path.name in ("figures", PER_RUN) and path.is_dir())
            or (path.name.startswith("table_") and path.suffix in (".md", ".csv", ".tex")))


#: the evaluation folder's store of each run's scored results (``<key>.npz``, :mod:`.records`),
#: reused by the next evaluation into that folder when nothing that decides them changed
#: (:func:`reuse_key`)
PER_RUN = "per_run"


def _code_digest() -> str:
    """Digest of the package's Python sources: any change of code invalidates reused results."""
    import hashlib

    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes())
    return h.hexdigest()


def scoring_options(opts: DictConfig) -> dict:
    """The evaluation options that decide a run's scored results (every option but the
    report's: figures, UMAP, tables, output folder)."""
    report_only = {"figures", "umap", "print_tables", "out", "distance_mode"}
    return {k: v for k, v in OmegaConf.to_container(opts, resolve=True).items() if k not in report_only}


def fingerprint(opts: DictConfig, baselines: Sequence[str], code: str) -> dict:
    """What scored a record (:mod:`.records`): the package's code digest and the commit it was
    read from, the scoring options' digest and the baselines. An archived run is merged only
    into an evaluation with the same (:func:`archived_mismatch`)."""
    from embodied_tactile.eval.records import digest
    from embodied_tactile.run.provenance import git_state

    return {"code": code, "commit": git_state(Path(__file__).resolve().parents[3]).get("commit"),
            "options": digest(scoring_options(opts)), "baselines": list(baselines)}


def archived_mismatch(run: Run, current: dict) -> str | None:
    """None when the archived ``run``'s record was scored as ``current`` would score it, else
    what differs (one line: the commit and options to evaluate it with)."""
    from embodied_tactile.eval.records import RecordError, read_fingerprint

    try:
        had = read_fingerprint(run.record)
    except RecordError as err:
        return str(err)
    diff = [k for k in ("code", "options", "baselines") if had.get(k) != current.get(k)]
    if not diff:
        return None
    return (f"{run.record}: scored with other {', '.join(diff)} (commit {str(had.get('commit'))[:12]}, baselines "
            f"{had.get('baselines')}) and its checkpoint is not here to score again: evaluate the study with that "
            "commit's code and options")


def reuse_key(run: Run, opts: DictConfig, baselines: Sequence[str], code: str) -> str:
    """What decides a run's scored results: its folder, the checkpoint's bytes, its config,
    split and metrics, the size and time of every data file it names (a deleted raw file's
    record in its place, ``data.keep_raw=false``), the evaluation's
    options (but those of the report only), the baselines and the package's code."""
    import hashlib

    h = hashlib.sha256()
    h.update(json.dumps([str(run.run_dir), list(baselines), code, scoring_options(opts)], sort_keys=True,
                        default=str).encode())
    with open(run.ckpt, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    for name in ("config_resolved.yaml", "split.json", "metrics.json", "krr_history.jsonl"):
        f = run.run_dir / name
        h.update(f.read_bytes() if f.exists() else b"-")
    data = (read_json(run.run_dir / "metrics.json").get("data") or {})
    from embodied_tactile.data.prepare import dropped_record_path

    raw = [Path(f) for f in data.get("raw_files") or []]
    files = raw + [dropped_record_path(f) for f in raw if not f.exists()] + list((data.get("cache_files") or {}).values())
    for f in map(Path, files):
        st = f.stat() if f.exists() else None
        h.update(f"{f}:{st.st_size if st else -1}:{st.st_mtime_ns if st else -1}".encode())
    return h.hexdigest()[:24]


def _reused(out: Path, key: str):
    """(results, history, info) an earlier evaluation into ``out`` stored under ``key``, or None."""
    from embodied_tactile.eval.records import RecordError, read_record

    f = out / PER_RUN / f"{key}.npz"
    if not f.exists():
        return None
    try:
        return read_record(f)[0]
    except RecordError as err:  # a damaged store is scored again, never trusted
        log.warning("%s; the run is scored again", err)
        return None


def archived(run: Run) -> tuple:
    """An archived run's scored results from its record, its paths those of the folder it
    now lies in."""
    from embodied_tactile.eval.records import read_record

    (results, history, info), _ = read_record(run.record)
    for r in results:
        r.params["run_dir"] = str(run.run_dir)
    info.update(run_dir=str(run.run_dir), checkpoint=None, archived=str(run.record))
    return results, history, info


class OwnedOutput:
    """An evaluation owns its output folder. A lock beside it (``.<name>.lock``, held while
    the evaluation runs): a second evaluation into the same folder is refused, naming the
    holder. Everything is written into a fresh ``.<name>.tmp-<pid>`` (the folder
    ``__enter__`` returns); :meth:`publish` renames it into place once complete (a previous
    folder is renamed aside first, then removed): the folder is never half written nor a mix
    of two evaluations. A failure leaves the previous folder as it was; a killed evaluation's
    temporary folder is removed by the next one. A folder holding anything an evaluation does
    not write (out= naming a folder of other files) is never replaced: refused."""

    def __init__(self, out: Path) -> None:
        self.out = Path(out)
        self.tmp = self.out.with_name(f".{self.out.name}.tmp-{os.getpid()}")
        self._fd: int | None = None

    def __enter__(self) -> Path:
        import shutil

        from embodied_tactile.run.runfolder import try_lock, write_holder

        self.out.parent.mkdir(parents=True, exist_ok=True)
        fd, holder = try_lock(self.out.with_name(f".{self.out.name}.lock"))
        if fd is None:
            raise EvaluationError(f"{self.out} is being written by another evaluation (pid {holder.get('pid', '?')} "
                                  f"on host {holder.get('host', '?')}); wait for it, or give another out=")
        write_holder(fd)
        self._fd = fd
        foreign = sorted(p.name for p in self.out.iterdir() if not _written_by_evaluation(p)) if self.out.is_dir() else []
        if foreign:
            self.__exit__()
            raise EvaluationError(f"{self.out} holds files an evaluation does not write ({', '.join(foreign[:3])}"
                                  f"{' ...' if len(foreign) > 3 else ''}): an evaluation replaces its whole output "
                                  "folder; give a new or empty out=")
        for stale in self.out.parent.glob(f".{self.out.name}.tmp-*"):  # the lock says no writer is alive
            log.warning("removing %s: an evaluation that did not finish", stale)
            shutil.rmtree(stale, ignore_errors=True)
        self.tmp.mkdir()
        return self.tmp

    def publish(self) -> None:
        import shutil

        aside = self.out.with_name(f".{self.out.name}.old-{os.getpid()}")
        if self.out.exists():
            os.rename(self.out, aside)
        os.rename(self.tmp, self.out)
        shutil.rmtree(aside, ignore_errors=True)

    def __exit__(self, *exc) -> None:
        import shutil

        if self.tmp.exists():  # not published: the previous folder stays as it was
            shutil.rmtree(self.tmp, ignore_errors=True)
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def cell(run: Run) -> tuple:
    c = run.cfg
    return (str(c.modality.name), str(c.skin.name), str(c.primitive.name))


def evaluate(target: str | os.PathLike, overrides: Sequence[str] = ()) -> dict:
    """Evaluate a run / checkpoint / multirun / study folder; return {"out": folder, "runs":
    [info...], "skipped": [...], "written": write_report's dict}. Prints the measured summary
    (:func:`terminal_summary`). Raises EvaluationError."""
    overrides, selection = split_overrides(overrides)
    opts = parse_options(overrides)
    if opts.torch_threads:  # else each run's own (evaluate_run)
        from embodied_tactile.run.threadenv import set_threads

        set_threads(int(opts.torch_threads))
    target = Path(target)
    kind, runs, skipped = discover(target, opts.checkpoint)
    runs = select_runs(runs, selection)
    baselines = list(opts.baselines) if opts.baselines is not None else list(
        BASELINES if kind == "run" else MULTIRUN_BASELINES)
    out = output_folder(target, runs, kind, opts, selection)
    # a run in training: refused alone, skipped (and named) in a folder of runs; so is a run that
    # did not finish there (interrupted, killed, failed): a folder's tables average finished runs
    states = {}
    current = fingerprint(opts, baselines, _code_digest())
    for r in list(runs):
        try:
            states[str(r.run_dir)] = st = run_state(r, bool(opts.allow_running))
            if kind != "run" and st["status"] not in ("finished", "training"):
                raise EvaluationError(f"{r.run_dir} is {st['status']} ({st['reason']}): not finished, so not "
                                      f"averaged with the others (python evaluate.py {r.run_dir} scores it alone)")
            if r.ckpt is None and (why := archived_mismatch(r, current)):
                raise EvaluationError(why)
        except EvaluationError as err:
            if kind == "run":
                raise
            runs.remove(r)
            states.pop(str(r.run_dir), None)
            skipped.append((r.run_dir, str(err)))
            log.warning("skipping %s", err)
    if not runs:
        raise EvaluationError(f"{target}: no run in it is finished (every one is being trained, interrupted or "
                              "failed); wait for one to end, or evaluate a run alone")
    for st in states.values():  # a run that is not finished says so first, with the checkpoint evaluated
        if st.get("line"):
            print(st["line"], flush=True)
    writable(out)
    owned = OwnedOutput(out)
    try:
        with owned:
            return _evaluate_runs(target, kind, runs, skipped, selection, opts, baselines, owned, states, current)
    except OSError as err:  # a full disk or a read-only folder while writing: nothing published
        if err.errno not in WRITE_ERRNOS:
            raise
        raise EvaluationError(f"cannot write the evaluation into {out}: {err.strerror or err}"
                              f"{f' ({err.filename})' if err.filename else ''}; nothing written, an earlier "
                              f"evaluation there is kept (free space, or give out=<another folder>)") from None


#: OS errors of a folder that cannot take the evaluation's files (full, read-only, quota, size limit, permissions)
WRITE_ERRNOS = (errno.ENOSPC, errno.EROFS, errno.EDQUOT, errno.EFBIG, errno.EACCES, errno.EPERM)


def writable(out: Path) -> None:
    """EvaluationError naming ``out`` and the OS reason when its folder cannot be written
    (read-only, full): checked before any data are prepared."""
    from embodied_tactile.run.settings import SettingsError, check_writable_dir

    try:
        check_writable_dir("out", out.parent)
    except SettingsError as err:
        raise EvaluationError(f"cannot write the evaluation into {out}: {str(err).split('(', 1)[-1].rstrip(')')}; "
                              "give out=<a writable folder>") from None


def _evaluate_runs(target: Path, kind: str, runs: list[Run], skipped: list, selection: dict, opts: DictConfig,
                   baselines: list[str], owned: OwnedOutput, states: dict[str, dict], current: dict) -> dict:
    """:func:`evaluate` once its output folder is owned: writes into ``owned.tmp``, then
    publishes it as ``owned.out``."""
    from embodied_tactile.eval.records import write_record
    from embodied_tactile.eval.report import write_report
    from embodied_tactile.eval.results import config_axes
    from embodied_tactile.run.provenance import peak_rss_bytes

    out, tmp = owned.out, owned.tmp
    t0 = time.perf_counter()
    cache = DataCache()
    # every configuration axis that differs between the runs (beyond modality / skin / primitive;
    # the seed is the replicate axis): tables group by all of them and average over seeds only
    axes = config_axes([OmegaConf.to_container(r.cfg, resolve=True) for r in runs], [r.name for r in runs])
    keys = [(cell(r), tuple(sorted(a.items()))) for r, a in zip(runs, axes)]
    cells = Counter(keys)
    # stream: runs sharing a data config one after the other, one DataModule in memory at a time
    data_keys = [DataCache.key(data_config(r, opts)) for r in runs]
    order = sorted(range(len(runs)), key=lambda i: (data_keys.index(data_keys[i]), i))
    per_run: dict[int, tuple] = {}
    n_reused = 0
    (tmp / PER_RUN).mkdir()
    for n, i in enumerate(order):
        run = runs[i]
        log.info("[%d/%d] %s (%s)", n + 1, len(runs), run.run_dir, run.ckpt.name if run.ckpt else run.record.name)
        if run.ckpt is None:
            stored, key = archived(run), None
            n_reused += 1
            log.info("    archived: its record, scored by the same code and options")
        else:
            key = reuse_key(run, opts, baselines, current["code"])
            stored = _reused(out, key)
            if stored is None:
                stored = evaluate_run(run, opts, cache, baselines)
            else:
                n_reused += 1
                log.info("    reused: scored by an earlier evaluation into %s with the same checkpoint, data, "
                         "options and code", out)
            write_record(tmp / PER_RUN / f"{key}.npz", stored, current)
        results, history, info = stored
        info["record"] = f"{PER_RUN}/{key}.npz" if key else info["archived"]
        info["run_state"] = states[str(run.run_dir)]
        seed = run.cfg.get("seed")
        for r in results:
            r.seed, r.axes = (None if seed is None else int(seed)), dict(axes[i])
            if cells[keys[i]] > 1:  # replicates of one configuration: tell them apart by seed (or folder)
                same = [runs[j].cfg.get("seed") for j in range(len(runs)) if keys[j] == keys[i]]
                r.replicate = f"seed={seed}" if same.count(seed) == 1 else run.name
        label = results[0].label.split("/", 1)[1]
        info["axes"], info["seed"], info["label"] = dict(axes[i]), seed, label
        per_run[i] = (results, history, info, label)
        log.info("    %s: NMSE overall %.4g (%d train / %d held-out, %.1f s)", label,
                 results[0].summary()["nmse_trajectory_overall"], info["n_train"], info["n_test"],
                 info["timings"]["total_s"])
        log.info("    %s", agreement_line(info["training_final_alignment"]))
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
    split_extra = {i["run_dir"]: {"n_train": i["n_train"], "n_test": i["n_test"],
                                  "split_file": str(Path(i["run_dir"]) / "split.json")} for i in infos}
    written = write_report(all_results, tmp, source=sources[0] if len(sources) == 1 else None,
                           split_sizes_=split_extra, histories=histories or None,
                           figures=bool(opts.figures), umap=bool(opts.umap), distance_mode=str(opts.distance_mode),
                           run_states=states)
    t_rep = time.perf_counter()
    summary = {"kind": kind, "target": str(target), "out": str(out), "options": OmegaConf.to_container(opts),
               "baselines": baselines, "runs": infos,
               "skipped": [{"run_dir": str(d), "reason": r} for d, r in skipped],
               "selection": selection, "datamodule_reuse": cache.hits, "runs_reused": n_reused,
               "timings": {"evaluate_s": t_eval - t0, "report_s": t_rep - t_eval},
               "peak_rss_bytes": peak_rss_bytes()}
    (tmp / "evaluation.json").write_text(json.dumps(summary, indent=1, default=str))
    if opts.print_tables:
        for p in written["tables"]:
            if p.endswith(".md"):
                print(Path(p).read_text())
    owned.publish()
    written = {k: [str(out / Path(p).relative_to(tmp)) for p in v] for k, v in written.items()}
    print("\n".join(terminal_summary(all_results, infos, skipped, out, t_rep - t0)))
    return {"out": str(out), "runs": infos, "skipped": summary["skipped"], "written": written}


# ----------------------------------------------------------------------------- terminal
METHOD_NAMES = {"latent_filter": "Latent Filter", "untrained": "the same, untrained", "handcrafted_krr": "hand-crafted KRR",
                "hybrid_krr": "hand-crafted + latents KRR",
                "gru": "GRU", "mean": "mean"}


def terminal_summary(results: Sequence, infos: Sequence[dict], skipped: Sequence[tuple], out: Path,
                     seconds: float) -> list[str]:
    """What was measured, as lines for the terminal. One run: its NMSE per factor, one row per
    method (the Latent Filter beside the baselines), and its agreement with the training's final
    alignment. Several runs: one row per run, the Latent Filter per factor beside the baselines'
    overall NMSE. Then the paper's findings that have at least one measured comparison, the
    skipped jobs and the output folder (which keeps every table)."""
    from embodied_tactile.eval.tables import fmt_cell
    from embodied_tactile.eval.verdicts import VERDICTS, evaluate_findings, summarise

    methods = list(dict.fromkeys(r.method for r in results))
    by_run: dict[str, dict] = {}
    for r in results:
        by_run.setdefault(str(r.params.get("run_dir")), {})[r.method] = r.summary()
    lines = ["Held-out NMSE (0 = perfect, 1 = the mean predictor's level), per factor over the whole trajectory; "
             "the read-out: the run's alignment (docs/reference/evaluation.md, \"The read-out over time\"):"]
    if len(infos) == 1:
        i = infos[0]
        s = by_run[i["run_dir"]]
        lines.append(f"{i['label']} ({i['n_train']} train / {i['n_test']} held-out trials, "
                     f"{Path(i['checkpoint']).name}, split {i['split']['kind']}: "
                     f"{SPLIT_KINDS.get(i['split']['kind'], 'not recorded')})")
        lines.append("| method | " + " | ".join(FACTOR_NAMES) + " | overall | last frame | first frame <= 0.5 |")
        lines.append("|---" * (len(FACTOR_NAMES) + 4) + "|")
        for m in methods:
            row = s[m]
            first = row.get("first_frame_below_half")
            lines.append(f"| {METHOD_NAMES.get(m, m)} | "
                         + " | ".join(fmt_cell(row["nmse_trajectory"][f]) for f in FACTOR_NAMES)
                         + f" | {fmt_cell(row['nmse_trajectory_overall'])} | {fmt_cell(row['nmse_last_step_overall'])}"
                         + f" | {'never' if first is None else first} |")
        lines.append(agreement_line(i["training_final_alignment"]))
    else:
        others = [m for m in methods if m != "latent_filter"]
        lines.append("| run | " + " | ".join(FACTOR_NAMES) + " | overall | "
                     + " | ".join(METHOD_NAMES.get(m, m) for m in others) + " | agrees with training |")
        lines.append("|---" * (len(FACTOR_NAMES) + 3 + len(others)) + "|")
        for i in infos:
            s = by_run[i["run_dir"]]
            lf = s.get("latent_filter", {})
            c = i["training_final_alignment"]
            agree = "–" if c.get("training_nmse_overall") is None or c["other"] else f"{c['difference']:+.1e}"
            lines.append(f"| {i['label']} | " + " | ".join(fmt_cell(lf.get("nmse_trajectory", {}).get(f))
                                                        for f in FACTOR_NAMES)
                         + f" | {fmt_cell(lf.get('nmse_trajectory_overall'))} | "
                         + " | ".join(fmt_cell(s.get(m, {}).get("nmse_trajectory_overall")) for m in others)
                         + f" | {agree} |")
        lf = [r for r in results if r.method == "latent_filter"]
        contexts = sorted({r.cell[4] for r in lf}, key=str)
        found = []
        for ctx in contexts:
            for f in summarise(evaluate_findings([r for r in lf if r.cell[4] == ctx])):
                if sum(f[v] for v in VERDICTS if v != "not measured"):
                    tag = "; ".join(f"{k}={v}" for k, v in ctx)
                    found.append(f"({f['finding']}) {f['claim']}: {f['verdict']} "
                                 f"({', '.join(f'{f[v]} {v}' for v in VERDICTS if f[v])})" + (f" [{tag}]" if tag else ""))
        if found:
            lines.append("The paper's findings with a measured comparison:")
            lines += [f"- {x}" for x in found]
    lines += [f"SKIPPED {d}: {r}" for d, r in skipped]
    lines.append(f"evaluated {len(infos)} run(s) ({len(skipped)} skipped) in {seconds:.1f} s -> {out} "
                 "(every table, figure and results.json)")
    return lines
