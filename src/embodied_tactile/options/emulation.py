"""``embodied-tactile emulate``'s options, typed, with their one default each (no heavy
imports): the trial the fake e-Skin serves, its pacing and the faults it injects
(:class:`FaultOptions`, also :class:`embodied_tactile.hardware.emulator.Faults`).
``configs/emulate.yaml`` composes :class:`EmulationOptions` and names none of them again."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from embodied_tactile import constants as C
from embodied_tactile.options.checks import at_least, bounds, one_of

PROBABILITY = bounds(0.0, 1.0)


@dataclass
class FaultOptions:
    """``faults``: per-request fault probabilities (checked in this order) and the disconnect trigger."""

    drop: float = field(default=0.0, metadata=PROBABILITY)      # ignore the request
    delay: float = field(default=0.0, metadata=PROBABILITY)     # answer after delay_s
    delay_s: float = field(default=0.15, metadata=at_least(0))  # beyond the recorder's timeout to be a fault
    truncate: float = field(default=0.0, metadata=PROBABILITY)  # send only part of the packet
    garbage: float = field(default=0.0, metadata=PROBABILITY)   # random bytes, a shifted packet or one followed by junk
    garbage_mode: str = field(default="mixed", metadata=one_of("random", "shift", "long", "mixed"))
    disconnect_after_packets: Optional[int] = field(default=None, metadata=at_least(0))
    disconnect_after_s: Optional[float] = field(default=None, metadata=at_least(0))
    seed: int = 0                                               # the faults' RNG seed


@dataclass
class EmulationOptions:
    """``embodied-tactile emulate``: the trial served (``trial_file``, else ``synthetic``
    seconds of a built-in trial, else one simulated trial), how it is paced, the faults."""

    trial_file: Optional[str] = None      # raw HDF5 file to serve a trial from
    trial_name: Optional[str] = None      # its trial (group name); null = the first valid trial
    synthetic: Optional[float] = field(default=None, metadata=bounds(0.0, None, lo_open=True))  # s; no simulator needed
    object_id: int = 0                    # the simulated trial's object, skin, primitive, action and seed
    skin: str = field(default="soft", metadata=one_of(*C.SKINS))
    primitive: str = field(default="pressing", metadata=one_of(*C.PRIMITIVES))
    action_index: int = 0
    sim_seed: int = 0
    rate: Optional[float] = field(default=None, metadata=at_least(0))  # packets/s; null = the trial's fs_tactile; 0 = as fast as asked
    pacing: str = field(default="fifo", metadata=one_of("fifo", "grid"))  # fifo: a backlog up to max_lag_s at once; grid: one per tick
    max_lag_s: float = field(default=0.05, metadata=at_least(0))
    loop: bool = True                     # false: stop answering at the end of the trial
    device: Optional[str] = None          # device map YAML of the wiring; null = configs/record/device/ideal.yaml's
    link: Optional[str] = None            # also create this symlink to the pty (a stable port name)
    max_seconds: Optional[float] = field(default=None, metadata=at_least(0))  # exit after this long
    faults: FaultOptions = field(default_factory=FaultOptions)


__all__ = ["EmulationOptions", "FaultOptions"]
