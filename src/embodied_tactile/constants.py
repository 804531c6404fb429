"""The experiment's fixed facts: wave objects, e-Skins, palpation primitives, sensors.

Pure Python + NumPy. Every other module (simulator, recorder, preprocessing, model
configs, evaluation tables) takes these facts from here, so the object catalogue and the
paper's action table exist exactly once.

Object index convention (documented in docs/reference/data_format.md)::

    object_id = 9 * frequency_index + 3 * material_index + amplitude_index   (0..26)
    object_id in 27..31: heterogeneous (thin stiff top layer over soft bulk)

with frequency in {10, 30, 50} /m, material in {Ecoflex 00-10, Ecoflex 00-50, PLA} and
amplitude in {5, 10, 20} mm (peak-to-peak of the surface height). The paper's "soft
objects" group {0,1,3,4,9,10,12,13,18,19,21,22} is taken verbatim for Table 2.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

# --------------------------------------------------------------------------- sensors
FS_TACTILE = 700.0  # Hz, e-Skin packets
FS_POSE = 100.0  # Hz, robot end-effector pose
TRIAL_DURATION = 10.0  # s of palpation per trial
N_TACTILE = int(round(FS_TACTILE * TRIAL_DURATION))  # 7000
N_POSE = int(round(FS_POSE * TRIAL_DURATION))  # 1000

ACC_GRID = (4, 4)
ACC_AXES = 3
ACC_RANGE_G = 2.0  # +-2 g
ACC_COUNTS_PER_G = 16384.0  # int16 at +-2 g
FSR_LAYERS = 2  # 0 = top (FSR_t), 1 = bottom (FSR_b)
FSR_GRID = (16, 16)
FSR_MAX_COUNT = 4095  # 12-bit ADC
TAXEL_PITCH_M = 2.5e-3
POSE_COLUMNS = ("x", "y", "z", "roll", "pitch", "yaw")  # m, m, m, rad, rad, rad

FACTOR_NAMES = ("spatial_frequency", "amplitude", "stiffness", "heterogeneity")
FACTOR_UNITS = ("1/m", "mm", "log10 Pa", "0/1")

SKINS = ("soft", "hard")
PRIMITIVES = ("pressing", "precession", "sliding")
SOURCES = ("simulated", "recorded")


# --------------------------------------------------------------------------- materials
@dataclass(frozen=True)
class Material:
    """Linear viscoelastic solid (standard linear solid / Zener).

    ``youngs_modulus`` is the long-term (relaxed) modulus E_inf in Pa; the instantaneous
    modulus is E_inf * (1 + relaxation_strength); ``relaxation_time`` is tau in s.
    """

    name: str
    youngs_modulus: float
    relaxation_strength: float
    relaxation_time: float
    density: float  # kg/m^3
    friction: float  # Coulomb coefficient against silicone skin


MATERIALS: Mapping[str, Material] = {
    "ecoflex_00_10": Material("Ecoflex 00-10", 55e3, 0.25, 0.8, 1040.0, 1.1),
    "ecoflex_00_50": Material("Ecoflex 00-50", 83e3, 0.20, 0.5, 1070.0, 1.0),
    "pla": Material("PLA", 3.5e9, 0.02, 0.05, 1240.0, 0.45),
    "ecoflex_00_31": Material("Ecoflex 00-31", 69e3, 0.22, 0.6, 1070.0, 1.0),
    "dragon_skin_30": Material("Dragon Skin 30", 590e3, 0.12, 0.3, 1080.0, 0.9),
}

OBJECT_MATERIALS = ("ecoflex_00_10", "ecoflex_00_50", "pla")
SPATIAL_FREQUENCIES = (10.0, 30.0, 50.0)  # 1/m
AMPLITUDES_MM = (5.0, 10.0, 20.0)  # peak-to-peak, mm

SOFT_OBJECTS = (0, 1, 3, 4, 9, 10, 12, 13, 18, 19, 21, 22)
HETEROGENEOUS_OBJECTS = (27, 28, 29, 30, 31)
#: the paper's Table 2 object groups, in its column order (``WaveObject.group``)
OBJECT_GROUPS = ("soft", "hard", "heterogeneous")
N_OBJECTS = 32


@dataclass(frozen=True)
class WaveObject:
    """One palpated object. Catalogue objects name their materials by ``MATERIALS`` key;
    objects of a simulated population (``sim.population``) carry their own :class:`Material`.
    Catalogue ids are 0..31; population ids start at :data:`POPULATION_ID_BASE`."""

    object_id: int
    spatial_frequency: float  # 1/m, centre of the band-pass
    amplitude_mm: float  # peak-to-peak surface height
    bulk: str | Material  # key into MATERIALS, or the material itself
    top_layer: str | Material | None = None  # heterogeneous objects: key into MATERIALS or the material
    top_thickness_mm: float = 0.0

    @property
    def heterogeneous(self) -> bool:
        return self.top_layer is not None

    @property
    def bulk_material(self) -> Material:
        return material(self.bulk)

    @property
    def top_material(self) -> Material | None:
        return None if self.top_layer is None else material(self.top_layer)

    @property
    def group(self) -> str:
        """The paper's Table 2 grouping: 'soft', 'hard' or 'heterogeneous'. Catalogue objects
        take the paper's lists verbatim (its "soft" group leaves out the 20 mm silicone
        objects); population objects: 'heterogeneous' with a top layer, 'hard' with a rigid
        bulk (E >= RIGID_MODULUS_PA), else 'soft'."""
        if self.object_id < N_OBJECTS:
            if self.object_id in HETEROGENEOUS_OBJECTS:
                return "heterogeneous"
            return "soft" if self.object_id in SOFT_OBJECTS else "hard"
        if self.heterogeneous:
            return "heterogeneous"
        return "hard" if self.bulk_material.youngs_modulus >= RIGID_MODULUS_PA else "soft"

    def factors(self) -> np.ndarray:
        """Ground truth (spatial frequency 1/m, amplitude mm, log10 E_bulk Pa, heterogeneity)."""
        return np.array(
            [
                self.spatial_frequency,
                self.amplitude_mm,
                np.log10(self.bulk_material.youngs_modulus),
                1.0 if self.heterogeneous else 0.0,
            ],
            dtype=np.float64,
        )

    def description(self) -> dict[str, float]:
        """The object's physical description beyond the factors (stored as trial attributes,
        docs/reference/data_format.md): the bulk's and the top layer's material parameters and the
        top layer's thickness (0 and NaN moduli for a homogeneous object)."""
        out: dict[str, float] = {"top_thickness_mm": float(self.top_thickness_mm if self.heterogeneous else 0.0)}
        for prefix, mat in (("bulk", self.bulk_material), ("top", self.top_material)):
            for k in MATERIAL_PARAMS:
                out[f"{prefix}_{k}"] = float("nan") if mat is None else float(getattr(mat, k))
        return out


