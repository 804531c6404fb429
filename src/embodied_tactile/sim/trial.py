"""One palpation trial: approach to a preload, 10 s of a primitive, sensors -> RawTrial."""

from __future__ import annotations

import numpy as np
from scipy import optimize, signal

from embodied_tactile import constants as C
from embodied_tactile.data.rawformat import RawTrial, make_attrs, trial_name
from embodied_tactile.sim import objects as O
from embodied_tactile.sim import physics as P
from embodied_tactile.sim.physics import PhysicsOverrides
from embodied_tactile.sim.validation import check_choice, check_int, check_overrides, check_trial

_STREAMS = ("placement", "tracking", "fsr", "acc", "stickslip", "clock")
_DEVICE_ENTROPY = 0xE5_C1A1  # per-skin calibration (offsets, gains): the same device every trial

# Skin geometry (tool frame: TCP at the skin backing, z up, skin surface at z = -H).
_PITCH = C.TAXEL_PITCH_M
_TAX = (np.arange(C.FSR_GRID[0]) - (C.FSR_GRID[0] - 1) / 2) * _PITCH
_TY, _TX = np.meshgrid(_TAX, _TAX, indexing="ij")  # row = y, column = x
_NODE_PITCH = C.FSR_GRID[0] * _PITCH / C.ACC_GRID[0]
_NAX = (np.arange(C.ACC_GRID[0]) - (C.ACC_GRID[0] - 1) / 2) * _NODE_PITCH
_NY, _NX = np.meshgrid(_NAX, _NAX, indexing="ij")
# contact-front sample points: P.FRONT_SUB^2 per accelerometer cell, (16, FRONT_SUB^2)
_SUB = (np.arange(P.FRONT_SUB) - (P.FRONT_SUB - 1) / 2) * (_NODE_PITCH / P.FRONT_SUB)
_SY, _SX = (a.reshape(1, -1) for a in np.meshgrid(_SUB, _SUB, indexing="ij"))
_FY, _FX = _NY.reshape(-1, 1) + _SY, _NX.reshape(-1, 1) + _SX


def _rot(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), shape (..., 3, 3)."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    r = np.empty(np.shape(roll) + (3, 3))
    r[..., 0, 0] = cy * cp
    r[..., 0, 1] = cy * sp * sr - sy * cr
    r[..., 0, 2] = cy * sp * cr + sy * sr
    r[..., 1, 0] = sy * cp
    r[..., 1, 1] = sy * sp * sr + cy * cr
    r[..., 1, 2] = sy * sp * cr - cy * sr
    r[..., 2, 0] = -sp
    r[..., 2, 1] = cp * sr
    r[..., 2, 2] = cp * cr
    return r


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def command(primitive: str, params: dict, t: np.ndarray, duration: float, physics: PhysicsOverrides):
    """Commanded offsets (x, y, z m; roll, pitch, yaw rad), each (N,), about the preload pose,
    and the analytic translational acceleration (N, 3) in m/s^2 of the primitive (paper's
    equations; rotations and the lift-off retraction add no acceleration)."""
    z6 = np.zeros((6, t.size))
    acc = np.zeros((t.size, 3))
    if primitive == "pressing":
        a, w = params["A_z_mm"] * 1e-3, params["omega_z_hz"]
    elif primitive == "precession":
        a, w = np.deg2rad(params["A_alpha_beta_deg"]), params["omega_alpha_beta_hz"]
    else:
        a, w = params["A_xy_mm"] * 1e-3, params["omega_xy_gamma_hz"]
    if physics.primitive_frequency_hz is not None:
        w = float(physics.primitive_frequency_hz)
    ph = 2 * np.pi * w * t
    w2 = (2 * np.pi * w) ** 2
    if primitive == "pressing":
        z6[2] = a * np.cos(ph + np.pi)
        acc[:, 2] = -w2 * z6[2]
    elif primitive == "precession":
        z6[3] = a * np.sin(ph + np.pi / 2)
        z6[4] = a * np.sin(ph)
    else:
        z6[0] = z6[1] = a * np.sin(ph)
        z6[5] = np.deg2rad(params["A_gamma_deg"]) * np.sin(ph)
        acc[:, 0] = acc[:, 1] = -w2 * z6[0]
    if physics.lift_off:
        s = duration / 3
        ramp = 0.1 * duration
        z6[2] += P.LIFT_OFF_M * (_smoothstep((t - s) / ramp) - _smoothstep((t - 2 * s + ramp) / ramp))
    return z6, acc


