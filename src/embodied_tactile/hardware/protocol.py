"""The modular e-Skin wire protocol: one request byte, one 1128-byte packet back.

Pure NumPy (no torch). See ``docs/reference/acquisition.md`` for the full description::

    request  : 1 byte  = (0b11 << 6) | 16 = 0xD0
    response : 1128 bytes, little-endian
        0-3      uint32       dt_acc   board accelerometer interval (us)
        4-7      uint32       dt_fsr   board FSR interval (us)
        8-103    48 x int16   acc, 16 sensors x (x, y, z), WIRING order, /16384 -> g
        104-1127 512 x uint16 FSR counts laid out (row 16, layer 2, column 16)

There is no header, sync word or checksum, so a misaligned or corrupt packet can only be
recognised by invariants (:class:`PlausibilityChecker`).

Device specifics (wiring of the accelerometers, dead channels to repair) live in a
:class:`DeviceMap` built from config (``configs/record/device/*.yaml``), never in constants.
"""

from __future__ import annotations

import struct
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from embodied_tactile import constants as C

MODE = 0b11
SIZE_FIELD = 16
COMMAND = (MODE << 6) | SIZE_FIELD  # 0xD0
COMMAND_BYTE = bytes([COMMAND])
N_ACC_SENSORS = C.ACC_GRID[0] * C.ACC_GRID[1]  # 16
PACKET_SIZE = 8 + 2 * N_ACC_SENSORS * C.ACC_AXES + 2 * C.FSR_LAYERS * C.FSR_GRID[0] * C.FSR_GRID[1]  # 1128
assert COMMAND == 0xD0 and PACKET_SIZE == 1128

#: One packet as a NumPy structured dtype (little-endian, unpadded).
PACKET_DTYPE = np.dtype(
    [
        ("dt_acc", "<u4"),
        ("dt_fsr", "<u4"),
        ("acc", "<i2", (N_ACC_SENSORS, C.ACC_AXES)),  # wiring order
        ("fsr", "<u2", (C.FSR_GRID[0], C.FSR_LAYERS, C.FSR_GRID[1])),  # (row, layer, col)
    ]
)
assert PACKET_DTYPE.itemsize == PACKET_SIZE

#: The authors' wire index -> grid position lookup (row-major 4x4).
DEFAULT_WIRING: tuple[int, ...] = (0, 7, 8, 9, 5, 6, 15, 10, 4, 2, 12, 11, 3, 1, 14, 13)
_AXES = {"x": 0, "y": 1, "z": 2}


# --------------------------------------------------------------------------- device map
@dataclass(frozen=True)
class AccRepair:
    """A dead accelerometer channel: ``sensor`` is the WIRE index (as labelled on the
    board), ``axis`` 0/1/2 (x/y/z). Replaced by the mean of the same axis of the valid
    4-connected grid neighbours."""

    sensor: int
    axis: int


@dataclass(frozen=True)
class FsrRepair:
    """Dead FSR lines of one layer: each dead column (row) is replaced by the mean of the
    nearest valid column (row) on either side, per taxel."""

    layer: int
    cols: tuple[int, ...] = ()
    rows: tuple[int, ...] = ()


