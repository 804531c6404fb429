"""The population default's budget curve and levers, read from evaluated runs
(docs/experiments/population_budget.md).

    python experiments/population_budget.py RUN [RUN ...] [--json OUT]

Each RUN is a train.py folder of the population scene, evaluated beforehand on the
validation objects and on the test objects:

    python evaluate.py RUN held_out=val baselines=[] umap=false figures=false
    python evaluate.py RUN baselines=[untrained,handcrafted,mean] umap=false figures=false

The script prints one row per run and side (val, test) and reader: optimiser steps, the
learning-rate schedule, whether it is the population default (``experiment=population`` as
configured now: ``population_default`` in the JSON, which the main job's closing lines quote),
training wall time, the NMSE curve's mean (whole trajectory), its
last frame, its first frame, its maximum and the first frame at or below 0.5 (mean over
factors, the run's own read-out: ``alignment`` of its config).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from omegaconf import OmegaConf

SIDES = {"val": "evaluation-val", "test": "evaluation"}
#: what makes a run the population default (``experiment=population``) apart from its seed
DEFAULT_KEYS = ("recipe", "trainer.max_epochs", "model.lr_schedule", "model.optimizer.lr", "data.actions",
                "data.n_objects", "data.windows_per_epoch", "modality.name", "alignment.readout")


def _select(cfg, key):
    if key == "recipe":  # the objective's own options, each at its default where a run predates it
        from dataclasses import asdict

        from embodied_tactile.model.options import ContextOptions

        given = cfg.model.get("context")
        return {**asdict(ContextOptions()), **OmegaConf.to_container(given, resolve=True)} if given else None
    v = OmegaConf.select(cfg, key)
    return OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v


def population_default():
    """``configs/train.yaml`` composed with ``experiment=population``."""
    from embodied_tactile.run.config import compose

    return compose(["experiment=population"])


def rows(run_dir: Path, default) -> list[dict]:
    cfg = OmegaConf.load(run_dir / "config_resolved.yaml")
    is_default = all(_select(cfg, k) == _select(default, k) for k in DEFAULT_KEYS)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    out = []
    for side, folder in SIDES.items():
        path = run_dir / folder / "results.json"
        if not path.exists():
            continue
        for r in json.loads(path.read_text())["runs"]:
            curve = r.get("nmse_curve_overall") or []
            out.append({
                "run": run_dir.name, "side": side, "reader": r["method"], "seed": int(cfg.seed),
                "population_default": is_default,
                "steps": (metrics.get("krr_final") or {}).get("step"), "epochs": int(cfg.trainer.max_epochs),
                "lr_schedule": str(cfg.model.get("lr_schedule", "constant")),
                "actions": list(cfg.data.actions), "train_wall_s": metrics.get("train_wall_s"),
                "whole": r["nmse_trajectory_overall"], "last": r["nmse_last_step_overall"],
                "first_frame": curve[0] if curve else None, "max": max(curve) if curve else None,
                "first_below_half": r.get("first_frame_below_half"),
            })
    return out


def _f(v) -> str:
    return "–" if v is None else f"{v:.3f}" if isinstance(v, float) else str(v)


def table(all_rows: list[dict]) -> str:
    head = ["run", "side", "reader", "steps", "schedule", "train wall (s)", "whole", "last", "frame 1", "max",
            "first <= 0.5"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in all_rows:
        first = "never" if r["first_below_half"] is None else r["first_below_half"]
        wall = None if r["train_wall_s"] is None else round(float(r["train_wall_s"]))
        lines.append(f"| {r['run']} | {r['side']} | {r['reader']} | {r['steps']} | {r['lr_schedule']} | {_f(wall)} | "
                     f"{_f(r['whole'])} | {_f(r['last'])} | {_f(r['first_frame'])} | {_f(r['max'])} | {first} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--json", type=Path, default=None, help="every row as JSON")
    args = ap.parse_args(argv)
    default = population_default()
    all_rows = [r for run in args.runs for r in rows(run, default)]
    print(table(all_rows))
    if args.json:
        args.json.write_text(json.dumps(all_rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
