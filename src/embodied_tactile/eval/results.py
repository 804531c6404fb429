"""Per-sequence evaluation results and the one-call recipe ``evaluate_latents``.

A :class:`Results` holds, for ONE model (or baseline) of one (modality, skin, primitive)
run, the predictions at every frame of every held-out sequence plus the metadata the
tables group by. Tables and figures take a list of them (several runs / methods).

Split dict (``train`` / ``test`` arguments of :func:`evaluate_latents`)::

    {
      "y": (n, T, d_y) float,           # latents (at least the one named by `latent`)
      "z": (n, T, d_z) float,           # optional
      "factors": (n, 4) float,          # ground truth in FACTOR_NAMES order (NaN = unknown)
      "object_id": (n,) int,            # 0..31
      "action_index": (n,) int,         # 0..15
      "seq_id": (n,) hashable,          # optional; when both splits carry it, they must be disjoint
    }
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from ..constants import FACTOR_NAMES, N_OBJECTS, OBJECT_GROUPS, get_object
from ..jsonio import to_jsonable
from ..options.alignment import LATENTS, AlignmentOptions
from .krr import Alignment, alignment_kwargs, assert_disjoint, fit_alignment
from .metrics import balanced_accuracy, nmse_over_time, nmse_trajectory, overall, reference_variance, roc_auc


@dataclass
class Results:
    """Held-out predictions of one method on one run. Shapes: n held-out sequences, T frames."""

    pred: np.ndarray  # (n, T, 4) predictions in original factor units
    factors: np.ndarray  # (n, 4) ground truth
    object_id: np.ndarray  # (n,)
    action_index: np.ndarray  # (n,)
    method: str = "latent_filter"  # e.g. 'latent_filter', 'handcrafted_krr', 'gru', 'mean'
    modality: str = "unknown"
    skin: str = "unknown"
    primitive: str = "unknown"
    source: str = "simulated"  # 'simulated' | 'recorded'
    n_train: int = 0
    latents_last: np.ndarray | None = None  # (n, d) last-step held-out latents (UMAP / distances)
    seq_id: np.ndarray | None = None
    params: dict = field(default_factory=dict)  # alignment params, timings, ...
    var_ref: np.ndarray | None = None  # (4,) reference variance (default: of `factors`)
    seed: int | None = None  # the run's seed: the replicate axis, the only one tables average over
    axes: dict = field(default_factory=dict)  # other configuration axes that differ between runs
    replicate: str = ""  # tells replicates of one cell apart in labels (e.g. 'seed=1'); '' when alone
    targets: str = "physical"  # target encoding of `factors` / `pred` (eval.targets); evaluate.py sets it
    split: str = "unknown"  # how the held-out set was drawn: 'trial' (paper) | 'object' (unseen objects)
    unseen_objects: bool | None = None  # True: no held-out object had a trial in training (from split.json)
    factors_physical: np.ndarray | None = None  # (n, 4) the trials' factors in physical units (figure legends)

    def __post_init__(self) -> None:
        self.pred = np.asarray(self.pred, dtype=np.float64)
        if self.pred.ndim == 2:
            self.pred = self.pred[:, None, :]
        self.factors = np.asarray(self.factors, dtype=np.float64)
        self.object_id = np.asarray(self.object_id, dtype=np.int64)
        self.action_index = np.asarray(self.action_index, dtype=np.int64)
        n = self.pred.shape[0]
        for name in ("factors", "object_id", "action_index"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"Results.{name} has {len(getattr(self, name))} rows, pred has {n}")
        if self.var_ref is None:
            self.var_ref = reference_variance(self.factors)

    @property
    def n_test(self) -> int:
        return int(self.pred.shape[0])

    @property
    def group(self) -> np.ndarray:
        """Table-2 object group per held-out sequence: 'soft' | 'hard' | 'heterogeneous' for a
        catalogue object, 'population' for any other (:func:`object_group`)."""
        return np.array([object_group(int(o)) for o in self.object_id])

    @property
    def label(self) -> str:
        extra = "".join(f"/{k}={v}" for k, v in sorted(self.axes.items()))
        return f"{self.method}/{self.modality}/{self.skin}/{self.primitive}{extra}" + (
            f"@{self.replicate}" if self.replicate else "")

    @property
    def cell(self) -> tuple:
        """Every configuration axis but the seed: (method, modality, skin, primitive, ((axis, value), ...)).
        Runs of one cell are replicates (seeds); tables average over them and nothing else."""
        return (self.method, self.modality, self.skin, self.primitive, tuple(sorted(self.axes.items())))

    def subset_nmse(self, mask=None) -> np.ndarray:
        """Whole-trajectory NMSE per factor over the masked sequences (reference variance)."""
        m = np.ones(self.n_test, bool) if mask is None else np.asarray(mask, bool)
        return nmse_trajectory(self.factors[m], self.pred[m], var_ref=self.var_ref)

    def curve(self, mask=None) -> np.ndarray:
        """NMSE vs interaction time (T, 4) over the masked sequences (reference variance)."""
        m = np.ones(self.n_test, bool) if mask is None else np.asarray(mask, bool)
        return nmse_over_time(self.factors[m], self.pred[m], var_ref=self.var_ref)

    def group_nmse(self, mask) -> np.ndarray:
        """Whole-trajectory NMSE per factor over the masked sequences, normalised by THEIR OWN
        variance (NaN, with a warning, for a factor constant inside the subset)."""
        m = np.asarray(mask, bool)
        return nmse_trajectory(self.factors[m], self.pred[m])

    def heterogeneity_scores(self) -> dict:
        """Heterogeneity as a binary decision from the continuous prediction: balanced accuracy
        (threshold 0.5, halfway between the 0/1 classes) and ROC-AUC, on the last frame and over
        the whole trajectory (every frame of every sequence a sample), with the class counts."""
        k = FACTOR_NAMES.index("heterogeneity")
        y = self.factors[:, k]
        fin = np.isfinite(y)
        last, traj = self.pred[:, -1, k], self.pred[:, :, k]
        if np.any((y[fin] != 0) & (y[fin] != 1)):  # not the catalogue's 0/1 factor (synthetic targets)
            nan = float("nan")
            return {"n_pos": 0, "n_neg": 0, "balanced_accuracy_last": nan, "balanced_accuracy_trajectory": nan,
                    "roc_auc_last": nan, "roc_auc_trajectory": nan}
        return {"n_pos": int((y[fin] == 1).sum()), "n_neg": int((y[fin] == 0).sum()),
                "balanced_accuracy_last": balanced_accuracy(y, last),
                "balanced_accuracy_trajectory": balanced_accuracy(y[:, None], traj),
                "roc_auc_last": roc_auc(y, last), "roc_auc_trajectory": roc_auc(y[:, None], traj)}

    def action_summary(self) -> dict:
        """Overall NMSE of each held-out parameter set's sequences (key: the action index 1-16,
        as the paper numbers them), whole trajectory and last frame, the run's total variance."""
        out = {}
        for a in np.unique(self.action_index):
            m = self.action_index == a
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                out[str(int(a) + 1)] = {"trajectory": overall(self.subset_nmse(m)), "last": overall(self.curve(m)[-1]),
                                        "n": int(m.sum())}
        return out

    def group_summary(self) -> dict:
        """Whole-trajectory NMSE per object group ('soft' | 'hard' | 'heterogeneous'): per factor
        and overall, over the group's held-out sequences, normalised by the run's reference
        variance (the paper's Table 2 convention); a group without held-out sequences is absent."""
        out = {}
        groups = self.group
        for g in (*OBJECT_GROUPS, POPULATION_GROUP):
            mask = groups == g
            if mask.any():
                v = self.subset_nmse(mask)
                out[g] = {**dict(zip(FACTOR_NAMES, _f(v))), "overall": overall(v), "n": int(mask.sum())}
        return out

    def summary(self) -> dict:
        """The headline numbers (JSON-ready)."""
        traj = self.subset_nmse()
        curve = self.curve()
        last = curve[-1]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a frame whose factors are all NaN
            curve_overall = np.nanmean(curve, axis=1)
        return {
            "label": self.label,
            "method": self.method,
            "modality": self.modality,
            "skin": self.skin,
            "primitive": self.primitive,
            "axes": dict(self.axes),
            "seed": self.seed,
            "source": self.source,
            "targets": self.targets,
            "split": self.split,
            "unseen_objects": self.unseen_objects,
            "n_train": int(self.n_train),
            "n_test": self.n_test,
            "nmse_trajectory": dict(zip(FACTOR_NAMES, _f(traj))),
            "nmse_trajectory_overall": overall(traj),
            "nmse_last_step": dict(zip(FACTOR_NAMES, _f(last))),
            "nmse_last_step_overall": overall(last),
            # the read-out over interaction time: mean over factors at every frame, and the
            # first frame at or below 0.5 (None: never)
            "nmse_curve_overall": _f(curve_overall),
            "first_frame_below_half": first_below(curve_overall, 0.5),
            "heterogeneity_classification": self.heterogeneity_scores(),
            # Table 2's convention: each object group's sequences, the run's total variance
            "nmse_trajectory_by_group": self.group_summary(),
            # Table 1's: each parameter set's sequences (action index 1-16), the run's total variance
            "nmse_by_action": self.action_summary(),
            "params": to_jsonable(self.params),
        }


