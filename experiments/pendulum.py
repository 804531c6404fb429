"""Pendulum benchmark for the Latent Filter (docs/reference/model.md, "Pendulum benchmark"; results in docs/experiments/pendulum.md).

The driven, damped pendulum of Deep Variational Bayes Filters (Karl et al. 2017): 8
objects (natural frequency {2, 3, 4, 5} rad/s x damping {0.1, 0.6} 1/s), random
piecewise-constant torque, 60 frames of 50 ms rendered as noisy 28x28 images. Trains the
pendulum scene of train.py (``python train.py experiment=pendulum``: the project's
LatentFilter, one channel, n_z = 8, n_y = 4; recipe=filter: observation dropout 0.5, bounded
evidence y, no labels; the prior's sigma learned) unsupervised with the ELBO (linear KL
warm-up over 10 % of the steps, y_weight 1) through ``run.training.train``, in a run folder
(checkpoints, metrics.json, the KRR read-out of (w0, d)), and prints the read-outs on held-out
sequences of the training systems and on systems never seen (parameters between the grid's),
each beside the untrained network's (linear / RBF kernel ridge R^2), the open-loop
prediction error and the run's NMSE on (w0, d). 128 training sequences per object by default.
Arguments after the options are Hydra overrides of the scene (``model.net.NAME=VALUE``,
``recipe=...``; docs/reference/model.md, "Options").

    python experiments/pendulum.py                                # 2500 steps, seed 0
    python experiments/pendulum.py --steps 500 --seed 1 --batch-size 16
    python experiments/pendulum.py model.net.obs_dropout=0 model.net.y_update=direct   # recipe=elbo's inference
    python experiments/pendulum.py recipe=context                                     # the context objective
"""

from __future__ import annotations

import argparse
import math
import time
from datetime import datetime
from pathlib import Path

from hydra.utils import instantiate

from embodied_tactile.eval.pendulum import DIAGNOSTIC_READOUTS, READOUTS, read_out
from embodied_tactile.eval.runs import load_module, load_run, untrained_module
from embodied_tactile.data.pendulum import N_OBJECTS
from embodied_tactile.jsonio import read_json
from embodied_tactile.run.threadenv import set_threads
from embodied_tactile.run.training import compose, train


def scene_overrides(steps: int, seed: int = 0, batch_size: int = 16, n_train: int = 128, y_weight: float = 1.0,
                    threads: int = 1) -> list[str]:
    """train.py overrides of the pendulum scene for ``steps`` optimiser steps: an epoch is one
    pass over the ``n_train`` x 8 training sequences, so the run has as many epochs as the
    steps need, stopped at ``steps`` (``trainer.max_steps``)."""
    per_epoch = math.ceil(n_train * N_OBJECTS / batch_size)
    return ["experiment=pendulum", f"seed={seed}", f"threads={threads}", f"data.batch_size={batch_size}",
            f"data.n_train={n_train}", f"annealing.schedule.y_weight={y_weight}",
            f"trainer.max_epochs={math.ceil(steps / per_epoch)}", f"+trainer.max_steps={steps}",
            "plain_progress=true"]


