"""The one description of a sensing modality (config group ``modality``).

A modality is a yaml file in ``configs/modality/`` and nothing else: its observation
channels (the C axis of ``obs``, in order), the fusion scheme, and for late fusion the
pathways (encoder/decoder groups of channels). :class:`Modality` is built from that yaml
(``Modality.from_config``) and is what the DataModule (which cached fields to read), the
Latent Filter (which encoders and decoders to build) and the baselines (which channels
to featurise) use. Adding a modality is one yaml file over the channels of
:data:`CHANNELS`.

Pure Python: no torch, no OmegaConf (a DictConfig is accepted through its mapping
interface).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

#: The sensor channels preprocessing produces: channel -> (cached field, index into that
#: field's channel axis or None, raw HDF5 dataset it is computed from).
CHANNELS: Mapping[str, tuple[str, int | None, str]] = {
    "acc": ("acc", None, "tactile/acc"),
    "fsr_t": ("fsr", 0, "tactile/fsr"),
    "fsr_b": ("fsr", 1, "tactile/fsr"),
}

FUSIONS = ("single", "early", "late")


def fields_for_channels(channels: Sequence[str]) -> list[str]:
    """Cached fields a list of observation channels needs (always with ``actions``)."""
    unknown = [c for c in channels if c not in CHANNELS]
    if unknown:
        raise ValueError(f"unknown observation channel(s) {unknown}; known: {sorted(CHANNELS)}")
    fields: list[str] = []
    for c in channels:
        if CHANNELS[c][0] not in fields:
            fields.append(CHANNELS[c][0])
    return [*fields, "actions"]


def _plain(x: Any) -> Any:
    if isinstance(x, Mapping):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)) or (hasattr(x, "__iter__") and not isinstance(x, (str, bytes))):
        return [_plain(v) for v in x]
    return x


@dataclass(frozen=True)
class Modality:
    """A validated modality.

    ``pathways``: ``((name, (channel, ...)), ...)``; one pathway ``main`` over every
    channel for ``single`` / ``early`` fusion; for ``late`` fusion the yaml's ``pathways``
    mapping, which must partition the channels into at least two groups.
    """

    name: str
    channels: tuple[str, ...]
    fusion: str
    pathways: tuple[tuple[str, tuple[str, ...]], ...]
    label: str = ""

    @classmethod
    def from_config(cls, cfg: Any) -> "Modality":
        """From a modality yaml (mapping with ``name``, ``channels``, ``fusion`` and, for
        late fusion, ``pathways``; extra keys such as ``module`` are ignored) or a Modality."""
        if isinstance(cfg, Modality):
            return cfg
        if not isinstance(cfg, Mapping):
            raise TypeError(f"a modality is a mapping (configs/modality/*.yaml), got {type(cfg).__name__}: {cfg!r}")
        cfg = _plain(cfg)
        missing = [k for k in ("name", "channels", "fusion") if k not in cfg]
        if missing:
            raise ValueError(f"modality config is missing {missing}: {cfg}")
        name = str(cfg["name"])
        channels = tuple(str(c) for c in cfg["channels"])
        if not channels or len(set(channels)) != len(channels):
            raise ValueError(f"modality {name!r}: channels must be non-empty and unique, got {list(channels)}")
        unknown = [c for c in channels if c not in CHANNELS]
        if unknown:
            raise ValueError(f"modality {name!r}: unknown channel(s) {unknown}; known: {sorted(CHANNELS)}")
        fusion = str(cfg["fusion"])
        if fusion not in FUSIONS:
            raise ValueError(f"modality {name!r}: fusion must be one of {FUSIONS}, got {fusion!r}")
        groups = cfg.get("pathways")
        if fusion != "late":
            if groups:
                raise ValueError(f"modality {name!r}: pathways are only meaningful for fusion='late'")
            pathways = (("main", channels),)
        else:
            if not groups:
                raise ValueError(f"modality {name!r}: late fusion needs a 'pathways' mapping "
                                 f"(pathway name -> channels), e.g. {{vibration: [acc], force: [fsr_t, fsr_b]}}")
            pathways = tuple((str(k), tuple(str(c) for c in v)) for k, v in dict(groups).items())
            used = [c for _, chans in pathways for c in chans]
            if sorted(used) != sorted(channels) or len(used) != len(set(used)):
                raise ValueError(f"modality {name!r}: pathways {dict(pathways)} must partition channels {list(channels)}")
            if len(pathways) < 2:
                raise ValueError(f"modality {name!r}: late fusion needs >= 2 pathways, got {dict(pathways)}")
        return cls(name=name, channels=channels, fusion=fusion, pathways=pathways, label=str(cfg.get("label") or name))

    # ------------------------------------------------------------------ derived
    @property
    def fields(self) -> list[str]:
        """Cached fields this modality reads (with ``actions``)."""
        return fields_for_channels(self.channels)

    @property
    def raw_fields(self) -> list[str]:
        """Raw HDF5 datasets its channels are computed from."""
        out: list[str] = []
        for c in self.channels:
            if CHANNELS[c][2] not in out:
                out.append(CHANNELS[c][2])
        return out

    def pathway_indices(self) -> list[tuple[str, list[int]]]:
        """``[(pathway, [indices into channels]), ...]``."""
        return [(name, [self.channels.index(c) for c in chans]) for name, chans in self.pathways]

    def to_config(self) -> dict[str, Any]:
        """Plain, checkpoint-safe mapping that :meth:`from_config` reads back."""
        cfg: dict[str, Any] = {"name": self.name, "label": self.label, "channels": list(self.channels),
                               "fusion": self.fusion}
        if self.fusion == "late":
            cfg["pathways"] = {name: list(chans) for name, chans in self.pathways}
        return cfg


def _config_dir() -> "Path":
    from pathlib import Path

    from embodied_tactile.paths import config_dir

    return Path(config_dir()) / "modality"


def modality_names() -> list[str]:
    """Names of the modalities defined in ``configs/modality/``."""
    return sorted(p.stem for p in _config_dir().glob("*.yaml"))


def load_modality(name: str) -> Modality:
    """The modality ``configs/modality/<name>.yaml`` of the project checkout (the same file
    Hydra composes), e.g. for scripts and tests that name a modality outside a Hydra run."""
    import yaml

    path = _config_dir() / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"unknown modality {name!r}: no {path} (defined: {modality_names()}); "
                         "pass the modality mapping itself outside a project checkout")
    return Modality.from_config(yaml.safe_load(path.read_text()))
