"""Pendulum benchmark for the Latent Filter (docs/reference/model.md, "Pendulum benchmark"; results in docs/experiments/pendulum.md).

The driven, damped pendulum of Deep Variational Bayes Filters (Karl et al. 2017): 8
objects (natural frequency {2, 3, 4, 5} rad/s x damping {0.1, 0.6} 1/s), random
piecewise-constant torque, 60 frames of 50 ms rendered as noisy 28x28 images. Trains the
project's LatentFilter (one channel, n_z = 8, n_y = 4; the project's default recipe: observation
dropout 0.5, bounded evidence y, no labels; the prior's sigma learned) unsupervised
with the ELBO (linear KL warm-up over 10 % of the steps, y_weight 1) and prints the read-outs on held-out
sequences of the training systems and on systems never seen (parameters between the grid's),
each beside the untrained network's (linear / RBF kernel ridge R^2), and the open-loop
prediction error. 128 training sequences per object by default.

    python experiments/pendulum.py                                # 2500 steps, seed 0
    python experiments/pendulum.py --steps 500 --seed 1 --batch-size 16
    python experiments/pendulum.py --remedy obs_dropout=0 --remedy y_update=direct   # recipe=elbo's inference
    python experiments/pendulum.py --context --remedy y_start=population             # the context objective
"""

from __future__ import annotations

import argparse
import time

import torch

from embodied_tactile.bench.pendulum_run import DIAGNOSTIC_READOUTS, READOUTS, run
from embodied_tactile.bench.remedies import REMEDIES, parse_remedy, remedy_kwargs
from embodied_tactile.model.options import ContextOptions
from embodied_tactile.run.runtime import set_threads

def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--steps", type=int, default=2500, help="optimiser steps (default 2500)")
    p.add_argument("--seed", type=int, default=0, help="data (train seed, test seed + 1000) and init seed")
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--n-train", type=int, default=128, help="training sequences per object (held-out: 8 per object)")
    p.add_argument("--y-weight", type=float, default=1.0, help="linear warm-up y_weight (1 = plain ELBO)")
    p.add_argument("--remedy", type=parse_remedy, action="append", default=[], metavar="NAME=VALUE",
                   help=f"training remedy, repeatable; NAME in {sorted(REMEDIES)}")
    p.add_argument("--context", action="store_true",
                   help="train with the context objective (recipe=context): y from another sequence of the same "
                        "system, the sequence rolled forward open-loop after --initial-frames filtered frames")
    p.add_argument("--initial-frames", type=int, default=ContextOptions.initial_frames,
                   help="with --context: target frames filtered before the rollout")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--log-every", type=int, default=0, help="print the loss every N steps (0: never)")
    p.add_argument("--save", metavar="PATH", help="write the trained network (config + state_dict, torch.save) here")
    a = p.parse_args(argv)
    set_threads(a.threads)
    t0 = time.perf_counter()
    res = run(a.steps, seed=a.seed, batch_size=a.batch_size, n_train=a.n_train, model_kwargs=remedy_kwargs(a.remedy),
              annealing={"name": "linear", "beta0": 0.01, "fraction": 0.1, "y_weight": a.y_weight},
              log_every=a.log_every,
              context={"source": "trial", "initial_frames": a.initial_frames} if a.context else None)
    if a.save:
        torch.save({"config": res["model"].config(), "state_dict": res["model"].state_dict(), "seed": a.seed,
                    "steps": a.steps, "n_train": a.n_train}, a.save)
    print(f"pendulum: {a.steps} steps, batch {a.batch_size}, seed {a.seed}, {a.n_train} training sequences per object, "
          f"y_weight {a.y_weight}, remedies {dict(a.remedy) or 'none'}, objective "
          f"{f'context (y from another sequence of the system, {a.initial_frames} initial frames)' if a.context else 'filtering ELBO'}")
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
    ol = res["open_loop"]
    print("\nopen loop after 20 filtered frames, image MSE x 1e3 against the noiseless frame")
    print("| horizon | model | last frame | last frame (noiseless) | mean image |\n|---|---|---|---|---|")
    for h in (1, 2, 5, 10, 15, 20, 30, 40):
        print(f"| {h} | {1e3 * ol['model'][h - 1]:.2f} | {1e3 * ol['last_frame'][h - 1]:.2f} | "
              f"{1e3 * ol['last_clean'][h - 1]:.2f} | {1e3 * ol['mean_image'][h - 1]:.2f} |")
    beats = ol["model"] < ol["last_clean"]
    first_loss = next((h + 1 for h, b in enumerate(beats) if not b), None)
    print(f"model beats the noiseless last frame up to horizon "
          f"{len(beats) if first_loss is None else first_loss - 1}")
    print(f"wall time: train {res['train_s']:.0f} s, read-outs {res['eval_s']:.0f} s, "
          f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
