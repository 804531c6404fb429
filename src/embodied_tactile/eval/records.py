"""A run's scored results as one portable file: what :func:`~.pipeline.evaluate_run` returns
(every method's :class:`~.results.Results`, the KRR history rows, the info dict), written as a
compressed ``.npz`` with no pickled objects.

An evaluation keeps one record per run in ``<evaluation>/per_run/<key>.npz`` and reuses it
while nothing that decides it changed (:func:`~.pipeline.reuse_key`). A record copied into its
run folder as ``scored.npz`` (``experiments/study_grid.py archive``) stands in for the
checkpoint: the folder's small files and its record travel in git from one machine to the
next, and the study's report merges them with the runs trained there (``docs/generated/study_runs/``).

Arrays keep their dtype: a record reused by the evaluation folder that wrote it gives the
numbers of its first scoring to the last digit. An archived record (:func:`archive_runs`, the
one that travels in git) is written ``compact``: the predictions (:data:`COMPACT`, the bulk of
a record) standardised per factor and kept in float16 (measured on a study run of MULTI-L soft
pressing, 128 test trials x 300 frames, 4 methods: 0.82 MB against 1.6 MB in float32 and
3.5 MB in float64; each method's NMSE per factor moved by at most 2.1e-5 of itself). Everything else is
JSON inside the archive (``meta``), NaN included.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from ..jsonio import to_jsonable
from ..run.runfolder import ARCHIVED_RECORD

#: the record format; a record of another format is scored again (or refused where it cannot be)
FORMAT = 1
#: the name of a record in a run folder: the run's scored results where its checkpoint is not kept
IN_RUN = ARCHIVED_RECORD
#: Results fields a compact record keeps standardised in float16 (the per-frame predictions: the bulk of a record)
COMPACT = ("pred",)


class RecordError(ValueError):
    """A record that cannot be read (message names the file and what is wrong)."""


def _quantized(value: np.ndarray, arrays: dict[str, np.ndarray], where: str) -> dict:
    """``value`` (..., factors) standardised per factor (last axis) into float16 (a standardised
    value is at most sqrt(n) in size: float16 holds it for any n below 4e9), NaN kept; JSON
    holding the offset and scale that read it back."""
    flat = value.reshape(-1, value.shape[-1])
    seen = np.isfinite(flat).any(axis=0)
    offset = np.zeros(flat.shape[1])
    scale = np.ones(flat.shape[1])
    if seen.any():
        offset[seen] = np.nanmean(flat[:, seen], axis=0)
        spread = np.nanstd(flat[:, seen], axis=0)
        scale[seen] = np.where(spread > 0, spread, 1.0)
    arrays[where] = ((value - offset) / scale).astype(np.float16)
    return {"__standardised__": where, "offset": offset.tolist(), "scale": scale.tolist()}


def _pack(obj: Any, arrays: dict[str, np.ndarray], where: str, compact: bool = False) -> Any:
    """``obj`` as JSON types; each ndarray moved into ``arrays`` under ``where`` (its path)."""
    from .results import Results

    if isinstance(obj, Results):
        out = {}
        for f in dataclasses.fields(obj):
            value, key = getattr(obj, f.name), f"{where}.{f.name}"
            if compact and f.name in COMPACT and isinstance(value, np.ndarray) and value.dtype.kind == "f":
                out[f.name] = _quantized(value, arrays, key)
            else:
                out[f.name] = _pack(value, arrays, key)
        return {"__results__": out}
    if isinstance(obj, np.ndarray):
        arrays[where] = obj
        return {"__array__": where}
    if isinstance(obj, dict):
        return {str(k): _pack(v, arrays, f"{where}.{k}", compact) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_pack(v, arrays, f"{where}.{i}", compact) for i, v in enumerate(obj)]
    return to_jsonable(obj)


def _unpack(obj: Any, arrays) -> Any:
    from .results import Results

    if isinstance(obj, dict):
        if "__array__" in obj and len(obj) == 1:
            return arrays[obj["__array__"]]
        if "__standardised__" in obj:
            return arrays[obj["__standardised__"]].astype(np.float64) * np.asarray(obj["scale"]) + np.asarray(obj["offset"])
        if "__results__" in obj and len(obj) == 1:
            fields = {k: _unpack(v, arrays) for k, v in obj["__results__"].items()}
            known = {f.name for f in dataclasses.fields(Results)}
            return Results(**{k: v for k, v in fields.items() if k in known})
        return {k: _unpack(v, arrays) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_unpack(v, arrays) for v in obj]
    return obj


def write_record(path: str | os.PathLike, scored: tuple, fingerprint: dict[str, Any], compact: bool = False) -> Path:
    """Write ``scored`` = (results, history, info) and its ``fingerprint`` (what scored it: the
    code digest, the evaluation options, the baselines) atomically to ``path``; ``compact``:
    the predictions standardised in float16 (the archived copy)."""
    path = Path(path)
    arrays: dict[str, np.ndarray] = {}
    results, history, info = scored
    meta = {"format": FORMAT, "fingerprint": to_jsonable(fingerprint),
            "results": _pack(list(results), arrays, "results", compact), "history": _pack(list(history), arrays, "history"),
            "info": _pack(dict(info), arrays, "info")}
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as fh:
        np.savez_compressed(fh, __meta__=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8), **arrays)
    os.replace(tmp, path)
    return path


def read_fingerprint(path: str | os.PathLike) -> dict[str, Any]:
    """The fingerprint of the record at ``path`` (reads only its ``meta``)."""
    return _meta(Path(path))["fingerprint"]


def _meta(path: Path) -> dict[str, Any]:
    try:
        with zipfile.ZipFile(path) as z, z.open("__meta__.npy") as fh:
            meta = json.loads(np.load(io.BytesIO(fh.read())).tobytes())
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as err:
        raise RecordError(f"{path}: not a scored record ({type(err).__name__}: {err})") from None
    if meta.get("format") != FORMAT:
        raise RecordError(f"{path}: record format {meta.get('format')!r}, this code reads {FORMAT}")
    return meta


def read_record(path: str | os.PathLike) -> tuple[tuple, dict[str, Any]]:
    """-> ((results, history, info), fingerprint) of the record at ``path``; RecordError
    naming the file when it is not one."""
    path = Path(path)
    meta = _meta(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files if k != "__meta__"}
        scored = (_unpack(meta["results"], arrays), _unpack(meta["history"], arrays), _unpack(meta["info"], arrays))
    except (OSError, KeyError, ValueError, TypeError) as err:
        raise RecordError(f"{path}: damaged record ({type(err).__name__}: {err})") from None
    return scored, meta["fingerprint"]


#: what an archived run folder keeps beside its record (checkpoints, logs and Hydra's own
#: config are left behind): what the study's report and the study lanes read
RUN_FILES = ("config_resolved.yaml", "metrics.json", "provenance.json", "split.json", "krr_history.jsonl",
             ".hydra/overrides.yaml")
#: what an archived part folder (a multirun) keeps
PART_FILES = ("multirun.yaml",)


def _copy_files(src: Path, dst: Path, names: tuple[str, ...]) -> None:
    import shutil

    for name in names:
        if (src / name).is_file():
            (dst / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / name, dst / name)


def archive_runs(evaluation: str | os.PathLike, study: str | os.PathLike, dest: str | os.PathLike) -> list[Path]:
    """Every run the evaluation folder ``evaluation`` scored, from the study folder ``study``
    into ``dest`` at the same relative path: its :data:`RUN_FILES` and its record as
    :data:`IN_RUN` (and each part's :data:`PART_FILES`). A run already in ``dest`` is left as
    it is. The record is written compact (its predictions in float16). Returns the run folders
    written."""
    import shutil

    from ..jsonio import read_json

    evaluation, study, dest = Path(evaluation), Path(study).resolve(), Path(dest)
    runs = read_json(evaluation / "evaluation.json").get("runs")
    if runs is None:
        raise RecordError(f"{evaluation}: no evaluation.json with its runs (evaluate the study first)")
    written = []
    for info in runs:
        run = Path(info["run_dir"]).resolve()
        if info.get("archived") or not info.get("record"):
            continue
        target = dest / run.relative_to(study)
        if (target / IN_RUN).exists():
            continue
        tmp = target.with_name(f".{target.name}.tmp-{os.getpid()}")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        _copy_files(run, tmp, RUN_FILES)
        scored, fp = read_record(evaluation / info["record"])
        write_record(tmp / IN_RUN, scored, fp, compact=True)
        _copy_files(run.parent, target.parent, PART_FILES)
        os.replace(tmp, target)
        written.append(target)
    return written


def restore_runs(archive: str | os.PathLike, study: str | os.PathLike) -> list[Path]:
    """Every archived run folder of ``archive`` (one holding :data:`IN_RUN`) copied into the
    study folder ``study`` at the same relative path, where no folder of that name is: the
    study's lanes skip them as finished and its evaluation merges their records. Returns the
    folders copied."""
    import shutil

    archive, study = Path(archive), Path(study)
    copied = []
    for record in sorted(archive.rglob(IN_RUN)):
        rel = record.parent.relative_to(archive)
        if (study / rel).exists():
            continue
        shutil.copytree(record.parent, study / rel)
        _copy_files(record.parent.parent, study / rel.parent, PART_FILES)
        copied.append(study / rel)
    return copied


def digest(payload: Any) -> str:
    """A short digest of a JSON-able payload (the evaluation options of a fingerprint)."""
    return hashlib.sha256(json.dumps(to_jsonable(payload), sort_keys=True).encode()).hexdigest()[:24]


__all__ = ["FORMAT", "IN_RUN", "PART_FILES", "RUN_FILES", "RecordError", "archive_runs", "digest",
           "restore_runs", "read_fingerprint", "read_record", "write_record"]
