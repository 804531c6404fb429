"""The raw trial format: one HDF5 file holds many trials, one group per trial.

This is the single reader/writer/validator of raw e-Skin trials; the simulator, the
serial recorder, preprocessing and the DataModule all go through it. Layout (see
``docs/reference/data_format.md``)::

    /                       attrs: format="embodied-tactile-raw", format_version=1
    /trials/<name>/         attrs: see REQUIRED_ATTRS / OPTIONAL_ATTRS
        tactile/t           (N,)            float64  s, strictly increasing
        tactile/acc         (N, 4, 4, 3)    float32  g, grid order (row-major 4x4), axes x,y,z
        tactile/fsr         (N, 2, 16, 16)  uint16   ADC counts 0..4095, layer 0 top, 1 bottom
        tactile/lost_at     (L,)            int64    optional (recorder): one entry per lost packet,
                                                     the index of the sample after the gap, 0..N
        pose/t              (M,)            float64  s, same clock as tactile/t
        pose/ee             (M, K>=6)       float32  x, y, z (m), roll, pitch, yaw (rad), extras
        baseline/{t,acc,fsr,lost_at}        optional no-contact baseline, same dtypes

A trial's identity is its group: (file, group name). The group name, not the attributes,
names the trial in caches and splits (a group may be renamed), and must be unique across
the files of one dataset (``check_unique_names``).

Every problem is reported as a :class:`TrialFormatError` naming file, trial and field.
A declared rate (``fs_tactile``, ``fs_pose``) must match its timestamps (``tactile/t``,
``baseline/t``, ``pose/t``) within ``RATE_TOLERANCE`` (:func:`_check_rate`); a clock may not
jump forward by more than :func:`gap_limit` where no lost packet is recorded, the pose log's
clock included (:func:`_check_continuity`).
A bad trial is skipped with a warning (``strict=True`` makes it fatal); it never takes the
other trials of the file down.
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

import h5py
import hdf5plugin  # registers the Blosc filter (new files) with HDF5; gzip files need nothing
import numpy as np

from embodied_tactile import constants as C

log = logging.getLogger(__name__)

FORMAT_NAME = "embodied-tactile-raw"
FORMAT_VERSION = 1

#: Field name -> dataset path inside a trial group.
FIELDS: Mapping[str, str] = {
    "t": "tactile/t",
    "acc": "tactile/acc",
    "fsr": "tactile/fsr",
    "lost_at": "tactile/lost_at",
    "pose_t": "pose/t",
    "pose": "pose/ee",
    "baseline_t": "baseline/t",
    "baseline_acc": "baseline/acc",
    "baseline_fsr": "baseline/fsr",
    "baseline_lost_at": "baseline/lost_at",
}
#: Where packets were lost (recorder): field -> the clock its sample indices refer to.
#: Optional; files written before it existed have none and stay valid.
LOST_FIELDS: Mapping[str, str] = {"lost_at": "t", "baseline_lost_at": "baseline_t"}
TACTILE_FIELDS = ("t", "acc", "fsr")
POSE_FIELDS = ("pose_t", "pose")
ALL_REQUIRED_FIELDS = ("t", "acc", "fsr", "pose_t", "pose")

#: attr -> python type it must convert to. Factors are NaN where unknown (recordings of
#: objects outside the catalogue).
REQUIRED_ATTRS: Mapping[str, type] = {
    "object_id": int,
    "skin": str,
    "primitive": str,
    "action_index": int,
    "action_params": np.ndarray,
    "action_param_names": str,  # JSON list
    "repetition": int,
    "spatial_frequency": float,
    "amplitude": float,
    "stiffness": float,
    "heterogeneity": float,
    "source": str,
    "fs_tactile": float,
    "fs_pose": float,
    "seed": int,
}
OPTIONAL_ATTRS: Mapping[str, type] = {
    "complete": bool,  # recorder: False while recording / after an interrupted trial
    "lost_packets": int,
    "missing_share": float,  # recorder: 1 - packets / (duration x fs_tactile)
    "device": str,
    "notes": str,
    "sim_physics_version": int,  # simulator: version of its physics (sim.physics.PHYSICS_VERSION); absent = 1
}

#: Documented ranges of the physical attributes (inclusive). The four factors may also be
#: NaN (unknown: that factor is left out of that factor's alignment); infinite values and
#: values outside these ranges are a format error. Heterogeneity is a class: 0 or 1.
PHYSICAL_RANGES: Mapping[str, tuple[float, float]] = {
    "spatial_frequency": (0.0, 1000.0),  # 1/m (catalogue and population: 10 .. 50)
    "amplitude": (0.0, 100.0),           # mm peak-to-peak (5 .. 20)
    "stiffness": (2.0, 11.0),            # log10 Pa of the bulk's Young's modulus (silicones ~4 .. 6, PLA 9.5)
    "heterogeneity": (0.0, 1.0),         # 0 or 1
}
#: Sampling rates may not exceed this (Hz); they must be finite and positive.
MAX_RATE_HZ = 100_000.0

#: Clock field -> the attribute that declares its sampling rate.
RATE_ATTRS: Mapping[str, str] = {"t": "fs_tactile", "baseline_t": "fs_tactile", "pose_t": "fs_pose"}
#: A declared step 1 / fs is accepted within the quartiles of the timestamps' steps widened
#: by this fraction: jitter, bursts, lost packets and a board a few percent off pass, a
#: rate declared twice or half too high on regular timestamps does not.
RATE_TOLERANCE = 0.2
#: Continuity of a clock: a step longer than ``max(MAX_GAP_S, GAP_STEPS / fs)`` is a gap,
#: accepted only where the trial's lost-packet positions (``tactile/lost_at``,
#: ``baseline/lost_at``) record a lost packet at the sample after it (the pose log, which
#: has none, may have no gap).
MAX_GAP_S = 0.5
GAP_STEPS = 10
#: Coverage: the share of the samples a clock's declared rate gives its span (a trial's whole
#: ``tactile/t``; the preprocessing's window of it) that may be missing -- lost, garbage, never
#: polled. Above it the recorder does not store ``complete=True``, the validator rejects the
#: trial and the preparation skips it (the resampling would interpolate that share).
MAX_MISSING_SHARE = 0.10


def missing_share(t: np.ndarray, fs: float, span: float | None = None) -> tuple[float, int, int, float, float]:
    """``(share, got, expected, largest gap s, its start s)`` of the samples a clock ``t`` of
    declared rate ``fs`` lacks over its first ``span`` seconds (default: all of it, ``t[-1] -
    t[0] + 1 / fs``): ``expected = span x fs``, ``got`` the samples in ``[t[0], t[0] + span)``,
    ``share = max(0, 1 - got / expected)``."""
    t = np.asarray(t, dtype=np.float64)
    if t.size < 2 or not fs > 0:
        return 0.0, int(t.size), int(t.size), 0.0, 0.0
    span = float(t[-1] - t[0]) + 1.0 / fs if span is None else float(span)
    expected = span * fs
    got = int(np.searchsorted(t, t[0] + span - 0.5 / fs))
    steps = np.diff(t[: max(got, 2)])
    i = int(np.argmax(steps))
    return max(0.0, 1.0 - got / expected), got, int(round(expected)), float(steps[i]), float(t[i] - t[0])


def coverage_problem(t: np.ndarray, fs: float, span: float | None = None, what: str = "the trial") -> str | None:
    """Why ``t`` misses more than :data:`MAX_MISSING_SHARE` of its samples over ``span``
    (:func:`missing_share`), or None."""
    share, got, expected, gap, at = missing_share(t, fs, span)
    if share <= MAX_MISSING_SHARE:
        return None
    return (f"{share:.1%} of the samples of {what} missing ({got} of the {expected} that fs_tactile={fs:g} Hz gives; "
            f"largest gap {gap:.3g} s at {at:.3g} s); at most {MAX_MISSING_SHARE:.0%} may be missing "
            "(rawformat.MAX_MISSING_SHARE)")

_DTYPES: Mapping[str, tuple[np.dtype, ...]] = {
    "t": (np.dtype("float64"),),
    "acc": (np.dtype("float32"), np.dtype("float64")),
    "fsr": (np.dtype("uint16"),),
    "pose_t": (np.dtype("float64"),),
    "pose": (np.dtype("float32"), np.dtype("float64")),
    "baseline_t": (np.dtype("float64"),),
    "baseline_acc": (np.dtype("float32"), np.dtype("float64")),
    "baseline_fsr": (np.dtype("uint16"),),
    "lost_at": (np.dtype("int64"),),
    "baseline_lost_at": (np.dtype("int64"),),
}
_TAIL_SHAPES: Mapping[str, tuple[int, ...] | None] = {
    "t": (),
    "acc": (*C.ACC_GRID, C.ACC_AXES),
    "fsr": (C.FSR_LAYERS, *C.FSR_GRID),
    "pose_t": (),
    "pose": None,  # (M, K>=6)
    "baseline_t": (),
    "baseline_acc": (*C.ACC_GRID, C.ACC_AXES),
    "baseline_fsr": (C.FSR_LAYERS, *C.FSR_GRID),
    "lost_at": (),
    "baseline_lost_at": (),
}


class TrialFormatError(ValueError):
    """A raw trial that does not meet the format. Names file, trial and field."""

    def __init__(self, file: str | os.PathLike, trial: str, field: str, problem: str):
        self.file = str(file)
        self.trial = trial
        self.field = field
        self.problem = problem
        super().__init__(f"{self.file}: trial '{trial}', field '{field}': {problem}")

    def __reduce__(self):  # picklable across process pools
        return (type(self), (self.file, self.trial, self.field, self.problem))


@dataclass
class RawTrial:
    """One trial in memory. Arrays as stored; ``attrs`` holds every REQUIRED_ATTRS key.

    ``group`` is the name of the group it was read from (its identity, see
    :func:`read_trial`); a trial built in memory has none and is named by its attributes.
    """

    t: np.ndarray
    acc: np.ndarray
    fsr: np.ndarray
    pose_t: np.ndarray
    pose: np.ndarray
    attrs: dict[str, Any]
    baseline_t: np.ndarray | None = None
    baseline_acc: np.ndarray | None = None
    baseline_fsr: np.ndarray | None = None
    lost_at: np.ndarray | None = None
    baseline_lost_at: np.ndarray | None = None
    group: str | None = None

    @property
    def name(self) -> str:
        """The group name: where the trial was read from, else :func:`trial_name`."""
        return self.group if self.group is not None else trial_name(self.attrs)

    @property
    def factors(self) -> np.ndarray:
        return np.array([float(self.attrs[k]) for k in C.FACTOR_NAMES], dtype=np.float64)


def trial_name(attrs: Mapping[str, Any]) -> str:
    """Canonical group name, e.g. ``obj07_soft_sliding_a03_r00``."""
    return (
        f"obj{int(attrs['object_id']):02d}_{attrs['skin']}_{attrs['primitive']}"
        f"_a{int(attrs['action_index']):02d}_r{int(attrs['repetition']):02d}"
    )


def make_attrs(
    *,
    object_id: int,
    skin: str,
    primitive: str,
    action_index: int,
    repetition: int,
    source: str,
    seed: int,
    factors: Sequence[float] | None = None,
    fs_tactile: float = C.FS_TACTILE,
    fs_pose: float = C.FS_POSE,
    **extra: Any,
) -> dict[str, Any]:
    """Attributes of a trial of object ``object_id``: the factors (from the catalogue for a
    catalogue id unless given; pass them, or NaNs for an unknown object, otherwise) and any
    ``extra`` attributes, e.g. the object's physical description (``WaveObject.description``)."""
    action = C.get_action(primitive, action_index)
    if factors is None:
        if not 0 <= int(object_id) < C.N_OBJECTS:
            raise ValueError(f"object {object_id} is not in the catalogue (0..{C.N_OBJECTS - 1}): pass its factors")
        factors = C.get_object(object_id).factors()
    attrs: dict[str, Any] = {
        "object_id": int(object_id),
        "skin": str(skin),
        "primitive": str(primitive),
        "action_index": int(action_index),
        "action_params": action.as_array(),
        "action_param_names": json.dumps(list(C.ACTION_PARAM_NAMES[primitive])),
        "repetition": int(repetition),
        "source": str(source),
        "fs_tactile": float(fs_tactile),
        "fs_pose": float(fs_pose),
        "seed": int(seed),
    }
    attrs.update({k: float(v) for k, v in zip(C.FACTOR_NAMES, factors)})
    attrs.update(extra)
    return attrs


