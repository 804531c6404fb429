"""Generate many simulated trials into one raw HDF5 file (resumable)."""

from __future__ import annotations

import logging
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Iterable

import h5py

from embodied_tactile import constants as C
from embodied_tactile.io.rawformat import make_attrs, trial_name, write_trial
from embodied_tactile.sim.physics import PhysicsOverrides
from embodied_tactile.sim.trial import simulate_trial

log = logging.getLogger(__name__)


_NEEDED = ("tactile/t", "tactile/acc", "tactile/fsr", "pose/t", "pose/ee")


def _existing(path: Path, seed: int) -> set[str]:
    """Names of the complete trials already in ``path``. A group left half-written by an
    interrupted run (write_trial sets the attributes last) is deleted so it is redone."""
    if not path.exists():
        return set()
    done: set[str] = set()
    with h5py.File(path, "a") as f:
        if "trials" not in f:
            return done
        for name in list(f["trials"].keys()):
            g = f["trials"][name]
            if "seed" in g.attrs and all(p in g for p in _NEEDED):
                done.add(name)
                if int(g.attrs["seed"]) != int(seed):
                    log.warning("%s: trial %s was simulated with seed %s, not %s", path, name, g.attrs["seed"], seed)
            else:
                log.warning("%s: removing incomplete trial %s (interrupted run)", path, name)
                del f["trials"][name]
    return done


def _job(args: tuple) -> object:
    object_id, skin, primitive, action, rep, seed, duration, physics = args
    return simulate_trial(object_id, skin, primitive, action, rep, seed, duration=duration, physics=physics)


def _init_worker() -> None:
    # one BLAS/OpenMP thread per worker process: the pool provides the parallelism
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"


def generate_dataset(
    path: str | os.PathLike,
    *,
    skin: str,
    primitive: str,
    objects: Iterable[int] = range(C.N_OBJECTS),
    actions: Iterable[int] = range(C.N_ACTIONS),
    repetitions: int = 1,
    seed: int = 0,
    workers: int = 2,
    overwrite: bool = False,
    duration: float = C.TRIAL_DURATION,
    physics: PhysicsOverrides | None = None,
) -> Path:
    """Simulate objects x actions x repetitions trials of one skin and primitive into ``path``.

    Trials already in the file are skipped (an interrupted run resumes) unless
    ``overwrite``, which regenerates them. Simulation runs in a pool of ``workers``
    processes; only the parent writes, one trial at a time, in deterministic order.
    """
    if skin not in C.SKINS:
        raise ValueError(f"skin must be one of {C.SKINS}, got {skin!r}")
    if primitive not in C.PRIMITIVES:
        raise ValueError(f"primitive must be one of {C.PRIMITIVES}, got {primitive!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    done = set() if overwrite else _existing(path, seed)
    jobs = []
    for o in objects:
        for a in actions:
            for r in range(int(repetitions)):
                name = trial_name(make_attrs(object_id=o, skin=skin, primitive=primitive, action_index=a, repetition=r, source="simulated", seed=seed))
                if name not in done:
                    jobs.append((int(o), skin, primitive, int(a), r, int(seed), float(duration), physics))
    log.info("%s: %d trials to simulate (%d already present)", path, len(jobs), len(done))
    if not jobs:
        with h5py.File(path, "a") as f:  # make sure the file exists with its root attrs
            f.require_group("trials")
        return path
    with h5py.File(path, "a") as f:
        if workers <= 1:
            results = map(_job, jobs)
            for trial in results:
                write_trial(f, trial, overwrite=overwrite)
        else:
            with ProcessPoolExecutor(max_workers=int(workers), initializer=_init_worker) as pool:
                for i, trial in enumerate(pool.map(_job, jobs, chunksize=4)):
                    write_trial(f, trial, overwrite=overwrite)
                    if (i + 1) % 64 == 0:
                        f.flush()
                        log.info("%s: %d / %d trials", path, i + 1, len(jobs))
    return path
