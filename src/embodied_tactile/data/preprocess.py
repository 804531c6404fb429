"""Methods-section preprocessing of raw e-Skin trials (paper: "Data processing & training").

Pure numpy / scipy / librosa (no torch). One trial -> three fields on the common
T = 300 frame grid (30 Hz over the 10 s trial); frame ``k`` covers
``[t0 + k/30, t0 + (k+1)/30)`` on the tactile clock (``t0 = tactile t[0]``) and its
centre ``t0 + (k + 0.5)/30`` is the frame's time stamp for every field:

``acc``     (T, 28, 28) float32  log-mel image of the 16 accelerometers (power summed
            over the 3 axes), ~[0, 1]
``fsr``     (T, 2, 28, 28) float32  block-averaged, /4095, bilinear 16x16 -> 28x28
``actions`` (T, 6) float32  end-effector pose relative to the first pose sample,
            positions in mm / 10, angles in degrees / 10

Every choice the paper leaves open is a :class:`PreprocessConfig` field and is
documented in ``docs/reference/preprocessing.md``. :func:`preprocess_trials` is the fast path: it
stacks the trials and runs each stage once over all channels of all trials.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Iterable, Sequence

import numpy as np
import scipy.fft
import scipy.ndimage
import scipy.signal

from embodied_tactile import constants as C
from embodied_tactile.data.rawformat import RawTrial, coverage_problem

#: Bump when the numbers this module produces change for the same config and raw data;
#: part of every cache key (``data.cache``). 2: the accelerometer path runs in float32
#: (resampling as a block matrix product, STFT, mel), values within 1e-5 of version 1.
PREPROCESS_VERSION = 3
#: 3: a trial whose tactile clock covers less than MIN_SPAN_FRACTION of the frame grid, or
#: whose pose log leaves more than the allowed gap of that span, is skipped (listed in the
#: cache's ``skipped``, file and trial named) instead of padded with its edge values.

#: A trial must cover at least this fraction of the scene's window (n_frames / frame_rate);
#: a shorter one is skipped. One longer than the window by more than LONG_FRACTION is cut to
#: the window with a warning (the first window of it is used, as always).
MIN_SPAN_FRACTION = 0.9
LONG_FRACTION = 0.05
#: The pose log may leave at most max(POSE_GAP_MIN_S, POSE_GAP_FRACTION x window) of the
#: used tactile span uncovered (before its first or after its last sample).
POSE_GAP_MIN_S = 0.5
POSE_GAP_FRACTION = 0.05

FIELDS = ("acc", "fsr", "actions")
#: How the three accelerometer axes become one spectrum per sensor (PreprocessConfig.acc_combine).
ACC_COMBINE = ("axes", "magnitude")

#: Raw fields (``rawformat.read_trial`` names) each processed field needs. ``t`` is the
#: tactile clock (a 56 kB vector): actions read it too, to align the pose to the tactile
#: frames, without touching the acc / fsr datasets.
RAW_FIELDS: dict[str, tuple[str, ...]] = {
    "acc": ("t", "acc"),
    "fsr": ("t", "fsr", "baseline_fsr"),
    "actions": ("t", "pose"),
}


@dataclass
class PreprocessConfig:
    """All preprocessing knobs. Defaults reproduce the paper where it is unambiguous and
    resolve its contradictions as documented in ``docs/reference/preprocessing.md``."""

    # -- common frame grid
    n_frames: int = 300  # T
    frame_rate: float = 30.0  # Hz -> 10 s trials

    # -- accelerometers: remove mean -> / scale -> 700 -> 600 Hz -> power summed over axes
    #: "axes": each axis' static part (gravity + offset) removed, the STFT power of the three
    #: axes summed (the power spectrum of the vibration vector, rotation invariant);
    #: "magnitude": |a| first, then its mean removed (keeps, to first order, only the
    #: component along gravity: lateral vibration enters |a| squared, docs/experiments/modality_bounds.md)
    acc_combine: str = "axes"
    acc_remove_mean: bool = True  # drop the static (gravity + offset) part
    acc_scale_g: float = C.ACC_RANGE_G  # fixed scale (g), never per-trial
    fs_resample: float = 600.0
    # -- log-mel. The paper's "window 800, 128 FFT points" cannot both hold (win <= n_fft).
    n_fft: int = 128
    win_length: int = 128
    hop_length: int = 20  # 600 Hz / 20 = 30 frames/s
    window: str = "hann"
    n_mels: int = 49
    fmin: float = 0.0
    fmax: float | None = None  # None = fs_resample / 2
    mel_htk: bool = False
    mel_norm: str | None = "slaney"
    db_amin: float = 1e-10  # power floor = -100 dB -> exactly 0 after scaling
    db_min: float = -100.0  # dB mapped to 0
    db_max: float = 20.0  # dB mapped to 1 (not clipped above)
    tile_shape: tuple[int, int] = (7, 7)  # n_mels bins of one sensor as a tile

    # -- FSR
    fsr_subtract_baseline: bool = True  # recorded trials with a no-contact baseline
    fsr_spatial_kernel: int = 1  # extra spatial k x k mean filter at 16x16; 1 = off
    fsr_max_count: int = C.FSR_MAX_COUNT
    resize_hw: tuple[int, int] = (28, 28)

    # -- actions
    pose_pos_scale: float = 100.0  # m -> mm / 10
    pose_ang_scale: float = float(180.0 / np.pi / 10.0)  # rad -> deg / 10

    def __post_init__(self) -> None:
        self.tile_shape = tuple(int(v) for v in self.tile_shape)  # type: ignore[assignment]
        self.resize_hw = tuple(int(v) for v in self.resize_hw)  # type: ignore[assignment]

    # ------------------------------------------------------------------ derived
    @property
    def duration(self) -> float:
        return self.n_frames / self.frame_rate

    @property
    def fmax_hz(self) -> float:
        return float(self.fs_resample / 2 if self.fmax is None else self.fmax)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["tile_shape"] = list(self.tile_shape)
        d["resize_hw"] = list(self.resize_hw)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "PreprocessConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown PreprocessConfig keys: {sorted(unknown)}")
        return cls(**d)

    def field_dict(self, field: str) -> dict[str, Any]:
        """The config entries that change the numbers of ``field`` (for cache keys)."""
        keys = _FIELD_KEYS[field]
        d = self.to_dict()
        d["fmax"] = self.fmax_hz  # None and fs/2 are the same setting
        return {k: d[k] for k in keys}

    def validate(self) -> "PreprocessConfig":
        """Raise ValueError with a clear message for impossible settings; returns self."""
        def bad(msg: str) -> None:
            raise ValueError(f"PreprocessConfig: {msg}")

        for name in ("n_frames", "n_fft", "win_length", "hop_length", "n_mels", "fsr_spatial_kernel", "fsr_max_count"):
            if int(getattr(self, name)) <= 0:
                bad(f"{name} must be a positive integer, got {getattr(self, name)!r}")
        for name in ("frame_rate", "fs_resample", "acc_scale_g", "db_amin", "pose_pos_scale", "pose_ang_scale"):
            if not float(getattr(self, name)) > 0:
                bad(f"{name} must be > 0, got {getattr(self, name)!r}")
        if self.win_length > self.n_fft:
            bad(
                f"win_length ({self.win_length}) > n_fft ({self.n_fft}): the STFT window cannot be "
                f"longer than the FFT (librosa raises ParameterError). The paper's 'window 800, "
                f"128 FFT points' is contradictory; set win_length <= n_fft, e.g. n_fft=win_length=128."
            )
        if self.n_fft < self.hop_length:
            bad(f"n_fft ({self.n_fft}) < hop_length ({self.hop_length}): frames would skip samples")
        if abs(self.hop_length * self.frame_rate - self.fs_resample) > 1e-9 * self.fs_resample:
            bad(
                f"hop_length ({self.hop_length}) / fs_resample ({self.fs_resample} Hz) must equal the frame "
                f"period 1/{self.frame_rate} s so that STFT frames are the {self.n_frames} tactile frames"
            )
        if not 0 <= self.fmin < self.fmax_hz <= self.fs_resample / 2 + 1e-9:
            bad(f"need 0 <= fmin ({self.fmin}) < fmax ({self.fmax_hz}) <= fs_resample/2 ({self.fs_resample / 2})")
        if self.n_mels > self.n_fft // 2 + 1:
            bad(f"n_mels ({self.n_mels}) > n_fft // 2 + 1 ({self.n_fft // 2 + 1} FFT bins) for n_fft ({self.n_fft})")
        if self.db_max <= self.db_min:
            bad(f"db_max ({self.db_max}) must exceed db_min ({self.db_min})")
        th, tw = self.tile_shape
        if th * tw != self.n_mels:
            bad(
                f"tile_shape {self.tile_shape} holds {th * tw} bins but n_mels is {self.n_mels}: each "
                f"sensor's mel bins must fill its tile (n_mels=49 for the paper's 7x7 tile)"
            )
        img = (C.ACC_GRID[0] * th, C.ACC_GRID[1] * tw)
        if img != tuple(self.resize_hw):
            bad(f"acc image {img} (4x4 sensors x tile {self.tile_shape}) != FSR resize_hw {self.resize_hw}: modalities must share H x W")
        if self.acc_combine not in ACC_COMBINE:
            bad(f"acc_combine must be one of {ACC_COMBINE}, got {self.acc_combine!r}")
        if self.fsr_spatial_kernel % 2 != 1:
            bad(f"fsr_spatial_kernel must be odd, got {self.fsr_spatial_kernel}")
        empty = np.flatnonzero(_mel_basis(self._mel_key()).sum(axis=1) == 0)
        if empty.size:
            bad(
                f"n_mels ({self.n_mels}) too many for n_fft ({self.n_fft}) over {self.fmin}-{self.fmax_hz} Hz: "
                f"mel filters {empty.tolist()} contain no FFT bin"
            )
        return self

    def _mel_key(self) -> tuple:
        return (float(self.fs_resample), int(self.n_fft), int(self.n_mels), float(self.fmin), self.fmax_hz, bool(self.mel_htk), self.mel_norm)


_COMMON_KEYS = ("n_frames", "frame_rate")
_FIELD_KEYS: dict[str, tuple[str, ...]] = {
    "acc": _COMMON_KEYS
    + ("acc_combine", "acc_remove_mean", "acc_scale_g", "fs_resample", "n_fft", "win_length", "hop_length", "window", "n_mels",
       "fmin", "fmax", "mel_htk", "mel_norm", "db_amin", "db_min", "db_max", "tile_shape"),
    "fsr": _COMMON_KEYS + ("fsr_subtract_baseline", "fsr_spatial_kernel", "fsr_max_count", "resize_hw"),
    "actions": _COMMON_KEYS + ("pose_pos_scale", "pose_ang_scale"),
}


# ============================================================================ helpers
@functools.lru_cache(maxsize=16)
def _mel_basis(key: tuple) -> np.ndarray:
    import librosa

    sr, n_fft, n_mels, fmin, fmax, htk, norm = key
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # empty filters are reported by validate()
        return librosa.filters.mel(sr=sr, n_fft=n_fft, n_mels=n_mels, fmin=fmin, fmax=fmax, htk=htk, norm=norm, dtype=np.float64)


@functools.lru_cache(maxsize=16)
def _stft_window(window: str, win_length: int, n_fft: int) -> np.ndarray:
    # float32. Same as librosa: periodic window of win_length, zero-padded to n_fft in the centre.
    w = scipy.signal.get_window(window, win_length, fftbins=True)
    lpad = (n_fft - win_length) // 2
    return np.pad(w, (lpad, n_fft - win_length - lpad)).astype(np.float32)


def stft_padding(cfg: PreprocessConfig, n_samples: int) -> tuple[int, int]:
    """Zero padding (left, right) of the resampled signal so that STFT frame ``k`` is
    centred on sample ``(k + 0.5) * hop`` = the tactile frame centre, giving exactly
    ``n_frames`` frames (``center=False`` framing of the padded signal)."""
    left = cfg.n_fft // 2 - cfg.hop_length // 2
    right = (cfg.n_frames - 1) * cfg.hop_length + cfg.n_fft - left - n_samples
    return left, right


def pad_last(y: np.ndarray, left: int, right: int) -> np.ndarray:
    if right < 0:
        y = y[..., : y.shape[-1] + right]
        right = 0
    widths = [(0, 0)] * (y.ndim - 1) + [(left, right)]
    return np.pad(y, widths)


def _resample_ratio(fs_in: float, fs_out: float) -> tuple[int, int]:
    fr = Fraction(fs_out / fs_in).limit_denominator(1000)
    return fr.numerator, fr.denominator


def _uniform(t: np.ndarray, x: np.ndarray, fs: float, n: int) -> np.ndarray:
    """``x`` (N, ...) on the uniform grid ``t[0] + arange(n) / fs`` (first axis).

    Regular streams (the usual case) are sliced; short or irregular ones (lost packets)
    are linearly interpolated, holding the edge values outside the recording.
    """
    t = np.asarray(t, dtype=np.float64)
    if len(t) >= n:
        d = np.diff(t[:n])
        if d.size == 0 or (abs(d.min() * fs - 1) < 0.25 and abs(d.max() * fs - 1) < 0.25):
            return x[:n]
    grid = t[0] + np.arange(n) / fs
    flat = np.asarray(x, dtype=np.float64).reshape(len(t), -1)
    j = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, len(t) - 2)
    w = np.clip((grid - t[j]) / (t[j + 1] - t[j]), 0.0, 1.0)[:, None]
    out = flat[j] * (1 - w) + flat[j + 1] * w
    return out.reshape(n, *x.shape[1:])


def bilinear_matrix(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) matrix of 1-D linear interpolation with the semantics of
    ``torch.nn.functional.interpolate(mode="bilinear", align_corners=False)`` (size given):
    source coordinate ``(i + 0.5) * n_in / n_out - 0.5``, clamped at 0, edge index clamped."""
    scale = n_in / n_out
    src = np.maximum((np.arange(n_out) + 0.5) * scale - 0.5, 0.0)
    i0 = np.minimum(np.floor(src).astype(np.int64), n_in - 1)
    i1 = np.minimum(i0 + 1, n_in - 1)
    lam = src - i0
    m = np.zeros((n_out, n_in))
    np.add.at(m, (np.arange(n_out), i0), 1.0 - lam)
    np.add.at(m, (np.arange(n_out), i1), lam)
    return m