def _open_loop_table(ol) -> None:
    """The open-loop prediction error per horizon against the copy-the-last-frame baselines."""
    print("\nopen loop after 20 filtered frames, image MSE x 1e3 against the noiseless frame")
    print("| horizon | model | last frame | last frame (noiseless) | mean image |\n|---|---|---|---|---|")
    for h in (1, 2, 5, 10, 15, 20, 30, 40):
        print(f"| {h} | {1e3 * ol['model'][h - 1]:.2f} | {1e3 * ol['last_frame'][h - 1]:.2f} | "
              f"{1e3 * ol['last_clean'][h - 1]:.2f} | {1e3 * ol['mean_image'][h - 1]:.2f} |")
    beats = ol["model"] < ol["last_clean"]
    first_loss = next((h + 1 for h, b in enumerate(beats) if not b), None)
    print(f"model beats the noiseless last frame up to horizon "
          f"{len(beats) if first_loss is None else first_loss - 1}")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--steps", type=int, default=2500, help="optimiser steps (default 2500)")
    p.add_argument("--seed", type=int, default=0, help="data (train seed, test seed + 1000) and init seed")
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--n-train", type=int, default=128, help="training sequences per object (held-out: 8 per object)")
    p.add_argument("--y-weight", type=float, default=1.0, help="linear warm-up y_weight (1 = plain ELBO)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--run-dir", help="the run folder (default logs/pendulum/runs/<time>)")
    p.add_argument("overrides", nargs="*", help="Hydra overrides of the scene, e.g. model.net.obs_dropout=0")
    a = p.parse_args(argv)
    set_threads(a.threads)
    t0 = time.perf_counter()
    run_dir = a.run_dir or f"logs/pendulum/runs/{datetime.now():%Y-%m-%d_%H-%M-%S-%f}"
    cfg = compose([*scene_overrides(a.steps, a.seed, a.batch_size, a.n_train, a.y_weight, a.threads),
                   *a.overrides], run_dir)
    train(cfg, run_dir)
    metrics = read_json(Path(run_dir) / "metrics.json")
    run = load_run(Path(run_dir), "last")
    trained = load_module(run)
    dm = instantiate(run.cfg.data)
    dm.prepare_data()
    dm.setup("fit")
    res = read_out(trained, untrained_module(run, trained), dm, seed=a.seed)
    context = run.cfg.model.get("context")
    print(f"pendulum: {a.steps} steps, batch {a.batch_size}, seed {a.seed}, {a.n_train} training sequences per object, "
          f"y_weight {a.y_weight}, overrides {' '.join(a.overrides) or 'none'}, objective "
          f"{f'context (y from another sequence of the system, {context.initial_frames} initial frames)' if context else 'filtering ELBO'}; "
          f"run folder {run_dir}")
    print("R^2 linear / kernel; held-out sequences of the training systems, and the unseen systems (w0, d between "
          "the training grid's); 'untrained': the same network at its initialisation")
    print("| read-out | held-out | held-out, untrained | unseen systems | unseen, untrained |\n|---|---|---|---|---|")
    for k in (*READOUTS, *DIAGNOSTIC_READOUTS):
        cells = [res[part][k] for part in ("readouts", "readouts_untrained", "readouts_unseen", "readouts_unseen_untrained")]
        print(f"| {k}{' (diagnostic)' if k in DIAGNOSTIC_READOUTS else ''} | "
              + " | ".join(f"{lin:.2f} / {krr:.2f}" for lin, krr in cells) + " |")
    dg = res["diagnostics"]
    print(f"\nheld-out: transition weight in q_filt {dg['transition_weight']:.3f}, median variance encoder "
          f"{dg['encoder_var']:.2e} / transition {dg['transition_var']:.2e}; per sequence nll {dg['nll']:.0f}, "
          f"kl_z {dg['kl_z']:.1f}, kl_y {dg['kl_y']:.2f}")
    print("gradient SNR of the filtering ELBO (median |mean| / std over 16 samples, one batch): "
          + ", ".join(f"{k} {v:.2f}" for k, v in res["gradient_snr"].items()))
    if res["open_loop"] is None:
        print("\nno open-loop prediction: the sequences are shorter than 20 filtered + 40 predicted frames")
    else:
        _open_loop_table(res["open_loop"])
    final = metrics.get("krr_final") or {}
    nmse = final.get("nmse") or {}
    print(f"\nthe run's KRR read-out of y -> (w0, d) on the held-out sequences (NMSE, whole trajectory / last frame): "
          f"{final.get('nmse_overall', float('nan')):.3f} / {final.get('nmse_last_overall', float('nan')):.3f} "
          f"(w0 {nmse.get('natural_frequency', float('nan')):.3f}, d {nmse.get('damping', float('nan')):.3f}; "
          f"mean predictor {final.get('nmse_mean_predictor_overall', float('nan')):.3f})")
    print(f"wall time: train {metrics.get('train_wall_s', float('nan')):.0f} s, read-outs {res['eval_s']:.0f} s, "
          f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
