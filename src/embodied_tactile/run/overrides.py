"""The command line's Hydra overrides before Hydra runs, for every Hydra entry point (train,
prepare, record, palpate, emulate, report): parsed as Hydra parses them
(:func:`parse_overrides`) and composed as Hydra will compose them (:func:`check_composes`),
so that a group option or key that does not exist is one line and exit status 2."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from embodied_tactile.run.config import compose, config_dir
from embodied_tactile.run.settings import SettingsError, fail


def parse_overrides(args: Sequence[str]) -> list:
    """Hydra's parse of the ``key=value`` arguments ([] for a malformed one: Hydra names it itself)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        return OverridesParser.create().parse_overrides([a for a in args if not a.startswith("-")])
    except Exception:
        return []


#: command-line flags after which Hydra does not compose the command's config as given (help,
#: another config file or folder, shell completion): :func:`check_composes` leaves them to Hydra
_OWN_FLAGS = ("-h", "--help", "--hydra-help", "-c", "--cfg", "-i", "--info", "-cp", "--config-path", "-cn",
              "--config-name", "-cd", "--config-dir", "-sc", "--shell-completion", "--experimental-rerun")


def check_composes(args: Sequence[str], config_name: str = "train", prog: str = "train.py") -> None:
    """The command line's overrides composed as Hydra will compose them, before Hydra runs:
    a group option that does not exist (``modality=mutli_l``) or a key the config does not
    hold (``trainer.max_epoch=3``) prints one line naming it and what exists, exit 2
    (Hydra's own report is several lines and exit 1). A sweep (``-m a=x,y``) is composed
    with each override's first value; every value of a swept group is checked to exist."""
    from hydra.errors import HydraException, MissingConfigException
    from omegaconf.errors import OmegaConfBaseException

    if any(a.split("=", 1)[0] in _OWN_FLAGS for a in args):
        return
    overrides = parse_overrides(args)
    if not overrides and any(not a.startswith("-") for a in args):
        return  # a malformed override: Hydra names it itself
    first = []
    for o in overrides:
        if not o.is_sweep_override():
            first.append(o.input_line)
            continue
        try:
            values = list(o.sweep_string_iterator())
        except Exception:  # noqa: BLE001 -- an interval sweep (a sweeper's): its values are the sweeper's
            return
        group = Path(config_dir()) / o.key_or_group.replace(".", "/")
        names = sorted(q.stem for q in group.glob("*.yaml"))
        for v in values:
            if names and not o.key_or_group.startswith("hydra") and str(v) not in names:
                fail(SettingsError(f"{o.key_or_group}={v}: no such option (configs/{o.key_or_group}/ holds "
                                   f"{', '.join(names)})"), prog)
        first.append(f"{o.get_key_element()}={values[0]}")
    try:
        compose(first, config_name, return_hydra_config=True)
    except MissingConfigException as err:
        missing = str(err).split("Could not find '", 1)[-1].split("'", 1)[0]
        group, _, value = missing.rpartition("/")
        options = ", ".join(getattr(err, "options", None) or [])
        fail(SettingsError(f"{group.replace('/', '.')}={value}: no such option"
                           + (f" (configs/{group}/ holds {options})" if options else "")), prog)
    except (HydraException, OmegaConfBaseException) as err:
        lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
        cause = str(err.__cause__).splitlines()[0] if err.__cause__ is not None and str(err.__cause__) else ""
        if lines and lines[0].startswith("Could not override '"):
            key = lines[0].split("'")[1]
            value = next((str(o.value()) for o in overrides if o.key_or_group == key), "")
            fail(SettingsError(f"{key}={value}: no such key in the config ({cause or lines[0]}); a new key is added "
                               f"with +{key}=..."), prog)
        fail(SettingsError("; ".join(lines + ([cause] if cause else []))), prog)
