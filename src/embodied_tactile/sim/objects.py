"""Wave-object surfaces: band-passed white noise, seeded by object id only.

Objects are given as catalogue ids or as ``WaveObject`` (population objects,
``sim.population``); the noise of object id k is the same draw for either."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy import ndimage

from embodied_tactile import constants as C
from embodied_tactile.sim import physics as P

_SURFACE_ENTROPY = 0x5EED_0B1E  # fixed: object k is the same object in every trial


def as_object(obj: int | C.WaveObject) -> C.WaveObject:
    """A catalogue id or an object -> the object."""
    return obj if isinstance(obj, C.WaveObject) else C.get_object(obj)


def surface_key(obj: int | C.WaveObject) -> tuple[int, float]:
    """What a surface depends on: (object id, spatial frequency)."""
    o = as_object(obj)
    return int(o.object_id), float(o.spatial_frequency)


@lru_cache(maxsize=64)
def _unit_surface(object_id: int, spatial_frequency: float) -> np.ndarray:
    """Band-passed white noise of object ``object_id`` at centre frequency
    ``spatial_frequency`` (1/m) scaled to peak-to-peak 1 (float64, mean 0 over the block).
    Read-only, cached."""
    rng = np.random.default_rng(np.random.SeedSequence([_SURFACE_ENTROPY, int(object_id)]))
    n = P.SURFACE_N
    white = rng.standard_normal((n, n))
    k = np.fft.fftfreq(n, d=P.SURFACE_DX_M)  # 1/m
    kr = np.hypot(k[:, None], k[None, :])
    sigma = max(P.BAND_REL_SIGMA * spatial_frequency, P.BAND_MIN_SIGMA)
    band = np.exp(-0.5 * ((kr - spatial_frequency) / sigma) ** 2)
    band[0, 0] = 0.0
    h = np.fft.ifft2(np.fft.fft2(white) * band).real
    h -= h.mean()
    h /= h.max() - h.min()
    h.setflags(write=False)
    return h


def surface(obj: int | C.WaveObject, amplitude_mm: float | None = None) -> np.ndarray:
    """Height (m) on the SURFACE_N^2 grid, peak-to-peak = amplitude over the whole block."""
    o = as_object(obj)
    return _surface(*surface_key(o), o.amplitude_mm if amplitude_mm is None else float(amplitude_mm))


@lru_cache(maxsize=64)
def _surface(object_id: int, spatial_frequency: float, amplitude_mm: float) -> np.ndarray:
    h = _unit_surface(object_id, spatial_frequency) * (amplitude_mm * 1e-3)
    h.setflags(write=False)
    return h


def sample(h: np.ndarray, x: np.ndarray, y: np.ndarray, order: int = 1) -> np.ndarray:
    """Heights at object-frame positions (m; block centred on 0), periodic block."""
    c = (P.SURFACE_N - 1) / 2.0
    coords = np.stack([np.ravel(x) / P.SURFACE_DX_M + c, np.ravel(y) / P.SURFACE_DX_M + c])
    out = ndimage.map_coordinates(h, coords, order=order, mode="grid-wrap", prefilter=order > 1)
    return out.reshape(np.shape(x))


def spline_coeffs(obj: int | C.WaveObject, amplitude_mm: float | None = None) -> np.ndarray:
    """Cubic B-spline coefficients of an object's heightmap (for smooth order-3 sampling)."""
    o = as_object(obj)
    return _spline_coeffs(*surface_key(o), o.amplitude_mm if amplitude_mm is None else float(amplitude_mm))


@lru_cache(maxsize=64)
def _spline_coeffs(object_id: int, spatial_frequency: float, amplitude_mm: float) -> np.ndarray:
    out = ndimage.spline_filter(_surface(object_id, spatial_frequency, amplitude_mm), order=3, mode="grid-wrap")
    out.setflags(write=False)
    return out


def sample_spline(coeffs: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    c = (P.SURFACE_N - 1) / 2.0
    coords = np.stack([np.ravel(x) / P.SURFACE_DX_M + c, np.ravel(y) / P.SURFACE_DX_M + c])
    out = ndimage.map_coordinates(coeffs, coords, order=3, mode="grid-wrap", prefilter=False)
    return out.reshape(np.shape(x))
