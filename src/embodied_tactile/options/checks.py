"""The bounds of typed options and the one checker that reads them (no heavy imports).

An option's bounds are its dataclass field's metadata (:func:`bounds`: ``field(default=1,
metadata=at_least(1))``, :func:`one_of` for a closed set); a bound between two fields is the
class's ``RULES``.
:func:`check_options` checks a config node against a dataclass: each present field's value
by the field's type (``Optional`` allows null, a ``Union`` any of its types, ``Any`` / a
dict anything) and bounds, nested option groups included, then the ``RULES``; the first
value that cannot work raises :class:`SettingsError` naming the key, the value and what is
allowed.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any


class SettingsError(ValueError):
    """A config value that cannot work; the message names key, value and what is allowed."""


def bounds(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
           hi_open: bool = False) -> dict[str, Any]:
    """Field metadata: the value lies in [lo, hi] (open ends with ``lo_open`` / ``hi_open``)."""
    return {"bounds": (lo, hi, lo_open, hi_open)}


def at_least(lo: float) -> dict[str, Any]:
    """Field metadata: the value is >= ``lo``."""
    return bounds(lo)


def one_of(*values: Any) -> dict[str, Any]:
    """Field metadata: the value is one of ``values`` (a list field: each of its items is)."""
    return {"choices": tuple(values)}


#: a bound between two fields: (field a, field b, test of (a, b), what is allowed)
Rule = tuple[str, str, Callable[[Any, Any], bool], str]


@dataclass(frozen=True)
class Spec:
    """Allowed values of one key: ``kinds`` among 'int', 'float', 'bool', 'str', 'list'
    (an int is accepted where a float is), optional bounds (inclusive unless ``lo_open`` /
    ``hi_open``) or ``choices``, None allowed or not."""

    kinds: tuple[str, ...]
    lo: float | None = None
    hi: float | None = None
    nullable: bool = False
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[Any, ...] | None = None

    def describe(self) -> str:
        names = {"int": "an integer", "float": "a number", "bool": "true/false", "str": "a string", "list": "a list"}
        if self.choices is not None:
            what = "a list of " if self.kinds == ("list",) else "one of "
            return what + ", ".join(map(str, self.choices)) + (" or null" if self.nullable else "")
        s = " or ".join(names[k] for k in self.kinds)
        if self.lo is not None and self.hi is not None:
            s += f" in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"
        elif self.lo is not None:
            s += f" {'>' if self.lo_open else '>='} {self.lo:g}"
        return s + (" or null" if self.nullable else "")

    def _choice(self, v: Any) -> bool:
        return v in self.choices and type(v) in {type(c) for c in self.choices}

    def accepts(self, v: Any) -> bool:
        if v is None:
            return self.nullable
        if self.choices is not None:
            if self.kinds == ("list",):  # a list whose every item is a choice
                return isinstance(v, (list, tuple)) and all(self._choice(x) for x in v)
            return self._choice(v)
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


_KINDS = {int: "int", float: "float", bool: "bool", str: "str", list: "list", tuple: "list"}
_ORDER = ("int", "float", "bool", "str", "list")


def _types(hint: Any) -> tuple[list[Any], bool]:
    """(the types a hint allows, None allowed)."""
    args = typing.get_args(hint) if typing.get_origin(hint) is typing.Union else (hint,)
    return [a for a in args if a is not type(None)], type(None) in args


def field_spec(hint: Any, metadata: Mapping[str, Any]) -> Spec | None:
    """The :class:`Spec` of a field of type ``hint`` with ``metadata`` (None: not checked, e.g.
    ``Any``, a dict, a nested option group)."""
    types, nullable = _types(hint)
    kinds = []
    for t in types:
        kind = _KINDS.get(typing.get_origin(t) or t)
        if kind is None:
            return None
        kinds.append(kind)
    lo, hi, lo_open, hi_open = metadata.get("bounds", (None, None, False, False))
    # one order whatever the Union's (typing caches Union[int, float] and Union[float, int] as one)
    kinds = sorted(set(kinds), key=_ORDER.index)
    choices = metadata.get("choices")
    return Spec(tuple(kinds), lo=lo, hi=hi, nullable=nullable, lo_open=lo_open, hi_open=hi_open,
                choices=None if choices is None else tuple(choices))


def _option_group(hint: Any) -> type | None:
    types, _ = _types(hint)
    return types[0] if len(types) == 1 and dataclasses.is_dataclass(types[0]) else None


#: what :func:`_get` returns for a mandatory value not given (``???`` in the config)
MISSING_VALUE = object()


def _get(node: Any, name: str) -> tuple[bool, Any]:
    """(present, value) of ``node[name]``, interpolations resolved where they can be (a value
    that resolves only inside a Hydra job, e.g. ``${hydra:...}``, is reported absent)."""
    from omegaconf import DictConfig, OmegaConf

    if isinstance(node, DictConfig):
        if name in node.keys() and OmegaConf.is_missing(node, name):  # `in node` is False for ???
            return True, MISSING_VALUE
        if name not in node:
            return False, None
        try:
            value = node[name]
        except Exception:  # unresolvable outside the job
            return False, None
        if OmegaConf.is_config(value) and not isinstance(value, DictConfig):
            try:
                value = OmegaConf.to_container(value, resolve=True)
            except Exception:
                return False, None
        return True, value
    if isinstance(node, Mapping):
        return (name in node), node.get(name)
    return False, None


def check_options(cls: type, node: Any, prefix: str) -> None:
    """Check ``node`` (a config node or a mapping; absent keys are not checked) against the
    option dataclass ``cls``; :class:`SettingsError` naming ``<prefix>.<key>`` for the first
    value that cannot work."""
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        present, v = _get(node, f.name)
        if not present or f.name.startswith("_"):
            continue
        key = f"{prefix}.{f.name}" if prefix else f.name
        if v is MISSING_VALUE:
            raise SettingsError(f"{key} has no value (??? in its config): give one on the command line "
                                f"({key}=...) or choose a group that sets it")
        group = _option_group(hints[f.name])
        if group is not None and v is not None and not isinstance(v, (str, int, float, bool, list)):
            check_options(group, v, key)
            continue
        spec = field_spec(hints[f.name], f.metadata)
        if spec is not None and not spec.accepts(v):
            raise SettingsError(f"{key}={v!r} ({type(v).__name__}): expected {spec.describe()}")
        values[f.name] = v
    for a, b, ok, rule in getattr(cls, "RULES", ()):
        va, vb = values.get(a), values.get(b)
        if va is not None and vb is not None and not ok(va, vb):
            pa, pb = (f"{prefix}.{k}" if prefix else k for k in (a, b))
            raise SettingsError(f"{pa}={va!r} and {pb}={vb!r}: expected {rule}")


__all__ = ["Rule", "SettingsError", "Spec", "at_least", "bounds", "check_options", "field_spec", "one_of"]
