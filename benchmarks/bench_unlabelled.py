"""What unlabelled population objects cost (docs/reference/simulator.md, "Object population"):
per added trial, the preparation's wall time, the raw file's growth and the size of the
caches in use; and the training loader's time per crop with and without the physical term's
feature targets (``data.context_features``).

    python benchmarks/bench_unlabelled.py --work /tmp/unlabelled_bench [--unlabelled 16]

A tiny labelled population (2 training, 1 validation, 1 test object; actions 6 and 14;
multi_l) is prepared in a new folder, then the same scene with ``--unlabelled`` more objects
(one worker each for simulation and preprocessing). The added trials' cost is the second
preparation's wall time over the trials it added, and the growth of the raw file; the cache
is per trial of the larger scene's caches (the scene's trials all cached again: preparing
the largest scene first avoids that). Loader: every 50-frame training crop with its context
read once, with and without ``target_features``. Say whether the machine was shared.
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True, type=Path, help="a new folder (removed first)")
    ap.add_argument("--unlabelled", type=int, default=16)
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from embodied_tactile.data.datamodule import TactileDataModule

    shutil.rmtree(args.work, ignore_errors=True)
    kw = dict(data_dir=str(args.work / "data"), objects="population", n_objects=2, n_val_objects=1, n_test_objects=1,
              actions=[6, 14], channels=["acc", "fsr_t", "fsr_b"], split="object", sim_workers=1,
              preprocess_workers=1, batch_size=16, train_window=50, context="trial")
    sizes = {}
    for n_unlabelled in (0, args.unlabelled):
        dm = TactileDataModule.from_config(n_unlabelled_objects=n_unlabelled, context_features=True, **kw)
        t0 = time.perf_counter()
        dm.prepare_data()
        wall = time.perf_counter() - t0
        dm.setup("fit")
        raw = sum(p.stat().st_size for p in dm.raw_paths)
        cache = {f: Path(p).stat().st_size for f, p in dm.cache_files.items()}
        sizes[n_unlabelled] = (len(dm.prepared.trials), wall, raw)
        ds = dm.train_crops
        t0 = time.perf_counter()
        for i in range(len(ds)):
            ds[i]
        with_features = (time.perf_counter() - t0) / len(ds)
        ds.feature_scale = None
        t0 = time.perf_counter()
        for i in range(len(ds)):
            ds[i]
        without = (time.perf_counter() - t0) / len(ds)
        n = len(dm.prepared.trials)
        print(f"{n_unlabelled} unlabelled: {n} trials, prepared in {wall:.1f} s, cache per trial "
              + ", ".join(f"{f} {b / n / 1e6:.2f} MB" for f, b in cache.items())
              + f"; loader {1e3 * with_features:.1f} ms per crop with target_features, {1e3 * without:.1f} ms without")
    (n0, _, raw0), (n1, wall1, raw1) = sizes[0], sizes[args.unlabelled]
    print(f"per added trial: {wall1 / (n1 - n0):.2f} s wall to simulate and cache, raw {(raw1 - raw0) / (n1 - n0) / 1e6:.2f} MB")
    shutil.rmtree(args.work, ignore_errors=True)


if __name__ == "__main__":
    main()
