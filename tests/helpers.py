"""Reference implementations the tests (and a benchmark) compare the package's fast paths with;
nothing in the package calls them. Importable as ``helpers`` (pytest puts ``tests/`` on the path
through its conftest.py)."""

from __future__ import annotations

import numpy as np
import scipy.signal

from embodied_tactile import constants as C
from embodied_tactile.data import cache as cache_mod
from embodied_tactile.data import preprocess as P
from embodied_tactile.data import rawformat
from embodied_tactile.data.preprocess import PreprocessConfig


def melspectrogram(y: np.ndarray, sr: float, n_fft: int, hop_length: int, win_length: int, window: str, n_mels: int,
                   fmin: float, fmax: float, htk: bool = False, norm: str | float | None = "slaney") -> np.ndarray:
    """``librosa.feature.melspectrogram(y, center=False, power=2.0)`` with its STFT taken by
    ``scipy.signal.ShortTimeFFT`` (librosa's periodic window, centred in ``n_fft``) and librosa's
    mel filterbank at its default float32: (n_mels, frames). Equal to librosa's to 4e-17 of its
    largest value, without ``librosa.stft``'s numba compilation (29 s on a cold cache; Intel Xeon
    @ 2.80GHz, 2026-11-29)."""
    import librosa

    pad = n_fft - win_length
    w = np.pad(scipy.signal.get_window(window, win_length, fftbins=True), (pad // 2, pad - pad // 2))
    stft = scipy.signal.ShortTimeFFT(w, hop=hop_length, fs=sr, mfft=n_fft, scale_to=None)
    x = stft.stft(y, p0=0, p1=(len(y) - n_fft) // hop_length + 1, k_offset=n_fft // 2)
    mel = librosa.filters.mel(sr=sr, n_fft=n_fft, n_mels=n_mels, fmin=fmin, fmax=fmax, htk=htk, norm=norm)
    return mel @ np.abs(x) ** 2


def power_to_db(s: np.ndarray, amin: float) -> np.ndarray:
    """``librosa.power_to_db(s, ref=1.0, amin=amin, top_db=None)`` (its definition; importing
    librosa's spectrum module compiles for 5 s on a cold numba cache)."""
    return 10.0 * np.log10(np.maximum(amin, s))


def acc_logmel_naive(acc: np.ndarray, cfg: PreprocessConfig, fs_tactile: float = C.FS_TACTILE) -> np.ndarray:
    """Reference loop: per sensor and signal (axis, or |a|), its own resample_poly and
    mel spectrogram (:func:`melspectrogram`); powers summed per sensor, one power_to_db call. (N, 4, 4, 3) -> (T, 28, 28) float32. The tests'
    reference (and benchmarks/bench_preprocess.py's)."""
    a = np.asarray(acc, dtype=np.float64)
    up, down = P._resample_ratio(fs_tactile, cfg.fs_resample)
    out = np.zeros((cfg.n_frames, cfg.n_mels, *C.ACC_GRID))
    for i in range(C.ACC_GRID[0]):
        for j in range(C.ACC_GRID[1]):
            if cfg.acc_combine == "magnitude":
                sigs = [np.sqrt((a[:, i, j, :] ** 2).sum(axis=-1))]
            else:
                sigs = [a[:, i, j, k] for k in range(a.shape[-1])]
            s = 0.0
            for sig in sigs:  # mel powers summed over the signals (axes)
                if cfg.acc_remove_mean:
                    sig = sig - sig.mean()
                y = scipy.signal.resample_poly(sig / cfg.acc_scale_g, up, down)
                left, right = P.stft_padding(cfg, len(y))
                s = s + melspectrogram(
                    P.pad_last(y, left, right), sr=cfg.fs_resample, n_fft=cfg.n_fft, hop_length=cfg.hop_length,
                    win_length=cfg.win_length, window=cfg.window, n_mels=cfg.n_mels, fmin=cfg.fmin,
                    fmax=cfg.fmax_hz, htk=cfg.mel_htk, norm=cfg.mel_norm,
                )[:, : cfg.n_frames]
            db = power_to_db(s, amin=cfg.db_amin)
            out[:, :, i, j] = ((db - cfg.db_min) / (cfg.db_max - cfg.db_min)).T
    return P.tile_layout(out, cfg.tile_shape).astype(np.float32)


def fingerprint_file(path, names, fields) -> dict[str, str]:
    """``{field: digest}`` of one raw file computed serially (trial names, attrs and the stored
    bytes of the datasets each field reads): the reference for the digests ``build_cache``
    computes chunk by chunk on its worker pool."""
    fields = list(fields)
    dpaths = cache_mod._fields_datasets(fields)
    attrs_json: dict[str, str] = {}
    digests: dict[str, dict[str, str]] = {}
    with rawformat.open_raw(path) as f, open(path, "rb") as fh:
        for name in names:
            try:
                attrs_json[name] = cache_mod._attrs_json(rawformat.read_attrs(f["trials"][name]))
            except (OSError, KeyError, RuntimeError) as exc:
                attrs_json[name] = f"unreadable: {exc}"
            digests[name] = cache_mod._trial_digests(f, fh, name, dpaths)
    return cache_mod._combine_fingerprint(names, attrs_json, digests, fields)
