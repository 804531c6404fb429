"""Polled e-Skin recorder: serial port -> plausibility check -> incremental HDF5.

One trial = a no-contact baseline (``baseline_s``) then the palpation (``duration_s``).
Every packet is stamped on receipt with the host's monotonic clock
(``time.perf_counter``; ``t = 0`` at the start of the trial, baseline samples have
``t < 0``; the wall-clock time of ``t = 0`` is stored as attr ``t0_wall``).

Packet handling (see ``docs/reference/acquisition.md``):

* write ``0xD0``, read exactly 1128 bytes; a short read (timeout) is a *lost* packet,
  never data, and is followed by a drain of ``late_guard_s`` so a late answer cannot
  shift the request/response pairing;
* a full read that fails :class:`~.protocol.PlausibilityChecker`, or is followed by
  extra bytes (a response longer than expected), is *garbage*: drain the input buffer
  (``reset_input_buffer`` + read until the line is quiet for ``quiet_s``) and resume;
* a plausible packet is only *committed* once the line is seen quiet before the next
  request (bytes waiting there mean the pairing was off: the pending packet is dropped,
  counted lost, and the line drained).

Every lost or garbage packet is located: the index of the sample that follows the gap
(the sample it would have been) is written to ``tactile/lost_at`` (``baseline/lost_at``
before ``t = 0``) with the next batch, so ``lost_packets + garbage_packets`` is
``len(tactile/lost_at) + len(baseline/lost_at)``.

Coverage: the packet rate is measured against the board's declared rate (``declared_hz``,
the trial's ``fs_tactile``): in the first ``rate_check_s`` (:func:`rate_problem`), and over
the whole trial, whose missing share -- the samples the declared rate gives
``duration_s`` that did not arrive, lost, garbage or never polled while the line was
drained -- is stored as attr ``missing_share``. Above
:data:`~embodied_tactile.data.rawformat.MAX_MISSING_SHARE` the trial ends
``low_coverage``: ``complete=False``, exit 3, the one line names the share.

Committed packets are buffered and written in batches through
:class:`~embodied_tactile.data.rawformat.IncrementalTrialWriter` every ``flush_s`` (<= 1 s),
each batch followed by a flush, so a crash loses at most the last ``flush_s``.

Storage: before each batch the room left for the trial's file (:func:`room_bytes`: free
disk space and the process's file-size limit) must exceed the batch, one new chunk per
dataset and ``reserve_mb``; otherwise the trial stops with ``stop_reason="disk_full"``
and the batch is not written. A write that fails anyway (I/O error) stops the trial with
``stop_reason="write_error"``. Either way the file is closed, ``complete=False``.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from embodied_tactile.hardware.pose import PoseSource
from embodied_tactile.hardware.protocol import (
    COMMAND_BYTE,
    PACKET_SIZE,
    DeviceMap,
    PlausibilityChecker,
    PlausibilityConfig,
    decode_packets,
)
from embodied_tactile.data.rawformat import MAX_MISSING_SHARE, IncrementalTrialWriter, rate_problem

log = logging.getLogger(__name__)

EXIT_COMPLETE = 0
EXIT_CONFIG = 2
EXIT_INCOMPLETE = 3

#: Bytes one packet takes once decoded and stored: t (float64) + acc (48 float32) + fsr (512 uint16).
SAMPLE_BYTES = 8 + 48 * 4 + 512 * 2
#: HDF5 metadata of a trial group (object headers, chunk indices, attributes): an upper bound.
METADATA_BYTES = 256 * 1024


def room_bytes(path: str | os.PathLike) -> int:
    """Bytes that can still be written to the file ``path``: the free space of its file
    system (as an unprivileged user sees it) and, where the process has a file-size limit
    (``ulimit -f``, RLIMIT_FSIZE), that limit minus the file's current size."""
    p = Path(path)
    room = shutil.disk_usage(p.parent if not p.is_dir() else p).free
    try:
        import resource  # noqa: PLC0415 - POSIX only
    except ImportError:  # pragma: no cover - Windows: no file-size limit
        return int(room)
    soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    if soft != resource.RLIM_INFINITY:
        size = p.stat().st_size if p.is_file() else 0
        room = min(room, soft - size)
    return int(room)


