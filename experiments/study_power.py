"""What more seeds buy the study grid: the detectable difference of every Overall comparison
at n seeds a cell, from the spread the grid measured at its own n, and the training time
the added seeds cost.

    python experiments/study_power.py [--evaluation logs/study/evaluation] [--runs docs/generated/study_runs]

Reads the evaluation's ``table_comparisons.csv`` (``evaluate.py`` on the study folder) and the
archived runs' ``metrics.json`` (``train_wall_s``). A comparison's detectable difference
at n seeds is (t_0.975 + t_0.80)(df_n) x se_n (``verdicts.detectable_difference``) with the
standard error shrinking as 1 / sqrt(n) from the one measured: paired comparisons have
df_n = n - 1, Welch comparisons (equal seeds a side) 2 (n - 1), their df at equal spreads.
The spread is the one observed at 3 seeds, itself uncertain by about a third. The training
time is the median run's ``train_wall_s`` (one torch thread, beside another lane) times the
runs added.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import statistics
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TARGETS = (0.05, 0.03)


def overall_comparisons(table: Path) -> list[dict]:
    """Every Overall comparison with a detectable difference: pairing, n, detectable."""
    with table.open() as fh:
        rows = list(csv.reader(line for line in fh if not line.startswith("#")))
    head, out = rows[0], []
    for r in rows[1:]:
        row = dict(zip(head, r))
        if row["score"] != "overall" or not row["detectable"]:
            continue
        n = min(int(x) for x in row["n"].split("/"))
        out.append({"pairing": row["pairing"], "n": n, "detectable": float(row["detectable"])})
    return out


def _factor(df: float) -> float:
    from scipy.stats import t

    return float(t.ppf(0.975, df) + t.ppf(0.80, df))


def detectable_at(c: dict, n: int) -> float:
    """The comparison's detectable difference at ``n`` seeds a cell."""
    n0 = c["n"]
    if c["pairing"].startswith("paired"):
        df0, df = n0 - 1, n - 1
    else:  # Welch with equal seeds a side: df about 2 (n - 1) at equal spreads
        df0, df = 2 * (n0 - 1), 2 * (n - 1)
    return c["detectable"] / _factor(df0) * _factor(df) * math.sqrt(n0 / n)


def run_times(runs: Path) -> list[float]:
    return [float(json.loads(m.read_text())["train_wall_s"]) for m in sorted(runs.glob("*/*/metrics.json"))]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--evaluation", type=Path, default=REPO / "logs" / "study" / "evaluation")
    ap.add_argument("--runs", type=Path, default=REPO / "docs" / "generated" / "study_runs")
    ap.add_argument("--cells", type=int, default=24)
    ap.add_argument("--seeds", nargs="+", type=int, default=[3, 4, 5, 6, 8, 10, 12])
    args = ap.parse_args(argv)
    comps = overall_comparisons(args.evaluation / "table_comparisons.csv")
    times = run_times(args.runs)
    if not comps or not times:
        sys.exit(f"no Overall comparisons in {args.evaluation} or no runs in {args.runs}")
    n0 = min(c["n"] for c in comps)
    run_s = statistics.median(times)
    print(f"{len(comps)} Overall comparisons measured at {n0} seeds a cell; {len(times)} runs, "
          f"median training {run_s:.0f} s a run (one thread)\n")
    print("| seeds a cell | median detectable | comparisons at most 0.05 | at most 0.03 | runs added | training added (one thread) |")
    print("|---|---|---|---|---|---|")
    for n in args.seeds:
        det = [detectable_at(c, n) for c in comps]
        added = max(n - n0, 0) * args.cells
        print(f"| {n} | {statistics.median(det):.4f} | {sum(d <= TARGETS[0] for d in det)} of {len(det)} | "
              f"{sum(d <= TARGETS[1] for d in det)} of {len(det)} | {added} | {added * run_s / 3600:.1f} h |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
