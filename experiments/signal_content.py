"""Do the simulated signals carry the population's factors? A reader built from physics, on
objects never touched.

Per object (both pressing actions side by side), three groups of summary features from the
raw trial, no learning in them:

- ``peak``: log peak total force of each FSR layer (stiffness and amplitude set how hard the
  object pushes back at a given depth);
- ``acc``: log RMS of each accelerometer axis (16 sensors x 3 axes);
- ``spec``: the top FSR layer's image at peak force: its radial power spectrum (9 rings of
  width 0.079 cycles per taxel; an empty ring is 0; normalised) and its contact area at 10 / 30 / 50 % of its maximum (the surface's spatial
  frequency sets the width of the contact patches).

Each group, and all three together, goes into an RBF kernel ridge regression fitted on the
training objects of the population (``sim.population`` roles), with the ridge and the
length scale chosen per factor on the validation objects; NMSE is on the test objects
(normalised by the training targets' variance; the mean predictor sits at ~1). Targets:
spatial frequency (1/m), log amplitude, log10 bulk Young's modulus, heterogeneity (0/1).
Nested training sets: the first N training objects, as ``data.n_objects=N`` uses.

    python experiments/signal_content.py --raw <data_dir>/raw/population0_soft_pressing.h5

The raw file is the population scene's (``python train.py experiment=population
data.n_objects=512`` simulates it, or :func:`embodied_tactile.sim.dataset.generate_dataset`).
Measured results: docs/experiments/signal_content.md.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

FACTORS = ("spatial_frequency", "log_amplitude", "log10_bulk_E", "heterogeneity")
GROUPS = ("peak", "acc", "spec", "peak+acc+spec")


def trial_features(fsr: np.ndarray, acc: np.ndarray) -> dict[str, np.ndarray]:
    """One trial's raw FSR (T, 2, 16, 16) and accelerometer (T, 4, 4, 3) -> feature groups."""
    fsr = fsr.astype(np.float64)
    total = fsr.sum((2, 3))  # (T, 2)
    top = fsr[int(total[:, 0].argmax()), 0]
    centred = top - top.mean()
    power = np.abs(np.fft.fft2(centred)) ** 2
    f = np.fft.fftfreq(top.shape[0])
    radius = np.hypot(f[:, None], f[None, :])
    ring = np.digitize(radius, np.linspace(0.0, 0.71, 9))
    spectrum = np.array([power[ring == b].mean() if (ring == b).any() else 0.0 for b in range(1, 10)])
    spectrum = spectrum / (spectrum.sum() + 1e-12)
    area = [(top > q * top.max()).mean() if top.max() > 0 else 0.0 for q in (0.1, 0.3, 0.5)]
    acc = acc.astype(np.float64)
    rms = np.sqrt(((acc - acc.mean(0)) ** 2).mean(0)).ravel()
    return {"peak": np.log1p(total.max(0)), "acc": np.log(rms + 1e-9),
            "spec": np.concatenate([np.log(spectrum + 1e-6), area])}


def object_table(raw: str) -> tuple[list[int], dict[int, dict[str, np.ndarray]], dict[int, np.ndarray]]:
    """Features (both actions concatenated, in action order) and targets per object."""
    from embodied_tactile.data.rawformat import iter_trials

    per: dict[int, dict[int, dict[str, np.ndarray]]] = {}
    targets: dict[int, np.ndarray] = {}
    for tr in iter_trials(raw):
        a = tr.attrs
        obj = int(a["object_id"])
        per.setdefault(obj, {})[int(a["action_index"])] = trial_features(tr.fsr, tr.acc)
        targets[obj] = np.array([a["spatial_frequency"], np.log(a["amplitude"]),
                                 np.log10(a["bulk_youngs_modulus"]), a["heterogeneity"]], dtype=np.float64)
    actions = sorted({k for d in per.values() for k in d})
    objects = sorted(o for o, d in per.items() if sorted(d) == actions)
    feats = {o: {g: np.concatenate([per[o][k][g] for k in actions]) for g in ("peak", "acc", "spec")}
             for o in objects}
    for o in objects:
        feats[o]["peak+acc+spec"] = np.concatenate([feats[o][g] for g in ("peak", "acc", "spec")])
    return objects, feats, targets


def krr_predict(x_tr: np.ndarray, y_tr: np.ndarray, x_te: np.ndarray, ridge: float, length: float) -> np.ndarray:
    """RBF kernel ridge on standardised features; length scale in units of sqrt(n_features)."""
    mu, sd = x_tr.mean(0), x_tr.std(0) + 1e-8
    a, b = (x_tr - mu) / sd, (x_te - mu) / sd
    scale = 2.0 * length**2 * a.shape[1]

    def kern(u, v):
        d2 = (u * u).sum(1)[:, None] + (v * v).sum(1)[None, :] - 2.0 * u @ v.T
        return np.exp(-np.maximum(d2, 0.0) / scale)

    ym = y_tr.mean(0)
    alpha = np.linalg.solve(kern(a, a) + ridge * np.eye(len(a)), y_tr - ym)
    return kern(b, a) @ alpha + ym


