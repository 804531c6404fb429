"""Latents of a trained module over a split: ``infer_latents`` run over cached batches, the
one path by which the training's KRR checks (:mod:`.callback`) and evaluate.py
(:mod:`.runs`, :mod:`.pipeline`) read them, so that both infer the same batches and read one
number (:func:`collect_split_latents`)."""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ..constants import FACTOR_NAMES
from ..options.alignment import AlignmentCheckOptions

LATENT_KEYS = {"y": ("y_mean",), "z": ("z_mean",), "both": ("z_mean", "y_mean")}

#: the batch keys kept between the training's checks (what ``infer_latents`` and
#: :func:`collect_latents` read)
CACHED_KEYS = ("obs", "actions", "factors", "object_id", "action_index", "seq_id")
#: sequences per inference batch of :func:`collect_split_latents` (the callback's ``infer_batch_size``)
INFER_BATCH_SIZE = AlignmentCheckOptions.infer_batch_size


def factor_names(datamodule) -> tuple[str, ...]:
    """The names of the ``factors`` columns a DataModule serves: its ``factor_names`` (the
    pendulum's natural frequency and damping), else the catalogue's four (FACTOR_NAMES)."""
    return tuple(getattr(datamodule, "factor_names", FACTOR_NAMES))


def rebatch(batches, batch_size: int) -> list[dict]:
    """Merge consecutive cached batches whose tensors agree in all but the first dimension
    into batches of up to ``batch_size`` sequences (lists are concatenated)."""
    import torch

    out: list[dict] = []
    for b in batches:
        last = out[-1] if out else None
        if (last is not None and last.keys() == b.keys() and len(last["factors"]) + len(b["factors"]) <= batch_size
                and all(not isinstance(v, torch.Tensor) or v.shape[1:] == last[k].shape[1:] for k, v in b.items())):
            out[-1] = {k: torch.cat([last[k], v]) if isinstance(v, torch.Tensor) else list(last[k]) + list(v)
                       for k, v in b.items()}
        else:
            out.append(dict(b))
    return out


def spread_subset(loader, max_sequences: int | None):
    """``loader``, or where its dataset holds more than ``max_sequences`` sequences, a loader
    of ``max_sequences`` of them evenly spaced over the dataset's order (which runs object by
    object): every object and parameter set keeps its share, where the first ``max_sequences``
    would hold only the first objects and leave the read-out to extrapolate to the others."""
    from torch.utils.data import DataLoader, Subset

    dataset = getattr(loader, "dataset", None)
    if max_sequences is None or dataset is None or not hasattr(dataset, "__len__") or len(dataset) <= max_sequences:
        return loader
    keep = np.unique(np.linspace(0, len(dataset) - 1, int(max_sequences)).round().astype(int))
    return DataLoader(Subset(dataset, keep.tolist()), batch_size=loader.batch_size, shuffle=False,
                      num_workers=loader.num_workers, collate_fn=loader.collate_fn, worker_init_fn=loader.worker_init_fn)


def cache_batches(loader, max_sequences: int | None) -> tuple[list[dict], bool]:
    """``max_sequences`` sequences of ``loader`` (all if None; evenly spaced over its dataset
    where it has more: :func:`spread_subset`) as CPU batches with the :data:`CACHED_KEYS` only
    -> (batches, whether they are the whole loader)."""
    import torch

    full = getattr(loader, "dataset", None)
    loader = spread_subset(loader, max_sequences)
    batches, n = [], 0
    for batch in loader:
        take = len(batch["factors"]) if max_sequences is None else min(len(batch["factors"]), max_sequences - n)
        batches.append({k: (v[:take].cpu() if isinstance(v, torch.Tensor) else list(v)[:take])
                        for k, v in batch.items() if k in CACHED_KEYS})
        n += take
        if max_sequences is not None and n >= max_sequences:
            return batches, full is not None and hasattr(full, "__len__") and len(full) == n
    return batches, True


