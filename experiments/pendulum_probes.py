"""Supervised probes on the pendulum benchmark (docs/experiments/pendulum.md, "What a
reader that is told the parameters gets"): how well can the hidden parameters (w0, d) be read at
all from the benchmark's data, by readers that are TOLD them?

* ``frames_gru``: the project's supervised conv + GRU (``eval.baselines.GRURegressor``) on
  the noisy 28x28 frames and the actions, trained on the training sequences to (w0, d);
* ``lf_path``: the Latent Filter's own inference path (``GRURegressor(arch="latent_filter")``:
  encoder, fusion with the transition, the y LSTM, a linear head on y; the benchmark's
  sizes, n_z 8, n_y 4, and the y options given by ``--lf-option``) trained the same way:
  what this y can hold when it is told the parameters, with no reconstruction to shape z;
* with ``--state``: readers of the true angle trajectory with N(0, sigma^2) added, sigma the
  per-frame Cramer-Rao bound of one noisy frame (``angle_precision``, 0.004 rad): the best
  angle any frame reader can see. ``state_lstm`` (the same LSTM as the trajectory probes,
  on (cos, sin) of the angle plus the actions, TOLD the labels) and ``physics_ls``
  (``least_squares_parameters``: per-sequence least squares TOLD the equation of motion,
  not the labels; no training). The two say what the data allow a learned reader of this
  size and a reader with the true model structure;
* with ``--load`` (a pendulum run folder: ``experiments/pendulum.py`` or ``train.py
  experiment=pendulum``): a small LSTM trained on that frozen model's filtered trajectories
  (its last checkpoint), ``z_trajectory`` (q_filt means z_1..z_t plus
  the actions) and ``y_trajectory`` (q(y_t) means plus the actions): whether the filter's
  z carries the parameters over time even where its y does not hold them.

Held-out R^2 at the last frame (the same held-out sequences as experiments/pendulum.py:
``generate(8, seed + 1000)``; training ``generate(n_train, seed)``). Every reader sees each
parameter's label, so what it reaches bounds what an unsupervised y, read out by a
regressor fitted on the same training sequences, can be expected to show.

    python experiments/pendulum_probes.py --seed 0                      # frames only
    python experiments/pendulum_probes.py --seed 0 --n-train 128 --gru-epochs 25
    python experiments/pendulum_probes.py --seed 0 --no-frames --state
    python experiments/pendulum_probes.py --seed 0 --no-frames --lf-path --lf-option y_update=evidence
    python experiments/pendulum.py --seed 0 --n-train 32 --run-dir /tmp/run model.net.NAME=VALUE ...
    python experiments/pendulum_probes.py --seed 0 --load /tmp/run --no-frames
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from torch import nn

import yaml

from embodied_tactile.data.modality import load_modality
from embodied_tactile.data.pendulum import N_OBJECTS, angle_precision, generate, least_squares_parameters
from embodied_tactile.eval.baselines import GRURegressor
from embodied_tactile.jsonio import read_json
from embodied_tactile.run.threadenv import set_threads


def _targets(data) -> np.ndarray:
    return np.stack([data.w0, data.damping], -1)


def _r2(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    return 1.0 - ((pred - target) ** 2).mean(0) / target.var(0)


def supervised(train, test, epochs: int, seed: int, **kwargs) -> dict[str, np.ndarray]:
    """GRURegressor on the frames (``kwargs`` pick its architecture) -> R^2 (w0, d) on the
    training and the held-out sequences at the last frame. It regresses 4 outputs: (w0, d)
    twice, each column standardised on its own."""
    four = lambda d: np.concatenate([_targets(d)] * 2, -1)  # noqa: E731
    # whole sequences, raw inputs: the probe this page measured (GRUOptions are evaluate.py's crops)
    reg = GRURegressor(in_channels=1, action_dim=1, epochs=epochs, batch_size=16, seed=seed, window=None,
                       windows_per_trial=1, input_standardize=False, **kwargs)
    reg.fit(train.obs, train.actions, four(train))
    return {name: _r2(reg.predict(d.obs, d.actions)[:, -1, :2], _targets(d)) for name, d in
            (("train", train), ("held-out", test))}


def lf_path_kwargs(options: dict) -> dict:
    """GRURegressor arguments for the Latent Filter's inference path with the benchmark's
    network (n_z 8, n_y 4, 8 objects) and the y ``options``."""
    net = {"n_z": 8, "n_y": 4, "n_objects": N_OBJECTS, "obs_sigma": 0.1, **options}
    return {"arch": "latent_filter", "modality": load_modality("pendulum").to_config(), "latent_filter": net}


def lf_options(texts) -> dict:
    """``NAME=VALUE`` texts (values read as YAML) -> LatentFilter keywords; ``prior.X`` names go
    into the ``prior`` mapping (as ``model.net.prior.X`` in a config)."""
    kwargs: dict = {}
    for text in texts:
        name, sep, value = text.partition("=")
        if not sep or not name:
            raise SystemExit(f"--lf-option {text!r}: expected NAME=VALUE")
        head, _, key = name.partition(".")
        if key:
            kwargs.setdefault(head, {})[key] = yaml.safe_load(value)
        else:
            kwargs[name] = yaml.safe_load(value)
    return kwargs


def trajectory_lstm(x_tr: np.ndarray, t_tr: np.ndarray, x_te: np.ndarray, t_te: np.ndarray, epochs: int,
                    seed: int, hidden: int = 64, skip: int = 10) -> dict[str, np.ndarray]:
    """LSTM over feature trajectories (N, T, F) -> (w0, d), least squares on frames t > skip."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    mu, sd = t_tr.mean(0), t_tr.std(0)
    xt, tt = torch.from_numpy(x_tr.astype(np.float32)), torch.from_numpy(((t_tr - mu) / sd).astype(np.float32))
    lstm, head = nn.LSTM(x_tr.shape[-1], hidden, batch_first=True), nn.Linear(hidden, 2)
    opt = torch.optim.Adam([*lstm.parameters(), *head.parameters()], lr=3e-3, weight_decay=1e-4)
    for _ in range(epochs):
        for idx in np.array_split(rng.permutation(len(xt)), max(1, len(xt) // 16)):
            h, _ = lstm(xt[idx])
            loss = ((head(h[:, skip:]) - tt[idx, None]) ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    with torch.no_grad():
        pred = {n: head(lstm(torch.from_numpy(x.astype(np.float32)))[0][:, -1]).numpy() * sd + mu
                for n, x in (("train", x_tr), ("held-out", x_te))}
    return {"train": _r2(pred["train"], t_tr), "held-out": _r2(pred["held-out"], t_te)}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seed", type=int, default=None,
                   help="data seed (train seed, held-out seed + 1000) and init seed (default: --load's, else 0)")
    p.add_argument("--n-train", type=int, default=None,
                   help="training sequences per object (default: --load's, else 32)")
    p.add_argument("--gru-epochs", type=int, default=100, help="frames_gru epochs (100 x 256 / 16 = 1600 steps)")
    p.add_argument("--no-frames", action="store_true", help="skip frames_gru")
    p.add_argument("--lf-path", action="store_true", help="also train lf_path (the Latent Filter's inference path)")
    p.add_argument("--lf-option", action="append", default=[], metavar="NAME=VALUE",
                   help="LatentFilter y option for lf_path, e.g. y_update=evidence y_evidence_max=1 (repeatable)")
    p.add_argument("--state", action="store_true",
                   help="also the readers of the true angle + per-frame CRB noise: state_lstm and physics_ls")
    p.add_argument("--load", metavar="RUN", help="a pendulum run folder (experiments/pendulum.py): probe its z and y")
    p.add_argument("--probe-epochs", type=int, default=300)
    p.add_argument("--probe-seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    if a.load:  # the run's own data unless told otherwise (then checked against the run below)
        from omegaconf import OmegaConf

        saved = OmegaConf.load(f"{a.load}/config_resolved.yaml").data
        a.seed = int(saved.seed) if a.seed is None else a.seed
        a.n_train = int(saved.n_train) if a.n_train is None else a.n_train
    a.seed = 0 if a.seed is None else a.seed
    a.n_train = 32 if a.n_train is None else a.n_train
    set_threads(a.threads)
    train, test = generate(a.n_train, seed=a.seed), generate(8, seed=a.seed + 1000)
    rows = []
    if not a.no_frames:
        t0 = time.perf_counter()
        rows.append(("frames_gru", f"seed {a.seed}, {a.gru_epochs} epochs", supervised(train, test, a.gru_epochs, a.seed),
                     time.perf_counter() - t0))
    if a.lf_path:
        opts = lf_options(a.lf_option)
        t0 = time.perf_counter()
        rows.append(("lf_path", f"seed {a.seed}, {a.gru_epochs} epochs, {opts or 'defaults'}",
                     supervised(train, test, a.gru_epochs, a.seed, **lf_path_kwargs(opts)), time.perf_counter() - t0))
    if a.state:
        sigma = angle_precision()
        noisy = {n: d.theta + sigma * np.random.default_rng(a.seed + k).standard_normal(d.theta.shape)
                 for k, (n, d) in enumerate((("train", train), ("held-out", test)))}
        x = {n: np.concatenate([np.cos(noisy[n])[..., None], np.sin(noisy[n])[..., None], d.actions], -1)
             for n, d in (("train", train), ("held-out", test))}
        for s in a.probe_seeds:
            t0 = time.perf_counter()
            r = trajectory_lstm(x["train"], _targets(train), x["held-out"], _targets(test), a.probe_epochs, s)
            rows.append(("state_lstm", f"angle + N(0, {sigma:.4f}^2), probe seed {s}, {a.probe_epochs} epochs", r,
                         time.perf_counter() - t0))
        t0 = time.perf_counter()
        r = {n: _r2(np.stack(least_squares_parameters(noisy[n], d.actions), -1), _targets(d))
             for n, d in (("train", train), ("held-out", test))}
        rows.append(("physics_ls", f"angle + N(0, {sigma:.4f}^2), told the equation, no training", r,
                     time.perf_counter() - t0))
    if a.load:
        from pathlib import Path

        from hydra.utils import instantiate

        from embodied_tactile.eval.pendulum import split_latents
        from embodied_tactile.eval.runs import load_module, load_run

        run = load_run(Path(a.load), "last")
        data_cfg = run.cfg.data
        if int(data_cfg.seed) != a.seed or int(data_cfg.n_train) != a.n_train:
            raise SystemExit(f"{a.load}: the model was trained on seed {data_cfg.seed} data, {data_cfg.n_train} sequences "
                             f"per object; --seed is {a.seed}, --n-train {a.n_train}")
        dm = instantiate(data_cfg)
        dm.setup("fit")
        if not (np.array_equal(dm.data["train"].obs, train.obs) and np.array_equal(dm.data["test"].obs, test.obs)):
            raise SystemExit(f"{a.load}: the run's training / held-out sequences are not this script's "
                             f"(generate({a.n_train}, {a.seed}) / generate(8, {a.seed + 1000}))")
        lat = dict(zip(("train", "held-out"), split_latents(load_module(run), dm, "test")))
        steps = (read_json(Path(a.load) / "metrics.json").get("krr_final") or {}).get("step", "?")
        for key in ("z", "y"):
            x = {n: np.concatenate([lat[n][key], d.actions], -1) for n, d in (("train", train), ("held-out", test))}
            for s in a.probe_seeds:
                t0 = time.perf_counter()
                r = trajectory_lstm(x["train"], _targets(train), x["held-out"], _targets(test), a.probe_epochs, s)
                rows.append((f"{key}_trajectory", f"probe seed {s}, {a.probe_epochs} epochs", r,
                             time.perf_counter() - t0))
    print(f"pendulum probes: data seed {a.seed}, {a.n_train} training / 8 held-out sequences per object"
          + (f", model {a.load} ({steps} steps)" if a.load else ""))
    print("| reader | run | w0 train / held-out R^2 | d train / held-out R^2 | s |\n|---|---|---|---|---|")
    for name, run, r, dt in rows:
        print(f"| {name} | {run} | {r['train'][0]:.2f} / **{r['held-out'][0]:.2f}** | "
              f"{r['train'][1]:.2f} / **{r['held-out'][1]:.2f}** | {dt:.0f} |")


if __name__ == "__main__":
    main()
