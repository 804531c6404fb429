"""Where touches come from: the :class:`TouchSource` protocol, answered by the simulator
(:class:`SimulatedTouchSource`) or by a recorder's raw HDF5 files (:class:`RecordedTouchSource`).

A touch is addressed by (object, action parameter set, ``use``): ``use`` counts how often the
episode already touched that object with that action (0 for the first time). Both sources
return one :class:`~embodied_tactile.data.rawformat.RawTrial`; preprocessing and the model
never see which source answered.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Protocol, runtime_checkable

from embodied_tactile import constants as C
from embodied_tactile.data.rawformat import RawTrial, read_trial, scan_raw, trial_name


@runtime_checkable
class TouchSource(Protocol):
    """Answers palpation actions on one skin with one primitive."""

    skin: str
    primitive: str

    def touch(self, object_id: int, action_index: int, use: int) -> RawTrial:
        """The ``use``-th touch of ``object_id`` with ``action_index`` (contact reset before it)."""
        ...


class SimulatedTouchSource:
    """The simulator (:func:`embodied_tactile.sim.episode.simulate_touch`) under one episode
    seed: the seed stream of each touch is (episode seed, object, action, use)."""

    def __init__(self, skin: str, primitive: str, episode_seed: int = 0, physics=None) -> None:
        from embodied_tactile.sim.episode import touch_seed

        touch_seed(episode_seed)  # validates
        if skin not in C.SKINS or primitive not in C.PRIMITIVES:
            raise ValueError(f"skin must be one of {C.SKINS} and primitive one of {C.PRIMITIVES}, "
                             f"got {skin!r}, {primitive!r}")
        self.skin, self.primitive, self.episode_seed, self.physics = skin, primitive, int(episode_seed), physics

    def touch(self, object_id: int, action_index: int, use: int) -> RawTrial:
        from embodied_tactile.sim.episode import simulate_touch

        return simulate_touch(object_id, self.skin, self.primitive, action_index, use, self.episode_seed,
                              physics=self.physics)


class RecordedTouchSource:
    """Recorded trials (the recorder's raw files): touch ``use`` of an action is the trial with
    ``repetition == use`` (e.g. ``obj07_soft_pressing_a14_r01``). A touch that was not
    recorded is an error naming the trial and the files searched."""

    def __init__(self, raw_files: Sequence[str | Path], skin: str, primitive: str) -> None:
        self.skin, self.primitive = skin, primitive
        self.files = [str(f) for f in raw_files]
        good, _ = scan_raw(self.files, validate_data=False)
        self._where = {info.name: info.file for info in good}

    def touch(self, object_id: int, action_index: int, use: int) -> RawTrial:
        name = trial_name(dict(object_id=object_id, skin=self.skin, primitive=self.primitive,
                               action_index=action_index, repetition=use))
        if name not in self._where:
            raise KeyError(f"touch {name!r} was not recorded (searched {self.files})")
        return read_trial(self._where[name], name)
