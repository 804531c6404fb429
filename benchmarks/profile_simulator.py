"""Where one simulated trial spends its time: the lines of ``sim.trial.simulate_trial`` by share.

    pip install line_profiler                                  # not a dependency of the project
    python benchmarks/profile_simulator.py [--trials 6] [--primitive pressing] [--top 12]

One thread (BLAS/OpenMP pinned), a warm-up trial first (surface caches), then ``--trials``
trials of soft-skin ``--primitive`` over several objects and parameter sets. Prints a Markdown
table of the ``--top`` lines by time with their share of the function's total, and the mean
time per trial (line_profiler's overhead included: compare shares, not absolute times).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import linecache  # noqa: E402
import sys  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=6)
    ap.add_argument("--primitive", default="pressing")
    ap.add_argument("--top", type=int, default=12)
    args = ap.parse_args(argv)
    try:
        from line_profiler import LineProfiler
    except ImportError:
        sys.exit("profile_simulator.py needs line_profiler: pip install line_profiler")
    from embodied_tactile.sim import trial as T

    T.simulate_trial(3, "soft", args.primitive, 6)  # warm-up: surface and spline caches
    lp = LineProfiler(T.simulate_trial)
    run = lp(T.simulate_trial)
    for i in range(args.trials):
        run(5 + i, "soft", args.primitive, (2 * i) % 16)
    stats = lp.get_stats()
    (fn_key, timings), = ((k, v) for k, v in stats.timings.items() if k[2] == "simulate_trial")
    total = sum(t for _, _, t in timings)
    rows = sorted(timings, key=lambda r: -r[2])[: args.top]
    print(f"simulate_trial, soft {args.primitive}: {total * stats.unit / args.trials * 1e3:.1f} ms per trial "
          f"(mean of {args.trials}, line_profiler's overhead included)\n")
    print("| line | ms per trial | share | code |")
    print("|---|---|---|---|")
    for line, _, t in rows:
        code = linecache.getline(fn_key[0], line).strip().replace("|", "\\|")
        print(f"| {line} | {t * stats.unit / args.trials * 1e3:.1f} | {t / total:.1%} | `{code[:90]}` |")


if __name__ == "__main__":
    main()
