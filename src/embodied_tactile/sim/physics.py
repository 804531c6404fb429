"""Physical constants of the simulator and the stable building blocks it integrates with.

Pure NumPy/SciPy. Everything here is vectorised over taxels and time:

* :func:`contact_pressure`  -- series-compliance Winkler contact law (skin + object),
  with strain stiffening and, for heterogeneous objects, the bending + membrane
  stiffening of a thin stiff top layer.
* :func:`qlv_relax`         -- quasi-linear viscoelasticity (standard linear solid
  branches) integrated with the EXACT exponential update for piecewise-linear input,
  as one :func:`scipy.signal.lfilter` pass: unconditionally stable for any tau > 0, dt > 0.
* :func:`skin_transmissibility` / :func:`skin_filter` -- the silicone between the
  contact and an accelerometer node as a base-excited mass-spring-damper (a mechanical
  low-pass); analytic magnitude for quasi-stationary tones, bilinear-transformed
  digital filter for broadband excitation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from embodied_tactile import constants as C
from embodied_tactile.sim.limits import PHYSICS_RATE_HZ, check_physics  # noqa: F401 (PHYSICS_RATE_HZ re-exported)

# --------------------------------------------------------------------------- constants
#: Grid of the object heightmaps: 256 x 256 samples at 1 mm (a 256 mm block; the skin
#: path never leaves its central +-40 mm).
SURFACE_N = 256
SURFACE_DX_M = 1e-3
#: Relative width (sigma / f0) of the Gaussian band-pass annulus; at least 4 /m.
BAND_REL_SIGMA = 0.3
BAND_MIN_SIGMA = 4.0

#: Effective depth of the object's deformed zone under a taxel-sized load (Winkler
#: foundation thickness for a half-space loaded over a ~10-20 mm contact).
OBJECT_DEFORM_DEPTH_M = 10e-3
POISSON = 0.5  # silicone (incompressible); shear modulus G = E / 3

#: Layer lines of the 3-D printed moulds / PLA objects (stair steps of height DZ on the
#: wave surface, cut at every height contour), and the relative texture strength:
#: PLA printed directly = 1, silicone cast in a printed mould = 0.5 (softer replica).
LAYER_HEIGHT_M = 0.2e-3
INFILL_PITCH_M = 0.3e-3  # raster lines on flat parts (crossed at speed / pitch)
INFILL_WEIGHT = 0.1  # relative height of the raster ridges (only on near-flat patches)
CONTACT_REF_PA = 2e3  # node contact weight w = p / (p + CONTACT_REF_PA)
ROUGHNESS = {"pla": 1.0, "ecoflex_00_10": 0.5, "ecoflex_00_50": 0.5, "dragon_skin_30": 0.5}
#: roughness of a material given as itself (population silicones): the cast silicones' value
SILICONE_ROUGHNESS = 0.5


def roughness(material: str | C.Material) -> float:
    """Texture roughness of a surface material (``ROUGHNESS`` by key; a material given as
    itself is a cast silicone)."""
    return ROUGHNESS[material] if isinstance(material, str) else SILICONE_ROUGHNESS

#: Contact averaging of the step texture over the contact zone (many steps with
#: incoherent phases under one accelerometer cell); calibrated so that a hard skin
#: sliding on rough PLA reaches a few tenths of a g.
TEXTURE_COUPLING = 0.1
#: Broadband stick-slip acceleration (g rms before the skin filter) per unit friction
#: coefficient at a crossing rate of STICKSLIP_REF_HZ.
STICKSLIP_G = 0.6
STICKSLIP_REF_HZ = 100.0
SLIP_VELOCITY_M_S = 2e-3  # regularisation of Coulomb friction (elastic pre-slip)

#: Version of the simulated physics, written to every simulated trial as the attribute
#: ``sim_physics_version`` (absent = 1). Bump it whenever a change alters the simulated
#: signals: ``generate_dataset`` re-simulates requested trials of an older version and
#: refuses a file that would keep unrequested ones (never one dataset of two physics).
#: 1: up to the contact-front transients; 2: contact-front transients at the printed
#: layer lines (:func:`front_density`, :func:`front_acceleration`).
PHYSICS_VERSION = 2
VERSION_ATTR = "sim_physics_version"
#: Contact front: each accelerometer cell (10 x 10 mm) is sampled on FRONT_SUB x FRONT_SUB
#: points (1.25 mm apart) to find the area of its surface at the skin's level; the
#: density is a Gaussian kernel estimate of width one layer height.
FRONT_SUB = 8

#: Accelerometer node: chip + flex island + the silicone cell co-moving with it.
NODE_MASS_KG = 1.0e-3
NODE_AREA_M2 = 9e-6  # load path above the 3 x 3 mm chip
SKIN_DAMPING = {"soft": 0.35, "hard": 0.2}  # damping ratio of the node resonance
ACC_NOISE_G = 0.003
ACC_OFFSET_G = 0.02  # per-axis zero-g offset (per device, fixed)
ACC_AA_HZ = 280.0  # accelerometer digital low-pass

#: Load spreading (Gaussian sigma, m) to the top and bottom FSR layers.
SPREAD_TOP_M = 1.5e-3
SPREAD_BOTTOM_M = 3.5e-3
MAX_SHEAR_STRAIN = 0.5

#: FSR: conductance ~ F^FSR_EXPONENT, divider at the force FSR_HALF_N (half-scale count).
FSR_EXPONENT = 0.7
FSR_HALF_N = 0.15
FSR_ACTIVATION_N = 0.005  # turn-on force: below it the FSR stays open circuit
FSR_NOISE_COUNTS = 0.6  # ADC noise floor (rms counts)
FSR_NOISE_REL = 0.006  # FSR resistance noise: sigma += REL * c (1 - c / 4095), c = count
FSR_OFFSET_COUNTS = 3.0  # zero-force offsets 0..3 counts (an unloaded FSR is ~open circuit)
FSR_GAIN_SPREAD = 0.1

#: Approach: quasi-static preload before the primitive starts.
PRELOAD_N = 1.5
MAX_PRELOAD_DEPTH_M = 60e-3
#: Robot: TCP at the skin backing, skin surface SKIN thickness below; object frame.
WORKSPACE_XY_M = (0.50, 0.0)
SURFACE_Z_M = 0.05
TRACK_ERR_M = 0.1e-3
TRACK_ERR_RAD = np.deg2rad(0.05)
PLACEMENT_ERR_M = 0.5e-3
LIFT_OFF_M = 0.03


@dataclass(frozen=True)
class PhysicsOverrides:
    """Overrides for stress tests; ``None`` keeps the catalogue value.

    ``youngs_modulus`` replaces the object's bulk relaxed modulus (Pa);
    ``relaxation_time`` replaces tau of object and skin (s; the top layer has no
    relaxation branch of its own); ``amplitude_mm`` rescales the surface peak-to-peak;
    ``primitive_frequency_hz`` replaces the action's frequency; ``lift_off`` retracts the
    robot 30 mm over the middle third of the trial; ``friction`` replaces the skin/object
    Coulomb coefficient (0 switches shear and stick-slip off).

    ``force_scale`` multiplies the contact pressure after the preload depth is found (the
    robot's motion is unchanged). An FSR count follows the scaled load F of its taxel: it
    stays at the taxel's offset while F is below the 5 mN activation force (taxels away
    from the contact receive only the Gaussian tails of the load spreading) and approaches
    full scale as 4095 x / (1 + x), x = ((gain F - 5 mN) / 0.15 N)^0.7, within 3 counts of
    4095 from about 4.5e3 N. So a huge scale does not saturate every sensor. At 1e6,
    measured on 12 two-second trials (3 primitives x 4 object/skin/action pairs): of the
    taxels reading > 20 counts at scale 1, 97.6-100 % of the samples are >= 4092; of the
    other taxels, 0-41 %; of all FSR samples, 9-48 % equal 4095. The bottom FSR
    map also moves with the larger shear traction; the accelerometers see the scale only
    through the contact weight of texture and stick-slip.

    Every field is checked on construction (:func:`embodied_tactile.sim.limits.check_physics`;
    ranges in docs/reference/simulator.md): an invalid value raises ``SimParameterError``.
    """

    youngs_modulus: float | None = None
    relaxation_time: float | None = None
    amplitude_mm: float | None = None
    primitive_frequency_hz: float | None = None
    lift_off: bool = False
    force_scale: float = 1.0
    friction: float | None = None  # Coulomb coefficient skin/object (0: no shear)

    def __post_init__(self) -> None:
        check_physics(self)


@dataclass(frozen=True)
class Mechanics:
    """Resolved mechanical parameters of one object / skin pair."""

    e_skin: float  # relaxed modulus, Pa
    g_skin: float
    tau_skin: float
    h_skin: float  # m
    e_obj: float  # bulk relaxed modulus
    g_obj: float
    tau_obj: float
    e_top: float  # 0 when homogeneous
    t_top: float  # m
    friction: float
    g_top: float = 0.0  # relaxation strength of the top layer (instantaneous modulus only)

    @property
    def bridging_length(self) -> float:
        """Flexural length (D / k)^(1/4) of the top layer on the bulk foundation (0 if none)."""
        if self.t_top <= 0:
            return 0.0
        d = self.e_top * self.t_top**3 / (12.0 * (1 - POISSON**2))
        k = self.e_obj / OBJECT_DEFORM_DEPTH_M
        return float((d / k) ** 0.25)


def mechanics(obj: C.WaveObject, skin: str, physics: PhysicsOverrides | None = None) -> Mechanics:
    physics = physics or PhysicsOverrides()
    sk = C.MATERIALS[C.SKIN_SPECS[skin].silicone]
    bulk = obj.bulk_material
    top = obj.top_material
    tau = physics.relaxation_time
    surface = top or bulk
    return Mechanics(
        e_skin=sk.youngs_modulus,
        g_skin=sk.relaxation_strength,
        tau_skin=float(tau) if tau is not None else sk.relaxation_time,
        h_skin=C.SKIN_SPECS[skin].total_thickness_mm * 1e-3,
        e_obj=float(physics.youngs_modulus) if physics.youngs_modulus is not None else bulk.youngs_modulus,
        g_obj=bulk.relaxation_strength,
        tau_obj=float(tau) if tau is not None else bulk.relaxation_time,
        e_top=top.youngs_modulus if top else 0.0,
        t_top=obj.top_thickness_mm * 1e-3,
        friction=float(physics.friction) if physics.friction is not None else min(surface.friction, sk.friction),
        g_top=top.relaxation_strength if top else 0.0,
    )


def _object_modulus(m: Mechanics, delta_obj: np.ndarray) -> np.ndarray:
    """Effective object modulus; a stiff top layer adds bending (linear) and membrane
    stretching (grows with (w / t)^2, the large-deflection plate term)."""
    if m.t_top <= 0:
        return np.full_like(delta_obj, m.e_obj)
    frac = m.t_top / OBJECT_DEFORM_DEPTH_M
    return m.e_obj + m.e_top * frac * (0.1 + (delta_obj / m.t_top) ** 2)


def contact_pressure(m: Mechanics, delta: np.ndarray, force_scale: float = 1.0) -> np.ndarray:
    """Relaxed contact pressure (Pa) for local penetration ``delta`` (m, <= 0: no contact).

    Series compliance per unit area: c = h_s / E_s(eps_s) + h_o / E_o(delta_o), with
    neo-Hookean-like stiffening E_s (1 + eps_s) of the compressed skin. The split of
    ``delta`` between skin and object follows the linear compliances. No singular strain
    terms: finite for the moduli the simulator accepts (sim/validation.py) and the
    penetrations they produce; zero without contact.
    """
    d = np.maximum(np.asarray(delta, dtype=np.float64), 0.0)
    cs0 = m.h_skin / m.e_skin
    co0 = OBJECT_DEFORM_DEPTH_M / (m.e_obj + (0.1 * m.e_top * m.t_top / OBJECT_DEFORM_DEPTH_M))
    frac_s = cs0 / (cs0 + co0)
    d_s = d * frac_s
    d_o = d - d_s
    cs = m.h_skin / (m.e_skin * (1.0 + d_s / m.h_skin))
    co = OBJECT_DEFORM_DEPTH_M / _object_modulus(m, d_o)
    return force_scale * d / (cs + co)


def relaxation_weights(m: Mechanics) -> tuple[float, float]:
    """Share of the series compliance carried by skin and object (weights of their
    relaxation branches in the combined reduced relaxation function)."""
    cs = m.h_skin / m.e_skin
    co = OBJECT_DEFORM_DEPTH_M / (m.e_obj + 0.1 * m.e_top * m.t_top / OBJECT_DEFORM_DEPTH_M)
    return cs / (cs + co), co / (cs + co)


def qlv_relax(p_elastic: np.ndarray, dt: float, branches: list[tuple[float, float]]) -> np.ndarray:
    """Quasi-linear viscoelastic response to the relaxed ("elastic") pressure history.

    G(t) = 1 + sum_k g_k exp(-t / tau_k). Each branch state q_k obeys
    dq/dt = -q / tau + dp_e/dt; for p_e linear over a step the exact update is
    q_n = a q_{n-1} + b (p_n - p_{n-1}),  a = exp(-dt/tau),  b = (tau/dt)(1 - a),
    i.e. one lfilter([b], [1, -a]) over the increments. |a| < 1 for every tau > 0, so
    the update is unconditionally stable (tau = 1e-5 s: a = 0, b -> tau/dt; tau = 100 s:
    a -> 1, b -> 1). The state starts relaxed (preload held before the trial).
    """
    dp = np.diff(p_elastic, axis=0, prepend=p_elastic[:1])
    out = np.array(p_elastic, dtype=np.float64, copy=True)
    for g, tau in branches:
        if g == 0:
            continue
        x = dt / max(float(tau), 1e-300)
        a = float(np.exp(-x))
        b = float(-np.expm1(-x) / x) if x > 1e-12 else 1.0
        out += g * signal.lfilter([b], [1.0, -a], dp, axis=0)
    return np.maximum(out, 0.0)


def local_skin_share(m: Mechanics) -> float:
    """Share of a small (mm-scale) indentation taken by the skin when pressed against the
    object's surface material: two elastic half-spaces in contact deform in proportion to
    their compliances (1 - nu^2) / E (Hertz theory, Johnson 1985, Contact Mechanics, ch. 4); with the
    same Poisson ratio the skin's share is E_o / (E_o + E_s). Instantaneous moduli
    E (1 + g): the transients last milliseconds, far below the relaxation times. At a
    layer step the deformed zone is as deep as the step's contact band is wide (< 2 mm),
    i.e. inside the cover and, for heterogeneous objects, inside the Dragon Skin top layer,
    which is why the surface material (the top layer if any, else the bulk, with its
    override) sets the share. In [0, 1] for every allowed modulus."""
    e_s = m.e_skin * (1 + m.g_skin)
    e_o = m.e_top * (1 + m.g_top) if m.t_top > 0 else m.e_obj * (1 + m.g_obj)
    return float(e_o / (e_o + e_s))


def front_density(penetration: np.ndarray, width: float = LAYER_HEIGHT_M) -> np.ndarray:
    """Area fraction per unit height (1/m) of a cell's surface at the skin's level: a
    Gaussian kernel estimate at penetration 0 over the cell's sample points (last axis).
    By the coarea formula this is the contact-front length over the cell divided by the
    surface slope there, per cell area; zero where the cell is out of contact or entirely
    in contact (no surface at the skin's level)."""
    u = np.asarray(penetration, dtype=np.float64) / width
    return np.exp(-0.5 * u * u).mean(axis=-1) / (width * np.sqrt(2 * np.pi))


def front_acceleration(z: np.ndarray, density: np.ndarray, share: float, dt: float,
                       layer: float = LAYER_HEIGHT_M) -> np.ndarray:
    """Base acceleration (m/s^2, along the skin normal) of the cover under each node from
    the printed layer lines engaging as the contact front advances (``z``: skin-surface
    height at the node, m, time on axis 0; ``density``: :func:`front_density` at the same
    samples).

    The printed surface is a staircase of terraces ``layer`` high. The skin's mean
    compression under a cell grows at share |dz/dt| A(z), A the cell's area fraction in
    contact. On a staircase A jumps by dA = layer x density each time the skin's level
    crosses a terrace (loading or unloading alike), so the compression rate jumps: a
    velocity step share |dz/dt| dA of the cover's surface, i.e. an acceleration impulse.
    The smooth surface's share (share |dz/dt|^2 density, already in the quasi-static
    compression term) is subtracted, leaving the zero-mean transient train: its rate is
    |dz/dt| / layer, its size grows with the indentation rate, the local contact stiffness
    (``share``) and the area the surface offers at the skin's level (flat crests: few
    large impulses; steep flanks: many small ones). Zero without contact (density 0)
    and when the skin does not move along its normal."""
    z = np.asarray(z, dtype=np.float64)
    speed = np.abs(np.gradient(z, dt, axis=0))
    level = np.floor(z / layer)
    crossings = np.abs(np.diff(level, axis=0, prepend=level[:1]))
    return share * speed * density * (layer * crossings - speed * dt) / dt


def node_resonance(skin: str) -> tuple[float, float]:
    """(natural frequency Hz, damping ratio) of an accelerometer node on its silicone cover."""
    spec = C.SKIN_SPECS[skin]
    mat = C.MATERIALS[spec.silicone]
    e_inst = mat.youngs_modulus * (1 + mat.relaxation_strength)
    k = e_inst * NODE_AREA_M2 / (spec.cover_thickness_mm * 1e-3)
    return float(np.sqrt(k / NODE_MASS_KG) / (2 * np.pi)), SKIN_DAMPING[skin]


def skin_transmissibility(f: np.ndarray, fn: float, zeta: float) -> np.ndarray:
    """|H(f)| of base-excited acceleration transmission (2 zeta w s + w^2)/(s^2 + 2 zeta w s + w^2)."""
    r = np.asarray(f, dtype=np.float64) / fn
    num = 1.0 + (2 * zeta * r) ** 2
    den = (1.0 - r**2) ** 2 + (2 * zeta * r) ** 2
    return np.sqrt(num / den)


def antialias(f: np.ndarray, fs: float = C.FS_TACTILE) -> np.ndarray:
    """Accelerometer digital low-pass magnitude; tones at or above Nyquist are removed."""
    f = np.asarray(f, dtype=np.float64)
    r2 = (f / ACC_AA_HZ) ** 2
    r4 = r2 * r2
    h = 1.0 / np.sqrt(1.0 + r4 * r4)
    return np.where(f < 0.5 * fs, h, 0.0)


def skin_filter(fn: float, zeta: float, fs: float = C.FS_TACTILE) -> tuple[np.ndarray, np.ndarray]:
    """Digital (bilinear, pre-warped at fn) version of the node transmissibility; fn is
    capped at 0.45 fs (the hard skin's 317 Hz becomes 315 Hz at 700 Hz)."""
    fn = min(fn, 0.45 * fs)
    wn = 2 * fs * np.tan(np.pi * fn / fs)  # pre-warp
    b, a = signal.bilinear([2 * zeta * wn, wn**2], [1.0, 2 * zeta * wn, wn**2], fs)
    return b, a
