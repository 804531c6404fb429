"""The context objective's ablation ladder on the validation objects (docs/experiments/context_objective.md).

    python experiments/context_ladder.py RUN [RUN ...]             # one row per run, then rung means
    python experiments/context_ladder.py --untrained RUN OUT       # OUT: RUN's network untrained, as a run folder
    python experiments/context_ladder.py --touches RUN [RUN ...]   # y from K = 1, 2 touches of each validation object
    python experiments/context_ladder.py --held-out test RUN ...   # the same on the test objects (the targets;
                                                                        # needs evaluate.py RUN held_out=test first)

Each RUN is a train.py folder of the population scene (any recipe). Per run:

* the read-out: last-frame and whole-trajectory NMSE (mean over factors) of the y latent on
  the validation objects, from ``RUN/evaluation-val/results.json``, written beforehand by
  ``python evaluate.py RUN held_out=val baselines=[mean] umap=false figures=false`` (the
  project's evaluation path: KRR alignment fitted on the training objects), and the NMSE over
  time at frames 30, 100 and 200 (mean over factors) from the same file; ``checkpoint=last``
  writes ``evaluation-last-val``, read with ``--checkpoint last``;
* on the validation objects' context / target pairs (the DataModule's ``context=trial``
  pairing, fixed by the run's split seed; 50-frame windows, the other trial of the same
  object as context), the same for every rung, A0 included:
  - KL_y: KL(q(y | context) || population marginal), per pair, summed over y's dimensions;
  - target prediction error: NMSE of the frames after the first 3 of the target window
    (squared error over the variance of the target frames about their per-pixel mean),
    predicted open-loop (:meth:`LatentFilter.rollout`, means, no sampling) from y = the
    posterior mean given the object's own context ("own"), or given the context of a
    different validation object ("swapped", A4).
The rung is the run's recipe and context settings; ``--untrained`` writes a run folder
holding the run's network at initialisation (same config, split and seed, training-set input
statistics) as ``checkpoints/last.ckpt``, to be evaluated with ``checkpoint=last`` (the floor;
it has no metrics.json, and its rung reads "floor (untrained)").
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import torch
from embodied_tactile.run.threadenv import set_threads

REPO = Path(__file__).resolve().parents[1]
INITIAL_FRAMES = 3
#: frames (0-based) at which the NMSE over time (mean over factors) is printed beside the two read-outs
CURVE_FRAMES = (29, 99, 199)


def rung(cfg, run_dir: Path) -> str:
    """The ladder's name for a run's objective ("floor" for a folder of --untrained)."""
    if not (run_dir / "metrics.json").exists():
        return "floor (untrained)"
    ctx = cfg.model.get("context")
    if not ctx:
        return "A0 filter"
    if ctx.source == "window":
        return "A1 window" + (" refilter" if ctx.refilter else "")
    if cfg.model.net.get("y_start", "fixed") == "population":
        return "A5 trial, population start" + (" refilter" if ctx.refilter else "")
    return "A3 trial refilter" if ctx.refilter else "A2 trial"


def readout(run_dir: Path, checkpoint: str, held_out: str = "val") -> dict:
    suffix = "-val" if held_out == "val" else ""
    name = f"evaluation{suffix}" if checkpoint == "best" else f"evaluation-{checkpoint}{suffix}"
    path = run_dir / name / "results.json"
    if not path.exists():
        return {}
    runs = json.loads(path.read_text())["runs"]
    lf = next(r for r in runs if r["method"] == "latent_filter")
    if (lf.get("params") or {}).get("held_out", "test") != held_out:
        raise SystemExit(f"{path}: not scored on the {held_out} objects")
    curve = np.asarray(json.loads(path.read_text())["curves_per_run"][lf["label"]], dtype=float)
    at = {f"f{t}": float(np.nanmean(curve[t])) for t in CURVE_FRAMES if t < len(curve)}
    return {"last": float(lf["nmse_last_step_overall"]), "traj": float(lf["nmse_trajectory_overall"]), **at}


def held_out_pairs(run, held_out: str = "val"):
    """The held-out objects' context / target pairs (the DataModule's ``context=trial``
    pairing: validation pairs as training sees them; test pairs built the same way, draws
    seeded by the split seed) -> their trials and batches."""
    from torch.utils.data import DataLoader

    from embodied_tactile.data.datamodule import TactileDataModule

    from embodied_tactile.eval.runs import data_config

    opts = OmegaConf.create({"data": {"batch_size": 64, "num_workers": 0}})
    data = data_config(run, opts)
    data["context"] = "trial"
    dm = TactileDataModule.from_config(data)
    dm.prepare_data()
    dm.setup("fit")
    if held_out == "val":
        return dm.val_pairs.trials, list(dm.val_dataloader())
    pairs = dm.held_out_pairs(dm.test_set.trials)
    return pairs.trials, list(DataLoader(pairs, batch_size=64, shuffle=False))


@torch.no_grad()
def prediction_scores(net, batches, objects: np.ndarray) -> dict:
    """KL_y and the target NMSE with own and swapped y over the validation pairs."""
    from embodied_tactile.model.networks import kl_diag_gaussians

    net.eval()
    ys, kls = [], []
    for b in batches:
        m, v = net.context_posterior(b["context_obs"], b["context_actions"])
        pm, pv = net.population_marginal(m.shape[0], m.device)
        kls.append(kl_diag_gaussians(m, v, pm, pv))
        ys.append(m)
    y = torch.cat(ys)
    n = len(y)
    # a different object's y for every pair: the next item at least half the set away
    swap = np.empty(n, dtype=int)
    for i in range(n):
        j = (i + n // 2) % n
        while objects[j] == objects[i]:
            j = (j + 1) % n
        swap[i] = j
    targets = torch.cat([b["obs"] for b in batches])[:, INITIAL_FRAMES:]
    centre = targets.mean(dim=(0, 1), keepdim=True)
    ref = float(((targets - centre) ** 2).sum())
    err = {"own": 0.0, "swapped": 0.0}
    start = 0
    for b in batches:
        k = len(b["obs"])
        for key, yy in (("own", y[start:start + k]), ("swapped", y[torch.as_tensor(swap[start:start + k])])):
            rec = net.rollout(b["obs"], b["actions"], yy, INITIAL_FRAMES, sample=False)["recon"]
            err[key] += float(((rec - b["obs"])[:, INITIAL_FRAMES:] ** 2).sum())
        start += k
    return {"kl_y": float(torch.cat(kls).mean()), "pred_own": err["own"] / ref, "pred_swapped": err["swapped"] / ref,
            "pairs": n}


def score(run_dir: Path, checkpoint: str, held_out: str = "val") -> dict:
    from embodied_tactile.eval.runs import load_module, load_run

    run = load_run(run_dir, checkpoint)
    trials, batches = held_out_pairs(run, held_out)
    objects = np.asarray([t.object_id for t in trials])  # evaluation only: which pairs to swap
    module = load_module(run)
    out = {"run": run_dir.name, "rung": rung(run.cfg, run_dir), "seed": int(run.cfg.seed), "checkpoint": run.ckpt.name,
           **readout(run_dir, checkpoint, held_out), **prediction_scores(module.model, batches, objects)}
    return out


def write_untrained(run_dir: Path, out: Path) -> Path:
    """``out``: a run folder with ``run_dir``'s config and split and its network at
    initialisation (seeded as train.py seeds it) in ``checkpoints/last.ckpt``."""
    import lightning as L
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    import embodied_tactile.run.config  # noqa: F401  the typed configs and resolver
    from embodied_tactile.data.datamodule import TactileDataModule
    from embodied_tactile.eval.runs import data_config, load_run

    run = load_run(run_dir, "last")
    out.mkdir(parents=True, exist_ok=True)
    for name in ("config_resolved.yaml", "split.json", "provenance.json"):
        shutil.copy(run_dir / name, out / name)
    L.seed_everything(int(run.cfg.seed), workers=True)
    module = instantiate(run.cfg.model)
    if module.model.input_standardize:
        opts = OmegaConf.create({"data": {"batch_size": None, "num_workers": 0}})
        dm = TactileDataModule.from_config(data_config(run, opts))
        dm.prepare_data()
        dm.setup("fit")
        module.use_data_statistics(dm.statistics)
    (out / "checkpoints").mkdir(exist_ok=True)
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                "pytorch-lightning_version": L.__version__}, out / "checkpoints" / "last.ckpt")
    return out


def _posteriors(net, batches, names) -> dict:
    """Filtered y over whole trials (``infer_latents``): y (n, T, d) means, the last frame's
    mean and var (n, d), factors, object ids, action indices and trial names."""
    ys, m, v, fac, obj, act = [], [], [], [], [], []
    with torch.no_grad():
        for b in batches:
            out = net.infer_latents(b)
            ys.append(out["y_mean"].numpy())
            m.append(out["y_mean"][:, -1])
            v.append(out["y_var"][:, -1])
            fac.append(b["factors"].numpy())
            obj.append(b["object_id"].numpy())
            act.append(b["action_index"].numpy())
    return {"y": np.concatenate(ys), "y_last": torch.cat(m), "y_var_last": torch.cat(v), "factors": np.concatenate(fac),
            "object_id": np.concatenate(obj), "action_index": np.concatenate(act), "seq_id": np.asarray(names)}


def _combined(split: dict, prior) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per object: ``combine_touches`` over its trials' last-frame posteriors -> means
    (n_objects, d), factors (n_objects, 4) and object ids."""
    from embodied_tactile.model.latent_filter import combine_touches

    objects = np.asarray(split["object_id"])
    means, facs, ids = [], [], []
    for o in sorted(set(objects.tolist())):
        idx = torch.as_tensor(np.flatnonzero(objects == o))
        cm, _ = combine_touches(split["y_last"][idx][:, None], split["y_var_last"][idx][:, None], *prior)
        means.append(cm[0].numpy())
        facs.append(split["factors"][int(idx[0])])
        ids.append(o)
    return np.stack(means), np.stack(facs), np.asarray(ids)