# --------------------------------------------------------------------------- writing
#: Blosc LZ4 with bit shuffle for new files: about gzip-1 + shuffle's size (3.4 vs 3.3 MB per
#: simulated trial) at a fifth of its decode time (5 vs 28 CPU ms per trial; docs/reference/preprocessing.md,
#: benchmarks/bench_preprocess.py). Files written with gzip earlier read unchanged: the filter
#: is a property of each stored dataset.
_COMPRESSION = dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.BITSHUFFLE))


def _ensure_root(f: h5py.File) -> h5py.Group:
    if "format" not in f.attrs:
        f.attrs["format"] = FORMAT_NAME
        f.attrs["format_version"] = FORMAT_VERSION
    return f.require_group("trials")


def _set_attrs(g: h5py.Group, attrs: Mapping[str, Any]) -> None:
    for k, v in attrs.items():
        g.attrs[k] = np.asarray(v, dtype=np.float64) if k == "action_params" else v


def write_trial(target: str | os.PathLike | h5py.File, trial: RawTrial, *, overwrite: bool = False) -> str:
    """Write ``trial`` as a group of ``target`` (a path, opened in append mode, or an open
    file). Returns the group name. The trial is validated before anything is written."""
    if not isinstance(target, h5py.File):
        with h5py.File(target, "a") as f:
            return write_trial(f, trial, overwrite=overwrite)
    validate_arrays(target.filename, trial.name, trial)
    trials = _ensure_root(target)
    name = trial.name
    if name in trials:
        if not overwrite:
            raise FileExistsError(f"{target.filename}: trial '{name}' exists (overwrite=False)")
        del trials[name]
    g = trials.create_group(name)
    for fld, path in FIELDS.items():
        arr = getattr(trial, fld)
        if arr is None:
            continue
        opts = _COMPRESSION if arr.ndim > 1 else {}
        # One-second chunks along time: few, large compressed blocks decode much faster than
        # h5py's automatic small chunks, and a modality reads whole trials anyway.
        chunks = (min(arr.shape[0], int(trial.attrs.get("fs_tactile", C.FS_TACTILE))), *arr.shape[1:]) if opts and arr.shape[0] else None
        g.create_dataset(path, data=arr, chunks=chunks, **opts)
    _set_attrs(g, trial.attrs)
    return name