def bilinear_resize(x: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
    """Resize the last two axes of ``x`` like torch bilinear (align_corners=False), as the
    separable product ``R_h @ x @ R_w.T``."""
    rh = bilinear_matrix(x.shape[-2], out_hw[0]).astype(x.dtype, copy=False)
    rw = bilinear_matrix(x.shape[-1], out_hw[1]).astype(x.dtype, copy=False)
    return np.matmul(np.matmul(rh, x), rw.T)


def tile_layout(mel: np.ndarray, tile_shape: tuple[int, int]) -> np.ndarray:
    """(..., n_mels, 4, 4) -> (..., 4*th, 4*tw): sensor (i, j)'s bins, row-major (lowest
    frequency top-left), fill rows th*i .. th*i+th-1 and cols tw*j .. tw*j+tw-1."""
    th, tw = tile_shape
    gh, gw = mel.shape[-2:]
    lead = mel.shape[:-3]
    x = mel.reshape(*lead, th, tw, gh, gw)
    nd = len(lead)
    x = np.moveaxis(x, (nd, nd + 1, nd + 2, nd + 3), (nd + 1, nd + 3, nd, nd + 2))  # -> gh, th, gw, tw
    return x.reshape(*lead, gh * th, gw * tw)


# ============================================================================ accelerometers
def acc_magnitude(acc: np.ndarray, cfg: PreprocessConfig) -> np.ndarray:
    """(..., N, 4, 4, 3) g -> (..., 16, N) float64: |a| per sensor, static part removed,
    divided by the fixed ``acc_scale_g``."""
    a = np.asarray(acc, dtype=np.float64)
    mag = np.sqrt(np.einsum("...k,...k->...", a, a))  # (..., N, 4, 4)
    mag = mag.reshape(*mag.shape[:-2], -1)  # (..., N, 16)
    mag = np.ascontiguousarray(np.moveaxis(mag, -2, -1))  # (..., 16, N), time contiguous
    if cfg.acc_remove_mean:
        mag -= mag.mean(axis=-1, keepdims=True)
    mag /= cfg.acc_scale_g
    return mag


def acc_axes(acc: np.ndarray, cfg: PreprocessConfig) -> np.ndarray:
    """(..., N, 4, 4, 3) g -> (..., 16, 3, N) float64: each axis per sensor, its static part
    (gravity + offset) removed, divided by the fixed ``acc_scale_g``."""
    a = np.asarray(acc, dtype=np.float64)
    a = a.reshape(*a.shape[:-3], -1, a.shape[-1])  # (..., N, 16, 3)
    a = np.ascontiguousarray(np.moveaxis(a, -3, -1))  # (..., 16, 3, N), time contiguous
    if cfg.acc_remove_mean:
        a -= a.mean(axis=-1, keepdims=True)
    a /= cfg.acc_scale_g
    return a


def acc_signals(acc: np.ndarray, cfg: PreprocessConfig) -> np.ndarray:
    """(..., N, 4, 4, 3) g -> (..., 16, A, N): the A signals per sensor whose mel powers are
    summed (``acc_combine``: "axes" A = 3, "magnitude" A = 1)."""
    if cfg.acc_combine == "magnitude":
        return acc_magnitude(acc, cfg)[..., None, :]
    return acc_axes(acc, cfg)


def _logmel_from_resampled(y: np.ndarray, cfg: PreprocessConfig, sum_axis: int | None = None) -> np.ndarray:
    """(..., n) resampled signals -> (..., n_mels, n_frames) scaled log-mel, float32.
    ``sum_axis``: an axis of ``y`` (negative, before the last) whose powers are summed
    before the dB (the accelerometer axes), removed from the output.

    The one STFT of the project: ``scipy.fft.rfft`` of a strided frame view (float32, the
    window librosa uses), ``|X|^2`` summed over ``sum_axis`` *before* the mel product (the
    filterbank is linear: one third of the mel work for three axes), librosa's mel
    filterbank. Equal to ``librosa.feature.melspectrogram(center=False)`` per channel to
    float32 precision (tests/helpers.py: ``acc_logmel_naive``, a hand-written librosa reference)."""
    left, right = stft_padding(cfg, y.shape[-1])
    yp = pad_last(np.asarray(y, dtype=np.float32), left, right)
    frames = np.lib.stride_tricks.sliding_window_view(yp, cfg.n_fft, axis=-1)[..., : cfg.hop_length * cfg.n_frames : cfg.hop_length, :]
    spec = scipy.fft.rfft(frames * _stft_window(cfg.window, cfg.win_length, cfg.n_fft), axis=-1, overwrite_x=True, workers=1)
    pw = np.square(spec.real)
    pw += np.square(spec.imag)  # (..., n_frames, n_fft//2+1) float32
    if sum_axis is not None:
        pw = pw.sum(axis=sum_axis - 1)  # y's last axis became (n_frames, bins)
    power = np.swapaxes(pw @ _mel_basis_f32(cfg._mel_key()).T, -1, -2)  # (..., n_mels, n_frames)
    # = librosa.power_to_db(ref=1, amin=db_amin, top_db=None), mapped to [db_min, db_max] -> [0, 1]
    np.maximum(power, np.float32(cfg.db_amin), out=power)
    db = np.log10(power, out=power)
    db *= np.float32(10.0 / (cfg.db_max - cfg.db_min))
    db -= np.float32(cfg.db_min / (cfg.db_max - cfg.db_min))
    return db


@functools.lru_cache(maxsize=16)
def _mel_basis_f32(key: tuple) -> np.ndarray:
    return np.ascontiguousarray(_mel_basis(key).astype(np.float32))


@functools.lru_cache(maxsize=16)
def _resample_blocks(up: int, down: int) -> tuple[int, np.ndarray]:
    """``scipy.signal.resample_poly(x, up, down)`` (default Kaiser FIR, zero padding) as a
    block product: output samples ``up*q .. up*q+up-1`` are ``x[down*(q-D) : down*(q+D+1)]
    @ H``. Returns ``(D, H)`` with ``H`` ((2D+1)*down, up) float64, read off the impulse
    responses of resample_poly itself (so its filter design is the one used)."""
    nb = 64
    while True:
        n, q0 = down * nb, nb // 2
        resp = []
        for r in range(down):
            e = np.zeros(n)
            e[down * q0 + r] = 1.0
            resp.append(scipy.signal.resample_poly(e, up, down).reshape(nb, up))  # (blocks, up)
        nz = np.flatnonzero(np.abs(np.stack(resp)).sum(axis=(0, 2)))
        d = int(max(q0 - nz.min(), nz.max() - q0))
        if d < q0 - 2:
            break
        nb *= 4
    # H[(k, r), p]: weight of x[down*(q + k - D) + r] in y[up*q + p], k = 0..2D
    h = np.stack([np.stack([resp[r][q0 - (k - d)] for r in range(down)]) for k in range(2 * d + 1)])
    return d, h.reshape((2 * d + 1) * down, up)


def resample(x: np.ndarray, up: int, down: int) -> np.ndarray:
    """``scipy.signal.resample_poly(x, up, down, axis=-1)`` in float32. A signal whose length
    is a multiple of ``down`` (10 s at 700 Hz) goes through one matrix product of
    overlapping ``down``-sample blocks (2x faster than resample_poly's float32 loop at 7:6);
    other lengths through resample_poly."""
    x = np.asarray(x, dtype=np.float32)
    n = x.shape[-1]
    if n % down:
        return scipy.signal.resample_poly(x, up, down, axis=-1).astype(np.float32, copy=False)
    d, h = _resample_blocks(up, down)
    xp = pad_last(x, down * d, down * d)
    win = np.lib.stride_tricks.sliding_window_view(xp, (2 * d + 1) * down, axis=-1)[..., ::down, :]  # (..., n/down, K)
    return (win @ h.astype(np.float32)).reshape(*x.shape[:-1], n // down * up)


def acc_logmel(acc: np.ndarray, cfg: PreprocessConfig, fs_tactile: float = C.FS_TACTILE) -> np.ndarray:
    """Vectorised accelerometer path. ``acc`` (B, N, 4, 4, 3) on a uniform grid of
    ``duration * fs_tactile`` samples -> (B, T, 28, 28) float32. One resampling product and
    one STFT + mel product over all 16 x A channels (A: ``acc_signals``) of a trial, float32.
    Trials go one at a time: the temporaries (25 MB per trial) then stay cache- and
    page-resident, 15 % less CPU than one pass over 8 trials."""
    if len(acc) > 1:
        return np.concatenate([acc_logmel(acc[b : b + 1], cfg, fs_tactile) for b in range(len(acc))])
    sig = acc_signals(acc, cfg)  # (B, 16, A, N)
    up, down = _resample_ratio(fs_tactile, cfg.fs_resample)
    y = resample(sig, up, down)  # (B, 16, A, 6000)
    mel = _logmel_from_resampled(y, cfg, sum_axis=-2)  # (B, 16, n_mels, T)
    b = mel.shape[0]
    mel = mel.reshape(b, C.ACC_GRID[0], C.ACC_GRID[1], cfg.n_mels, cfg.n_frames)
    mel = np.moveaxis(mel, (1, 2, 4), (3, 4, 1))  # (B, T, n_mels, 4, 4)
    return tile_layout(mel, cfg.tile_shape).astype(np.float32, copy=False)


# ============================================================================ FSR
def _frame_edges(t: np.ndarray, cfg: PreprocessConfig) -> np.ndarray:
    """Sample index where each frame starts (n_frames + 1 edges, last = end)."""
    rel = np.asarray(t, dtype=np.float64) - float(t[0])
    edges = np.arange(cfg.n_frames + 1) / cfg.frame_rate
    tol = 1e-6 / cfg.frame_rate  # a sample exactly on an edge opens the next frame
    return np.searchsorted(rel, edges - tol, side="left")


def fsr_frames(trials: Sequence[RawTrial], cfg: PreprocessConfig) -> np.ndarray:
    """Mean of the FSR samples whose time stamp falls in each frame (temporal box filter
    + 30 Hz decimation, i.e. anti-aliasing), then optional baseline subtraction and the
    spatial k x k mean -> (B, T, 2, 16, 16) float32 counts."""
    B, T = len(trials), cfg.n_frames
    out = np.empty((B, T, C.FSR_LAYERS, *C.FSR_GRID), dtype=np.float32)
    for b, tr in enumerate(trials):
        # One strided sum per frame (float32 is exact here: <= 2^24 / 4095 samples per frame).
        # Faster than np.add.reduceat along axis 0 and generic in the frame edges.
        e = _frame_edges(tr.t, cfg)
        x = np.asarray(tr.fsr).reshape(len(tr.fsr), -1)
        o = out[b].reshape(T, -1)
        counts = np.diff(e)
        for k in np.flatnonzero(counts):
            np.sum(x[e[k] : e[k + 1]], axis=0, dtype=np.float32, out=o[k])
        o[counts > 0] /= counts[counts > 0, None].astype(np.float32)
        if not counts.all():  # packet gaps / short recording: hold the previous frame
            valid = np.flatnonzero(counts)
            if valid.size == 0:
                raise ValueError(f"trial {tr.name}: no FSR sample inside the {cfg.duration:g} s frame grid")
            src = np.maximum.accumulate(np.where(counts > 0, np.arange(T), -1))
            o[:] = o[np.where(src < 0, valid[0], src)]
    if cfg.fsr_subtract_baseline:
        for b, tr in enumerate(trials):
            if tr.baseline_fsr is not None and len(tr.baseline_fsr):
                base = np.asarray(tr.baseline_fsr, dtype=np.float32).mean(axis=0)
                np.maximum(out[b] - base, 0.0, out=out[b])
    if cfg.fsr_spatial_kernel > 1:
        out = scipy.ndimage.uniform_filter(out, size=(1, 1, 1, cfg.fsr_spatial_kernel, cfg.fsr_spatial_kernel), mode="nearest")
    return out


def fsr_images(trials: Sequence[RawTrial], cfg: PreprocessConfig) -> np.ndarray:
    """(B, T, 2, 28, 28) float32 in [0, 1]."""
    x = fsr_frames(trials, cfg) * np.float32(1.0 / cfg.fsr_max_count)
    return bilinear_resize(x, cfg.resize_hw).astype(np.float32, copy=False)


# ============================================================================ actions
def trial_t0(trial: RawTrial) -> float:
    """Start of the frame grid: first tactile time stamp (pose clock if tactile absent)."""
    return float(trial.t[0]) if len(trial.t) else float(trial.pose_t[0])


def pose_actions(trial: RawTrial, cfg: PreprocessConfig) -> np.ndarray:
    """(T, 6) float32: pose linearly interpolated at the frame centres (edge values held
    outside the pose recording), relative to the first pose sample; positions m -> mm/10,
    angles (unwrapped) rad -> deg/10."""
    pt = np.asarray(trial.pose_t, dtype=np.float64)
    p = np.asarray(trial.pose, dtype=np.float64)[:, :6].copy()
    p[:, 3:] = np.unwrap(p[:, 3:], axis=0)
    p -= p[0]
    tc = trial_t0(trial) + (np.arange(cfg.n_frames) + 0.5) / cfg.frame_rate
    out = np.stack([np.interp(tc, pt, p[:, k]) for k in range(6)], axis=1)
    out[:, :3] *= cfg.pose_pos_scale
    out[:, 3:] *= cfg.pose_ang_scale
    return out.astype(np.float32)


# ============================================================================ time coverage
def time_problems(trial: RawTrial, cfg: PreprocessConfig, fields: Iterable[str]) -> tuple[dict[str, str], float | None]:
    """``({field: problem}, seconds)``: the fields of ``fields`` that cannot be computed
    because the trial is much shorter than the window or misses more than
    :data:`~embodied_tactile.data.rawformat.MAX_MISSING_SHARE` of the window's samples (every
    field), or its pose log does not cover the tactile span (``actions``); ``seconds`` is the trial's length when it is
    longer than the window by more than LONG_FRACTION (cut to it), else None."""
    fields = tuple(fields)
    window = cfg.duration
    t = np.asarray(trial.t, dtype=np.float64) if trial.t is not None else np.empty(0)
    if t.size < 2:
        return {}, None
    fs = float(trial.attrs.get("fs_tactile", C.FS_TACTILE))
    covered = float(t[-1] - t[0]) + 1.0 / fs  # N samples at fs cover N / fs seconds
    if covered < MIN_SPAN_FRACTION * window:
        why = (f"tactile/t: the recording covers {covered:.3g} s, the scene's window is {window:g} s "
               f"(n_frames / frame_rate; at least {MIN_SPAN_FRACTION:.0%} needed)")
        return {f: why for f in fields}, None
    span = min(covered, window)  # the part of the recording the scene's frames are resampled from
    hole = coverage_problem(t, fs, span, what=f"the scene's {span:.3g} s window")
    if hole:  # the resampling would interpolate over it
        return {f: f"tactile/t: {hole}" for f in fields}, None
    out: dict[str, str] = {}
    if "actions" in fields and trial.pose_t is not None and len(trial.pose_t):
        pt = np.asarray(trial.pose_t, dtype=np.float64)
        end = float(t[0]) + min(covered, window)
        fs_pose = float(trial.attrs.get("fs_pose", C.FS_POSE))
        gap = max(0.0, float(pt[0]) - float(t[0])) + max(0.0, end - float(pt[-1]) - 1.0 / fs_pose)
        allowed = max(POSE_GAP_MIN_S, POSE_GAP_FRACTION * window)
        if gap > allowed:
            out["actions"] = (f"pose/t: the pose log covers {pt[0] - t[0]:.3g} .. {pt[-1] - t[0]:.3g} s of the tactile "
                              f"span 0 .. {end - t[0]:.3g} s ({gap:.3g} s uncovered, at most {allowed:.3g} s allowed)")
    return out, (covered if covered > window * (1 + LONG_FRACTION) else None)


# ============================================================================ entry points
def preprocess_trials(
    trials: Sequence[RawTrial], cfg: PreprocessConfig | None = None, fields: Iterable[str] = FIELDS
) -> dict[str, np.ndarray]:
    """Batched preprocessing: ``{field: (B, ...) array}`` for the requested fields only.

    ``acc`` needs only ``t`` and ``acc`` of each trial, ``fsr`` only ``t``, ``fsr`` (and
    ``baseline_fsr``), ``actions`` only ``pose_t``, ``pose`` (and ``t`` for alignment).
    """
    cfg = (cfg or PreprocessConfig()).validate()
    fields = tuple(fields)
    unknown = set(fields) - set(FIELDS)
    if unknown:
        raise ValueError(f"unknown fields {sorted(unknown)}; choose from {FIELDS}")
    out: dict[str, np.ndarray] = {}
    if not trials:
        return out
    if "acc" in fields:
        acc = np.empty((len(trials), cfg.n_frames, *cfg.resize_hw), dtype=np.float32)
        groups: dict[float, list[int]] = {}
        for i, tr in enumerate(trials):
            groups.setdefault(float(tr.attrs.get("fs_tactile", C.FS_TACTILE)), []).append(i)
        for fs, idx in groups.items():
            n = int(round(cfg.duration * fs))
            stack = np.stack([_uniform(trials[i].t, trials[i].acc, fs, n) for i in idx])
            acc[idx] = acc_logmel(stack, cfg, fs)
        out["acc"] = acc
    if "fsr" in fields:
        out["fsr"] = fsr_images(trials, cfg)
    if "actions" in fields:
        out["actions"] = np.stack([pose_actions(tr, cfg) for tr in trials])
    return out


def output_shape(cfg: PreprocessConfig, field: str) -> tuple[int, ...]:
    """Shape of one trial's processed ``field`` (float32), as :func:`preprocess_trials` makes it."""
    shapes = {
        "acc": (cfg.n_frames, *cfg.resize_hw),
        "fsr": (cfg.n_frames, C.FSR_LAYERS, *cfg.resize_hw),
        "actions": (cfg.n_frames, 6),
    }
    return shapes[field]


def preprocess_trial(trial: RawTrial, cfg: PreprocessConfig | None = None, fields: Iterable[str] = FIELDS) -> dict[str, np.ndarray]:
    """One trial: ``acc`` (T, 28, 28), ``fsr`` (T, 2, 28, 28), ``actions`` (T, 6), float32."""
    return {k: v[0] for k, v in preprocess_trials([trial], cfg, fields).items()}