@dataclass(frozen=True)
class DeviceMap:
    """Per-device wiring and dead-channel repair map."""

    name: str = "ideal"
    wiring: tuple[int, ...] = DEFAULT_WIRING
    acc_repair: tuple[AccRepair, ...] = ()
    fsr_repair: tuple[FsrRepair, ...] = ()
    _plan: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        w = tuple(int(i) for i in self.wiring)
        if sorted(w) != list(range(N_ACC_SENSORS)):
            raise ValueError(f"device '{self.name}': wiring must be a permutation of 0..15, got {list(w)}")
        object.__setattr__(self, "wiring", w)
        for r in self.acc_repair:
            if not (0 <= r.sensor < N_ACC_SENSORS and 0 <= r.axis < C.ACC_AXES):
                raise ValueError(f"device '{self.name}': bad acc repair {r}")
        for r in self.fsr_repair:
            if not 0 <= r.layer < C.FSR_LAYERS or any(not 0 <= c < C.FSR_GRID[1] for c in r.cols) or any(not 0 <= c < C.FSR_GRID[0] for c in r.rows):
                raise ValueError(f"device '{self.name}': bad fsr repair {r}")
        self._plan.update(_build_plan(self))

    @property
    def wiring_array(self) -> np.ndarray:
        return np.asarray(self.wiring, dtype=np.intp)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any] | None) -> "DeviceMap":
        """From a plain mapping / OmegaConf node::

            name: eskin_v1
            wiring: [0, 7, 8, ...]
            acc_repair: [{sensor: 6, axis: z}]
            fsr_repair: [{layer: 1, cols: [6, 7]}]
        """
        if cfg is None:
            return cls()
        cfg = dict(cfg)
        acc = []
        for r in cfg.get("acc_repair") or ():
            axis = r["axis"]
            acc.append(AccRepair(int(r["sensor"]), _AXES[axis] if isinstance(axis, str) else int(axis)))
        fsr = [FsrRepair(int(r["layer"]), tuple(int(c) for c in r.get("cols") or ()), tuple(int(c) for c in r.get("rows") or ())) for r in cfg.get("fsr_repair") or ()]
        return cls(str(cfg.get("name", "device")), tuple(cfg.get("wiring") or DEFAULT_WIRING), tuple(acc), tuple(fsr))

    def describe(self) -> str:
        """Compact JSON-able description stored with every recorded trial."""
        import json

        return json.dumps(
            {
                "name": self.name,
                "wiring": list(self.wiring),
                "acc_repair": [{"sensor": r.sensor, "axis": r.axis} for r in self.acc_repair],
                "fsr_repair": [{"layer": r.layer, "cols": list(r.cols), "rows": list(r.rows)} for r in self.fsr_repair],
            }
        )


def _nearest_valid(i: int, dead: set[int], n: int) -> list[int]:
    out = []
    for step in (-1, 1):
        j = i + step
        while 0 <= j < n and j in dead:
            j += step
        if 0 <= j < n:
            out.append(j)
    return out


def _build_plan(dm: DeviceMap) -> dict:
    """Precompute repairs as (target index, source indices) lists on flat views."""
    rows, cols = C.ACC_GRID
    wiring = dm.wiring
    dead_acc = {(wiring[r.sensor], r.axis) for r in dm.acc_repair}
    acc_plan = []
    for r in dm.acc_repair:
        g = wiring[r.sensor]
        gr, gc = divmod(g, cols)
        nb = [(gr + dr) * cols + gc + dc for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)) if 0 <= gr + dr < rows and 0 <= gc + dc < cols]
        nb = [n for n in nb if (n, r.axis) not in dead_acc]
        if not nb:
            raise ValueError(f"device '{dm.name}': acc sensor {r.sensor} axis {r.axis} has no valid neighbour")
        acc_plan.append((g, r.axis, nb))
    fsr_plan = []  # (layer, 'col'|'row', index, [sources])
    for r in dm.fsr_repair:
        dc, dr = set(r.cols), set(r.rows)
        for c in r.cols:
            src = _nearest_valid(c, dc, C.FSR_GRID[1])
            if not src:
                raise ValueError(f"device '{dm.name}': fsr layer {r.layer} column {c} has no valid neighbour")
            fsr_plan.append((r.layer, "col", c, src))
        for rr in r.rows:
            src = _nearest_valid(rr, dr, C.FSR_GRID[0])
            if not src:
                raise ValueError(f"device '{dm.name}': fsr layer {r.layer} row {rr} has no valid neighbour")
            fsr_plan.append((r.layer, "row", rr, src))
    return {"acc": acc_plan, "fsr": fsr_plan}


