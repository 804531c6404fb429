"""LightningDataModule over preprocessed HDF5 trajectories: the one place that knows both
the files (raw + cache) and torch.

Flow: ``prepare_data`` runs the data preparation stage (:mod:`embodied_tactile.data.prepare`:
simulate missing trials, lock the data folder, build the per-field caches, list the
scene's usable trials), unless a prepared scene was attached (:meth:`TactileDataModule.attach`);
``setup`` splits the prepared trials into train / validation / test (:func:`split_trials`:
by trial, the paper's split, or by whole object), stable for a seed. Validation trials come from training objects and
pick checkpoints; test trials are touched only by evaluation. A modality reads only its own
fields: ``acc`` never opens FSR data, raw or cached.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import asdict
from pathlib import Path
from typing import Any, Mapping, Sequence

import h5py
import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, RandomSampler

from embodied_tactile.data.prepare import PreparedData, Scene, TrialRef, data_dir_lock, prepare_scene
from embodied_tactile.options.data import LoaderOptions, SceneOptions, SplitOptions, group_options
from embodied_tactile.data.statistics import DataStatistics
from embodied_tactile.jsonio import write_json
from embodied_tactile.data.modality import CHANNELS, fields_for_channels
from embodied_tactile.data.features import handcrafted_features

__all__ = ["ConstantChannelError", "TactileDataModule", "TactileSequenceDataset", "split_trials", "TrialRef", "PreparedData", "Scene",
           "data_dir_lock", "fields_for_channels"]

log = logging.getLogger(__name__)

SPLITS = ("trial", "object")
CONTEXTS = (None, "trial", "window")


def _hash_key(seed: int, name: str) -> bytes:
    return hashlib.blake2b(f"{seed}/{name}".encode(), digest_size=8).digest()


def _stratified_objects(by_obj: Mapping[int, Sequence[TrialRef]], test_fraction: float, seed: int) -> set[int]:
    """Whole objects to hold out, balanced over every factor's levels.

    ``round(test_fraction * n_objects)`` objects (at least 1, at most all but one) are taken
    one at a time, each time the one that least increases
    ``sum_{k, level} (held(k, level) - test_fraction * n(k, level))^2``, the distance of the
    held-out counts per factor level from their proportional share, among the objects that
    keep every level at or below ``ceil(test_fraction * n(k, level))``; ties go to a seeded
    hash order. Every level so keeps most of its objects in training (the KRR
    alignment and the population prior interpolate, they do not extrapolate), and the
    heterogeneous minority is held out in proportion rather than by chance."""
    objs = sorted(by_obj, key=lambda o: _hash_key(seed, f"object{o}"))
    n_test = min(max(int(round(test_fraction * len(objs))), 1), len(objs) - 1)
    levels = {o: [(k, round(float(v), 6) if np.isfinite(v) else None) for k, v in enumerate(by_obj[o][0].factors)]
              for o in objs}
    count: dict[tuple[int, Any], int] = {}
    for o in objs:
        for key in levels[o]:
            count[key] = count.get(key, 0) + 1
    cap = {key: int(np.ceil(test_fraction * n)) for key, n in count.items()}
    held: dict[tuple[int, Any], int] = {}
    taken: list[int] = []
    budget = [20000]  # search nodes; the caps are loose enough that the first branch nearly always succeeds

    def cost(o: int) -> float:  # growth of sum (held - f n)^2 if o were taken
        return sum(2.0 * (held.get(key, 0) - test_fraction * count[key]) + 1.0 for key in levels[o])

    def take(o: int, step: int) -> None:
        (taken.append if step > 0 else taken.remove)(o)
        for key in levels[o]:
            held[key] = held.get(key, 0) + step

    def search() -> bool:  # depth-first within the caps, cheapest first
        if len(taken) == n_test:
            return True
        if budget[0] <= 0:
            return False
        budget[0] -= 1
        feasible = [o for o in objs if o not in taken and all(held.get(key, 0) < cap[key] for key in levels[o])]
        for o in sorted(feasible, key=cost):  # stable: ties keep the seeded hash order
            take(o, +1)
            if search():
                return True
            take(o, -1)
        return False

    if not search():  # no assignment within the caps: the least-deviation greedy one
        for o in list(taken):
            take(o, -1)
        while len(taken) < n_test:
            take(min((o for o in objs if o not in taken), key=cost), +1)
    return set(taken)


class ConstantChannelError(ValueError):
    """A channel of the modality carries no signal over the training split."""


def split_trials(trials: Sequence[TrialRef], *, by: str = SplitOptions.split,
                 test_fraction: float = SplitOptions.test_fraction, val_fraction: float = SplitOptions.val_fraction,
                 seed: int = SplitOptions.split_seed, roles: Mapping[int, str] | None = None
                 ) -> tuple[list[TrialRef], list[TrialRef], list[TrialRef]]:
    """Train / validation / test split, independent of listing order and stable for a seed.

    ``by="trial"`` (the paper's split; it measures recognition of objects seen in training):
      * ``test``: per object, ``round(test_fraction * n)`` of its ``n`` trials (at least 1 and
        at most n - 1 when n >= 2), so every object is on both sides;
      * ``val``: ``round(val_fraction * N)`` of all N trials (at least 1 where possible), from
        the training objects' remaining trials, one per object in a seeded object order and
        only from objects that keep at least one training trial.
    ``by="object"`` (objects never touched in training): train, validation and test objects
      are disjoint. ``roles`` (object id -> 'train' | 'val' | 'test', a population's fixed
      roles) decides where given (objects of role 'unlabelled' are in none of the three:
      :attr:`TactileDataModule.unlabelled` serves them); otherwise ``round(test_fraction * n_objects)`` test objects
      and then ``round(val_fraction * n_objects)`` validation objects (at least 1 each while
      a training object remains) are drawn balanced over factor levels
      (:func:`_stratified_objects`).

    ``test`` is touched only by evaluation (evaluate.py, the KRR callback's report), never by
    model selection; ``val`` picks checkpoints and drives early stopping (empty, with a
    warning, when nothing can be spared). The order inside an object is a hash of (seed,
    trial name), so adding trials of other objects does not reshuffle an object's assignment
    more than necessary.
    """
    if by not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {by!r}")
    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"test_fraction must be in (0, 1), got {test_fraction}")
    if not 0.0 <= val_fraction < 1.0 - test_fraction:
        raise ValueError(f"val_fraction must be in [0, 1 - test_fraction), got {val_fraction}")
    by_obj: dict[int, list[TrialRef]] = {}
    for tr in trials:
        by_obj.setdefault(tr.object_id, []).append(tr)
    for obj in by_obj:
        by_obj[obj].sort(key=lambda t: _hash_key(seed, t.name))
    key = lambda t: t.name  # noqa: E731
    if by == "object":
        if len(by_obj) < 2:
            raise ValueError(f"split=object needs at least 2 objects, got {sorted(by_obj)}")
        if roles is not None:
            unknown = sorted(set(by_obj) - set(roles))
            if unknown:
                raise ValueError(f"objects {unknown[:5]} have no role in the population's split")
            role = {o: roles[o] for o in by_obj}
        else:
            held = _stratified_objects(by_obj, test_fraction, seed)
            rest = {o: t for o, t in by_obj.items() if o not in held}
            val_objs: set[int] = set()
            n_val = int(round(val_fraction * len(by_obj)))
            if val_fraction > 0 and len(rest) >= 2:
                val_objs = _stratified_objects(rest, min(max(n_val, 1), len(rest) - 1) / len(rest), seed + 1)
            role = {o: "test" if o in held else "val" if o in val_objs else "train" for o in by_obj}
        out = {r: sorted((t for o, items in by_obj.items() if role[o] == r for t in items), key=key)
               for r in ("train", "val", "test")}
        if not out["val"] and val_fraction > 0:
            log.warning("no validation objects: checkpoints follow the last epoch")
        if not out["train"] or not out["test"]:
            raise ValueError(f"split=object left no {'training' if not out['train'] else 'test'} objects")
        return out["train"], out["val"], out["test"]
    test: list[TrialRef] = []
    pool: dict[int, list[TrialRef]] = {}  # training objects' trials still available
    for obj in sorted(by_obj):
        items = by_obj[obj]
        n = len(items)
        if n >= 2:
            n_test = min(max(int(round(test_fraction * n)), 1), n - 1)
        else:
            n_test = 0
            log.warning("object %d has a single trial: it is used for training only", obj)
        test.extend(items[:n_test])
        pool[obj] = list(items[n_test:])
    n_val = int(round(val_fraction * len(trials)))
    if val_fraction > 0:
        n_val = max(n_val, 1)
    val: list[TrialRef] = []
    order = sorted(pool, key=lambda o: _hash_key(seed, f"val-object{o}"))
    while len(val) < n_val:
        spare = [o for o in order if len(pool[o]) >= 2]
        if not spare:
            break
        for o in spare:
            if len(val) == n_val:
                break
            val.append(pool[o].pop(0))
    if n_val and not val:
        log.warning("no validation trials: no training object has a trial to spare; checkpoints follow the last epoch")
    train = [t for items in pool.values() for t in items]
    return sorted(train, key=key), sorted(val, key=key), sorted(test, key=key)


class TactileSequenceDataset(Dataset):
    """Preprocessed sequences of one split. Opens its HDF5 caches lazily in each worker
    and pickles without the handles.

    ``seq_len`` keeps the first frames of every trial (None = all). ``window`` serves a
    random ``window``-frame crop of each trial instead (offset drawn from torch's RNG, so
    ``seed_everything`` makes it reproducible), ``windows_per_trial`` crops per trial and
    pass; only the HDF5 rows of the crop are read. A trial shorter than ``window`` is
    served whole.

    ``context`` pairs every item (the target) with context frames of the same object for
    the context objective (docs/reference/model.md, "The context objective"), served as
    ``context_obs`` / ``context_actions`` (with ``context_trial`` and
    ``context_first_frame``): ``"trial"``, a ``window``-frame crop (the whole trial without
    ``window``) of another trial of the same object, drawn at random among its trials in
    this set (``context_touches`` > 1: that many distinct other trials, served with a leading
    touch axis, ``context_obs`` (M, T, C, 28, 28), ``context_trial`` their names joined by
    ``+``); ``"window"``, a second ``window``-frame crop of the same trial, disjoint from
    the target's (two disjoint crops, which one is the target drawn at random). The object
    id only picks the trials to pair; it is served as before and never used as the pairing's
    output. ``draw_seed`` makes every item's draws a function of (seed, index) (validation:
    the same pairs every epoch); None = torch's global RNG.

    ``feature_scale`` (mean, std) of k hand-crafted features: every item also carries
    ``target_features`` (k,), the served crop's hand-crafted features at its last frame
    (:func:`~embodied_tactile.data.features.handcrafted_features`, a summary of the whole crop)
    shifted and scaled by them: the targets of the context objective's physical term.
    """

    def __init__(self, cache_files: Mapping[str, str], trials: Sequence[TrialRef], channels: Sequence[str],
                 seq_len: int | None = None, window: int | None = None, windows_per_trial: int = 1,
                 context: str | None = None, draw_seed: int | None = None, context_touches: int = 1,
                 feature_scale: tuple[np.ndarray, np.ndarray] | None = None):
        self.cache_files = dict(cache_files)
        self.trials = list(trials)
        self.channels = list(channels)
        self.fields = fields_for_channels(self.channels)
        missing = [f for f in self.fields if f not in self.cache_files]
        if missing:
            raise ValueError(f"no cache file for field(s) {missing}")
        self.seq_len = seq_len
        if window is not None and int(window) < 2:
            raise ValueError(f"train window must be >= 2 frames (the recursion needs a transition), got {window}")
        if int(windows_per_trial) < 1:
            raise ValueError(f"windows_per_trial must be >= 1, got {windows_per_trial}")
        self.window = None if window is None else int(window)
        self.windows_per_trial = int(windows_per_trial)
        if context not in CONTEXTS:
            raise ValueError(f"context must be one of {CONTEXTS}, got {context!r}")
        if context == "window" and self.window is None:
            raise ValueError("context='window' needs a window: two disjoint crops of one trial")
        self.context = context
        self.draw_seed = draw_seed
        if int(context_touches) < 1 or (int(context_touches) > 1 and context != "trial"):
            raise ValueError(f"context_touches must be 1, or > 1 with context='trial' (other trials of the object), "
                             f"got {context_touches} with context={context!r}")
        self.context_touches = int(context_touches)
        self.feature_scale = None if feature_scale is None else tuple(np.asarray(v, np.float64) for v in feature_scale)
        #: trial name -> the other trials of its object in this set (context='trial')
        self.others: dict[str, list[TrialRef]] = {}
        if context == "trial":
            by_obj: dict[int, list[TrialRef]] = {}
            for tr in self.trials:
                by_obj.setdefault(tr.object_id, []).append(tr)
            few = sorted(o for o, items in by_obj.items() if len(items) < 1 + self.context_touches)
            if few:
                raise ValueError(f"context='trial' pairs each trial with {self.context_touches} other trial(s) of its "
                                 f"object, but object(s) {few[:5]} have fewer than {1 + self.context_touches} trials "
                                 "in this set")
            self.others = {tr.name: [t for t in by_obj[tr.object_id] if t.name != tr.name] for tr in self.trials}
        self._handles: dict[str, h5py.File] | None = None
        # (field, trial) -> its h5py dataset: a group lookup by name costs more than the read of
        # a 50-frame crop (43 % of the training loader's time at the default scene)
        self._datasets: dict[tuple[str, str], h5py.Dataset] = {}

    def __len__(self) -> int:
        return len(self.trials) * self.windows_per_trial

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_handles"], state["_datasets"] = None, {}
        return state

    def _open(self) -> dict[str, h5py.File]:
        if self._handles is None:
            self._handles = {f: h5py.File(self.cache_files[f], "r") for f in self.fields}
        return self._handles

    def close(self) -> None:
        if self._handles:
            for h in self._handles.values():
                h.close()
        self._handles, self._datasets = None, {}

    def _dataset(self, h: dict[str, h5py.File], fld: str, tr: TrialRef) -> h5py.Dataset:
        """The h5py dataset of field ``fld`` of one trial, looked up once per open file."""
        key = (fld, tr.name)
        ds = self._datasets.get(key)
        if ds is None:
            ds = self._datasets[key] = h[fld]["trials"][tr.name][fld]
        return ds

    def _length(self, h: dict[str, h5py.File], tr: TrialRef) -> int:
        n = self._dataset(h, "actions", tr).shape[0]
        return n if self.seq_len is None else min(n, int(self.seq_len))

    def _rows(self, h: dict[str, h5py.File], tr: TrialRef, gen: torch.Generator | None = None) -> slice:
        if self.window is None:
            return slice(None, self.seq_len)
        n = self._length(h, tr)
        if n <= self.window:
            return slice(None, n)
        start = int(torch.randint(0, n - self.window + 1, (), generator=gen))
        return slice(start, start + self.window)

    def _disjoint_rows(self, h: dict[str, h5py.File], tr: TrialRef, gen: torch.Generator | None
                       ) -> tuple[slice, slice]:
        """Two disjoint ``window``-frame crops of one trial (target, context): the first
        start uniform over [0, n - 2w], the second over [first + w, n - w], their roles at
        random."""
        n, w = self._length(h, tr), int(self.window)
        if n < 2 * w:
            raise ValueError(f"trial '{tr.name}' has {n} frames: two disjoint {w}-frame windows need {2 * w}")
        a = int(torch.randint(0, n - 2 * w + 1, (), generator=gen))
        b = int(torch.randint(a + w, n - w + 1, (), generator=gen))
        first, second = slice(a, a + w), slice(b, b + w)
        return (first, second) if int(torch.randint(0, 2, (), generator=gen)) else (second, first)

    def _read(self, h: dict[str, h5py.File], tr: TrialRef, sl: slice) -> tuple[np.ndarray, np.ndarray]:
        """Observations (T, C, 28, 28) and actions (T, n_a) of rows ``sl`` of one trial."""
        cache: dict[str, np.ndarray] = {}
        planes = []
        for c in self.channels:
            fld, idx, _ = CHANNELS[c]
            if fld not in cache:
                cache[fld] = self._dataset(h, fld, tr)[sl]
            arr = cache[fld]
            planes.append(arr if idx is None else arr[:, idx])
        obs = np.stack(planes, axis=1).astype(np.float32, copy=False)
        actions = self._dataset(h, "actions", tr)[sl].astype(np.float32, copy=False)
        for fld, arr in (("obs", obs), ("actions", actions)):
            if not np.isfinite(arr).all():  # a damaged cache is a bug to report, not to feed the model
                src = self.cache_files["actions" if fld == "actions" else CHANNELS[self.channels[0]][0]]
                raise ValueError(f"{src}: trial '{tr.name}', field '{fld}': non-finite values in the preprocessed cache")
        return obs, actions

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        if not 0 <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} items")
        tr = self.trials[i % len(self.trials)]
        h = self._open()
        gen = None if self.draw_seed is None else torch.Generator().manual_seed(self.draw_seed * 1_000_003 + i)
        ctx_tr, ctx_sl = None, None
        if self.context == "window":
            sl, ctx_sl = self._disjoint_rows(h, tr, gen)
            ctx_tr = tr
        else:
            sl = self._rows(h, tr, gen)
        if self.context == "trial" and self.context_touches > 1:
            others = self.others[tr.name]
            picks = torch.randperm(len(others), generator=gen)[:self.context_touches]
            touches = [(others[int(j)], self._rows(h, others[int(j)], gen)) for j in picks]
        elif self.context == "trial":
            others = self.others[tr.name]
            ctx_tr = others[int(torch.randint(0, len(others), (), generator=gen))]
            ctx_sl = self._rows(h, ctx_tr, gen)
        obs, actions = self._read(h, tr, sl)
        item = {
            "obs": torch.from_numpy(np.ascontiguousarray(obs)),
            "actions": torch.from_numpy(np.ascontiguousarray(actions)),
            "object_id": torch.tensor(tr.object_id, dtype=torch.long),
            "factors": torch.tensor(tr.factors, dtype=torch.float32),
            "action_index": torch.tensor(tr.action_index, dtype=torch.long),
            "trial": tr.name,  # named in errors (the model's non-finite guard)
            "first_frame": torch.tensor(sl.start or 0, dtype=torch.long),  # of this crop in the trial
        }
        if self.feature_scale is not None:
            f, _ = handcrafted_features(obs[None], actions[None], self.channels)
            mean, std = self.feature_scale
            item["target_features"] = torch.from_numpy(((f[0, -1] - mean) / std).astype(np.float32))
        if ctx_tr is not None:
            c_obs, c_actions = self._read(h, ctx_tr, ctx_sl)
            item.update(context_obs=torch.from_numpy(np.ascontiguousarray(c_obs)),
                        context_actions=torch.from_numpy(np.ascontiguousarray(c_actions)),
                        context_trial=ctx_tr.name,
                        context_first_frame=torch.tensor(ctx_sl.start or 0, dtype=torch.long))
        elif self.context_touches > 1:
            reads = [self._read(h, c_tr, c_sl) for c_tr, c_sl in touches]
            item.update(context_obs=torch.from_numpy(np.stack([r[0] for r in reads])),
                        context_actions=torch.from_numpy(np.stack([r[1] for r in reads])),
                        context_trial="+".join(c_tr.name for c_tr, _ in touches),
                        context_first_frame=torch.tensor([c_sl.start or 0 for _, c_sl in touches], dtype=torch.long))
        return item


def _plain(value: Any) -> Any:
    """An OmegaConf container as plain Python (Hydra hands nodes over as they are)."""
    from omegaconf import OmegaConf

    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def _options(cls: type, given: Any) -> Any:
    """``given`` as an options dataclass ``cls`` (a mapping: its keys over the defaults)."""
    if isinstance(given, cls):
        return given
    return cls(**{k: _plain(v) for k, v in dict(given or {}).items()})


class TactileDataModule(L.LightningDataModule):
    """Serves batches ``obs (B,T,C,28,28)``, ``actions (B,T,6)``, ``object_id``, ``factors``,
    ``action_index`` for one skin x primitive x modality scene.

    Three groups of options (:mod:`embodied_tactile.options.data`, each a dataclass or a
    mapping of its keys over the defaults): ``scene`` (what is prepared), ``split`` (how it is
    split), ``loader`` (how it is served); :meth:`from_config` takes the flat keys of a data
    config. The keys:
        source: ``"simulated"`` (raw file ``<data_dir>/raw/<skin>_<primitive>.h5``, missing
            trials simulated by the preparation stage) or ``"recorded"`` (``raw_files``, never
            generated).
        raw_files: recorded files: paths or glob patterns, absolute, ``~`` or relative to
            the working directory (see :attr:`raw_paths`).
        channels: observation channels of the modality, e.g. ``["acc", "fsr_t", "fsr_b"]``.
        objects / actions: subsets of object ids / action indices (None = all).
        preprocess: keyword arguments of ``PreprocessConfig``.
        objects="population": the simulated object population (``sim.population``) with
            ``n_objects`` training, ``n_val_objects`` validation and ``n_test_objects`` test
            objects drawn with ``population_seed``; its roles decide ``split="object"``.
        split: ``"trial"`` (the paper's: every object on both sides; recognition) or
            ``"object"`` (train, validation and test objects disjoint); see :func:`split_trials`.
        test_fraction / val_fraction: held-out test and validation shares (of trials for
            ``split="trial"``, of objects for ``split="object"``).
        split_file: where the split is saved (JSON); reused if it exists and matches.
        seq_len: keep the first ``seq_len`` frames of every trial (None = all).
        train_window / windows_per_trial: the training loader serves ``windows_per_trial``
            random ``train_window``-frame crops of every training trial per epoch (None =
            whole trials). Held-out and alignment loaders always serve whole trials.
        windows_per_epoch: instead of ``windows_per_trial`` (which is then null): this many
            crops per epoch, drawn as shuffled passes over the training trials, so the
            optimiser-step budget does not depend on the number of training objects.
        context: None, ``"trial"`` or ``"window"``: the context objective's pairing
            (:class:`TactileSequenceDataset`, ``recipe=context``): the training crops and the
            validation loader serve targets with context frames of the same object
            (validation: ``train_window``-frame crops drawn once, seeded by ``split_seed``,
            the same every epoch). The alignment and evaluation loaders
            (:meth:`train_eval_dataloader`, :meth:`val_eval_dataloader`,
            :meth:`test_dataloader`) serve whole trials as without it.
        context_touches: with ``context="trial"``, how many other trials of the object make
            up one context (``model.context.touches``).
        strict: a bad raw trial is fatal instead of skipped.
        include_incomplete: also use recordings marked ``complete=False`` (interrupted);
            by default they are left out and counted in a warning.
        allow_large_population: prepare a population scene of more than
            ``prepare.POPULATION_MAX_TRIALS`` trials (refused otherwise, with its estimate).
    """

    def __init__(self, scene: SceneOptions | Mapping[str, Any] | None = None,
                 split: SplitOptions | Mapping[str, Any] | None = None,
                 loader: LoaderOptions | Mapping[str, Any] | None = None):
        super().__init__()
        scene, split, loader = (_options(cls, given) for cls, given in
                                ((SceneOptions, scene), (SplitOptions, split), (LoaderOptions, loader)))
        #: what the preparation stage prepares (validates source, skin, primitive, raw_files, channels)
        self.scene = Scene.from_config(asdict(scene))
        self.source = self.scene.source
        self.skin = self.scene.skin
        self.primitive = self.scene.primitive
        self.channels = list(self.scene.channels)
        self.fields = self.scene.fields
        if split.split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split.split!r}")
        self.split = split.split  # the split's kind ('trial' | 'object')
        self.test_fraction = float(split.test_fraction)
        self.val_fraction = float(split.val_fraction)
        self.split_seed = int(split.split_seed)
        self.split_file = split.split_file
        self.batch_size = int(loader.batch_size)
        self.num_workers = int(loader.num_workers)
        self.seq_len = loader.seq_len
        self.train_window = None if loader.train_window is None else int(loader.train_window)
        per_trial, per_epoch = loader.windows_per_trial, loader.windows_per_epoch
        if (per_trial is None) == (per_epoch is None):
            raise ValueError(f"give one of windows_per_trial ({per_trial}) and windows_per_epoch "
                             f"({per_epoch}), the other null")
        if per_epoch is not None and int(per_epoch) < 1:
            raise ValueError(f"windows_per_epoch must be >= 1, got {per_epoch}")
        self.windows_per_trial = 1 if per_trial is None else int(per_trial)
        self.windows_per_epoch = None if per_epoch is None else int(per_epoch)
        self.pin_memory = bool(loader.pin_memory)
        if loader.context not in CONTEXTS:
            raise ValueError(f"context must be one of {CONTEXTS}, got {loader.context!r}")
        self.context = loader.context
        self.context_touches = int(loader.context_touches)
        self.context_features = bool(loader.context_features)
        #: the unlabelled objects' trials (population ``n_unlabelled_objects``, NaN factors):
        #: served by the training loader beside the training split, never by the alignment,
        #: statistics or evaluation loaders
        self.unlabelled: list[TrialRef] = []
        #: (mean, std) of the hand-crafted features (``context_features``; :meth:`feature_scale`)
        self.features_scale: tuple[np.ndarray, np.ndarray] | None = None
        #: the preparation stage's result (prepare_data, or attach() with one prepared elsewhere)
        self.prepared: PreparedData | None = None
        self.train_set: TactileSequenceDataset | None = None
        #: the training split's channel statistics and size (setup("fit")), handed to the model by
        #: :class:`embodied_tactile.run.handover.HandOverStatistics`
        self.statistics: DataStatistics | None = None
        self.val_set: TactileSequenceDataset | None = None  # model selection (training objects)
        self.test_set: TactileSequenceDataset | None = None  # held out: evaluation only
        self.train_crops: TactileSequenceDataset | None = None  # what train_dataloader serves
        self.val_pairs: TactileSequenceDataset | None = None  # what val_dataloader serves with a context

    @classmethod
    def from_config(cls, data: Mapping[str, Any] | None = None, /, **flat: Any) -> "TactileDataModule":
        """The DataModule of a flat data config (``configs/data/*.yaml``, a run's saved
        ``data``, or keyword arguments; ``_target_`` ignored), sorted into its three groups
        (:func:`embodied_tactile.options.data.group_options`)."""
        given = {**(_plain(data) or {}), **{k: _plain(v) for k, v in flat.items()}}
        return cls(*group_options(given))

    # ------------------------------------------------------------------ preparation
    @property
    def raw_paths(self) -> list[Path]:
        """The raw files (:attr:`Scene.raw_paths <embodied_tactile.data.prepare.Scene.raw_paths>`)."""
        return self.scene.raw_paths

    @property
    def cache_dir(self) -> Path:
        return self.scene.cache_dir

    @property
    def cache_files(self) -> dict[str, str]:
        """``{field: cache path}`` once prepared, else empty."""
        return self.prepared.cache_files if self.prepared else {}

    @property
    def skipped(self) -> list[dict[str, str]]:
        """``{file, trial, field, problem}`` of each bad trial left out (once prepared)."""
        return self.prepared.skipped if self.prepared else []

    @property
    def excluded_incomplete(self) -> list[str]:
        """complete=False recordings left out (once prepared)."""
        return self.prepared.excluded_incomplete if self.prepared else []

    def attach(self, prepared: PreparedData) -> None:
        """Serve a scene prepared elsewhere (``prepare_scene``); it must be this DataModule's
        scene. ``prepare_data`` then has nothing left to do."""
        if prepared.scene != self.scene:
            raise ValueError(f"prepared scene {prepared.scene} is not this DataModule's scene {self.scene}")
        self.prepared = prepared

    def prepare_data(self) -> None:
        """The data preparation stage (:func:`embodied_tactile.data.prepare.prepare_scene`):
        simulate missing trials (simulator source), build the per-field caches, list the
        scene's trials. Runs once per DataModule object (fit then validate reuse it)."""
        if self.prepared is None:
            self.prepared = prepare_scene(self.scene)

    def setup(self, stage: str | None = None) -> None:
        """The split and its datasets (once); for fitting, the training split's
        :attr:`statistics` too."""
        if self.train_set is None:
            self._build_sets()
        if stage == "fit" and self.statistics is None:
            statistics = DataStatistics.of(self.train_eval_dataloader(), len(self.train_set))
            self._check_statistics(statistics)
            self.statistics = statistics

    def _check_statistics(self, statistics: DataStatistics) -> None:
        """:class:`ConstantChannelError` naming the first channel whose training frames are
        all one value (or not finite): its layer, cached field and raw dataset, the
        modality's channels and the raw files (the encoders divide by its std)."""
        from embodied_tactile.data.modality import CHANNELS

        for i, c in enumerate(self.channels):
            mean, std = float(statistics.channel_mean[i]), float(statistics.channel_std[i])
            if np.isfinite(mean) and np.isfinite(std) and std > 0:
                continue
            field, layer, dataset = CHANNELS[c]
            what = "constant" if np.isfinite(std) else "not finite"
            files = [str(p) for p in self.raw_paths]
            raise ConstantChannelError(
                f"channel {c} ({'layer ' + str(layer) + ' of ' if layer is not None else ''}cached field {field}, raw "
                f"dataset {dataset}) of the modality's channels {self.channels} is {what} over the "
                f"{len(self.train_set)} training trials (mean {mean:.6g}, std {std:.3g}) in raw file(s) "
                f"{', '.join(files[:3])}{' ...' if len(files) > 3 else ''}: a dead or unplugged sensor layer; the "
                "encoders standardise by its std. Fix the recording or choose a modality without it")

    def _build_sets(self) -> None:
        if self.prepared is None:
            # prepare_data ran in another process (DDP rank 0): the cache keys are
            # deterministic, so the stage finds the existing files without recomputing.
            self.prepared = prepare_scene(self.scene, simulate=False)
        refs = self.prepared.trials
        roles = self.scene.object_roles() or {}
        if self.split_file and Path(self.split_file).exists():
            train, val, test = self._load_split(refs)
        else:
            train, val, test = split_trials(refs, by=self.split, test_fraction=self.test_fraction,
                                            val_fraction=self.val_fraction, seed=self.split_seed,
                                            roles=roles or None)
            if self.split_file:
                self._save_split(train, val, test)
        self.unlabelled = sorted((t for t in refs if roles.get(t.object_id) == "unlabelled"), key=lambda t: t.name)
        if self.unlabelled and self.split != "object":
            raise ValueError("data.n_unlabelled_objects needs split=object (the unlabelled objects are new objects)")
        if self.context_features:
            self.features_scale = self.feature_scale(train + self.unlabelled)
        self.train_set = TactileSequenceDataset(self.cache_files, train, self.channels, self.seq_len)
        self.val_set = TactileSequenceDataset(self.cache_files, val, self.channels, self.seq_len)
        self.test_set = TactileSequenceDataset(self.cache_files, test, self.channels, self.seq_len)
        self.train_crops = self.train_set
        if (self.train_window is not None or self.windows_per_trial != 1 or self.windows_per_epoch is not None
                or self.context is not None or self.unlabelled or self.context_features):
            self.train_crops = TactileSequenceDataset(self.cache_files, train + self.unlabelled, self.channels,
                                                      self.seq_len, window=self.train_window,
                                                      windows_per_trial=self.windows_per_trial, context=self.context,
                                                      context_touches=self.context_touches,
                                                      feature_scale=self.features_scale)
        self.val_pairs = self.held_out_pairs(val) if self.context is not None and val else self.val_set
        log.info("data: %d train / %d validation / %d test sequences (split=%s), %d unlabelled, channels %s, "
                 "skipped %d bad trial(s)", len(train), len(val), len(test), self.split, len(self.unlabelled),
                 self.channels, len(self.skipped))

    #: at most this many training trials (evenly spaced in name order) fix the feature scale
    FEATURE_SCALE_TRIALS = 512

    def feature_scale(self, trials: Sequence[TrialRef]) -> tuple[np.ndarray, np.ndarray]:
        """(mean, std) of the hand-crafted features (k,) of the served crops' length: each of
        up to :attr:`FEATURE_SCALE_TRIALS` training trials, evenly spaced in name order, read
        from its first frame for ``train_window`` frames (the whole trial without a window),
        its features at the last of them (:func:`~embodied_tactile.data.features.handcrafted_features`);
        std floored at 1e-6. No property label is read."""
        if not trials:
            raise ValueError("feature_scale needs training trials")
        ordered = sorted(trials, key=lambda t: t.name)
        picks = np.unique(np.linspace(0, len(ordered) - 1, min(len(ordered), self.FEATURE_SCALE_TRIALS)).round().astype(int))
        ds = TactileSequenceDataset(self.cache_files, [ordered[i] for i in picks], self.channels, self.seq_len)
        rows = []
        try:
            h = ds._open()
            for tr in ds.trials:
                n = ds._length(h, tr)
                obs, actions = ds._read(h, tr, slice(0, n if self.train_window is None else min(n, self.train_window)))
                rows.append(handcrafted_features(obs[None], actions[None], self.channels)[0][0, -1])
        finally:
            ds.close()
        f = np.stack(rows)
        return f.mean(0), np.maximum(f.std(0), 1e-6)

    def held_out_pairs(self, trials: Sequence[TrialRef]) -> TactileSequenceDataset:
        """Fixed context / target pairs of held-out trials (this DataModule's ``context``
        pairing, ``train_window``-frame crops drawn once, seeded by ``split_seed``): what
        ``val_dataloader`` serves with a context; the context objective's benchmark builds the
        test objects' pairs with it."""
        if self.context is None:
            raise ValueError("held_out_pairs needs a DataModule with context=trial|window")
        return TactileSequenceDataset(self.cache_files, trials, self.channels, self.seq_len,
                                      window=self.train_window, context=self.context, draw_seed=self.split_seed,
                                      context_touches=self.context_touches)

    def _load_split(self, refs: Sequence[TrialRef]) -> tuple[list[TrialRef], list[TrialRef], list[TrialRef]]:
        """Reuse a saved split (resumed runs, evaluation): the split belongs to the run.

        A split file written before the train / val / test split (keys ``train`` and ``val``
        only) held out its ``val`` trials for both selection and scoring: they are read as
        the test set, with no validation set, and a warning says so."""
        saved = json.loads(Path(self.split_file).read_text())
        if "test" not in saved:
            log.warning("%s predates the train/val/test split: its held-out 'val' trials are the test set, "
                        "and this run has no validation set", self.split_file)
            saved = {**saved, "val": [], "test": saved["val"]}
        by_name = {r.name: r for r in refs}
        missing = [n for n in saved["train"] + saved["val"] + saved["test"] if n not in by_name]
        if missing:
            raise RuntimeError(
                f"split file {self.split_file} names {len(missing)} trial(s) absent from the data "
                f"(e.g. {missing[:3]}); the data changed since the run was started"
            )
        log.info("reusing the saved split %s", self.split_file)
        return tuple([by_name[n] for n in saved[k]] for k in ("train", "val", "test"))  # type: ignore[return-value]

    def _save_split(self, train: Sequence[TrialRef], val: Sequence[TrialRef], test: Sequence[TrialRef]) -> None:
        path = Path(self.split_file)
        path.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "seed": self.split_seed,
            "split": self.split,
            "test_fraction": self.test_fraction,
            "val_fraction": self.val_fraction,
            "source": self.source,
            "raw_files": [str(p) for p in self.raw_paths],
            "train": [t.name for t in train],
            "val": [t.name for t in val],
            "test": [t.name for t in test],
            "skipped": self.skipped,
        }
        write_json(path, payload, indent=1)

    # ------------------------------------------------------------------ loaders
    def _loader(self, ds: Dataset, shuffle: bool, batch_size: int | None = None) -> DataLoader:
        return DataLoader(
            ds,
            batch_size=batch_size or self.batch_size,
            shuffle=shuffle,
            num_workers=self.num_workers,
            pin_memory=self.pin_memory,
            persistent_workers=self.num_workers > 0,
            drop_last=False,
        )

    def train_dataloader(self) -> DataLoader:
        assert self.train_crops is not None, "call setup() first"
        if self.windows_per_epoch is None:
            return self._loader(self.train_crops, shuffle=True)
        # a fixed number of windows per epoch, whatever the number of training trials: each
        # epoch walks through shuffled passes over the trials (torch's RNG, seeded)
        sampler = RandomSampler(self.train_crops, replacement=False, num_samples=self.windows_per_epoch)
        return DataLoader(self.train_crops, batch_size=self.batch_size, sampler=sampler, num_workers=self.num_workers,
                          pin_memory=self.pin_memory, persistent_workers=self.num_workers > 0, drop_last=False)

    def train_eval_dataloader(self) -> DataLoader:
        """Training split, fixed order (for latent alignment / evaluation)."""
        assert self.train_set is not None, "call setup() first"
        return self._loader(self.train_set, shuffle=False)

    def val_dataloader(self) -> DataLoader:
        """Validation trials: checkpoint selection, early stopping (with a ``context``: the
        fixed context / target pairs of the validation trials)."""
        assert self.val_pairs is not None, "call setup() first"
        return self._loader(self.val_pairs, shuffle=False)

    def val_eval_dataloader(self) -> DataLoader:
        """Validation split, whole trials, fixed order (evaluation with ``held_out=val``)."""
        assert self.val_set is not None, "call setup() first"
        return self._loader(self.val_set, shuffle=False)

    def test_dataloader(self) -> DataLoader:
        """The held-out test trials: evaluation only, never model selection."""
        assert self.test_set is not None, "call setup() first"
        return self._loader(self.test_set, shuffle=False)

    def teardown(self, stage: str | None = None) -> None:
        for ds in (self.train_set, self.train_crops, self.val_set, self.val_pairs, self.test_set):
            if ds is not None:
                ds.close()

    def describe(self) -> dict[str, Any]:
        """Summary of the scene (printed by the main job, saved with runs)."""
        info: dict[str, Any] = {
            "source": self.source,
            "skin": self.skin,
            "primitive": self.primitive,
            "channels": self.channels,
            "raw_files": [str(p) for p in self.raw_paths],
            "cache_files": self.cache_files,
            "skipped": len(self.skipped),
            "excluded_incomplete": len(self.excluded_incomplete),
        }
        if self.prepared is not None:  # what this process's preparation stage did
            info["simulated"] = self.prepared.simulated
            info["cache_built"] = list(self.prepared.cache_built)
        if self.train_set is not None and self.val_set is not None and self.test_set is not None:
            everything = self.train_set.trials + self.val_set.trials + self.test_set.trials
            info["split"] = self.split
            info["n_train"] = len(self.train_set)
            info["n_val"] = len(self.val_set)
            info["n_test"] = len(self.test_set)
            info["n_unlabelled"] = len(self.unlabelled)
            info["test_objects"] = sorted({t.object_id for t in self.test_set.trials})
            info["objects"] = sorted({t.object_id for t in everything})
            info["actions"] = sorted({t.action_index for t in everything})
            sample = self.train_set[0]
            info["obs_shape"] = list(sample["obs"].shape)
            info["actions_shape"] = list(sample["actions"].shape)
        return info
