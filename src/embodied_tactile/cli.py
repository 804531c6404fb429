"""The command-line side of the Hydra entry points: one line and exit status 2 for a bad
setting (:func:`fail`), ``main()`` of a Hydra command (:func:`hydra_command`), train's entry point
(:func:`train_main`: ``embodied-tactile train`` and ``python train.py``), and its
Hydra callback (:class:`EntryCallback`, registered in ``configs/train.yaml``): settings are
checked (:mod:`embodied_tactile.run.settings`) and the run folder claimed
(:mod:`embodied_tactile.run.runfolder`) before Hydra creates it; a multirun ends with its summary
(:mod:`embodied_tactile.run.summary`)."""

from __future__ import annotations

import dataclasses
import sys
import typing
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import hydra
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from embodied_tactile.options.checks import check_options, field_spec
from embodied_tactile.run.config import config_dir
from embodied_tactile.run.overrides import check_composes, parse_overrides
from embodied_tactile.run.settings import (EXIT_BAD_SETTINGS, SettingsError, check_paths, check_sweep_folder,
                                           check_train_config, config_value, fail)


def hydra_command(config_name: str, run: Callable[[DictConfig], int], prog: str,
                  errors: tuple[type[Exception], ...] = (), options: type | None = None
                  ) -> Callable[[Sequence[str] | None], None]:
    """``main(argv=None)`` of a Hydra command (``embodied-tactile record`` / ``emulate`` /
    ``palpate`` / ``report``) whose ``run(cfg)`` returns the exit status; ``argv`` (default
    ``sys.argv[1:]``) are its ``key=value`` overrides. With ``options`` (the dataclass the
    config composes), the overrides are checked before Hydra composes (:func:`check_overrides`)
    and the composed config after (:func:`~embodied_tactile.options.checks.check_options`).
    A group option or key that does not exist is one line before Hydra runs
    (:func:`~embodied_tactile.run.overrides.check_composes`, as train's). A bad option or an
    exception of ``errors`` prints ``<prog>: error: <message>`` and exits 2; ``--help`` /
    ``--cfg`` exit 0."""
    code: list[int | None] = [None]

    @hydra.main(version_base="1.3", config_path=config_dir(), config_name=config_name)
    def app(cfg: DictConfig) -> None:
        try:
            if options is not None:
                check_options(options, cfg, "")
            code[0] = run(cfg)
        except (SettingsError, *errors) as err:
            print(f"{prog}: error: {err}", file=sys.stderr)
            code[0] = EXIT_BAD_SETTINGS

    def main(argv: Sequence[str] | None = None) -> None:
        code[0] = None
        saved = sys.argv
        if argv is not None:
            sys.argv = [saved[0] if saved else prog, *argv]
        try:
            if options is not None:
                check_overrides(options, sys.argv[1:], prog)
            check_composes(sys.argv[1:], config_name, prog)  # a group option or key that does not exist
            app()
        except SystemExit as exc:
            if code[0] is None and exc.code not in (0, None):
                sys.exit(EXIT_BAD_SETTINGS)
            raise
        finally:
            sys.argv = saved
        # Hydra returned without running the app (--help, --cfg): nothing failed
        sys.exit(0 if code[0] is None and _info_only() else (EXIT_BAD_SETTINGS if code[0] is None else code[0]))

    return main


@hydra.main(version_base="1.3", config_path=config_dir(), config_name="train")
def _train_app(cfg: DictConfig) -> None:
    from embodied_tactile.run.training import run_job  # loads torch and Lightning: only once the settings passed

    run_job(cfg)


def train_main(argv: Sequence[str] | None = None) -> int:
    """``embodied-tactile train`` and ``python train.py``: Hydra ``key=value`` overrides over
    configs/train.yaml (``-m`` for a sweep; default ``sys.argv[1:]``) -> the exit status
    (train.py's docstring lists them). Values of the typed options are checked before Hydra
    merges them (:func:`check_typed_overrides`), the composed config by :class:`EntryCallback`."""
    args = list(sys.argv[1:] if argv is None else argv)
    saved = sys.argv
    sys.argv = [saved[0] if saved else "train.py", *args]
    try:
        check_typed_overrides(args)  # one line for a value of the wrong type, before Hydra merges it
        check_composes(args)  # one line for a group option or key that does not exist (Hydra's own: exit 1)
        _train_app()
    except SystemExit as exc:
        return exit_status(exc)
    finally:
        sys.argv = saved
    return 0