#: bulk moduli at or above this are rigid (the paper's "hard" group: PLA; silicones are < 1 MPa)
RIGID_MODULUS_PA = 1e8
#: Material fields stored per layer as trial attributes (``bulk_<field>``, ``top_<field>``)
MATERIAL_PARAMS = ("youngs_modulus", "relaxation_strength", "relaxation_time", "density", "friction")
#: population objects have ids POPULATION_ID_BASE + k (catalogue ids stay 0..N_OBJECTS - 1)
POPULATION_ID_BASE = 1000


def material(key: str | Material) -> Material:
    """A material given by ``MATERIALS`` key or as itself."""
    return key if isinstance(key, Material) else MATERIALS[key]


def _build_objects() -> tuple[WaveObject, ...]:
    objs: list[WaveObject] = []
    for fi, f0 in enumerate(SPATIAL_FREQUENCIES):
        for mi, mat in enumerate(OBJECT_MATERIALS):
            for ai, amp in enumerate(AMPLITUDES_MM):
                objs.append(WaveObject(9 * fi + 3 * mi + ai, f0, amp, mat))
    # Heterogeneous: a 1-3 mm Dragon Skin 30 skin cast over Ecoflex 00-10 bulk.
    hetero = [(10.0, 10.0, 1.0), (30.0, 10.0, 2.0), (50.0, 10.0, 3.0), (30.0, 5.0, 2.0), (30.0, 20.0, 1.5)]
    for k, (f0, amp, th) in enumerate(hetero):
        objs.append(WaveObject(27 + k, f0, amp, "ecoflex_00_10", "dragon_skin_30", th))
    return tuple(objs)


