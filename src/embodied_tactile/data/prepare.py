"""Data preparation stage: raw trials -> per-field caches -> the scene's usable trials.

:func:`prepare_scene` does, for one :class:`Scene` (skin x primitive x channels x objects
x actions, simulated or recorded), under an advisory lock on the data folder
(:func:`data_dir_lock`, so parallel sweep jobs and DDP ranks can share ``data/``):

1. simulator source: simulate the missing trials into ``<data_dir>/raw/<skin>_<primitive>.h5``
   (``sim.generate_dataset``; trials already there are kept). Recorded files are never written;
2. build (or find) the per-field preprocessing caches (``data.cache.build_cache``; only the
   fields of the scene's channels: an acc-only scene never reads FSR data);
3. list the cached trials of the scene, skipping bad ones with their reason
   (:func:`list_trials`).

It returns :class:`PreparedData`: the cache files, the usable trials, the skipped trials
with reasons, the interrupted recordings left out. The DataModule splits and serves it
(``TactileDataModule.prepare_data`` calls this stage); ``python -m embodied_tactile.run.prepare_cli``
runs it on its own. No torch here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import glob
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import h5py

from embodied_tactile import constants as C
from embodied_tactile.data.rawformat import unique_paths
from embodied_tactile.data.modality import fields_for_channels
from embodied_tactile.options.data import SceneOptions, scene_values

log = logging.getLogger(__name__)

#: ``data.objects`` value of the simulated object population (``sim.population``)
POPULATION = "population"

#: A population scene with more trials than this ((training + validation + test objects) x
#: actions x repetitions) is refused unless ``allow_large_population`` is set: its
#: estimate is printed first (docs/reference/simulator.md, "Object population").
POPULATION_MAX_TRIALS = 10_000
#: Estimates per trial (docs/experiments/population_scene_cost.md; docs/reference/data_format.md):
#: raw file 3.4 MB, each cached field (acc, fsr) 0.94 MB, 0.41 CPU s of simulation and
#: preprocessing.
RAW_MB_PER_TRIAL = 3.4
CACHE_MB_PER_FIELD = 0.94
CPU_S_PER_TRIAL = 0.41


def population_estimate(n_objects: int, n_val: int, n_test: int, n_actions: int, repetitions: int,
                        fields: Sequence[str], workers: int, n_unlabelled: int = 0) -> tuple[int, float, float]:
    """``(trials, disk GB, wall hours)`` of preparing a population scene from scratch
    (``n_unlabelled`` unlabelled objects on top of the labelled ones)."""
    trials = (int(n_objects) + int(n_val) + int(n_test) + int(n_unlabelled)) * int(n_actions) * int(repetitions)
    mb = trials * (RAW_MB_PER_TRIAL + CACHE_MB_PER_FIELD * sum(f != "actions" for f in fields))
    return trials, mb / 1e3, trials * CPU_S_PER_TRIAL / max(1, int(workers)) / 3600


def check_population_size(n_objects: int, n_val: int, n_test: int, n_actions: int, repetitions: int,
                          fields: Sequence[str], workers: int, allow: bool, n_unlabelled: int = 0) -> None:
    """ValueError with the estimate when the population has more than POPULATION_MAX_TRIALS
    trials and ``allow`` is false."""
    trials, gb, hours = population_estimate(n_objects, n_val, n_test, n_actions, repetitions, fields, workers,
                                            n_unlabelled)
    if trials > POPULATION_MAX_TRIALS and not allow:
        extra = f" + {n_unlabelled} unlabelled" if n_unlabelled else ""
        raise ValueError(
            f"data.n_objects={n_objects}: the population scene has {trials:,} trials ({n_objects} + {n_val} + {n_test}{extra} "
            f"objects x {n_actions} action(s) x {repetitions}), more than the {POPULATION_MAX_TRIALS:,} allowed "
            f"without data.allow_large_population=true; preparing it takes about {gb:,.0f} GB of disk and "
            f"{hours:,.1f} h with {workers} worker(s)")


@contextlib.contextmanager
def data_dir_lock(data_dir: Path) -> Iterator[None]:
    """Exclusive advisory lock on a data folder while trials are simulated and caches built.

    Parallel sweep jobs (joblib launcher, DDP ranks, several users) share ``data/``: without
    it two jobs would append to the same raw HDF5 file at once. POSIX only; elsewhere the
    lock is a no-op and parallel jobs need separate data folders.
    """
    data_dir.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    with open(data_dir / ".prepare.lock", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


_IMPORTED = __import__("time").time()


def process_start_time() -> float:
    """When this process started, in seconds since the epoch (Linux: ``/proc/self/stat``'s
    start time after boot + ``/proc/stat``'s boot time); elsewhere when this module was
    imported."""
    try:
        stat = Path("/proc/self/stat").read_text()
        ticks = int(stat.rsplit(")", 1)[1].split()[19])  # field 22: starttime, in clock ticks after boot
        boot = next(int(ln.split()[1]) for ln in Path("/proc/stat").read_text().splitlines() if ln.startswith("btime "))
        return boot + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return _IMPORTED


def remove_stale_temporaries(folder: Path) -> list[Path]:
    """Remove the ``*.tmp-*`` files in ``folder`` last written before this process started:
    what a killed cache build left (a build under way holds :func:`data_dir_lock`, which the
    caller holds, and writes after its own start). Each one is named in a warning."""
    started = process_start_time()
    removed = []
    for tmp in sorted(folder.glob("*.tmp-*")) if folder.is_dir() else []:
        try:
            if tmp.is_file() and tmp.stat().st_mtime < started:
                tmp.unlink()
                removed.append(tmp)
                log.warning("removed %s: a temporary file of a preparation that did not finish", tmp)
        except FileNotFoundError:
            continue
    return removed


#: the factors an unlabelled object's trials are listed with: its labels are never read
UNLABELLED = (float("nan"),) * len(C.FACTOR_NAMES)


@dataclass(frozen=True)
class TrialRef:
    name: str
    object_id: int
    action_index: int
    skin: str
    primitive: str
    factors: tuple[float, float, float, float]


def catalogue_trials(actions: Sequence[int] | None = None, repetitions: int = SceneOptions.repetitions,
                     skin: str = SceneOptions.skin, primitive: str = SceneOptions.primitive) -> list[TrialRef]:
    """The trials a simulated scene of the 32 wave objects lists (objects x ``actions``, None:
    all 16, x ``repetitions``), named as the raw file names them, without simulating: for
    split arithmetic (which trials are held out, how many batches an epoch has)."""
    from ..constants import N_ACTIONS, OBJECTS
    from .rawformat import trial_name

    acts = range(N_ACTIONS) if actions is None else [int(a) for a in actions]
    return [TrialRef(trial_name({"object_id": o.object_id, "skin": skin, "primitive": primitive, "action_index": a,
                                 "repetition": r}), o.object_id, a, skin, primitive, tuple(float(x) for x in o.factors()))
            for o in OBJECTS for a in acts for r in range(int(repetitions))]


@dataclass(frozen=True)
class Scene:
    """What to prepare: the data keys of ``configs/data/*.yaml`` that decide which trials
    exist and how they are preprocessed (not the split or the loaders).

    ``source="simulated"``: raw file ``<data_dir>/raw/<skin>_<primitive>.h5``, missing trials
    simulated; ``"recorded"``: ``raw_files`` (paths or glob patterns), never generated.
    ``objects`` / ``actions``: subsets (None = all). ``objects="population"`` (simulated
    only): the object population of ``sim.population`` with ``n_objects`` training objects,
    ``n_val_objects`` validation and ``n_test_objects`` test objects, drawn with
    ``population_seed``, and ``n_unlabelled_objects`` unlabelled objects after them, listed
    with NaN factors (:func:`list_trials`): trained on, never labelled. ``preprocess``: ``PreprocessConfig`` keyword arguments. ``strict``:
    a bad raw trial is fatal instead of skipped. ``include_incomplete``: also use recordings
    marked ``complete=False``.
    """

    data_dir: str
    source: str
    raw_files: tuple[str, ...]
    skin: str
    primitive: str
    channels: tuple[str, ...]
    objects: tuple[int, ...] | str | None
    n_objects: int
    n_val_objects: int
    n_test_objects: int
    population_seed: int
    n_unlabelled_objects: int
    actions: tuple[int, ...] | None
    repetitions: int
    sim_seed: int
    sim_workers: int = field(compare=False)  # how, not what: scenes equal whatever the workers
    preprocess: Mapping[str, Any]
    preprocess_workers: int = field(compare=False)
    strict: bool
    include_incomplete: bool
    allow_large_population: bool = field(compare=False)
    keep_raw: bool = field(compare=False)  # how the files are kept, not what the trials are

    def __post_init__(self) -> None:
        if self.source not in C.SOURCES:
            raise ValueError(f"source must be one of {C.SOURCES}, got {self.source!r}")
        if self.skin not in C.SKINS:
            raise ValueError(f"skin must be one of {C.SKINS}, got {self.skin!r}")
        if self.primitive not in C.PRIMITIVES:
            raise ValueError(f"primitive must be one of {C.PRIMITIVES}, got {self.primitive!r}")
        if self.source == "recorded" and not self.raw_files:
            raise ValueError("source='recorded' needs raw_files (paths or glob patterns of recorded HDF5 files)")
        if isinstance(self.objects, str):
            if self.objects != POPULATION:
                raise ValueError(f"objects must be a list of object ids, null or {POPULATION!r}, got {self.objects!r}")
            if self.source != "simulated":
                raise ValueError("objects='population' needs the simulator (source='simulated')")
            for k in ("n_objects", "n_val_objects", "n_test_objects"):
                if isinstance(getattr(self, k), bool) or not isinstance(getattr(self, k), int) or getattr(self, k) < 1:
                    raise ValueError(f"{k} must be an integer >= 1, got {getattr(self, k)!r}")
            if (isinstance(self.n_unlabelled_objects, bool) or not isinstance(self.n_unlabelled_objects, int)
                    or self.n_unlabelled_objects < 0):
                raise ValueError(f"n_unlabelled_objects must be an integer >= 0, got {self.n_unlabelled_objects!r}")
            if isinstance(self.population_seed, bool) or not isinstance(self.population_seed, int) or self.population_seed < 0:
                raise ValueError(f"population_seed must be an integer >= 0, got {self.population_seed!r}")
            check_population_size(self.n_objects, self.n_val_objects, self.n_test_objects,
                                  C.N_ACTIONS if self.actions is None else len(self.actions), self.repetitions,
                                  fields_for_channels(self.channels), self.sim_workers, self.allow_large_population,
                                  self.n_unlabelled_objects)
        elif self.n_unlabelled_objects:
            raise ValueError(f"n_unlabelled_objects={self.n_unlabelled_objects} needs objects='population'")
        if not isinstance(self.keep_raw, bool):
            raise ValueError(f"keep_raw must be true or false, got {self.keep_raw!r}")
        if not self.keep_raw and self.source != "simulated":
            raise ValueError("keep_raw=false needs the simulator (source='simulated'): recordings are never deleted")
        norm = {
            "data_dir": str(self.data_dir),
            "raw_files": tuple(str(f) for f in (self.raw_files or ())),
            "channels": tuple(self.channels),
            "objects": (None if self.objects is None else self.objects if isinstance(self.objects, str)
                        else tuple(sorted(int(o) for o in self.objects))),
            "actions": None if self.actions is None else tuple(sorted(int(a) for a in self.actions)),
            "repetitions": int(self.repetitions), "sim_seed": int(self.sim_seed),
            "sim_workers": int(self.sim_workers), "preprocess": dict(self.preprocess or {}),
            "preprocess_workers": int(self.preprocess_workers), "strict": bool(self.strict),
            "include_incomplete": bool(self.include_incomplete),
        }
        for k, v in norm.items():
            object.__setattr__(self, k, v)
        fields_for_channels(self.channels)  # unknown channels fail here, naming them

    @classmethod
    def from_config(cls, data: Mapping[str, Any] | None = None, /, **kw: Any) -> "Scene":
        """The scene of a data config (``cfg.data``, or keyword arguments): its preparation
        keys (:func:`~embodied_tactile.options.data.scene_values`: the defaults where it is silent,
        ``actions: null`` all 16 sets); the split and loader keys are the DataModule's and are ignored here."""
        return cls(**scene_values({**(data or {}), **kw}))

    @property
    def is_population(self) -> bool:
        return self.objects == POPULATION

    def population_objects(self) -> dict[str, list[C.WaveObject]]:
        """The population's objects by role (``sim.population.population``)."""
        from embodied_tactile.sim.population import population

        return population(self.n_objects, seed=self.population_seed, n_val=self.n_val_objects,
                          n_test=self.n_test_objects, n_unlabelled=self.n_unlabelled_objects)

    def object_ids(self) -> set[int] | None:
        """The ids of the scene's objects (None = every object in the raw files)."""
        if self.is_population:
            return {o.object_id for objs in self.population_objects().values() for o in objs}
        return None if self.objects is None else set(self.objects)

    def object_roles(self) -> dict[int, str] | None:
        """Population scenes: object id -> 'train' | 'val' | 'test' | 'unlabelled' (fixed by the
        draw); else None."""
        if not self.is_population:
            return None
        return {o.object_id: role for role, objs in self.population_objects().items() for o in objs}

    @property
    def fields(self) -> list[str]:
        """Cached fields the channels need (always with ``actions``)."""
        return fields_for_channels(self.channels)

    @property
    def cache_dir(self) -> Path:
        return Path(self.data_dir) / "cache"

    @property
    def raw_paths(self) -> list[Path]:
        """The raw files. Recorded: each ``raw_files`` entry is a path or a glob pattern
        (``*``, ``?``, ``[...]``, ``**``), absolute, ``~`` or relative to the working
        directory; matches sorted, each file once, as absolute paths. An entry naming an
        existing file is that file, even with glob characters in its path (``x [1]/a.h5``;
        ``glob.escape`` writes a pattern for such a folder). A pattern that matches
        nothing, or a path that does not exist, is an error naming it. Simulated:
        ``raw/<skin>_<primitive>.h5`` for simulator seed 0, ``raw/<skin>_<primitive>_sim<seed>.h5``
        for another (one file per simulated dataset: the trial names do not hold the seed)."""
        if self.source == "simulated":
            suffix = "" if int(self.sim_seed) == 0 else f"_sim{int(self.sim_seed)}"
            prefix = f"population{int(self.population_seed)}_" if self.is_population else ""
            return [Path(self.data_dir) / "raw" / f"{prefix}{self.skin}_{self.primitive}{suffix}.h5"]
        paths: list[str] = []
        for pattern in self.raw_files:
            expanded = os.path.expanduser(str(pattern))
            if os.path.isfile(expanded):  # an existing file is taken literally, '[', '*' or '?' in its path or not
                matches = [expanded]
            elif glob.has_magic(expanded):
                matches = sorted(p for p in glob.glob(expanded, recursive=True) if os.path.isfile(p))
                if not matches:
                    raise FileNotFoundError(f"data.raw_files pattern {pattern!r} matches no file (cwd {os.getcwd()})")
            elif not os.path.isfile(expanded):
                raise FileNotFoundError(f"data.raw_files: recorded raw file not found: {pattern!r} (cwd {os.getcwd()})")
            else:
                matches = [expanded]
            paths.extend(os.path.abspath(p) for p in matches)
        return [Path(p) for p in unique_paths(paths)]

    def preprocess_config(self):
        from embodied_tactile.data.preprocess import PreprocessConfig

        cfg = PreprocessConfig(**self.preprocess)
        cfg.validate()
        return cfg


@dataclass
class PreparedData:
    """What :func:`prepare_scene` prepared.

    ``cache_files``: ``{field: path}``; ``trials``: the scene's usable trials (sorted by
    name); ``skipped``: ``{file, trial, field, problem}`` of every trial left out as bad;
    ``excluded_incomplete``: names of interrupted recordings left out (empty with
    ``include_incomplete``); ``simulated``: trials simulated by this call; ``cache_built``:
    fields whose cache this call computed (the others were cache hits)."""

    scene: Scene
    raw_files: list[str]
    cache_files: dict[str, str]
    trials: list[TrialRef]
    skipped: list[dict[str, str]] = field(default_factory=list)
    excluded_incomplete: list[str] = field(default_factory=list)
    simulated: int = 0
    cache_built: list[str] = field(default_factory=list)
    #: ``{field: {trial: digest}}`` of every valid raw trial (its name, attributes and the
    #: bytes that field reads): a run's data identity per trial (run.provenance.data_identity)
    trial_digests: dict[str, dict[str, str]] = field(default_factory=dict)
    #: the raw file was deleted (``keep_raw=False``): now, or by an earlier preparation
    raw_dropped: bool = False

    def summary(self) -> str:
        """Multi-line report (printed by the CLI)."""
        s = self.scene
        lines = [f"prepared {s.source} scene skin={s.skin} primitive={s.primitive} channels={list(s.channels)} "
                 f"in {s.data_dir}",
                 f"raw files: {', '.join(self.raw_files)}"
                 + (" (deleted, keep_raw=false: the caches stand for it)" if self.raw_dropped else "")]
        if s.source == "simulated":
            lines.append(f"simulated: {self.simulated} new trial(s)")
        lines.append(f"trials: {len(self.trials)} usable, {len(self.skipped)} skipped, "
                     f"{len(self.excluded_incomplete)} incomplete left out")
        lines += [f"  skipped {e.get('file')} / {e.get('trial')} ({e.get('field')}): {e.get('problem')}"
                  for e in self.skipped]
        if self.excluded_incomplete:
            lines.append(f"  incomplete (data.include_incomplete=true uses them): {', '.join(self.excluded_incomplete)}")
        lines.append("cache files:")
        lines += [f"  {fld}: {path} ({'built' if fld in self.cache_built else 'cache hit'})"
                  for fld, path in self.cache_files.items()]
        return "\n".join(lines)


def _n_raw_trials(path: Path) -> int:
    if not path.exists():
        return 0
    with h5py.File(path, "r") as f:
        return len(f["trials"]) if "trials" in f else 0


def prepare_scene(scene: Scene, *, simulate: bool = True) -> PreparedData:
    """Simulate the missing trials (simulator source, ``simulate=True``), build or find the
    caches and list the usable trials, all under :func:`data_dir_lock` (which first removes
    the temporary files a killed build left: :func:`remove_stale_temporaries`).

    ``simulate=False`` (a DDP rank whose rank 0 prepared the scene) only finds the caches:
    their keys are deterministic, so nothing is recomputed when they exist.

    ``keep_raw=False`` (simulated): every field is cached, then the raw file is deleted and a
    record beside it (:func:`dropped_record_path`) keeps what finds the caches again: the raw
    file's trials and, per field, its digests. A later preparation whose trials the record
    covers uses the caches it names; one it does not cover (other trials, another preprocessing
    configuration, another physics version, a damaged cache) simulates the raw file again from
    its seed first."""
    from embodied_tactile.data.cache import build_cache, verify_cache
    from embodied_tactile.data.preprocess import FIELDS

    with data_dir_lock(Path(scene.data_dir)):
        remove_stale_temporaries(scene.cache_dir)
        found = _from_dropped(scene)
        if found is not None:
            cache_files, digests = found
            raw_paths = [str(p) for p in scene.raw_paths]
            trials, skipped, incomplete = list_trials(scene, cache_files, raw_paths)
            return PreparedData(scene=scene, raw_files=raw_paths, cache_files=cache_files, trials=trials,
                                skipped=skipped, excluded_incomplete=incomplete, trial_digests=digests,
                                raw_dropped=True)
        simulated = 0
        if scene.source == "simulated" and simulate:
            from embodied_tactile.sim import generate_dataset

            raw = scene.raw_paths[0]
            raw.parent.mkdir(parents=True, exist_ok=True)
            before = _n_raw_trials(raw)
            generate_dataset(
                raw, skin=scene.skin, primitive=scene.primitive, objects=_scene_objects(scene),
                actions=scene.actions if scene.actions is not None else range(C.N_ACTIONS),
                repetitions=scene.repetitions, seed=scene.sim_seed, workers=scene.sim_workers,
            )
            simulated = _n_raw_trials(raw) - before
            dropped_record_path(raw).unlink(missing_ok=True)  # the raw file is here again: the record is history
        raw_paths = [str(p) for p in scene.raw_paths]  # recorded: raises for a missing file or an empty pattern
        fields = tuple(scene.fields) if scene.keep_raw else FIELDS  # before dropping the raw file: every field
        existing = set(scene.cache_dir.glob("*.h5")) if scene.cache_dir.exists() else set()
        digests: dict[str, dict[str, str]] = {}
        files = build_cache(raw_paths, scene.cache_dir, scene.preprocess_config(), fields=fields,
                            workers=scene.preprocess_workers, strict=scene.strict, trial_digests=digests)
        # a cache found (not built now) is checked once per preparation: each array against its crc32
        damaged = {fld: bad for fld, path in files.items() if Path(path) in existing and (bad := verify_cache(path))}
        if damaged:  # set the damaged files aside (kept) and rebuild those fields from the raw files
            asides = {}
            for fld, bad in damaged.items():
                asides[fld] = _set_aside(Path(files[fld]))
                log.warning("%s: %d cached array(s) fail their checksum (e.g. %s); moved to %s, rebuilding %s from "
                            "the raw files", files[fld], len(bad), ", ".join(bad[:3]), asides[fld].name, fld)
            files = build_cache(raw_paths, scene.cache_dir, scene.preprocess_config(), fields=fields,
                                workers=scene.preprocess_workers, strict=scene.strict)
            for aside in asides.values():  # rebuilt: the newest damaged copy is kept for inspection, no older one
                _prune_set_aside(aside)
        built = [k for k, v in files.items() if Path(v) not in existing and k in scene.fields]
        cache_files = {k: str(v) for k, v in files.items() if k in scene.fields}
        trials, skipped, incomplete = list_trials(scene, cache_files, raw_paths)
        dropped = not scene.keep_raw and simulate and _drop_raw(scene, {k: Path(v) for k, v in files.items()}, digests)
    return PreparedData(scene=scene, raw_files=raw_paths, cache_files=cache_files, trials=trials, skipped=skipped,
                        excluded_incomplete=incomplete, simulated=simulated, cache_built=built,
                        trial_digests={k: v for k, v in digests.items() if k in scene.fields}, raw_dropped=dropped)


def _scene_objects(scene: Scene) -> list:
    """The objects a simulated scene simulates: its population's, its list, or all 32."""
    if scene.is_population:
        return [o for objs in scene.population_objects().values() for o in objs]
    return list(scene.objects) if scene.objects is not None else list(range(C.N_OBJECTS))


def _requested_trials(scene: Scene) -> set[str]:
    """The raw trial names a simulated scene asks for (``sim.generate_dataset``'s)."""
    from embodied_tactile.sim.dataset import requested_trials

    return requested_trials(_scene_objects(scene), scene.skin, scene.primitive,
                            scene.actions if scene.actions is not None else range(C.N_ACTIONS), scene.repetitions)


#: ``format`` of the record a deleted raw file leaves (:func:`dropped_record_path`)
DROPPED_FORMAT = "embodied-tactile-dropped-raw"


def dropped_record_path(raw: Path) -> Path:
    """``<raw file>.dropped.json``: what a simulated raw file deleted by ``keep_raw=False`` left."""
    return raw.with_name(raw.name + ".dropped.json")


def _drop_raw(scene: Scene, files: Mapping[str, Path], digests: Mapping[str, Mapping[str, str]]) -> bool:
    """Write the record of the scene's raw file (atomically), then delete the raw file; a file
    holding any trial not marked ``source = "simulated"`` is kept (False), with a warning
    (docs/reference/data_format.md, "What is never deleted")."""
    from embodied_tactile.data.cache import cache_info
    from embodied_tactile.sim.physics import PHYSICS_VERSION

    raw = scene.raw_paths[0]
    with h5py.File(raw, "r") as f:
        names = sorted(f["trials"]) if "trials" in f else []
        other = next((n for n in names if f["trials"][n].attrs.get("source") not in ("simulated", b"simulated")), None)
    if other is not None:
        log.warning("keep_raw=false: %s is kept, its trial %s is not marked source=simulated", raw, other)
        return False
    record = {
        "format": DROPPED_FORMAT, "raw_file": raw.name, "skin": scene.skin, "primitive": scene.primitive,
        "sim_seed": scene.sim_seed, "sim_physics_version": PHYSICS_VERSION, "raw_bytes": raw.stat().st_size,
        "trials": names,
        "fields": {fld: {"source_digest": cache_info(path)["source_digests"][0], "trial_digests": dict(digests[fld])}
                   for fld, path in files.items()},
    }
    target = dropped_record_path(raw)
    tmp = target.with_name(f"{target.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(record, sort_keys=True))
    os.replace(tmp, target)
    raw.unlink()
    log.info("deleted %s (%.2f GB, %d trials; keep_raw=false): every field is cached, %s finds the caches",
             raw, record["raw_bytes"] / 1e9, len(names), target.name)
    return True


def _from_dropped(scene: Scene) -> tuple[dict[str, str], dict[str, dict[str, str]]] | None:
    """``(cache_files, trial_digests)`` of a simulated scene whose raw file was deleted
    (``keep_raw=False``), found through its record: None when the raw file is there, there is
    no record, or the record does not cover the scene (its trials, physics version or
    fields), or a cache it names is missing or damaged (each said in a log line): then the
    raw file is simulated again."""
    from embodied_tactile.data.cache import _is_complete, cache_key, verify_cache
    from embodied_tactile.sim.physics import PHYSICS_VERSION

    if scene.source != "simulated":
        return None
    raw = scene.raw_paths[0]
    path = dropped_record_path(raw)
    if raw.exists() or not path.exists():
        return None
    try:
        rec = json.loads(path.read_text())
        ok = rec.get("format") == DROPPED_FORMAT
    except (OSError, ValueError):
        rec, ok = {}, False
    if not ok:
        log.warning("%s is not a record of a deleted raw file; simulating %s again", path, raw.name)
        return None
    why = None
    if (rec.get("skin"), rec.get("primitive"), rec.get("sim_seed")) != (scene.skin, scene.primitive, scene.sim_seed):
        why = f"it records skin={rec.get('skin')} primitive={rec.get('primitive')} sim_seed={rec.get('sim_seed')}"
    elif rec.get("sim_physics_version") != PHYSICS_VERSION:
        why = f"its trials were simulated by physics version {rec.get('sim_physics_version')}, not {PHYSICS_VERSION}"
    elif missing := _requested_trials(scene) - set(rec.get("trials", [])):
        why = f"the scene asks for {len(missing)} trial(s) it does not list (e.g. {sorted(missing)[0]})"
    cfg = scene.preprocess_config()
    files: dict[str, str] = {}
    for fld in scene.fields if why is None else ():
        entry = rec.get("fields", {}).get(fld)
        target = None if entry is None else scene.cache_dir / f"{fld}-{cache_key(fld, cfg, [entry['source_digest']])}.h5"
        if target is None or not _is_complete(target):
            why = f"no cache of field {fld} at this preprocessing configuration"
            break
        if bad := verify_cache(target):
            why = f"{target.name}: {len(bad)} cached array(s) fail their checksum"
            break
        files[fld] = str(target)
    if why is not None:
        log.warning("%s: %s; simulating %s again from seed %d", path.name, why, raw.name, scene.sim_seed)
        return None
    log.info("raw file %s was deleted (keep_raw=false); its caches, found by %s: %s", raw.name, path.name,
             ", ".join(Path(f).name for f in files.values()))
    return files, {fld: dict(rec["fields"][fld]["trial_digests"]) for fld in scene.fields}


def _set_aside(path: Path) -> Path:
    """Rename a damaged cache file to ``<name>.corrupt`` (``-1``, ``-2``... when taken)."""
    target, n = path.with_name(path.name + ".corrupt"), 0
    while target.exists():
        n += 1
        target = path.with_name(f"{path.name}.corrupt-{n}")
    path.rename(target)
    return target


def _prune_set_aside(keep: Path) -> list[Path]:
    """Once a damaged cache file's rebuild succeeded: remove the older damaged copies of the
    same file (``<name>.corrupt``, ``<name>.corrupt-N``) beside ``keep``, the newest, each
    named in a log line: one copy per cache file, not one per failure (each as large as
    the cache)."""
    name = keep.name.rsplit(".corrupt", 1)[0]
    removed = []
    for old in keep.parent.glob(f"{glob.escape(name)}.corrupt*"):
        if old != keep and (old.name == f"{name}.corrupt" or old.name.startswith(f"{name}.corrupt-")):
            old.unlink(missing_ok=True)
            removed.append(old)
            log.info("removed %s: an older damaged copy of %s (the newest is kept: %s)", old, name, keep.name)
    return removed


def list_trials(scene: Scene, cache_files: Mapping[str, str], raw_paths: Sequence[str] | None = None
                ) -> tuple[list[TrialRef], list[dict[str, str]], list[str]]:
    """Trials present in every needed cache and matching the scene.

    Returns ``(trials, skipped, excluded_incomplete)``: the usable trials, every trial left
    out as bad, once each (listed by a cache, absent from one: see :func:`_whole_trials`;
    mislabelled; or dead in one channel: :func:`_without_dead_channels`; :func:`_one_per_trial`), and the
    interrupted recordings left out (``complete=False``; used with ``include_incomplete``).
    RuntimeError when no trial is usable."""
    fields = scene.fields
    skipped: list[dict[str, str]] = []
    per_field: list[dict[str, dict[str, Any]]] = []
    for fld in fields:
        with h5py.File(cache_files[fld], "r") as f:
            # the raw files a cache was built from, by position, are the ones it stands for now:
            # its key holds their digests in that order (a copied or moved data folder keeps its
            # caches; only the paths stored in them are old)
            try:
                built_from = [os.path.abspath(p) for p in json.loads(f.attrs.get("sources", "[]"))]
            except (TypeError, ValueError):
                built_from = []
            now = [os.path.abspath(p) for p in raw_paths] if raw_paths is not None else built_from
            moved = dict(zip(built_from, now)) if len(built_from) == len(now) else {}
            entries = {}
            for name, g in f["trials"].items():
                entries[name] = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in g.attrs.items()}
                src = os.path.abspath(str(entries[name].get("source_file")))
                entries[name]["source_file"] = moved.get(src, src)
            per_field.append(entries)
            try:
                listed = json.loads(f.attrs.get("skipped", "[]"))
            except (TypeError, ValueError):
                listed = []
            for entry in listed:  # a trial rejected at scan time is listed by every field's cache
                if entry.get("file") is not None:
                    f_abs = os.path.abspath(str(entry["file"]))
                    entry = {**entry, "file": moved.get(f_abs, entry["file"])}
                if entry not in skipped:
                    skipped.append(entry)
    names = _whole_trials(fields, per_field, cache_files, skipped)
    skipped = _one_per_trial(skipped)
    object_ids = scene.object_ids()
    roles = scene.object_roles() or {}
    sets = recording_sets(per_field[0], names)
    refs = []
    incomplete: list[str] = []
    for name in names:
        a = per_field[0][name]
        if str(a["skin"]) != scene.skin or str(a["primitive"]) != scene.primitive:
            src = str(a.get("source_file"))
            if sets.get(src) == (scene.skin, scene.primitive):  # a mislabelled trial of this scene's set
                entry = {"file": src, "trial": name, "field": "attrs/skin" if str(a["skin"]) != scene.skin
                         else "attrs/primitive",
                         "problem": f"skin={a['skin']} primitive={a['primitive']} in a recording set of "
                                    f"{scene.skin}/{scene.primitive} trials: its attributes disagree with its file; "
                                    "left out (fix the attributes, or move the trial to a file of its own scene)"}
                log.warning("skipping %s / %s: %s", src, name, entry["problem"])
                skipped.append(entry)
            continue
        if object_ids is not None and int(a["object_id"]) not in object_ids:
            continue
        if scene.actions is not None and int(a["action_index"]) not in scene.actions:
            continue
        if scene.source == "simulated" and int(a.get("repetition", 0)) >= scene.repetitions:
            continue
        if not bool(a.get("complete", True)):  # an interrupted recording
            incomplete.append(name)
            if not scene.include_incomplete:
                continue
        refs.append(TrialRef(name=name, object_id=int(a["object_id"]), action_index=int(a["action_index"]),
                             skin=str(a["skin"]), primitive=str(a["primitive"]),
                             factors=(UNLABELLED if roles.get(int(a["object_id"])) == "unlabelled"
                                      else tuple(float(a[k]) for k in C.FACTOR_NAMES))))
    refs = _without_dead_channels(scene, cache_files, refs, per_field[0], skipped)
    skipped = _one_per_trial(skipped)  # a trial dead in two channels is one skipped trial
    if incomplete and not scene.include_incomplete:
        log.warning("excluded %d incomplete recording(s) (complete=False: interrupted), e.g. %s; "
                    "data.include_incomplete=true uses them", len(incomplete), incomplete[:3])
    elif incomplete:
        log.info("using %d incomplete recording(s) (include_incomplete=true)", len(incomplete))
    if not refs:
        raise RuntimeError(
            f"no usable trials for skin={scene.skin} primitive={scene.primitive} objects={scene.objects} "
            f"actions={scene.actions} in {dict(cache_files)} (skipped: {skipped[:5]})"
        )
    return refs, skipped, (incomplete if not scene.include_incomplete else [])


def _without_dead_channels(scene: Scene, cache_files: Mapping[str, str], refs: list[TrialRef],
                           attrs: Mapping[str, Mapping[str, Any]], skipped: list[dict[str, str]]) -> list[TrialRef]:
    """``refs`` less the trials in which a channel of the scene is dead: its cached array (every
    frame and taxel of the trial's window; one layer of the FSR) holds one value while the channel
    varies in another trial of the scene (a dead or unplugged layer in one recording). Each is
    added to ``skipped`` (field: the raw dataset and layer) with a warning naming file, trial
    and channel. A channel constant in every trial skips nothing here: that is the dead
    layer of the whole scene, refused by the DataModule's statistics check
    (``ConstantChannelError``)."""
    from embodied_tactile.data.modality import CHANNELS

    constant: dict[str, dict[str, float]] = {}  # channel -> {trial: its one value}
    for fld in dict.fromkeys(CHANNELS[c][0] for c in scene.channels):
        chans = [(c, CHANNELS[c][1]) for c in scene.channels if CHANNELS[c][0] == fld]
        with h5py.File(cache_files[fld], "r") as f:
            for ref in refs:
                arr = f["trials"][ref.name][fld][()]
                for c, layer in chans:
                    x = arr if layer is None else arr[:, layer]
                    lo, hi = x.min(), x.max()
                    if lo == hi:
                        constant.setdefault(c, {})[ref.name] = float(lo)
    dead: dict[str, list[str]] = {}  # trial -> its dead channels, in the scene's order
    for c in scene.channels:
        flat = constant.get(c, {})
        if not flat or len(flat) == len(refs):
            continue
        fld, layer, dataset = CHANNELS[c]
        for ref in refs:
            if ref.name not in flat:
                continue
            src = str(attrs[ref.name].get("source_file"))
            entry = {"file": src, "trial": ref.name, "field": dataset + ("" if layer is None else f" layer {layer}"),
                     "problem": f"channel {c} ({'layer ' + str(layer) + ' of ' if layer is not None else ''}cached "
                                f"field {fld}) reads one value ({flat[ref.name]:.6g}) in every cached frame of the trial while "
                                f"{len(refs) - len(flat)} other trial(s) of the scene vary: a dead or unplugged "
                                "sensor layer in this trial; left out"}
            log.warning("skipping %s / %s: %s", src, ref.name, entry["problem"])
            skipped.append(entry)
            dead.setdefault(ref.name, []).append(c)
    return [r for r in refs if r.name not in dead]


def recording_sets(attrs: Mapping[str, Mapping[str, Any]], names: Sequence[str]) -> dict[str, tuple[str, str]]:
    """``{raw file: (skin, primitive)}`` the most trials of each file hold: the scene the file
    records. A trial of that file with other attributes disagrees with its file (a file
    whose trials are mostly of another scene is that scene's, and its trials are not this
    scene's to name)."""
    from collections import Counter

    counts: dict[str, Counter] = {}
    for name in names:
        a = attrs[name]
        counts.setdefault(str(a.get("source_file")), Counter())[(str(a["skin"]), str(a["primitive"]))] += 1
    return {f: c.most_common(1)[0][0] for f, c in counts.items()}


def _one_per_trial(entries: Sequence[Mapping[str, str]]) -> list[dict[str, str]]:
    """One ``{file, trial, field, problem}`` per bad trial, in first-seen order: a trial
    rejected by several caches (a broken clock fails every field that reads it) keeps the
    fields joined by ``", "`` and its distinct problems joined by ``"; "``."""
    merged: dict[tuple[str | None, str | None], dict[str, list[str]]] = {}
    for e in entries:
        m = merged.setdefault((e.get("file"), e.get("trial")), {"field": [], "problem": []})
        for key in ("field", "problem"):
            if str(e.get(key)) not in m[key]:
                m[key].append(str(e.get(key)))
    return [{"file": f, "trial": t, "field": ", ".join(m["field"]), "problem": "; ".join(m["problem"])}
            for (f, t), m in merged.items()]


def _whole_trials(fields: Sequence[str], per_field: Sequence[Mapping[str, Mapping[str, Any]]],
                  cache_files: Mapping[str, str], skipped: list[dict[str, str]]) -> list[str]:
    """Names of the trials that every needed cache holds, all from one raw file.

    A trial listed as skipped for any field, or absent from a cache, is skipped whole;
    one absent without a reason is added to ``skipped`` with a warning. Fields of one
    name from different raw files are an error (never a stitched trial)."""
    bad = {(e.get("file"), e.get("trial")) for e in skipped}
    mixed = []
    out = []
    for name in sorted(set().union(*per_field)):
        sources = {fld: os.path.abspath(str(entries[name].get("source_file")))
                   for fld, entries in zip(fields, per_field) if name in entries}
        if len(set(sources.values())) > 1:
            mixed.append(f"'{name}': " + ", ".join(f"{fld} from {src}" for fld, src in sources.items()))
            continue
        src = next(iter(sources.values()))
        if (src, name) in bad:
            continue
        absent = [fld for fld in fields if fld not in sources]
        for fld in absent:
            entry = {"file": str(src), "trial": name, "field": fld,
                     "problem": f"absent from the cache {cache_files[fld]} (no reason listed there)"}
            log.warning("skipping %s / %s: %s", src, name, entry["problem"])
            skipped.append(entry)
        if not absent:
            out.append(name)
    if mixed:
        raise RuntimeError(f"cached fields of one trial come from different raw files: {'; '.join(mixed[:5])}"
                           f"{' ...' if len(mixed) > 5 else ''} (caches {dict(cache_files)}); rebuild the caches")
    return out
