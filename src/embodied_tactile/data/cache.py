"""Per-field HDF5 cache of preprocessed trials, keyed by config + code version + source data.

One file per field, ``<cache_dir>/<field>-<key>.h5``, so that an acc-only run never reads
or computes FSR data. ``key`` hashes

* that field's part of :class:`PreprocessConfig` (``cfg.field_dict(field)``),
* ``PREPROCESS_VERSION`` and ``CACHE_FORMAT_VERSION``,
* per raw file: its trial names, each trial's attributes and a SHA-256 digest of the
  *stored* bytes (compressed chunks, read without decompressing) of exactly the raw
  datasets the field reads and validates (``preprocess.RAW_FIELDS`` with their clocks and
  lost-packet positions; an absent ``lost_at`` adds nothing, so older files keep their keys).

A trial is cached under its group name, from its one raw file (``source_file``): a group
name in two raw files is an error (``rawformat.check_unique_names``), never two halves of
one trial. A field that cannot be computed for a trial is listed in that field's
``skipped``; the DataModule then skips the trial whole.

Layout::

    /                 attrs: format, cache_format_version, preprocess_version, field, key,
                             config (full JSON), field_config (JSON), sources (JSON list),
                             skipped (JSON list of {file, trial, field, problem}),
                             n_trials, complete=True
    /trials/<name>/<field>   the processed array; group attrs = the raw trial's attrs
                             plus ``source_file``

A cache is written under a temporary name and ``os.replace``-d into place, so a file with
the final name is always complete; an existing one is reused as is.
"""

from __future__ import annotations

import collections
import contextlib
import hashlib
import json
import logging
import mmap
import multiprocessing as mp
import os
import uuid
import zlib
from pathlib import Path
from typing import Any, BinaryIO, Iterable, Iterator, Mapping, Sequence

import h5py
import numpy as np

from embodied_tactile.data.preprocess import (
    FIELDS,
    PREPROCESS_VERSION,
    RAW_FIELDS,
    PreprocessConfig,
    output_shape,
    preprocess_trials,
    time_problems,
)
from embodied_tactile.data import rawformat
from embodied_tactile.jsonio import to_jsonable
from embodied_tactile.data.rawformat import FIELDS as RAW_PATHS
from embodied_tactile.data.rawformat import TrialFormatError
from embodied_tactile.options.data import SceneOptions
from embodied_tactile.run.workers import init_worker, one_blas_thread

log = logging.getLogger(__name__)

CACHE_FORMAT = "embodied-tactile-preprocessed"
CACHE_FORMAT_VERSION = 2  # 2: a crc32 of each cached array (dataset attr ``crc32``), checked once per preparation


# ============================================================================ fingerprints
def _dataset_digest(ds: h5py.Dataset, fh: BinaryIO | None = None) -> str:
    """SHA-256 (first 128 bits) of a dataset's stored bytes: its compressed chunks exactly as stored in the
    file (no decompression; adjacent chunks read in one go from ``fh``), or the data of a
    contiguous dataset; plus shape, dtype, filters and the chunk index. SHA-256: hardware
    accelerated (SHA-NI), 1.4 GB/s against blake2b's 0.74 on the development box; this hash
    runs over every stored byte before a build (chunk by chunk on the build's worker pool)."""
    h = hashlib.sha256()
    h.update(repr((ds.shape, str(ds.dtype), ds.chunks, ds.compression, ds.compression_opts)).encode())
    if ds.chunks is None or fh is None:
        h.update(np.ascontiguousarray(ds[()]).tobytes())
        return h.hexdigest()[:32]
    spans: list[tuple[int, int, tuple, int]] = []
    try:
        ds.id.chunk_iter(lambda i: spans.append((i.byte_offset, i.size, tuple(i.chunk_offset), i.filter_mask)))
    except (AttributeError, NotImplementedError):  # HDF5 < 1.12.3: hash the decoded data
        h.update(np.ascontiguousarray(ds[()]).tobytes())
        return h.hexdigest()[:32]
    spans.sort()  # by position in the file: adjacent chunks are read in one go
    blobs: dict[int, memoryview] = {}
    i = 0
    while i < len(spans):
        j, end = i + 1, spans[i][0] + spans[i][1]
        while j < len(spans) and spans[j][0] == end:
            end += spans[j][1]
            j += 1
        fh.seek(spans[i][0])
        data = fh.read(end - spans[i][0])
        if len(data) != end - spans[i][0]:
            raise OSError(f"truncated file: chunk bytes {spans[i][0]}..{end} missing")
        view = memoryview(data)  # slices without copying
        for off, size, _, _ in spans[i:j]:
            blobs[off] = view[off - spans[i][0] : off - spans[i][0] + size]
        i = j
    for off, size, chunk, mask in sorted(spans, key=lambda s: s[2]):  # hash in logical order
        h.update(repr((chunk, mask, size)).encode())
        h.update(blobs[off])
    return h.hexdigest()[:32]