def _file_id(path: str | os.PathLike) -> tuple[int, int] | None:
    """(device, inode) of the file at ``path``; None when nothing is there."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def trial_bytes(seconds: float, fs_tactile: float, fs_pose: float = 0.0, pose_columns: int = 6, chunk: int = 700) -> int:
    """Upper estimate of the bytes ``seconds`` of recording take in a trial file: every
    sample, pose included, one partly filled chunk per dataset, and the group's metadata."""
    pose = math.ceil(seconds * fs_pose) * (8 + 4 * pose_columns)
    return int(math.ceil(seconds * fs_tactile) * SAMPLE_BYTES + pose + 2 * chunk * SAMPLE_BYTES + METADATA_BYTES)


@dataclass
class RecorderSettings:
    port: str = "/dev/ttyACM0"  # device path or pyserial URL (loop://, socket://host:port, rfc2217://...)
    baud: int = 500000
    timeout: float = 0.1  # s, per-packet read timeout
    settle_s: float = 1.0  # wait after opening, then flush both buffers (the board resets on open)
    baseline_s: float = 2.0
    duration_s: float = 10.0
    flush_s: float = 0.5  # <= 1 s
    quiet_s: float = 0.02  # drain until no byte arrived for this long
    late_guard_s: float = 0.1  # drain window after a timeout (a late answer must land in it)
    max_drain_s: float = 2.0  # a line that never goes quiet is treated as a fault
    reserve_mb: float = 64.0  # stop the trial (disk_full) before less than this would stay writable
    declared_hz: float | None = None  # the trial's fs_tactile: the packet rate of the first rate_check_s is checked against it
    rate_check_s: float = 1.0
    max_missing_share: float = MAX_MISSING_SHARE  # above it (of duration_s x declared_hz) the trial is not complete

    def __post_init__(self) -> None:
        if not 0 < self.flush_s <= 1.0:
            raise ValueError(f"flush_s must be in (0, 1], got {self.flush_s}")
        if self.timeout <= 0 or self.duration_s <= 0 or self.baseline_s < 0:
            raise ValueError("timeout and duration_s must be > 0, baseline_s >= 0")
        if not self.reserve_mb >= 0:
            raise ValueError(f"reserve_mb must be >= 0, got {self.reserve_mb}")

    @property
    def reserve_bytes(self) -> int:
        return int(self.reserve_mb * 2**20)


@dataclass
class RecordResult:
    # complete | interrupted | unplugged | no_data | disk_full | write_error | output_vanished | rate_mismatch
    # | low_coverage
    status: str
    n_trial: int = 0
    n_baseline: int = 0
    n_pose: int = 0
    lost: int = 0
    garbage: int = 0
    elapsed_s: float = 0.0
    rate_hz: float = 0.0
    jitter_std_s: float = float("nan")
    jitter_max_s: float = float("nan")
    cpu_s: float = 0.0
    wall_s: float = 0.0
    garbage_reasons: dict[str, int] = field(default_factory=dict)
    path: str = ""
    trial: str = ""
    unwritten: int = 0  # packets received but not written (disk_full / write_error)
    declared_hz: float | None = None  # the board's declared rate the trial is measured against
    missing_share: float | None = None  # 1 - packets / (duration_s x declared_hz); None without a declared rate

    message: str = ""  # why the trial stopped early, when it did not end by itself (rate_mismatch)

    @property
    def exit_code(self) -> int:
        if self.status == "rate_mismatch":  # the board or the config is wrong: a setting, not a lost recording
            return EXIT_CONFIG
        return EXIT_COMPLETE if self.status == "complete" else EXIT_INCOMPLETE

    def summary(self) -> str:
        return (
            f"{self.status}: {self.n_trial} packets in {self.elapsed_s:.2f} s -> {self.rate_hz:.1f} packets/s"
            + (f" of {self.declared_hz:g} declared, {self.missing_share:.1%} of the samples missing"
               if self.missing_share is not None else "") + "; "
            f"jitter std {self.jitter_std_s * 1e3:.3f} ms, max interval {self.jitter_max_s * 1e3:.3f} ms; "
            f"lost {self.lost}, garbage {self.garbage}; baseline {self.n_baseline} packets, pose {self.n_pose} samples; "
            f"cpu {self.cpu_s:.2f} s; -> {self.path}:{self.trial}"
            + (f"; {self.unwritten} packets received but not written" if self.unwritten else "")
        )


class _Unplugged(Exception):
    pass