def _tracking_error(rng: np.random.Generator, n: int) -> np.ndarray:
    """Smooth tracking error (6, n) at the pose rate: white noise through a 4th-order 1 Hz
    Butterworth low-pass (smooth enough to differentiate twice), scaled to TRACK_ERR_*."""
    sos = signal.butter(4, 1.0, fs=C.FS_POSE, output="sos")
    e = signal.sosfilt(sos, rng.standard_normal((6, n + 400)), axis=1)[:, 400:]
    e /= np.sqrt(np.sum(signal.sosfilt(sos, np.r_[1.0, np.zeros(999)]) ** 2))  # unit std
    scale = np.array([P.TRACK_ERR_M] * 3 + [P.TRACK_ERR_RAD] * 3)[:, None]
    return e * scale


def _world_points(pose6: np.ndarray, lx: np.ndarray, ly: np.ndarray, lz: float) -> np.ndarray:
    """Object-frame positions (N, K, 3) of tool-frame points (K,) for poses (6, N)."""
    r = _rot(pose6[3], pose6[4], pose6[5])
    loc = np.stack([lx.ravel(), ly.ravel(), np.full(lx.size, lz)])  # (3, K)
    return np.matmul(r, loc).transpose(0, 2, 1) + pose6[:3].T[:, None, :]


def _shift_kernels(shift_px: np.ndarray, sigma_px: float) -> np.ndarray:
    """(N, 16, 16) Gaussian kernels K[n, i, j] ~ g(i - j - shift_n), each row normalised
    over the array: a receiving taxel averages the sources around i - shift (the skin's
    pressure just outside the array is taken equal to that at its edge, so the edges do
    not lose load)."""
    idx = np.arange(C.FSR_GRID[0], dtype=np.float64)
    d = idx[None, :, None] - idx[None, None, :] - shift_px[:, None, None]
    k = np.exp(-0.5 * (d / max(sigma_px, 1e-3)) ** 2)
    return k / k.sum(axis=2, keepdims=True)


