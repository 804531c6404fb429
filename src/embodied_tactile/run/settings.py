"""Which settings can work: the checks that stop train.py at the entry with one line naming
the key and the value.

:func:`check_train_config` type- and range-checks the keys of the composed train config that reach
Lightning / the data module / the optimiser as numbers or flags (``SCHEMA``), and
:func:`check_paths` makes sure the data and log folders can be created and written.
Both raise :class:`SettingsError`; :class:`embodied_tactile.cli.EntryCallback` runs them
before Hydra creates the run folder and exits with status :data:`EXIT_BAD_SETTINGS`.
``train.py`` runs the type check again per job (values swept with ``-m``).
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

EXIT_BAD_SETTINGS = 2


class SettingsError(ValueError):
    """A config value that cannot work; the message names key, value and what is allowed."""


@dataclass(frozen=True)
class Spec:
    """Allowed values of one key: ``kinds`` among 'int', 'float', 'bool', 'str', 'list'
    (an int is accepted where a float is), optional bounds (inclusive unless ``lo_open`` /
    ``hi_open``), None allowed or not."""

    kinds: tuple[str, ...]
    lo: float | None = None
    hi: float | None = None
    nullable: bool = False
    lo_open: bool = False
    hi_open: bool = False

    def describe(self) -> str:
        names = {"int": "an integer", "float": "a number", "bool": "true/false", "str": "a string", "list": "a list"}
        s = " or ".join(names[k] for k in self.kinds)
        if self.lo is not None and self.hi is not None:
            s += f" in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"
        elif self.lo is not None:
            s += f" {'>' if self.lo_open else '>='} {self.lo:g}"
        return s + (" or null" if self.nullable else "")

    def accepts(self, v: Any) -> bool:
        if v is None:
            return self.nullable
        if isinstance(v, bool):
            return "bool" in self.kinds
        if isinstance(v, int):
            ok = "int" in self.kinds or "float" in self.kinds
        elif isinstance(v, float):
            ok = "float" in self.kinds and math.isfinite(v)
        elif isinstance(v, str):
            return "str" in self.kinds
        elif isinstance(v, (list, tuple)):
            return "list" in self.kinds
        else:
            return False
        if self.lo is not None and not (v > self.lo if self.lo_open else v >= self.lo):
            return False
        return ok and (self.hi is None or (v < self.hi if self.hi_open else v <= self.hi))


INT0, INT1 = Spec(("int",), lo=0), Spec(("int",), lo=1)
FLAG = Spec(("bool",))
NONNEG = Spec(("float",), lo=0)

#: key -> Spec. Keys absent from a config (e.g. callbacks=none) are not checked.
SCHEMA: dict[str, Spec] = {
    "seed": Spec(("int",)),
    "resume": FLAG,
    "validate_at_end": FLAG,
    "plain_progress": Spec(("bool", "str")),
    "trainer.max_epochs": Spec(("int",), lo=-1, nullable=True),
    "trainer.max_steps": Spec(("int",), lo=-1, nullable=True),
    "trainer.devices": Spec(("int", "str", "list")),
    "trainer.num_nodes": INT1,
    "trainer.gradient_clip_val": Spec(("float",), lo=0, nullable=True),
    "trainer.log_every_n_steps": INT1,
    "trainer.check_val_every_n_epoch": Spec(("int",), lo=1, nullable=True),
    "trainer.num_sanity_val_steps": Spec(("int",), lo=-1),
    "trainer.limit_train_batches": Spec(("int", "float"), lo=0, nullable=True),
    "trainer.limit_val_batches": Spec(("int", "float"), lo=0, nullable=True),
    "trainer.accumulate_grad_batches": INT1,
    "trainer.fast_dev_run": Spec(("bool", "int")),
    "trainer.enable_progress_bar": FLAG,
    "trainer.deterministic": Spec(("bool", "str")),
    "data.batch_size": INT1,
    "data.num_workers": INT0,
    "data.repetitions": INT1,
    "data.seq_len": Spec(("int",), lo=1, nullable=True),
    "data.train_window": Spec(("int",), lo=2, nullable=True),  # the recursion needs a transition
    "data.windows_per_trial": Spec(("int",), lo=1, nullable=True),
    "data.windows_per_epoch": Spec(("int",), lo=1, nullable=True),
    "data.test_fraction": Spec(("float",), lo=0, hi=1, lo_open=True, hi_open=True),
    "data.val_fraction": Spec(("float",), lo=0, hi=1, hi_open=True),
    "data.sim_workers": INT1,
    "data.allow_large_population": FLAG,
    "data.n_objects": INT1,
    "data.n_val_objects": INT1,
    "data.n_test_objects": INT1,
    "data.population_seed": INT0,
    "data.preprocess_workers": INT1,
    "model.net.n_z": INT1,
    "model.net.n_y": INT1,
    "model.net.obs_sigma": Spec(("float",), lo=0, lo_open=True),
    "model.net.obs_sigma_min": NONNEG,
    "model.net.obs_dropout": Spec(("float",), lo=0, hi=1, hi_open=True),
    "model.code_lr_scale": Spec(("float",), lo=0, lo_open=True),
    "model.optimizer.lr": Spec(("float",), lo=0),
    "model.context.initial_frames": INT1,
    "callbacks.krr_alignment.every_n_epochs": Spec(("int",), lo=0, nullable=True),  # null = spread `points`
    "callbacks.krr_alignment.points": INT1,
}


def config_value(cfg: DictConfig, key: str) -> tuple[bool, Any]:
    """(present, value) with interpolations resolved where they can be (a value that only
    resolves inside a Hydra job, e.g. ``${hydra:...}``, is reported absent)."""
    node: Any = cfg
    for part in key.split("."):
        if not isinstance(node, DictConfig) or part not in node:
            return False, None
        try:
            node = node[part]
        except Exception:  # unresolvable outside the job
            return False, None
    if isinstance(node, DictConfig):
        return False, None
    if OmegaConf.is_config(node):
        node = OmegaConf.to_container(node, resolve=True)
    return True, node


#: Bounds between two keys: (key a, key b, test of (a, b), what is allowed).
PAIRS: tuple[tuple[str, str, Callable[[float, float], bool], str], ...] = (
    ("data.test_fraction", "data.val_fraction", lambda t, v: t + v < 1, "test_fraction + val_fraction < 1"),
    ("model.net.obs_sigma", "model.net.obs_sigma_min", lambda s, m: s > m, "obs_sigma > obs_sigma_min"),
)


def check_train_config(cfg: DictConfig) -> None:
    """Raise SettingsError for the first key of SCHEMA whose value is of the wrong type or
    range, then for the first pair of PAIRS that breaks its bound."""
    for key, spec in SCHEMA.items():
        present, v = config_value(cfg, key)
        if present and not spec.accepts(v):
            raise SettingsError(f"{key}={v!r} ({type(v).__name__}): expected {spec.describe()}")
    _check_population(cfg)
    for a, b, ok, rule in PAIRS:
        (has_a, va), (has_b, vb) = config_value(cfg, a), config_value(cfg, b)
        if has_a and has_b and va is not None and vb is not None and not ok(va, vb):
            raise SettingsError(f"{a}={va!r} and {b}={vb!r}: expected {rule}")


def _check_population(cfg: DictConfig) -> None:
    """A population scene larger than ``prepare.POPULATION_MAX_TRIALS`` trials needs
    ``data.allow_large_population=true``: SettingsError with its disk and time estimate."""
    present, objects = config_value(cfg, "data.objects")
    if not present or objects != "population":
        return
    from embodied_tactile import constants as C
    from embodied_tactile.data.prepare import check_population_size, fields_for_channels

    get = lambda key, default: (lambda p: p[1] if p[0] and p[1] is not None else default)(config_value(cfg, key))  # noqa: E731
    actions = get("data.actions", None)
    try:
        check_population_size(int(get("data.n_objects", 256)), int(get("data.n_val_objects", 32)),
                              int(get("data.n_test_objects", 64)), C.N_ACTIONS if actions is None else len(actions),
                              int(get("data.repetitions", 1)), fields_for_channels(get("data.channels", ["acc"])),
                              int(get("data.sim_workers", 2)), bool(get("data.allow_large_population", False)))
    except ValueError as err:
        raise SettingsError(str(err)) from None


def check_writable_dir(key: str, value: Any) -> Path:
    """Create the folder if needed and write a probe file into it; SettingsError naming the
    key, the path and the OS reason otherwise."""
    if value is None or str(value) == "":
        raise SettingsError(f"{key} is empty: give a folder")
    p = Path(str(value)).expanduser()
    try:
        if p.exists() and not p.is_dir():
            raise SettingsError(f"{key}={value}: exists and is not a folder")
        p.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=p):
            pass
    except OSError as err:
        raise SettingsError(f"{key}={value}: cannot create or write this folder ({err.strerror or err})") from None
    return p


def check_paths(cfg: DictConfig, *, run_dir_key: str | None = None) -> None:
    """paths.data_dir, paths.log_dir (and the run / sweep folder's parent when given)."""
    for key in ("paths.data_dir", "paths.log_dir"):
        present, v = config_value(cfg, key)
        if present:
            check_writable_dir(key, v)
    if run_dir_key:
        present, v = config_value(cfg, run_dir_key)
        if present and v:
            check_writable_dir(run_dir_key, Path(str(v)).parent)


__all__ = ["EXIT_BAD_SETTINGS", "SettingsError", "SCHEMA", "Spec", "check_train_config", "check_paths",
           "check_writable_dir"]
