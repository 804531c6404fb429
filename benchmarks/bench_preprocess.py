"""Benchmark of data.preprocess / data.cache on synthetic 10 s trials.

    python benchmarks/bench_preprocess.py [--trials 64] [--workers 2]

Prints two tables. Raw-format codecs: file size, write and read (decode) CPU time per
trial for the candidates (gzip-1 + shuffle, the format's old default; lzf; Blosc-LZ4 with
byte or bit shuffle, the current default; uncompressed). Stages: vectorised acc path vs
the naive loop (one mel spectrogram per channel: scipy's ShortTimeFFT and
librosa's filterbank, tests/helpers.py; before 84d1ac1 it called librosa's melspectrogram), the same vectorised path with
librosa's melspectrogram instead of the package's STFT, in-memory throughput of the full
pipeline (acc + fsr + actions) on ``workers`` processes, and the end-to-end cache build
from a raw HDF5 file (read + decompress + preprocess + write).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from embodied_tactile import constants as C
from embodied_tactile.data import cache as cache_mod
import h5py
import hdf5plugin
import scipy.signal

from embodied_tactile.data import preprocess as P
from embodied_tactile.data.preprocess import PreprocessConfig, acc_logmel, preprocess_trials
from embodied_tactile.data.rawformat import RawTrial, make_attrs, read_trial, write_trial

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers import acc_logmel_naive  # noqa: E402  the tests' reference loop (tests/helpers.py)

CODECS = {
    "gzip-1 + shuffle (old default)": {"compression": "gzip", "compression_opts": 1, "shuffle": True},
    "lzf": {"compression": "lzf"},
    "lzf + shuffle": {"compression": "lzf", "shuffle": True},
    "blosc-lz4 + shuffle": dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE)),
    "blosc-lz4 + bitshuffle (default)": dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.BITSHUFFLE)),
    "uncompressed": {},
}


def codec_rows(trials: list[RawTrial], path: Path) -> list[tuple[str, float, float, float]]:
    """(codec, MB/trial, write CPU ms/trial, best read CPU ms/trial) for tactile acc + fsr in
    the format's one-second chunks (the bulk of a trial: 1.3 + 7.2 MB raw)."""
    rows = []
    for name, opts in CODECS.items():
        if path.exists():
            path.unlink()
        c0 = time.process_time()
        with h5py.File(path, "w") as f:
            for i, tr in enumerate(trials):
                g = f.create_group(str(i))
                for fld in ("acc", "fsr"):
                    a = getattr(tr, fld)
                    g.create_dataset(fld, data=a, chunks=(int(C.FS_TACTILE), *a.shape[1:]), **opts)
        write = time.process_time() - c0
        read = float("inf")
        for _ in range(3):
            c0 = time.process_time()
            with h5py.File(path, "r") as f:
                for i in range(len(trials)):
                    f[str(i)]["acc"][()], f[str(i)]["fsr"][()]
            read = min(read, time.process_time() - c0)
        n = len(trials)
        rows.append((name, path.stat().st_size / n / 1e6, 1000 * write / n, 1000 * read / n))
    return rows


def acc_logmel_librosa(acc: np.ndarray, cfg: PreprocessConfig) -> np.ndarray:
    """The vectorised path with librosa's melspectrogram (one call on all channels, float64)
    in place of the package's STFT: the comparison behind "one STFT" in the docs."""
    import librosa

    sig = P.acc_signals(acc, cfg)
    y = scipy.signal.resample_poly(sig, 6, 7, axis=-1)
    left, right = P.stft_padding(cfg, y.shape[-1])
    power = librosa.feature.melspectrogram(
        y=P.pad_last(y, left, right), sr=cfg.fs_resample, n_fft=cfg.n_fft, hop_length=cfg.hop_length,
        win_length=cfg.win_length, window=cfg.window, center=False, n_mels=cfg.n_mels, fmin=cfg.fmin,
        fmax=cfg.fmax_hz, htk=cfg.mel_htk, norm=cfg.mel_norm,
    ).sum(axis=-3)
    db = 10 * np.log10(np.maximum(power, cfg.db_amin))
    mel = ((db - cfg.db_min) / (cfg.db_max - cfg.db_min)).reshape(len(acc), 4, 4, cfg.n_mels, -1)
    return P.tile_layout(np.moveaxis(mel, (1, 2, 4), (3, 4, 1)), cfg.tile_shape).astype(np.float32)


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
    from embodied_tactile.data.cache import one_blas_thread as one

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
    ap.add_argument("--raw", default=None, help="take the trials from this raw HDF5 file (e.g. a simulated scene) instead of synthesising them")
    args = ap.parse_args()
    cfg = PreprocessConfig().validate()
    if args.raw:
        with h5py.File(args.raw, "r") as f:
            names = sorted(f["trials"])[: args.trials]
        trials = [read_trial(args.raw, n) for n in names]
        args.trials = len(trials)
    else:
        trials = [synthetic_trial(i) for i in range(args.trials)]
    rows = []  # (stage, n_trials, wall s, cpu s, naive cpu s or None)
    load0 = os.getloadavg()[0]
    w = args.workers

    # -- acc: vectorised vs naive, same process, same trials
    k = min(8, args.trials)
    acc = np.stack([tr.acc for tr in trials[:k]])
    with _one_blas_thread():
        acc_logmel(acc[:1], cfg); acc_logmel_librosa(acc[:1], cfg); acc_logmel_naive(trials[0].acc, cfg)  # warm-up
        naive = _best(lambda: [acc_logmel_naive(tr.acc, cfg) for tr in trials[:k]], 2)
        rows.append(("acc naive loop (one STFT per channel), 1 proc", k, *naive, naive))
        rows.append(("acc vectorised, librosa melspectrogram, 1 proc", k, *_best(lambda: acc_logmel_librosa(acc, cfg), 3), naive))
        rows.append(("acc vectorised, package STFT (f32), 1 proc", k, *_best(lambda: acc_logmel(acc, cfg), 3), naive))
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
            rows.append((f"read raw HDF5 only (blosc-lz4), {w} procs", len(trials), *_pool_best(pool, _read, tasks, 1), None))
        for label in (f"build_cache raw -> 3 caches, {w} workers", "build_cache again (reuse: fingerprint only)"):
            t0, c0 = time.perf_counter(), _cpu_all()
            cache_mod.build_cache([raw], tmp / "cache", cfg, workers=w, chunk_size=args.chunk)
            rows.append((label, len(trials), time.perf_counter() - t0, _cpu_all() - c0, None))
        codecs = codec_rows(trials[: min(8, len(trials))], tmp / "codec.h5")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    src = f"trials of {args.raw}" if args.raw else "synthetic 10 s trials"
    print(f"\nraw-format codecs, tactile acc + fsr of {min(8, len(trials))} {src}, one-second chunks, 1 proc (CPU time)\n")
    print(f"| {'codec':<34} | {'MB/trial':>8} | {'write CPU ms/trial':>18} | {'read CPU ms/trial':>17} |")
    print(f"|{'-' * 36}|{'-' * 10}|{'-' * 20}|{'-' * 19}|")
    for name, mb, wr, rd in codecs:
        print(f"| {name:<34} | {mb:8.2f} | {wr:18.1f} | {rd:17.1f} |")
    print(f"\n{args.trials} {src}, {os.cpu_count()} CPUs, {w} workers, chunk {args.chunk}, "
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
