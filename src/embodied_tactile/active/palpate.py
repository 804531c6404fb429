"""Closed-loop active palpation with a trained Latent Filter (docs/reference/active.md).

    embodied-tactile palpate run=logs/train/runs/<run> object=7 budget=4
    embodied-tactile palpate run=<run> object=7 budget=6 policy=random seed=1
    embodied-tactile palpate run=<run> mode=evaluate budget=8 'evaluate.seeds=[0,1,2]'

``mode=episode`` runs one episode on one object: after every touch it prints the factor
estimates with their uncertainty (KRR of the posterior mean +- the Monte-Carlo std through
the KRR) and redraws ``<out>/episode_obj<id>_<policy>_s<seed>.png``. ``mode=evaluate`` runs
every policy on the objects of the run's test split for every seed and writes NMSE against
the number of touches as md / csv / tex / json tables and a PNG figure to ``<out>``.

Exit codes: 0 done; 2 a bad setting or a run that cannot be used (one line on stderr).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from embodied_tactile import constants as C
from embodied_tactile.cli import hydra_command
from embodied_tactile.run.threadenv import set_threads

log = logging.getLogger("embodied_tactile.active.palpate")


class SettingError(ValueError):
    """A bad palpate setting."""


def _source(cfg: DictConfig, model, seed: int):
    from embodied_tactile.active.source import RecordedTouchSource, SimulatedTouchSource

    if cfg.source == "simulated":
        return SimulatedTouchSource(model.skin, model.primitive, seed)
    if cfg.source == "recorded":
        if not cfg.raw_files:
            raise SettingError("source=recorded needs raw_files=[...] (the recorder's HDF5 files)")
        return RecordedTouchSource(list(cfg.raw_files), model.skin, model.primitive)
    raise SettingError(f"source must be 'simulated' or 'recorded', got {cfg.source!r}")


def _check(cfg: DictConfig) -> None:
    if cfg.run is None or str(cfg.run) == "":
        raise SettingError("run=<folder of a trained run> is required (e.g. run=logs/train/runs/<date>)")
    if not Path(str(cfg.run)).exists():
        raise SettingError(f"no such run folder: {cfg.run}")
    if cfg.mode not in ("episode", "evaluate"):
        raise SettingError(f"mode must be 'episode' or 'evaluate', got {cfg.mode!r}")
    if not (isinstance(cfg.budget, int) and cfg.budget >= 1):
        raise SettingError(f"budget must be an integer >= 1 touch, got {cfg.budget!r}")
    if not (isinstance(cfg.object, int) and 0 <= cfg.object < C.N_OBJECTS):
        raise SettingError(f"object must be a catalogue id 0..{C.N_OBJECTS - 1}, got {cfg.object!r}")
    if cfg.policy not in ("active", "random", "fixed", "single"):
        raise SettingError(f"policy must be active, random, fixed or single, got {cfg.policy!r}")


def _fixed_order(cfg: DictConfig, model, info: dict, cache) -> list[int]:
    from embodied_tactile.active.evaluation import fit_fixed_order

    if cfg.fixed_order:
        return [int(a) for a in cfg.fixed_order]
    n = int(cfg.calibration_touches or len(model.actions))
    t0 = time.perf_counter()
    order, table = fit_fixed_order(model, info["train_objects"], n, cache=cache)
    print(f"fixed order fitted on calibration episodes of {len(info['train_objects'])} training objects: "
          f"{order} (candidate NMSE per step {np.round(table, 3).tolist()}, {time.perf_counter() - t0:.0f} s)",
          flush=True)
    return order


def plot_episode(path: Path, model, object_id: int, actions, est, std, truth, policy: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from embodied_tactile.eval.targets import target_units

    k = np.arange(1, len(actions) + 1)
    units = target_units(model.targets)
    fig, axes = plt.subplots(1, 4, figsize=(13, 3.2))
    for j, ax in enumerate(axes):
        ax.errorbar(k, est[:, j], yerr=std[:, j], marker="o", capsize=3, label="estimate +- std")
        ax.axhline(truth[j], color="k", ls="--", lw=1, label="truth")
        ax.set_title(f"{C.FACTOR_NAMES[j]}", fontsize=9)
        ax.set_xlabel("touch (action index)")
        ax.set_xticks(k, [f"{i}\n({a})" for i, a in zip(k, actions)], fontsize=7)
        ax.set_ylabel(units[j], fontsize=7)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"object {object_id}, policy {policy}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(cfg: DictConfig) -> int:
    import torch

    from embodied_tactile.active.episode import run_episodes
    from embodied_tactile.active.load import PalpationError, load_palpation_model
    from embodied_tactile.active.policy import make_policy

    _check(cfg)
    set_threads(int(cfg.threads))
    try:
        model, info = load_palpation_model(str(cfg.run), checkpoint=str(cfg.checkpoint), threads=int(cfg.threads))
    except PalpationError as err:
        raise SettingError(str(err)) from err
    used = [str(cfg.policy)] if cfg.mode == "episode" else [str(p) for p in cfg.evaluate.policies]
    checks = ([("first_action", int(cfg.first_action))] if cfg.first_action is not None else []) \
        + ([("single_action", int(cfg.single_action))] if "single" in used else [])
    for name, a in checks:  # before the calibration episodes (the fixed order's first action is one of the run's)
        if a not in model.actions:
            raise SettingError(f"{name}={a} is not an action of the run (trained on actions {list(model.actions)})")
    out = Path(cfg.out) if cfg.out else Path(info["run_dir"]) / "palpation"
    out.mkdir(parents=True, exist_ok=True)
    active = OmegaConf.to_container(cfg.active, resolve=True)
    needs_fixed = cfg.mode == "evaluate" and "fixed" in cfg.evaluate.policies or cfg.policy == "fixed" \
        or cfg.first_action is None
    from embodied_tactile.active.evaluation import calibration_cache, fit_error_score

    calib = calibration_cache(model)
    fixed = _fixed_order(cfg, model, info, calib) if needs_fixed else []
    error_score = None
    if active.get("criterion") == "learned" and (cfg.mode == "evaluate" or cfg.policy == "active"):
        t0 = time.perf_counter()
        error_score = fit_error_score(model, info["train_objects"], cache=calib)
        print(f"learned error score fitted on calibration episodes of {len(info['train_objects'])} training objects "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    del calib
    first = int(cfg.first_action) if cfg.first_action is not None else fixed[0]

    if cfg.mode == "episode":
        pol = make_policy(str(cfg.policy), model=model, first_action=first, single_action=int(cfg.single_action),
                          fixed_order=fixed, active=active, error_score=error_score)
        truth = model.true_factors([cfg.object])[0]
        png = out / f"episode_obj{cfg.object:02d}_{cfg.policy}_s{cfg.seed}.png"
        hist: dict[str, list] = {"a": [], "e": [], "s": []}
        print(f"object {cfg.object}: truth ({model.targets}) " +
              ", ".join(f"{n}={v:.3g}" for n, v in zip(C.FACTOR_NAMES, truth)), flush=True)

        def on_touch(k, a, e, s):
            hist["a"].append(int(a[0]))
            hist["e"].append(e[0])
            hist["s"].append(s[0])
            print(f"touch {k + 1}/{cfg.budget} action {int(a[0])} ({dict(C.get_action(model.primitive, int(a[0])).params)}): "
                  + ", ".join(f"{n}={m:.3g}+-{d:.2g}" for n, m, d in zip(C.FACTOR_NAMES, e[0], s[0])), flush=True)
            plot_episode(png, model, cfg.object, hist["a"], np.array(hist["e"]), np.array(hist["s"]), truth, cfg.policy)

        ep = run_episodes(model, _source(cfg, model, int(cfg.seed)), [cfg.object], pol, int(cfg.budget),
                          seed=int(cfg.seed), n_factor_samples=int(cfg.n_factor_samples), on_touch=on_touch)
        if ep.decision_s:
            print(f"decision latency: {1e3 * np.mean(ep.decision_s):.0f} ms per decision (mean of {len(ep.decision_s)})")
        print(f"figure: {png}")
        return 0

    from embodied_tactile.active.evaluation import evaluate_policies, summarise, write_outputs

    objects = info["test_objects"] if cfg.evaluate.objects == "test" else [int(o) for o in cfg.evaluate.objects]
    seeds = [int(s) for s in cfg.evaluate.seeds]
    pols = [str(p) for p in cfg.evaluate.policies]
    t0 = time.perf_counter()
    res = evaluate_policies(model, objects, budget=int(cfg.budget), seeds=seeds, policies=pols, fixed_order=fixed,
                            first_action=first, single_action=int(cfg.single_action), active=active,
                            n_factor_samples=int(cfg.n_factor_samples), error_score=error_score)
    summ = summarise(res["curves"])
    unseen = info.get("unseen_test_objects")
    caption = (f"NMSE (sum of squared errors / (n x catalogue variance) per factor, mean over the 4 factors; "
               f"targets {model.targets}) after each touch, over {len(objects)} objects of the run's test split "
               f"(split={info['split']}, {'objects unseen in training' if unseen else 'objects also seen in training with other trials'}), "
               f"mean and 95 % t interval over seeds {seeds}. Policies: {pols}; fixed order {fixed}; "
               f"single action {cfg.single_action}; active: {active}, first touch {first}.")
    meta = {"run": info["run_dir"], "checkpoint": info["checkpoint"], "objects": objects, "seeds": seeds,
            "fixed_order": fixed, "first_action": first, "single_action": int(cfg.single_action), "active": active,
            "split": info["split"], "wall_s": time.perf_counter() - t0,
            "title": f"{model.skin} {model.primitive}, {len(objects)} test objects, seeds {seeds}"}
    paths = write_outputs(out, summ, res, meta, caption)
    print(Path(paths["md"]).read_text())
    tgt = summ.get("target")
    if tgt:
        print(f"target: active reaches random's final NMSE {tgt['reference_final_nmse']:.4f} after "
              f"{tgt['touches_needed']} of {summ['budget']} touches (per seed {tgt['touches_needed_per_seed']}); "
              f"met (<= 60 %): {tgt['met']}")
    if res["decision_s"]:
        print(f"active decision wall time: {1e3 * np.mean(res['decision_s']):.0f} ms per decision for "
              f"{len(objects)} episodes at once")
    print("written: " + ", ".join(paths.values()))
    return 0


main = hydra_command("palpate", run, "palpate", errors=(SettingError,))


if __name__ == "__main__":
    main()
