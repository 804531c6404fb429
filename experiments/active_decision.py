"""Latency of one active-palpation decision (docs/reference/active.md): does choosing the next touch fit
between two touches?

One decision = imagined rollouts of every candidate action from the current filter state
(``n_rollouts`` futures x ``horizon`` frames each, batched) + the KRR alignment of the
imagined posteriors (``n_y_samples`` draws each). It times
:func:`embodied_tactile.active.policy.expected_variance_reduction` for one episode (B = 1)
with 4 candidate actions, one torch thread, and prints a table of the median and worst
latency in ms next to the time one touch takes (10 s of palpation).

    python experiments/active_decision.py                       # default-size network, synthetic KRR
    python experiments/active_decision.py --run logs/train/runs/<run>   # a trained run

Without ``--run`` the network is an untrained LatentFilter of the default sizes (multi_l,
n_z = n_y = 16, LSTM and transition 128) and the KRR an exact KRR on 320 synthetic rows (the
default scene's 80 training trials x 4 frames): the same amount of computation as the
trained default run.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch
from embodied_tactile.run.threadenv import set_threads


def _synthetic_model():
    from embodied_tactile.active.model import PalpationModel
    from embodied_tactile.data.preprocess import PreprocessConfig
    from embodied_tactile.eval.krr import fit_alignment
    from embodied_tactile.model import LatentFilter

    torch.manual_seed(0)
    net = LatentFilter("multi_l").eval()
    rng = np.random.default_rng(0)
    y = rng.standard_normal((80, 300, 16)).astype(np.float32)
    align = fit_alignment(y, rng.integers(0, 3, (80, 4)).astype(float), cv=2, n_threads=1)
    nominal = {a: (rng.standard_normal((300, 6)) * 0.1).astype(np.float32) for a in (2, 6, 10, 14)}
    return PalpationModel(net=net, channels=("acc", "fsr_t", "fsr_b"), preprocess=PreprocessConfig(),
                          alignment=align, ref_var=np.ones(4), nominal_actions=nominal)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", default=None, help="trained run folder (default: default-size untrained network)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--settings", default="1x300,4x300,8x300,4x100",
                    help="comma-separated n_rollouts x horizon settings")
    args = ap.parse_args()
    set_threads(1)
    from embodied_tactile.active.episode import filter_touch
    from embodied_tactile.active.policy import expected_variance_reduction

    if args.run:
        from embodied_tactile.active.load import load_palpation_model

        model, _ = load_palpation_model(args.run)
        source = f"run {args.run}"
    else:
        model = _synthetic_model()
        source = "default-size untrained LatentFilter (multi_l), synthetic KRR (320 rows)"
    C = len(model.channels)
    T = next(iter(model.nominal_actions.values())).shape[0]
    obs = torch.rand(1, T, C, 28, 28, generator=torch.Generator().manual_seed(0))
    acts = model.nominal_batch([model.actions[-1]])
    t0 = time.perf_counter()
    _, state = filter_touch(model.net, obs, acts, None)
    touch_filter_ms = 1e3 * (time.perf_counter() - t0)
    print(f"# one active decision, B = 1 episode, {len(model.actions)} candidate actions, torch threads 1; {source}")
    print(f"# filtering one touch ({T} frames, filter_step) took {touch_filter_ms:.0f} ms; one touch lasts 10 s")
    print("| n_rollouts | horizon (frames) | criterion | median ms | max ms |")
    print("|---|---|---|---|---|")
    for spec in args.settings.split(","):
        m, h = (int(x) for x in spec.split("x"))
        for crit in (("variance", "spread") if m > 1 else ("variance",)):
            times = []
            for r in range(args.repeats):
                t0 = time.perf_counter()
                expected_variance_reduction(model, state, list(model.actions), n_rollouts=m, horizon=h,
                                            n_y_samples=32, seed=r, criterion=crit)
                times.append(1e3 * (time.perf_counter() - t0))
            print(f"| {m} | {h} | {crit} | {statistics.median(times):.0f} | {max(times):.0f} |")
    # the learned score: one KRR per candidate on the posterior mean (synthetic score of the
    # same size as fit_error_score's: 4 first touches x 32 objects rows per candidate)
    from embodied_tactile.active.policy import predicted_error
    from embodied_tactile.eval.krr import fit_alignment

    rng = np.random.default_rng(0)
    n_y = int(state["z"].shape[1]) if not hasattr(model.net, "n_y") else int(model.net.n_y)
    ys = rng.standard_normal((128, n_y))
    score = {a: fit_alignment(ys, rng.random((128, 1)), cv=2, n_threads=1) for a in model.actions}
    y_now = rng.standard_normal((1, n_y))
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        predicted_error(score, y_now, list(model.actions))
        times.append(1e3 * (time.perf_counter() - t0))
    print(f"| - | - | learned | {statistics.median(times):.1f} | {max(times):.1f} |")


if __name__ == "__main__":
    main()
