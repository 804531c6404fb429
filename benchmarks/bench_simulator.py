"""Simulator benchmark: cost of one 10 s trial and of the default dataset.

    python benchmarks/bench_simulator.py            # full: 512 trials, 2 workers
    python benchmarks/bench_simulator.py --quick    # 64-trial subset, extrapolated to 512

Prints a markdown table. Per-trial figures are single-threaded (BLAS/OpenMP pinned to one
thread); both wall and process CPU seconds are given because the machine may be shared.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from embodied_tactile import constants as C  # noqa: E402
from embodied_tactile.data.rawformat import scan_raw  # noqa: E402
from embodied_tactile.sim import generate_dataset, simulate_trial  # noqa: E402


def per_trial(repeats: int) -> dict[str, tuple[float, float]]:
    out = {}
    for prim in C.PRIMITIVES:
        simulate_trial(0, "soft", prim, 0)  # warm the surface cache
        walls, cpus = [], []
        for i in range(repeats):
            w0, c0 = time.perf_counter(), time.process_time()
            simulate_trial((7 * i) % C.N_OBJECTS, C.SKINS[i % 2], prim, (5 * i) % C.N_ACTIONS, seed=i)
            walls.append(time.perf_counter() - w0)
            cpus.append(time.process_time() - c0)
        out[prim] = (statistics.median(walls), statistics.median(cpus))
    return out


def dataset(out_dir: Path, quick: bool, workers: int, primitive: str, skin: str) -> tuple[int, float, int, float]:
    objects = list(range(0, C.N_OBJECTS, 4)) if quick else list(range(C.N_OBJECTS))
    actions = list(range(C.N_ACTIONS))[:: (2 if quick else 1)]
    path = out_dir / f"bench_{skin}_{primitive}.h5"
    if path.exists():
        path.unlink()
    def cpu() -> float:
        ru = [resource.getrusage(w) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
        return sum(r.ru_utime + r.ru_stime for r in ru)

    t0, c0 = time.perf_counter(), cpu()
    generate_dataset(path, skin=skin, primitive=primitive, objects=objects, actions=actions, workers=workers)
    wall = time.perf_counter() - t0
    cpu_s = cpu() - c0
    good, errors = scan_raw(path, validate_data=False)
    n = len(objects) * len(actions)
    assert len(good) == n and not errors, (len(good), errors)
    size = path.stat().st_size
    path.unlink()
    return n, wall, size, cpu_s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="64-trial subset, extrapolated to 512")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--primitive", default="sliding", choices=C.PRIMITIVES)
    ap.add_argument("--skin", default="soft", choices=C.SKINS)
    ap.add_argument("--out-dir", default=None, help="where to write the temporary dataset (default: a temp dir)")
    args = ap.parse_args()

    rows = []
    for prim, (wall, cpu) in per_trial(args.repeats).items():
        rows.append((f"one 10 s trial, {prim} (median of {args.repeats}, 1 thread)", f"{wall:.3f} s wall / {cpu:.3f} s CPU", "<= 0.2 s"))
    with tempfile.TemporaryDirectory(dir=args.out_dir) as tmp:
        n, wall, size, cpu_s = dataset(Path(tmp), args.quick, args.workers, args.primitive, args.skin)
    full = C.N_OBJECTS * C.N_ACTIONS
    scale = full / n
    label = f"{args.skin}/{args.primitive}, {args.workers} workers"
    rows.append((f"dataset {n} trials ({label})", f"{wall:.1f} s wall, {cpu_s:.1f} CPU-s (simulate + write), {size / 1e9:.3f} GB ({size / n / 1e6:.2f} MB/trial)", ""))
    if n != full:
        rows.append((f"dataset {full} trials, extrapolated x{scale:.0f}", f"{wall * scale:.0f} s wall, {cpu_s * scale:.0f} CPU-s (= {cpu_s * scale / 2:.0f} s on 2 idle cores), {size * scale / 1e9:.2f} GB", "<= 180 s, <= 2 GB"))
    else:
        rows[-1] = (rows[-1][0], rows[-1][1] + f" (= {cpu_s / 2:.0f} s on 2 idle cores)", "<= 180 s, <= 2 GB")
    print(f"\nmachine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} (1 min)\n")
    print("| measurement | result | budget |")
    print("|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} |")


if __name__ == "__main__":
    main()
