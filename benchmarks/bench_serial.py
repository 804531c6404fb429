"""Sustained e-Skin packet rate through the pty emulator, and recorder CPU use.

    python benchmarks/bench_serial.py [--duration 10] [--rows paced,unpaced,faults]

The emulator runs in its own process (``embodied-tactile emulate``), the
recorder (the same ``Recorder`` the CLI uses, writing HDF5 through
``IncrementalTrialWriter``) in this one, so the CPU figure is the recorder's alone:
process CPU time (user + system, ``resource.getrusage``) / wall time of the recording.
Target: >= 700 packets/s with no loss when no fault is injected.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from embodied_tactile.hardware.pose import StaticPoseSource
from embodied_tactile.hardware.protocol import DeviceMap
from embodied_tactile.hardware.recorder import Recorder, RecorderSettings, finish, open_port
from embodied_tactile.data import rawformat as R

ROWS = {
    "paced": ("paced 700/s, no faults", []),
    "grid": ("paced 700/s on a fixed grid (no backlog), no faults", ["pacing=grid"]),
    "unpaced": ("as fast as requested, no faults", ["rate=0"]),
    "faults": ("paced 700/s, 0.2% drop/delay/truncate/garbage each", ["faults.drop=0.002", "faults.delay=0.002", "faults.truncate=0.002", "faults.garbage=0.002"]),
}


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def run_row(key: str, duration: float, tmp: Path) -> dict:
    label, extra = ROWS[key]
    emu = subprocess.Popen(
        [sys.executable, "-m", "embodied_tactile", "emulate", "synthetic=3", "faults.seed=7", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    port = emu.stdout.readline().strip()
    settings = RecorderSettings(port=port, timeout=0.1, settle_s=0.2, baseline_s=0.0, duration_s=duration, flush_s=0.5)
    attrs = R.make_attrs(object_id=0, skin="soft", primitive="pressing", action_index=0, repetition=0, source="recorded", seed=0)
    writer = R.IncrementalTrialWriter(tmp / f"bench_{key}.h5", attrs)
    ser = open_port(port, 500000, settings.timeout)
    try:
        cpu0, wall0 = _cpu(), time.perf_counter()
        res = Recorder(ser, writer, settings, device=DeviceMap.from_config({"name": "eskin_v1", "acc_repair": [{"sensor": 6, "axis": "z"}], "fsr_repair": [{"layer": 1, "cols": [6, 7]}]}), pose=StaticPoseSource()).run()
        cpu, wall = _cpu() - cpu0, time.perf_counter() - wall0 - settings.settle_s
        finish(writer, res)
    finally:
        ser.close()
        emu.terminate()
        emu.wait(5)
    good, _ = R.scan_raw(writer.path, strict=True)
    return {
        "row": label, "packets": res.n_trial, "seconds": res.elapsed_s, "rate": res.rate_hz, "lost": res.lost, "garbage": res.garbage,
        "jit_std_ms": res.jitter_std_s * 1e3, "max_dt_ms": res.jitter_max_s * 1e3, "cpu_pct": 100 * cpu / wall, "valid": len(good) == 1,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--rows", default="paced,grid,unpaced,faults")
    args = ap.parse_args()
    out = []
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as d:
        for key in args.rows.split(","):
            out.append(run_row(key, args.duration, Path(d)))
    hdr = f"| {'condition':52s} | packets | rate (pkt/s) | lost | garbage | jitter std (ms) | max interval (ms) | recorder CPU (% of 1 core) | scan_raw |"
    print(hdr)
    print("|" + "|".join("-" * (len(c) + 0) for c in hdr.split("|")[1:-1]) + "|")
    for r in out:
        print(
            f"| {r['row']:52s} | {r['packets']:7d} | {r['rate']:12.1f} | {r['lost']:4d} | {r['garbage']:7d} | {r['jit_std_ms']:15.3f} | "
            f"{r['max_dt_ms']:17.2f} | {r['cpu_pct']:26.1f} | {'ok' if r['valid'] else 'BAD':8s} |"
        )
    print(f"{os.cpu_count()} CPUs, load average {load0[0]:.2f} before / {os.getloadavg()[0]:.2f} after; {args.duration:g} s per row")


if __name__ == "__main__":
    main()