class IncrementalTrialWriter:
    """Append tactile and pose samples to a trial group as they arrive (for recorders).

    Datasets are chunked and resizable; :meth:`flush` makes everything appended so far
    durable. The trial carries ``complete=False`` until :meth:`close` with ``complete=True``,
    so an interrupted recording stays readable and is marked as such. ``lost_at`` /
    ``baseline_lost_at`` take the sample index of each lost packet (kept even when empty:
    an empty ``tactile/lost_at`` says no packet was lost).
    """

    def __init__(self, path: str | os.PathLike, attrs: Mapping[str, Any], *, chunk: int = 700, pose_columns: int = 6):
        self.path = Path(path)
        self.chunk = int(chunk)
        self.file = h5py.File(self.path, "a")  # default libver: no SWMR status flags, so a crash leaves a file that opens
        trials = _ensure_root(self.file)
        self.name = trial_name(attrs)
        if self.name in trials:
            raise FileExistsError(f"{self.path}: trial '{self.name}' exists")
        self.group = trials.create_group(self.name)
        _set_attrs(self.group, {**attrs, "complete": False})
        self._ds: dict[str, h5py.Dataset] = {}
        for fld in FIELDS:
            tail = _TAIL_SHAPES[fld] if fld != "pose" else (pose_columns,)
            rows = min(chunk, 64) if fld in LOST_FIELDS else chunk
            self._ds[fld] = self.group.create_dataset(
                FIELDS[fld], shape=(0, *tail), maxshape=(None, *tail), dtype=_DTYPES[fld][0], chunks=(rows, *tail)
            )
        self.file.flush()
        self._flushed = {fld: 0 for fld in FIELDS}

    def append(self, fld: str, values: np.ndarray) -> None:
        ds = self._ds[fld]
        values = np.asarray(values, dtype=ds.dtype)
        if values.shape[1:] != ds.shape[1:]:
            values = values.reshape(-1, *ds.shape[1:])
        n = ds.shape[0]
        ds.resize(n + values.shape[0], axis=0)
        ds[n:] = values

    def count(self, fld: str) -> int:
        return int(self._ds[fld].shape[0])

    def set_attrs(self, **attrs: Any) -> None:
        _set_attrs(self.group, attrs)

    def flush(self) -> None:
        self.file.flush()
        self._flushed = {fld: int(ds.shape[0]) for fld, ds in self._ds.items()}

    def rollback(self) -> None:
        """Cut every dataset back to its length at the last :meth:`flush` (a batch whose
        write failed half way leaves no field longer than its clock)."""
        for fld, ds in self._ds.items():
            if ds.shape[0] != self._flushed[fld]:
                ds.resize(self._flushed[fld], axis=0)

    def close(self, *, complete: bool) -> None:
        if not self.file.id.valid:
            return
        baseline = [f for f in FIELDS if f.startswith("baseline")]
        if all(self._ds[f].shape[0] == 0 for f in baseline):
            for fld in baseline:
                del self.group[FIELDS[fld]]
            del self.group["baseline"]
        self.group.attrs["complete"] = bool(complete)
        self.file.flush()
        self.file.close()

    def abandon(self) -> None:
        """Close after a failed write, writing nothing more (errors of the close ignored):
        the trial keeps what its last successful :meth:`flush` stored, ``complete=False``."""
        if not self.file.id.valid:
            return
        try:
            self.file.close()
        except (OSError, RuntimeError) as exc:
            log.warning("%s: closing after a failed write: %s", self.path, exc)