def _upsample(src: np.ndarray, ratio: int, n: int) -> np.ndarray:
    """Linear interpolation by an integer ``ratio`` along axis 0 (float32): sample m of the
    output lies at src index m / ratio. ``src`` needs ceil(n / ratio) + 1 rows."""
    blocks = -(-n // ratio)
    s = src.astype(np.float32, copy=False)
    f = (np.arange(ratio, dtype=np.float32) / ratio).reshape(1, ratio, *([1] * (src.ndim - 1)))
    a, b = s[:blocks, None], s[1 : blocks + 1, None]
    out = a + (b - a) * f
    return out.reshape(blocks * ratio, *src.shape[1:])[:n]


def _upsample_cubic(src: np.ndarray, ratio: int, n: int) -> np.ndarray:
    """Catmull-Rom (cubic, C1) interpolation by an integer ``ratio`` along axis 0 (float64)."""
    blocks = -(-n // ratio)
    s = np.concatenate([src[:1], src, src[-1:], src[-1:]], axis=0)
    p0, p1, p2, p3 = (s[i : i + blocks, None] for i in range(4))
    f = (np.arange(ratio) / ratio).reshape(1, ratio, *([1] * (src.ndim - 1)))
    out = p1 + 0.5 * f * ((p2 - p0) + f * ((2 * p0 - 5 * p1 + 4 * p2 - p3) + f * (3 * (p1 - p2) + p3 - p0)))
    return out.reshape(blocks * ratio, *src.shape[1:])[:n]


def _fast_noise(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Unit-variance float32 noise (triangular: sum of two random signed bytes) at a
    fraction of the cost of Gaussian draws; it ends in integer ADC counts anyway. Its mean
    is -0.0096 (bytes span -128..127), i.e. -0.006 counts at the 0.6-count noise floor."""
    n = int(np.prod(shape))
    raw = np.frombuffer(rng.bytes(2 * n), dtype=np.int8)
    out = raw[:n].astype(np.float32)
    out += raw[n:]
    out *= np.float32(1.0 / np.sqrt(2 * (256.0**2 - 1) / 12))
    return out.reshape(shape)


def _preload_depth(mech: P.Mechanics, h_tax: np.ndarray, dz_tax: np.ndarray) -> float:
    """TCP z (object frame) at which the relaxed contact force equals PRELOAD_N, or
    MAX_PRELOAD_DEPTH_M below first touch if the force stays below it there (a very soft
    object: the trial then runs at a smaller preload)."""
    top = float(np.max(h_tax - dz_tax))  # TCP z at first touch
    area = _PITCH**2

    def excess(s: float) -> float:
        return float(P.contact_pressure(mech, h_tax - (top - s + dz_tax)).sum() * area - P.PRELOAD_N)

    if excess(P.MAX_PRELOAD_DEPTH_M) <= 0:
        return top - P.MAX_PRELOAD_DEPTH_M
    s = optimize.brentq(excess, 0.0, P.MAX_PRELOAD_DEPTH_M, xtol=1e-9)
    return top - s


def _streams(seed: int, object_id: int, skin: str, primitive: str, action_index: int, repetition: int):
    ss = np.random.SeedSequence(
        entropy=int(seed),
        spawn_key=(int(object_id), C.SKINS.index(skin), C.PRIMITIVES.index(primitive), int(action_index), int(repetition)),
    )
    return dict(zip(_STREAMS, (np.random.default_rng(s) for s in ss.spawn(len(_STREAMS)))))


def _device(skin: str):
    """Per-skin calibration: FSR offsets / gains (2, 16, 16), accelerometer offsets (4, 4, 3)."""
    rng = np.random.default_rng(np.random.SeedSequence([_DEVICE_ENTROPY, C.SKINS.index(skin)]))
    fsr_off = rng.uniform(0, P.FSR_OFFSET_COUNTS, (C.FSR_LAYERS, *C.FSR_GRID)).astype(np.float32)
    fsr_gain = (1 + P.FSR_GAIN_SPREAD * rng.uniform(-1, 1, (C.FSR_LAYERS, *C.FSR_GRID))).astype(np.float32)
    acc_off = rng.uniform(-P.ACC_OFFSET_G, P.ACC_OFFSET_G, (*C.ACC_GRID, C.ACC_AXES))
    return fsr_off, fsr_gain, acc_off


def fsr_counts(force_n: np.ndarray, gain: np.ndarray | float = 1.0) -> np.ndarray:
    """Noise-free FSR counts (float32): conductance ~ (gain F)^0.7 in a divider into the
    12-bit ADC, 4095 x / (1 + x) with x = ((gain F - 5 mN) / 0.15 N)^0.7 (``gain``: per-taxel
    sensitivity). The divider approaches full scale without reaching it: half scale at
    0.15 N, within 3 counts of 4095 from about 4.5e3 N, within 0.5 count (rounds to 4095)
    from about 5.8e4 N."""
    f = np.maximum(force_n * gain - np.float32(P.FSR_ACTIVATION_N), 0)
    x = (f / np.float32(P.FSR_HALF_N)) ** np.float32(P.FSR_EXPONENT)
    return np.float32(C.FSR_MAX_COUNT) * x / (1 + x)


def quantise(values: np.ndarray, lo: float, hi: float, *, trial: str, field: str) -> np.ndarray:
    """Round ``values`` (float, in ADC steps) to the nearest step and clip to [lo, hi], in
    place. Non-finite values are refused with a FloatingPointError naming the trial and
    field: rounding or clipping would turn NaN into an arbitrary integer count."""
    bad = ~np.isfinite(values)
    if bad.any():
        first = tuple(int(i) for i in np.argwhere(bad)[0])
        raise FloatingPointError(
            f"simulated trial {trial!r}, field {field!r}: {int(bad.sum())} non-finite value(s) before "
            f"quantisation, first at index {first}; refusing to convert them to ADC counts"
        )
    np.rint(values, out=values)
    return np.clip(values, lo, hi, out=values)


def simulate_trial(
    object_id: int | C.WaveObject,
    skin: str,
    primitive: str,
    action_index: int,
    repetition: int = 0,
    seed: int = 0,
    *,
    duration: float = C.TRIAL_DURATION,
    physics: PhysicsOverrides | None = None,
) -> RawTrial:
    """Simulate one trial of ``object_id`` (a catalogue id or a ``WaveObject``, e.g. of
    ``sim.population``). Deterministic: the same arguments (seed, object, skin, primitive,
    action, repetition, duration, physics) give identical arrays. Every argument is checked
    first (:func:`embodied_tactile.sim.validation.check_trial`, ``SimParameterError``)."""
    check_trial(object_id, skin, primitive, action_index, repetition, seed, duration, physics)
    obj = O.as_object(object_id)
    object_id = obj.object_id
    name = trial_name(dict(object_id=object_id, skin=skin, primitive=primitive, action_index=action_index, repetition=repetition))
    physics = physics or PhysicsOverrides()
    action = C.get_action(primitive, action_index)
    mech = P.mechanics(obj, skin, physics)
    rng = _streams(seed, object_id, skin, primitive, action_index, repetition)
    fsr_off, fsr_gain, acc_off = _device(skin)

    n_t = max(int(round(C.FS_TACTILE * duration)), 2)
    n_pose = max(int(round(C.FS_POSE * duration)), 2)
    ratio = int(round(C.FS_TACTILE / P.PHYSICS_RATE_HZ))  # 7
    n_p = -(-n_t // ratio) + 1  # physics frames covering the tactile samples
    H = mech.h_skin

    # ---------------------------------------------------------------- clocks
    jit = rng["clock"]
    t_tac = np.arange(n_t) / C.FS_TACTILE + jit.uniform(-20e-6, 20e-6, n_t)
    t_pose = np.arange(n_pose) / C.FS_POSE + jit.uniform(-0.5e-3, 0.5e-3, n_pose)
    t_phys = np.arange(n_p) / P.PHYSICS_RATE_HZ  # uniform physics grid (= nominal pose grid)
    dt = 1.0 / P.PHYSICS_RATE_HZ

    # ---------------------------------------------------------------- surfaces
    h_con = O.surface(obj, physics.amplitude_mm)  # heightmap (m)
    h_spl = O.spline_coeffs(obj, physics.amplitude_mm)

    # ---------------------------------------------------------------- poses
    x0, y0 = rng["placement"].normal(0.0, P.PLACEMENT_ERR_M, 2)
    err = _tracking_error(rng["tracking"], n_p)  # (6, n_p) on the physics grid
    cmd_p, _ = command(primitive, action.params, t_phys, duration, physics)
    cmd_0, _ = command(primitive, action.params, np.zeros(1), duration, physics)
    pose0 = cmd_0.copy()
    pose0[0] += x0
    pose0[1] += y0
    pose0[2] = 0.0  # approach at the primitive's start orientation, pressing centred on preload
    w0 = _world_points(pose0, _TX, _TY, -H)[0]
    h0 = O.sample(h_con, w0[:, 0], w0[:, 1])
    z_pre = _preload_depth(mech, h0, w0[:, 2] - pose0[2])

    pose_p = cmd_p + err
    pose_p[0] += x0
    pose_p[1] += y0
    pose_p[2] += z_pre

    # ---------------------------------------------------------------- contact (physics rate)
    wt = _world_points(pose_p, _TX, _TY, -H)  # (n_p, 256, 3)
    h_t = O.sample(h_con, wt[..., 0], wt[..., 1])
    delta = h_t - wt[..., 2]  # penetration, m
    p_el = P.contact_pressure(mech, delta, physics.force_scale)
    ws, wo = P.relaxation_weights(mech)
    p = P.qlv_relax(p_el, dt, [(mech.g_skin * ws, mech.tau_skin), (mech.g_obj * wo, mech.tau_obj)])

    # shear: regularised Coulomb traction -> inter-layer shear displacement (tool frame)
    vel = np.gradient(wt[..., :2], dt, axis=0)  # skin-surface velocity over the fixed object
    psum = p.sum(axis=1)
    incontact = psum > 0
    wgt = np.where(incontact[:, None], p / np.where(incontact, psum, 1.0)[:, None], 0.0)
    v = np.einsum("nk,nkc->nc", wgt, vel)
    speed = np.linalg.norm(v, axis=1)
    ncont = np.maximum((p > 0).sum(axis=1), 1)
    p_mean = psum / ncont
    tau = mech.friction * p_mean * np.tanh(speed / P.SLIP_VELOCITY_M_S)
    g_inter = mech.e_skin / 3.0
    h_inter = C.SKIN_SPECS[skin].interlayer_thickness_mm * 1e-3
    u_lin = tau * h_inter / g_inter
    u_max = P.MAX_SHEAR_STRAIN * h_inter
    u = u_max * np.tanh(u_lin / u_max)
    dirn = -v / np.maximum(speed, 1e-12)[:, None]  # traction on the skin opposes its motion
    cy, sy = np.cos(pose_p[5]), np.sin(pose_p[5])
    ux = (cy * dirn[:, 0] + sy * dirn[:, 1]) * u  # into the tool frame
    uy = (-sy * dirn[:, 0] + cy * dirn[:, 1]) * u

    # ---------------------------------------------------------------- FSR maps
    pm = p.reshape(n_p, *C.FSR_GRID)
    zero = np.zeros(n_p)
    # a stiff top layer of the object spreads the load over its flexural length (bridging)
    lb = mech.bridging_length
    kt = _shift_kernels(zero[:1], np.hypot(P.SPREAD_TOP_M, lb) / _PITCH)[0]
    top = kt @ pm @ kt.T
    sb = np.hypot(P.SPREAD_BOTTOM_M, lb) / _PITCH
    kby, kbx = _shift_kernels(uy / _PITCH, sb), _shift_kernels(ux / _PITCH, sb)
    bot = kby @ pm @ kbx.transpose(0, 2, 1)
    force = np.stack([top, bot], axis=1) * _PITCH**2  # (n_p, 2, 16, 16) N per taxel
    counts_p = fsr_counts(force.astype(np.float32), fsr_gain) + fsr_off  # linear in time: fold in
    counts = _upsample(counts_p, ratio, n_t)
    noise = _fast_noise(rng["fsr"], counts.shape)
    # resistance noise enters through the divider slope c (1 - c / full): none at the rails
    noise *= counts * (np.float32(P.FSR_NOISE_REL) - counts * np.float32(P.FSR_NOISE_REL / C.FSR_MAX_COUNT)) + np.float32(P.FSR_NOISE_COUNTS)
    counts += noise
    fsr = quantise(counts, 0, C.FSR_MAX_COUNT, trial=name, field="tactile/fsr").astype(np.uint16)

    # ---------------------------------------------------------------- accelerometers (700 Hz)
    cmd_t, acc_cmd = command(primitive, action.params, t_tac, duration, physics)
    err_t = np.stack([np.interp(t_tac, t_phys, e) for e in err])
    pose_t6 = cmd_t + err_t
    pose_t6[0] += x0
    pose_t6[1] += y0
    pose_t6[2] += z_pre
    rt = _rot(pose_t6[3], pose_t6[4], pose_t6[5])  # (n_t, 3, 3)
    # specific force of the rigid skin body: R^T (a / g + z)
    f_world = acc_cmd / 9.81
    f_world[:, 2] += 1.0
    acc = np.matmul(rt.transpose(0, 2, 1), f_world[:, :, None])[:, None, :, 0].repeat(16, axis=1)  # (n_t, 16, 3)

    # local compression of the skin under each node (quasi-static, along the normal)
    pool = p.reshape(n_p, 4, 4, 4, 4).mean(axis=(2, 4)).reshape(n_p, 16)
    d_node = np.maximum(delta.reshape(n_p, 4, 4, 4, 4).mean(axis=(2, 4)).reshape(n_p, 16), 0) * ws
    dd = np.gradient(np.gradient(d_node, dt, axis=0), dt, axis=0) / 9.81
    acc[..., 2] += _upsample(dd, ratio, n_t)
    w_node = _upsample(pool / (pool + P.CONTACT_REF_PA), ratio, n_t).astype(np.float64)  # contact weight

    # texture: stair steps of the printed layers (crossed at |dh/dt| / dz) and infill lines
    wn_ = _world_points(pose_t6, _NX, _NY, -H)  # (n_t, 16, 3)
    wn_p = _world_points(pose_p, _NX, _NY, -H)  # (n_p, 16, 3): heights at the physics rate,
    h_n = _upsample_cubic(O.sample_spline(h_spl, wn_p[..., 0], wn_p[..., 1]), ratio, n_t)  # C1 in time
    dtt = 1.0 / C.FS_TACTILE
    f_step = np.abs(np.gradient(h_n, dtt, axis=0)) / P.LAYER_HEIGHT_M
    f_inf = np.abs(np.gradient(wn_[..., 0], dtt, axis=0)) / P.INFILL_PITCH_M
    fn, zeta = P.node_resonance(skin)
    rough = P.roughness(obj.top_layer or obj.bulk)
    gain = P.TEXTURE_COUPLING * rough * w_node / 9.81
    amp_step = gain * (2 * np.pi * f_step) ** 2 * (P.LAYER_HEIGHT_M / np.pi)
    amp_step *= P.skin_transmissibility(f_step, fn, zeta) * P.antialias(f_step)
    amp_inf = P.INFILL_WEIGHT * gain * (2 * np.pi * f_inf) ** 2 * (P.LAYER_HEIGHT_M / np.pi)
    amp_inf *= P.skin_transmissibility(f_inf, fn, zeta) * P.antialias(f_inf)
    phase0 = rng["stickslip"].uniform(0, 2 * np.pi, (2, 16))
    acc[..., 2] += amp_step * np.sin(2 * np.pi * h_n / P.LAYER_HEIGHT_M + phase0[0])
    acc[..., 2] += amp_inf * np.sin(2 * np.pi * wn_[..., 0] / P.INFILL_PITCH_M + phase0[1])

    # contact front: the printed layer lines engage as the skin presses into the surface;
    # each terrace crossed under a node is a velocity step of the cover (physics.front_acceleration)
    wf = _world_points(pose_p, _FX, _FY, -H)  # (n_p, 16 * FRONT_SUB^2, 3)
    pen_f = (O.sample(h_con, wf[..., 0], wf[..., 1]) - wf[..., 2]).reshape(n_p, 16, -1)
    dens = _upsample(P.front_density(pen_f), ratio, n_t).astype(np.float64)
    share = P.local_skin_share(mech)
    a_front = P.front_acceleration(wn_[..., 2], dens, share, dtt)
    b, a = P.skin_filter(fn, zeta)
    acc[..., 2] += signal.lfilter(b, a, a_front, axis=0) / 9.81

    # stick-slip: broadband bursts, rate ~ crossing rate, filtered by the skin
    slip = np.tanh(np.linalg.norm(np.gradient(wn_[..., :2], dtt, axis=0), axis=-1) / P.SLIP_VELOCITY_M_S)
    rate = f_step + P.INFILL_WEIGHT * f_inf
    inten = P.STICKSLIP_G * mech.friction * rough * w_node * slip * np.sqrt(rate / P.STICKSLIP_REF_HZ)
    burst = rng["stickslip"].standard_normal((n_t, 16, 3)) * inten[..., None] * np.array([1.0, 1.0, 0.5])
    acc += signal.lfilter(b, a, burst, axis=0)

    acc = acc.reshape(n_t, *C.ACC_GRID, 3) + acc_off
    acc += rng["acc"].standard_normal(acc.shape) * P.ACC_NOISE_G
    lsb = 1.0 / C.ACC_COUNTS_PER_G
    acc = quantise(acc / lsb, -C.ACC_RANGE_G * C.ACC_COUNTS_PER_G, C.ACC_RANGE_G * C.ACC_COUNTS_PER_G - 1, trial=name, field="tactile/acc") * lsb
    acc = acc.astype(np.float32)

    # ---------------------------------------------------------------- recorded pose
    cmd_r, _ = command(primitive, action.params, t_pose, duration, physics)
    err_r = np.stack([np.interp(t_pose, t_phys, e) for e in err])
    pose = cmd_r + err_r
    pose[0] += x0 + P.WORKSPACE_XY_M[0]
    pose[1] += y0 + P.WORKSPACE_XY_M[1]
    pose[2] += z_pre + P.SURFACE_Z_M
    pose = pose.T.astype(np.float32)

    attrs = make_attrs(
        object_id=object_id,
        skin=skin,
        primitive=primitive,
        action_index=action_index,
        repetition=repetition,
        source="simulated",
        seed=seed,
        factors=obj.factors(),
        **obj.description(),
        **{P.VERSION_ATTR: P.PHYSICS_VERSION},
    )
    return RawTrial(t=t_tac, acc=acc, fsr=fsr, pose_t=t_pose, pose=pose, attrs=attrs)


def force_indentation(
    object_id: int, skin: str, depths_m: np.ndarray, *, physics: PhysicsOverrides | None = None
) -> np.ndarray:
    """Quasi-static (relaxed) normal force (N) of the skin pressed flat onto the object's
    contact surface at the nominal trial position, for indentations ``depths_m`` measured
    from first touch. The same contact law the trials integrate."""
    check_int("object_id", object_id, 0, C.N_OBJECTS - 1)
    check_choice("skin", skin, C.SKINS)
    check_overrides(physics)
    physics = physics or PhysicsOverrides()
    obj = C.get_object(object_id)
    mech = P.mechanics(obj, skin, physics)
    h_con = O.surface(object_id, physics.amplitude_mm)
    w0 = _world_points(np.zeros((6, 1)), _TX, _TY, -mech.h_skin)[0]
    h0 = O.sample(h_con, w0[:, 0], w0[:, 1])
    gap = h0.max() - h0  # distance of each taxel to the surface at first touch
    d = np.asarray(depths_m, dtype=np.float64)[..., None]
    return P.contact_pressure(mech, d - gap, physics.force_scale).sum(axis=-1) * _PITCH**2
