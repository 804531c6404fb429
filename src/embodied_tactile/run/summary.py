"""What a finished run says last, and where the latest run is.

* :func:`run_summary_lines` -- the end of ``python train.py``: held-out NMSE per factor and
  overall from the run's last KRR alignment (``krr_history.jsonl``), the training time, where
  the checkpoint, metrics and figures are, and the exact ``python evaluate.py <run>`` command;
  then (:func:`protocol_lines`) what the number means: beside the untrained network and the
  mean predictor, what the split measures, and where objects never touched are measured.
* :func:`multirun_summary_lines` -- the end of ``python train.py -m ...`` (printed by the
  Hydra callback :class:`embodied_tactile.cli.EntryCallback`): one line per job, the
  multirun folder and its evaluate command.
* :func:`latest_run` -- the most recent run or multirun under ``<log_dir>/train`` (what
  ``python evaluate.py`` with no argument evaluates).
"""

from __future__ import annotations

import json
import os
import shlex
from pathlib import Path
from typing import Any, Mapping, Sequence

from ..constants import FACTOR_NAMES
from embodied_tactile.jsonio import read_json
from ..model.compat import UNSAVED_OPTIONS, UNSAVED_PRIOR_OPTIONS
from ..model.options import LatentFilterOptions, PriorOptions

FACTOR_SHORT = {"spatial_frequency": "spatial freq.", "amplitude": "amplitude", "stiffness": "stiffness",
                "heterogeneity": "heterogeneity"}
HISTORY = "krr_history.jsonl"
RULE = "-" * 72


def recipe(cfg) -> str:
    """The settings that tell the learning curve's Latent Filter recipes apart, as the run
    used them: the prior's object labels, the KL schedule's y weight, the y update and the
    observation dropout (the last three where the run's config has them); with the context
    objective its context source and the settings that tell its rungs apart; a learning-rate
    schedule other than constant."""
    from omegaconf import OmegaConf

    labels = bool(OmegaConf.select(cfg, "model.net.prior.labels", default=UNSAVED_PRIOR_OPTIONS["labels"]))
    parts = ["labels" if labels else "no labels"]
    if labels and OmegaConf.select(cfg, "model.net.prior.learn_embedding", default=PriorOptions.learn_embedding):
        parts.append("learned codes")
    y_weight = OmegaConf.select(cfg, "annealing.schedule.y_weight", default=None)
    if y_weight is not None:
        parts.append(f"y_weight {float(y_weight):g}")
    y_update = OmegaConf.select(cfg, "model.net.y_update", default=None)
    if y_update is not None:
        parts.append(f"y {y_update}")
    # a config silent on it predates the option: those networks were trained without dropout (compat)
    dropout = float(OmegaConf.select(cfg, "model.net.obs_dropout", default=UNSAVED_OPTIONS["obs_dropout"]) or 0.0)
    if dropout > 0:
        parts.append(f"dropout {dropout:g}")
    if OmegaConf.select(cfg, "model.net.y_start", default=LatentFilterOptions.y_start) == "population":
        parts.append("y from the population")
    schedule = OmegaConf.select(cfg, "model.lr_schedule", default="constant")
    if schedule != "constant":
        parts.append(f"{schedule} schedule")
    context = OmegaConf.select(cfg, "model.context", default=None)
    if context:
        touches = int(context.get("touches", 1) or 1)
        parts.insert(0, f"context objective ({context.get('source', 'trial')}"
                     + (f", {touches} touches" if touches > 1 else "")
                     + (", refilter" if context.get("refilter") else "")
                     + "".join(f", {k} {float(context.get(k) or 0):g}" for k in ("invariance", "physical")
                               if float(context.get(k) or 0) > 0) + ")")
    unlabelled = int(OmegaConf.select(cfg, "data.n_unlabelled_objects", default=0) or 0)
    if unlabelled:
        parts.append(f"{unlabelled} unlabelled objects")
    return ", ".join(parts)


def krr_history(run_dir: str | os.PathLike) -> list[dict]:
    try:
        lines = (Path(run_dir) / HISTORY).read_text().splitlines()
    except OSError:
        return []
    rows = []
    for ln in lines:
        try:
            rows.append(json.loads(ln))
        except ValueError:  # a line cut by a kill
            continue
    return rows


