"""The one place where simulator inputs are checked (ranges in docs/reference/simulator.md).

Every public entry point (``PhysicsOverrides``, ``simulate_trial``, ``force_indentation``,
``generate_dataset``, the ``simulate`` CLI) goes through these functions before any
physics runs or any file is touched. A bad value raises :class:`SimParameterError`,
which names the parameter, the value and the allowed range.
"""

from __future__ import annotations

import math
import numbers
from typing import Any, Iterable, Mapping

from embodied_tactile import constants as C
from embodied_tactile.sim import physics as P
from embodied_tactile.sim.limits import (MAX_AMPLITUDE_MM, MAX_FORCE_SCALE, MAX_FRICTION,  # noqa: F401 (re-exported)
                                         MAX_PRIMITIVE_FREQUENCY_HZ, YOUNGS_MODULUS_RANGE_PA, SimParameterError,
                                         check_physics, check_range)

#: Shortest trial: two physics (= pose) steps, so both clocks span the trial.
MIN_DURATION_S = 2.0 / P.PHYSICS_RATE_HZ
#: Longest trial: peak memory grows by about 10 MB per simulated second in each worker
#: process (about 0.5 GB at 40 s, measured), so 300 s needs about 3 GB per worker.
MAX_DURATION_S = 300.0
def check_int(name: str, value: Any, lo: int, hi: int | None = None) -> int:
    """``value`` as an integer within lo..hi (integral floats such as 3.0 are accepted)."""
    allowed = f"an integer in {lo}..{hi}" if hi is not None else f"an integer >= {lo}"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise SimParameterError(name, value, allowed)
    if not math.isfinite(float(value)) or float(value) != int(value):
        raise SimParameterError(name, value, allowed)
    v = int(value)
    if v < lo or (hi is not None and v > hi):
        raise SimParameterError(name, value, allowed)
    return v


def check_choice(name: str, value: Any, choices: Iterable[str]) -> str:
    choices = tuple(choices)
    if not isinstance(value, str) or value not in choices:
        raise SimParameterError(name, value, f"one of {', '.join(choices)}")
    return value


def physics_overrides(values: Mapping[str, Any] | None) -> Any:
    """A validated ``PhysicsOverrides`` from a mapping (the CLI's ``physics.*`` keys);
    an unknown key is a :class:`SimParameterError` too."""
    from dataclasses import fields

    if not values:
        return None
    known = [f.name for f in fields(P.PhysicsOverrides)]
    for key, value in values.items():
        if key not in known:
            raise SimParameterError(f"physics.{key}", value, f"a known override ({', '.join(known)})")
    return P.PhysicsOverrides(**values)


def check_trial(object_id: Any, skin: Any, primitive: Any, action_index: Any, repetition: Any, seed: Any,
                duration: Any, physics: Any) -> None:
    """Check the arguments of one simulated trial (``physics`` may be None; ``object_id`` a
    catalogue id or a ``WaveObject``)."""
    check_object(object_id)
    check_choice("skin", skin, C.SKINS)
    check_choice("primitive", primitive, C.PRIMITIVES)
    check_int("action_index", action_index, 0, C.N_ACTIONS - 1)
    check_int("repetition", repetition, 0)
    check_int("seed", seed, 0)
    check_duration(duration)
    check_overrides(physics)


def check_object(obj: Any) -> None:
    """A catalogue id, or a ``WaveObject`` whose geometry and materials the simulator accepts
    (the ranges of docs/reference/simulator.md; the same modulus range as the overrides)."""
    if not isinstance(obj, C.WaveObject):
        check_int("object_id", obj, 0, C.N_OBJECTS - 1)
        return
    check_int("object.object_id", obj.object_id, 0)
    check_range("object.spatial_frequency", obj.spatial_frequency, 0.0, 1.0 / (2 * P.SURFACE_DX_M), lo_open=True)
    check_range("object.amplitude_mm", obj.amplitude_mm, 0.0, 100.0, lo_open=True)
    layers = [("bulk", obj.bulk)] + ([("top_layer", obj.top_layer)] if obj.top_layer is not None else [])
    for name, key in layers:
        if isinstance(key, str):
            check_choice(f"object.{name}", key, C.MATERIALS)
        mat = C.material(key)
        check_range(f"object.{name}.youngs_modulus", mat.youngs_modulus, *YOUNGS_MODULUS_RANGE_PA)
        check_range(f"object.{name}.relaxation_strength", mat.relaxation_strength, 0.0, 10.0)
        check_range(f"object.{name}.relaxation_time", mat.relaxation_time, 0.0, lo_open=True)
        check_range(f"object.{name}.friction", mat.friction, 0.0, 10.0)
    if obj.top_layer is not None:
        check_range("object.top_thickness_mm", obj.top_thickness_mm, 0.0, 20.0, lo_open=True)


def check_overrides(physics: Any) -> None:
    """``physics`` is None or a valid ``PhysicsOverrides``."""
    if physics is not None:
        if not isinstance(physics, P.PhysicsOverrides):
            raise SimParameterError("physics", physics, "a PhysicsOverrides or None")
        check_physics(physics)


def check_duration(duration: Any) -> float:
    return check_range("duration", duration, MIN_DURATION_S, MAX_DURATION_S)