# ----------------------------------------------------------------------------- run axes
NAMED_AXES = {"modality": "modality.name", "skin": "skin.name", "primitive": "primitive.name"}
REPLICATE_KEY = "seed"
_NOT_AXES = ("paths.", "hydra.", "tags", "task_name", "plain_progress", "resume")


def flatten_config(cfg: Mapping, prefix: str = "") -> dict[str, Any]:
    """Nested config dict -> {"a.b.c": leaf} (lists are leaves, as strings)."""
    out: dict[str, Any] = {}
    for k, v in cfg.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten_config(v, key + "."))
        else:
            out[key] = str(v) if isinstance(v, (list, tuple)) else v
    return out


def config_axes(configs: Sequence[Mapping], run_names: Sequence[str] = ()) -> list[dict]:
    """The configuration axes of a set of runs, beyond modality / skin / primitive and the seed.

    ``configs``: each run's resolved config (nested dicts). Returns, per run, {dotted key:
    value} for the keys whose value differs between the runs and that are not a function of
    (modality, skin, primitive, seed) and the axes already kept (derived keys such as
    ``data.channels`` or ``data.seed`` are dropped; ``*.name`` keys are preferred as labels).
    Keys holding a run's own folder (checkpoint dirs) and ``paths.*`` / ``hydra.*`` are not axes.
    """
    flat = [flatten_config(c) for c in configs]
    if len(flat) < 2:
        return [{} for _ in flat]
    names = [str(n) for n in run_names]
    keys = sorted(set().union(*flat))
    differing = []
    for k in keys:
        vals = [f.get(k) for f in flat]
        if len({repr(v) for v in vals}) < 2 or k == REPLICATE_KEY or k.startswith(_NOT_AXES):
            continue
        if any(k.startswith(n.split(".")[0] + ".") for n in NAMED_AXES.values()):
            continue
        if names and any(n and n in str(v) for n, v in zip(names, vals)):
            continue  # holds the run folder (e.g. the checkpoint dir): differs by construction
        differing.append(k)
    differing.sort(key=lambda k: (not k.endswith(".name"), k.count("."), k))
    context = [[repr(f.get(p)) for p in (*NAMED_AXES.values(), REPLICATE_KEY)] for f in flat]
    kept: list[str] = []
    for k in differing:
        seen: dict[tuple, str] = {}
        determined = True
        for ctx, f in zip(context, flat):
            v = repr(f.get(k))
            if seen.setdefault(tuple(ctx), v) != v:
                determined = False
                break
        if not determined:
            kept.append(k)
            for ctx, f in zip(context, flat):
                ctx.append(repr(f.get(k)))
    return [{k: f.get(k) for k in kept} for f in flat]


