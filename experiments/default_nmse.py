"""Held-out NMSE of the default scene against training choices (error against run time).

    python experiments/default_nmse.py                      # every variant below, in turn
    python experiments/default_nmse.py --only default whole_trials
    python experiments/default_nmse.py --only default --seeds 0 1     # speed targets 2 and 5 (docs/experiments/speed_levers.md)
    python experiments/default_nmse.py --work /tmp/nmse --data-dir data -- trainer.max_epochs=8

Each variant is one ``python train.py <overrides>`` run of the embedded default scene
(multi_l, soft skin, pressing; 80 training / 16 validation / 32 held-out sequences) in its own folder under
``--work``, all sharing one data folder (simulated once). The KRR callback's last entry in
``krr_history.jsonl`` gives the held-out NMSE on the y latent (whole trajectory and last
frame, mean over the four factors) and the training wall time; ``metrics.json`` the training
phase and the peak memory. About 3.5 minutes per variant and seed on a quiet 2-core box; run it
alone (other jobs inflate every time). Prints one Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: name -> train.py overrides on top of the default (the typed defaults, no experiment)
VARIANTS: dict[str, list[str]] = {
    "default": [],  # direct y posterior, 6 x 50-frame windows, y_weight 10
    "previous_default": ["data.train_window=null", "data.windows_per_trial=1", "data.windows_per_epoch=null", "annealing.schedule.y_weight=1.0"],
    "whole_trials": ["data.train_window=null", "data.windows_per_trial=1", "data.windows_per_epoch=null"],
    "evidence_whole": ["model.net.y_update=evidence", "data.train_window=null", "data.windows_per_trial=1", "data.windows_per_epoch=null"],
    "evidence_windows": ["model.net.y_update=evidence"],
    "y_weight_1": ["annealing.schedule.y_weight=1.0"],
    "prior_no_action": ["model.net.prior.action_term=false"],
}


def run(name: str, overrides: list[str], work: Path, data_dir: Path, extra: list[str], seed: int) -> dict:
    run_dir = work / name / f"seed{seed}"
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, str(REPO / "train.py"), f"paths.data_dir={data_dir}",
                           f"hydra.run.dir={run_dir}", "resume=false", "logger=none", f"seed={seed}",
                           *overrides, *extra],
                          cwd=REPO, env=dict(os.environ, WANDB_MODE="disabled"), capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        lines = [ln for ln in proc.stderr.splitlines() if "Error" in ln or "Exception" in ln]
        return {"name": name, "seed": seed, "error": lines[-1:] or [f"exit code {proc.returncode}"], "wall_s": wall}
    rows = [json.loads(line) for line in (run_dir / "krr_history.jsonl").read_text().splitlines() if line.strip()]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    last = rows[-1]
    return {"name": name, "seed": seed, "overrides": " ".join(overrides) or "(default)", "epochs": last["epoch"] + 1,
            "steps": last["step"], "train_s": metrics["train_wall_s"], "wall_s": wall,
            "data_prepare_s": metrics.get("data_prepare_s"), "peak_rss_gb": metrics["peak_rss_bytes"] / 1e9,
            "points": len(rows), "t0_point": rows[0].get("initial", False) and rows[0]["train_wall_time_s"] == 0.0,
            "callback_fraction": last["callback_fraction"],
            "traj": last["nmse_overall"], "last": last["nmse_last_overall"],
            "curve": [(r["train_wall_time_s"], r["nmse_overall"], r["nmse_last_overall"]) for r in rows]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_default_nmse"))
    ap.add_argument("--data-dir", type=Path, help="data folder to share (default: <work>/data)")
    ap.add_argument("--only", nargs="*", choices=sorted(VARIANTS), help="variants to run (default: all)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="seeds to run each variant with")
    ap.add_argument("extra", nargs="*", help="overrides appended to every run (after --)")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    data_dir = args.data_dir or args.work / "data"
    results = [run(n, VARIANTS[n], args.work, data_dir, args.extra, seed)
               for n in (args.only or list(VARIANTS)) for seed in args.seeds]
    print("\nHeld-out NMSE on y (mean over 4 factors; 0 = perfect, 1 = train mean), default scene; train s = the")
    print("training phase (metrics.json train_wall_s: fit + held-out ELBO, data preparation apart), peak RSS of the")
    print("train.py process, KRR points in krr_history.jsonl (t = 0 row included) and the callback's share of training")
    print("| variant | seed | overrides | epochs | optimiser steps | train s | data prep s | peak RSS GB | KRR points (t = 0) "
          "| callback % | NMSE traj | NMSE last |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        if "error" in r:
            print(f"| {r['name']} | {r['seed']} | FAILED: {r['error'][0]} | | | | | | | | | |")
            continue
        print(f"| {r['name']} | {r['seed']} | {r['overrides']} | {r['epochs']} | {r['steps']} | {r['train_s']:.1f} | "
              f"{r['data_prepare_s']:.1f} | {r['peak_rss_gb']:.2f} | {r['points']} ({'yes' if r['t0_point'] else 'no'}) | "
              f"{100 * r['callback_fraction']:.1f} | {r['traj']:.4f} | {r['last']:.4f} |")
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f} (figures are for a quiet box only if this is low)")
    print("\nNMSE against training wall time (s: traj / last) per variant:")
    for r in results:
        if "curve" in r:
            print(f"  {r['name']} seed {r['seed']}: " + ", ".join(f"{t:.0f}s: {a:.3f}/{b:.3f}" for t, a, b in r["curve"]))
    (args.work / "results.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
