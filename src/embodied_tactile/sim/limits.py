"""Limits of the simulator's physical inputs and their checks. No simulator imports, so
:mod:`.physics` (``PhysicsOverrides`` checks itself on construction) and :mod:`.validation`
(every entry point's arguments) both build on it without importing each other in a loop.
Ranges in docs/reference/simulator.md."""

from __future__ import annotations

import math
import numbers
from typing import Any

#: Quasi-static contact solve rate (= pose rate), Hz: one contact solve per physics step.
PHYSICS_RATE_HZ = 100.0
#: Contact is solved once per physics step (100 Hz), so a primitive must stay below the
#: Nyquist frequency of that step: f < PHYSICS_RATE_HZ / 2 = 50 Hz.
MAX_PRIMITIVE_FREQUENCY_HZ = PHYSICS_RATE_HZ / 2.0
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