def _raw_datasets(field: str) -> list[str]:
    """Dataset paths (inside a trial group) that processing ``field`` reads and validates."""
    return [RAW_PATHS[f] for f in rawformat.fields_needed(RAW_FIELDS[field])]


_LOST_PATHS = {RAW_PATHS[f] for f in rawformat.LOST_FIELDS}


def _trial_digests(f: h5py.File, fh: BinaryIO, name: str, dpaths: Iterable[str]) -> dict[str, str]:
    """``{dataset path: digest}`` of one trial's datasets ``dpaths`` (``"missing"`` /
    ``"unreadable: ..."`` for a dataset that is absent / cannot be read; an absent optional
    lost-packet dataset is left out: it adds nothing to the fingerprint)."""
    out: dict[str, str] = {}
    try:
        g: h5py.Group | None = f["trials"][name]
    except (OSError, KeyError, RuntimeError):
        g = None
    for dpath in dpaths:
        if dpath in _LOST_PATHS and g is not None and dpath not in g:
            continue  # optional, newer than the format: absent adds nothing
        try:
            out[dpath] = "missing" if g is None or dpath not in g else _dataset_digest(g[dpath], fh)
        except (OSError, KeyError, RuntimeError, ValueError, TypeError) as exc:
            out[dpath] = f"unreadable: {type(exc).__name__}: {exc}"
    return out


def _attrs_json(attrs: dict[str, Any]) -> str:
    return json.dumps(to_jsonable(attrs), sort_keys=True)


def _combine_fingerprint(
    names: Iterable[str], attrs_json: dict[str, str], digests: dict[str, dict[str, str]], fields: Sequence[str]
) -> dict[str, str]:
    """``{field: digest}`` of one raw file from its trials' attrs (JSON) and dataset digests
    (:func:`_trial_digests`), trials in sorted name order."""
    hs = {f: hashlib.blake2b(digest_size=16) for f in fields}
    for name in sorted(names):
        for fld in fields:
            hs[fld].update(f"{name}\0{attrs_json[name]}\0".encode())
            for dpath in _raw_datasets(fld):
                if dpath in digests[name]:
                    hs[fld].update(f"{dpath}={digests[name][dpath]}\0".encode())
    return {fld: h.hexdigest() for fld, h in hs.items()}


def trial_fingerprint(name: str, attrs_json: str, digests: Mapping[str, str], field: str) -> str:
    """One trial's digest for one field: its name, attributes (JSON) and the stored bytes of
    the raw datasets that field reads (16 hex digits)."""
    h = hashlib.blake2b(f"{name}\0{attrs_json}\0".encode(), digest_size=8)
    for dpath in _raw_datasets(field):
        if dpath in digests:
            h.update(f"{dpath}={digests[dpath]}\0".encode())
    return h.hexdigest()


def _fields_datasets(fields: Iterable[str]) -> list[str]:
    return list(dict.fromkeys(d for f in fields for d in _raw_datasets(f)))


def cache_key(field: str, cfg: PreprocessConfig, source_digests: Sequence[str]) -> str:
    payload = {
        "field": field,
        "cache_format_version": CACHE_FORMAT_VERSION,
        "preprocess_version": PREPROCESS_VERSION,
        "config": cfg.field_dict(field),
        "sources": list(source_digests),
    }
    return hashlib.blake2b(json.dumps(payload, sort_keys=True).encode(), digest_size=8).hexdigest()


def _is_complete(path: Path) -> bool:
    try:
        with h5py.File(path, "r") as f:
            return bool(f.attrs.get("complete", False)) and f.attrs.get("format") == CACHE_FORMAT
    except OSError:
        return False


# ============================================================================ worker
def _err(file: str, trial: str, field: str, problem: str) -> dict[str, str]:
    return {"file": str(file), "trial": trial, "field": field, "problem": problem}