def score(feats, targets, train, val, test, group: str) -> np.ndarray:
    """Test NMSE per factor, hyper-parameters chosen per factor on the validation objects."""
    x = {role: np.stack([feats[o][group] for o in objs]) for role, objs in
         (("train", train), ("val", val), ("test", test))}
    y = {role: np.stack([targets[o] for o in objs]) for role, objs in
         (("train", train), ("val", val), ("test", test))}
    best: dict[int, tuple[float, float, float]] = {}
    for ridge in (1e-3, 1e-2, 1e-1, 1.0):
        for length in (0.3, 1.0, 3.0):
            err = ((krr_predict(x["train"], y["train"], x["val"], ridge, length) - y["val"]) ** 2).mean(0)
            for j, e in enumerate(err):
                if j not in best or e < best[j][0]:
                    best[j] = (e, ridge, length)
    var = y["train"].var(0)
    out = np.empty(len(FACTORS))
    for j in range(len(FACTORS)):
        pred = krr_predict(x["train"], y["train"], x["test"], best[j][1], best[j][2])
        out[j] = ((pred[:, j] - y["test"][:, j]) ** 2).mean() / var[j]
    return out


def local_relief(n_objects: int, seed: int) -> tuple[float, float, np.ndarray]:
    """Peak-to-peak height within the patch's window at the block centre (where pressing
    lands, to within the 0.5 mm placement error) over the block's amplitude, for population
    objects 0..n-1: -> (variance of log ratio, variance of log amplitude, ratio percentiles 5/50/95)."""
    from embodied_tactile import constants as C
    from embodied_tactile.sim import objects as O
    from embodied_tactile.sim import physics as P
    from embodied_tactile.sim.population import population_object

    half = int(round(C.FSR_GRID[0] * C.TAXEL_PITCH_M / P.SURFACE_DX_M / 2))
    c = P.SURFACE_N // 2
    ratio, log_amp = [], []
    for k in range(n_objects):
        o = population_object(k, seed)
        h = O.surface(o)[c - half:c + half, c - half:c + half] * 1e3
        ratio.append(np.log((h.max() - h.min()) / o.amplitude_mm))
        log_amp.append(np.log(o.amplitude_mm))
    r = np.array(ratio)
    return float(r.var()), float(np.var(log_amp)), np.exp(np.percentile(r, [5, 50, 95]))


def main() -> None:
    from embodied_tactile.sim.population import object_role, population_index

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--raw", required=True, help="population raw HDF5 file")
    ap.add_argument("--n-train", type=int, nargs="+", default=[24, 64, 128, 256, 512])
    ap.add_argument("--n-val", type=int, default=32)
    ap.add_argument("--n-test", type=int, default=64)
    ap.add_argument("--population-seed", type=int, default=0, help="for the local-relief line")
    args = ap.parse_args()
    t0 = time.perf_counter()
    objects, feats, targets = object_table(args.raw)
    print(f"{len(objects)} objects with both actions read from {args.raw} in {time.perf_counter() - t0:.0f} s")
    role = {o: object_role(o, n_val=args.n_val, n_test=args.n_test) for o in objects}
    val = [o for o in objects if role[o] == "val"]
    test = [o for o in objects if role[o] == "test"]
    train_all = sorted((o for o in objects if role[o] == "train"), key=population_index)
    print(f"test objects {len(test)}, validation objects {len(val)}, training objects available {len(train_all)}")
    print(f"\n| training objects | features | {' | '.join(FACTORS)} | mean |")
    print("|---|---|" + "---|" * (len(FACTORS) + 1))
    for n in args.n_train:
        if n > len(train_all):
            print(f"| {n} | (not run: {len(train_all)} training objects in the file) |" + " |" * len(FACTORS))
            continue
        for group in GROUPS:
            e = score(feats, targets, train_all[:n], val, test, group)
            print(f"| {n} | {group} | " + " | ".join(f"{v:.3f}" for v in e) + f" | {e.mean():.3f} |")
    v_ratio, v_amp, pct = local_relief(len(objects), args.population_seed)
    print(f"\nlocal relief under the patch / block amplitude over {len(objects)} objects: median {pct[1]:.2f}, "
          f"5-95 % {pct[0]:.2f}-{pct[2]:.2f}; var log ratio {v_ratio:.3f} / var log amplitude {v_amp:.3f} "
          f"= NMSE {v_ratio / v_amp:.2f} of the local relief as a reader of log amplitude")


if __name__ == "__main__":
    main()
