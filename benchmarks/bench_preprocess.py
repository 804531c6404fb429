"""Benchmark of data.preprocess / data.cache on synthetic 10 s trials.

    python benchmarks/bench_preprocess.py [--trials 64] [--workers 2]

Prints one table: vectorised acc path vs the naive per-sensor loop, in-memory
throughput of the full pipeline (acc + fsr + actions) on ``workers`` processes, and the
end-to-end cache build from a raw HDF5 file (read + decompress + preprocess + write).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from embodied_tactile import constants as C
from embodied_tactile.data import cache as cache_mod
from embodied_tactile.data.preprocess import PreprocessConfig, acc_logmel, acc_logmel_naive, preprocess_trials
from embodied_tactile.io.rawformat import RawTrial, make_attrs, write_trial


def synthetic_trial(i: int, seed: int = 0) -> RawTrial:
    """10 s trial: per-sensor sine vibrations over gravity + noise, a moving Gaussian
    pressure blob, a pressing pose (sinusoidal z, small roll ramp)."""
    rng = np.random.default_rng(seed + i)
    n, m = C.N_TACTILE, C.N_POSE
    t = 100.0 + np.arange(n) / C.FS_TACTILE
    f = rng.uniform(5, 250, size=(4, 4, 1))
    amp = rng.uniform(0.01, 0.3, size=(4, 4, 1))
    acc = np.zeros((n, 4, 4, 3), np.float32)
    acc[..., 2] = (1.0 + amp * np.sin(2 * np.pi * f * t[None, None, :]) ).transpose(2, 0, 1)
    acc += rng.normal(0, 2e-3, acc.shape).astype(np.float32)
    yy, xx = np.mgrid[0:16, 0:16]
    cx = 8 + 4 * np.sin(2 * np.pi * 0.2 * (t - t[0]))
    blob = np.exp(-(((xx[None] - cx[:, None, None]) ** 2 + (yy[None] - 8) ** 2) / 8.0))
    fsr = np.stack([3000 * blob, 1500 * blob], axis=1) + rng.uniform(0, 20, (n, 2, 16, 16))
    fsr = np.clip(fsr, 0, 4095).astype(np.uint16)
    pose_t = 100.0 + np.arange(m) / C.FS_POSE
    pose = np.zeros((m, 6), np.float32)
    pose[:, 2] = 0.1 + 0.004 * np.cos(2 * np.pi * 0.4 * (pose_t - pose_t[0]) + np.pi)
    pose[:, 3] = 0.01 * (pose_t - pose_t[0])
    attrs = make_attrs(object_id=i % 32, skin="soft", primitive="pressing", action_index=i % 16,
                       repetition=i // 32, source="simulated", seed=seed + i)
    return RawTrial(t=t, acc=acc, fsr=fsr, pose_t=pose_t, pose=pose, attrs=attrs)


def _work(chunk):
    trials, cfg = chunk
    return {k: v.shape for k, v in preprocess_trials(trials, cfg).items()}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=64)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--chunk", type=int, default=8)
    args = ap.parse_args()
    cfg = PreprocessConfig().validate()
    trials = [synthetic_trial(i) for i in range(args.trials)]
    rows = []

    # -- acc: vectorised vs naive, same process, same trials
    k = min(8, args.trials)
    acc = np.stack([tr.acc for tr in trials[:k]])
    acc_logmel(acc[:1], cfg); acc_logmel_naive(trials[0].acc, cfg)  # warm-up (librosa, caches)
    t0 = time.perf_counter(); acc_logmel(acc, cfg); t_vec = time.perf_counter() - t0
    cfg_l = PreprocessConfig(stft_backend="librosa")
    t0 = time.perf_counter(); acc_logmel(acc, cfg_l); t_lib = time.perf_counter() - t0
    t0 = time.perf_counter()
    for tr in trials[:k]:
        acc_logmel_naive(tr.acc, cfg)
    t_naive = time.perf_counter() - t0
    rows.append(("acc naive per-sensor loop, 1 proc", k / t_naive, 1.0))
    rows.append(("acc vectorised, librosa STFT, 1 proc", k / t_lib, t_naive / t_lib))
    rows.append(("acc vectorised, numpy STFT, 1 proc", k / t_vec, t_naive / t_vec))

    # -- full pipeline in memory, 1 proc and `workers` procs
    t0 = time.perf_counter(); preprocess_trials(trials[:k], cfg); t1 = time.perf_counter() - t0
    rows.append(("full pipeline in memory, 1 proc", k / t1, None))
    chunks = [(trials[i : i + args.chunk], cfg) for i in range(0, len(trials), args.chunk)]
    with mp.get_context("fork").Pool(args.workers) as pool:
        pool.map(_work, chunks[:args.workers])  # warm-up
        t0 = time.perf_counter(); pool.map(_work, chunks); tw = time.perf_counter() - t0
    rows.append((f"full pipeline in memory, {args.workers} procs", len(trials) / tw, None))

    # -- end to end: raw HDF5 -> per-field caches
    tmp = Path(tempfile.mkdtemp(prefix="bench_pre_"))
    try:
        raw = tmp / "raw.h5"
        for tr in trials:
            write_trial(raw, tr)
        t0 = time.perf_counter()
        cache_mod.build_cache([raw], tmp / "cache", cfg, workers=args.workers)
        tb = time.perf_counter() - t0
        rows.append((f"build_cache raw->3 caches, {args.workers} workers", len(trials) / tb, None))
        t0 = time.perf_counter()
        cache_mod.build_cache([raw], tmp / "cache", cfg, workers=args.workers)
        rows.append(("build_cache again (reuse: fingerprint only)", len(trials) / (time.perf_counter() - t0), None))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    print(f"\n{args.trials} synthetic 10 s trials, {os.cpu_count()} CPUs, chunk {args.chunk}\n")
    print(f"| {'stage':<46} | {'trials/s':>9} | {'vs naive':>8} |")
    print(f"|{'-' * 48}|{'-' * 11}|{'-' * 10}|")
    for name, rate, ratio in rows:
        print(f"| {name:<46} | {rate:9.1f} | {'' if ratio is None else f'{ratio:7.1f}x':>8} |")


if __name__ == "__main__":
    main()