#: The parent's output buffer (an anonymous shared mapping), inherited by the forked pool
#: workers: they place the processed arrays of a chunk in a slot of it instead of pickling
#: ~2.8 MB per trial through the pool's pipe (about 3 CPU ms per trial, both ends).
_OUT: mmap.mmap | None = None


def _slot_layout(cfg: PreprocessConfig, fields: Sequence[str]) -> tuple[int, dict[str, tuple[int, tuple[int, ...]]]]:
    """``(bytes per trial, {field: (offset in a trial's span, shape)})`` of a slot of ``_OUT``."""
    layout, off = {}, 0
    for f in fields:
        shape = output_shape(cfg, f)
        layout[f] = (off, shape)
        off += 4 * int(np.prod(shape))  # float32
    return off, layout


def _slot_array(slot: int, slot_bytes: int, pos: int, trial_bytes: int, off: int, shape: tuple[int, ...]) -> np.ndarray:
    assert _OUT is not None
    return np.frombuffer(_OUT, np.float32, int(np.prod(shape)), slot * slot_bytes + pos * trial_bytes + off).reshape(shape)


def _digest_chunk(task: tuple[str, list[str], list[str]]) -> dict[str, dict[str, str]]:
    """Worker: ``{trial: {dataset path: digest}}`` of one chunk of one raw file."""
    path, names, dpaths = task
    with rawformat.open_raw(path) as f, open(path, "rb") as fh:
        return {name: _trial_digests(f, fh, name, dpaths) for name in names}


def _process_chunk(task: tuple) -> tuple[list, list]:
    """Read one chunk of trials (one open of the file, only the raw fields needed, the
    attrs ``scan_raw`` read) and preprocess it batched.

    Returns ``(results, errors)``: results ``[(name, {field: array or None})]`` (None: in
    ``slot`` of ``_OUT`` at the trial's position in the chunk), errors as dicts
    (TrialFormatError does not survive pickling)."""
    path, names, attrs, fields, cfg_dict, slot, slot_bytes = task
    cfg = PreprocessConfig.from_dict(cfg_dict)
    raw_union = sorted({r for f in fields for r in RAW_FIELDS[f]})
    results: dict[str, dict[str, np.ndarray]] = {}
    errors: list[dict] = []
    groups: dict[tuple[str, ...], list] = {}  # fields that can be computed -> trials
    try:
        fh = rawformat.open_raw(path)
    except TrialFormatError as exc:  # the file went away or broke since the scan
        return [], [_err(exc.file, name, "*", f"{exc.field}: {exc.problem}") for name in names]
    long: list[str] = []

    def add(tr, flds) -> None:  # the fields the trial's time coverage allows (time_problems)
        probs, seconds = time_problems(tr, cfg, flds)
        errors.extend(_err(path, tr.name, f, p) for f, p in probs.items())
        keep = tuple(f for f in flds if f not in probs)
        if keep:
            groups.setdefault(keep, []).append(tr)
            if seconds is not None:
                long.append(f"{tr.name} ({seconds:.3g} s)")

    with fh:
        for name, at in zip(names, attrs):
            try:
                tr = rawformat.read_trial(path, name, fields=raw_union, attrs=at, file=fh)
                add(tr, tuple(fields))
                continue
            except TrialFormatError as exc:
                first = exc
            # isolate the broken field(s): retry each field with its own raw datasets
            ok: list[str] = []
            tr = None
            for f in fields:
                try:
                    t_f = rawformat.read_trial(path, name, fields=RAW_FIELDS[f], attrs=at, file=fh)
                    tr = t_f if tr is None else _merge(tr, t_f)
                    ok.append(f)
                except TrialFormatError as exc:
                    errors.append(_err(exc.file, exc.trial, f, f"{exc.field}: {exc.problem}"))
            if not ok and not errors:
                errors.append(_err(first.file, first.trial, "*", f"{first.field}: {first.problem}"))
            if ok and tr is not None:
                add(tr, tuple(ok))
    if long:
        log.warning("%s: %d trial(s) longer than the scene's %g s window are cut to it: %s%s", path, len(long),
                    cfg.duration, ", ".join(long[:3]), " ..." if len(long) > 3 else "")
    for flds, trials in groups.items():
        try:
            out = preprocess_trials(trials, cfg, flds)
            for i, tr in enumerate(trials):
                results[tr.name] = {f: out[f][i] for f in flds}
        except (ValueError, FloatingPointError) as exc:  # isolate the offending trial(s)
            for tr in trials:
                try:
                    o = preprocess_trials([tr], cfg, flds)
                    results[tr.name] = {f: o[f][0] for f in flds}
                except (ValueError, FloatingPointError) as e2:
                    errors.extend(_err(path, tr.name, f, f"preprocess: {e2}") for f in flds)
            log.debug("chunk fell back to per-trial processing: %s", exc)
    ordered = [(n, results[n]) for n in names if n in results]
    if slot is not None:  # into the shared slot; an array of an unexpected shape travels pickled
        trial_bytes, layout = _slot_layout(cfg, fields)
        for pos, (name, arrays) in enumerate(ordered):
            for f, arr in arrays.items():
                off, shape = layout[f]
                if arr.shape == shape and arr.dtype == np.float32:
                    _slot_array(slot, slot_bytes, pos, trial_bytes, off, shape)[...] = arr
                    arrays[f] = None
    return ordered, errors


