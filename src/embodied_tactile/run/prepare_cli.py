"""Prepare a scene's data on its own: simulate missing trials, build the caches, list the trials.

    embodied-tactile prepare                                  # train.py's default scene
    embodied-tactile prepare skin=hard primitive=sliding modality=acc
    embodied-tactile prepare data=recorded 'data.raw_files=[recordings/*.h5]'
    embodied-tactile prepare debug=fast paths.data_dir=/scratch/data

The overrides are train.py's: the config is ``configs/train.yaml`` composed with them (its
data / modality / skin / primitive / experiment / debug groups and ``configs/local/``), so
this prepares exactly the scene ``python train.py <same overrides>`` would, and that run then
finds its caches (cache hits). Only the preparation keys of ``data`` are used
(:class:`embodied_tactile.data.prepare.Scene`); split, loader, model and trainer keys are
ignored. It prints the usable trials, the skipped ones with their reasons, the interrupted
recordings left out and the cache files (built now or cache hits).

Exit codes: 0 prepared; 2 a bad override or setting (one line on stderr, nothing
prepared); 1 the data cannot be prepared (a bad trial with ``data.strict=true``, no usable
trial), with the reason on stderr.
"""

from __future__ import annotations

import logging
import sys
import time

from embodied_tactile.run.config import compose  # registers the typed configs


def scene_from_train_config(overrides: list[str]):
    """The :class:`~embodied_tactile.data.prepare.Scene` of ``configs/train.yaml`` + overrides."""
    from omegaconf import OmegaConf

    from embodied_tactile.data.prepare import Scene

    cfg = compose(overrides)
    keys = [k for k in Scene.__dataclass_fields__ if k in cfg.data]  # resolves only these keys
    values = {k: cfg.data[k] for k in keys}
    return Scene.from_config({k: OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v
                              for k, v in values.items()})


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if any(a in ("-h", "--help") for a in argv):
        print(__doc__)
        return 0
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from embodied_tactile.data.prepare import prepare_scene
    from embodied_tactile.data.rawformat import TrialFormatError
    from embodied_tactile.run.overrides import check_composes

    try:
        check_composes(argv, "train", "prepare")  # train's check: one line for a group option or key that does not exist
    except SystemExit as exc:
        return int(exc.code)
    try:
        scene = scene_from_train_config(argv)
        scene.raw_paths  # a recorded pattern matching nothing fails here, before anything is written
    except (HydraException, OmegaConfBaseException, ValueError, FileNotFoundError) as exc:
        print(f"prepare: error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    t0 = time.perf_counter()
    try:
        prepared = prepare_scene(scene)
    except (TrialFormatError, RuntimeError) as exc:
        print(f"prepare: error: {exc}", file=sys.stderr)
        return 1
    print(prepared.summary())
    print(f"data preparation took {time.perf_counter() - t0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