# --------------------------------------------------------------------------- validation
def _check_attrs(file: str, name: str, attrs: Mapping[str, Any]) -> None:
    for key, typ in REQUIRED_ATTRS.items():
        if key not in attrs:
            raise TrialFormatError(file, name, f"attrs/{key}", "required attribute is missing")
        val = attrs[key]
        try:
            if typ is np.ndarray:
                arr = np.asarray(val, dtype=np.float64)
                if arr.ndim != 1 or not np.all(np.isfinite(arr)):
                    raise ValueError("must be a finite 1-D float array")
            elif typ is str:
                if not isinstance(val, (str, bytes)):
                    raise ValueError(f"must be a string, got {type(val).__name__}")
            elif typ is int:
                if float(val) != int(val):
                    raise ValueError("must be an integer")
            else:
                float(val)
        except (TypeError, ValueError) as exc:
            raise TrialFormatError(file, name, f"attrs/{key}", f"bad value {val!r}: {exc}") from None
    if _s(attrs["skin"]) not in C.SKINS:
        raise TrialFormatError(file, name, "attrs/skin", f"must be one of {C.SKINS}, got {_s(attrs['skin'])!r}")
    if _s(attrs["primitive"]) not in C.PRIMITIVES:
        raise TrialFormatError(file, name, "attrs/primitive", f"must be one of {C.PRIMITIVES}, got {_s(attrs['primitive'])!r}")
    if _s(attrs["source"]) not in C.SOURCES:
        raise TrialFormatError(file, name, "attrs/source", f"must be one of {C.SOURCES}, got {_s(attrs['source'])!r}")
    if not 0 <= int(attrs["action_index"]) < C.N_ACTIONS:
        raise TrialFormatError(file, name, "attrs/action_index", f"must be in 0..{C.N_ACTIONS - 1}")
    for key in ("fs_tactile", "fs_pose"):
        if not 0 < float(attrs[key]) <= MAX_RATE_HZ:
            raise TrialFormatError(file, name, f"attrs/{key}",
                                   f"sampling rate {float(attrs[key])!r} Hz: must be finite, positive and <= {MAX_RATE_HZ:g}")
    for key in ("object_id", "repetition"):
        if int(attrs[key]) < 0:
            raise TrialFormatError(file, name, f"attrs/{key}", f"must be >= 0, got {int(attrs[key])}")
    for key, (lo, hi) in PHYSICAL_RANGES.items():
        v = float(attrs[key])
        if math.isnan(v):
            continue  # unknown: allowed
        if not lo <= v <= hi:
            raise TrialFormatError(file, name, f"attrs/{key}", f"{v!r} outside the documented range [{lo:g}, {hi:g}] "
                                   "(NaN if unknown; docs/reference/data_format.md)")
        if key == "heterogeneity" and v not in (0.0, 1.0):
            raise TrialFormatError(file, name, f"attrs/{key}", f"{v!r}: must be 0 or 1 (NaN if unknown)")


