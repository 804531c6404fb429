"""Where does each modality's information go? Upper bounds per modality, side by side.

    python experiments/modality_bounds.py --data-dir /tmp/mod9/data
    python experiments/modality_bounds.py --data-dir /tmp/mod9/data --primitive sliding
    python experiments/modality_bounds.py --data-dir /tmp/mod9/data --modalities acc --gru-epochs 5
    python experiments/modality_bounds.py --data-dir /tmp/mod9/data --preprocess acc_combine=magnitude

Scene: the default one (soft skin, pressing) at the default budget's size, 32 objects
x 4 actions (indices 2, 6, 10, 14), prepared by the project's preparation stage
(``TactileDataModule.prepare_data``: simulates missing trials into ``<data-dir>/raw``,
builds the caches), split by ``split_trials`` with ``--seed`` (the paper's trial split;
the baselines train on the train split, like evaluate.py, and are scored on the test split).
Targets: ``design_rank`` (evaluate.py's default). ``--population N``: the population scene
instead (``experiment=population``: N training objects, the object split, actions 6 and 14,
physical targets), e.g. ``--population 256 --modalities multi_l --gru-max-batches 30
--gru-epochs 16`` is evaluate.py's GRU baseline of a population run.

For each of the six modalities (channels from ``configs/modality/<name>.yaml``):

* ``gru``: the supervised GRU regressor (``eval.baselines.evaluate_gru``, evaluate.py's
  budget: 50-frame windows x 6 per trial, ``--gru-epochs``, seed ``--seed``) on that
  modality's PREPROCESSED inputs: what a network can read from exactly what the Latent
  Filter sees;
* ``handcrafted_krr``: the hand-crafted features + KRR alignment (``evaluate_handcrafted``)
  on the same inputs;
* with ``--lf-supervised``, ``latent_filter_supervised``: the Latent Filter's own inference
  path (encoder, fusion with the transition, y LSTM; default sizes) with a linear head on y,
  trained supervised like the GRU for ``--lf-epochs`` (default 16: the Latent Filter's
  default budget of 480 optimiser steps): what the unsupervised model's y could hold at
  its budget, which separates the objective from the architecture and the budget;
* with ``--lf-codes``, ``latent_filter_codes``: the same path and budget trained to output
  a fixed random N(0, 0.5^2) code per training object (``eval.baselines.
  evaluate_code_regression``), its outputs aligned to the factors by the KRR: what the
  label-conditioned prior's pull onto fixed object codes could put into y, were it a
  regression (docs/experiments/object_codes.md).

For acc also two probes on the RAW 700 Hz accelerometer signal (``tactile/acc`` of the raw
HDF5), features -> the same KRR alignment:

* ``raw_xyz_krr``: per-axis (x, y, z, tool frame) log band energies in 1-15, 15-50,
  50-150, 150-340 Hz and the per-axis spectral centroid, averaged over the 16 nodes;
* ``raw_mag_krr``: the same on |a| (what ``acc_combine=magnitude`` kept).

Every raw feature is causal like the hand-crafted ones (a running mean of per-frame band
energies over frames 0..t), so it is scored over the whole trajectory and at the last frame
like every other method. Prints one Markdown table: held-out NMSE per factor and overall,
whole trajectory / last frame. ``--json`` writes the summaries.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from embodied_tactile.options.alignment import alignment_options
from embodied_tactile.run.threadenv import set_threads

os.environ.setdefault("OMP_NUM_THREADS", "1")

MODALITIES = ("acc", "fsr_t", "fsr_b", "fsr_tb", "multi_e", "multi_l")
ALL_CHANNELS = ("acc", "fsr_t", "fsr_b")
BANDS_HZ = ((1.0, 15.0), (15.0, 50.0), (50.0, 150.0), (150.0, 340.0))


def load_split(data_dir: Path, skin: str, primitive: str, seed: int, actions, sim_workers: int,
               preprocess: dict | None = None, population: int | None = None):
    """(train, test) dicts with obs over ALL_CHANNELS, actions, factors, ids. ``population``:
    the simulated population with that many training objects under the object split
    (population and simulator seed 0, targets physical); else the catalogue under the trial
    split (``seed``, targets design_rank)."""
    import torch

    from embodied_tactile.data.datamodule import TactileDataModule
    from embodied_tactile.eval.targets import encode_split

    dm = TactileDataModule.from_config(data_dir=str(data_dir), skin=skin, primitive=primitive, channels=ALL_CHANNELS,
                           actions=list(actions), sim_seed=0, sim_workers=sim_workers, preprocess=preprocess or {},
                           preprocess_workers=sim_workers,
                           split_seed=seed, split_file=None, batch_size=16,
                           **({} if population is None else dict(objects="population", n_objects=population,
                                                                 population_seed=0, split="object")))
    dm.prepare_data()
    dm.setup("fit")
    out = []
    for ds, loader in ((dm.train_set, dm.train_eval_dataloader()), (dm.test_set, dm.test_dataloader())):
        batches = list(loader)
        d = {k: torch.cat([b[k] for b in batches]).numpy() for k in ("obs", "actions", "factors", "object_id",
                                                                        "action_index")}
        d["seq_id"] = np.asarray([t.name for t in ds.trials])
        out.append(encode_split(d, targets_of(population)))
    raw_paths = [str(p) for p in dm.raw_paths]
    return out[0], out[1], raw_paths


def targets_of(population: int | None) -> str:
    return "design_rank" if population is None else "physical"


def _frame_energy(x: np.ndarray, fs: float, n_frames: int, frame_rate: float) -> np.ndarray:
    """x (N, ...) -> mean square per 1/frame_rate frame, (n_frames, ...)."""
    per = int(round(fs / frame_rate))
    n = min(len(x), per * n_frames)
    e = (x[:n] ** 2).reshape(n // per, per, *x.shape[1:]).mean(1)
    if len(e) < n_frames:
        e = np.concatenate([e, np.repeat(e[-1:], n_frames - len(e), 0)])
    return e


def raw_acc_features(acc: np.ndarray, fs: float, n_frames: int = 300, frame_rate: float = 30.0,
                     magnitude: bool = False) -> np.ndarray:
    """Raw accelerometer trial (N, 4, 4, 3) g -> causal features (n_frames, k): per axis (or
    |a|) log10 running-mean band energies in BANDS_HZ (node average) and the band-energy
    centroid (Hz)."""
    from scipy import signal

    a = np.asarray(acc, dtype=np.float64).reshape(len(acc), 16, 3)
    x = np.linalg.norm(a, axis=-1)[..., None] if magnitude else a
    x = x - x.mean(0, keepdims=True)  # static part (gravity, offsets)
    cum = np.arange(1, n_frames + 1)[:, None]
    energies = []
    for lo, hi in BANDS_HZ:
        sos = signal.butter(4, [lo, min(hi, 0.49 * fs)], btype="band", fs=fs, output="sos")
        y = signal.sosfilt(sos, x, axis=0)  # causal
        e = _frame_energy(y, fs, n_frames, frame_rate).mean(1)  # (T, axes): node average
        energies.append(np.cumsum(e, 0) / cum)
    e = np.stack(energies, -1)  # (T, axes, bands)
    centres = np.array([np.sqrt(lo * hi) for lo, hi in BANDS_HZ])
    cent = (e * centres).sum(-1) / (e.sum(-1) + 1e-30)
    feats = np.concatenate([np.log10(e + 1e-12).reshape(n_frames, -1), cent], 1)
    return feats


def raw_probe(train, test, raw_paths, *, magnitude: bool, alignment, meta: dict, targets: str):
    from embodied_tactile.eval.results import Results
    from embodied_tactile.eval.krr import alignment_kwargs, fit_alignment
    from embodied_tactile.data.rawformat import read_trial

    def feats(split):
        out = []
        for name in split["seq_id"]:
            for p in raw_paths:
                try:
                    tr = read_trial(p, str(name), fields=("t", "acc"))
                    break
                except Exception:  # noqa: BLE001 - the trial lives in another raw file
                    continue
            else:
                raise FileNotFoundError(f"trial {name} in none of {raw_paths}")
            fs = float(tr.attrs.get("fs_tactile", 700.0))
            out.append(raw_acc_features(tr.acc, fs, n_frames=split["obs"].shape[1], magnitude=magnitude))
        return np.stack(out)

    f_tr, f_te = feats(train), feats(test)
    align = fit_alignment(f_tr, train["factors"], ids=train["seq_id"], **alignment_kwargs(alignment, "trial", None))
    pred = align.predict(f_te, ids=test["seq_id"])
    return Results(pred, test["factors"], test["object_id"], test["action_index"],
                   method="raw_mag_krr" if magnitude else "raw_xyz_krr", n_train=len(f_tr),
                   params={"alignment": align.params}, seq_id=test["seq_id"], targets=targets, **meta)


def subset(split: dict, channels) -> dict:
    idx = [ALL_CHANNELS.index(c) for c in channels]
    out = dict(split)
    out["obs"] = split["obs"][:, :, idx]
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", type=Path, default=Path("/tmp/modality_bounds/data"))
    ap.add_argument("--skin", default="soft")
    ap.add_argument("--primitive", default="pressing")
    ap.add_argument("--actions", type=int, nargs="+", default=None,
                    help="action indices (default 2 6 10 14; with --population 6 14, the population scene's)")
    ap.add_argument("--population", type=int, default=None, metavar="N",
                    help="the population scene (experiment=population) with N training objects, object split, "
                         "physical targets, instead of the 32-object catalogue")
    ap.add_argument("--modalities", nargs="+", default=list(MODALITIES), choices=MODALITIES)
    ap.add_argument("--seed", type=int, default=0, help="split seed and GRU seed")
    ap.add_argument("--gru-epochs", type=int, default=20)
    ap.add_argument("--gru-window", default="50", help="GRU training crop in frames; 'none' = whole trials")
    ap.add_argument("--gru-standardize", action="store_true",
                    help="GRU input_standardize: each channel standardised by its training-set mean / std")
    ap.add_argument("--gru-windows-per-trial", type=int, default=6, help="GRU crops per trial and epoch")
    ap.add_argument("--gru-max-batches", type=int, default=None,
                    help="GRU batches per epoch at most (evaluate.py's population runs: 30, 480 steps in 16 epochs)")
    ap.add_argument("--lf-supervised", action="store_true",
                    help="also train the Latent Filter's inference path supervised (method latent_filter_supervised)")
    ap.add_argument("--lf-codes", action="store_true",
                    help="also train that path on random object codes, KRR to the factors (method latent_filter_codes)")
    ap.add_argument("--lf-epochs", type=int, default=16,
                    help="epochs of --lf-supervised / --lf-codes (16 = the default budget)")
    ap.add_argument("--methods", nargs="*", default=["gru", "handcrafted_krr"], choices=["gru", "handcrafted_krr"],
                    help="which of the GRU and hand-crafted rows to run (default both)")
    ap.add_argument("--no-raw", action="store_true", help="skip the raw-signal probes")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--preprocess", nargs="*", default=[], metavar="KEY=VALUE",
                    help="PreprocessConfig overrides, e.g. acc_combine=magnitude (the previous acc path)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)

    import torch

    set_threads(1)
    from embodied_tactile.eval.baselines import evaluate_code_regression, evaluate_gru, evaluate_handcrafted
    from embodied_tactile.constants import FACTOR_NAMES
    from embodied_tactile.data.modality import load_modality

    t0 = time.perf_counter()
    pre = dict(kv.split("=", 1) for kv in args.preprocess)
    actions = args.actions or ([2, 6, 10, 14] if args.population is None else [6, 14])
    targets = targets_of(args.population)
    train, test, raw_paths = load_split(args.data_dir, args.skin, args.primitive, args.seed, actions, args.workers,
                                        pre, args.population)
    print(f"# scene skin={args.skin} primitive={args.primitive} actions={actions}: {len(train['seq_id'])} train / "
          f"{len(test['seq_id'])} test trials (split seed {args.seed}); data {time.perf_counter() - t0:.0f} s",
          file=sys.stderr)
    alignment = alignment_options(dict(final_segment=0.1, frames_per_sequence=4, cv=5, n_threads=1))  # evaluate.yaml's
    gru_window = None if args.gru_window.lower() == "none" else int(args.gru_window)
    gru = dict(epochs=args.gru_epochs, window=gru_window, windows_per_trial=args.gru_windows_per_trial, batch_size=16,
               hidden=64, lr=1e-3, seed=args.seed, input_standardize=args.gru_standardize,
               max_batches_per_epoch=args.gru_max_batches)
    rows = []
    for name in args.modalities:
        chans = list(load_modality(name).channels)
        tr, te = subset(train, chans), subset(test, chans)
        meta = dict(modality=name, skin=args.skin, primitive=args.primitive)
        lf = dict(gru, arch="latent_filter", modality=name, epochs=args.lf_epochs)
        extra = ["latent_filter_supervised"] * args.lf_supervised + ["latent_filter_codes"] * args.lf_codes
        for method in (*args.methods, *extra):
            t1 = time.perf_counter()
            if method == "handcrafted_krr":
                res = evaluate_handcrafted(tr, te, chans, alignment=alignment, **meta)
            elif method == "latent_filter_codes":
                res = evaluate_code_regression(tr, te, gru=lf, alignment=alignment, **meta)
            else:
                res = evaluate_gru(tr, te, gru=gru if method == "gru" else lf, **meta)
            rows.append((res.summary(), time.perf_counter() - t1))
            print(f"# {name} {method}: {rows[-1][0]['nmse_trajectory_overall']:.3f} ({rows[-1][1]:.0f} s)",
                  file=sys.stderr)
        if name == "acc" and not args.no_raw:
            for mag in (False, True):
                t1 = time.perf_counter()
                res = raw_probe(train, test, raw_paths, magnitude=mag, alignment=alignment, meta=meta, targets=targets)
                rows.append((res.summary(), time.perf_counter() - t1))
                print(f"# acc {res.method}: {rows[-1][0]['nmse_trajectory_overall']:.3f}", file=sys.stderr)

    short = {"spatial_frequency": "sf", "amplitude": "amp", "stiffness": "stiff", "heterogeneity": "het"}
    head = [short.get(f, f) for f in FACTOR_NAMES] + ["overall"]
    scene = "catalogue, trial split" if args.population is None else f"population of {args.population}, object split"
    print(f"\nHeld-out NMSE, whole trajectory / last frame ({scene}, targets {targets}), skin={args.skin}, "
          f"primitive={args.primitive}, preprocess {pre or 'default'}, {len(train['seq_id'])} train / {len(test['seq_id'])} test trials, "
          f"split seed {args.seed}, GRU seed {args.seed} ({args.gru_epochs} epochs, window {gru_window} x "
          f"{args.gru_windows_per_trial} per trial, at most {args.gru_max_batches} batches per epoch, "
          f"input_standardize {args.gru_standardize}"
          + (f"; latent_filter_supervised / _codes {args.lf_epochs} epochs, same windows"
             if args.lf_supervised or args.lf_codes else "") + ")\n")
    print("| modality | method | " + " | ".join(head) + " | s |")
    print("|---|---|" + "---|" * (len(head) + 1))
    for s, dt in rows:
        cells = [f"{s['nmse_trajectory'][f]:.2f} / {s['nmse_last_step'][f]:.2f}" for f in FACTOR_NAMES]
        cells.append(f"**{s['nmse_trajectory_overall']:.3f} / {s['nmse_last_step_overall']:.3f}**")
        print(f"| {s['modality']} | {s['method']} | " + " | ".join(cells) + f" | {dt:.0f} |")
    if args.json:
        args.json.write_text(json.dumps([s for s, _ in rows], indent=1, default=str))


if __name__ == "__main__":
    main()
