"""Simulate raw e-Skin trials into one HDF5 file.

    embodied-tactile simulate skin=soft primitive=sliding \
        out=data/raw/soft_sliding.h5 objects=[0,1] actions=[0,5] repetitions=1 seed=0 workers=2

Every field of :class:`~embodied_tactile.options.simulation.SimulateOptions` can be overridden with ``key=value`` (OmegaConf
dotlist syntax); ``objects`` / ``actions`` default to the whole catalogue / action table.
An invalid value (ranges in docs/reference/simulator.md) or an output file the simulator may not
write into exits with status 2 and a one-line message on stderr; nothing is written.
"""

from __future__ import annotations

import logging
import sys
import time

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from embodied_tactile.options.simulation import SimulateOptions


def parse(argv: list[str]) -> SimulateOptions:
    base = OmegaConf.structured(SimulateOptions)
    cfg = OmegaConf.merge(base, OmegaConf.from_dotlist(list(argv)))
    return cfg  # type: ignore[return-value]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if any(a in ("-h", "--help") for a in argv):
        print(__doc__)
        print(OmegaConf.to_yaml(OmegaConf.structured(SimulateOptions)))
        return 0
    from embodied_tactile.sim import OutputFileError, SimParameterError, generate_dataset
    from embodied_tactile.sim.validation import physics_overrides

    try:
        cfg = parse(argv)
        out = str(cfg.out)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None)
        print(f"simulate: error: {key + ': ' if key else ''}{str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    logging.basicConfig(level=getattr(logging, str(cfg.log_level).upper(), logging.INFO), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    t0 = time.perf_counter()
    try:
        path = generate_dataset(
            out,
            skin=cfg.skin,
            primitive=cfg.primitive,
            objects=list(cfg.objects),
            actions=list(cfg.actions),
            repetitions=cfg.repetitions,
            seed=cfg.seed,
            workers=cfg.workers,
            overwrite=cfg.overwrite,
            duration=cfg.duration,
            physics=physics_overrides(OmegaConf.to_container(cfg.physics) if cfg.physics else None),
        )
    except (SimParameterError, OutputFileError) as exc:
        print(f"simulate: error: {exc}", file=sys.stderr)
        return 2
    logging.getLogger("embodied_tactile.sim.simulate").info("wrote %s in %.1f s", path, time.perf_counter() - t0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
