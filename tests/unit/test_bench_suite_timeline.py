"""benchmarks/bench_suite_timeline.py: the table of a suite run's per-worker busy time and idle
gaps, from the rows its plugin writes (no timings of this run asserted)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_suite_timeline.py"


@pytest.fixture(scope="module")
def timeline():
    spec = importlib.util.spec_from_file_location("bench_suite_timeline", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _write(folder: Path, worker: str, rows: list[tuple[str, str, float, float]]) -> None:
    (folder / f"{worker}.tsv").write_text("".join(f"{n}\t{p}\t{s:.3f}\t{e:.3f}\n" for n, p, s, e in rows))


def test_busy_time_and_idle_gaps_per_worker(timeline, tmp_path, monkeypatch, capsys):
    t = 1000.0
    _write(tmp_path, "gw0", [("<session>", "start", t, t), ("<session>", "collected", t + 10, t + 10),
                             ("a.py::x", "setup", t + 10, t + 11), ("a.py::x", "call", t + 11, t + 20),
                             ("a.py::y", "call", t + 65, t + 70)])  # 45 s waiting before y
    _write(tmp_path, "gw1", [("<session>", "collected", t + 10, t + 10), ("b.py::z", "call", t + 10, t + 70)])
    _write(tmp_path, "main", [("<session>", "start", t, t)])  # xdist's controller: no tests, no row
    monkeypatch.setattr(sys, "argv", ["bench_suite_timeline.py", str(tmp_path), "--long", "30"])
    timeline.main()
    out = capsys.readouterr().out
    assert "| gw0 | 10.0 s | 70.0 s | 15.0 s | 45.0 s in 1 |" in out
    assert "| gw1 | 10.0 s | 70.0 s | 60.0 s | 0.0 s in 0 |" in out
    assert "gw0: idle 45.0 s from 20.0 s, before a.py::y" in out
    assert "gw1: 60.0 s call at 10.0 s: b.py::z" in out
    assert "main" not in out


def test_a_folder_without_rows_is_a_clear_error(timeline, tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["bench_suite_timeline.py", str(tmp_path)])
    with pytest.raises(SystemExit, match="no <worker>.tsv"):
        timeline.main()