def split_posteriors(run_dir: Path, checkpoint: str, held_out: str = "val", untrained: bool = False):
    """A run's network and :func:`_posteriors` of its training trials and of its validation
    (or test) trials, factors encoded as the run's targets -> (run, net, train, held-out).
    ``untrained``: the same network at its initialisation (``untrained_module``), the floor."""
    from embodied_tactile.data.datamodule import TactileDataModule
    from embodied_tactile.eval.pipeline import parse_options
    from embodied_tactile.eval.runs import data_config, load_module, load_run, trial_names, untrained_module
    from embodied_tactile.eval.targets import encode_split

    run = load_run(run_dir, checkpoint)
    dm = TactileDataModule.from_config(data_config(run, parse_options([])))
    dm.prepare_data()
    dm.setup("fit")
    module = load_module(run)
    net = (untrained_module(run, module) if untrained else module).model
    targets = str(run.cfg.get("targets") or "design_rank")
    tr = encode_split(_posteriors(net, dm.train_eval_dataloader(), trial_names(dm, "train")), targets)
    loader = dm.val_eval_dataloader() if held_out == "val" else dm.test_dataloader()
    te = encode_split(_posteriors(net, loader, trial_names(dm, held_out)), targets)
    return run, net, tr, te


def touches(run_dir: Path, checkpoint: str, prior: str = "start", held_out: str = "val") -> dict:
    """The K-touch read-out on the validation (or test) objects (every one has 2 trials, the population
    scene's 2 actions), last-frame NMSE (mean over factors, normalised by the variance of the
    validation targets):

    * ``evaluate K=1``: evaluate.py's alignment (its default options: fitted on the final
      tenth of the training trials' filtered y) applied to each validation trial's last frame;
      the last-frame NMSE of ``evaluate.py held_out=val``;
    * ``evaluate K=2``: the same alignment applied to each validation object's two trials'
      last-frame posteriors combined by ``combine_touches`` (the prior counted once:
      ``prior`` "start", ``LatentFilter.touch_prior``, or "marginal", the population marginal);
    * ``same-K K=1`` / ``same-K K=2``: an alignment (evaluate.py's options, CV folds by object)
      fitted on the training objects' y at the same K (one latent per trial, the last frame's;
      one per object, its trials combined) and applied to the validation objects' y at that K.
    """
    from embodied_tactile.eval.krr import alignment_kwargs, fit_alignment
    from embodied_tactile.options.alignment import alignment_options
    from embodied_tactile.eval.metrics import nmse, overall, reference_variance
    from embodied_tactile.eval.results import evaluate_latents

    run, net, tr, te = split_posteriors(run_dir, checkpoint, held_out)
    align_opts = alignment_options({"readout": "final_segment"})  # one alignment of the final tenth, read at the last frame
    _, align = evaluate_latents(tr, te, latent="y", alignment=align_opts, split="object")
    if prior == "marginal":
        with torch.no_grad():
            pm, pv = net.population_marginal(1, torch.device("cpu"))
        touch_prior = (pm[0], pv[0])
    else:
        touch_prior = net.touch_prior()
    var_ref = reference_variance(te["factors"])
    score = lambda f, p: overall(nmse(f, p, var_ref=var_ref))  # noqa: E731
    val2, val2_f, _ = _combined(te, touch_prior)
    out = {"evaluate K=1": score(te["factors"], align.predict(te["y_last"].numpy())[:, 0]),
           "evaluate K=2": score(val2_f, align.predict(val2)[:, 0])}
    kw = alignment_kwargs(align_opts, "object", tr["object_id"])
    kw.pop("final_segment", None), kw.pop("frames_per_sequence", None)
    one = fit_alignment(tr["y_last"].numpy(), tr["factors"], **kw)
    out["same-K K=1"] = score(te["factors"], one.predict(te["y_last"].numpy())[:, 0])
    tr2, tr2_f, tr2_o = _combined(tr, touch_prior)
    two = fit_alignment(tr2, tr2_f, **{**kw, "groups": tr2_o if kw.get("groups") is not None else None})
    out["same-K K=2"] = score(val2_f, two.predict(val2)[:, 0])
    return {"run": run_dir.name, "rung": rung(run.cfg, run_dir), "seed": int(run.cfg.seed), **out}