def repair(acc: np.ndarray, fsr: np.ndarray, device: DeviceMap) -> None:
    """Patch dead channels in place. ``acc`` (N, 4, 4, 3) grid order, ``fsr`` (N, 2, 16, 16)."""
    plan = device._plan
    if plan["acc"]:
        flat = acc.reshape(acc.shape[0], N_ACC_SENSORS, C.ACC_AXES)
        for g, axis, nb in plan["acc"]:
            flat[:, g, axis] = flat[:, nb, axis].mean(axis=1)
    for layer, kind, idx, src in plan["fsr"]:
        if kind == "col":
            vals = fsr[:, layer][:, :, src].astype(np.float64).mean(axis=2)
            fsr[:, layer, :, idx] = np.rint(vals).astype(fsr.dtype)
        else:
            vals = fsr[:, layer][:, src, :].astype(np.float64).mean(axis=1)
            fsr[:, layer, idx, :] = np.rint(vals).astype(fsr.dtype)


# --------------------------------------------------------------------------- decode / encode
def decode_packets(buf: bytes | bytearray | memoryview | np.ndarray, device: DeviceMap | None = None, *, apply_repair: bool = True):
    """Decode ``n`` back-to-back packets at once.

    Returns ``(acc (n,4,4,3) float32 g grid order, fsr (n,2,16,16) uint16, dt_acc (n,) uint32,
    dt_fsr (n,) uint32)``. ``len(buf)`` must be a multiple of :data:`PACKET_SIZE`.
    """
    device = device or DeviceMap()
    if len(buf) % PACKET_SIZE:
        raise ValueError(f"buffer of {len(buf)} bytes is not a whole number of {PACKET_SIZE}-byte packets")
    rec = np.frombuffer(buf, dtype=PACKET_DTYPE)
    n = rec.shape[0]
    acc = np.empty((n, N_ACC_SENSORS, C.ACC_AXES), dtype=np.float32)
    acc[:, device.wiring_array] = rec["acc"]  # wire i -> grid position wiring[i]
    acc *= np.float32(1.0 / C.ACC_COUNTS_PER_G)
    acc = acc.reshape(n, *C.ACC_GRID, C.ACC_AXES)
    fsr = np.ascontiguousarray(rec["fsr"].transpose(0, 2, 1, 3))  # (n, layer, row, col)
    if apply_repair:
        repair(acc, fsr, device)
    return acc, fsr, rec["dt_acc"].copy(), rec["dt_fsr"].copy()


def decode_packet(packet: bytes | bytearray | memoryview, device: DeviceMap | None = None, *, apply_repair: bool = True):
    """Decode one packet: ``(acc (4,4,3) g grid order, fsr (2,16,16) uint16, dt_acc, dt_fsr)``."""
    if len(packet) != PACKET_SIZE:
        raise ValueError(f"packet has {len(packet)} bytes, expected {PACKET_SIZE}")
    acc, fsr, da, df = decode_packets(packet, device, apply_repair=apply_repair)
    return acc[0], fsr[0], int(da[0]), int(df[0])


def encode_packets(acc_grid_g: np.ndarray, fsr: np.ndarray, dt_acc, dt_fsr, device: DeviceMap | None = None) -> bytes:
    """Inverse of :func:`decode_packets` (without repair): ``acc`` (n,4,4,3) g grid order,
    ``fsr`` (n,2,16,16) counts. Accelerations are rounded to the nearest count and clipped
    to int16; FSR counts are clipped to 0..4095."""
    device = device or DeviceMap()
    acc = np.asarray(acc_grid_g, dtype=np.float64).reshape(-1, N_ACC_SENSORS, C.ACC_AXES)
    n = acc.shape[0]
    fsr = np.asarray(fsr).reshape(n, C.FSR_LAYERS, *C.FSR_GRID)
    rec = np.zeros(n, dtype=PACKET_DTYPE)
    rec["dt_acc"] = np.broadcast_to(np.asarray(dt_acc, dtype=np.uint32), (n,))
    rec["dt_fsr"] = np.broadcast_to(np.asarray(dt_fsr, dtype=np.uint32), (n,))
    counts = np.clip(np.rint(acc * C.ACC_COUNTS_PER_G), -32768, 32767).astype("<i2")
    rec["acc"] = counts[:, device.wiring_array]  # wire i reads grid position wiring[i]
    rec["fsr"] = np.clip(fsr, 0, C.FSR_MAX_COUNT).astype("<u2").transpose(0, 2, 1, 3)
    return rec.tobytes()


