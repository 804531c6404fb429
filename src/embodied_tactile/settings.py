"""Bad settings stop train.py at the entry with one line naming the key and the value.

:func:`check_train_config` type- and range-checks the keys of the composed train config that reach
Lightning / the data module / the optimiser as numbers or flags (``SCHEMA``), and
:func:`check_paths` makes sure the data and log folders can be created and written.
Both raise :class:`SettingsError`; :class:`EntryCallback` (a Hydra callback, registered in
``configs/train.yaml``) runs them before Hydra creates the run folder, prints
``train.py: error: <message>`` and exits with status 2 -- no traceback, no empty run
folder. ``train.py`` runs the type check again per job (values swept with ``-m``).
"""

from __future__ import annotations

import math
import os
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

EXIT_BAD_SETTINGS = 2


def config_dir() -> str:
    """The Hydra config folder: ``$EMBODIED_TACTILE_CONFIG_DIR`` if set, else the project
    checkout's ``configs/``."""
    env = os.environ.get("EMBODIED_TACTILE_CONFIG_DIR")
    if env:
        return str(Path(env).resolve())
    return str(Path(__file__).resolve().parents[2] / "configs")


def hydra_command(config_name: str, run: Callable[[DictConfig], int], prog: str,
                  errors: tuple[type[Exception], ...] = ()) -> Callable[[], None]:
    """``main()`` of a Hydra command (``python -m embodied_tactile.record`` / ``.palpate``)
    whose ``run(cfg)`` returns the exit status. An exception of ``errors`` prints
    ``<prog>: error: <message>`` and exits 2; so does a config composition error (Hydra's
    own exit 1); ``--help`` / ``--cfg`` exit 0."""
    code: list[int | None] = [None]

    import hydra

    @hydra.main(version_base="1.3", config_path=config_dir(), config_name=config_name)
    def app(cfg: DictConfig) -> None:
        try:
            code[0] = run(cfg)
        except errors as err:
            print(f"{prog}: error: {err}", file=sys.stderr)
            code[0] = EXIT_BAD_SETTINGS

    def main() -> None:
        code[0] = None
        try:
            app()
        except SystemExit as exc:
            if code[0] is None and exc.code not in (0, None):
                sys.exit(EXIT_BAD_SETTINGS)
            raise
        # Hydra returned without running the app (--help, --cfg): nothing failed
        sys.exit(0 if code[0] is None and _info_only() else (EXIT_BAD_SETTINGS if code[0] is None else code[0]))

    return main


def _info_only() -> bool:
    return any(a in ("--help", "-h", "--hydra-help", "--cfg", "-c", "--info", "-i") or a.startswith("--cfg=")
               for a in sys.argv[1:])


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


def _get(cfg: DictConfig, key: str) -> tuple[bool, Any]:
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
        present, v = _get(cfg, key)
        if present and not spec.accepts(v):
            raise SettingsError(f"{key}={v!r} ({type(v).__name__}): expected {spec.describe()}")
    _check_population(cfg)
    for a, b, ok, rule in PAIRS:
        (has_a, va), (has_b, vb) = _get(cfg, a), _get(cfg, b)
        if has_a and has_b and va is not None and vb is not None and not ok(va, vb):
            raise SettingsError(f"{a}={va!r} and {b}={vb!r}: expected {rule}")


def _check_population(cfg: DictConfig) -> None:
    """A population scene larger than ``prepare.POPULATION_MAX_TRIALS`` trials needs
    ``data.allow_large_population=true``: SettingsError with its disk and time estimate."""
    present, objects = _get(cfg, "data.objects")
    if not present or objects != "population":
        return
    from embodied_tactile import constants as C
    from embodied_tactile.data.prepare import check_population_size, fields_for_channels

    get = lambda key, default: (lambda p: p[1] if p[0] and p[1] is not None else default)(_get(cfg, key))  # noqa: E731
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
        present, v = _get(cfg, key)
        if present:
            check_writable_dir(key, v)
    if run_dir_key:
        present, v = _get(cfg, run_dir_key)
        if present and v:
            check_writable_dir(run_dir_key, Path(str(v)).parent)


def fail(err: SettingsError, prog: str = "train.py") -> None:
    """The one line and exit status 2."""
    print(f"{prog}: error: {err}", file=sys.stderr)
    raise SystemExit(EXIT_BAD_SETTINGS)


try:  # Hydra is a dependency of train.py; keep this module importable without it
    from hydra.experimental.callback import Callback as _HydraCallback
except ImportError:  # pragma: no cover
    _HydraCallback = object  # type: ignore[misc,assignment]


class EntryCallback(_HydraCallback):
    """Hydra callback of train.py: check settings before any folder is made; at the end of a
    multirun, print its summary (:mod:`embodied_tactile.summary`)."""

    def __init__(self) -> None:
        self._sweep_dir: str | None = None

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._check(config, "hydra.run.dir")
        from .runfolder import claim_at_entry  # the folder's lock and resume check, before Hydra writes into it

        try:
            claim_at_entry(config)
        except SettingsError as err:
            fail(err)

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._check(config, "hydra.sweep.dir")
        present, v = _get(config, "hydra.sweep.dir")
        self._sweep_dir = str(v) if present else None

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        from .summary import print_multirun_summary

        if self._sweep_dir and Path(self._sweep_dir).is_dir():
            print_multirun_summary(self._sweep_dir)

    @staticmethod
    def _check(config: DictConfig, run_dir_key: str) -> None:
        try:
            check_train_config(config)
            check_paths(config, run_dir_key=run_dir_key)
        except SettingsError as err:
            fail(err)


__all__ = ["SettingsError", "SCHEMA", "Spec", "check_train_config", "check_paths", "check_writable_dir",
           "fail", "EntryCallback", "EXIT_BAD_SETTINGS"]


def prior_rows(objects: Any, n_test: int, n_val: int, n_train: int) -> int:
    """Rows of the prior's object-code table for a scene (``${prior_rows:...}`` in
    configs/model/latent_filter.yaml): the catalogue's 32, or every population id."""
    from embodied_tactile.constants import N_OBJECTS, POPULATION_ID_BASE

    if objects == "population":
        return POPULATION_ID_BASE + int(n_test) + int(n_val) + int(n_train)
    return N_OBJECTS


def lf_default(name: str) -> Any:
    """A Latent Filter option's default from the class signatures (``${lf_default:obs_sigma}``,
    ``${lf_default:prior.learn_sigma}``, ``${lf_default:encoder.widths}`` in
    configs/model/latent_filter.yaml): :func:`~embodied_tactile.models.latent_filter.default_option`."""
    from embodied_tactile.models.latent_filter import default_option

    value = default_option(str(name))
    return OmegaConf.create(value) if isinstance(value, (list, dict)) else value


for _name, _resolver in (("prior_rows", prior_rows), ("lf_default", lf_default)):
    if not OmegaConf.has_resolver(_name):
        OmegaConf.register_new_resolver(_name, _resolver)
