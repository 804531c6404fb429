"""The thread environment of a training, importing nothing heavy: how long OpenMP's threads
spin at a barrier, set before torch loads OpenMP, and the registry of the trainings running
on this machine (``run.threads.ThreadShare`` divides the cores among them).

torch's intra-op pool (ATen parallel backend: OpenMP; the pip wheels bundle GNU libgomp)
keeps a waiting thread spinning for about 3 ms by default (300,000 spins). When two
trainings oversubscribe the cores, each one's spinning threads take the time the other's
working threads need; ``OMP_WAIT_POLICY=PASSIVE`` (no spinning) cured that but made every
one of a step's thousands of small parallel regions pay a sleep and a wake-up: a lone
training's 2-thread step took 0.31 s instead of 0.16 s (docs/experiments/speed_levers.md,
2026-11-27). ``GOMP_SPINCOUNT=1000`` (about 10 µs of spinning) keeps the lone step at 0.18 s
and two oversubscribed trainings at 0.49 s a step each (0.37 s under PASSIVE); with the
thread share (one thread each) nothing oversubscribes. libgomp reads the variable once, when
torch loads it, so this module imports nothing heavy and train.py imports it before torch.
A ``GOMP_SPINCOUNT`` or ``OMP_WAIT_POLICY`` the user set is kept (libgomp lets
``GOMP_SPINCOUNT`` win over the policy); other OpenMP runtimes ignore the variable.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

#: libgomp's spins at a barrier before a thread sleeps (about 10 µs), unless the user set
#: GOMP_SPINCOUNT or OMP_WAIT_POLICY
SPIN_COUNT = "1000"


def spin_briefly() -> bool:
    """Set ``GOMP_SPINCOUNT`` (unless it or ``OMP_WAIT_POLICY`` is set) and say whether it can
    still take effect (torch not imported yet in this process)."""
    if "OMP_WAIT_POLICY" not in os.environ:
        os.environ.setdefault("GOMP_SPINCOUNT", SPIN_COUNT)
    return "torch" not in sys.modules


#: environment variable naming another registry folder (the tests' own, say)
REGISTRY_ENV = "EMBODIED_TACTILE_TRAININGS_DIR"


def registry_dir() -> Path:
    """Where this user's live trainings register: ``$EMBODIED_TACTILE_TRAININGS_DIR`` if
    set, else ``<temp dir>/embodied_tactile-<uid>/trainings``."""
    import tempfile

    if os.environ.get(REGISTRY_ENV):
        return Path(os.environ[REGISTRY_ENV])
    uid = os.getuid() if hasattr(os, "getuid") else 0
    return Path(tempfile.gettempdir()) / f"embodied_tactile-{uid}" / "trainings"


class TrainingRegistry:
    """The trainings running on this machine (one user's): one file per training process,
    ``<pid>-<ns>.live``, which the process holds locked (``fcntl.flock``) while it lives.
    The OS frees the lock when the process ends, kill -9 included, so a file whose lock
    can be taken is a finished training's and is removed by whoever counts. A file is
    locked before it gets its ``.live`` name (a rename), so a count never sees it unlocked.
    Where ``fcntl`` is missing (Windows) only this process counts."""

    SUFFIX = ".live"

    def __init__(self, folder: str | os.PathLike | None = None) -> None:
        self._folder = folder
        self._fd: int | None = None
        self._path: Path | None = None

    @property
    def folder(self) -> Path:
        """The folder given, else :func:`registry_dir` (read when used, not when built)."""
        return Path(self._folder) if self._folder is not None else registry_dir()

    @property
    def registered(self) -> bool:
        return self._fd is not None

    def register(self) -> None:
        """Enter this process (once; later calls do nothing)."""
        if self._fd is not None:
            return
        try:
            import fcntl
        except ImportError:  # pragma: no cover - Windows
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        name = f"{os.getpid()}-{time.time_ns()}"
        tmp = self.folder / f"{name}.tmp"
        fd = os.open(tmp, os.O_CREAT | os.O_WRONLY | os.O_TRUNC, 0o600)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.write(fd, f"{os.getpid()} {' '.join(sys.argv)}\n".encode())
        path = tmp.with_suffix(self.SUFFIX)
        os.replace(tmp, path)
        self._fd, self._path = fd, path

    def release(self) -> None:
        """Leave the registry (the process ending does the same)."""
        if self._fd is None:
            return
        try:
            self._path.unlink(missing_ok=True)
        finally:
            os.close(self._fd)
            self._fd = self._path = None

    def count(self) -> int:
        """Live trainings, this process included when registered; finished ones' files removed."""
        try:
            import fcntl
        except ImportError:  # pragma: no cover - Windows
            return 1
        live = 0
        for path in self.folder.glob(f"*{self.SUFFIX}"):
            if path == self._path:
                live += 1
                continue
            try:
                fd = os.open(path, os.O_RDONLY)
            except OSError:  # removed meanwhile
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:  # held: a live training
                live += 1
            else:  # nobody holds it: its training ended without removing it
                path.unlink(missing_ok=True)
            finally:
                os.close(fd)
        return max(live, 1 if self.registered else 0)


spin_briefly()


def set_threads(n: int) -> int:
    """The one place that sets the intra-op threads: torch, and OMP / MKL / OpenBLAS for
    processes started later (DataLoader workers, numba, BLAS in sklearn). Returns ``n``."""
    n = int(n)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(n)
    import torch

    torch.set_num_threads(n)
    return n