#: exit statuses of a stop signal (128 + SIGINT / SIGTERM)
STOP_STATUSES = (130, 143)


def process_exit(code: int) -> typing.NoReturn:
    """The end of a command's process with ``code`` (train.py, evaluate.py, ``embodied-tactile``).
    After a stop signal (:data:`STOP_STATUSES`) the exit handlers run (``atexit``: log files
    flushed and closed, temporary folders removed), the standard streams are flushed and the
    process ends without the interpreter's teardown of every module and object: 1.6 CPU s
    with torch and Lightning loaded, tens of seconds on a loaded machine, and nothing of the
    run is left to write by then (docs/experiments/stop_latency.md)."""
    if code in STOP_STATUSES:
        import atexit
        import os

        atexit._run_exitfuncs()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    sys.exit(code)


def exit_status(exc: SystemExit) -> int:
    """The exit status of a ``SystemExit`` (a message as its code: printed, status 1, as Python does)."""
    if exc.code is None or isinstance(exc.code, int):
        return exc.code or 0
    print(exc.code, file=sys.stderr)
    return 1


def check_overrides(options: type, args: Sequence[str], prog: str) -> None:
    """The ``key=value`` overrides of a command whose config is the dataclass ``options``,
    checked before Hydra composes: a key the options do not declare, a value of the wrong type
    or out of its bounds prints one line naming the key and exits 2 (Hydra's own error is
    several lines). ``hydra.*`` keys are left to Hydra."""
    for o in parse_overrides(args):
        key = o.key_or_group
        if key == "hydra" or key.startswith(("hydra.", "hydra/")) or o.is_delete():
            continue
        if not _declared(options, key.split("."))[1] or o.package is not None:
            fail(SettingsError(f"{key}: no such option (embodied-tactile {prog} --help lists them)"), prog)
        for value in _values(o):
            node = _typed_value(options, key, key, value, prog)
            try:
                check_options(options, node, "")
            except SettingsError as err:
                fail(err, prog)


def _values(override: Any) -> list:
    """An override's value, or every value of a sweep, as parsed (a sweep over lists, e.g.
    ``data.raw_files=[a.h5,b.h5],[c.h5]``, gives lists; numbers give numbers)."""
    if not override.is_sweep_override():
        return [override.value()]
    from hydra.core.override_parser.types import Transformer

    return list(override.sweep_iterator(transformer=Transformer.identity))


def _typed_value(options: Any, path: str, shown: str, value: Any, prog: str) -> DictConfig:
    """``options`` (a dataclass or an instance) as a structured config with ``path`` set to
    ``value``; a value its type refuses is one line naming ``shown`` and exit 2."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    node = OmegaConf.structured(options)
    try:
        OmegaConf.update(node, path, value, merge=True)
    except OmegaConfBaseException:
        cls = options if isinstance(options, type) else type(options)
        hint, _ = _declared(cls, path.split("."))
        spec = field_spec(hint, _metadata(cls, path.split(".")))
        expected = spec.describe() if spec is not None else str(hint).replace("typing.", "")
        fail(SettingsError(f"{shown}={value!r} ({type(value).__name__}): expected {expected}"), prog)
    return node


def _metadata(cls: type, path: Sequence[str]) -> Any:
    """The field metadata of a (nested) dataclass's key (empty when not a field)."""
    for i, part in enumerate(path):
        fields = {f.name: f for f in dataclasses.fields(cls)} if dataclasses.is_dataclass(cls) else {}
        if part not in fields:
            return {}
        if i == len(path) - 1:
            return fields[part].metadata
        cls = typing.get_type_hints(cls)[part]
    return {}


def _info_only() -> bool:
    return any(a in ("--help", "-h", "--hydra-help", "--cfg", "-c", "--info", "-i") or a.startswith("--cfg=")
               for a in sys.argv[1:])