def _merge(a: rawformat.RawTrial, b: rawformat.RawTrial) -> rawformat.RawTrial:
    """Fields of one trial (same file, same group) read in two passes, as one RawTrial."""
    assert a.name == b.name, (a.name, b.name)
    for fld in RAW_PATHS:
        va, vb = getattr(a, fld), getattr(b, fld)
        if (va is None or len(va) == 0) and vb is not None and len(vb):
            setattr(a, fld, vb)
    return a


class _Workers:
    """The build's process pool (fork: workers inherit ``_OUT``), or this process when
    ``workers <= 1``. ``map`` keeps task order; ``process`` runs chunk tasks with at most
    ``slots`` in flight, each owning one slot of ``_OUT`` until the parent has written it."""

    def __init__(self, workers: int, n_tasks: int, slot_bytes: int):
        self.n = min(workers, n_tasks)
        self.pool = None
        self.slot_bytes = slot_bytes
        self.slots = self.n + 2 if self.n > 1 and "fork" in mp.get_all_start_methods() else 0
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> "_Workers":
        global _OUT
        if self.n <= 1:
            self._stack.enter_context(one_blas_thread())
            return self
        if self.slots:
            _OUT = mmap.mmap(-1, max(1, self.slots * self.slot_bytes))  # shared; pages touched on use, in the workers
            self._stack.callback(self._close_out)
            ctx = mp.get_context("fork")
        else:
            ctx = mp.get_context()
        self.pool = self._stack.enter_context(ctx.Pool(self.n, initializer=init_worker))
        return self

    @staticmethod
    def _close_out() -> None:
        global _OUT
        _OUT = None  # unmapped once the last view of it is gone (closing it now would fail on a live view)

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def map(self, fn, tasks: list) -> list:
        return [fn(t) for t in tasks] if self.pool is None else self.pool.map(fn, tasks, chunksize=1)

    def process(self, tasks: list) -> Iterator[tuple[tuple, int | None, list, list]]:
        """Yield ``(task, slot, results, errors)`` in task order; the slot is free again
        once the caller asks for the next one."""
        if self.pool is None:
            for t in tasks:
                yield (t, None, *_process_chunk((*t, None, 0)))
            return
        if not self.slots:  # no fork: the arrays travel pickled
            for t, out in zip(tasks, self.pool.imap(_process_chunk, [(*t, None, 0) for t in tasks])):
                yield (t, None, *out)
            return
        free = list(range(self.slots))
        pending: collections.deque = collections.deque()
        todo = iter(tasks)

        def submit() -> None:
            while free:
                t = next(todo, None)
                if t is None:
                    return
                slot = free.pop()
                pending.append((t, slot, self.pool.apply_async(_process_chunk, ((*t, slot, self.slot_bytes),))))

        submit()
        while pending:
            t, slot, res = pending.popleft()
            yield (t, slot, *res.get())
            free.append(slot)
            submit()


_ATTR_TYPES: dict[Any, tuple] = {}


def _write_attrs(g: h5py.Group, attrs: dict[str, Any]) -> None:
    """``g.attrs[k] = v`` for a new group, through h5py's low-level calls: the same types
    (str as variable-length UTF-8, numbers as 0-d arrays, lists as arrays) at half the
    CPU time of the high-level setter (no existence check, HDF5 types made once per dtype)."""
    for k, v in attrs.items():
        data = np.array(v, dtype=h5py.string_dtype()) if isinstance(v, str) else np.asarray(v)
        key = "str" if isinstance(v, str) else data.dtype if data.dtype.kind != "O" else None
        types = _ATTR_TYPES.get(key) if key is not None else None
        if types is None:
            types = (h5py.h5t.py_create(data.dtype, logical=True), h5py.h5t.py_create(data.dtype))
            if key is not None:
                _ATTR_TYPES[key] = types
        at = h5py.h5a.create(g.id, k.encode(), types[0], h5py.h5s.create_simple(data.shape))
        try:
            at.write(data, mtype=types[1])
        finally:
            at.close()


