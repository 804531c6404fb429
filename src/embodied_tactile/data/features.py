"""The hand-crafted physical features of a touch (one implementation: the hand-crafted
reader :func:`embodied_tactile.eval.baselines.evaluate_handcrafted` reads them, and so does
the context objective's physical auxiliary, whose targets they are:
:meth:`embodied_tactile.data.datamodule.TactileDataModule.feature_scale`). NumPy only.

Computed from the PREPROCESSED sequences the model sees
(``obs`` (n, T, C, 28, 28) + ``actions`` (n, T, 6)), so the comparison is on equal
inputs (raw 700 Hz signals would give the baseline information the model never gets).
Every feature is *causal*: the value at frame t summarises frames 0..t only (running
max / running means from cumulative sums). The feature vector at frame t therefore plays
the role of a latent at frame t: the alignment is fitted on the final segment of the
training sequences (= whole-sequence features) and applied at every frame of the held-out
sequences, exactly like the Latent Filter's latents. Features (those whose channels
exist in the modality):

* force: per-frame force F_t = mean over taxels of the available FSR layers; running peak
  force, running mean force;
* force-indentation slope: least-squares slope of F against depth (-z, action column 2)
  and against the drive s_t = ||a_t - a_0|| (all six action columns);
* hysteresis: signed loop area sum F_t ds_t relative to sum |F_t ds_t| (loading vs
  unloading; 0 for an elastic contact);
* relaxation: mean relative force change dF/F over frames where the action is still
  (|ds| < 10 % of its running max) and in contact (F > 50 % of its running max);
* top/bottom shear proxy (both FSR layers): distance between the pressure centroids of the
  two layers, and the top-bottom difference energy mean((top - bottom)^2) / mean(top^2 +
  bottom^2), averaged over contact frames;
* contact area fraction (taxels above 10 % of the frame max) and spatial-spectrum centroid
  of the (top) force image (2-D FFT radial frequency), over contact frames;
* vibration (acc channel, 4 x 4 tiles of 7 x 7 log-mel bins in [0, 1] scaled dB):
  low / mid / high band mean level (mel bins 0-15 / 16-31 / 32-48), spectral centroid
  (in mel-bin units, power-weighted), running std of the high band.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from ..options.evaluation import HandcraftedOptions

_EPS = 1e-8


def _cummean(x: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Running (weighted) mean along axis 1; frames with zero total weight so far -> 0."""
    if w is None:
        w = np.ones_like(x)
    num = np.cumsum(x * w, axis=1)
    den = np.cumsum(w, axis=1)
    return np.where(den > 0, num / np.maximum(den, _EPS), 0.0)


def _centroid(img: np.ndarray) -> np.ndarray:
    """img (..., H, W) -> pressure centroid (..., 2) in taxel units (positive part)."""
    p = np.clip(img, 0.0, None)
    h, w = img.shape[-2:]
    tot = p.sum((-2, -1)) + _EPS
    cy = (p.sum(-1) * np.arange(h)).sum(-1) / tot
    cx = (p.sum(-2) * np.arange(w)).sum(-1) / tot
    return np.stack([cy, cx], -1)


def _spatial_centroid(img: np.ndarray) -> np.ndarray:
    """Radial spatial-frequency centroid of each image (..., H, W) (DC removed)."""
    h, w = img.shape[-2:]
    spec = np.abs(np.fft.rfft2(img - img.mean((-2, -1), keepdims=True)))
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    r = np.sqrt(fy**2 + fx**2)
    return (spec * r).sum((-2, -1)) / (spec.sum((-2, -1)) + _EPS)


def _acc_bins(acc: np.ndarray, tile=(7, 7), grid=(4, 4)) -> np.ndarray:
    """acc image (n, T, 28, 28) -> (n, T, 16, 49) mel bins per sensor (inverse of tile_layout)."""
    n, t = acc.shape[:2]
    x = acc.reshape(n, t, grid[0], tile[0], grid[1], tile[1])
    x = np.transpose(x, (0, 1, 2, 4, 3, 5))
    return x.reshape(n, t, grid[0] * grid[1], tile[0] * tile[1])