class _RateMismatch(Exception):
    pass


class _StorageStop(Exception):
    """The trial cannot be written further; ``reason`` is its stop reason."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


class Recorder:
    """Record one trial from an open pyserial-like ``port`` into ``writer``."""

    def __init__(
        self,
        port: Any,
        writer: IncrementalTrialWriter,
        settings: RecorderSettings,
        *,
        device: DeviceMap | None = None,
        plausibility: PlausibilityConfig | None = None,
        pose: PoseSource | None = None,
        should_stop: Callable[[], bool] = lambda: False,
        on_phase: Callable[[str], None] | None = None,
        room: Callable[[], int] | None = None,
    ):
        self.ser = port
        self.writer = writer
        self.s = settings
        self.device = device or DeviceMap()
        self.checker = PlausibilityChecker(plausibility)
        self.pose = pose
        self.should_stop = should_stop
        self.on_phase = on_phase or (lambda phase: None)
        self.room = room or (lambda: room_bytes(writer.path))
        self._file_id = _file_id(writer.path)  # the file being written, to notice it vanish
        self._write_failed = False
        self._unwritten = 0
        self.lost = 0
        self.garbage = 0
        self.reasons: dict[str, int] = {}
        self._bufs: dict[str, tuple[bytearray, list[float]]] = {"baseline": (bytearray(), []), "trial": (bytearray(), [])}
        self._lost_at: dict[str, list[int]] = {"baseline": [], "trial": []}  # not yet written
        self._phase = "baseline"
        self._trial_t: list[float] = []
        self._n_base = 0
        self._n_pose = 0
        self._t0 = 0.0
        self._last_t: float | None = None
        self._pose_last = -np.inf
        self._rate_checked = settings.declared_hz is None
        self._rate_t: list[float] = []  # host receipt times of the packets of the first rate_check_s

    # ------------------------------------------------------------------ serial helpers
    def _in_waiting(self) -> int:
        try:
            return int(self.ser.in_waiting)
        except (OSError, ValueError) as exc:  # serial.SerialException is an OSError
            raise _Unplugged(str(exc)) from exc

    def _drain(self, quiet_s: float) -> None:
        """reset_input_buffer, then keep discarding until nothing arrived for ``quiet_s``."""
        try:
            self.ser.reset_input_buffer()
            t_end = time.perf_counter() + self.s.max_drain_s
            quiet_since = time.perf_counter()
            while True:
                now = time.perf_counter()
                if self.ser.in_waiting:
                    self.ser.reset_input_buffer()
                    quiet_since = now
                elif now - quiet_since >= quiet_s:
                    return
                if now > t_end:
                    log.warning("input never went quiet within %.1f s", self.s.max_drain_s)
                    return
                if self.should_stop():
                    return
                time.sleep(min(0.002, quiet_s / 4))
        except (OSError, ValueError) as exc:
            raise _Unplugged(str(exc)) from exc

    def _poll_once(self) -> tuple[bytes, float] | None:
        """One request/response. Returns ``(packet, t_host)`` or None (lost / garbage)."""
        try:
            self.ser.write(COMMAND_BYTE)
            pkt = self.ser.read(PACKET_SIZE)
        except (OSError, ValueError) as exc:
            raise _Unplugged(str(exc)) from exc
        t_host = time.perf_counter()
        if len(pkt) < PACKET_SIZE:  # timeout / short read: lost, never data
            self._lose(t_host)
            self._drain(max(self.s.late_guard_s, self.s.quiet_s))
            return None
        reason = self.checker.check(pkt)
        if reason is None and self._in_waiting():
            reason = "longer than expected"
        if reason is not None:
            self.garbage += 1
            self._mark(t_host)  # the sample it would have been
            key = reason.split("=")[0].split(" ")[0]
            self.reasons[key] = self.reasons.get(key, 0) + 1
            log.debug("garbage packet (%s): resync", reason)
            self._drain(self.s.quiet_s)
            return None
        return bytes(pkt), t_host

    # ------------------------------------------------------------------ writing
    def _lose(self, t_host: float) -> None:
        """Count a lost packet and note where: the number of samples of its phase (baseline
        before ``t = 0``, else trial) committed so far, i.e. the index of the next one."""
        self.lost += 1
        self._mark(t_host)

    def _mark(self, t_host: float) -> None:
        """Note a sample that did not arrive (lost or garbage) in ``lost_at`` of its phase."""
        phase = "baseline" if t_host - self._t0 < 0 else "trial"
        written = self._n_base if phase == "baseline" else len(self._trial_t)
        self._lost_at[phase].append(written + len(self._bufs[phase][1]))

    def _commit(self, pkt: bytes, t_host: float) -> None:
        """Buffer a genuine packet; ``t < 0`` (before the trial start) goes to the baseline."""
        t = t_host - self._t0
        if self._last_t is not None and t <= self._last_t:  # keep timestamps strictly increasing
            t = math.nextafter(self._last_t, math.inf)
        self._last_t = t
        buf, ts = self._bufs["baseline" if t < 0 else "trial"]
        buf += pkt
        ts.append(t)

    def _check_room(self) -> None:
        """Raise _StorageStop("disk_full") unless the next batch fits with ``reserve_mb`` to spare."""
        n = sum(len(ts) for _, ts in self._bufs.values())
        chunk = self.writer.chunk
        need = n * SAMPLE_BYTES + 2 * chunk * SAMPLE_BYTES + 64 * 1024  # the batch, a new chunk per dataset, pose and attrs
        room = self.room()
        if room - need < self.s.reserve_bytes:
            raise _StorageStop(
                "disk_full",
                f"{self.writer.path}: {room / 2**20:.1f} MB writable (free disk space / file-size limit), the next "
                f"write needs {need / 2**20:.1f} MB and {self.s.reserve_mb:g} MB are kept in reserve",
            )

    def _drop_pending(self) -> None:
        """Forget the packets not yet written (the trial stopped for lack of room)."""
        for buf, ts in self._bufs.values():
            self._unwritten += len(ts)
            buf.clear()
            ts.clear()
        for lost_at in self._lost_at.values():
            lost_at.clear()

    def _check_output(self) -> None:
        """Raise _StorageStop("output_vanished") when the trial's file is no longer at its
        path (its folder deleted or moved, its disk unmounted): what is written after that
        would go to a file nobody can open."""
        if self._file_id is not None and _file_id(self.writer.path) != self._file_id:
            n = len(self._trial_t) + self._n_base + sum(len(ts) for _, ts in self._bufs.values())
            raise _StorageStop(
                "output_vanished",
                f"{self.writer.path}: the output file vanished during the trial (its folder deleted, moved or "
                f"unmounted); the {n} packet(s) recorded went with it")

    def _flush(self) -> None:
        if self._write_failed:
            return
        self._check_output()
        self._check_room()
        try:
            self._write_batch()
        except (OSError, RuntimeError) as exc:  # h5py reports failed writes as OSError / RuntimeError
            self._write_failed = True
            full = isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT)
            raise _StorageStop("write_error", f"{self.writer.path}: write failed{' (no space)' if full else ''}: {exc}") from exc

    def _write_batch(self) -> None:
        for phase, (buf, ts) in self._bufs.items():
            if not ts:
                continue
            acc, fsr, _, _ = decode_packets(buf, self.device)
            pre = "" if phase == "trial" else "baseline_"
            self.writer.append(pre + "t", np.asarray(ts, dtype=np.float64))
            self.writer.append(pre + "acc", acc)
            self.writer.append(pre + "fsr", fsr)
            if phase == "trial":
                self._trial_t.extend(ts)
            else:
                self._n_base += len(ts)
            buf.clear()
            ts.clear()
        for phase, lost_at in self._lost_at.items():  # after the samples they point into
            if lost_at:
                self.writer.append("lost_at" if phase == "trial" else "baseline_lost_at", np.asarray(lost_at, dtype=np.int64))
                lost_at.clear()
        if self.pose is not None and self._phase == "trial":
            pt, pv = self.pose.poll(time.perf_counter() - self._t0)
            pt, pv = np.asarray(pt, dtype=np.float64).reshape(-1), np.asarray(pv)
            # a live source may repeat or reorder samples: keep the strictly increasing, t >= 0 ones
            keep = pt >= 0
            if keep.any():
                last = self._pose_last
                cm = np.maximum.accumulate(np.where(keep, pt, -np.inf))
                keep &= (pt == cm) & (pt > last) & np.concatenate([[True], np.diff(cm) > 0])
            pt, pv = pt[keep], pv[keep]
            if len(pt):
                self._pose_last = float(pt[-1])
                self.writer.append("pose_t", pt)
                self.writer.append("pose", pv)
                self._n_pose += len(pt)
        self.writer.set_attrs(lost_packets=self.lost, garbage_packets=self.garbage)
        self.writer.flush()

    # ------------------------------------------------------------------ main loop
    def _start_trial(self) -> None:
        self._flush()  # the baseline is on disk before the trial starts
        self._phase = "trial"
        wall0 = time.time() - (time.perf_counter() - self._t0)
        iso = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(wall0)) + f".{int((wall0 % 1) * 1e6):06d}Z"
        self.writer.set_attrs(t0_wall=wall0, t0_wall_iso=iso)
        if self.pose is not None:
            self.pose.start(self._t0, wall0)
        self.on_phase("trial")

    def _check_rate(self, t_poll0: float, now: float) -> None:
        """After ``rate_check_s`` of polling: the host timestamps of the packets committed so
        far against the declared rate, by the raw format's own rule
        (:func:`~embodied_tactile.data.rawformat.rate_problem`): a trial stopped here is one
        that ``scan_raw`` would reject later. _RateMismatch naming both rates."""
        self._rate_checked = True
        t = np.asarray(self._rate_t)
        self._rate_t = []
        if t.size < 3:
            return  # nothing arrived: the trial ends as no_data / unplugged on its own
        problem = rate_problem(t, float(self.s.declared_hz))
        if problem:
            raise _RateMismatch(f"in the first {now - t_poll0:.1f} s the packets' {problem.format(key='fs_tactile')}: "
                                "set fs_tactile to the board's rate or fix its firmware")

    def _loop(self, t_end: float) -> bool:
        """Poll until ``t_end`` (perf_counter). Returns False if stopped early."""
        pending: tuple[bytes, float] | None = None
        next_flush = time.perf_counter() + self.s.flush_s
        t_poll0 = time.perf_counter()
        while True:
            # commit the previous packet only if nothing is waiting: the pairing held
            if self._in_waiting():
                if pending is not None:
                    self._lose(pending[1])
                    pending = None
                self._drain(self.s.quiet_s)
            elif pending is not None:
                self._commit(*pending)
                pending = None
            now = time.perf_counter()
            if not self._rate_checked and now - t_poll0 >= self.s.rate_check_s:
                self._check_rate(t_poll0, now)
            if self._phase == "baseline" and now >= self._t0:
                self._start_trial()
            if now >= next_flush:
                self._flush()
                next_flush = now + self.s.flush_s
            if self.should_stop():
                return False
            if now >= t_end:
                return True
            pending = self._poll_once()
            if pending is not None and not self._rate_checked:
                self._rate_t.append(pending[1])

    def run(self) -> RecordResult:
        s = self.s
        status, message = "complete", ""
        cpu0 = time.process_time()
        t_start = time.perf_counter()
        try:
            try:
                if s.settle_s > 0:
                    time.sleep(s.settle_s)
                self.ser.reset_output_buffer()
                self._drain(s.quiet_s)
            except (OSError, ValueError) as exc:
                raise _Unplugged(str(exc)) from exc
            self._t0 = time.perf_counter() + s.baseline_s  # trial clock: t = 0 at the trial start
            if s.baseline_s > 0:
                self.on_phase("baseline")
            if not self._loop(self._t0 + s.duration_s):
                status = "interrupted"
        except _Unplugged as exc:
            log.error("device lost: %s", exc)
            status = "unplugged"
        except _StorageStop as exc:
            log.error("trial stopped: %s", exc)
            status = exc.reason
            if exc.reason == "output_vanished":
                message = str(exc)
        except _RateMismatch as exc:
            log.error("trial stopped: %s", exc)
            status, message = "rate_mismatch", str(exc)
        finally:
            try:
                if status != "output_vanished":
                    self._flush()
            except _StorageStop as exc:
                if status in ("complete", "interrupted", "unplugged"):
                    log.error("trial stopped: %s", exc)
                    status = exc.reason
                    message = str(exc) if exc.reason == "output_vanished" else message
            except Exception:  # noqa: BLE001 - never lose the close that follows
                log.exception("final flush failed")
            self._drop_pending()
            if self.pose is not None:
                self.pose.close()
        trial_t = np.asarray(self._trial_t)
        elapsed = (float(trial_t[-1] - trial_t[0]) if trial_t.size > 1 else 0.0)
        d = np.diff(trial_t)
        if status == "complete" and trial_t.size < 2:
            status = "no_data"
        missing = None
        if s.declared_hz:  # the board's declared rate: the samples the trial should hold
            missing = max(0.0, 1.0 - trial_t.size / (s.duration_s * float(s.declared_hz)))
            if status == "complete" and missing > s.max_missing_share:
                status = "low_coverage"
                message = (f"{missing:.1%} of the samples missing: {trial_t.size} packets in {s.duration_s:g} s where "
                           f"fs_tactile={float(s.declared_hz):g} Hz gives {s.duration_s * float(s.declared_hz):.0f} "
                           f"({self.lost} lost, {self.garbage} garbage, the rest not polled while the line was "
                           f"drained; at most {s.max_missing_share:.0%}: rawformat.MAX_MISSING_SHARE)")
        res = RecordResult(
            status=status,
            n_trial=int(trial_t.size),
            n_baseline=self._n_base,
            n_pose=self._n_pose,
            lost=self.lost,
            garbage=self.garbage,
            elapsed_s=elapsed,
            rate_hz=(trial_t.size - 1) / elapsed if elapsed > 0 else 0.0,
            jitter_std_s=float(d.std()) if d.size else float("nan"),
            jitter_max_s=float(d.max()) if d.size else float("nan"),
            cpu_s=time.process_time() - cpu0,
            garbage_reasons=dict(self.reasons),
            path=str(self.writer.path),
            trial=self.writer.name,
            wall_s=time.perf_counter() - t_start,
            unwritten=self._unwritten,
            message=message,
            declared_hz=float(s.declared_hz) if s.declared_hz else None,
            missing_share=missing,
        )
        return res


class PortBusy(OSError):
    """The serial port is held by another program (another recorder)."""


def open_port(url: str, baud: int, timeout: float):
    """Open a device path or pyserial URL (``loop://``, ``socket://host:port``, a pty path).
    A device path is opened exclusively (an advisory ``flock`` that every recorder takes):
    while one recorder holds it, another one gets :class:`PortBusy` and never touches the
    line, so the running trial goes on undisturbed."""
    import serial  # noqa: PLC0415

    kw = dict(baudrate=baud, timeout=timeout, write_timeout=max(1.0, timeout))
    if "://" not in str(url):
        kw["exclusive"] = True
    try:
        return serial.serial_for_url(url, **kw)
    except serial.SerialException as exc:
        if "exclusively lock" in str(exc):
            raise PortBusy(f"{url} is in use by another program (a recorder still running?): {exc}") from None
        raise


def finish(writer: IncrementalTrialWriter, res: RecordResult, extra_attrs: dict[str, Any] | None = None) -> None:
    """Store the run's statistics and close the trial (``complete`` only for a full run).
    After a failed write the datasets are cut back to the last flushed batch; if the file
    refuses that too, it is closed as it is (its ``complete=False`` was stored when the
    trial began) and the error logged."""
    try:
        if res.status == "write_error":
            writer.rollback()
        writer.set_attrs(
            lost_packets=res.lost,
            garbage_packets=res.garbage,
            stop_reason=res.status,
            achieved_rate_hz=res.rate_hz,
            jitter_std_s=res.jitter_std_s,
            jitter_max_s=res.jitter_max_s,
            unwritten_packets=res.unwritten,
            **({"missing_share": res.missing_share} if res.missing_share is not None else {}),
            **(extra_attrs or {}),
        )
        writer.close(complete=res.status == "complete")
    except (OSError, RuntimeError) as exc:
        if res.status == "complete":
            res.status = "write_error"
        log.error("%s: closing trial '%s' failed: %s", writer.path, writer.name, exc)
        writer.abandon()


def trial_file(out: str | os.PathLike, name: str) -> Path:
    """The file a trial is recorded into: one file per trial, ``<out without .h5>.<trial name>.h5``
    (``recordings/obj03.h5`` -> ``recordings/obj03.obj03_soft_pressing_a06_r00.h5``), so a
    crash or a full disk during one trial never touches the files of the others."""
    p = Path(out)
    stem = p.name[: -len(p.suffix)] if p.suffix in (".h5", ".hdf5") else p.name
    return p.with_name(f"{stem}.{name}.h5")


def default_out(path: str | Path) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    return p
