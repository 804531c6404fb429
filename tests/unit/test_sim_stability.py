"""Numerical stability of the simulator over extreme physics (>= 200 short trials)."""

from __future__ import annotations

import itertools
import warnings

import numpy as np
import pytest

from embodied_tactile import constants as C
from embodied_tactile.sim import PhysicsOverrides, contact_pressure, mechanics, qlv_relax, simulate_trial
from embodied_tactile.sim import validation as V

E_GRID = (1e3, 1e5, 3e7, 1e9, 1e10)  # Pa
TAU_GRID = (1e-5, 1e-2, 1.0, 100.0)  # s
AMP_GRID = (0.0, 15.0, 30.0)  # mm peak-to-peak
FREQ_GRID = (0.01, 0.7, 2.0)  # Hz (> 0: a frequency of 0 is refused; 0.01 Hz holds still over 0.5 s)


def _cases():
    cases = []
    for i, (e, tau, amp, w) in enumerate(itertools.product(E_GRID, TAU_GRID, AMP_GRID, FREQ_GRID)):
        prim = C.PRIMITIVES[i % 3]
        cases.append((i % 32, C.SKINS[(i // 3) % 2], prim, (7 * i) % 16,
                      PhysicsOverrides(youngs_modulus=e, relaxation_time=tau, amplitude_mm=amp,
                                       primitive_frequency_hz=w, lift_off=(i % 5 == 0))))
    for j, (prim, skin, lift, scale) in enumerate(itertools.product(C.PRIMITIVES, C.SKINS, (False, True), (1e-6, 1e6))):
        cases.append((27 + j % 5, skin, prim, 15, PhysicsOverrides(lift_off=lift, force_scale=scale, relaxation_time=1e-5 if j % 2 else 100.0)))
    return cases


CASES = _cases()


def test_grid_is_large_enough():
    assert len(CASES) >= 200


def _check(tr):
    assert np.isfinite(tr.acc).all() and np.isfinite(tr.t).all() and np.isfinite(tr.pose).all()
    assert tr.fsr.dtype == np.uint16 and int(tr.fsr.max()) <= C.FSR_MAX_COUNT
    assert float(np.abs(tr.acc).max()) <= C.ACC_RANGE_G
    assert np.all(np.diff(tr.t) > 0) and np.all(np.diff(tr.pose_t) > 0)


@pytest.mark.filterwarnings("error")
@pytest.mark.slow
def test_extreme_grid_finite_and_in_range():
    saturated = 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with np.errstate(divide="raise", over="raise", invalid="raise"):
            for oid, skin, prim, act, phys in CASES:
                tr = simulate_trial(oid, skin, prim, act, duration=0.5, physics=phys)
                _check(tr)
                saturated += int((tr.fsr == C.FSR_MAX_COUNT).any())
    assert saturated >= 6  # the force_scale=1e6 cases really saturate


#: The ends of the allowed ranges (sim/validation.py, docs/reference/simulator.md), combined so that the
#: largest forces (stiffest object, deepest surface, largest scale) meet.
EDGES = [
    PhysicsOverrides(youngs_modulus=V.YOUNGS_MODULUS_RANGE_PA[0], amplitude_mm=V.MAX_AMPLITUDE_MM, relaxation_time=1e-300),
    PhysicsOverrides(youngs_modulus=V.YOUNGS_MODULUS_RANGE_PA[1], amplitude_mm=V.MAX_AMPLITUDE_MM, relaxation_time=1e300,
                     force_scale=V.MAX_FORCE_SCALE, friction=V.MAX_FRICTION),
    PhysicsOverrides(primitive_frequency_hz=0.999 * V.MAX_PRIMITIVE_FREQUENCY_HZ, friction=V.MAX_FRICTION, force_scale=1e-300),
    PhysicsOverrides(primitive_frequency_hz=1e-6, amplitude_mm=0.0, friction=0.0, lift_off=True),
]


@pytest.mark.filterwarnings("error")
def test_allowed_range_edges_finite_and_in_range():
    with np.errstate(divide="raise", over="raise", invalid="raise"):
        for k, phys in enumerate(EDGES):
            for prim in C.PRIMITIVES:
                for oid, skin in ((6, "hard"), (27, "soft")):
                    _check(simulate_trial(oid, skin, prim, 15, duration=0.5, physics=phys))
            _check(simulate_trial(8, C.SKINS[k % 2], C.PRIMITIVES[k % 3], k, duration=V.MIN_DURATION_S, physics=phys))


@pytest.mark.filterwarnings("error")
def test_qlv_update_is_stable_for_any_tau():
    rng = np.random.default_rng(0)
    p = np.abs(np.cumsum(rng.standard_normal((500, 8)), axis=0)) * 1e3
    with np.errstate(divide="raise", over="raise", invalid="raise"):
        for tau in (1e-9, 1e-5, 1e-3, 1.0, 100.0, 1e6):
            out = qlv_relax(p, 1.0 / 100.0, [(0.5, tau), (3.0, tau * 7)])
            assert np.isfinite(out).all() and (out >= 0).all()
            # bounded by the instantaneous-modulus response
            assert out.max() <= (1 + 0.5 + 3.0) * p.max() * 1.0001
    # tau -> 0: relaxed response; tau -> inf: instantaneous (elastic with E0) increments
    fast = qlv_relax(p, 0.01, [(0.5, 1e-9)])
    np.testing.assert_allclose(fast, p, rtol=1e-6, atol=1e-6 * p.max())


@pytest.mark.filterwarnings("error")
def test_contact_law_finite_over_extremes():
    d = np.r_[-1.0, 0.0, np.logspace(-9, -1, 50)]
    for e in (1e3, 1e10):
        for skin in C.SKINS:
            for oid in (0, 27):
                m = mechanics(C.get_object(oid), skin, PhysicsOverrides(youngs_modulus=e))
                p = contact_pressure(m, d)
                assert np.isfinite(p).all() and (p >= 0).all() and p[0] == 0 and p[1] == 0
                assert np.all(np.diff(p[2:]) > 0)  # monotone in indentation


@pytest.mark.filterwarnings("error")
def test_contact_front_finite_on_stiff_and_extreme_cases():
    from embodied_tactile.sim import physics as P

    with np.errstate(divide="raise", over="raise", invalid="raise"):
        shares = [P.local_skin_share(mechanics(C.get_object(oid), skin, PhysicsOverrides(youngs_modulus=e)))
                  for e in (V.YOUNGS_MODULUS_RANGE_PA[0], 1e5, V.YOUNGS_MODULUS_RANGE_PA[1]) for skin in C.SKINS for oid in (0, 6)]
        assert all(0.0 < s <= 1.0 for s in shares) and max(shares) > 0.999 and min(shares) < 1e-4
        # a fast, deep press (2 m/s: far beyond any action) on a fully stiff surface: every
        # sample crosses terraces; the kicks stay finite and bounded by share v dz dens / dt
        rng = np.random.default_rng(1)
        z = np.cumsum(rng.uniform(-2.0, 2.0, (700, 16)) / 700, axis=0)
        dens = P.front_density(rng.normal(0, 1e-3, (700, 16, 64)))
        acc = P.front_acceleration(z, dens, 1.0, 1 / 700)
        bound = 2.0 * (np.abs(np.diff(np.floor(z / P.LAYER_HEIGHT_M), axis=0)).max() + 1) * P.LAYER_HEIGHT_M * dens.max() * 700
        assert np.isfinite(acc).all() and np.abs(acc).max() <= bound
        # PLA at the largest amplitude with the hard skin (share 1, 317 Hz node): in range
        for prim in C.PRIMITIVES:
            tr = simulate_trial(6, "hard", prim, 15, duration=1.0, physics=PhysicsOverrides(amplitude_mm=V.MAX_AMPLITUDE_MM))
            _check(tr)


def test_continuity_without_lift_off():
    tr = simulate_trial(4, "soft", "pressing", 15, duration=2.0, physics=PhysicsOverrides(relaxation_time=1e-5))
    total = tr.fsr.astype(np.float64).sum(axis=(2, 3))[:, 0]
    # no jumps beyond what 2 Hz motion + noise can produce between 1.4 ms samples
    assert np.abs(np.diff(total)).max() < 0.05 * (total.max() - total.min()) + 200