# ============================================================================ build
def build_cache(
    raw_paths: Sequence[str | os.PathLike],
    cache_dir: str | os.PathLike,
    cfg: PreprocessConfig | None = None,
    fields: Iterable[str] = FIELDS,
    *,
    workers: int = SceneOptions.preprocess_workers,
    strict: bool = False,
    chunk_size: int = 8,
    compression: str | None = None,
    trial_digests: dict[str, dict[str, str]] | None = None,
) -> dict[str, Path]:
    """Preprocess every valid trial of ``raw_paths`` into one cache file per field and
    return ``{field: path}``. Existing complete caches with the same key are reused;
    missing fields are computed in one pass (each trial read once, only the raw datasets
    those fields need). Bad trials are logged, skipped and listed in the root attr
    ``skipped``; ``strict=True`` raises the first TrialFormatError instead. A trial name
    found in two raw files raises, strict or not (``rawformat.check_unique_names``).
    ``trial_digests``, when given, is filled with ``{field: {trial: digest}}``
    (:func:`trial_fingerprint`, from the digests the cache key is computed from: nothing
    is hashed twice)."""
    cfg = (cfg or PreprocessConfig()).validate()
    fields = tuple(dict.fromkeys(fields))
    unknown = set(fields) - set(FIELDS)
    if unknown:
        raise ValueError(f"unknown fields {sorted(unknown)}; choose from {FIELDS}")
    paths = rawformat.unique_paths(raw_paths)  # each file once, order kept
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)

    # 1) trial index (attrs only, read once here and handed on; data are validated when a
    #    worker reads them); raises on a trial name held by two files
    infos, scan_errors = rawformat.scan_raw(paths, validate_data=False, strict=strict)
    by_file: dict[str, list[str]] = {p: [] for p in paths}
    attrs: dict[tuple[str, str], dict[str, Any]] = {}
    for info in infos:
        by_file[info.file].append(info.name)
        attrs[(info.file, info.name)] = info.attrs
    chunks = [(p, by_file[p][i : i + chunk_size]) for p in paths for i in range(0, len(by_file[p]), chunk_size)]
    slot_bytes = chunk_size * _slot_layout(cfg, fields)[0]

    with _Workers(workers, len(chunks), slot_bytes) as pool:
        # 2) keys from config + fingerprints of only the datasets each field reads, hashed
        #    chunk by chunk on the pool
        dpaths = _fields_datasets(fields)
        found = pool.map(_digest_chunk, [(p, names, dpaths) for p, names in chunks])
        per_file: dict[str, dict[str, dict[str, str]]] = {p: {} for p in paths}
        for (p, _), d in zip(chunks, found):
            per_file[p].update(d)
        digests: dict[str, list[str]] = {f: [] for f in fields}
        for p in paths:
            if by_file[p]:
                ajson = {n: _attrs_json(attrs[(p, n)]) for n in by_file[p]}
                fp = _combine_fingerprint(by_file[p], ajson, per_file[p], fields)
            else:
                fp = {f: "no-valid-trials" for f in fields}
            for f in fields:
                digests[f].append(fp[f])
            if trial_digests is not None:
                for n in by_file[p]:
                    for f in fields:
                        trial_digests.setdefault(f, {})[n] = trial_fingerprint(n, ajson[n], per_file[p][n], f)
        targets = {f: cache_dir / f"{f}-{cache_key(f, cfg, digests[f])}.h5" for f in fields}
        todo = tuple(f for f in fields if not _is_complete(targets[f]))
        for f in fields:
            if f not in todo:
                log.info("cache hit for %s: %s", f, targets[f])
        if not todo:
            return targets

        # 3) compute the missing fields chunk by chunk on the pool; the parent streams the
        #    results into temp files while the workers go on
        cfg_dict = cfg.to_dict()
        tasks = [(p, names, [attrs[(p, n)] for n in names], todo, cfg_dict) for p, names in chunks]
        trial_bytes, layout = _slot_layout(cfg, todo)
        base_err = [_err(e.file, e.trial, "*", f"{e.field}: {e.problem}") for e in scan_errors]
        skipped: dict[str, list[dict]] = {f: list(base_err) for f in todo}
        tmp = {f: targets[f].with_name(f"{targets[f].name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}") for f in todo}
        files = {f: h5py.File(tmp[f], "w") for f in todo}
        counts = {f: 0 for f in todo}
        try:
            for f, h in files.items():
                h.attrs["format"] = CACHE_FORMAT
                h.attrs["complete"] = False
                h.create_group("trials")
            for (path, _, _, _, _), slot, results, errors in pool.process(tasks):
                for e in errors:
                    if strict:
                        raise TrialFormatError(e["file"], e["trial"], e["field"], e["problem"])
                    log.warning("skipping %s / %s for %s: %s", e["file"], e["trial"], e["field"], e["problem"])
                    for f in todo if e["field"] == "*" else [e["field"]]:
                        skipped[f].append(e)
                source = os.path.abspath(path)  # one identity, whatever the cwd or spelling
                for pos, (name, arrays) in enumerate(results):
                    trial_attrs = {**attrs[(path, name)], "source_file": source}
                    for f, arr in arrays.items():
                        if arr is None:
                            arr = _slot_array(slot, slot_bytes, pos, trial_bytes, *layout[f])
                        g = files[f]["trials"].create_group(name)  # names are unique: scan_raw checked
                        g.create_dataset(f, data=arr, compression=compression).attrs["crc32"] = _crc(arr)
                        _write_attrs(g, trial_attrs)
                        counts[f] += 1
            for f, h in files.items():
                h.attrs.update(
                    {
                        "cache_format_version": CACHE_FORMAT_VERSION,
                        "preprocess_version": PREPROCESS_VERSION,
                        "field": f,
                        "key": targets[f].stem.split("-", 1)[1],
                        "config": json.dumps(cfg.to_dict(), sort_keys=True),
                        "field_config": json.dumps(cfg.field_dict(f), sort_keys=True),
                        "sources": json.dumps(paths),
                        "source_digests": json.dumps(digests[f]),
                        "skipped": json.dumps(skipped[f]),
                        "n_trials": counts[f],
                        "complete": True,
                    }
                )
                h.close()
                os.replace(tmp[f], targets[f])
                log.info("wrote %s (%d trials, %d skipped)", targets[f], counts[f], len(skipped[f]))
        finally:
            for f, h in files.items():
                if h.id.valid:
                    h.close()
                if tmp[f].exists():
                    tmp[f].unlink()
    return targets


