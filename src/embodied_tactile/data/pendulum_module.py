"""The pendulum as a scene of train.py (``python train.py experiment=pendulum``): the sequences of
:mod:`embodied_tactile.data.pendulum` (numpy, no torch) served as the tactile DataModule
serves trials (docs/reference/model.md, "Pendulum benchmark").

Batches hold ``obs`` (B, T, 1, 28, 28), ``actions`` (B, T, 1), ``object_id`` (the system,
0..7; -1 for an unseen system), ``factors`` (B, 2): the system's (w0 [rad/s], d [1/s]) in
:attr:`PendulumDataModule.factor_names` order, the targets of the KRR read-out,
``action_index`` (0: the pendulum has one action kind), ``seq_id`` (unique over the sets)
and ``trial`` (a label such as ``test/12``); with ``context="trial"`` also
``context_obs`` / ``context_actions`` (another sequence of the same system).
"""

from __future__ import annotations

from typing import Any, Optional, Sequence

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from embodied_tactile.data.pendulum import UNSEEN_SYSTEMS, PendulumData, generate
from embodied_tactile.data.statistics import DataStatistics
from embodied_tactile.options.data import PendulumOptions

_O = PendulumOptions
#: each set's data seed offset from ``seed`` (test and unseen: the benchmark's held-out seeds)
SEED_OFFSETS = {"train": 0, "test": 1000, "unseen": 2000, "val": 3000}
#: each set's first ``seq_id``: ids never repeat across sets
_ID_BASE = {"train": 0, "val": 1_000_000, "test": 2_000_000, "unseen": 3_000_000}


class PendulumSequences(Dataset):
    """One pendulum sequence per item (see the module docstring).

    ``context=True`` (the context objective, docs/reference/model.md "The context objective")
    adds ``context_obs`` / ``context_actions``: another sequence of the same system, drawn by
    a generator seeded with ``seed`` (read in one process, so the draws repeat with the seed).
    The system id pairs the sequences and reaches the model only as ``object_id``, which the
    context objective never reads."""

    def __init__(self, data: PendulumData, name: str = "train", context: bool = False, seed: int = 0) -> None:
        self.data, self.name = data, name
        self.context = bool(context)
        self._rng = np.random.default_rng(seed)
        self._factors = np.stack([data.w0, data.damping], -1).astype(np.float32)
        self._same = ({int(o): np.flatnonzero(data.object_id == o) for o in np.unique(data.object_id)}
                      if self.context else {})
        if self.context and min(len(v) for v in self._same.values()) < 2:
            raise ValueError("pendulum context pairing needs at least 2 sequences per system")

    def __len__(self) -> int:
        return len(self.data)

    def __getitem__(self, i: int) -> dict[str, Any]:
        d = self.data
        item = {"obs": torch.from_numpy(d.obs[i]), "actions": torch.from_numpy(d.actions[i]),
                "object_id": torch.as_tensor(d.object_id[i]), "factors": torch.from_numpy(self._factors[i]),
                "action_index": torch.tensor(0), "seq_id": torch.tensor(_ID_BASE[self.name] + i),
                "trial": f"{self.name}/{i}"}
        if self.context:
            others = self._same[int(d.object_id[i])]
            j = int(self._rng.choice(others[others != i]))
            item.update(context_obs=torch.from_numpy(d.obs[j]), context_actions=torch.from_numpy(d.actions[j]))
        return item


class PendulumDataModule(L.LightningDataModule):
    """The pendulum's sets (:class:`~embodied_tactile.options.data.PendulumOptions`): training
    sequences of the 8 systems, validation (the checkpoints' ELBO) and test (the KRR read-out:
    ``test_dataloader``) sequences of the same systems drawn with other seeds, and the unseen
    systems (:data:`~embodied_tactile.data.pendulum.UNSEEN_SYSTEMS`, ``unseen_dataloader``).
    An epoch is one shuffled pass over the training sequences. ``statistics``
    (:class:`~embodied_tactile.data.statistics.DataStatistics` of the training images) goes to
    the module through :class:`~embodied_tactile.run.handover.HandOverStatistics`, as the
    tactile DataModule's."""

    #: what ``factors`` holds, column by column (the read-out's targets, rad/s and 1/s)
    factor_names = ("natural_frequency", "damping")
    #: held-out sequences of the training systems: the callback's protocol name
    split = "trial"

    def __init__(self, seed: int = _O.seed, n_train: int = _O.n_train, n_val: int = _O.n_val, n_test: int = _O.n_test,
                 n_steps: int = _O.n_steps, batch_size: int = _O.batch_size, context: Optional[str] = _O.context,
                 channels: Sequence[str] = ("fsr_t",)) -> None:
        super().__init__()
        if len(channels) != 1:
            raise ValueError(f"the pendulum renders one image channel: data.channels must name one, got {list(channels)}")
        self.channels = list(channels)
        if context not in (None, "trial"):
            raise ValueError(f"the pendulum pairs whole sequences: data.context must be null or 'trial', got {context!r}")
        self.seed, self.n_steps, self.batch_size = int(seed), int(n_steps), int(batch_size)
        self.sizes = {"train": int(n_train), "val": int(n_val), "test": int(n_test), "unseen": int(n_test)}
        self.context = context
        self.data: dict[str, PendulumData] = {}
        self.statistics: DataStatistics | None = None
        self.train_set = self.val_set = self.test_set = self.unseen_set = None

    def generate(self, name: str) -> PendulumData:
        """One set, drawn by :func:`~embodied_tactile.data.pendulum.generate` (once)."""
        if name not in self.data:
            self.data[name] = generate(self.sizes[name], seed=self.seed + SEED_OFFSETS[name], n_steps=self.n_steps,
                                       systems=UNSEEN_SYSTEMS if name == "unseen" else None)
        return self.data[name]

    def prepare_data(self) -> None:
        for name in ("train", "val", "test"):
            self.generate(name)

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        pair = self.context == "trial"
        self.train_set = PendulumSequences(self.generate("train"), "train", context=pair, seed=self.seed)
        self.val_set = PendulumSequences(self.generate("val"), "val", context=pair, seed=self.seed + 1)
        self.test_set = PendulumSequences(self.generate("test"), "test")
        self.unseen_set = PendulumSequences(self.generate("unseen"), "unseen")
        train = self.data["train"]
        self.statistics = DataStatistics.of([{"obs": train.obs}], len(train))

    def _loader(self, ds: Dataset, shuffle: bool = False) -> DataLoader:
        return DataLoader(ds, batch_size=self.batch_size, shuffle=shuffle)

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_set, shuffle=True)

    def train_eval_dataloader(self) -> DataLoader:
        """The training sequences in order, without context pairs (the read-outs)."""
        return self._loader(PendulumSequences(self.data["train"], "train"))

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_set)

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.test_set)

    def unseen_dataloader(self) -> DataLoader:
        """The unseen systems' sequences (object id -1): a second held-out set."""
        return self._loader(self.unseen_set)

    def describe(self) -> dict[str, Any]:
        """Summary of the scene (saved with runs)."""
        info: dict[str, Any] = {"scene": "pendulum", "seed": self.seed, "n_steps": self.n_steps,
                                "factors": list(self.factor_names), "context": self.context}
        if self.train_set is not None:
            info.update({f"n_{k}": len(self.data[k]) for k in ("train", "val", "test", "unseen")})
            info["obs_shape"] = list(self.data["train"].obs.shape[1:])
            info["actions_shape"] = list(self.data["train"].actions.shape[1:])
        return info


__all__ = ["PendulumDataModule", "PendulumSequences", "SEED_OFFSETS"]