def _to_device(batch, device):
    import torch

    if isinstance(batch, torch.Tensor):
        return batch.to(device)
    if isinstance(batch, Mapping):
        return {k: _to_device(v, device) for k, v in batch.items()}
    if isinstance(batch, (list, tuple)):
        return type(batch)(_to_device(v, device) for v in batch)
    return batch


def collect_latents(pl_module, loader, *, latent: str = "y", max_sequences: int | None = None) -> dict[str, np.ndarray]:
    """Run ``pl_module.infer_latents`` over ``loader`` -> split dict for
    :func:`~embodied_tactile.eval.results.evaluate_latents`: ``"z"`` / ``"y"`` (n, T, d) from
    ``z_mean`` / ``y_mean`` (those the module returns; the ones ``latent`` needs are required),
    ``factors``, ``object_id``, ``action_index`` and ``seq_id`` when batches carry it.
    Usable outside the callback (evaluate.py)."""
    import torch

    need = LATENT_KEYS[latent]
    lat: dict[str, list] = {"z": [], "y": []}
    fac, obj, act, ids = [], [], [], []
    n = 0
    was_training = pl_module.training
    pl_module.eval()
    try:
        with torch.no_grad():
            for batch in loader:
                batch = _to_device(batch, pl_module.device)
                out = pl_module.infer_latents(batch)
                missing = [k for k in need if k not in out]
                if missing:
                    raise KeyError(f"infer_latents returned {sorted(out)}; latent={latent!r} needs {list(need)}")
                take = len(batch["factors"]) if max_sequences is None else min(len(batch["factors"]), max_sequences - n)
                for k in ("z", "y"):
                    if f"{k}_mean" in out:
                        lat[k].append(out[f"{k}_mean"][:take].float().cpu().numpy())
                fac.append(batch["factors"][:take].float().cpu().numpy())
                obj.append(batch["object_id"][:take].cpu().numpy())
                act.append(batch["action_index"][:take].cpu().numpy())
                if "seq_id" in batch:
                    sid = batch["seq_id"][:take]
                    ids.append(np.asarray(sid.cpu() if hasattr(sid, "cpu") else sid))
                n += take
                if max_sequences is not None and n >= max_sequences:
                    break
    finally:
        pl_module.train(was_training)
    res = {k: np.concatenate(v) for k, v in lat.items() if v}
    res.update({"factors": np.concatenate(fac), "object_id": np.concatenate(obj), "action_index": np.concatenate(act)})
    if ids:
        res["seq_id"] = np.concatenate(ids)
    return res


def collect_split_latents(pl_module, train, held, *, latent: str = "y", batch_size: int = INFER_BATCH_SIZE
                          ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """:func:`collect_latents` of the training and the held-out batches inferred together,
    merged (:func:`rebatch`) into batches of up to ``batch_size`` sequences, training
    sequences first -> (training split, held-out split). The training's read-outs and
    evaluate.py read latents through this one function: a sequence's float32 latents depend
    on the batch it is filtered in (~1e-7), which the KRR fit magnifies to 1e-5 - 1e-4 NMSE,
    so the two infer the same batches to reproduce one number."""
    train, held = list(train), list(held)
    return split_at(collect_latents(pl_module, rebatch(train + held, batch_size), latent=latent), count_sequences(train))


def count_sequences(batches) -> int:
    """Sequences in a list of batches."""
    return sum(len(b["factors"]) for b in batches)


def split_at(joint: dict[str, np.ndarray], n: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """A joint split dict cut into its first ``n`` sequences and the rest."""
    return {k: v[:n] for k, v in joint.items()}, {k: v[n:] for k, v in joint.items()}


__all__ = ["CACHED_KEYS", "INFER_BATCH_SIZE", "LATENT_KEYS", "cache_batches", "spread_subset", "collect_latents", "collect_split_latents",
           "count_sequences", "factor_names", "rebatch", "split_at"]