def check_attrs(file: str | os.PathLike, name: str, attrs: Mapping[str, Any]) -> None:
    """The attribute checks of :func:`scan_raw` on one trial's attributes (the recorder runs
    them before its first packet): TrialFormatError naming file, trial and attribute."""
    _check_attrs(str(file), name, attrs)


def _s(v: Any) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def _check_array(file: str, name: str, fld: str, arr: np.ndarray | h5py.Dataset, n: int | None) -> None:
    path = FIELDS[fld]
    if arr.dtype not in _DTYPES[fld]:
        raise TrialFormatError(file, name, path, f"dtype {arr.dtype} not in {[str(d) for d in _DTYPES[fld]]}")
    tail = _TAIL_SHAPES[fld]
    if tail is None:  # pose: (M, K>=6)
        if arr.ndim != 2 or arr.shape[1] < 6:
            raise TrialFormatError(file, name, path, f"shape {arr.shape}, expected (M, K>=6)")
    elif arr.ndim != 1 + len(tail) or tuple(arr.shape[1:]) != tail:
        raise TrialFormatError(file, name, path, f"shape {arr.shape}, expected (N, {', '.join(map(str, tail))})".replace(", )", ")"))
    if n is not None and arr.shape[0] != n:
        raise TrialFormatError(file, name, path, f"has {arr.shape[0]} samples, its timestamps have {n} (truncated?)")


def _check_values(file: str, name: str, fld: str, data: np.ndarray) -> None:
    path = FIELDS[fld]
    if data.shape[0] < 2 and fld in ("t", "pose_t"):
        raise TrialFormatError(file, name, path, f"needs at least 2 samples, has {data.shape[0]}")
    if data.dtype.kind == "f":
        bad = ~np.isfinite(data)
        if bad.any():
            idx = np.argwhere(bad)[0]
            raise TrialFormatError(file, name, path, f"{int(bad.sum())} non-finite value(s), first at index {tuple(int(i) for i in idx)}")
    if fld.endswith("t") and fld in ("t", "pose_t", "baseline_t"):
        d = np.diff(data)
        if (d <= 0).any():
            i = int(np.argmax(d <= 0))
            raise TrialFormatError(file, name, path, f"timestamps not strictly increasing at sample {i + 1} ({data[i]!r} -> {data[i + 1]!r})")
    if fld.endswith("fsr") and data.size and int(data.max()) > C.FSR_MAX_COUNT:
        raise TrialFormatError(file, name, path, f"count {int(data.max())} exceeds the 12-bit range 0..{C.FSR_MAX_COUNT}")
    if fld.endswith("acc") and data.size and float(np.abs(data).max()) > C.ACC_RANGE_G * 1.0001:
        raise TrialFormatError(file, name, path, f"|acc| {float(np.abs(data).max()):.3g} g exceeds the +-{C.ACC_RANGE_G} g range")


