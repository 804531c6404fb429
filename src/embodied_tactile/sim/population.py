"""A population of simulated objects with continuous properties (docs/reference/simulator.md, "Object population").

Object ``k`` of population ``seed`` has id ``POPULATION_ID_BASE + k`` and is drawn from its
own stream ``SeedSequence([entropy, seed, k])``: it is the same object whatever the size
of the population, so a population of 64 training objects is a subset of one of 512.

Roles are fixed by ``k``: the first ``n_test`` objects are the test objects, the next
``n_val`` the validation objects, the next ``n_train`` the (labelled) training objects, and
the ``n_unlabelled`` after them unlabelled objects (training data whose property labels are
never served). A learning curve over the number of training or unlabelled objects therefore
scores every size on the same test objects, selects checkpoints on the same validation
objects and fits the read-out on the same labelled objects.

The draw (per object, independent):

* spatial frequency uniform over the catalogue's range, 10-50 1/m;
* amplitude log-uniform over 5-20 mm (the catalogue doubles it per level);
* with probability ``RIGID_SHARE`` a rigid object (PLA, the catalogue's material);
  otherwise a silicone whose relaxed Young's modulus is log-uniform over
  ``SILICONE_MODULUS_PA`` (1.5 decades around the catalogue's and the skins' silicones),
  its relaxation strength, relaxation time, density and friction interpolated in
  log10 E between the silicones of ``MATERIALS`` (held at the end values outside them);
* a silicone object is heterogeneous with probability ``HETEROGENEOUS_SHARE``: a Dragon
  Skin 30 top layer of thickness uniform over ``TOP_THICKNESS_MM`` over a bulk at most
  a third of the top layer's modulus (the catalogue's heterogeneous objects are a stiff skin
  over soft bulk), drawn log-uniform up to that bound.

Pure NumPy: no torch, no HDF5.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from embodied_tactile import constants as C

POPULATION_ENTROPY = 0x0B1EC7_5EED
SPATIAL_FREQUENCY = (10.0, 50.0)  # 1/m, uniform
AMPLITUDE_MM = (5.0, 20.0)  # log-uniform
SILICONE_MODULUS_PA = (10**4.5, 10**6.0)  # log-uniform: 31.6 kPa - 1 MPa
RIGID_SHARE = 0.2
HETEROGENEOUS_SHARE = 0.25  # of the silicone objects
TOP_LAYER = "dragon_skin_30"
TOP_THICKNESS_MM = (0.5, 3.0)
TOP_TO_BULK_MIN_RATIO = 3.0
RIGID = "pla"
#: the silicones the viscoelastic parameters are interpolated between (sorted by modulus)
_SILICONES = tuple(sorted((m for k, m in C.MATERIALS.items() if C.MATERIALS[k].youngs_modulus < C.RIGID_MODULUS_PA),
                          key=lambda m: m.youngs_modulus))


def silicone(youngs_modulus: float) -> C.Material:
    """A silicone of relaxed modulus ``youngs_modulus`` (Pa) with the catalogue silicones'
    viscoelastic parameters, density and friction interpolated in log10 E."""
    log_e = np.log10([m.youngs_modulus for m in _SILICONES])
    x = float(np.log10(youngs_modulus))
    at = {k: float(np.interp(x, log_e, [getattr(m, k) for m in _SILICONES]))
          for k in ("relaxation_strength", "relaxation_time", "density", "friction")}
    return C.Material(f"silicone E={youngs_modulus:.4g} Pa", float(youngs_modulus), **at)


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(10 ** rng.uniform(np.log10(lo), np.log10(hi)))


@lru_cache(maxsize=4096)
def population_object(k: int, seed: int = 0) -> C.WaveObject:
    """Object ``k`` of population ``seed`` (id ``POPULATION_ID_BASE + k``)."""
    if int(k) < 0 or int(seed) < 0:
        raise ValueError(f"population object index and seed must be >= 0, got k={k}, seed={seed}")
    rng = np.random.default_rng(np.random.SeedSequence([POPULATION_ENTROPY, int(seed), int(k)]))
    f0 = float(rng.uniform(*SPATIAL_FREQUENCY))
    amp = _log_uniform(rng, *AMPLITUDE_MM)
    kind, hetero = rng.uniform(), rng.uniform()  # drawn always: one stream layout for every object
    thickness = float(rng.uniform(*TOP_THICKNESS_MM))
    u_modulus = rng.uniform()
    oid = C.POPULATION_ID_BASE + int(k)
    if kind < RIGID_SHARE:
        return C.WaveObject(oid, f0, amp, RIGID)
    lo, hi = SILICONE_MODULUS_PA
    if hetero < HETEROGENEOUS_SHARE:
        hi = min(hi, C.MATERIALS[TOP_LAYER].youngs_modulus / TOP_TO_BULK_MIN_RATIO)
    e = float(10 ** (np.log10(lo) + u_modulus * (np.log10(hi) - np.log10(lo))))
    if hetero < HETEROGENEOUS_SHARE:
        return C.WaveObject(oid, f0, amp, silicone(e), TOP_LAYER, thickness)
    return C.WaveObject(oid, f0, amp, silicone(e))


def population_index(object_id: int) -> int:
    """k of a population object id (ValueError for a catalogue id)."""
    k = int(object_id) - C.POPULATION_ID_BASE
    if k < 0:
        raise ValueError(f"object {object_id} is not a population object (ids start at {C.POPULATION_ID_BASE})")
    return k


def population(n_train: int, *, seed: int = 0, n_val: int = 32, n_test: int = 64, n_unlabelled: int = 0
               ) -> dict[str, list[C.WaveObject]]:
    """The population's objects by role: ``{"test": [...], "val": [...], "train": [...]}``
    (objects 0..n_test-1, then n_val, then n_train), and ``"unlabelled"`` (the n_unlabelled
    objects after them) when n_unlabelled > 0."""
    for name, v, lo in (("n_train", n_train, 1), ("n_val", n_val, 1), ("n_test", n_test, 1),
                        ("n_unlabelled", n_unlabelled, 0)):
        if int(v) < lo:
            raise ValueError(f"population {name} must be >= {lo}, got {v}")
    labelled = int(n_test) + int(n_val) + int(n_train)
    objs = [population_object(k, seed) for k in range(labelled + int(n_unlabelled))]
    out = {"test": objs[:n_test], "val": objs[n_test:n_test + n_val], "train": objs[n_test + n_val:labelled]}
    if int(n_unlabelled) > 0:
        out["unlabelled"] = objs[labelled:]
    return out


def object_role(object_id: int, *, n_val: int, n_test: int, n_train: int | None = None) -> str:
    """'test', 'val' or 'train' of a population object id; with ``n_train``, 'unlabelled'
    for the objects after the training objects."""
    k = population_index(object_id)
    if n_train is not None and k >= n_test + n_val + n_train:
        return "unlabelled"
    return "test" if k < n_test else "val" if k < n_test + n_val else "train"