# ============================================================================ checksums
def _crc(arr: np.ndarray) -> int:
    return zlib.crc32(memoryview(np.ascontiguousarray(arr)).cast("B"))


def verify_cache(path: str | os.PathLike) -> list[str]:
    """The ``<trial>/<field>`` arrays of a cache file whose crc32 does not match the one
    stored when it was written (or that cannot be read); [] when every array is intact. Reads
    the whole file once (the preparation stage runs it once per run, not per step)."""
    bad: list[str] = []
    try:
        with h5py.File(path, "r") as f:
            for name, g in f["trials"].items():
                for fld, ds in g.items():
                    try:
                        ok = int(ds.attrs["crc32"]) == _crc(ds[()])
                    except (OSError, KeyError, RuntimeError, ValueError):
                        ok = False
                    if not ok:
                        bad.append(f"{name}/{fld}")
    except (OSError, KeyError, RuntimeError) as exc:
        return [f"*: unreadable ({exc})"]
    return bad


# ============================================================================ reading
def load_cached(path: str | os.PathLike, trial_name: str, field: str) -> np.ndarray:
    """The processed ``field`` array of one trial."""
    with h5py.File(path, "r") as f:
        return f["trials"][trial_name][field][()]


def list_cached(path: str | os.PathLike) -> list[tuple[str, dict[str, Any]]]:
    """``[(trial_name, attrs)]`` of a cache file, in file order."""
    with h5py.File(path, "r") as f:
        return [(name, rawformat.read_attrs(g)) for name, g in f["trials"].items()]


def cache_info(path: str | os.PathLike) -> dict[str, Any]:
    """Root attrs of a cache file, JSON attrs decoded."""
    with h5py.File(path, "r") as f:
        out = rawformat.read_attrs(f)
    for k in ("config", "field_config", "sources", "source_digests", "skipped"):
        if k in out:
            out[k] = json.loads(out[k])
    return out
