"""The read-out over interaction time, screened on the validation objects
(docs/experiments/readout_over_time.md).

    python experiments/readout_screen.py RUN [RUN ...] [--held-out val] [--out docs/experiments/readout_screen.json]

For each RUN (a train.py folder; the population scene's for objects never touched) the
script reads, on the training side and on the held-out side (``--held-out val``: the
validation objects, which pick settings; ``test`` only to report a chosen setting), the y
latents of the trained network (final weights), of the same network untrained (the run's
architecture and seed at step 0) and the hand-crafted physical features, then scores every
candidate read-out below on each of them with the project's alignment (``fit_alignment``;
the run's own ``alignment`` for everything not named). Per reader and candidate it prints
the NMSE curve's mean (whole trajectory), its last frame, its first frame, its maximum and
the first frame at or below 0.5 (mean over factors; 1 = the training mean).

Candidates (``CANDIDATES``):

* ``paper``: one alignment fitted on the final tenth of each training trial, applied to
  every frame (the paper's protocol, ``readout=final_segment``);
* ``paper_bounded``: the same, each prediction clipped to the training targets' range;
* ``whole_trial``: one alignment with its rows drawn from every frame of the training
  trials (``final_segment=1.0``);
* ``per_time_<k>``: a probe per span of ``k`` equal spans (``readout=per_time``);
* ``per_time_10_bounded``: 10 spans, each prediction clipped to the training targets' range;
* ``per_time_10_dense``: 10 spans, 12 rows per training sequence and span instead of 4.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from embodied_tactile.eval.baselines import handcrafted_features
from embodied_tactile.eval.krr import alignment_kwargs, fit_alignment
from embodied_tactile.eval.metrics import nmse_over_time, overall
from embodied_tactile.eval.pipeline import parse_options, run_alignment, run_targets
from embodied_tactile.eval.results import first_below
from embodied_tactile.eval.runs import (DataCache, collect_split, data_config, discover, load_module, trial_names,
                                        untrained_module)
from embodied_tactile.eval.targets import encode_split
from embodied_tactile.options.alignment import AlignmentOptions, alignment_options
from embodied_tactile.data.modality import Modality
from embodied_tactile.run.threadenv import set_threads

CANDIDATES = {
    "paper": {"readout": "final_segment"},
    "paper_bounded": {"readout": "final_segment", "bounded": True},
    "whole_trial": {"readout": "final_segment", "final_segment": 1.0},
    "per_time_5": {"readout": "per_time", "time_bins": 5},
    "per_time_10": {"readout": "per_time", "time_bins": 10},
    "per_time_20": {"readout": "per_time", "time_bins": 20},
    "per_time_10_bounded": {"readout": "per_time", "time_bins": 10, "bounded": True},
    "per_time_10_dense": {"readout": "per_time", "time_bins": 10, "frames_per_sequence": 12},
}
READERS = ("latent_filter", "untrained", "handcrafted")


def reader_inputs(run_dir: Path, held_out: str) -> tuple[dict, dict, dict, str]:
    """Per reader (n, T, d) inputs of the training side and the held-out side, the factors
    (encoded as the run's targets), the run's alignment and its split kind; kept in
    ``RUN/readout_inputs-<held_out>.npz`` (the final weights' latents) for the next call."""
    stash = run_dir / f"readout_inputs-{held_out}.npz"
    if stash.exists():
        z = np.load(stash, allow_pickle=True)
        return z["train"].item(), z["held"].item(), z["alignment"].item(), str(z["split"])
    tr, te, alignment, split = _reader_inputs(run_dir, held_out)
    np.savez(stash, train=np.array(tr, dtype=object), held=np.array(te, dtype=object),
             alignment=np.array(alignment, dtype=object), split=split)
    return tr, te, alignment, split


def _reader_inputs(run_dir: Path, held_out: str) -> tuple[dict, dict, dict, str]:
    opts = parse_options([f"held_out={held_out}", "torch_threads=1"])
    _, (run,), _ = discover(run_dir, "last")
    cache = DataCache()
    key, dm = cache.get(data_config(run, opts))
    model = load_module(run)
    floor = untrained_module(run, model)
    targets = run_targets(run.cfg, opts)
    sides = {}
    for side in ("train", held_out):
        batches, names = cache.batches(key, dm, side), trial_names(dm, side)
        trained, _ = collect_split(model, batches, names, "y")
        untrained, _ = collect_split(floor, batches, names, "y")
        feats, _ = handcrafted_features(trained["obs"], trained["actions"], Modality.from_config(run.cfg.modality).channels)
        enc = encode_split(trained, targets)
        sides[side] = {"latent_filter": trained["y"], "untrained": untrained["y"], "handcrafted": feats,
                       "factors": enc["factors"], "object_id": enc["object_id"], "seq_id": enc["seq_id"]}
    return sides["train"], sides[held_out], run_alignment(run.cfg, opts), str(dm.split)


def read(candidate: dict, x_tr, f_tr, x_te, alignment: AlignmentOptions, split: str, objects) -> np.ndarray:
    """Predictions (n_te, T, K) of one candidate read-out."""
    cand = dict(candidate)
    bounded = cand.pop("bounded", False)
    align = fit_alignment(x_tr, f_tr, **alignment_kwargs(alignment_options(alignment, cand), split, objects))
    pred = align.predict(x_te)
    if bounded:
        pred = np.clip(pred, np.nanmin(f_tr, axis=0), np.nanmax(f_tr, axis=0))
    return pred


def scores(curve_per_factor: np.ndarray) -> dict:
    """The numbers reported per reader (mean over factors)."""
    curve = np.array([overall(row) for row in curve_per_factor])
    return {"whole": float(curve.mean()), "last": float(curve[-1]), "first_frame": float(curve[0]),
            "max": float(curve.max()), "first_below_half": first_below(curve, 0.5)}


def screen(run_dir: Path, held_out: str, candidates=tuple(CANDIDATES), readers=READERS) -> list[dict]:
    tr, te, alignment, split = reader_inputs(run_dir, held_out)
    rows = []
    for reader in readers:
        for name in candidates:
            cand = CANDIDATES[name]
            pred = read(cand, tr[reader], tr["factors"], te[reader], alignment, split, tr["object_id"])
            rows.append({"run": str(run_dir), "held_out": held_out, "reader": reader, "readout": name,
                         **scores(nmse_over_time(te["factors"], pred))})
            print(_row(rows[-1]), flush=True)
    return rows


def _row(r: dict) -> str:
    first = "never" if r["first_below_half"] is None else r["first_below_half"]
    return (f"| {Path(r['run']).name} | {r['reader']} | {r['readout']} | {r['whole']:.3f} | {r['last']:.3f} | "
            f"{r['first_frame']:.3f} | {r['max']:.3f} | {first} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--held-out", default="val", choices=("val", "test"))
    ap.add_argument("--out", type=Path, default=None, help="JSON file for every row")
    ap.add_argument("--candidates", nargs="+", default=list(CANDIDATES), choices=list(CANDIDATES))
    ap.add_argument("--readers", nargs="+", default=list(READERS), choices=list(READERS))
    args = ap.parse_args(argv)
    import torch

    set_threads(1)
    print("| run | reader | read-out | whole | last | frame 1 | max | first <= 0.5 |")
    print("|---|---|---|---|---|---|---|---|")
    rows = [r for run in args.runs for r in screen(run, args.held_out, args.candidates, args.readers)]
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
