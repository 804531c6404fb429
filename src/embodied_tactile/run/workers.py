"""The start of a worker process of the data preparation's pools (the simulation's and the
caches'): one BLAS thread, the default SIGTERM, Ctrl-C left to the parent, and freed memory
kept in the process.

Memory: a simulated trial allocates and frees arrays of up to 24 MB (the contact front's
1.0 M sub-grid points). glibc serves each from fresh pages of its own mapping and returns them
when freed, so every trial faulted 6,500-13,000 pages in again: 16-28 ms of system time
against 104-124 ms of user time per soft-pressing trial (AMD EPYC, loaded machine,
2026-12-08; docs/experiments/simulator_speed.md). With the mmap threshold at 32 MB (glibc's
ceiling) and the heap trimmed only above 256 MB those arrays come from the heap and stay
there: no page faults, the same peak resident memory (346 MB), the same arrays.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal

#: glibc's mallopt parameters (malloc.h) and the values the workers set
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD_BYTES = 32 << 20  # glibc's largest (DEFAULT_MMAP_THRESHOLD_MAX on 64-bit)
TRIM_THRESHOLD_BYTES = 256 << 20  # 64 MB still faulted 5,800 pages a trial


def one_blas_thread():
    """Parallelism comes from the process pool: keep BLAS single-threaded inside it
    (oversubscribed OpenBLAS threads spin and were 3-5x slower on a loaded 2-core box)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def hold_freed_memory() -> bool:
    """Large arrays from the heap, and freed heap kept up to ``TRIM_THRESHOLD_BYTES``
    (glibc's ``mallopt``); False where the C library has no mallopt (macOS, Windows) or
    refuses a value: the process then runs with its allocator's defaults."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) & bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))


def init_worker() -> None:
    """A pool's initializer (simulation and caches)."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"  # for libraries loaded after the fork
    one_blas_thread()  # applied on construction; holds for the worker's life (3 ms per call)
    hold_freed_memory()
    # a forked worker inherits train.py's stop handlers; the pool ends its workers with SIGTERM,
    # which must end them (a handler that records the signal left a worker waiting on the task
    # queue's lock and the pool's join hanging: seen in a sweep on 2026-11-26)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
