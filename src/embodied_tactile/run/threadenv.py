"""The thread environment of a training, importing nothing heavy: OpenMP's wait policy, set
before torch loads OpenMP, and the registry of the trainings running on this machine
(``runtime.ThreadShare`` divides the cores among them).

torch's intra-op pool (ATen parallel backend: OpenMP) keeps its threads spinning at every
barrier for a while by default (OMP_WAIT_POLICY=ACTIVE behaviour). When two trainings share
the cores, each one's spinning threads take the time the other's working threads need.
``PASSIVE`` makes waiting threads sleep instead. The OpenMP runtime reads the variable
once, when the library is loaded (``import torch``), so this module imports nothing heavy
and is imported by ``train.py`` before torch. A value the user set is kept.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

#: the wait policy of every training unless OMP_WAIT_POLICY is already set
OMP_WAIT_POLICY = "PASSIVE"


def wait_passively() -> bool:
    """Set ``OMP_WAIT_POLICY`` (unless set) and say whether it can still take effect (torch
    not imported yet in this process)."""
    os.environ.setdefault("OMP_WAIT_POLICY", OMP_WAIT_POLICY)
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


wait_passively()