#: the group of an object outside the 32-object catalogue (its factors come from its trials)
POPULATION_GROUP = "population"


def object_group(object_id: int) -> str:
    """The paper's Table 2 group of a catalogue object ('soft' | 'hard' | 'heterogeneous');
    :data:`POPULATION_GROUP` for an object outside the catalogue."""
    return get_object(object_id).group if 0 <= int(object_id) < N_OBJECTS else POPULATION_GROUP


SPLIT_KINDS = {"trial": "held-out trials of training objects: recognition (the paper's split)",
               "object": "whole objects held out (generalisation to unseen objects)"}


def split_report(split: Mapping[str, Any], objects: Mapping[str, int]) -> dict:
    """What a run's ``split.json`` says about generalisation: the split kind, the object ids
    on each side and ``unseen_objects`` = no test object has a trial in training or validation
    (checked from the trials' objects, whatever the kind says). ``objects``: trial name ->
    object id, from the trials' attributes (a name is a label, never parsed); a trial of the
    split missing from it is an error. ``seen_test_objects`` lists the test objects that do."""
    sides = {k: [str(n) for n in split.get(k) or []] for k in ("train", "val", "test")}
    missing = [n for v in sides.values() for n in v if n not in objects]
    if missing:
        raise ValueError(f"{len(missing)} trial(s) of the split have no known object (e.g. {missing[:3]}): "
                         "the split and the served trials differ")
    objs = {k: sorted({int(objects[n]) for n in v}) for k, v in sides.items()}
    fitted = set(objs["train"]) | set(objs["val"])
    seen = sorted(set(objs["test"]) & fitted)
    return {"kind": str(split.get("split", "trial")), "n_train": len(sides["train"]), "n_val": len(sides["val"]),
            "n_test": len(sides["test"]), "train_objects": objs["train"], "test_objects": objs["test"],
            "unseen_objects": bool(objs["test"]) and not seen, "seen_test_objects": seen}