def _declared(cls: type, path: Sequence[str]) -> tuple[Any, bool]:
    """(declared type, known) of a field of a (nested) dataclass."""
    hint: Any = cls
    for i, part in enumerate(path):
        hints = typing.get_type_hints(hint)
        if part not in hints:
            return Any, False
        hint = hints[part]
        inner = [a for a in typing.get_args(hint) if a is not type(None)]
        if i < len(path) - 1 and len(inner) == 1 and dataclasses.is_dataclass(inner[0]):
            hint = inner[0]  # an optional group (Optional[ContextOptions]): its fields' types
        if not dataclasses.is_dataclass(hint):
            break
    return hint, True


def _typed_nodes() -> dict[str, Any]:
    """Config node -> an instance of its typed options (``model``'s optional context group
    present, so that its keys are typed too)."""
    from embodied_tactile.model.options import ContextOptions
    from embodied_tactile.options.alignment import AlignmentOptions
    from embodied_tactile.run.config import DataNode, ModelNode

    return {"model": ModelNode(context=ContextOptions()), "data": DataNode(), "alignment": AlignmentOptions()}


#: data groups that only a scene of their own name composes (configs/experiment/<name>.yaml)
SCENE_DATA = ("pendulum",)


def check_typed_overrides(args: Sequence[str]) -> None:
    """Command-line values of the typed options (``model.*``, ``data.*``, ``alignment.*``,
    :mod:`embodied_tactile.run.config`) checked against their dataclass types before Hydra
    merges them, every value of a sweep included: one line naming key, value and the type,
    exit 2 (Hydra's own merge error is several lines, exit 1). A key the options do not
    declare is left to Hydra. A scene's data group chosen without its scene (``data=pendulum``
    without ``experiment=pendulum``) is one line naming the scene."""
    nodes = _typed_nodes()
    overrides = parse_overrides(args)
    groups = {o.key_or_group: o.value() for o in overrides if not o.is_sweep_override()}
    for scene in SCENE_DATA:
        if groups.get("data") == scene and groups.get("experiment") != scene:
            fail(SettingsError(f"data={scene} is the data of a scene that also sets the modality and the model: "
                               f"python train.py experiment={scene}"))
    for o in overrides:
        root, _, rest = o.key_or_group.partition(".")
        if root not in nodes or not rest or o.is_delete() or not _declared(type(nodes[root]), rest.split("."))[1]:
            continue
        for value in _values(o):
            _typed_value(nodes[root], rest, o.key_or_group, value, "train.py")


class EntryCallback(Callback):
    """Hydra callback of train.py: check settings before any folder is made; at the end of a
    multirun, print its summary (:mod:`embodied_tactile.run.summary`)."""

    def __init__(self) -> None:
        self._sweep_dir: str | None = None

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._check(config, "hydra.run.dir")
        # runfolder loads lightning (seconds): only train.py's callback needs it, so that record /
        # palpate start at once (a recorder on a busy port must be refused while the other runs)
        from embodied_tactile.run.runfolder import RunFinished, claim_at_entry

        try:
            claim_at_entry(config)
        except SettingsError as err:
            fail(err)
        except RunFinished as done:  # before Hydra writes .hydra/ or the log: no byte of the run changes
            print(f"train.py: {done}", flush=True)
            raise SystemExit(0) from None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._check(config, "hydra.sweep.dir")
        try:
            check_sweep_folder(config)
        except SettingsError as err:
            fail(err)
        present, v = config_value(config, "hydra.sweep.dir")
        self._sweep_dir = str(v) if present else None

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """The sweep's table (job, status, overrides, reason); exit 1 when a job did not finish."""
        from embodied_tactile.run.summary import multirun_rows, print_multirun_summary  # loads torch: only here

        if self._sweep_dir and Path(self._sweep_dir).is_dir():
            print_multirun_summary(self._sweep_dir)
            if any(r["status"] != "finished" for r in multirun_rows(self._sweep_dir)):
                raise SystemExit(1)

    @staticmethod
    def _check(config: DictConfig, run_dir_key: str) -> None:
        try:
            check_train_config(config)
            check_paths(config, run_dir_key=run_dir_key)
        except SettingsError as err:
            fail(err)


__all__ = ["EntryCallback", "STOP_STATUSES", "check_overrides", "check_typed_overrides", "exit_status",
           "hydra_command", "process_exit", "train_main"]
