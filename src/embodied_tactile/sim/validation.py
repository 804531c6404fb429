"""The one place where simulator inputs are checked (ranges in docs/simulator.md).

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

#: Shortest trial: two physics (= pose) steps, so both clocks span the trial.
MIN_DURATION_S = 2.0 / P.PHYSICS_RATE_HZ
#: Longest trial: peak memory grows by about 10 MB per simulated second in each worker
#: process (about 0.5 GB at 40 s, measured), so 300 s needs about 3 GB per worker.
MAX_DURATION_S = 300.0
#: Contact is solved once per physics step (100 Hz), so a primitive must stay below the
#: Nyquist frequency of that step: f < PHYSICS_RATE_HZ / 2 = 50 Hz.
MAX_PRIMITIVE_FREQUENCY_HZ = P.PHYSICS_RATE_HZ / 2.0
#: Young's modulus override (Pa): 1 Pa is softer than any solid (the softest gels are about
#: 100 Pa), 1e12 Pa is diamond.
YOUNGS_MODULUS_RANGE_PA = (1.0, 1e12)
#: Surface peak-to-peak override: 5x the largest catalogue amplitude (20 mm). It bounds the
#: penetration, hence the contact forces (measured: at most about 9 N per taxel at 100 mm,
#: E = 1e12 Pa, instantaneous modulus), which MAX_FORCE_SCALE relies on.
MAX_AMPLITUDE_MM = 100.0
#: Coulomb coefficient: elastomers on rough surfaces reach about 1-4; larger values only
#: saturate the shear (tanh) and clip the accelerometers.
MAX_FRICTION = 10.0
#: FSR forces are float32 (max 3.4e38): with per-taxel forces below about 10 N (see
#: MAX_AMPLITUDE_MM) a multiplier up to 1e30 keeps every scaled force finite.
MAX_FORCE_SCALE = 1e30


class SimParameterError(ValueError):
    """An invalid simulator input. Names the parameter, the value and the allowed range."""

    def __init__(self, parameter: str, value: Any, allowed: str):
        self.parameter = parameter
        self.value = value
        self.allowed = allowed
        super().__init__(f"invalid simulator parameter {parameter}={value!r}: allowed {allowed}")

    def __reduce__(self):  # picklable across process pools
        return (type(self), (self.parameter, self.value, self.allowed))


def _real(name: str, value: Any, allowed: str) -> float:
    """``value`` as a finite float (bools and strings refused)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(float(value)):
        raise SimParameterError(name, value, allowed)
    return float(value)


def check_range(name: str, value: Any, lo: float | None = None, hi: float | None = None, *,
                lo_open: bool = False, hi_open: bool = False) -> float:
    """``value`` as a finite float within [lo, hi] (an open end with ``lo_open`` / ``hi_open``)."""
    lo_s = "-inf" if lo is None else f"{lo:g}"
    hi_s = "inf" if hi is None else f"{hi:g}"
    allowed = f"a finite number in {'(' if lo_open or lo is None else '['}{lo_s}, {hi_s}{')' if hi_open or hi is None else ']'}"
    v = _real(name, value, allowed)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise SimParameterError(name, value, allowed)
    if hi is not None and (v > hi or (hi_open and v == hi)):
        raise SimParameterError(name, value, allowed)
    return v


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


def check_physics(ph: Any) -> None:
    """Check every field of a :class:`~embodied_tactile.sim.physics.PhysicsOverrides`."""
    if ph.youngs_modulus is not None:
        check_range("physics.youngs_modulus", ph.youngs_modulus, *YOUNGS_MODULUS_RANGE_PA)
    if ph.relaxation_time is not None:
        check_range("physics.relaxation_time", ph.relaxation_time, 0.0, lo_open=True)
    if ph.amplitude_mm is not None:
        check_range("physics.amplitude_mm", ph.amplitude_mm, 0.0, MAX_AMPLITUDE_MM)
    if ph.primitive_frequency_hz is not None:
        check_range("physics.primitive_frequency_hz", ph.primitive_frequency_hz, 0.0, MAX_PRIMITIVE_FREQUENCY_HZ,
                    lo_open=True, hi_open=True)
    if not isinstance(ph.lift_off, bool):
        raise SimParameterError("physics.lift_off", ph.lift_off, "true or false")
    check_range("physics.force_scale", ph.force_scale, 0.0, MAX_FORCE_SCALE, lo_open=True)
    if ph.friction is not None:
        check_range("physics.friction", ph.friction, 0.0, MAX_FRICTION)


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
    (the ranges of docs/simulator.md; the same modulus range as the overrides)."""
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
