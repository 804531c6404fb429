"""Target encodings: what the alignment regresses and NMSE scores, per factor.

The catalogue's ground truth (``constants.WaveObject.factors``) is physical: spatial
frequency in 1/m, amplitude in mm, stiffness as log10 of the bulk Young's modulus in Pa,
heterogeneity 0/1. NMSE divides by the target's variance, so the encoding decides which
confusions count. In log10 Pa the three bulk materials sit at 4.74 / 4.92 / 9.54: the PLA vs
silicone step carries almost all the variance, and confusing the two Ecoflex grades costs
about 2e-4 NMSE. The study cannot then say whether a modality tells the silicones apart.

Encodings (``encode_factors``):

* ``design_rank`` (default): every ordinal factor as the rank of the paper's design level
  (0, 1, 2): spatial frequency 10 / 30 / 50 1/m (equally spaced: the same NMSE as 1/m),
  amplitude 5 / 10 / 20 mm (a doubling per level, so one step costs the same everywhere),
  stiffness Ecoflex 00-10 / Ecoflex 00-50 / PLA (each material step counts the same);
  heterogeneity stays 0/1. A value between two levels maps linearly between their ranks
  (stiffness in log10 Pa); a value outside the levels is an error.
* ``physical``: the catalogue's units unchanged (the earlier default; stiffness in log10 Pa).

Shore hardness was considered for stiffness: the Ecoflex grades are Shore 00-10 and 00-50
while PLA is measured on the Shore D scale, so the three materials share no scale; the rank
keeps the order without inventing a conversion.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ..constants import AMPLITUDES_MM, FACTOR_NAMES, FACTOR_UNITS, MATERIALS, OBJECT_MATERIALS, SPATIAL_FREQUENCIES
from ..options.alignment import TARGET_ENCODINGS

DEFAULT_TARGETS = "design_rank"

#: the paper's design levels of each ordinal factor, in the catalogue's units (ascending)
DESIGN_LEVELS: Mapping[str, tuple[float, ...]] = {
    "spatial_frequency": tuple(float(f) for f in SPATIAL_FREQUENCIES),
    "amplitude": tuple(float(a) for a in AMPLITUDES_MM),
    "stiffness": tuple(float(np.log10(MATERIALS[m].youngs_modulus)) for m in OBJECT_MATERIALS),
}

_RANK_UNITS = {"spatial_frequency": "rank of 10/30/50 1/m", "amplitude": "rank of 5/10/20 mm",
               "stiffness": "rank of Ecoflex 00-10/00-50/PLA", "heterogeneity": "0/1"}


def design_range(encoding: str = DEFAULT_TARGETS) -> np.ndarray:
    """Per factor (FACTOR_NAMES order), the span of the paper's design in ``encoding``'s units:
    highest minus lowest design level (heterogeneity 0/1: 1). The range a min-max scaling to
    [0, 1] over the design divides by."""
    lo = [DESIGN_LEVELS[f][0] if f in DESIGN_LEVELS else 0.0 for f in FACTOR_NAMES]
    hi = [DESIGN_LEVELS[f][-1] if f in DESIGN_LEVELS else 1.0 for f in FACTOR_NAMES]
    enc = encode_factors(np.array([lo, hi]), encoding)
    return enc[1] - enc[0]


def target_units(encoding: str) -> tuple[str, ...]:
    """The unit of each factor's target under ``encoding`` (FACTOR_NAMES order)."""
    _check(encoding)
    if encoding == "physical":
        return tuple(FACTOR_UNITS)
    return tuple(_RANK_UNITS[f] for f in FACTOR_NAMES)


def describe_targets(encoding: str) -> str:
    """One sentence for captions: the encoding and each factor's unit."""
    units = ", ".join(f"{f} [{u}]" for f, u in zip(FACTOR_NAMES, target_units(encoding)))
    return f"Targets: {encoding} ({units})."


def encode_factors(factors, encoding: str = DEFAULT_TARGETS) -> np.ndarray:
    """(n, 4) catalogue factors (physical units, NaN = unknown) -> (n, 4) targets of ``encoding``;
    ``physical`` also takes a scene's own (n, K) factors (the pendulum's) unchanged.

    Raises ValueError naming the factor, the value and the allowed range when a finite value
    lies outside the design levels (``design_rank``)."""
    _check(encoding)
    f = np.array(factors, dtype=np.float64, copy=True)
    if encoding == "physical" and f.ndim == 2:  # any scene's own factors (the pendulum's w0, d) as they are
        return f
    if f.ndim != 2 or f.shape[1] != len(FACTOR_NAMES):
        raise ValueError(f"factors must be (n, {len(FACTOR_NAMES)}), got shape {f.shape}")
    for k, name in enumerate(FACTOR_NAMES):
        levels = DESIGN_LEVELS.get(name)
        if levels is None:
            continue
        col = f[:, k]
        ok = np.isfinite(col)
        tol = 1e-5 * max(1.0, abs(levels[-1]))  # factors served as float32 by the DataModule
        bad = ok & ((col < levels[0] - tol) | (col > levels[-1] + tol))
        if bad.any():
            raise ValueError(f"factor {name}: value {col[bad][0]!r} outside the design levels "
                             f"[{levels[0]}, {levels[-1]}] (targets=design_rank; use targets=physical)")
        col[ok] = np.interp(col[ok], levels, np.arange(len(levels), dtype=np.float64))
    return f


def encode_split(split: Mapping, encoding: str = DEFAULT_TARGETS) -> dict:
    """A split dict (``factors`` + anything else) with its factors encoded; other keys shared."""
    out = dict(split)
    out["factors"] = encode_factors(split["factors"], encoding)
    return out


def _check(encoding: str) -> None:
    if encoding not in TARGET_ENCODINGS:
        raise ValueError(f"targets must be one of {TARGET_ENCODINGS}, got {encoding!r}")
