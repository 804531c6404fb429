"""Fake e-Skin on a pseudo-terminal.

    python -m embodied_tactile.hardware.emulate --trial-file data/raw/sim.h5 [--trial-name NAME]
    python -m embodied_tactile.hardware.emulate --object-id 3 --skin soft --primitive sliding --action-index 5
    python -m embodied_tactile.hardware.emulate --synthetic 2.0 --drop 0.01 --garbage 0.01 --seed 1

Prints the pty path on the first line of stdout (flushed), e.g. ``/dev/pts/7``; point the
recorder at it (``python -m embodied_tactile.hardware.record port=/dev/pts/7``). Runs until
Ctrl-C / SIGTERM, ``--max-seconds`` or a ``--disconnect-*`` fault. Exit 0, or 2 on a bad
option / unreadable trial.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys

from embodied_tactile import constants as C


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m embodied_tactile.hardware.emulate", description=__doc__.split("\n\n")[0])
    src = p.add_argument_group("trial to serve (default: simulate one)")
    src.add_argument("--trial-file", help="raw HDF5 file to serve a trial from")
    src.add_argument("--trial-name", help="trial group name (default: the first valid trial)")
    src.add_argument("--synthetic", type=float, metavar="SECONDS", help="serve a built-in synthetic trial of this length (no simulator needed)")
    src.add_argument("--object-id", type=int, default=0)
    src.add_argument("--skin", default="soft", choices=C.SKINS)
    src.add_argument("--primitive", default="pressing", choices=C.PRIMITIVES)
    src.add_argument("--action-index", type=int, default=0)
    src.add_argument("--sim-seed", type=int, default=0, help="simulator seed")
    p.add_argument("--rate", type=float, default=None, help="packets/s (default: the trial's fs_tactile, 700); 0 = as fast as requested")
    p.add_argument("--pacing", default="fifo", choices=("fifo", "grid"), help="fifo: a backlog of up to --max-lag-s is answered at once; grid: at most one packet per 1/rate tick")
    p.add_argument("--max-lag-s", type=float, default=0.05)
    p.add_argument("--no-loop", action="store_true", help="stop answering at the end of the trial instead of looping")
    p.add_argument("--device", default=None, help="device map YAML for the wiring (default: configs/record/device/ideal.yaml semantics)")
    p.add_argument("--link", default=None, help="also create this symlink to the pty (a stable port name)")
    p.add_argument("--max-seconds", type=float, default=None, help="exit after this long")
    f = p.add_argument_group("fault injection (probabilities per request)")
    f.add_argument("--drop", type=float, default=0.0, help="ignore the request")
    f.add_argument("--delay", type=float, default=0.0, help="answer after --delay-s (beyond the recorder timeout)")
    f.add_argument("--delay-s", type=float, default=0.15)
    f.add_argument("--truncate", type=float, default=0.0, help="send only part of the packet")
    f.add_argument("--garbage", type=float, default=0.0, help="send random bytes, a shifted packet or a packet followed by junk")
    f.add_argument("--garbage-mode", default="mixed", choices=("random", "shift", "long", "mixed"))
    f.add_argument("--disconnect-after-packets", type=int, default=None)
    f.add_argument("--disconnect-after-s", type=float, default=None)
    f.add_argument("--seed", type=int, default=0, help="fault RNG seed")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from embodied_tactile.hardware.emulator import Emulator, Faults, load_trial, simulated_trial, synthetic_trial
    from embodied_tactile.hardware.protocol import DeviceMap

    try:
        if args.trial_file:
            trial = load_trial(args.trial_file, args.trial_name)
        elif args.synthetic:
            trial = synthetic_trial(args.synthetic)
        else:
            trial = simulated_trial(args.object_id, args.skin, args.primitive, args.action_index, seed=args.sim_seed)
        device = None
        if args.device:
            from omegaconf import OmegaConf

            device = DeviceMap.from_config(OmegaConf.to_container(OmegaConf.load(args.device), resolve=True))
        faults = Faults(
            drop=args.drop, delay=args.delay, delay_s=args.delay_s, truncate=args.truncate, garbage=args.garbage,
            garbage_mode=args.garbage_mode, disconnect_after_packets=args.disconnect_after_packets,
            disconnect_after_s=args.disconnect_after_s, seed=args.seed,
        )
        emu = Emulator(trial, device=device, rate=args.rate, faults=faults, loop=not args.no_loop, pacing=args.pacing, max_lag_s=args.max_lag_s)
    except ImportError as exc:
        print(f"emulate: the simulator is not available ({exc}); use --trial-file or --synthetic", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001
        print(f"emulate: {exc}", file=sys.stderr)
        return 2
    port = emu.open(args.link)
    print(port, flush=True)

    def on_signal(signum, frame):  # noqa: ARG001
        emu._stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        stats = emu.serve(max_seconds=args.max_seconds)
    finally:
        emu.close()
    print(json.dumps({"emulator": stats.as_dict()}), file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
