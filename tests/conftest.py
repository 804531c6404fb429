"""Shared fixtures: a tiny simulated scene built once per session, CPU-only, no network."""

from __future__ import annotations

import contextlib
import os
import zlib
from pathlib import Path

import pytest
import embodied_tactile.run.config  # noqa: E402,F401  registers the typed configs and ${prior_rows:...}

# Never reach the network from tests; keep numba's cache out of read-only site-packages.
os.environ.setdefault("WANDB_MODE", "disabled")
os.environ.setdefault("WANDB_OFFLINE", "true")
os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(os.environ.get("TMPDIR", "/tmp")) / "embodied_tactile_numba"))
# The tests' trainings count each other, not the machine's (threadenv.TrainingRegistry).
TEST_TRAININGS_DIR = Path(os.environ.get("TMPDIR", "/tmp")) / f"embodied_tactile_test_trainings_{os.getpid()}"
os.environ.setdefault("EMBODIED_TACTILE_TRAININGS_DIR", str(TEST_TRAININGS_DIR))

REPO = Path(__file__).resolve().parents[1]


def share_files() -> tuple[Path, Path]:
    """The lock files of :func:`machine_share`: named after the run's training registry folder,
    which the workers inherit from the controller, so the controller can remove them."""
    base = os.environ["EMBODIED_TACTILE_TRAININGS_DIR"]
    return Path(f"{base}.share.turnstile"), Path(f"{base}.share.lock")


def pytest_sessionfinish(session, exitstatus):
    """The tests' training registry folder and the workers' lock files go when the run ends.
    Under pytest-xdist the workers inherit the controller's folder (the variable is set before
    they start), so the controller removes them, after every worker has finished."""
    if not hasattr(session.config, "workerinput") and os.environ.get("EMBODIED_TACTILE_TRAININGS_DIR") == str(TEST_TRAININGS_DIR):
        import shutil

        shutil.rmtree(TEST_TRAININGS_DIR, ignore_errors=True)
        for f in share_files():
            f.unlink(missing_ok=True)


#: The tiny scene: 4 objects (soft, hard, PLA-high-frequency, heterogeneous) x 2 actions x 2 reps.
TINY_OBJECTS = [0, 8, 17, 27]
TINY_ACTIONS = [0, 10]


def tiny_scene(data_dir: Path, channels=("acc",), **kw):
    """The tiny scene (soft / pressing, TINY_OBJECTS x TINY_ACTIONS x 2 repetitions) as the
    preparation stage's :class:`~embodied_tactile.data.prepare.Scene`."""
    from embodied_tactile.data.prepare import Scene

    args = dict(data_dir=str(data_dir), source="simulated", skin="soft", primitive="pressing",
                channels=tuple(channels), objects=TINY_OBJECTS, actions=TINY_ACTIONS, repetitions=2,
                sim_workers=2, preprocess_workers=1)
    args.update(kw)
    return Scene.from_config(**args)


@pytest.fixture(scope="session")
def tiny_prepared(tmp_path_factory):
    """The tiny scene prepared once by the preparation stage (simulated raw trials, acc and
    actions caches): ``PreparedData``."""
    from embodied_tactile.data.prepare import prepare_scene

    return prepare_scene(tiny_scene(tmp_path_factory.mktemp("data")))


@pytest.fixture(scope="session")
def tiny_data_dir(tiny_prepared) -> Path:
    """A data dir holding raw soft/pressing trials of the tiny scene (simulated once, by the
    preparation stage; its acc and actions caches are there too)."""
    return Path(tiny_prepared.scene.data_dir)


def tiny_datamodule(data_dir: Path, channels, **kw):
    from embodied_tactile.data.datamodule import TactileDataModule

    args = dict(
        data_dir=str(data_dir), source="simulated", skin="soft", primitive="pressing", channels=list(channels),
        objects=TINY_OBJECTS, actions=TINY_ACTIONS, repetitions=2, sim_workers=1, preprocess_workers=1,
        batch_size=4, num_workers=0, train_window=None, windows_per_trial=1, windows_per_epoch=None,  # whole trials
    )
    args.update(kw)
    return TactileDataModule.from_config(**args)