def encode_packet(acc_grid_g: np.ndarray, fsr: np.ndarray, dt_acc: int, dt_fsr: int, device: DeviceMap | None = None) -> bytes:
    """One packet (``acc`` (4,4,3) g grid order, ``fsr`` (2,16,16))."""
    return encode_packets(np.asarray(acc_grid_g)[None], np.asarray(fsr)[None], dt_acc, dt_fsr, device)


# --------------------------------------------------------------------------- plausibility
@dataclass
class PlausibilityConfig:
    dt_min_us: int = 200  # board intervals outside [dt_min, dt_max] are impossible
    dt_max_us: int = 100_000
    dt_rel_tol: float = 1.0  # |dt - median(recent)| <= dt_rel_tol * median(recent) + dt_abs_tol_us
    dt_abs_tol_us: int = 500
    history: int = 32  # accepted packets kept for the median
    gravity_min_g: float = 0.25  # norm of the mean acceleration over the 16 sensors
    gravity_max_g: float = 2.5

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any] | None) -> "PlausibilityConfig":
        return cls(**dict(cfg or {}))


_FSR_OFF = 8 + 2 * N_ACC_SENSORS * C.ACC_AXES
_HDR = struct.Struct("<II")


class PlausibilityChecker:
    """Invariants a genuine, aligned packet satisfies (there is no checksum):

    1. every FSR word <= 4095 (12-bit ADC: the top 4 bits of all 512 uint16 are zero);
    2. ``dt_acc`` and ``dt_fsr`` within ``[dt_min_us, dt_max_us]``;
    3. each dt consistent with the median of the last ``history`` accepted packets;
    4. gravity sanity: the norm of the mean acceleration over the 16 sensors lies in
       ``[gravity_min_g, gravity_max_g]`` (the skin is static or moves slowly; the board
       always senses about 1 g).

    :meth:`check` returns ``None`` for a plausible packet (and records its dt), else a
    short reason string.
    """

    def __init__(self, cfg: PlausibilityConfig | None = None):
        self.cfg = cfg or PlausibilityConfig()
        self._dt_acc: deque[int] = deque(maxlen=self.cfg.history)
        self._dt_fsr: deque[int] = deque(maxlen=self.cfg.history)

    def reset_history(self) -> None:
        self._dt_acc.clear()
        self._dt_fsr.clear()

    def check(self, packet: bytes | bytearray | memoryview) -> str | None:
        cfg = self.cfg
        if len(packet) != PACKET_SIZE:
            return f"length {len(packet)}"
        fsr = np.frombuffer(packet, dtype="<u2", offset=_FSR_OFF)
        if (fsr > C.FSR_MAX_COUNT).any():
            return "fsr>4095"
        dt_acc, dt_fsr = _HDR.unpack_from(packet, 0)
        for name, dt, hist in (("dt_acc", dt_acc, self._dt_acc), ("dt_fsr", dt_fsr, self._dt_fsr)):
            if not cfg.dt_min_us <= dt <= cfg.dt_max_us:
                return f"{name}={dt}us out of range"
            if len(hist) >= 4:
                med = float(np.median(hist))
                if abs(dt - med) > cfg.dt_rel_tol * med + cfg.dt_abs_tol_us:
                    return f"{name}={dt}us inconsistent with recent {med:.0f}us"
        acc = np.frombuffer(packet, dtype="<i2", count=N_ACC_SENSORS * C.ACC_AXES, offset=8).reshape(N_ACC_SENSORS, C.ACC_AXES)
        g = float(np.linalg.norm(acc.mean(axis=0))) / C.ACC_COUNTS_PER_G
        if not cfg.gravity_min_g <= g <= cfg.gravity_max_g:
            return f"|mean acc|={g:.2f}g implausible"
        self._dt_acc.append(dt_acc)
        self._dt_fsr.append(dt_fsr)
        return None

