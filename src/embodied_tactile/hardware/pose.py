"""Robot end-effector pose sources for the recorder.

A pose source delivers ``(t, pose)`` samples on the recorder's *trial clock* (seconds
since the start of the trial, ``time.perf_counter`` based). The recorder calls
:meth:`PoseSource.poll` about every ``flush_s`` and appends what it returns.

Built in: :class:`StaticPoseSource` (no robot connected: a fixed pose at ``fs`` Hz) and
:class:`ReplayPoseSource` (a pose log file, CSV or ``.npy``, columns
``t, x, y, z, roll, pitch, yaw`` [, extras]). A live robot interface subclasses
:class:`PoseSource` (see ``docs/reference/acquisition.md``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Sequence

import numpy as np

from embodied_tactile import constants as C


class PoseSource:
    """Extension point for a live robot interface.

    Subclass and implement :meth:`poll`; optionally :meth:`start` (connect, subscribe)
    and :meth:`close`. ``columns`` is the number of pose columns (>= 6: x, y, z in m,
    roll, pitch, yaw in rad, then extras). Timestamps must be on the trial clock: convert
    robot time with the ``t0_perf`` / ``t0_wall`` given to :meth:`start` (e.g.
    ``t = robot_epoch_time - t0_wall``) and return them strictly increasing.
    """

    columns: int = 6
    name: str = "custom"

    def start(self, t0_perf: float, t0_wall: float) -> None:
        """Called once when the trial clock starts (``t=0`` is ``t0_perf`` on
        ``time.perf_counter`` and ``t0_wall`` on ``time.time``)."""
        self.t0_perf, self.t0_wall = t0_perf, t0_wall

    def poll(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        """New samples with ``t <= now`` (trial clock) since the previous call:
        ``(t (k,) float64, pose (k, columns) float)``. Must not block for long."""
        raise NotImplementedError

    def close(self) -> None:
        """Disconnect; called once at the end (also after an interrupted trial)."""


def _empty(cols: int) -> tuple[np.ndarray, np.ndarray]:
    return np.zeros(0), np.zeros((0, cols), dtype=np.float32)


class StaticPoseSource(PoseSource):
    """No robot: the skin stays at a fixed, configured pose, sampled at ``fs`` Hz."""

    name = "static"

    def __init__(self, pose: Sequence[float] = (0, 0, 0, 0, 0, 0), fs: float = C.FS_POSE):
        self.pose = np.asarray(pose, dtype=np.float32).reshape(-1)
        if self.pose.shape[0] < 6:
            raise ValueError(f"static pose needs >= 6 values (x y z roll pitch yaw), got {self.pose.shape[0]}")
        self.columns = self.pose.shape[0]
        self.fs = float(fs)
        self._k = 0

    def poll(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        if now < 0:
            return _empty(self.columns)
        k_end = int(np.floor(now * self.fs)) + 1
        t = np.arange(self._k, k_end) / self.fs
        self._k = max(self._k, k_end)
        return t, np.repeat(self.pose[None], t.shape[0], axis=0)


def load_pose_log(path: str | Path) -> np.ndarray:
    """Read a pose log: ``.npy`` (array (M, >=7)) or CSV (comma/whitespace separated,
    an optional header line whose first field is ``t``). Columns ``t,x,y,z,roll,pitch,yaw``."""
    path = Path(path)
    if path.suffix == ".npy":
        arr = np.load(path)
    else:
        text = path.read_text().splitlines()
        skip = 1 if text and text[0].strip() and not _is_number(text[0].replace(",", " ").split()[0]) else 0
        arr = np.loadtxt(path, delimiter="," if "," in (text[skip] if len(text) > skip else "") else None, skiprows=skip, ndmin=2)
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] < 7:
        raise ValueError(f"{path}: pose log must have columns t,x,y,z,roll,pitch,yaw (got shape {arr.shape})")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{path}: pose log has non-finite values")
    if np.any(np.diff(arr[:, 0]) <= 0):
        raise ValueError(f"{path}: pose log timestamps are not strictly increasing")
    return arr


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


class ReplayPoseSource(PoseSource):
    """Replay a pose log recorded by the robot controller.

    ``time_base="trial"``: the file's ``t`` is seconds since the start of the trial (same
    clock as ``tactile/t``); ``time_base="wall"``: ``t`` is Unix epoch seconds
    (``time.time()`` on a clock synchronised with the recording host) and is converted
    with the trial's wall-clock start. In both cases ``offset_s`` is then added
    (``pose_t = t_file [- t0_wall] + offset_s``). Samples are released as the trial clock
    passes them, so the file fills up like a live stream; only ``pose_t >= 0`` is kept.
    """

    name = "replay"

    def __init__(self, file: str | Path, time_base: str = "trial", offset_s: float = 0.0):
        if time_base not in ("trial", "wall"):
            raise ValueError(f"pose time_base must be 'trial' or 'wall', got {time_base!r}")
        self.file = str(file)
        self.data = load_pose_log(file)
        self.columns = self.data.shape[1] - 1
        self.time_base = time_base
        self.offset_s = float(offset_s)
        self._t: np.ndarray | None = None
        self._i = 0

    def start(self, t0_perf: float, t0_wall: float) -> None:
        super().start(t0_perf, t0_wall)
        t = self.data[:, 0] - (t0_wall if self.time_base == "wall" else 0.0) + self.offset_s
        self._t = t
        self._i = int(np.searchsorted(t, 0.0, side="left"))

    def poll(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        if self._t is None:
            self.start(time.perf_counter(), time.time())
        j = int(np.searchsorted(self._t, now, side="right"))
        if j <= self._i:
            return _empty(self.columns)
        i, self._i = self._i, j
        return self._t[i:j].copy(), self.data[i:j, 1:].astype(np.float32)
