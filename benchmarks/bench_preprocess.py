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
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from embodied_tactile import constants as C
from embodied_tactile.data import cache as cache_mod
from embodied_tactile.data.preprocess import PreprocessConfig, acc_logmel, acc_logmel_naive, preprocess_trials
from embodied_tactile.io.rawformat import RawTrial, make_attrs, read_trial, write_trial


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


_TRIALS: list[RawTrial] = []  # inherited by the forked workers: no pickling of inputs


def _work(task):
    lo, hi, cfg = task
    c0 = time.process_time()
    with _one_blas_thread():
        preprocess_trials(_TRIALS[lo:hi], cfg)
    return time.process_time() - c0


def _read(task):
    path, names = task
    c0 = time.process_time()
    for n in names:
        read_trial(path, n, ("t", "acc", "fsr", "pose", "baseline_fsr"))
    return time.process_time() - c0


def _one_blas_thread():
    from embodied_tactile.data.cache import _one_blas_thread as one

    return one()


def _cpu_all() -> float:
    """CPU seconds of this process and its reaped children."""
    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def _best(fn, repeat: int = 2) -> tuple[float, float]:
    """(best wall, best CPU) seconds over ``repeat`` runs of ``fn`` in this process."""
    wall = cpu = float("inf")
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
    return wall, cpu


def _pool_best(pool, fn, tasks, repeat: int = 2) -> tuple[float, float]:
    """(best wall, its summed worker CPU) of ``pool.map(fn, tasks)``."""
    best = (float("inf"), float("inf"))
    for _ in range(repeat):
        t0 = time.perf_counter()
        cpu = sum(pool.map(fn, tasks))
        best = min(best, (time.perf_counter() - t0, cpu))
    return best


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=64)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--chunk", type=int, default=8)
    args = ap.parse_args()
    cfg = PreprocessConfig().validate()
    trials = [synthetic_trial(i) for i in range(args.trials)]
    rows = []  # (stage, n_trials, wall s, cpu s, naive cpu s or None)
    load0 = os.getloadavg()[0]
    w = args.workers

    # -- acc: vectorised vs naive, same process, same trials
    k = min(8, args.trials)
    acc = np.stack([tr.acc for tr in trials[:k]])
    cfg_l = PreprocessConfig(stft_backend="librosa")
    with _one_blas_thread():
        acc_logmel(acc[:1], cfg); acc_logmel(acc[:1], cfg_l); acc_logmel_naive(trials[0].acc, cfg)  # warm-up
        naive = _best(lambda: [acc_logmel_naive(tr.acc, cfg) for tr in trials[:k]], 1)
        rows.append(("acc naive per-sensor loop, 1 proc", k, *naive, naive))
        rows.append(("acc vectorised, librosa STFT, 1 proc", k, *_best(lambda: acc_logmel(acc, cfg_l)), naive))
        rows.append(("acc vectorised, numpy STFT (default), 1 proc", k, *_best(lambda: acc_logmel(acc, cfg)), naive))
        rows.append(("fsr only, 1 proc", k, *_best(lambda: preprocess_trials(trials[:k], cfg, ("fsr",))), None))
        rows.append(("actions only, 1 proc", k, *_best(lambda: preprocess_trials(trials[:k], cfg, ("actions",))), None))
        rows.append(("full pipeline in memory, 1 proc", k, *_best(lambda: preprocess_trials(trials[:k], cfg)), None))

    # -- full pipeline in memory on `workers` processes (trials inherited through fork)
    _TRIALS[:] = trials
    chunks = [(i, i + args.chunk, cfg) for i in range(0, len(trials), args.chunk)]
    with mp.get_context("fork").Pool(w) as pool:
        pool.map(_work, chunks[:w])  # warm-up
        rows.append((f"full pipeline in memory, {w} procs", len(trials), *_pool_best(pool, _work, chunks), None))

    # -- end to end: raw HDF5 -> per-field caches
    tmp = Path(tempfile.mkdtemp(prefix="bench_pre_"))
    try:
        raw = tmp / "raw.h5"
        for tr in trials:
            write_trial(raw, tr)
        names = [tr.name for tr in trials]
        tasks = [(raw, names[i : i + args.chunk]) for i in range(0, len(names), args.chunk)]
        with mp.get_context("fork").Pool(w) as pool:
            rows.append((f"read raw HDF5 only (gzip), {w} procs", len(trials), *_pool_best(pool, _read, tasks, 1), None))
        for label in (f"build_cache raw -> 3 caches, {w} workers", "build_cache again (reuse: fingerprint only)"):
            t0, c0 = time.perf_counter(), _cpu_all()
            cache_mod.build_cache([raw], tmp / "cache", cfg, workers=w, chunk_size=args.chunk)
            rows.append((label, len(trials), time.perf_counter() - t0, _cpu_all() - c0, None))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    print(f"\n{args.trials} synthetic 10 s trials, {os.cpu_count()} CPUs, {w} workers, chunk {args.chunk}, "
          f"load average {load0:.1f} -> {os.getloadavg()[0]:.1f}")
    print("wall trials/s = as measured on this (possibly shared) box; CPU ms/trial = CPU time of all our")
    print(f"processes; idle-box estimate = trials/s if each process had its own core (min(procs, {w}) / CPU per trial)\n")
    print(f"| {'stage':<46} | {'wall trials/s':>13} | {'CPU ms/trial':>12} | {'idle-box est. trials/s':>22} | {'vs naive (CPU)':>14} |")
    print(f"|{'-' * 48}|{'-' * 15}|{'-' * 14}|{'-' * 24}|{'-' * 16}|")
    for name, n, wall, cpu, ref in rows:
        procs = 1 if "1 proc" in name else w
        est = procs * n / cpu
        ratio = "" if ref is None else f"{ref[1] / cpu:.1f}x"
        print(f"| {name:<46} | {n / wall:13.1f} | {1000 * cpu / n:12.1f} | {est:22.1f} | {ratio:>14} |")


if __name__ == "__main__":
    main()
