"""Physics and format tests of the palpation simulator (CPU, short trials)."""

from __future__ import annotations

import logging
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
from scipy import signal

from embodied_tactile import constants as C
from embodied_tactile.data.rawformat import read_trial, scan_raw
from embodied_tactile.sim import (
    PhysicsOverrides,
    contact_pressure,
    force_indentation,
    generate_dataset,
    mechanics,
    simulate_trial,
)
from embodied_tactile.sim import objects as O
from embodied_tactile.sim.dataset import PENDING_ATTR, OutputFileError

SLIDE_FAST = 15  # A_xy 8 mm, A_gamma 6 deg, 0.8 Hz
PRESS_DEEP = 15  # A_z 8 mm, 0.8 Hz


def hf_energy(trial, f_lo: float = 30.0) -> float:
    """Mean power (g^2) of all accelerometer channels above f_lo Hz."""
    a = trial.acc.reshape(len(trial.t), -1).astype(np.float64)
    b, a_ = signal.butter(4, f_lo, "high", fs=C.FS_TACTILE)
    return float((signal.filtfilt(b, a_, a - a.mean(0), axis=0) ** 2).mean())


def fsr_minus_offset(trial) -> np.ndarray:
    return np.clip(trial.fsr.astype(np.float64) - 5.0, 0.0, None)


