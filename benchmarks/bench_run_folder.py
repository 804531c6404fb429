"""What the run-folder guarantees cost the main job: the atomic checkpoint write against
Lightning's own, and the once-per-preparation cache checksum.

Checkpoints: the default model's (``python train.py``: MULTI-L) state dict plus an Adam
state of the same size, saved ``--repeats`` times by Lightning's ``TorchCheckpointIO`` and
by ``runfolder.AtomicCheckpointIO`` (temporary file, fsync, rename) into ``--work``; the
median of each and the difference times the main job's checkpoint count (two per epoch,
``trainer.max_epochs`` of the composed default: configs/train.yaml).

Cache: ``data.cache.verify_cache`` over every ``*.h5`` in ``<data-dir>/cache`` (the main
job's data folder once prepared), seconds and MB/s.

    python benchmarks/bench_run_folder.py --work /tmp/rfbench [--data-dir data] [--repeats 7]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path
from embodied_tactile.run.threadenv import set_threads


def checkpoint_times(work: Path, repeats: int) -> dict[str, float]:
    import torch
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate
    from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO

    from embodied_tactile.run.runfolder import AtomicCheckpointIO
    from embodied_tactile.run.config import config_dir  # registers the typed configs

    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["hydra.runtime.output_dir=/tmp"])
    model = instantiate(cfg.model)
    sd = model.state_dict()
    ckpt = {"state_dict": sd, "optimizer_states": [{"state": {k: {"exp_avg": v.clone(), "exp_avg_sq": v.clone()}
                                                              for k, v in sd.items() if v.is_floating_point()}}],
            "global_step": 1, "epoch": 0}
    work.mkdir(parents=True, exist_ok=True)
    out = {"max_epochs": int(cfg.trainer.max_epochs)}
    for name, io in (("lightning", TorchCheckpointIO()), ("atomic", AtomicCheckpointIO())):
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            io.save_checkpoint(ckpt, work / f"{name}.ckpt")
            times.append(time.perf_counter() - t0)
        out[name] = statistics.median(times)
    out["mb"] = os.path.getsize(work / "atomic.ckpt") / 1e6
    set_threads(1)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--data-dir", type=Path, default=None)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    c = checkpoint_times(args.work, args.repeats)
    n = 2 * c["max_epochs"]
    print(f"checkpoint {c['mb']:.1f} MB: Lightning {c['lightning'] * 1e3:.1f} ms, atomic {c['atomic'] * 1e3:.1f} ms "
          f"(median of {args.repeats}); x {n} checkpoints of the main job: {(c['atomic'] - c['lightning']) * n:+.2f} s")
    if args.data_dir is not None:
        from embodied_tactile.data.cache import verify_cache

        for path in sorted((args.data_dir / "cache").glob("*.h5")):
            t0 = time.perf_counter()
            bad = verify_cache(path)
            dt = time.perf_counter() - t0
            mb = os.path.getsize(path) / 1e6
            print(f"verify_cache {path.name}: {mb:.0f} MB in {dt:.2f} s ({mb / dt:.0f} MB/s), {len(bad)} damaged")


if __name__ == "__main__":
    main()
