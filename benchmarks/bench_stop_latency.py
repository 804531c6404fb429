"""Seconds from a stop signal to the end of ``python train.py``, in every phase of a training,
with one CPU-busy process beside it.

    python benchmarks/bench_stop_latency.py --work /tmp/stoplat
    python benchmarks/bench_stop_latency.py --work /tmp/stoplat --signals SIGTERM --phases training

The scene is ``debug=fast`` (the tests' smallest: 4 objects x 3 actions, 20-frame windows)
at ``threads=1``, every run in its own ``hydra.run.dir`` under ``--work``. One process
spinning in a Python loop (started here, ended at the end) shares the machine throughout.
For each phase and signal a training starts afresh and the signal is sent once its
``train.log`` shows the phase (``--delay`` seconds later where the phase lasts):

* data preparation, simulation: a new data folder; on ``N trials to simulate`` (N > 0);
* data preparation, caches: the raw file there, no cache; on ``0 trials to simulate`` (no delay);
* check before training: prepared data; on ``phase: check before training`` (no delay);
* training: prepared data, 50 epochs; on ``phase: training``;
* final read-out: prepared data, 1 epoch; on ``phase: final read-out`` (no delay).

Printed: the CPU (``lscpu``), the cores, the load average, then one row per run: phase,
signal, seconds from the signal to the process's exit, the CPU seconds the training used in
them (on a loaded machine the wall time is these over the share of a core it gets), the exit code and where
``metrics.json`` says the signal found the run (``stopped_in``; ``-`` where no run folder
state was written yet). The target: every row within 5 s, exit 130 (SIGINT) / 143 (SIGTERM).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from bench_shared_machine import REPO, cpu_model, environment, train_command

TARGET_S = 5.0
SCENE = ["debug=fast", "threads=1"]
#: phase -> (data folder it starts from, extra overrides, trigger line, seconds after it)
PHASES = {
    "data preparation (simulation)": ("empty", [], re.compile(r": [1-9]\d* trials to simulate"), True),
    "data preparation (caches)": ("raw", [], re.compile(r": 0 trials to simulate"), False),
    "check before training": ("prepared", [], re.compile(r"phase: check before training"), False),
    "training": ("prepared", ["trainer.max_epochs=50"], re.compile(r"phase: training"), True),
    "final read-out": ("prepared", [], re.compile(r"phase: final read-out"), False),
}


def busy() -> subprocess.Popen:
    """One process keeping one core busy (a Python loop)."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


def prepare(work: Path, env: dict[str, str]) -> dict[str, Path]:
    """Data folders: ``empty``, ``raw`` (the scene's raw file only) and ``prepared`` (raw file
    and caches, by ``embodied-tactile prepare``)."""
    prepared = work / "data_prepared"
    if not (prepared / "cache").is_dir():
        subprocess.run([sys.executable, "-m", "embodied_tactile", "prepare", *SCENE[:1], f"paths.data_dir={prepared}"],
                       cwd=REPO, env=env, check=True, stdout=subprocess.DEVNULL)
    raw = work / "data_raw"
    shutil.rmtree(raw, ignore_errors=True)
    shutil.copytree(prepared / "raw", raw / "raw")
    return {"empty": work / "data_empty", "raw": raw, "prepared": prepared}


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a running process so far (``/proc/<pid>/stat``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def fresh_copy(kind: str, folders: dict[str, Path], dest: Path) -> Path:
    shutil.rmtree(dest, ignore_errors=True)
    if kind == "empty":
        return dest
    shutil.copytree(folders[kind], dest)
    return dest


def stop_once(work: Path, name: str, phase: str, sig: signal.Signals, folders: dict[str, Path], env: dict[str, str],
              delay: float, timeout: float) -> dict:
    """One training stopped by ``sig`` in ``phase``: seconds from the signal to its exit."""
    kind, extra, trigger, delayed = PHASES[phase]
    run_dir, data = work / name / "run", fresh_copy(kind, folders, work / name / "data")
    shutil.rmtree(run_dir, ignore_errors=True)
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    log_path = run_dir / "train.log"
    with open(work / name / "stdout.log", "w") as out:
        proc = subprocess.Popen(train_command(run_dir, data, [*SCENE, *extra, f"paths.log_dir={work / name / 'logs'}"]),
                                cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
        t_start, sent = time.perf_counter(), None
        while proc.poll() is None and time.perf_counter() - t_start < timeout:
            text = log_path.read_text(errors="replace") if log_path.exists() else ""
            if trigger.search(text):
                if delayed:
                    time.sleep(delay)
                cpu_at_signal = cpu_seconds(proc.pid)
                sent = time.perf_counter()
                proc.send_signal(sig)
                break
            time.sleep(0.01)
        if sent is None:
            proc.kill()
            proc.wait()
            return {"phase": phase, "signal": sig.name, "seconds": None, "cpu": None, "code": proc.returncode,
                    "stopped_in": f"not reached ({'exited' if proc.returncode is not None else 'timeout'})"}
        _, status, usage = os.wait4(proc.pid, 0)
        seconds = time.perf_counter() - sent
        proc.returncode = code = os.waitstatus_to_exitcode(status)
        cpu = usage.ru_utime + usage.ru_stime - cpu_at_signal
    metrics = run_dir / "metrics.json"
    stopped_in = json.loads(metrics.read_text()).get("stopped_in", "-") if metrics.exists() else "-"
    return {"phase": phase, "signal": sig.name, "seconds": seconds, "cpu": cpu, "code": code, "stopped_in": stopped_in}


def _num(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the data and run folders")
    ap.add_argument("--phases", nargs="*", default=list(PHASES), choices=list(PHASES), metavar="PHASE")
    ap.add_argument("--signals", nargs="*", default=["SIGTERM", "SIGINT"], choices=["SIGTERM", "SIGINT"])
    ap.add_argument("--delay", type=float, default=1.0, help="seconds after the trigger line in lasting phases")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds to wait for a phase")
    args = ap.parse_args()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    env = environment(None)
    print(f"CPU: {cpu_model()}, {os.cpu_count()} cores; load average {os.getloadavg()[0]:.2f} (1 min) before")
    folders = prepare(work, env)
    spinner = busy()
    rows = []
    try:
        for phase in args.phases:
            for s in args.signals:
                name = f"{re.sub(r'[^a-z]+', '_', phase)}_{s.lower()}"
                rows.append(stop_once(work, name, phase, signal.Signals[s], folders, env, args.delay, args.timeout))
                r = rows[-1]
                print(f"  {r['phase']:<30} {r['signal']:<8} {_num(r['seconds']):>6} s ({_num(r['cpu'])} CPU s)  "
                      f"exit {r['code']}  stopped_in: {r['stopped_in']}", flush=True)
    finally:
        spinner.kill()
        spinner.wait()
    print(f"load average {os.getloadavg()[0]:.2f} (1 min) after; one busy process beside each training\n")
    print("| phase | signal | seconds to exit | CPU s after the signal | exit code | stopped_in (metrics.json) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['phase']} | {r['signal']} | {_num(r['seconds'])} | {_num(r['cpu'])} | {r['code']} | {r['stopped_in']} |")
    slow = [r for r in rows if r["seconds"] is None or r["seconds"] > TARGET_S
            or r["code"] != 128 + signal.Signals[r["signal"]].value]
    print(f"\n{len(rows) - len(slow)} of {len(rows)} within {TARGET_S:g} s with the signal's exit code")


if __name__ == "__main__":
    main()
