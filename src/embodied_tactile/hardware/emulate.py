"""Fake e-Skin on a pseudo-terminal: ``embodied-tactile emulate key=value ...``.

    embodied-tactile emulate trial_file=data/raw/sim.h5 [trial_name=NAME]
    embodied-tactile emulate object_id=3 skin=soft primitive=sliding action_index=5
    embodied-tactile emulate synthetic=2.0 faults.drop=0.01 faults.garbage=0.01 faults.seed=1

Hydra ``key=value`` over ``configs/emulate.yaml``; every option with its one default is
:class:`~embodied_tactile.options.emulation.EmulationOptions` (the faults under ``faults.``).
Prints the pty path on the first line of stdout (flushed), e.g. ``/dev/pts/7``; point the
recorder at it (``embodied-tactile record port=/dev/pts/7``). Runs until Ctrl-C / SIGTERM,
``max_seconds`` or a ``faults.disconnect_after_*`` fault, then prints its statistics as JSON
on stderr. Exit 0, or 2 on a bad option / unreadable trial (one line naming it).
"""

from __future__ import annotations

import json
import signal
import sys

from omegaconf import DictConfig, OmegaConf

from embodied_tactile.cli import hydra_command
from embodied_tactile.options.emulation import EmulationOptions


def run(cfg: DictConfig) -> int:
    from embodied_tactile.hardware.emulator import Emulator, Faults, load_trial, simulated_trial, synthetic_trial
    from embodied_tactile.hardware.protocol import DeviceMap

    opts: EmulationOptions = OmegaConf.to_object(cfg)  # type: ignore[assignment]
    try:
        if opts.trial_file:
            trial = load_trial(opts.trial_file, opts.trial_name)
        elif opts.synthetic:
            trial = synthetic_trial(opts.synthetic)
        else:
            trial = simulated_trial(opts.object_id, opts.skin, opts.primitive, opts.action_index, seed=opts.sim_seed)
        device = None
        if opts.device:
            device = DeviceMap.from_config(OmegaConf.to_container(OmegaConf.load(opts.device), resolve=True))
        faults = Faults(**vars(opts.faults))
        emu = Emulator(trial, device=device, rate=opts.rate, faults=faults, loop=opts.loop, pacing=opts.pacing,
                       max_lag_s=opts.max_lag_s)
    except ImportError as exc:
        print(f"emulate: the simulator is not available ({exc}); use trial_file= or synthetic=", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001
        print(f"emulate: {exc}", file=sys.stderr)
        return 2
    port = emu.open(opts.link)
    print(port, flush=True)

    def on_signal(signum, frame):  # noqa: ARG001
        emu._stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        stats = emu.serve(max_seconds=opts.max_seconds)
    finally:
        emu.close()
    print(json.dumps({"emulator": stats.as_dict()}), file=sys.stderr, flush=True)
    return 0


main = hydra_command("emulate", run, "emulate", options=EmulationOptions)


if __name__ == "__main__":
    main()
