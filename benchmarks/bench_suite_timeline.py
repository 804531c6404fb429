"""Where the test suite's wall time goes under pytest-xdist: each worker's busy time, its idle
gaps (waiting for the realtime share, for a shared fixture, for the scheduler) and its longest
test phases.

    PYTHONPATH=benchmarks TIMELINE_DIR=/tmp/tl python -m pytest -n auto --dist worksteal -p bench_suite_timeline
    python benchmarks/bench_suite_timeline.py /tmp/tl [--gap 1.0] [--long 15]

Loaded as a pytest plugin (``-p bench_suite_timeline``), this module appends one row per test
phase (set-up, call, tear-down) to ``$TIMELINE_DIR/<worker>.tsv``: node id, phase,
start and end (seconds since the epoch). Run as a script, it prints a table per worker from
those files. A gap is time between the end of one phase and the start of the next on the same
worker: the scheduler's hand-over, or a test waiting in ``tests/conftest.py``'s
``pytest_runtest_protocol`` for its machine share (outside the set-up's own timing).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import pytest

_out = None


def _file():
    global _out
    if _out is None:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        _out = open(Path(os.environ["TIMELINE_DIR"]) / f"{worker}.tsv", "a", buffering=1)
    return _out


def _row(nodeid: str, phase: str, start: float) -> None:
    _file().write(f"{nodeid}\t{phase}\t{start:.3f}\t{time.time():.3f}\n")


def pytest_sessionstart(session):
    _row("<session>", "start", time.time())


def pytest_collection_finish(session):
    _row("<session>", "collected", time.time())


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item):
    start = time.time()
    yield
    _row(item.nodeid, "setup", start)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    start = time.time()
    yield
    _row(item.nodeid, "call", start)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item):
    start = time.time()
    yield
    _row(item.nodeid, "teardown", start)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="the TIMELINE_DIR of a run")
    ap.add_argument("--gap", type=float, default=1.0, help="list idle gaps longer than this (s)")
    ap.add_argument("--long", type=float, default=15.0, help="list test phases longer than this (s)")
    args = ap.parse_args()
    workers = {f.stem: [line.rstrip("\n").split("\t") for line in f.open()] for f in sorted(args.folder.glob("*.tsv"))}
    workers = {w: rows for w, rows in workers.items() if any(r[1] == "collected" for r in rows)}  # not xdist's controller
    if not workers:
        raise SystemExit(f"bench_suite_timeline: no <worker>.tsv in {args.folder}")
    t0 = min(float(r[2]) for rows in workers.values() for r in rows)
    print("| worker | collected at | last phase ends | busy | idle gaps > {:g} s |".format(args.gap))
    print("|---|---|---|---|---|")
    details = []
    for worker, rows in workers.items():
        collected = next(float(r[3]) - t0 for r in rows if r[1] == "collected")
        phases = sorted((float(r[2]) - t0, float(r[3]) - t0, r[1], r[0]) for r in rows if r[0] != "<session>")
        busy = sum(end - start for start, end, *_ in phases)
        gaps, until = [], collected
        for start, end, phase, node in phases:
            if start - until > args.gap:
                gaps.append((until, start - until, node))
            until = max(until, end)
        print(f"| {worker} | {collected:.1f} s | {until:.1f} s | {busy:.1f} s | {sum(g[1] for g in gaps):.1f} s in {len(gaps)} |")
        details += [f"{worker}: idle {length:.1f} s from {at:.1f} s, before {node}" for at, length, node in gaps]
        details += [f"{worker}: {end - start:.1f} s {phase} at {start:.1f} s: {node}"
                    for start, end, phase, node in phases if end - start > args.long]
    print()
    print("\n".join(details))


if __name__ == "__main__":
    main()