def rate_problem(t: np.ndarray, declared: float) -> str | None:
    """Why timestamps ``t`` do not fit the declared rate ``declared`` (Hz), or None: the
    declared step ``1 / fs`` must lie within the steps' interquartile range widened by
    ``RATE_TOLERANCE`` (regular timestamps: the median step within the tolerance; a polled
    stream that arrives in bursts or with jitter: anywhere among its typical steps). The
    recorder applies it to its first second, :func:`scan_raw` to the whole clock."""
    q25, median, q75 = (float(v) for v in np.quantile(np.diff(np.asarray(t, dtype=np.float64)), [0.25, 0.5, 0.75]))
    if q25 / (1 + RATE_TOLERANCE) <= 1.0 / declared <= q75 * (1 + RATE_TOLERANCE):
        return None
    shown = 1.0 / median if median > 0 else math.inf
    return (f"timestamps show {shown:.4g} Hz (median step {median * 1e3:.4g} ms, quartiles {q25 * 1e3:.4g} to "
            f"{q75 * 1e3:.4g} ms) but {{key}} declares {declared:g} Hz (a step of {1e3 / declared:.4g} ms; "
            f"tolerance {RATE_TOLERANCE:.0%})")


def _check_rate(file: str, name: str, fld: str, data: np.ndarray, attrs: Mapping[str, Any] | None) -> None:
    """The rate declared for clock ``fld`` (``RATE_ATTRS``) against its timestamps (:func:`rate_problem`)."""
    key = RATE_ATTRS.get(fld)
    if key is None or attrs is None or key not in attrs or data.shape[0] < 2:
        return
    problem = rate_problem(data, float(attrs[key]))
    if problem:
        raise TrialFormatError(file, name, FIELDS[fld], problem.format(key=f"attrs/{key}") + f": fix {key} or the timestamps")


def gap_limit(declared: float | None) -> float:
    """The longest step a clock of declared rate ``declared`` (Hz) may take without a lost
    packet recorded there: ``max(MAX_GAP_S, GAP_STEPS / declared)``."""
    return max(MAX_GAP_S, GAP_STEPS / float(declared)) if declared else MAX_GAP_S


def _check_continuity(file: str, name: str, data: Mapping[str, np.ndarray], attrs: Mapping[str, Any] | None) -> None:
    """Gaps in each clock (the pose log's included) beyond :func:`gap_limit` that no lost
    packet explains: TrialFormatError naming the clock, the sample and the sizes. (Whether
    the pose log covers the part of the tactile clock a scene uses is the preprocessing's
    check, which knows the window.)"""
    attrs = attrs or {}
    for clock, lost in (("t", "lost_at"), ("baseline_t", "baseline_lost_at"), ("pose_t", None)):
        t = data.get(clock)
        if t is None or len(t) < 2:
            continue
        rate = attrs.get(RATE_ATTRS[clock])
        limit = gap_limit(float(rate) if rate else None)
        steps = np.diff(np.asarray(t, dtype=np.float64))
        after = np.flatnonzero(steps > limit) + 1  # the sample after each gap
        if lost is not None and lost in data and after.size:
            after = after[~np.isin(after, np.asarray(data[lost]))]
        if after.size:
            i = int(after[0])
            raise TrialFormatError(
                file, name, FIELDS[clock],
                f"{after.size} gap(s) longer than {limit:.3g} s; the first {steps[i - 1]:.3g} s before sample {i} "
                f"({float(t[i - 1]):.6g} s -> {float(t[i]):.6g} s), with no lost packet recorded there"
                + (f" ({FIELDS[lost]})" if lost is not None else "") + " (rawformat.MAX_GAP_S / GAP_STEPS)")


def _check_coverage(file: str, name: str, data: Mapping[str, np.ndarray], attrs: Mapping[str, Any] | None) -> None:
    """The trial's ``tactile/t`` against its declared ``fs_tactile`` (:func:`coverage_problem`)."""
    t, fs = data.get("t"), (attrs or {}).get("fs_tactile")
    if t is None or not fs:
        return
    problem = coverage_problem(t, float(fs))
    if problem:
        raise TrialFormatError(file, name, FIELDS["t"], problem)


def _check_lost(file: str, name: str, fld: str, data: np.ndarray, n: int | None) -> None:
    """Lost-packet positions: sample indices 0..n (n = after the last sample), non-decreasing."""
    path = FIELDS[fld]
    if n is None:
        raise TrialFormatError(file, name, path, f"present without its clock {FIELDS[LOST_FIELDS[fld]]}")
    if data.size and (int(data.min()) < 0 or int(data.max()) > n):
        raise TrialFormatError(file, name, path, f"sample index {int(data.min()) if data.min() < 0 else int(data.max())} outside 0..{n}")
    d = np.diff(data)
    if (d < 0).any():
        i = int(np.argmax(d < 0))
        raise TrialFormatError(file, name, path, f"indices decrease at entry {i + 1} ({int(data[i])} -> {int(data[i + 1])})")


def fields_needed(fields: Iterable[str]) -> list[str]:
    """The fields to read for ``fields``: with their clocks, and with the clocks' lost-packet
    positions (validated whenever the clock is read; optional)."""
    need = set(fields)
    if need & {"acc", "fsr"}:
        need.add("t")
    if "pose" in need:
        need.add("pose_t")
    need.update(lost for lost, clock in LOST_FIELDS.items() if clock in need)
    return [f for f in FIELDS if f in need]


