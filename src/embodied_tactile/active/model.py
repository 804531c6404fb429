"""What an active palpation episode needs from a trained run, in one object.

:class:`PalpationModel` holds the Latent Filter (``net``), the preprocessing of the run's
scene, its observation channels, the KRR alignment y -> factors (fitted on the run's
training split, exactly as ``evaluate.py`` fits it), the factor reference variance that
normalises NMSE and the uncertainty, and the nominal action trajectory of every action
parameter set the run was trained on (the mean preprocessed pose trajectory of its training
trials with that parameter set: what the robot will do, before it does it).

Load one from a run folder with :func:`embodied_tactile.active.load.load_palpation_model`;
tests build one from a constructed network.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from embodied_tactile.data.preprocess import PreprocessConfig, preprocess_trial
from embodied_tactile.eval.krr import Alignment
from embodied_tactile.eval.targets import encode_factors
from embodied_tactile.data.rawformat import RawTrial
from embodied_tactile.data.modality import CHANNELS, fields_for_channels


@dataclass
class PalpationModel:
    net: Any  # LatentFilter (step / filter_step / n_y)
    channels: tuple[str, ...]
    preprocess: PreprocessConfig
    alignment: Alignment
    ref_var: np.ndarray  # (4,) factor variance (targets encoding) over the catalogue: NMSE / uncertainty scale
    nominal_actions: Mapping[int, np.ndarray]  # action index -> (T, n_a) float32
    skin: str = "soft"
    primitive: str = "pressing"
    targets: str = "design_rank"
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.ref_var = np.asarray(self.ref_var, dtype=np.float64)
        if self.ref_var.shape != (4,) or not np.all(self.ref_var > 0):
            raise ValueError(f"ref_var must be 4 positive variances, got {self.ref_var}")
        if not self.nominal_actions:
            raise ValueError("nominal_actions is empty: the run has no training trial of any action")
        self.nominal_actions = {int(k): np.asarray(v, dtype=np.float32) for k, v in self.nominal_actions.items()}

    @property
    def actions(self) -> tuple[int, ...]:
        """The action parameter sets the model knows (those of its training scene)."""
        return tuple(sorted(self.nominal_actions))

    # ------------------------------------------------------------------ data
    def observe(self, trial: RawTrial) -> tuple[np.ndarray, np.ndarray]:
        """One raw touch -> (obs (T, C, 28, 28), actions (T, n_a)) float32, with the run's
        preprocessing and channel order (the DataModule's stacking of cached fields)."""
        fields = fields_for_channels(self.channels)
        pre = preprocess_trial(trial, self.preprocess, fields)
        planes = []
        for c in self.channels:
            fld, idx, _ = CHANNELS[c]
            planes.append(pre[fld] if idx is None else pre[fld][:, idx])
        obs = np.stack(planes, axis=1).astype(np.float32, copy=False)
        acts = pre["actions"].astype(np.float32, copy=False)
        for name, arr in (("obs", obs), ("actions", acts)):
            if not np.isfinite(arr).all():
                raise ValueError(f"touch {trial.group or trial.attrs}: field {name!r} has non-finite values after "
                                 "preprocessing")
        return obs, acts

    def true_factors(self, object_ids: Sequence[int]) -> np.ndarray:
        """(n, 4) catalogue factors of the objects in the targets encoding."""
        from embodied_tactile import constants as C

        return encode_factors(np.stack([C.get_object(int(o)).factors() for o in object_ids]), self.targets)

    # ------------------------------------------------------------------ y -> factors
    def factors_of(self, y: np.ndarray) -> np.ndarray:
        """KRR alignment of latents y (n, n_y) -> (n, 4) factor estimates (targets encoding)."""
        return self.alignment.predict(np.asarray(y, dtype=np.float64))[:, 0, :]

    def factor_moments(self, y_mean: np.ndarray, y_var: np.ndarray, n_samples: int,
                       rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance (n, 4) of f(y) for y ~ N(y_mean, diag y_var) (n, n_y), f the
        KRR alignment, by ``n_samples`` Monte-Carlo draws per row (the same standard-normal
        draws for every row, so rows are compared on common random numbers)."""
        y_mean = np.asarray(y_mean, dtype=np.float64)
        y_var = np.asarray(y_var, dtype=np.float64)
        n, d = y_mean.shape
        eps = rng.standard_normal((int(n_samples), d))
        ys = y_mean[:, None, :] + np.sqrt(np.maximum(y_var, 0.0))[:, None, :] * eps[None]
        f = self.alignment.predict(ys.reshape(n * int(n_samples), d))[:, 0, :].reshape(n, int(n_samples), -1)
        return f.mean(axis=1), f.var(axis=1)

    def normalised_variance(self, var: np.ndarray) -> np.ndarray:
        """Sum over factors of var_k / ref_var_k: (..., 4) -> (...). The quantity the active
        policy minimises (docs/reference/active.md, eq. 3)."""
        return (np.asarray(var) / self.ref_var).sum(axis=-1)

    # ------------------------------------------------------------------ torch helpers
    def nominal_batch(self, action_indices: Sequence[int]) -> torch.Tensor:
        """(len, T, n_a) nominal action trajectories of ``action_indices``."""
        missing = [int(a) for a in action_indices if int(a) not in self.nominal_actions]
        if missing:
            raise ValueError(f"action(s) {missing} unknown to this model (trained on actions {list(self.actions)})")
        return torch.from_numpy(np.stack([self.nominal_actions[int(a)] for a in action_indices]))