def last_alignment(run_dir: str | os.PathLike) -> dict | None:
    """The last row of ``<run>/krr_history.jsonl`` (None when the run has none)."""
    rows = krr_history(run_dir)
    return rows[-1] if rows else None


#: how many of the last periodic checks :func:`check_spread` compares
FLAT_CHECKS = 3


def check_spread(rows: Sequence[Mapping], n: int = FLAT_CHECKS) -> tuple[list[Mapping], float] | None:
    """How flat a run's curve ends: its last ``n`` periodic checks (neither the step-0 row nor
    the final alignment; the last check reads the final weights) and their spread, (max - min)
    / min of their whole-trajectory NMSE. None with fewer than ``n`` checks or a value
    missing."""
    checks = [r for r in rows if not r.get("final") and not r.get("initial")][-n:]
    values = [r.get("nmse_overall") for r in checks]
    if len(checks) < n or any(v is None for v in values) or min(values) <= 0:
        return None
    return checks, (max(values) - min(values)) / min(values)


def show_path(p: str | os.PathLike, cwd: str | os.PathLike | None = None) -> str:
    """Relative to ``cwd`` when inside it (what the user types), else absolute."""
    p = Path(p).absolute()
    cwd = Path(cwd or os.getcwd()).absolute()
    try:
        return str(p.relative_to(cwd))
    except ValueError:
        return str(p)


def evaluate_command(target: str | os.PathLike, cwd: str | os.PathLike | None = None) -> str:
    return f"python evaluate.py {shlex.quote(show_path(target, cwd))}"


def duration(seconds: float | None) -> str:
    if seconds is None:
        return "unknown"
    s = float(seconds)
    if s < 60:
        return f"{s:.1f} s"
    m, s = divmod(int(round(s)), 60)
    if m < 60:
        return f"{m} min {s:02d} s"
    h, m = divmod(m, 60)
    return f"{h} h {m:02d} min"


def _fmt(v: Any) -> str:
    return "n/a" if v is None else f"{float(v):.4g}"


def nmse_lines(row: Mapping | None) -> list[str]:
    if not row:
        return ["held-out NMSE: no KRR alignment in this run (callbacks.krr_alignment off); "
                "evaluate.py computes it"]
    per = row.get("nmse") or {}
    parts = "  ".join(f"{FACTOR_SHORT.get(f, f)} {_fmt(per.get(f))}" for f in (per or FACTOR_NAMES))
    where = [f"step {row['step']}"] if "step" in row else []
    if row.get("train_wall_time_s") is not None:
        where.append(f"{duration(row['train_wall_time_s'])} into training")
    if row.get("n_test") is not None:
        where.append(f"{row['n_test']} held-out sequences")
    lines = [f"held-out NMSE (last KRR alignment: {', '.join(where) or 'krr_history.jsonl'}): "
             f"overall {_fmt(row.get('nmse_overall'))}",
             f"  per factor: {parts}"]
    boot = row.get("bootstrap_objects")
    if boot and None not in (boot.get("overall_ci95") or [None]):
        (lo, hi), (llo, lhi) = boot["overall_ci95"], boot.get("last_overall_ci95") or (None, None)
        lines.append(f"  95 % interval over resampled test objects (the test sample's own noise; another seed adds "
                     f"its own): whole [{_fmt(lo)}, {_fmt(hi)}], last frame {_fmt(row.get('nmse_last_overall'))} "
                     f"[{_fmt(llo)}, {_fmt(lhi)}]")
    return lines