def _clock(fld: str) -> str:
    return "pose_t" if fld.startswith("pose") else "baseline_t" if fld.startswith("baseline") else "t"


def _optional(fld: str) -> bool:
    return fld.startswith("baseline") or fld in LOST_FIELDS


def validate_arrays(file: str | os.PathLike, name: str, trial: RawTrial, fields: Iterable[str] = ALL_REQUIRED_FIELDS) -> None:
    """Validate an in-memory trial (used before writing)."""
    file = str(file)
    _check_attrs(file, name, trial.attrs)
    counts = {"t": None, "pose_t": None, "baseline_t": None}
    for fld in fields_needed(fields):
        arr = getattr(trial, fld)
        if arr is None:
            if _optional(fld):
                continue
            raise TrialFormatError(file, name, FIELDS[fld], "required dataset is missing")
        arr = np.asarray(arr)
        clock = _clock(fld)
        _check_array(file, name, fld, arr, counts[clock] if fld != clock and fld not in LOST_FIELDS else None)
        if fld == clock:
            counts[clock] = arr.shape[0]
        _check_values(file, name, fld, arr)
        _check_rate(file, name, fld, arr, trial.attrs)
        if fld in LOST_FIELDS:
            _check_lost(file, name, fld, arr, counts[clock])
    present = {f: np.asarray(getattr(trial, f)) for f in fields_needed(fields) if getattr(trial, f) is not None}
    _check_continuity(file, name, present, trial.attrs)
    _check_coverage(file, name, present, trial.attrs)


def _read_group(file: str, name: str, g: h5py.Group, fields: Iterable[str], check: bool = True,
                attrs: Mapping[str, Any] | None = None) -> dict[str, np.ndarray]:
    """Read (and validate) the named fields of one trial group; opens only those datasets.
    ``attrs``: the group's attributes, for the rate check of each clock."""
    out: dict[str, np.ndarray] = {}
    counts: dict[str, int | None] = {"t": None, "pose_t": None, "baseline_t": None}
    for fld in fields_needed(fields):
        path = FIELDS[fld]
        try:
            if path not in g:
                if _optional(fld):
                    continue
                raise TrialFormatError(file, name, path, "required dataset is missing")
            ds = g[path]
            if not isinstance(ds, h5py.Dataset):
                raise TrialFormatError(file, name, path, "is not a dataset")
            clock = _clock(fld)
            if check:
                _check_array(file, name, fld, ds, counts[clock] if fld != clock and fld not in LOST_FIELDS else None)
            data = ds[()]
        except TrialFormatError:
            raise
        except (OSError, KeyError, RuntimeError, ValueError) as exc:  # corrupt chunks, truncated file
            raise TrialFormatError(file, name, path, f"unreadable ({type(exc).__name__}: {exc})") from None
        if fld == clock:
            counts[clock] = data.shape[0]
        if check:
            _check_values(file, name, fld, data)
            _check_rate(file, name, fld, data, attrs)
            if fld in LOST_FIELDS:
                _check_lost(file, name, fld, data, counts[clock])
        out[fld] = data
    if check:
        _check_continuity(file, name, out, attrs)
        _check_coverage(file, name, out, attrs)
    return out


def read_attrs(g: h5py.Group) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in g.attrs.items():
        if isinstance(v, bytes):
            v = v.decode()
        elif isinstance(v, np.generic):
            v = v.item()
        out[k] = v
    return out


# --------------------------------------------------------------------------- reading
@dataclass
class TrialInfo:
    """A validated trial's address and attributes (no sensor data loaded)."""

    file: str
    name: str
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def factors(self) -> np.ndarray:
        return np.array([float(self.attrs[k]) for k in C.FACTOR_NAMES], dtype=np.float64)


def open_raw(path: str | os.PathLike) -> h5py.File:
    """Open a raw file read-only, turning any failure into a TrialFormatError naming the file."""
    path = str(path)
    try:
        f = h5py.File(path, "r")
    except (OSError, ValueError) as exc:
        raise TrialFormatError(path, "*", "file", f"cannot open HDF5 file ({exc})") from None
    if "trials" not in f:
        f.close()
        raise TrialFormatError(path, "*", "trials", "no /trials group: not a raw trial file")
    return f


def unique_paths(paths: Iterable[str | os.PathLike]) -> list[str]:
    """Each file once (the same file under two spellings too), first spelling and order kept."""
    seen: dict[str, str] = {}
    for p in paths:
        seen.setdefault(os.path.realpath(os.path.expanduser(str(p))), str(p))
    return list(seen.values())


