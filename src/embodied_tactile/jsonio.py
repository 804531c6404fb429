"""JSON for run artefacts: one converter for numpy values and one atomic writer.

NumPy + stdlib only, so the simulator side, the cache and the evaluation all share it.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np


def to_jsonable(obj: Any, *, nan_to_none: bool = False) -> Any:
    """Plain JSON types from numpy arrays / scalars, bytes, tuples and mappings.

    ``nan_to_none`` maps non-finite floats to ``null`` (strict JSON); otherwise they stay
    floats (Python's json writes NaN / Infinity). Unknown objects become their ``str``.
    """
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v, nan_to_none=nan_to_none) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v, nan_to_none=nan_to_none) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist(), nan_to_none=nan_to_none)
    if isinstance(obj, bytes):
        return obj.decode()
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return None if nan_to_none and not math.isfinite(f) else f
    if obj is None or isinstance(obj, str):
        return obj
    if hasattr(obj, "item"):  # torch / numpy 0-d
        return to_jsonable(obj.item(), nan_to_none=nan_to_none)
    return str(obj)


def write_json(path: str | os.PathLike, payload: Any, *, indent: int = 2, nan_to_none: bool = False) -> Path:
    """Write JSON atomically (temp file + os.replace): a crash never leaves half a file."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(to_jsonable(payload, nan_to_none=nan_to_none), indent=indent, allow_nan=not nan_to_none))
    os.replace(tmp, path)
    return path


def read_json(path: str | os.PathLike) -> dict:
    """The JSON object in ``path``; ``{}`` when the file is missing or unreadable."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
