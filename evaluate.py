"""Evaluate trained Latent Filter runs: KRR alignment, NMSE tables, curves, UMAP, baselines.

    python evaluate.py                                              # the most recent run / multirun
    python evaluate.py logs/train/runs/<run>                        # one run (best checkpoint)
    python evaluate.py logs/train/runs/<run>/checkpoints/last.ckpt  # one checkpoint
    python evaluate.py logs/train/multiruns/<time>                  # every job of a sweep
    python evaluate.py logs/train/study                             # a study run in parts (sub-multiruns), merged
    python evaluate.py <run> latent=both baselines=[handcrafted,gru,mean] gru.epochs=5 out=/tmp/ev
    python evaluate.py <multirun> modality=multi_l seed=[0,1]       # select runs by any config key

Why argparse + OmegaConf and not ``@hydra.main``: Hydra takes no positional arguments (every
command-line word must be an override), and the run folder is the one thing every call
needs. So the path is an argparse positional and the options are an OmegaConf dotlist
merged over ``configs/evaluate.yaml`` (the same ``key=value`` syntax as train.py; unknown
keys are an error; any other ``key=value`` selects runs by their config).

The recipe, per run (docs/reference/evaluation.md):

1. reload the run's OWN config, saved split and checkpoint (best by default)
   (:mod:`embodied_tactile.eval.runs`): a run trained with ``modality=fsr_tb`` evaluates as
   fsr_tb; ``configs/evaluate.yaml`` holds evaluation options only;
2. collect latents over the training split (fit) and the held-out test split (scored; trial
   names are the leakage guard's ids, objects and factors come from the trials' attributes);
3. score the Latent Filter's KRR alignment and the baselines (hand-crafted features -> KRR,
   supervised GRU, mean predictor) on the same split, and compare with the training's final
   alignment (:mod:`embodied_tactile.eval.pipeline`);
4. write every table, figure and ``results.json`` into ``<run>/evaluation`` (a multirun's or
   study's folder: every job aggregated), and print what was measured: the NMSE per factor
   beside the baselines and, for a study, the paper's findings with a measured comparison.
"""

from embodied_tactile.cli import process_exit
from embodied_tactile.eval.command import main
from embodied_tactile.eval.pipeline import evaluate  # noqa: F401  in-process: evaluate(path, overrides)

if __name__ == "__main__":
    process_exit(main())