OBJECTS: tuple[WaveObject, ...] = _build_objects()
assert [o.object_id for o in OBJECTS] == list(range(N_OBJECTS))


# --------------------------------------------------------------------------- skins
@dataclass(frozen=True)
class Skin:
    name: str
    silicone: str  # key into MATERIALS
    cover_thickness_mm: float  # silicone above the accelerometers
    interlayer_thickness_mm: float  # compliant layer between FSR_t and FSR_b
    total_thickness_mm: float


SKIN_SPECS: Mapping[str, Skin] = {
    "soft": Skin("soft", "ecoflex_00_31", 1.5, 3.0, 8.0),
    "hard": Skin("hard", "dragon_skin_30", 1.5, 3.0, 8.0),
}


# --------------------------------------------------------------------------- primitives
@dataclass(frozen=True)
class ActionSet:
    """One row of the paper's Table ``tab:action_config`` for one primitive."""

    primitive: str
    action_index: int  # 0-based; the paper's tables print action_index + 1
    params: Mapping[str, float] = field(default_factory=dict)

    def as_array(self) -> np.ndarray:
        return np.array([self.params[k] for k in ACTION_PARAM_NAMES[self.primitive]], dtype=np.float64)


#: Parameter names per primitive, in storage order. Amplitudes in mm or degrees, frequencies in Hz.
ACTION_PARAM_NAMES: Mapping[str, tuple[str, ...]] = {
    "pressing": ("A_z_mm", "omega_z_hz"),
    # The paper's table header says "(mm)" for the precession angles; they are angles:
    # we read the values as degrees of roll / pitch.
    "precession": ("A_alpha_beta_deg", "omega_alpha_beta_hz"),
    "sliding": ("A_xy_mm", "A_gamma_deg", "omega_xy_gamma_hz"),
}

_FREQS = (0.2, 0.4, 0.6, 0.8)


def _build_actions() -> Mapping[str, tuple[ActionSet, ...]]:
    out: dict[str, tuple[ActionSet, ...]] = {}
    for prim, amps in (
        ("pressing", [(2.0,), (4.0,), (6.0,), (8.0,)]),
        ("precession", [(3.0,), (4.0,), (5.0,), (6.0,)]),
        ("sliding", [(2.0, 3.0), (4.0, 4.0), (6.0, 5.0), (8.0, 6.0)]),
    ):
        rows = []
        for ai, amp in enumerate(amps):
            for fi, w in enumerate(_FREQS):
                values = (*amp, w)
                rows.append(ActionSet(prim, 4 * ai + fi, dict(zip(ACTION_PARAM_NAMES[prim], values))))
        out[prim] = tuple(rows)
    return out


ACTIONS: Mapping[str, tuple[ActionSet, ...]] = _build_actions()
N_ACTIONS = 16


def get_object(object_id: int) -> WaveObject:
    if not 0 <= int(object_id) < N_OBJECTS:
        raise ValueError(f"object_id must be in 0..{N_OBJECTS - 1}, got {object_id}")
    return OBJECTS[int(object_id)]


def get_action(primitive: str, action_index: int) -> ActionSet:
    if primitive not in ACTIONS:
        raise ValueError(f"primitive must be one of {PRIMITIVES}, got {primitive!r}")
    if not 0 <= int(action_index) < N_ACTIONS:
        raise ValueError(f"action_index must be in 0..{N_ACTIONS - 1}, got {action_index}")
    return ACTIONS[primitive][int(action_index)]