def mean_maps(trial, block: int = 35) -> np.ndarray:
    """Offset-subtracted FSR maps averaged over blocks of samples (20 Hz; averages out the
    white ADC noise, keeps the spatial structure). (N / block, 2, 16, 16)."""
    f = fsr_minus_offset(trial)
    n = (len(f) // block) * block
    return f[:n].reshape(-1, block, *f.shape[1:]).mean(axis=1)


def map_roughness(m: np.ndarray) -> float:
    """Discrete-Laplacian energy of maps (N, 16, 16) relative to their energy."""
    lap = m[:, 1:-1, 1:-1] * 4 - m[:, 2:, 1:-1] - m[:, :-2, 1:-1] - m[:, 1:-1, 2:] - m[:, 1:-1, :-2]
    return float((lap**2).sum() / (m**2).sum())


# --------------------------------------------------------------------------- format
def test_full_trial_shapes_ranges_and_clock():
    tr = simulate_trial(5, "soft", "precession", 3)
    assert tr.t.shape == (C.N_TACTILE,) and tr.t.dtype == np.float64
    assert tr.acc.shape == (C.N_TACTILE, 4, 4, 3) and tr.acc.dtype == np.float32
    assert tr.fsr.shape == (C.N_TACTILE, 2, 16, 16) and tr.fsr.dtype == np.uint16
    assert tr.pose_t.shape == (C.N_POSE,) and tr.pose.shape == (C.N_POSE, 6) and tr.pose.dtype == np.float32
    assert np.all(np.diff(tr.t) > 0) and np.all(np.diff(tr.pose_t) > 0)
    assert abs(tr.t[-1] - tr.pose_t[-1]) < 0.02  # one clock
    assert tr.fsr.max() <= C.FSR_MAX_COUNT and np.abs(tr.acc).max() <= C.ACC_RANGE_G
    # quantised to 1/16384 g; gravity on the skin-normal axis; a noise floor of a few mg
    assert np.allclose(tr.acc * C.ACC_COUNTS_PER_G, np.rint(tr.acc * C.ACC_COUNTS_PER_G))
    assert 0.95 < tr.acc[..., 2].mean() < 1.05 and abs(tr.acc[..., 0].mean()) < 0.1
    # 1e-3 Hz: the robot holds still over 1 s (a frequency of 0 is refused)
    still = simulate_trial(5, "soft", "pressing", 0, duration=1.0, physics=PhysicsOverrides(primitive_frequency_hz=1e-3))
    noise = still.acc[..., 2].astype(np.float64) - still.acc[..., 2].mean(0)
    assert 0.001 < noise.std() < 0.01
    # precession: commanded roll follows A sin(2 pi w t + pi/2), i.e. starts at +A
    amp = np.deg2rad(C.get_action("precession", 3).params["A_alpha_beta_deg"])
    assert tr.pose[0, 3] == pytest.approx(amp, abs=2e-3)
    assert attrs_ok(tr.attrs)


def attrs_ok(attrs) -> bool:
    from embodied_tactile.sim.physics import PHYSICS_VERSION

    return (attrs["source"] == "simulated" and attrs["object_id"] == 5 and attrs["skin"] == "soft"
            and attrs["sim_physics_version"] == PHYSICS_VERSION)


def test_determinism_and_independent_streams():
    a = simulate_trial(12, "hard", "sliding", 7, repetition=0, seed=3, duration=1.0)
    b = simulate_trial(12, "hard", "sliding", 7, repetition=0, seed=3, duration=1.0)
    c = simulate_trial(12, "hard", "sliding", 7, repetition=1, seed=3, duration=1.0)
    d = simulate_trial(12, "hard", "sliding", 7, repetition=0, seed=4, duration=1.0)
    for f in ("t", "acc", "fsr", "pose_t", "pose"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert not np.array_equal(a.fsr, c.fsr) and not np.array_equal(a.acc, c.acc)
    assert not np.array_equal(a.acc, d.acc)
    # noise (and placement / tracking error) differ, the physics does not: trials stay correlated
    a = simulate_trial(12, "hard", "pressing", PRESS_DEEP, repetition=0, seed=3, duration=2.0)
    c = simulate_trial(12, "hard", "pressing", PRESS_DEEP, repetition=1, seed=3, duration=2.0)
    ta, tc = fsr_minus_offset(a).sum(axis=(2, 3))[:, 0], fsr_minus_offset(c).sum(axis=(2, 3))[:, 0]
    assert np.corrcoef(ta, tc)[0, 1] > 0.9
    # the object is the same object in every trial (seeded by object id only)
    h1 = O.surface(12).copy()
    O._surface.cache_clear()
    O._unit_surface.cache_clear()
    np.testing.assert_array_equal(h1, O.surface(12))
    assert not np.array_equal(O.surface(12), O.surface(13))


def test_surface_peak_to_peak_and_band():
    for oid in (0, 13, 26):
        obj = C.get_object(oid)
        h = O.surface(oid)
        assert np.ptp(h) == pytest.approx(obj.amplitude_mm * 1e-3, rel=1e-9)
        spec = np.abs(np.fft.fft2(h)) ** 2
        k = np.fft.fftfreq(h.shape[0], d=1e-3)
        kr = np.hypot(k[:, None], k[None, :])
        centroid = (spec * kr).sum() / spec.sum()
        assert centroid == pytest.approx(obj.spatial_frequency, rel=0.35)


# --------------------------------------------------------------------------- contact
def test_stiffer_object_gives_more_force_at_same_indentation():
    d = np.array([0.5e-3, 2e-3, 5e-3])
    for skin in C.SKINS:
        p = [contact_pressure(mechanics(C.get_object(o), skin), d) for o in (0, 3, 6)]  # 00-10, 00-50, PLA
        assert np.all(p[0] < p[1]) and np.all(p[1] < p[2])
        f = [force_indentation(1, skin, d, physics=PhysicsOverrides(youngs_modulus=e)) for e in (1e4, 1e5, 1e6, 1e9)]
        assert all(np.all(f[i] < f[i + 1]) for i in range(3))
    # the stiffer skin also gives more force on the same object
    assert np.all(force_indentation(1, "soft", d) < force_indentation(1, "hard", d))
    # and the mechanism reaches the FSRs: same displacement amplitude, larger force swing
    swings = []
    for e in (3e4, 3e5, 3e6):
        tr = simulate_trial(1, "soft", "pressing", PRESS_DEEP, duration=2.0, physics=PhysicsOverrides(youngs_modulus=e))
        swings.append(fsr_minus_offset(tr)[:, 0].sum(axis=(1, 2)).std())
    assert swings[0] < swings[1] < swings[2]


@pytest.mark.slow
def test_heterogeneous_objects_stiffen_and_bridge():
    d = np.linspace(0.5e-3, 4e-3, 10)
    for skin in C.SKINS:
        homo = contact_pressure(mechanics(C.get_object(1), skin), d)  # Ecoflex 00-10 bulk, no top layer
        for oid in C.HETEROGENEOUS_OBJECTS:
            het = contact_pressure(mechanics(C.get_object(oid), skin), d)
            k_homo = np.polyfit(np.log(d), np.log(homo), 1)[0]
            k_het = np.polyfit(np.log(d), np.log(het), 1)[0]
            assert k_het > k_homo + 0.15, (oid, skin, k_homo, k_het)  # stiffening (membrane)
            assert np.all(np.diff(het, 2) > 0)  # convex: stiffening
    # the stiff top layer bridges fine surface detail: smoother pressure maps than the
    # homogeneous Ecoflex 00-10 object with the same spatial frequency and amplitude
    for het, homo in ((27, 1), (28, 10), (29, 19), (31, 11)):
        assert mechanics(C.get_object(het), "soft").bridging_length > 1e-3
        r = [map_roughness(mean_maps(simulate_trial(o, "hard", "pressing", PRESS_DEEP, duration=2.0))[:, 0]) for o in (het, homo)]
        assert r[0] < 0.8 * r[1], (het, homo, r)


def test_viscoelastic_relaxation_after_step():
    from embodied_tactile.sim import qlv_relax

    step = np.r_[np.zeros(10), np.ones(500)][:, None]
    out = qlv_relax(step, 0.01, [(0.3, 0.5)])[:, 0]
    assert out[10] == pytest.approx(1.3, rel=0.02)  # instantaneous modulus
    assert out[-1] == pytest.approx(1.0, abs=1e-3)  # relaxed modulus
    assert np.all(np.diff(out[10:]) <= 1e-12)  # monotone relaxation


# --------------------------------------------------------------------------- vibration
@pytest.mark.slow
def test_sliding_vibration_grows_with_spatial_frequency_and_roughness():
    for skin in C.SKINS:
        e = {o: hf_energy(simulate_trial(o, skin, "sliding", SLIDE_FAST, duration=2.0)) for o in (2, 11, 20, 18, 26)}
        assert e[2] < e[11] < e[20], (skin, e)  # 10, 30, 50 /m at 20 mm
        assert e[18] < e[20], (skin, e)  # 5 mm vs 20 mm at 50 /m
        assert e[20] < e[26], (skin, e)  # cast silicone vs printed PLA (rougher layer lines)
    # faster sliding (8 mm vs 2 mm amplitude at 0.8 Hz) crosses more steps per second
    slow = hf_energy(simulate_trial(20, "hard", "sliding", 3, duration=2.0))
    assert slow < 0.5 * e[20]
    # pressing (no sliding) excites far less high-frequency vibration than sliding
    press = hf_energy(simulate_trial(20, "hard", "pressing", PRESS_DEEP, duration=2.0))
    assert press < 0.5 * e[20]


def press_hf_z(trial, f_lo: float = 30.0, window=None) -> float:
    """rms (g) of the skin-normal acceleration above f_lo Hz, all nodes, optional time window."""
    z = trial.acc[..., 2].reshape(len(trial.t), -1).astype(np.float64)
    b, a_ = signal.butter(4, f_lo, "high", fs=C.FS_TACTILE)
    x = signal.filtfilt(b, a_, z - z.mean(0), axis=0)
    return float(np.sqrt((x[window if window is not None else slice(None)] ** 2).mean()))


@pytest.mark.slow
def test_pressing_contact_front_transients_follow_their_physical_drivers(monkeypatch):
    """Pressing: the printed layer lines engaging at the advancing contact front
    (physics.front_acceleration) put surface-dependent vibration on the skin normal."""
    from embodied_tactile.sim import physics as P

    press = {o: press_hf_z(simulate_trial(o, "soft", "pressing", PRESS_DEEP, duration=2.0)) for o in (0, 1, 6, 27)}
    assert press[6] > 1.8 * press[0], press  # PLA vs Ecoflex 00-10, same geometry: stiffer surface, larger share
    assert press[27] > 1.5 * press[1], press  # Dragon Skin top layer vs plain Ecoflex 00-10, same geometry
    # same stroke (2 mm), 4x slower (0.2 vs 0.8 Hz, one vs four cycles): impulses v dz density
    # at a rate v / dz, so far less energy (at the amplitude, not the speed: a deeper
    # stroke keeps each cell at its contact front a smaller part of the cycle)
    slow, fast = (press_hf_z(simulate_trial(6, "soft", "pressing", a, duration=5.0)) for a in (0, 3))
    assert slow < 0.4 * fast, (slow, fast)
    # the mechanism is what carries it: without it pressing PLA is at the 3 mg noise floor
    monkeypatch.setattr(P, "front_acceleration", lambda z, *a, **k: np.zeros_like(z))
    off = press_hf_z(simulate_trial(6, "soft", "pressing", PRESS_DEEP, duration=2.0))
    assert off < 0.006 and press[6] > 3 * off, (off, press[6])


def test_no_contact_front_transients_without_contact():
    lift = simulate_trial(6, "hard", "pressing", PRESS_DEEP, duration=3.0, physics=PhysicsOverrides(lift_off=True))
    up = (lift.t > 1.35) & (lift.t < 1.65)  # retracted 30 mm: no contact
    down = lift.t < 0.9
    assert press_hf_z(lift, window=up) < 0.005 < 2 * 0.005 < press_hf_z(lift, window=down)


def test_front_density_and_acceleration_by_hand():
    from embodied_tactile.sim import physics as P

    dz = P.LAYER_HEIGHT_M
    # density: a cell whose points all sit at the skin's level -> 1 / (width sqrt(2 pi));
    # out of contact or entirely pressed in -> 0
    assert P.front_density(np.zeros((1, 64)))[0] == pytest.approx(1 / (dz * np.sqrt(2 * np.pi)))
    assert P.front_density(np.full((1, 64), -5e-3))[0] < 1e-100 and P.front_density(np.full((1, 64), 5e-3))[0] < 1e-100
    # a node moving down at 10 mm/s over terraces 0.2 mm high crosses one every 20 ms:
    # velocity steps share * v * dz * density, minus their mean (zero-mean train)
    dt, v, dens, share = 1e-3, 10e-3, 500.0, 0.4
    z = 1e-4 - v * dt * np.arange(200)
    acc = P.front_acceleration(z[:, None], np.full((200, 1), dens), share, dt)[:, 0]
    steps = np.abs(np.diff(np.floor(z / dz), prepend=np.floor(z[0] / dz))) > 0
    assert steps.sum() == 10
    np.testing.assert_allclose(acc[steps], share * v * dens * (dz - v * dt) / dt)
    np.testing.assert_allclose(acc[~steps], -share * v * dens * v)
    assert abs(acc.mean()) < 0.02 * acc.max()
    # unloading crosses the same terraces: the same positive kicks (the compression rate
    # drops in magnitude); no motion or no surface at the skin's level: nothing
    up = P.front_acceleration(z[::-1, None], np.full((200, 1), dens), share, dt)[:, 0]
    assert (up > 0).sum() == 10
    np.testing.assert_allclose(up[up > 0], acc[steps])
    assert not P.front_acceleration(np.full((50, 1), 1e-4), np.full((50, 1), dens), share, dt).any()
    assert not P.front_acceleration(z[:, None], np.zeros((200, 1)), share, dt).any()
    assert not P.front_acceleration(z[:, None], np.full((200, 1), dens), 0.0, dt).any()


def test_local_skin_share_follows_the_surface_material():
    from embodied_tactile.sim import physics as P

    share = {(o, s): P.local_skin_share(mechanics(C.get_object(o), s)) for o in (0, 13, 6, 27) for s in C.SKINS}
    for s in C.SKINS:
        assert share[(0, s)] < share[(13, s)] < share[(27, s)] < share[(6, s)] <= 1.0  # 00-10 < 00-50 < DS30 < PLA
        assert share[(6, s)] > 0.999
    # Ecoflex 00-10 (69 kPa instantaneous) against the soft skin's Ecoflex 00-31 (84 kPa)
    assert share[(0, "soft")] == pytest.approx(55e3 * 1.25 / (55e3 * 1.25 + 69e3 * 1.22))
    assert share[(0, "hard")] < share[(0, "soft")]  # the stiffer skin takes less of the step


def test_soft_skin_attenuates_high_frequency_vibration():
    for oid in (20, 24, 11):
        soft = hf_energy(simulate_trial(oid, "soft", "sliding", SLIDE_FAST, duration=2.0), 100.0)
        hard = hf_energy(simulate_trial(oid, "hard", "sliding", SLIDE_FAST, duration=2.0), 100.0)
        assert soft < 0.7 * hard, (oid, soft, hard)


# --------------------------------------------------------------------------- FSR layers
@pytest.mark.slow
def test_bottom_map_is_smoother_than_top():
    for skin in C.SKINS:
        for oid, bound in ((0, 1.0), (11, 1.0), (20, 0.85), (24, 0.85)):
            m = mean_maps(simulate_trial(oid, skin, "pressing", PRESS_DEEP, duration=2.0))
            assert map_roughness(m[:, 1]) < bound * map_roughness(m[:, 0]), (skin, oid)


@pytest.mark.slow
def test_shear_displaces_bottom_map_against_sliding_direction():
    """Same trial with and without friction (same seed: same noise, poses and contact).
    The top map does not change (an FSR senses normal force only); the bottom map is
    displaced along the traction on the skin, i.e. against the sliding velocity. The
    displacement is estimated per frame by least squares (optical-flow style):
    B_fric - B_ref ~ -s . grad(B_ref)."""

    def shift(tr, ref):
        b, r = fsr_minus_offset(tr)[:, 1], fsr_minus_offset(ref)[:, 1]
        gy, gx = np.gradient(r, axis=(1, 2))
        d = b - r
        sx = -(d * gx).sum(axis=(1, 2)) / ((gx**2).sum(axis=(1, 2)) + 1e-9)
        sy = -(d * gy).sum(axis=(1, 2)) / ((gy**2).sum(axis=(1, 2)) + 1e-9)
        return sx, sy

    amplitude = {}
    for skin in C.SKINS:
        amplitude[skin] = 0.0
        for oid in (10, 20, 27):
            tr = simulate_trial(oid, skin, "sliding", SLIDE_FAST, duration=3.0)
            ref = simulate_trial(oid, skin, "sliding", SLIDE_FAST, duration=3.0, physics=PhysicsOverrides(friction=0.0))
            np.testing.assert_array_equal(tr.fsr[:, 0], ref.fsr[:, 0])
            sx, sy = shift(tr, ref)
            vx = np.interp(tr.t, tr.pose_t[1:], np.diff(tr.pose[:, 0].astype(np.float64)) / np.diff(tr.pose_t))
            vy = np.interp(tr.t, tr.pose_t[1:], np.diff(tr.pose[:, 1].astype(np.float64)) / np.diff(tr.pose_t))
            assert np.corrcoef(sx, vx)[0, 1] < -0.5, (skin, oid, np.corrcoef(sx, vx)[0, 1])
            assert np.corrcoef(sy, vy)[0, 1] < -0.5, (skin, oid, np.corrcoef(sy, vy)[0, 1])
            amplitude[skin] += np.median(np.abs(sx)) + np.median(np.abs(sy))
    assert amplitude["soft"] > 2 * amplitude["hard"], amplitude  # the soft inter-layer shears more


def test_saturation_and_lift_off():
    sat = simulate_trial(6, "hard", "pressing", PRESS_DEEP, duration=1.0, physics=PhysicsOverrides(force_scale=1e6))
    ref = simulate_trial(6, "hard", "pressing", PRESS_DEEP, duration=1.0)
    touched = ref.fsr > 100  # every taxel in contact saturates
    assert touched.mean() > 0.1 and (sat.fsr[touched] >= C.FSR_MAX_COUNT - 3).mean() > 0.9
    assert (sat.fsr[touched] == C.FSR_MAX_COUNT).mean() > 0.6
    # ... but only the touched ones (PhysicsOverrides docstring): taxels out of contact keep
    # their offsets, so far from every FSR sample saturates
    assert (sat.fsr[~touched & (ref.fsr < 20)] < 20).mean() > 0.9
    assert 0.05 < (sat.fsr == C.FSR_MAX_COUNT).mean() < 0.5
    lift = simulate_trial(6, "soft", "pressing", 0, duration=3.0, physics=PhysicsOverrides(lift_off=True))
    mid = (lift.t > 1.4) & (lift.t < 1.6)
    assert fsr_minus_offset(lift)[mid].max() < 10  # no contact: offsets + noise only
    assert fsr_minus_offset(lift)[lift.t < 0.5].sum(axis=(1, 2, 3)).min() > 100


# --------------------------------------------------------------------------- dataset / CLI
def test_generate_dataset_resumes_and_passes_scan(tmp_path):
    path = tmp_path / "raw.h5"
    generate_dataset(path, skin="hard", primitive="pressing", objects=[0, 27], actions=[1], duration=0.5, workers=1)
    with h5py.File(path, "r") as f:
        first = f["trials/obj00_hard_pressing_a01_r00/tactile/fsr"][()]
    generate_dataset(path, skin="hard", primitive="pressing", objects=[0, 27], actions=[1, 2], duration=0.5, workers=2)
    good, errors = scan_raw(path)
    assert errors == []
    assert sorted(g.name for g in good) == [
        "obj00_hard_pressing_a01_r00",
        "obj00_hard_pressing_a02_r00",
        "obj27_hard_pressing_a01_r00",
        "obj27_hard_pressing_a02_r00",
    ]
    tr = read_trial(path, "obj00_hard_pressing_a01_r00")
    np.testing.assert_array_equal(tr.fsr, first)
    assert tr.attrs["heterogeneity"] == 0.0
    assert read_trial(path, "obj27_hard_pressing_a02_r00").attrs["heterogeneity"] == 1.0
    # an interrupted write (attributes are written last; the simulator names the group it
    # is writing in the file's simulator_writing attribute first) is redone on resume
    with h5py.File(path, "a") as f:
        g = f["trials/obj27_hard_pressing_a02_r00"]
        for k in list(g.attrs):
            del g.attrs[k]
        f.attrs[PENDING_ATTR] = "obj27_hard_pressing_a02_r00"
    generate_dataset(path, skin="hard", primitive="pressing", objects=[0, 27], actions=[1, 2], duration=0.5, workers=1)
    good, errors = scan_raw(path)
    assert errors == [] and len(good) == 4
    with h5py.File(path, "r") as f:
        assert PENDING_ATTR not in f.attrs


@pytest.mark.slow  # simulate CLI subprocess
def test_cli_writes_requested_trials(tmp_path):
    out = tmp_path / "cli.h5"
    cmd = [sys.executable, "-m", "embodied_tactile.sim.simulate", "skin=soft", "primitive=sliding", f"out={out}",
           "objects=[0,1]", "actions=[0,5]", "repetitions=1", "seed=0", "workers=2", "duration=0.5"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    assert res.returncode == 0, res.stderr
    good, errors = scan_raw(out)
    assert errors == []
    assert sorted(g.name for g in good) == [
        f"obj{o:02d}_soft_sliding_a{a:02d}_r00" for o in (0, 1) for a in (0, 5)
    ]
    assert all(g.attrs["source"] == "simulated" for g in good)


# --------------------------------------------------------------------------- never delete data
def _digest(path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def _write_trial_as(path, source: str, *, drop: str | None = None, object_id: int = 0, action: int = 1) -> str:
    """Write a short trial marked ``source`` into ``path``, optionally without dataset ``drop``."""
    import dataclasses

    from embodied_tactile.data.rawformat import write_trial

    tr = simulate_trial(object_id, "hard", "pressing", action, duration=0.5)
    name = write_trial(path, dataclasses.replace(tr, attrs={**tr.attrs, "source": source}))
    if drop:
        with h5py.File(path, "a") as f:
            del f["trials"][name][drop]
    return name


@pytest.mark.parametrize("drop", [None, "tactile/fsr"])
@pytest.mark.parametrize("overwrite", [False, True])
def test_file_with_recorded_trials_is_never_modified(tmp_path, drop, overwrite):
    """A recorded trial, complete or lacking a sensor field, is left byte-for-byte intact:
    the simulator refuses the whole file, naming it, before writing anything."""
    path = tmp_path / "recorded.h5"
    name = _write_trial_as(path, "recorded", drop=drop)
    before = _digest(path)
    for objects in ([0], [8]):  # the recorded trial's own name, and another trial
        with pytest.raises(OutputFileError) as info:
            generate_dataset(path, skin="hard", primitive="pressing", objects=objects, actions=[1], duration=0.5,
                             workers=1, overwrite=overwrite)
        assert str(path) in str(info.value) and name in str(info.value) and "recorded" in str(info.value)
        assert _digest(path) == before


def _set_version(path, name: str, version: int | None) -> None:
    with h5py.File(path, "a") as f:
        g = f["trials"][name]
        if version is None:
            del g.attrs["sim_physics_version"]  # written before the attribute existed
        else:
            g.attrs["sim_physics_version"] = version


def test_trials_of_an_older_physics_are_resimulated(tmp_path, monkeypatch, caplog):
    from embodied_tactile.sim import dataset as D
    from embodied_tactile.sim.physics import PHYSICS_VERSION

    path = tmp_path / "raw.h5"
    generate_dataset(path, skin="hard", primitive="pressing", objects=[0], actions=[1, 2, 3], duration=0.5, workers=1)
    _set_version(path, "obj00_hard_pressing_a01_r00", None)
    _set_version(path, "obj00_hard_pressing_a02_r00", PHYSICS_VERSION - 1)
    with h5py.File(path, "a") as f:  # an old trial lacking a field is redone too
        del f["trials/obj00_hard_pressing_a02_r00/tactile/fsr"]
    calls = []
    real = D.simulate_trial
    monkeypatch.setattr(D, "simulate_trial", lambda *a, **k: calls.append(a[:5]) or real(*a, **k))
    with caplog.at_level(logging.WARNING, logger="embodied_tactile.sim.dataset"):
        generate_dataset(path, skin="hard", primitive="pressing", objects=[0], actions=[1, 2, 3], duration=0.5, workers=1)
    assert calls == [(0, "hard", "pressing", 1, 0), (0, "hard", "pressing", 2, 0)]  # not a03 (current)
    assert any(str(path) in r.getMessage() and "re-simulating 2 trial(s)" in r.getMessage() for r in caplog.records), caplog.text
    with h5py.File(path, "r") as f:
        assert {int(g.attrs["sim_physics_version"]) for g in f["trials"].values()} == {PHYSICS_VERSION}
    good, errors = scan_raw(path)
    assert errors == [] and len(good) == 3


def test_file_with_unrequested_trials_of_an_older_physics_moves_aside_unchanged(tmp_path, caplog):
    from embodied_tactile.sim.physics import PHYSICS_VERSION

    path = tmp_path / "raw.h5"
    generate_dataset(path, skin="hard", primitive="pressing", objects=[0, 8], actions=[1], duration=0.5, workers=1)
    _set_version(path, "obj08_hard_pressing_a01_r00", None)
    before = _digest(path)
    with caplog.at_level(logging.WARNING, logger="embodied_tactile.sim.dataset"):
        generate_dataset(path, skin="hard", primitive="pressing", objects=[0, 3], actions=[1], duration=0.5, workers=1)
    aside = tmp_path / "raw.physics-v1.h5"
    assert _digest(aside) == before  # kept whole and unchanged
    msg = caplog.text
    assert str(path) in msg and str(aside) in msg and "obj08_hard_pressing_a01_r00" in msg and f"version {PHYSICS_VERSION}" in msg
    with h5py.File(path, "r") as f:  # the new file: the requested trials only, all of this physics
        assert sorted(f["trials"]) == ["obj00_hard_pressing_a01_r00", "obj03_hard_pressing_a01_r00"]
        assert {int(g.attrs["sim_physics_version"]) for g in f["trials"].values()} == {PHYSICS_VERSION}
    # a second move finds a free name
    _set_version(path, "obj03_hard_pressing_a01_r00", None)
    generate_dataset(path, skin="hard", primitive="pressing", objects=[0], actions=[1], duration=0.5, workers=1)
    assert (tmp_path / "raw.physics-v1.1.h5").exists() and _digest(aside) == before
    # a recorded trial is never touched, stale simulated trials or not
    rec = tmp_path / "rec.h5"
    _write_trial_as(rec, "recorded")
    _write_trial_as(rec, "simulated", object_id=8)
    _set_version(rec, "obj08_hard_pressing_a01_r00", None)
    before = _digest(rec)
    with pytest.raises(OutputFileError, match="recorded"):
        generate_dataset(rec, skin="hard", primitive="pressing", objects=[0, 8], actions=[1], duration=0.5, workers=1)
    assert _digest(rec) == before


def test_unmarked_incomplete_group_is_not_deleted(tmp_path):
    """A group without attributes that the simulator did not mark as its own write (no
    simulator_writing attribute naming it) may be anyone's: it is left intact."""
    path = tmp_path / "raw.h5"
    generate_dataset(path, skin="hard", primitive="pressing", objects=[0], actions=[1, 2], duration=0.5, workers=1)
    with h5py.File(path, "a") as f:
        g = f["trials/obj00_hard_pressing_a02_r00"]
        for k in list(g.attrs):
            del g.attrs[k]
    before = _digest(path)
    with pytest.raises(OutputFileError, match="obj00_hard_pressing_a02_r00"):
        generate_dataset(path, skin="hard", primitive="pressing", objects=[0], actions=[1, 2], duration=0.5, workers=1)
    assert _digest(path) == before


def test_only_missing_simulated_trials_are_simulated(tmp_path, monkeypatch, caplog):
    from embodied_tactile.sim import dataset as D

    path = tmp_path / "raw.h5"
    generate_dataset(path, skin="hard", primitive="pressing", objects=[0], actions=[1, 2], duration=0.5, workers=1)
    calls = []
    real = D.simulate_trial
    monkeypatch.setattr(D, "simulate_trial", lambda *a, **k: calls.append(a[:5]) or real(*a, **k))
    with h5py.File(path, "r") as f:
        kept = {n: f["trials"][n]["tactile/fsr"].id.get_offset() for n in f["trials"]}
    generate_dataset(path, skin="hard", primitive="pressing", objects=[0, 8], actions=[1, 2], duration=0.5, workers=1)
    assert calls == [(8, "hard", "pressing", 1, 0), (8, "hard", "pressing", 2, 0)]
    with h5py.File(path, "r") as f:
        assert {n: f["trials"][n]["tactile/fsr"].id.get_offset() for n in kept} == kept  # not rewritten
    # a simulated trial that lacks a sensor field is not deleted and re-simulated: it is
    # kept (an acc-only reader can still use it) with a warning naming file, trial and
    # field, and the file is unchanged ...
    with h5py.File(path, "a") as f:
        del f["trials/obj08_hard_pressing_a02_r00/tactile/acc"]
    before = _digest(path)
    calls.clear()
    with caplog.at_level(logging.WARNING, logger="embodied_tactile.sim.dataset"):
        generate_dataset(path, skin="hard", primitive="pressing", objects=[0, 8], actions=[1, 2], duration=0.5, workers=1)
    assert any(str(path) in r.getMessage() and "obj08_hard_pressing_a02_r00" in r.getMessage()
               and "tactile/acc" in r.getMessage() for r in caplog.records), caplog.text
    assert _digest(path) == before and calls == []
    # ... trials not requested are left alone, damaged or not ...
    generate_dataset(path, skin="hard", primitive="pressing", objects=[0], actions=[1, 2], duration=0.5, workers=1)
    assert _digest(path) == before and calls == []
    # ... and overwrite=true regenerates it (a simulated trial: the simulator's own)
    generate_dataset(path, skin="hard", primitive="pressing", objects=[8], actions=[2], duration=0.5, workers=1, overwrite=True)
    assert calls == [(8, "hard", "pressing", 2, 0)]
    good, errors = scan_raw(path)
    assert errors == [] and len(good) == 4


def test_file_that_is_not_a_raw_file_is_left_alone(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["calibration"] = np.arange(3)
    before = _digest(path)
    with pytest.raises(OutputFileError, match="calibration"):
        generate_dataset(path, skin="hard", primitive="pressing", objects=[0], actions=[1], duration=0.5, workers=1)
    assert _digest(path) == before
    path.write_bytes(b"not hdf5")
    with pytest.raises(OutputFileError, match="cannot be opened"):
        generate_dataset(path, skin="hard", primitive="pressing", objects=[0], actions=[1], duration=0.5, workers=1)
    assert path.read_bytes() == b"not hdf5"


def test_cli_refuses_a_recorded_file_with_exit_2(tmp_path, capsys):
    from embodied_tactile.sim.simulate import main

    path = tmp_path / "recorded.h5"
    _write_trial_as(path, "recorded")
    before = _digest(path)
    rc = main([f"out={path}", "skin=hard", "primitive=pressing", "objects=[8]", "actions=[1]", "duration=0.5", "workers=1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and str(path) in err[0]
    assert _digest(path) == before