@pytest.fixture(scope="session")
def fast_data_dir(tiny_data_dir, tmp_path_factory) -> Path:
    """A copy of the tiny scene's raw file for train.py runs with ``debug=fast``, which
    simulate that scene's extra action into it: the shared ``tiny_data_dir`` stays exactly
    the tiny scene, whatever order the tests run in."""
    import shutil

    d = tmp_path_factory.mktemp("fast_data")
    shutil.copytree(tiny_data_dir / "raw", d / "raw")
    return d


@pytest.fixture(scope="session")
def train_py_run(fast_data_dir, tmp_path_factory):
    """``python train.py debug=fast trainer.max_epochs=2 hydra.run.dir=run`` on the tiny scene,
    started in a folder of its own in a fresh interpreter, as a user starts it (the session's
    one train.py subprocess of the default recipe; the other runs use train.py's entry point in
    this process): (run folder ``<folder>/run``, ``subprocess.CompletedProcess`` with its
    output). Tests only read it, so under pytest-xdist the workers share it: the first to need
    it trains in the run's common temporary folder, the others wait for it and read its outcome."""
    import fcntl
    import json
    import subprocess
    import sys

    shared = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = shared.parent  # the session's folder, above each worker's own
    folder, done = shared / "train_py", shared / "train_py.json"
    with open(shared / "train_py.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            folder.mkdir(exist_ok=True)
            env = {**os.environ, "WANDB_MODE": "disabled", "PYTHONUNBUFFERED": "1"}
            res = subprocess.run([sys.executable, str(REPO / "train.py"), "debug=fast", "trainer.max_epochs=2",
                                  f"paths.data_dir={fast_data_dir}", "hydra.run.dir=run"], cwd=folder, env=env,
                                 capture_output=True, text=True, timeout=300)
            done.write_text(json.dumps({"args": res.args, "returncode": res.returncode, "stdout": res.stdout,
                                        "stderr": res.stderr}))
    res = subprocess.CompletedProcess(**json.loads(done.read_text()))
    assert res.returncode == 0, f"train.py failed ({res.returncode}):\n{res.stdout[-3000:]}\n{res.stderr[-5000:]}"
    return folder / "run", res


@contextlib.contextmanager
def machine_share(alone: bool):
    """Under pytest-xdist, a readers-writer lock shared by the run's workers: ``alone`` waits
    until no other worker runs a test and keeps them waiting, else it runs beside the others
    (a turnstile keeps a waiting ``alone`` from being starved). Without xdist: nothing to do."""
    if os.environ.get("PYTEST_XDIST_TESTRUNUID") is None:
        yield
        return
    import fcntl

    turnstile_file, lock_file = share_files()
    with open(turnstile_file, "a") as turnstile, open(lock_file, "a") as lock:
        fcntl.flock(turnstile, fcntl.LOCK_EX)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        finally:
            fcntl.flock(turnstile, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _realtime(item) -> bool:
    return item is not None and item.get_closest_marker("realtime") is not None


class _Share:
    """This worker's :func:`machine_share`, kept from one ``realtime`` test to the next one it
    runs: a run of them waits once for the other worker's test in progress, not once each."""

    stack = contextlib.ExitStack()
    alone: bool | None = None


def pytest_collection_modifyitems(items):
    """The ``realtime`` tests first, in their collected order: one worker runs them as one block
    and takes the machine once (:class:`_Share`), instead of waiting for the other worker's
    test in progress at each module of them. Deterministic, so every xdist worker collects the
    same order."""
    items.sort(key=lambda item: not _realtime(item))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """A test marked ``realtime`` (the recorder polling an emulated board at 700 packets/s)
    runs, with the set-up and tear-down of its fixtures, while no other worker runs a test or
    sets up a fixture (:func:`machine_share`): on 2 cores a training or a simulation beside
    the recorder drops over 10 % of its packets, and the trial is rightly stored incomplete.
    The share is kept while the next test of this worker is realtime too."""
    alone = _realtime(item)
    if not (alone and _Share.alone):
        _Share.stack.close()
        _Share.stack.enter_context(machine_share(alone))
        _Share.alone = alone
    try:
        yield
    finally:
        if not (alone and _realtime(nextitem)):
            _Share.stack.close()
            _Share.alone = None


@pytest.fixture()
def restore_logging():
    """For a test that runs a Hydra app in this process (record / palpate main): Hydra's job
    logging replaces the root logger's handlers (a console handler on this test's captured
    output, a file handler); put the handlers and levels back so later tests log as before."""
    import logging

    root, pkg = logging.getLogger(), logging.getLogger("embodied_tactile")
    handlers, levels = root.handlers[:], (root.level, pkg.level)
    yield
    for h in root.handlers:
        if h not in handlers:
            h.close()
    root.handlers[:] = handlers
    root.setLevel(levels[0])
    pkg.setLevel(levels[1])


def train_in_process(*args: str, cwd: Path | None = None):
    """``python train.py <args>`` run by train.py's entry point (``cli.train_main``) in this
    process: a ``subprocess.CompletedProcess`` with its exit status and what it printed
    (Python's stdout / stderr: Hydra's console log, prints and warnings). A fresh interpreter
    costs seconds of imports per run; what a run changes in the process is put back
    afterwards: the working folder, environment, torch threads, SIGINT / SIGTERM handlers,
    every logger's handlers and level (Hydra's job logging), warning filters and Hydra's
    global state; and what the end of train.py's process would end: the run folders' locks
    it took (held "for the rest of the process", run.runfolder.lock) and the files its
    objects left open (a garbage collection)."""
    import contextlib
    import gc
    import io
    import logging
    import signal
    import subprocess
    import warnings

    import torch
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig

    from embodied_tactile.cli import train_main
    from embodied_tactile.run import runfolder

    loggers = [logging.getLogger(), *(lg for lg in logging.root.manager.loggerDict.values()
                                      if isinstance(lg, logging.Logger))]
    logs = {lg: (lg.handlers[:], lg.level, lg.propagate, lg.disabled) for lg in loggers}
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    env, threads, here, filters = dict(os.environ), torch.get_num_threads(), os.getcwd(), warnings.filters[:]
    held, created = set(runfolder._held), set(runfolder._created)
    out, err = io.StringIO(), io.StringIO()
    try:
        if cwd is not None:
            os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = train_main(list(args))
    finally:
        os.chdir(here)
        os.environ.clear()
        os.environ.update(env)
        torch.set_num_threads(threads)
        for s, h in handlers.items():
            signal.signal(s, h)
        for lg in [logging.getLogger(), *logging.root.manager.loggerDict.values()]:
            if not isinstance(lg, logging.Logger):
                continue
            kept, level, propagate, disabled = logs.get(lg, ([], logging.NOTSET, True, False))
            for h in lg.handlers:
                if h not in kept:
                    h.close()
            lg.handlers[:] = kept
            lg.setLevel(level)
            lg.propagate, lg.disabled = propagate, disabled
        warnings.filters[:] = filters
        HydraConfig.instance().cfg = None
        GlobalHydra.instance().clear()
        for run_dir in set(runfolder._held) - held:
            runfolder.release(run_dir)
        runfolder._created.intersection_update(created)
        gc.collect()
    return subprocess.CompletedProcess(["train.py", *args], code, out.getvalue(), err.getvalue())


def stable_seed(text: str, modulo: int = 1000) -> int:
    """A seed from a label that is the same in every process (``hash()`` of a str is salted
    per process, which made synthetic tables differ between runs)."""
    return zlib.crc32(text.encode()) % modulo
