"""A :class:`~embodied_tactile.active.model.PalpationModel` from a trained run folder, loaded
as evaluate.py loads it (:mod:`embodied_tactile.eval.runs`: checkpoint choice, the run's data
config with its saved split, the prepared DataModule, latent collection) with its alignment
settings (``configs/evaluate.yaml``): the alignment an episode is scored with is the one
evaluate.py reports for that run.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from embodied_tactile.eval import runs as R
from embodied_tactile.eval.pipeline import parse_options, run_alignment, run_targets
from embodied_tactile.run.threadenv import set_threads

from .model import PalpationModel


class PalpationError(RuntimeError):
    """A run that cannot be palpated with (missing folder, checkpoint, split, action)."""


def load_palpation_model(run: str | Path, *, checkpoint: str = "best", eval_overrides: Sequence[str] = (),
                         threads: int = 1) -> tuple[PalpationModel, dict[str, Any]]:
    """-> (model, info). ``info``: run_dir, checkpoint, split kind, test object ids (from the
    run's ``split.json`` test trials), training object ids, the training split's per-action
    single-touch NMSE (used to order the fixed baseline's first touch)."""
    import torch

    from embodied_tactile.eval.krr import alignment_kwargs, fit_alignment
    from embodied_tactile.eval.metrics import reference_variance
    from embodied_tactile.eval.targets import encode_split

    run_dir = Path(run)
    if not run_dir.exists():
        raise PalpationError(f"no such run folder: {run_dir} (give a folder made by train.py, e.g. "
                             "logs/train/runs/<date>)")
    try:
        kind, runs, _ = R.discover(run_dir, checkpoint)
    except R.EvaluationError as err:
        raise PalpationError(str(err)) from err
    if kind != "run":
        raise PalpationError(f"{run_dir} is a multirun folder; give one of its job folders")
    r = runs[0]
    opts = parse_options([f"checkpoint={checkpoint}", *eval_overrides])
    try:
        data = R.data_config(r, opts)
    except R.EvaluationError as err:
        raise PalpationError(str(err)) from err
    set_threads(int(threads))
    cache = R.DataCache()
    key, dm = cache.get(data)
    try:
        module = R.load_module(r)  # eval mode; an older network layout is a clear error
    except R.EvaluationError as err:
        raise PalpationError(str(err)) from err
    tr, _ = R.collect_split(module, cache.batches(key, dm, "train"), R.trial_names(dm, "train"), "y")
    targets = run_targets(r.cfg, opts)
    tr = encode_split(tr, targets)
    split = str(data.get("split", "trial"))
    # the state after whole touches is what a palpation reads: the run's alignment, final segment
    final_segment = dataclasses.replace(run_alignment(r.cfg, opts), readout="final_segment")
    align = fit_alignment(tr["y"], tr["factors"], ids=tr["seq_id"], **alignment_kwargs(final_segment, split, tr["object_id"]))
    nominal = {int(a): tr["actions"][tr["action_index"] == a].mean(axis=0) for a in np.unique(tr["action_index"])}
    from embodied_tactile import constants as C
    from embodied_tactile.data.prepare import Scene
    from embodied_tactile.eval.targets import encode_factors

    catalogue = encode_factors(np.stack([o.factors() for o in C.OBJECTS]), targets)
    scene = Scene.from_config(data)
    model = PalpationModel(net=module.model, channels=tuple(data["channels"]), preprocess=scene.preprocess_config(),
                           alignment=align, ref_var=reference_variance(catalogue), nominal_actions=nominal,
                           skin=str(r.cfg.skin.name), primitive=str(r.cfg.primitive.name), targets=targets)
    split = R.run_split(r, data["split_file"], R.trial_objects(dm))
    test_objects = sorted({int(t.object_id) for t in dm.test_set.trials})
    train_objects = sorted({int(t.object_id) for t in dm.train_set.trials})
    info = {"run_dir": str(r.run_dir), "checkpoint": str(r.ckpt), "split": split.get("kind"),
            "test_objects": test_objects, "train_objects": train_objects,
            "unseen_test_objects": split.get("unseen_objects"), "alignment": align.params,
            "n_train_sequences": int(len(tr["factors"]))}
    model.info = info
    cache.clear()
    return model, info
