"""Train a Latent Filter on one scene (modality x skin x primitive).

    python train.py                                            # embedded default (simulator)
    python train.py modality=multi_l skin=soft primitive=sliding
    python train.py -m sweep=ablation                          # the paper's 24 models
    python train.py experiment=paper                           # the paper's lr / batch / epochs

Each run folder (logs/train/runs/<time> or the multirun sub-folder named after its
overrides) holds the resolved config, checkpoints/last.ckpt and the best checkpoint,
metrics.json, split.json and provenance.json (git commit, package versions, raw data digests).
Starting again with the same folder (hydra.run.dir=...) resumes from last.ckpt; the folder
is locked while a training runs, and a restart with settings, split or data (per trial) that
differ, or with fewer epochs than its checkpoint's, is refused; the same command on a
finished run changes nothing (embodied_tactile.run.runfolder). Exit codes: 0 finished (or
already finished), 2 bad setting or refused start (a new run's folder removed), 130 / 143
SIGINT / SIGTERM within seconds in any phase (last.ckpt saved after the step under way,
"interrupted", stopped_in), 74 a checkpoint could not be written, 1 any other failure; a multirun runs every job and exits 1 when one did not finish (its table
says why).
"""

from __future__ import annotations

import embodied_tactile.run.threadenv  # noqa: F401  OpenMP's spin count before torch loads it
from embodied_tactile.cli import process_exit, train_main  # = embodied-tactile train; the recipe: embodied_tactile.run.training

if __name__ == "__main__":
    process_exit(train_main())