def select_latents(split: Mapping[str, Any], latent: str = "y") -> np.ndarray:
    """'y' | 'z' | 'both' (concatenated z then y on the last axis) -> (n, T, d)."""
    if latent == "both":
        return np.concatenate([np.asarray(split["z"]), np.asarray(split["y"])], axis=-1)
    if latent not in LATENTS:
        raise ValueError(f"latent must be one of {', '.join(LATENTS)}, got {latent!r}")
    return np.asarray(split[latent])


def evaluate_latents(
    train: Mapping[str, Any],
    test: Mapping[str, Any],
    *,
    latent: str = "y",
    method: str = "latent_filter",
    modality: str = "unknown",
    skin: str = "unknown",
    primitive: str = "unknown",
    source: str = "simulated",
    alignment: AlignmentOptions | None = None,
    params: Mapping[str, Any] | None = None,
    split: str = "trial",
) -> tuple[Results, Alignment]:
    """Fit the KRR alignment on ``train`` (final segments), predict every frame of ``test``.

    ``alignment``: the typed read-out (None: the defaults); its ``groups`` ('auto', 'sequence'
    or 'object') is resolved by :func:`~embodied_tactile.eval.krr.resolve_cv_grouping` for the
    run's ``split`` kind ('trial' | 'object'). Raises
    :class:`~embodied_tactile.eval.krr.LeakageError` when both splits carry ``seq_id`` and
    they intersect.
    """
    assert_disjoint(train.get("seq_id"), test.get("seq_id"))
    x_tr = select_latents(train, latent)
    x_te = select_latents(test, latent)
    kw = alignment_kwargs(alignment, split, train.get("object_id"))
    t0 = time.perf_counter()
    align = fit_alignment(x_tr, train["factors"], ids=train.get("seq_id"), **kw)
    t1 = time.perf_counter()
    pred = align.predict(x_te, ids=test.get("seq_id"))
    t2 = time.perf_counter()
    p = {"alignment": align.params, "latent": latent, "krr_fit_s": t1 - t0, "krr_predict_s": t2 - t1,
         "krr_predict_s_per_sequence": (t2 - t1) / max(1, len(x_te))}
    p.update(params or {})
    res = Results(
        pred=pred,
        factors=test["factors"],
        object_id=test["object_id"],
        action_index=test["action_index"],
        method=method,
        modality=modality,
        skin=skin,
        primitive=primitive,
        source=source,
        n_train=len(x_tr),
        latents_last=np.asarray(x_te)[:, -1, :] if np.ndim(x_te) == 3 else np.asarray(x_te),
        seq_id=None if test.get("seq_id") is None else np.asarray(test["seq_id"]),
        factors_physical=None if test.get("factors_physical") is None else np.asarray(test["factors_physical"]),
        params=p,
    )
    return res, align


def first_below(curve, level: float) -> int | None:
    """The first index of ``curve`` at or below ``level`` (None when it never gets there)."""
    hit = np.flatnonzero(np.asarray(curve, dtype=np.float64) <= level)
    return int(hit[0]) if hit.size else None


def _f(v) -> list:
    return [float(x) for x in np.asarray(v, dtype=np.float64).ravel()]


def scored_on_validation(runs: Sequence[Mapping[str, Any]]) -> list[str]:
    """Methods of a ``results.json``'s ``runs`` that evaluate.py scored on the validation side
    (``held_out=val``, kept in each result's ``params``): readers of test-side reports refuse them."""
    return sorted({r.get("method", "?") for r in runs if (r.get("params") or {}).get("held_out", "test") != "test"})
