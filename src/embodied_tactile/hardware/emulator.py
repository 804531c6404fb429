"""A fake e-Skin on a pseudo-terminal, for tests, benchmarks and dry runs of the recorder.

The emulator opens a pty pair, prints/returns the slave path (what a recorder opens like
``/dev/ttyACM0``) and answers every ``0xD0`` request byte with the next packet of a raw
trial, paced at the trial's rate (or as fast as requested). Faults can be injected with
given probabilities (seedable): ``drop`` (no answer), ``delay`` (answer after
``delay_s``, i.e. after the recorder's timeout), ``truncate`` (only part of the packet),
``garbage`` (random bytes, the packet shifted by a few junk bytes, or followed by junk) and ``disconnect``
(close the pty after N packets or t seconds, like an unplugged cable).

Pure NumPy + os/pty; no torch, no pyserial needed on this side.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import os
import select
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from embodied_tactile import constants as C
from embodied_tactile.hardware.protocol import COMMAND, PACKET_SIZE, DeviceMap, encode_packets
from embodied_tactile.data import rawformat as R
from embodied_tactile.options.checks import check_options
from embodied_tactile.options.emulation import FaultOptions

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- trials to serve
def synthetic_trial(
    duration_s: float = 1.0,
    fs: float = C.FS_TACTILE,
    *,
    seed: int = 0,
    object_id: int = 0,
    skin: str = "soft",
    primitive: str = "pressing",
    action_index: int = 0,
    repetition: int = 0,
) -> R.RawTrial:
    """A small, deterministic trial (no simulator needed). Frame ``k`` is identifiable:
    ``fsr[k, 0, 0, 0] = k % 4096`` and ``fsr[k, 0, 0, 1] = k // 4096``; accelerations are
    gravity on z plus a small vibration, already on the 1/16384 g grid."""
    rng = np.random.default_rng(seed)
    n = max(2, int(round(duration_s * fs)))
    t = np.arange(n) / fs
    acc = np.zeros((n, *C.ACC_GRID, C.ACC_AXES))
    acc[..., 2] = 1.0
    acc += 0.05 * np.sin(2 * np.pi * 30 * t)[:, None, None, None] + rng.normal(0, 0.01, acc.shape)
    acc = (np.rint(acc * C.ACC_COUNTS_PER_G) / C.ACC_COUNTS_PER_G).astype(np.float32)
    fsr = rng.integers(0, 1200, (n, C.FSR_LAYERS, *C.FSR_GRID)).astype(np.uint16)
    k = np.arange(n)
    fsr[:, 0, 0, 0] = k % 4096
    fsr[:, 0, 0, 1] = k // 4096
    m = max(2, int(round(duration_s * C.FS_POSE)))
    pose_t = np.arange(m) / C.FS_POSE
    pose = np.zeros((m, 6), dtype=np.float32)
    pose[:, 2] = 0.1 - 0.002 * np.sin(2 * np.pi * 0.2 * pose_t)
    attrs = R.make_attrs(
        object_id=object_id, skin=skin, primitive=primitive, action_index=action_index,
        repetition=repetition, source="simulated", seed=seed, fs_tactile=fs, notes="synthetic emulator trial",
    )
    return R.RawTrial(t=t, acc=acc, fsr=fsr, pose_t=pose_t, pose=pose, attrs=attrs)


def load_trial(path: str | os.PathLike, name: str | None = None) -> R.RawTrial:
    """A trial of a raw HDF5 file (the first valid one unless ``name`` is given)."""
    if name is None:
        good, errors = R.scan_raw(path, fields=("t", "acc", "fsr"), validate_data=False)
        if not good:
            raise R.TrialFormatError(path, "*", "trials", f"no valid trial ({len(errors)} bad)")
        name = good[0].name
    return R.read_trial(path, name, fields=("t", "acc", "fsr"))


def simulated_trial(object_id: int, skin: str, primitive: str, action_index: int, seed: int = 0) -> R.RawTrial:
    """A trial from the palpation simulator (imported lazily: the emulator works without it)."""
    from embodied_tactile.sim import simulate_trial  # noqa: PLC0415  (optional dependency)

    return simulate_trial(object_id, skin, primitive, action_index, seed=seed)


# --------------------------------------------------------------------------- faults
@dataclass
class Faults(FaultOptions):
    """Per-request fault probabilities (checked in this order) and the disconnect trigger
    (:class:`~embodied_tactile.options.emulation.FaultOptions`, checked on construction)."""

    def __post_init__(self) -> None:
        check_options(FaultOptions, dataclasses.asdict(self), "faults")


@dataclass
class EmulatorStats:
    requests: int = 0
    sent: int = 0  # intact, aligned, on-time packets
    dropped: int = 0
    delayed: int = 0
    truncated: int = 0
    garbage: int = 0
    disconnected: bool = False
    served: list[int] = field(default_factory=list)  # frame index of every intact on-time packet

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d.pop("served")
        return d


# --------------------------------------------------------------------------- the emulator
class Emulator:
    """Serve ``trial`` on a fresh pty. Use :meth:`open` then :meth:`serve` (blocking) or
    :meth:`start` (background thread) and :meth:`stop`.

    ``rate``: packets per second (default: the trial's ``fs_tactile``); ``0`` answers as
    fast as requested; ``pacing``/``max_lag_s``: see :meth:`_pace`. Frames are served in order and the trial loops (``loop=False``:
    stop answering at the end).
    """

    def __init__(self, trial: R.RawTrial, *, device: DeviceMap | None = None, rate: float | None = None, faults: Faults | None = None, loop: bool = True,
                 pacing: str = "fifo", max_lag_s: float = 0.05):
        self.trial = trial
        self.device = device or DeviceMap()
        self.rate = float(trial.attrs.get("fs_tactile", C.FS_TACTILE) if rate is None else rate)
        self.faults = faults or Faults()
        self.loop = loop
        if pacing not in ("fifo", "grid"):
            raise ValueError(f"pacing must be fifo|grid, got {pacing!r}")
        self.pacing, self.max_lag_s = pacing, float(max_lag_s)
        self.rng = np.random.default_rng(self.faults.seed)
        n = trial.t.shape[0]
        dt = np.diff(np.asarray(trial.t, dtype=np.float64)) * 1e6
        nominal = 1e6 / (float(trial.attrs.get("fs_tactile", C.FS_TACTILE)) or C.FS_TACTILE)
        dt_us = np.clip(np.rint(np.concatenate([[nominal], dt])), 1, 2**32 - 1).astype(np.uint32) if n > 1 else np.full(n, nominal)
        self.packets = encode_packets(trial.acc, trial.fsr, dt_us, dt_us, self.device)
        self.n_frames = n
        self.stats = EmulatorStats()
        self.master: int | None = None
        self.slave: int | None = None
        self.port: str | None = None
        self._link: Path | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._frame = 0
        self._grid0: float | None = None
        self._next_time: float | None = None
        self._last_tick = -1
        self._t_first: float | None = None

    # ------------------------------------------------------------------ pty
    def open(self, link: str | os.PathLike | None = None) -> str:
        """Create the pty (raw mode) and return the slave path; ``link``: also make a
        symlink with a stable name pointing at it."""
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)  # no echo / line discipline before the recorder configures it
        self.port = os.ttyname(self.slave)
        if link is not None:
            self._link = Path(link)
            if self._link.is_symlink() or self._link.exists():
                self._link.unlink()
            self._link.symlink_to(self.port)
        return self.port

    def close(self) -> None:
        for fd in (self.master, self.slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = None
        if self._link is not None and self._link.is_symlink():
            self._link.unlink()

    # ------------------------------------------------------------------ serving
    def start(self, link: str | os.PathLike | None = None) -> str:
        port = self.port or self.open(link)
        self._thread = threading.Thread(target=self.serve, name="eskin-emulator", daemon=True)
        self._thread.start()
        return port

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self.close()

    def serve(self, max_seconds: float | None = None) -> EmulatorStats:
        """Answer requests until :meth:`stop`, ``max_seconds`` or a disconnect fault."""
        if self.master is None:
            self.open()
        t_end = None if max_seconds is None else time.perf_counter() + max_seconds
        try:
            while not self._stop.is_set() and not self.stats.disconnected:
                if t_end is not None and time.perf_counter() >= t_end:
                    break
                r, _, _ = select.select([self.master], [], [], 0.05)
                if not r:
                    continue
                try:
                    data = os.read(self.master, 4096)
                except OSError as exc:  # EIO: no slave side open at the moment
                    if exc.errno != errno.EIO:
                        raise
                    time.sleep(0.01)
                    continue
                for _ in range(data.count(COMMAND)):  # other bytes are ignored, like the board
                    self._answer()
                    if self.stats.disconnected or self._stop.is_set():
                        break
        finally:
            if self.stats.disconnected:
                self.close()
        return self.stats

    def _write(self, payload: bytes) -> None:
        view = memoryview(payload)
        while view:
            n = os.write(self.master, view)
            view = view[n:]

    def _pace(self) -> None:
        """Hold the answer until the next sample is due.

        ``pacing="fifo"`` (default): samples are due on a fixed ``1/rate`` grid and the
        board keeps up to ``max_lag_s`` of them, so after a slow request the backlog is
        answered at once (the average rate stays ``rate`` if the reader keeps up on
        average). ``pacing="grid"``: no backlog, at most one answer per grid tick; ticks
        missed by a slow reader are lost (the rate drops with host latency)."""
        if self.rate <= 0:
            return
        now = time.perf_counter()
        period = 1.0 / self.rate
        if self.pacing == "grid":
            if self._grid0 is None:
                self._grid0, self._last_tick = now, -1
            tick = int((now - self._grid0) // period)
            if tick <= self._last_tick:
                tick = self._last_tick + 1
                wait = self._grid0 + tick * period - now
                if wait > 0:
                    time.sleep(wait)
            self._last_tick = tick
            return
        if self._next_time is None or now - self._next_time > self.max_lag_s:
            self._next_time = now - (0.0 if self._next_time is None else self.max_lag_s)
        wait = self._next_time - now
        if wait > 0:
            time.sleep(wait)
        self._next_time += period

    def _answer(self) -> None:
        st, f = self.stats, self.faults
        st.requests += 1
        now = time.perf_counter()
        if self._t_first is None:
            self._t_first = now
        if (f.disconnect_after_packets is not None and st.sent >= f.disconnect_after_packets) or (
            f.disconnect_after_s is not None and now - self._t_first >= f.disconnect_after_s
        ):
            log.info("emulator: disconnect after %d packets", st.sent)
            st.disconnected = True
            self.close()
            return
        if self._frame >= self.n_frames:
            if not self.loop:
                st.dropped += 1
                return
            self._frame = 0
        u = self.rng.random(4)
        if u[0] < f.drop:
            st.dropped += 1
            return
        self._pace()
        k = self._frame
        pkt = self.packets[k * PACKET_SIZE : (k + 1) * PACKET_SIZE]
        self._frame += 1
        if u[1] < f.delay:
            st.delayed += 1
            time.sleep(f.delay_s)
            self._write(pkt)
        elif u[2] < f.truncate:
            st.truncated += 1
            self._write(pkt[: int(self.rng.integers(1, PACKET_SIZE))])
        elif u[3] < f.garbage:
            st.garbage += 1
            mode = f.garbage_mode if f.garbage_mode != "mixed" else ("random", "shift", "long")[int(self.rng.integers(3))]
            junk = self.rng.integers(0, 256, int(self.rng.integers(1, 64)), dtype=np.uint8).tobytes()
            if mode == "random":
                self._write(self.rng.integers(0, 256, PACKET_SIZE, dtype=np.uint8).tobytes())
            elif mode == "shift":  # junk bytes in front: the packet arrives shifted, its tail spills over
                self._write(junk + pkt)
            else:  # "long": a response longer than a packet (junk after it)
                self._write(pkt + junk)
        else:
            self._write(pkt)
            st.sent += 1
            st.served.append(k)