#: what each split's held-out NMSE measures (the last lines of ``python train.py``)
SPLIT_MEANING = {
    "trial": ("held-out trials of the training objects (data.split=trial, the paper's protocol)",
              "This protocol measures recognition: every held-out trial is another touch of an object met "
              "in training."),
    "object": ("trials of objects never touched in training (data.split=object)",
               "This split measures generalisation to objects never touched in training."),
}
#: scenes read by a reader of their own, not by evaluate.py: modality name -> (what the held-out
#: sequences are, what they measure, the command that reads the run (``{run}``: its folder))
OWN_READERS = {
    "pendulum": ("held-out sequences of the 8 training systems",
                 "This measures recognition of the training systems; systems never seen, the z read-outs and "
                 "open-loop prediction: experiments/pendulum_probes.py, experiments/pendulum.py.",
                 "python experiments/pendulum_probes.py --load {run} --no-frames"),
}
POPULATION_COMMAND = "python train.py experiment=population"
POPULATION_PAGE = "docs/experiments/label_free_objectives.md"
#: the latest measurement of the population default: the label-free objectives' screen
#: (experiments/population_objectives.py analyse --json), each row marked whether its run is
#: the population default as configured
POPULATION_SCORES = Path(__file__).resolve().parents[3] / "docs" / "experiments" / "label_free_objectives.json"


def population_scores(path: str | os.PathLike | None = None) -> dict[str, tuple[float, float, int]]:
    """Per reader (``latent_filter``, ``untrained``, ...): (whole trajectory, last frame, seeds),
    the mean over seeds of the population default's runs on the test objects (empty when the
    file holds none)."""
    try:
        rows = json.loads(Path(path or POPULATION_SCORES).read_text())
    except (OSError, ValueError):
        return {}
    out: dict[str, tuple[float, float, int]] = {}
    for reader in dict.fromkeys(r["reader"] for r in rows):
        sel = [r for r in rows if r["reader"] == reader and r.get("population_default") and r["side"] == "test"]
        if sel:
            out[reader] = (sum(r["whole"] for r in sel) / len(sel), sum(r["last"] for r in sel) / len(sel), len(sel))
    return out


def run_config(run_dir: str | os.PathLike):
    """The run's ``config_resolved.yaml`` (an empty config when it cannot be read)."""
    from omegaconf import OmegaConf

    try:
        return OmegaConf.load(Path(run_dir) / "config_resolved.yaml")
    except OSError:
        return OmegaConf.create({})


def untrained_floor(initial: Mapping) -> Mapping:
    """The untrained network's read-out in a run's step-0 row: its ``floor`` (the final
    alignment's read-out), or for a run before it the step-0 check itself."""
    return initial.get("floor", initial)


def protocol_lines(run_dir: str | os.PathLike, cfg=None, rows: Sequence[Mapping] | None = None) -> list[str]:
    """What the run's held-out number means: the final alignment beside the same read-out of
    the untrained network (the step-0 row's ``floor``) and the mean predictor, whole
    trajectory and last frame; what the split measures (the run's ``config_resolved.yaml``); and the command,
    number and page for objects never touched. ``cfg`` / ``rows``: the run's config
    (:func:`run_config`) and history (:func:`krr_history`) when the caller has read them."""
    from omegaconf import OmegaConf

    rows = krr_history(run_dir) if rows is None else rows
    final = next((r for r in reversed(rows) if r.get("final")), None)
    if final is None:
        return []
    cfg = run_config(run_dir) if cfg is None else cfg
    split = str(OmegaConf.select(cfg, "data.split", default="trial"))
    where, meaning = SPLIT_MEANING.get(split, (f"data.split={split}", ""))
    modality = OmegaConf.select(cfg, "modality.name", default="?")
    own = OWN_READERS.get(modality)
    if own is not None:
        where, meaning = own[:2]

    label = f"Latent Filter {modality} ({recipe(cfg)})"
    initial = next((r for r in rows if r.get("initial")), None)
    table = [("this run", final.get("nmse_overall"), final.get("nmse_last_overall"))]
    if initial:
        floor = untrained_floor(initial)
        table.append(("the same, untrained (step 0)", floor.get("nmse_overall"), floor.get("nmse_last_overall")))
    if final.get("nmse_mean_predictor_overall") is not None:
        m = final["nmse_mean_predictor_overall"]
        table.append(("mean predictor", m, m))
    lines = [f"{label} on {final.get('n_test', '?')} {where}:",
             f"  {'NMSE, mean over factors':30}  {'whole trajectory':>16}  {'last frame':>10}"]
    lines += [f"  {name:30}  {_fmt(w):>16}  {_fmt(l):>10}" for name, w, l in table]
    if meaning:
        lines.append(meaning)
    if own is not None:  # a scene of its own: the tactile population says nothing about it
        return lines
    pop = population_scores()
    if "latent_filter" in pop:
        w, last, n = pop["latent_filter"]
        measured = f"the population default: whole trajectory {w:.3f}, last frame {last:.3f} ({n} seed(s), 64 test objects"
        if "untrained" in pop:
            measured += f"; untrained {pop['untrained'][0]:.3f} / {pop['untrained'][1]:.3f}"
        measured += ")"
    else:
        measured = "the population default: not yet measured"
    lines.append(f"Objects never touched: {POPULATION_COMMAND}; measured: {measured}; {POPULATION_PAGE}")
    return lines


