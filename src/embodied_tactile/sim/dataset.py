"""Generate many simulated trials into one raw HDF5 file (resumable, never deleting data).

Ownership rules (docs/reference/data_format.md, "What is never deleted"): the simulator writes only
into a new file or a file whose every trial is marked ``source="simulated"``; it adds only
the trials that are missing; the one group it may remove is its own interrupted write,
which it names in the file's ``simulator_writing`` attribute before creating the group.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Iterable

import h5py

from embodied_tactile import constants as C
from embodied_tactile.data.rawformat import trial_name, write_trial
from embodied_tactile.options.simulation import SimulationOptions
from embodied_tactile.sim import objects as O
from embodied_tactile.sim.physics import PHYSICS_VERSION, VERSION_ATTR, PhysicsOverrides
from embodied_tactile.sim.trial import simulate_trial
from embodied_tactile.sim.validation import (SimParameterError, check_choice, check_duration, check_int, check_object,
                                             check_overrides)
from embodied_tactile.run.workers import init_worker

log = logging.getLogger(__name__)


_NEEDED = ("tactile/t", "tactile/acc", "tactile/fsr", "pose/t", "pose/ee")
#: Root attribute naming the trial group the simulator is writing right now. It is set (and
#: flushed) before the group is created and removed once the group is complete, so a group
#: it names after a crash is the simulator's own half-written trial.
PENDING_ATTR = "simulator_writing"


class OutputFileError(ValueError):
    """The output file holds data the simulator must not alter. Names file and trial."""

    def __init__(self, file: str | os.PathLike, trial: str, problem: str):
        self.file, self.trial, self.problem = str(file), trial, problem
        super().__init__(f"{self.file}: trial {trial!r}: {problem}")

    def __reduce__(self):
        return (type(self), (self.file, self.trial, self.problem))


def _text(v: object) -> str | None:
    return v.decode() if isinstance(v, bytes) else (None if v is None else str(v))


def _inventory(path: Path, seed: int) -> tuple[set[str], dict[str, str], str | None, dict[str, int]]:
    """Read ``path`` (read-only) and return (complete simulated trials, damaged simulated
    trials -> what they lack, the simulator's own interrupted group or None, stale trials
    -> their physics version). A stale trial is a simulated trial, complete or not, whose
    ``sim_physics_version`` (absent = 1) is not :data:`PHYSICS_VERSION`; it is in neither
    of the first two.

    Raises :class:`OutputFileError` if the file holds anything the simulator did not write
    and mark: a trial whose ``source`` is not ``"simulated"`` (recorded, or no attributes),
    or content outside ``/trials``. Such a file is never opened for writing.
    """
    if not path.exists():
        return set(), {}, None, {}
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise OutputFileError(path, "*", f"cannot be opened as HDF5 ({exc}); simulated trials are only written into a new or a simulated raw file") from None
    complete: set[str] = set()
    damaged: dict[str, str] = {}
    stale: dict[str, int] = {}
    with f:
        other = sorted(k for k in f.keys() if k != "trials")
        if other:
            raise OutputFileError(path, "*", f"holds {other}, not only /trials: not a simulated raw file; choose another output file")
        if "trials" not in f:
            return complete, damaged, None, stale
        pending = _text(f.attrs.get(PENDING_ATTR))
        for name in f["trials"].keys():
            if name == pending:
                continue
            g = f["trials"][name]
            source = _text(g.attrs.get("source"))
            if source != "simulated":
                raise OutputFileError(
                    path, name,
                    f"source={source!r}, not 'simulated': the file holds trials the simulator did not write, "
                    "and simulated trials are never written into such a file (it is left unchanged); choose another output file",
                )
            version = int(g.attrs.get(VERSION_ATTR, 1))
            if version != PHYSICS_VERSION:
                stale[name] = version  # damaged or not: it is redone, or the file is refused
                continue
            lacks = [p for p in _NEEDED if p not in g] + (["attrs/seed"] if "seed" not in g.attrs else [])
            if lacks:
                damaged[name] = ", ".join(lacks)
                continue
            complete.add(name)
            if int(g.attrs["seed"]) != int(seed):
                log.warning("%s: trial %s was simulated with seed %s, not %s", path, name, g.attrs["seed"], seed)
        return complete, damaged, pending if pending is not None and pending in f["trials"] else None, stale


def _checked_object(i: int, obj: int | C.WaveObject) -> int | C.WaveObject:
    if isinstance(obj, C.WaveObject):
        check_object(obj)
        return obj
    return check_int(f"objects[{i}]", obj, 0, C.N_OBJECTS - 1)


def _name(object_id: int, skin: str, primitive: str, action_index: int, repetition: int) -> str:
    return trial_name(dict(object_id=object_id, skin=skin, primitive=primitive, action_index=action_index,
                           repetition=repetition))


def requested_trials(objects: Iterable[int | C.WaveObject], skin: str, primitive: str, actions: Iterable[int],
                     repetitions: int) -> set[str]:
    """The raw trial names of objects x actions x repetitions (what :func:`generate_dataset` simulates)."""
    acts = list(actions)
    return {_name(O.as_object(o).object_id, skin, primitive, int(a), r)
            for o in objects for a in acts for r in range(int(repetitions))}


def _job(args: tuple) -> object:
    object_id, skin, primitive, action, rep, seed, duration, physics = args
    return simulate_trial(object_id, skin, primitive, action, rep, seed, duration=duration, physics=physics)


def _aside_path(path: Path, version: int) -> Path:
    """A free name next to ``path`` for a file of an older physics: ``<stem>.physics-v<N>[.k].h5``."""
    aside, k = path.with_name(f"{path.stem}.physics-v{version}{path.suffix}"), 1
    while aside.exists():
        aside, k = path.with_name(f"{path.stem}.physics-v{version}.{k}{path.suffix}"), k + 1
    return aside


def generate_dataset(
    path: str | os.PathLike,
    *,
    skin: str,
    primitive: str,
    objects: Iterable[int | C.WaveObject] = range(C.N_OBJECTS),
    actions: Iterable[int] = range(C.N_ACTIONS),
    repetitions: int = SimulationOptions.repetitions,
    seed: int = SimulationOptions.seed,
    workers: int = SimulationOptions.workers,
    overwrite: bool = False,
    duration: float = SimulationOptions.duration,
    physics: PhysicsOverrides | None = None,
) -> Path:
    """Simulate objects x actions x repetitions trials of one skin and primitive into ``path``.
    ``objects``: catalogue ids or ``WaveObject`` (a population, ``sim.population``).

    Only missing trials are simulated (an interrupted run resumes); ``overwrite``
    regenerates the requested trials. A requested trial simulated by an older physics
    (``sim_physics_version`` attribute absent or not :data:`PHYSICS_VERSION`) is
    re-simulated with a warning; when the file also holds older trials that are not requested,
    it is moved aside whole and unchanged (``<stem>.physics-v<N>.h5``, a warning names both)
    and the requested trials go into a new file: one file never holds two physics and
    nothing is deleted. The file must be new or hold simulated trials only
    (:class:`OutputFileError` otherwise, before anything is written). A simulated trial that
    lacks a field is present, not missing: it is kept with a warning naming the field (a
    reader that needs the field skips it), and regenerated only with ``overwrite``. Every argument is
    checked first (``SimParameterError``). Simulation runs in a pool of ``workers``
    processes (0 or 1: in this process); only the parent writes, one trial at a time, in
    deterministic order.
    """
    skin = check_choice("skin", skin, C.SKINS)
    primitive = check_choice("primitive", primitive, C.PRIMITIVES)
    objects = list(dict.fromkeys(_checked_object(i, o) for i, o in enumerate(objects)))
    if len({O.as_object(o).object_id for o in objects}) != len(objects):
        raise SimParameterError("objects", [O.as_object(o).object_id for o in objects], "objects with distinct ids")
    actions = list(dict.fromkeys(check_int(f"actions[{i}]", a, 0, C.N_ACTIONS - 1) for i, a in enumerate(actions)))
    if not objects:
        raise SimParameterError("objects", objects, f"a non-empty list of object ids 0..{C.N_OBJECTS - 1}")
    if not actions:
        raise SimParameterError("actions", actions, f"a non-empty list of action indices 0..{C.N_ACTIONS - 1}")
    repetitions = check_int("repetitions", repetitions, 1)
    seed = check_int("seed", seed, 0)
    workers = check_int("workers", workers, 0)
    duration = check_duration(duration)
    check_overrides(physics)
    if not isinstance(overwrite, bool):
        raise SimParameterError("overwrite", overwrite, "true or false")
    path = Path(path)
    complete, damaged, partial, stale = _inventory(path, seed)
    ids = {o: O.as_object(o).object_id for o in objects}
    requested = requested_trials(objects, skin, primitive, actions, repetitions)
    kept_stale = sorted(set(stale) - requested)
    if kept_stale:  # older trials this run would not redo: the file moves aside whole, unchanged
        aside = _aside_path(path, min(stale.values()))
        path.rename(aside)
        log.warning("%s holds %d trial(s) simulated by physics version %s that this run does not regenerate "
                    "(first: %s); the simulator is at version %d and one file never mixes two physics: the file "
                    "is kept unchanged as %s and the requested trials are simulated into a new %s",
                    path, len(kept_stale), stale[kept_stale[0]], kept_stale[0], PHYSICS_VERSION, aside, path.name)
        complete, damaged, partial, stale = _inventory(path, seed)
    jobs = []
    for o in objects:
        for a in actions:
            for r in range(repetitions):
                name = _name(ids[o], skin, primitive, a, r)
                if name in damaged and not overwrite:
                    log.warning(
                        "%s: trial %s lacks %s; kept as it is (the simulator never deletes a trial, and a reader "
                        "that needs the field skips the trial): remove it or pass overwrite=true to regenerate it",
                        path, name, damaged[name],
                    )
                elif overwrite or name not in complete or name in stale:
                    jobs.append((o, skin, primitive, a, r, seed, duration, physics))
    if stale:
        log.warning("%s: re-simulating %d trial(s) simulated by an older physics version (first: %s, version %d; now %d)",
                    path, len(stale), min(stale), stale[min(stale)], PHYSICS_VERSION)
    log.info("%s: %d trials to simulate (%d already present)", path, len(jobs), len(complete) + len(damaged) + len(stale))
    if not jobs and partial is None:
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "a") as f:
        if partial is not None:
            log.warning("%s: removing trial %s, left half-written by an interrupted simulator run", path, partial)
            del f["trials"][partial]
            del f.attrs[PENDING_ATTR]
            f.flush()

        def write(trial) -> None:
            f.attrs[PENDING_ATTR] = trial.name
            f.flush()  # the mark reaches the file before the group does
            write_trial(f, trial, overwrite=overwrite or trial.name in stale)
            del f.attrs[PENDING_ATTR]

        if workers <= 1:
            for trial in map(_job, jobs):
                write(trial)
        else:
            with ProcessPoolExecutor(max_workers=workers, initializer=init_worker) as pool:
                for i, trial in enumerate(pool.map(_job, jobs, chunksize=4)):
                    write(trial)
                    if (i + 1) % 64 == 0:
                        log.info("%s: %d / %d trials", path, i + 1, len(jobs))
    return path
