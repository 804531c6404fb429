"""Every simulator input is checked at its boundary.

An invalid value raises SimParameterError (a ValueError) naming the parameter, the value
and the allowed range; the CLI exits 2 with one line on stderr and writes nothing; the
quantisation step never turns a non-finite value into an ADC count.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from embodied_tactile import constants as C
from embodied_tactile.sim import PhysicsOverrides, SimParameterError, force_indentation, generate_dataset, simulate_trial
from embodied_tactile.sim import validation as V
from embodied_tactile.sim.trial import quantise
from embodied_tactile.sim.simulate import main as simulate_main

NAN, INF = float("nan"), float("inf")

#: (override, bad value): every PhysicsOverrides field, each way it can be wrong.
BAD_PHYSICS = [
    ("youngs_modulus", -1e5), ("youngs_modulus", 0.0), ("youngs_modulus", 0.5), ("youngs_modulus", 1e13),
    ("youngs_modulus", NAN), ("youngs_modulus", INF), ("youngs_modulus", "3e4"),
    ("relaxation_time", 0.0), ("relaxation_time", -1.0), ("relaxation_time", NAN), ("relaxation_time", INF),
    ("amplitude_mm", -1.0), ("amplitude_mm", 101.0), ("amplitude_mm", NAN),
    ("primitive_frequency_hz", 0.0), ("primitive_frequency_hz", -0.5), ("primitive_frequency_hz", 50.0),
    ("primitive_frequency_hz", 1e3), ("primitive_frequency_hz", NAN),
    ("force_scale", -1.0), ("force_scale", 0.0), ("force_scale", 1e31), ("force_scale", NAN), ("force_scale", INF),
    ("friction", -0.1), ("friction", 11.0), ("friction", NAN),
    ("lift_off", "yes"), ("lift_off", 1),
]


def _named(exc: SimParameterError, parameter: str, value) -> None:
    msg = str(exc)
    assert isinstance(exc, ValueError)
    assert exc.parameter == parameter and parameter in msg
    assert repr(value) in msg, msg  # the value as given
    assert "allowed" in msg and exc.allowed in msg


@pytest.mark.parametrize("field,value", BAD_PHYSICS, ids=[f"{f}={v!r}" for f, v in BAD_PHYSICS])
def test_bad_physics_override_is_named(field, value):
    with pytest.raises(SimParameterError) as info:
        PhysicsOverrides(**{field: value})
    _named(info.value, f"physics.{field}", value)


#: (argument, bad value) of simulate_trial.
BAD_TRIAL = [
    ("duration", 0.0), ("duration", -1.0), ("duration", NAN), ("duration", INF),
    ("duration", 0.5 * V.MIN_DURATION_S), ("duration", V.MAX_DURATION_S + 1),
    ("object_id", C.N_OBJECTS), ("object_id", -1), ("object_id", 1.5),
    ("skin", "medium"), ("primitive", "poking"),
    ("action_index", C.N_ACTIONS), ("action_index", -1),
    ("repetition", -1), ("seed", -1), ("seed", 0.5),
    ("physics", {"force_scale": 2.0}),
]


@pytest.mark.parametrize("arg,value", BAD_TRIAL, ids=[f"{a}={v!r}" for a, v in BAD_TRIAL])
def test_bad_trial_argument_is_named(arg, value):
    kw = dict(object_id=0, skin="soft", primitive="pressing", action_index=0, repetition=0, seed=0, duration=0.5)
    kw[arg] = value
    with pytest.raises(SimParameterError) as info:
        simulate_trial(**kw)
    _named(info.value, arg, value)


def test_every_override_field_is_covered():
    """A new PhysicsOverrides field must get its range check (and a bad case above)."""
    from dataclasses import fields

    assert {f.name for f in fields(PhysicsOverrides)} == {f for f, _ in BAD_PHYSICS}


def test_force_indentation_checks_its_arguments():
    with pytest.raises(SimParameterError, match="object_id=99"):
        force_indentation(99, "soft", np.array([1e-3]))
    with pytest.raises(SimParameterError, match="skin='medium'"):
        force_indentation(0, "medium", np.array([1e-3]))


@pytest.mark.parametrize("kw,parameter", [
    (dict(duration=0.0), "duration"), (dict(objects=[0, 32]), "objects[1]"), (dict(actions=[]), "actions"),
    (dict(repetitions=0), "repetitions"), (dict(workers=-1), "workers"), (dict(seed=-3), "seed"),
    (dict(physics={"friction": 0.3}), "physics"),
])
def test_generate_dataset_checks_before_touching_the_file(tmp_path, kw, parameter):
    path = tmp_path / "raw.h5"
    args = dict(skin="soft", primitive="pressing", objects=[0], actions=[0], duration=0.5, workers=1)
    args.update(kw)
    with pytest.raises(SimParameterError) as info:
        generate_dataset(path, **args)
    assert info.value.parameter == parameter
    assert not path.exists()


def test_valid_edges_are_accepted():
    """The ends of each allowed range are simulator inputs like any other."""
    PhysicsOverrides(youngs_modulus=V.YOUNGS_MODULUS_RANGE_PA[0], relaxation_time=1e-300, amplitude_mm=0.0,
                     primitive_frequency_hz=math.nextafter(V.MAX_PRIMITIVE_FREQUENCY_HZ, 0.0),
                     force_scale=V.MAX_FORCE_SCALE, friction=0.0)
    PhysicsOverrides(youngs_modulus=V.YOUNGS_MODULUS_RANGE_PA[1], amplitude_mm=V.MAX_AMPLITUDE_MM,
                     friction=V.MAX_FRICTION, force_scale=1e-300, primitive_frequency_hz=1e-6)
    assert V.check_duration(V.MIN_DURATION_S) == V.MIN_DURATION_S
    assert V.MAX_PRIMITIVE_FREQUENCY_HZ == 50.0  # Nyquist of the 100 Hz physics step


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_quantisation_refuses_non_finite(bad, dtype):
    x = np.array([[1.2, 4100.0], [bad, 7.6]], dtype=dtype)
    with pytest.raises(FloatingPointError) as info:
        quantise(x, 0, C.FSR_MAX_COUNT, trial="obj00_soft_pressing_a00_r00", field="tactile/fsr")
    msg = str(info.value)
    assert "obj00_soft_pressing_a00_r00" in msg and "tactile/fsr" in msg and "(1, 0)" in msg
    ok = quantise(np.array([1.2, 4100.0, -3.0, 7.6], dtype=dtype), 0, C.FSR_MAX_COUNT, trial="t", field="f")
    np.testing.assert_array_equal(ok, [1.0, 4095.0, 0.0, 8.0])


# --------------------------------------------------------------------------- CLI
def test_cli_in_process_exit_2_for_every_bad_physics(tmp_path, capsys):
    out = tmp_path / "x.h5"
    for field, value in BAD_PHYSICS:
        if isinstance(value, str) or (isinstance(value, float) and not math.isfinite(value)):
            continue  # dotlist spelling differs; test_cli_exits_2_with_one_line covers NaN
        rc = simulate_main([f"out={out}", "objects=[0]", "actions=[0]", "duration=0.5", "workers=1",
                            f"physics.{field}={str(value).lower()}"])
        err = capsys.readouterr().err.strip()
        assert rc == 2, (field, value)
        assert len(err.splitlines()) == 1 and f"physics.{field}=" in err, err
        assert not out.exists()


@pytest.mark.parametrize("arg,name", [
    ("physics.youngs_modulus=-1e5", "physics.youngs_modulus"),
    ("physics.relaxation_time=.nan", "physics.relaxation_time"),
    ("duration=0", "duration"),
    ("physics.primitive_frequency_hz=60", "physics.primitive_frequency_hz"),
])
def test_cli_exits_2_with_one_line(tmp_path, capsys, arg, name):
    """The command's arguments as typed (``python -m embodied_tactile.sim.simulate ...``: its
    main in this process; test_simulator's CLI test starts it in a subprocess)."""
    out = tmp_path / "cli.h5"
    capsys.readouterr()
    rc = simulate_main([f"out={out}", "objects=[0]", "actions=[0]", "duration=0.5", "workers=1", arg])
    err = capsys.readouterr().err
    assert rc == 2, (rc, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and name in lines[0] and "allowed" in lines[0], err
    assert not out.exists()