def where_computed(run: Path, metrics: Mapping) -> str:
    """", on <CPU model>, <n> torch thread(s)" (provenance.json; the threads of every KRR check
    in krr_history.jsonl and of the final read-out, in the order they held: ``threads=auto``
    re-counts them each epoch, so "2 then 1 torch threads (1 from step 840)"): what a number's
    last digits depend on; "" where the run folder does not say."""
    try:
        model = (read_json(run / "provenance.json").get("cpu") or {}).get("model")
    except (OSError, ValueError):
        model = None
    seen = [(r.get("step"), r["torch_threads"]) for r in krr_history(run) if r.get("torch_threads")]
    final = (metrics.get("krr_final") or {}).get("torch_threads")
    if final and (not seen or seen[-1][1] != final):
        seen.append((None, final))
    runs = [seen[0]] if seen else []  # (first step, threads) of each stretch of one thread count
    for step, n in seen[1:]:
        if n != runs[-1][1]:
            runs.append((step, n))
    parts = [model] if model else []
    if len(runs) == 1:
        n = runs[0][1]
        parts.append(f"{n} torch thread{'' if n == 1 else 's'}")
    elif runs:
        steps = ", ".join(f"{n} from step {step}" if step is not None else f"{n} in the final read-out"
                          for step, n in runs[1:])
        parts.append(f"{' then '.join(str(n) for _, n in runs)} torch threads ({steps})")
    return f", on {', '.join(parts)}" if parts else ""


def run_summary_lines(run_dir: str | os.PathLike, metrics: Mapping | None = None, *,
                      cwd: str | os.PathLike | None = None) -> list[str]:
    """The closing block of one run (``metrics``: the dict train.py writes to metrics.json;
    read from ``<run>/metrics.json`` when None)."""
    run = Path(run_dir)
    m = dict(metrics) if metrics is not None else read_json(run / "metrics.json")
    status = m.get("status", "unknown")
    lines = [RULE, f"run {status}: {show_path(run, cwd)}"]
    if status == "failed" and m.get("error"):
        lines.append(f"error: {m['error']}")
    from omegaconf import OmegaConf

    cfg = run_config(run)
    rows = krr_history(run)
    lines += nmse_lines(rows[-1] if rows else None)
    spread = check_spread(rows)
    if spread is not None:
        checks, frac = spread
        decay = OmegaConf.select(cfg, "model.weight_average", default=None)
        weights = "" if decay is None else f", of the weights' moving average (decay {decay:g})"
        lines.append(f"checks:        the last {len(checks)} (steps {', '.join(str(r.get('step')) for r in checks)}): "
                     f"{', '.join(_fmt(r['nmse_overall']) for r in checks)}, spread {100 * frac:.0f} % "
                     f"(the checks' cheaper read-out{weights})")
    t = f"training time: {duration(m.get('train_wall_s'))}"
    if m.get("data_prepare_s") is not None:
        t += f" (data preparation {duration(m.get('data_prepare_s'))} on top)"
    lines.append(t + where_computed(run, m))
    # the final weights: the read-out above and evaluate.py's default (checkpoint=last)
    ckpt, best = m.get("last_checkpoint") or m.get("best_checkpoint"), m.get("best_checkpoint")
    ck_dir = run / "checkpoints"
    if ckpt:  # relative to the run folder (metrics.json of before: absolute)
        also = f" (lowest validation loss: {Path(best).name})" if best and best != ckpt else ""
        lines.append(f"checkpoint:    {show_path(run / ckpt, cwd)}{also}")
    elif ck_dir.is_dir() and any(ck_dir.glob("*.ckpt")):
        lines.append(f"checkpoints:   {show_path(ck_dir, cwd)}/")
    else:
        lines.append("checkpoint:    none written")
    have = [n for n in ("metrics.json", HISTORY, "csv/metrics.csv") if (run / n).exists()]
    lines.append(f"metrics:       {show_path(run, cwd)}/{{{','.join(have)}}}" if len(have) > 1 else
                 f"metrics:       {show_path(run / have[0], cwd) if have else 'none written'}")
    own = OWN_READERS.get(OmegaConf.select(cfg, "modality.name", default=None))
    if own is None:
        lines.append(f"figures:       {show_path(run / 'evaluation', cwd)}/ (tables, figures/), written by:")
        lines.append(f"next:          {evaluate_command(run, cwd)}")
    else:
        lines.append(f"next:          {own[2].format(run=show_path(run, cwd))}")
    lines.append(RULE)
    protocol = protocol_lines(run, cfg, rows)
    if protocol:
        lines += protocol + [RULE]
    return lines