def handcrafted_features(obs, actions, channels: Sequence[str],
                         options: HandcraftedOptions | Mapping[str, Any] | None = None) -> tuple[np.ndarray, list[str]]:
    """Causal hand-crafted features at every frame: -> (features (n, T, k), names).

    ``obs`` (n, T, C, 28, 28) with ``channels`` naming the C axis ('acc', 'fsr_t', 'fsr_b');
    ``actions`` (n, T, 6); ``options``: the thresholds (:class:`HandcraftedOptions`, its
    defaults where None or silent). Float64 internally; NaN-free output.
    """
    opt = options if isinstance(options, HandcraftedOptions) else HandcraftedOptions(**dict(options or {}))
    obs = np.asarray(obs, dtype=np.float32)
    act = np.asarray(actions, dtype=np.float64)
    channels = list(channels)
    if obs.ndim != 5 or obs.shape[2] != len(channels):
        raise ValueError(f"obs must be (n, T, C={len(channels)}, H, W), got {obs.shape}")
    feats: list[np.ndarray] = []
    names: list[str] = []

    def add(name, v):
        names.append(name)
        feats.append(np.nan_to_num(np.asarray(v, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0))

    fsr_idx = [channels.index(c) for c in ("fsr_t", "fsr_b") if c in channels]
    s = np.linalg.norm(act - act[:, :1], axis=-1)  # drive (n, T)
    ds = np.diff(s, axis=1, prepend=s[:, :1])
    depth = -(act[:, :, 2] - act[:, :1, 2])
    if fsr_idx:
        layers = obs[:, :, fsr_idx].astype(np.float64)  # (n, T, L, H, W)
        force = layers.mean((-3, -2, -1))  # (n, T)
        runmax = np.maximum.accumulate(force, axis=1)
        contact = (force > opt.contact_fraction * runmax) & (runmax > _EPS)
        add("peak_force", runmax)
        add("mean_force", _cummean(force))
        for nm, drv in (("slope_force_depth", depth), ("slope_force_drive", s)):
            mx, my = _cummean(drv), _cummean(force)
            cov = _cummean(drv * force) - mx * my
            var = _cummean(drv * drv) - mx * mx
            add(nm, np.where(var > 1e-10, cov / np.maximum(var, 1e-10), 0.0))
        loop = np.cumsum(force * ds, axis=1)
        absl = np.cumsum(np.abs(force * ds), axis=1)
        add("hysteresis", loop / (absl + _EPS))
        dforce = np.diff(force, axis=1, prepend=force[:, :1]) / (np.abs(force) + _EPS)
        still = (np.abs(ds) < opt.still_fraction * np.maximum.accumulate(np.abs(ds), axis=1)) & contact
        add("relaxation", _cummean(np.clip(dforce, -1, 1), still.astype(float)))
        img = layers[:, :, 0]
        thr = opt.area_fraction * img.max((-2, -1), keepdims=True)
        area = ((img > thr) & (thr > 0)).mean((-2, -1))
        add("contact_area", _cummean(area, contact.astype(float)))
        add("spatial_freq_centroid", _cummean(_spatial_centroid(img), contact.astype(float)))
        if len(fsr_idx) == 2:
            top, bot = layers[:, :, 0], layers[:, :, 1]
            off = np.linalg.norm(_centroid(top) - _centroid(bot), axis=-1)
            add("shear_centroid_offset", _cummean(off, contact.astype(float)))
            energy = ((top - bot) ** 2).mean((-2, -1)) / (((top**2) + (bot**2)).mean((-2, -1)) + _EPS)
            add("top_bottom_diff_energy", _cummean(energy, contact.astype(float)))
    if "acc" in channels:
        bins = _acc_bins(obs[:, :, channels.index("acc")].astype(np.float64))  # (n, T, 16, 49)
        level = bins.mean(2)  # (n, T, 49) scaled dB averaged over sensors
        nb = level.shape[-1]
        edges = np.linspace(0, nb, 4).astype(int)
        for nm, lo, hi in zip(("acc_low_band", "acc_mid_band", "acc_high_band"), edges[:-1], edges[1:]):
            band = level[..., lo:hi].mean(-1)
            add(nm, _cummean(band))
        power = 10.0 ** (12.0 * (level - level.max(-1, keepdims=True)))  # scaled dB in [0,1] spans 120 dB
        cent = (power * np.arange(nb)).sum(-1) / (power.sum(-1) + _EPS)
        add("acc_spectral_centroid", _cummean(cent))
        high = level[..., edges[2]:].mean(-1)
        m1, m2 = _cummean(high), _cummean(high**2)
        add("acc_high_band_std", np.sqrt(np.maximum(m2 - m1**2, 0.0)))
    if not feats:
        raise ValueError(f"no hand-crafted feature for channels {channels}")
    return np.stack(feats, axis=-1), names


__all__ = ["handcrafted_features"]