def check_unique_names(files_by_name: Mapping[str, Sequence[str]]) -> None:
    """A trial is one group of one file, and its group name identifies it (in caches and
    splits): a name held by two files of one dataset is an error naming both files, whatever
    the state of either copy. Rename one group to keep both (``docs/reference/data_format.md``)."""
    dups = {n: fs for n, fs in files_by_name.items() if len(fs) > 1}
    if not dups:
        return
    name = sorted(dups)[0]
    others = "; ".join(f"'{n}' in {' and '.join(dups[n])}" for n in sorted(dups)[1:6])
    more = f" ({len(dups) - 1} more duplicate name(s): {others}{' ...' if len(dups) > 6 else ''})" if len(dups) > 1 else ""
    raise TrialFormatError(
        dups[name][1], name, "group",
        f"duplicate trial: the group name '{name}' is in {' and '.join(dups[name])}; trial names must be unique "
        f"across the raw files of a dataset: rename one group (the group name is the trial's identity){more}",
    )


def scan_raw(
    paths: str | os.PathLike | Sequence[str | os.PathLike],
    *,
    fields: Iterable[str] = ALL_REQUIRED_FIELDS,
    strict: bool = False,
    validate_data: bool = True,
) -> tuple[list[TrialInfo], list[TrialFormatError]]:
    """Validate every trial in ``paths`` for the given fields.

    Returns ``(good, errors)``. Bad trials are logged and skipped unless ``strict``, in
    which case the first error is raised. Only the datasets behind ``fields`` are opened.
    A file given twice is scanned once; a group name found in two files raises
    (:func:`check_unique_names`), strict or not.
    """
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    paths = unique_paths(paths)
    files_by_name: dict[str, list[str]] = {}
    good: list[TrialInfo] = []
    errors: list[TrialFormatError] = []

    def fail(err: TrialFormatError) -> None:
        if strict:
            raise err
        log.warning("skipping bad trial: %s", err)
        errors.append(err)

    for p in paths:
        try:
            f = open_raw(p)
        except TrialFormatError as err:
            fail(err)
            continue
        with f:
            try:
                names = list(f["trials"].keys())
            except (OSError, RuntimeError, KeyError) as exc:
                fail(TrialFormatError(p, "*", "trials", f"unreadable trial index ({exc})"))
                continue
            for name in names:
                files_by_name.setdefault(name, []).append(str(p))
                try:
                    try:
                        g = f["trials"][name]
                        attrs = read_attrs(g)
                    except (OSError, RuntimeError, KeyError) as exc:
                        raise TrialFormatError(p, name, "group", f"unreadable ({exc})") from None
                    _check_attrs(str(p), name, attrs)
                    if validate_data:
                        _read_group(str(p), name, g, fields, attrs=attrs)
                    good.append(TrialInfo(str(p), name, attrs))
                except TrialFormatError as err:
                    fail(err)
    check_unique_names(files_by_name)
    return good, errors


def read_trial(
    path: str | os.PathLike,
    name: str,
    fields: Iterable[str] = ALL_REQUIRED_FIELDS,
    *,
    check: bool = True,
    attrs: Mapping[str, Any] | None = None,
    file: h5py.File | None = None,
) -> RawTrial:
    """Read one trial (only ``fields``; the others are left as empty arrays, optional ones
    absent from the file as None). Its ``name`` is the group name ``name``.

    ``file``: ``path`` already opened with :func:`open_raw` (many trials, one open);
    ``attrs``: the group's attributes as :func:`scan_raw` read them (``TrialInfo.attrs``),
    not read again (reading ~16 HDF5 attributes costs about as much as decoding a trial's
    pose and clocks)."""
    if file is None:
        with open_raw(path) as f:
            return read_trial(path, name, fields, check=check, attrs=attrs, file=f)
    if name not in file["trials"]:
        raise TrialFormatError(path, name, "group", "no such trial")
    g = file["trials"][name]
    attrs = read_attrs(g) if attrs is None else dict(attrs)
    if check:
        _check_attrs(str(path), name, attrs)
    data = _read_group(str(path), name, g, fields, check=check, attrs=attrs)
    empty = np.zeros((0,))
    return RawTrial(
        t=data.get("t", empty),
        acc=data.get("acc", empty),
        fsr=data.get("fsr", empty),
        pose_t=data.get("pose_t", empty),
        pose=data.get("pose", empty),
        attrs=attrs,
        baseline_t=data.get("baseline_t"),
        baseline_acc=data.get("baseline_acc"),
        baseline_fsr=data.get("baseline_fsr"),
        lost_at=data.get("lost_at"),
        baseline_lost_at=data.get("baseline_lost_at"),
        group=name,
    )


def iter_trials(path: str | os.PathLike, fields: Iterable[str] = ALL_REQUIRED_FIELDS, strict: bool = False) -> Iterator[RawTrial]:
    """Yield every valid trial of one file (bad ones logged and skipped unless strict)."""
    good, _ = scan_raw(path, fields=fields, strict=strict, validate_data=False)
    for info in good:
        try:
            yield read_trial(info.file, info.name, fields)
        except TrialFormatError as err:
            if strict:
                raise
            log.warning("skipping bad trial: %s", err)