def print_run_summary(run_dir, metrics: Mapping | None = None) -> None:
    print("\n".join(run_summary_lines(run_dir, metrics)), flush=True)


#: a multirun job's outcome (status, reason), written by train.py beside Hydra's record of the job
OUTCOME = ".hydra/outcome.json"


def record_outcome(job_dir: str | os.PathLike, status: str, reason: str = "") -> None:
    """Write a multirun job's outcome to ``<job>/.hydra/outcome.json`` (nothing when Hydra
    keeps no ``.hydra/`` there): what the sweep's table says of it."""
    from embodied_tactile.jsonio import write_json

    d = Path(job_dir) / Path(OUTCOME).parent
    if d.is_dir():
        write_json(d / Path(OUTCOME).name, {"status": status, "reason": reason})


def _jobs(sweep_dir: Path) -> list[Path]:
    """The sweep's job folders: those Hydra started (``.hydra/overrides.yaml``) or that hold a run."""
    return sorted((d for d in sweep_dir.iterdir() if d.is_dir() and ((d / "config_resolved.yaml").exists()
                                                                   or (d / ".hydra" / "overrides.yaml").exists())),
                  key=lambda d: d.name)


def _overrides(job: Path) -> list[str]:
    try:
        from omegaconf import OmegaConf

        return [str(o) for o in OmegaConf.load(job / ".hydra" / "overrides.yaml")]
    except Exception:  # noqa: BLE001 -- no or damaged overrides.yaml: the folder name says them
        return [job.name]


def multirun_rows(sweep_dir: str | os.PathLike) -> list[dict]:
    """One dict per job of a sweep: ``job`` (folder), ``overrides`` (those that differ
    between the jobs; all of them for a single job), ``status`` and ``reason`` (the job's
    outcome, else its metrics.json), ``nmse`` (last KRR) and ``train_s``."""
    sweep = Path(sweep_dir)
    jobs = _jobs(sweep) if sweep.is_dir() else []
    overrides = {d: _overrides(d) for d in jobs}
    common = set.intersection(*(set(o) for o in overrides.values())) if len(jobs) > 1 else set()
    rows = []
    for d in jobs:
        m, outcome = read_json(d / "metrics.json"), read_json(d / OUTCOME)
        status = outcome.get("status") or m.get("status", "unknown")
        reason = outcome.get("reason") if outcome else (m.get("error") or "")
        rows.append({"job": d.name, "overrides": [o for o in overrides[d] if o not in common], "status": status,
                     "reason": "" if status == "finished" else (reason or "no reason recorded"),
                     "nmse": (last_alignment(d) or {}).get("nmse_overall"), "train_s": m.get("train_wall_s")})
    return rows


