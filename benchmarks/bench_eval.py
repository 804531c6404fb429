"""KRR alignment cost and accuracy: fit + predict time vs number of training sequences,
exact RBF-KRR vs Nystroem + Ridge, on a synthetic task with a known smooth nonlinear map.

    python benchmarks/bench_eval.py [--n 128 512 2048] [--t 300] [--frames 1] [--threads 1]

Synthetic task: 4 latent causes u ~ U(-1, 1); factors = (sin 2u0, u1^3 + u1, exp u2,
tanh 2u3); latents (n, T, 16) converge over time to tanh(u W) plus noise 0.05. Held-out:
128 sequences, all T frames predicted. NMSE at the last frame and over the trajectory.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from embodied_tactile.eval import fit_alignment, nmse, nmse_trajectory


def synthetic(n, t, d, seed, w):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, (n, 4))
    factors = np.c_[np.sin(2 * u[:, 0]), u[:, 1] ** 3 + u[:, 1], np.exp(u[:, 2]), np.tanh(2 * u[:, 3])]
    conv = (1 - np.exp(-np.arange(t) / 30.0))[None, :, None]
    lat = np.tanh(u @ w)[:, None, :] * conv + 0.05 * rng.normal(size=(n, t, d))
    return lat.astype(np.float32), factors


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, nargs="+", default=[128, 512, 2048])
    ap.add_argument("--t", type=int, default=300)
    ap.add_argument("--d", type=int, default=16)
    ap.add_argument("--n-test", type=int, default=128)
    ap.add_argument("--frames", type=int, default=1, help="final-segment frames per training sequence")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--max-exact-rows", type=int, default=4096)
    args = ap.parse_args()
    w = np.random.default_rng(1234).normal(size=(4, args.d))
    xte, yte = synthetic(args.n_test, args.t, args.d, 999, w)
    print(f"T={args.t} d={args.d} held-out={args.n_test} seqs x {args.t} frames, frames/seq={args.frames}, "
          f"grid 5 alpha x 4 gamma, 5 grouped folds, BLAS threads={args.threads}")
    head = f"{'n_train':>7} {'rows':>6} {'method':>15} {'fit_s':>7} {'predict_s':>9} {'nmse_last':>9} {'nmse_traj':>9}  alpha / gamma*d"
    print(head)
    print("-" * len(head))
    for n in args.n:
        xtr, ytr = synthetic(n, args.t, args.d, n, w)
        rows = n * args.frames
        for method, thr in (("exact_krr", 10**9), ("nystroem_ridge", 0)):
            if method == "exact_krr" and rows > args.max_exact_rows:
                print(f"{n:>7} {rows:>6} {method:>15}  skipped (rows > {args.max_exact_rows})")
                continue
            t0 = time.perf_counter()
            al = fit_alignment(xtr, ytr, frames_per_sequence=args.frames, nystroem_threshold=thr, n_components=500,
                               n_threads=args.threads)
            t1 = time.perf_counter()
            from threadpoolctl import threadpool_limits

            with threadpool_limits(args.threads):
                pred = al.predict(xte)
            t2 = time.perf_counter()
            last = np.mean(nmse(yte, pred[:, -1]))
            traj = np.mean(nmse_trajectory(yte, pred))
            print(f"{n:>7} {rows:>6} {al.params['method']:>15} {t1 - t0:>7.2f} {t2 - t1:>9.2f} {last:>9.4f} {traj:>9.4f}"
                  f"  {al.params['alpha']:.0e} / {al.params['gamma_times_d']:.1f}")


if __name__ == "__main__":
    main()