def table(rows: list[dict]) -> str:
    def f(v):
        return "–" if v is None else f"{v:.3f}"

    frames = " | ".join(f"NMSE frame {t + 1}" for t in CURVE_FRAMES)
    lines = [f"| run | rung | seed | NMSE last frame | NMSE whole trajectory | {frames} | KL_y | target NMSE own y | "
             "target NMSE swapped y |", "|---" * (8 + len(CURVE_FRAMES)) + "|"]
    for r in rows:
        at = " | ".join(f(r.get(f"f{t}")) for t in CURVE_FRAMES)
        lines.append(f"| {r['run']} | {r['rung']} | {r['seed']} | {f(r.get('last'))} | {f(r.get('traj'))} | {at} | "
                     f"{r['kl_y']:.2f} | {r['pred_own']:.4f} | {r['pred_swapped']:.4f} |")
    lines += ["", "| rung | seeds | NMSE last frame | NMSE whole trajectory | KL_y | target NMSE own y | "
                  "target NMSE swapped y |", "|---|---|---|---|---|---|---|"]
    for name in sorted({r["rung"] for r in rows}):
        rs = [r for r in rows if r["rung"] == name]
        mean = {k: (float(np.mean([r[k] for r in rs])) if all(r.get(k) is not None for r in rs) else None)
                for k in ("last", "traj", "kl_y", "pred_own", "pred_swapped")}
        lines.append(f"| {name} | {', '.join(str(r['seed']) for r in rs)} | {f(mean['last'])} | {f(mean['traj'])} | "
                     f"{mean['kl_y']:.2f} | {mean['pred_own']:.4f} | {mean['pred_swapped']:.4f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="*", type=Path)
    ap.add_argument("--checkpoint", default="best", choices=("best", "last"))
    ap.add_argument("--held-out", default="val", choices=("val", "test"),
                    help="the objects read: validation (screening) or test (the targets; read once a rung is chosen)")
    ap.add_argument("--untrained", nargs=2, type=Path, metavar=("RUN", "OUT"))
    ap.add_argument("--json", type=Path, help="also write the rows here")
    ap.add_argument("--touches", action="store_true", help="the K-touch read-out (K = 1, 2) instead of the ladder")
    ap.add_argument("--touch-prior", default="start", choices=("start", "marginal"),
                    help="the prior combine_touches counts once: the touches' own start (touch_prior) or the population marginal")
    args = ap.parse_args(argv)
    set_threads(1)
    if args.untrained:
        print(write_untrained(*args.untrained))
        return 0
    if args.touches:
        rows = [touches(r, args.checkpoint, args.touch_prior, args.held_out) for r in args.runs]
        keys = ("evaluate K=1", "evaluate K=2", "same-K K=1", "same-K K=2")
        print("| run | rung | seed | " + " | ".join(keys) + " |\n" + "|---" * (3 + len(keys)) + "|")
        for r in rows:
            print(f"| {r['run']} | {r['rung']} | {r['seed']} | " + " | ".join(f"{r[k]:.3f}" for k in keys) + " |")
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1))
        return 0
    rows = [score(r, args.checkpoint, args.held_out) for r in args.runs]
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