def multirun_summary_lines(sweep_dir: str | os.PathLike, *, cwd: str | os.PathLike | None = None) -> list[str]:
    """One line per job (status, last KRR NMSE overall, training time, the overrides that tell
    it apart and, when it did not finish, why), the folder and the evaluate command."""
    sweep = Path(sweep_dir)
    rows = multirun_rows(sweep)
    n_ok = sum(r["status"] == "finished" for r in rows)
    lines = [RULE, f"multirun: {len(rows)} job(s), {n_ok} finished, {len(rows) - n_ok} not: {show_path(sweep, cwd)}"]
    if rows:
        w = max(len(r["job"]) for r in rows)
        table = [(r["job"], r["status"], _fmt(r["nmse"]), duration(r["train_s"]), " ".join(r["overrides"]), r["reason"])
                 for r in rows]
        wt, wo = max(len(t[3]) for t in table), max([len("overrides")] + [len(t[4]) for t in table])
        lines.append(f"  {'job'.ljust(w)}  {'status':11}  {'NMSE (last KRR)':>15}  {'training time'.ljust(wt)}  "
                     f"{'overrides'.ljust(wo)}  reason")
        lines += [f"  {a.ljust(w)}  {b:11}  {c:>15}  {t.ljust(wt)}  {o.ljust(wo)}  {why}".rstrip()
                  for a, b, c, t, o, why in table]
    lines.append(f"tables and figures: {show_path(sweep / 'evaluation', cwd)}/, written by:")
    lines.append(f"next: {evaluate_command(sweep, cwd)}")
    lines.append(RULE)
    return lines


def print_multirun_summary(sweep_dir) -> None:
    print("\n".join(multirun_summary_lines(sweep_dir)), flush=True)


# ----------------------------------------------------------------------------- latest run
def _started(run_dir: Path) -> float | None:
    """When a run started: mtime of its provenance.json / config_resolved.yaml (written once
    at the start; the folder's own mtime moves when an evaluation is added)."""
    for name in ("provenance.json", "config_resolved.yaml"):
        p = run_dir / name
        if p.exists():
            return p.stat().st_mtime
    return None


def _has_checkpoint(run_dir: Path) -> bool:
    ck = run_dir / "checkpoints"
    return ck.is_dir() and any(ck.glob("*.ckpt"))


def candidates(train_dir: str | os.PathLike) -> list[tuple[float, Path, str, bool]]:
    """(start time, folder, 'run' | 'multirun', evaluable) under ``<train_dir>/runs`` and
    ``<train_dir>/multiruns``, newest first."""
    root = Path(train_dir)
    out = []
    for d in sorted((root / "runs").glob("*")) if (root / "runs").is_dir() else []:
        t = _started(d) if d.is_dir() else None
        if t is not None:
            out.append((t, d, "run", _has_checkpoint(d)))
    for d in sorted((root / "multiruns").glob("*")) if (root / "multiruns").is_dir() else []:
        jobs = _jobs(d) if d.is_dir() else []
        times = [t for t in (_started(j) for j in jobs) if t is not None]
        if times:
            out.append((max(times), d, "multirun", any(_has_checkpoint(j) for j in jobs)))
    out.sort(key=lambda c: c[0], reverse=True)
    return out


def latest_run(train_dir: str | os.PathLike) -> tuple[Path, str, list[Path]]:
    """-> (folder, 'run' | 'multirun', newer folders passed over because they hold no
    checkpoint). FileNotFoundError (naming the folders looked in) when there is none."""
    cands = candidates(train_dir)
    passed: list[Path] = []
    for _, d, kind, ok in cands:
        if ok:
            return d, kind, passed
        passed.append(d)
    root = Path(train_dir)
    why = (f"{len(cands)} folder(s) there, none with a checkpoint (failed or killed before the first epoch)"
           if cands else "nothing there")
    raise FileNotFoundError(f"no trained run under {root}/runs or {root}/multiruns ({why}); "
                            "train one with `python train.py`, or give a run folder: python evaluate.py <run>")


def picked_message(folder: Path, kind: str, passed: Sequence[Path], train_dir) -> str:
    msg = f"evaluate.py: no path given; evaluating the most recent {kind} under {show_path(train_dir)}: {show_path(folder)}"
    if passed:
        msg += f" (passed over {len(passed)} newer folder(s) without a checkpoint: " + ", ".join(
            show_path(p) for p in passed[:3]) + ("..." if len(passed) > 3 else "") + ")"
    return msg
