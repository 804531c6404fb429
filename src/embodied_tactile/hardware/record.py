"""Record one e-Skin trial from a serial port into the raw HDF5 format.

    python -m embodied_tactile.hardware.record port=/dev/ttyACM0 out=data/raw/recorded.h5 \\
        trial.object_id=3 trial.skin=soft trial.primitive=sliding trial.action_index=5 trial.repetition=0

Hydra app, config ``configs/record.yaml`` (+ ``configs/record/device/*.yaml``). The config
directory is resolved as ``$EMBODIED_TACTILE_CONFIG_DIR`` if set, else the repository's
``configs/`` next to ``src/`` (works from the repo and from an editable install).

Each trial goes into its own file next to ``out`` (:func:`~.acquisition.recorder.trial_file`:
``out=recordings/obj03.h5`` -> ``recordings/obj03.<trial name>.h5``), so a crash, a full
disk or a file-size limit during one trial never touches the others.

Exit codes: 0 the full trial was recorded (``complete=True``); 3 incomplete (Ctrl-C /
SIGTERM, device unplugged, no data, disk full or a failed write: everything written so
far is stored, readable, ``complete=False``; or the output file vanished with its folder:
one line naming it, what was recorded went with it); 2 configuration or port error (trial
attributes the raw format's validator rejects, a port held by another recorder, too
little room for the baseline and the first second: nothing recorded), or a packet rate
in the first second that does not match ``fs_tactile`` (stopped, ``complete=False``,
``stop_reason=rate_mismatch``); 1 unexpected error.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import sys
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from embodied_tactile import constants as C
from embodied_tactile.cli import hydra_command

log = logging.getLogger("embodied_tactile.hardware.record")


_POSE_BUILTIN_KEYS = ("kind", "file", "time_base", "offset_s", "static_pose", "fs")


def make_pose_source(cfg: DictConfig):
    from embodied_tactile.hardware.pose import ReplayPoseSource, StaticPoseSource

    p = cfg.pose
    if p.get("_target_"):
        node = {k: v for k, v in OmegaConf.to_container(p, resolve=True).items() if k not in _POSE_BUILTIN_KEYS}
        return hydra.utils.instantiate(node)
    kind = str(p.kind)
    if kind == "static":
        return StaticPoseSource(list(p.static_pose), fs=float(p.fs))
    if kind == "replay":
        if not p.file:
            raise ValueError("pose.kind=replay needs pose.file")
        return ReplayPoseSource(p.file, time_base=str(p.time_base), offset_s=float(p.offset_s))
    if kind == "none":
        return None
    raise ValueError(f"pose.kind must be static|replay|none (or set pose._target_), got {kind!r}")


def make_trial_attrs(cfg: DictConfig, device_desc: str, pose_name: str) -> dict[str, Any]:
    from embodied_tactile.data.rawformat import make_attrs

    t = cfg.trial
    oid = int(t.object_id)
    if t.factors is not None:
        factors = [math.nan if v is None else float(v) for v in t.factors]
        if len(factors) != len(C.FACTOR_NAMES):
            raise ValueError(f"trial.factors needs {len(C.FACTOR_NAMES)} values {C.FACTOR_NAMES}")
    elif 0 <= oid < C.N_OBJECTS:
        factors = None  # catalogue
    else:
        factors = [math.nan] * len(C.FACTOR_NAMES)
    return make_attrs(
        object_id=oid,
        skin=str(t.skin),
        primitive=str(t.primitive),
        action_index=int(t.action_index),
        repetition=int(t.repetition),
        source="recorded",
        seed=int(t.seed),
        factors=factors,
        fs_tactile=float(cfg.fs_tactile),
        fs_pose=float(cfg.fs_pose),
        device=device_desc,
        notes=str(t.notes or ""),
        port=str(cfg.port),
        pose_source=pose_name,
        baseline_s=float(cfg.baseline_s),
        duration_s=float(cfg.duration_s),
    )


def _check_room(path, settings, fs_tactile: float, fs_pose: float, pose_columns: int) -> None:
    """ValueError when ``path`` has no room for the baseline and the first second of the
    trial beside ``reserve_mb``; a warning when the whole trial will not fit (it then stops
    early with ``stop_reason=disk_full``)."""
    from embodied_tactile.hardware.recorder import room_bytes, trial_bytes

    room = room_bytes(path) - settings.reserve_bytes
    first = trial_bytes(settings.baseline_s + 1.0, fs_tactile, fs_pose, pose_columns)
    whole = trial_bytes(settings.baseline_s + settings.duration_s, fs_tactile, fs_pose, pose_columns)
    where = f"{path.parent}: {(room + settings.reserve_bytes) / 2**20:.1f} MB writable (free disk space / file-size limit)"
    if room < first:
        raise ValueError(f"{where}, the baseline and the first second need {first / 2**20:.1f} MB "
                         f"beside the reserve of reserve_mb={settings.reserve_mb:g} MB")
    if room < whole:
        print(f"record: warning: {where}, the whole trial needs about {whole / 2**20:.1f} MB beside the reserve of "
              f"{settings.reserve_mb:g} MB: it will stop early (disk_full)", file=sys.stderr, flush=True)


def _check_not_recorded(path, session, name: str) -> None:
    """FileExistsError when the trial's file exists, or ``session`` (a file holding many
    trials, as the recorder wrote them before one file per trial) holds the trial."""
    if path.exists():
        raise FileExistsError(f"{path} exists: trial '{name}' was recorded; bump trial.repetition or use another out")
    if session.is_file():
        import h5py

        try:
            with h5py.File(session, "r") as f:
                held = "trials" in f and name in f["trials"]
        except OSError:
            return
        if held:
            raise FileExistsError(f"{session} holds trial '{name}'; bump trial.repetition or use another out")


def run(cfg: DictConfig) -> int:
    """Record one trial as configured; returns the exit code."""
    from embodied_tactile.hardware.protocol import DeviceMap, PlausibilityConfig
    from embodied_tactile.hardware.recorder import (
        EXIT_CONFIG,
        PortBusy,
        Recorder,
        RecorderSettings,
        default_out,
        finish,
        open_port,
        trial_file,
    )
    from embodied_tactile.data.rawformat import IncrementalTrialWriter, check_attrs, trial_name

    logging.getLogger("embodied_tactile").setLevel(str(cfg.get("log_level", "INFO")))
    # ---- configuration (exit 2 on any problem, nothing written)
    try:
        settings = RecorderSettings(
            port=str(cfg.port), baud=int(cfg.baud), timeout=float(cfg.timeout), settle_s=float(cfg.settle_s),
            baseline_s=float(cfg.baseline_s), duration_s=float(cfg.duration_s), flush_s=float(cfg.flush_s),
            quiet_s=float(cfg.quiet_s), late_guard_s=float(cfg.late_guard_s), reserve_mb=float(cfg.reserve_mb),
            declared_hz=float(cfg.fs_tactile), rate_check_s=float(cfg.get("rate_check_s", 1.0)),
        )
        device = DeviceMap.from_config(OmegaConf.to_container(cfg.device, resolve=True))
        plaus = PlausibilityConfig.from_config(OmegaConf.to_container(cfg.plausibility, resolve=True))
        pose = make_pose_source(cfg)
        attrs = make_trial_attrs(cfg, device.describe(), getattr(pose, "name", "none") if pose is not None else "none")
        out = trial_file(default_out(cfg.out), trial_name(attrs))
        check_attrs(str(out), trial_name(attrs), attrs)  # what scan_raw would reject later, refused now
        pose_columns = getattr(pose, "columns", 6) if pose is not None else 0
        _check_not_recorded(out, default_out(cfg.out), trial_name(attrs))
        _check_room(out, settings, float(cfg.fs_tactile), float(cfg.fs_pose), pose_columns)
    except Exception as exc:  # noqa: BLE001 - any config problem -> exit 2
        log.error("configuration error: %s", exc)
        print(f"record: configuration error: {exc}", file=sys.stderr, flush=True)
        return EXIT_CONFIG
    # ---- port
    try:
        ser = open_port(settings.port, settings.baud, settings.timeout)
    except PortBusy as exc:  # another recorder: refused before the line is touched
        print(f"record: error: port {exc}", file=sys.stderr, flush=True)
        return EXIT_CONFIG
    except Exception as exc:  # noqa: BLE001 - SerialException, ValueError (bad URL), OSError
        print(f"record: cannot open port {settings.port!r}: {exc}", file=sys.stderr, flush=True)
        return EXIT_CONFIG
    try:
        writer = IncrementalTrialWriter(out, attrs, pose_columns=pose_columns or 6)
    except (FileExistsError, OSError) as exc:
        ser.close()
        print(f"record: cannot write trial {trial_name(attrs)!r} to {out}: {exc}", file=sys.stderr, flush=True)
        return EXIT_CONFIG

    stop = {"sig": None}

    def on_signal(signum, frame):  # noqa: ARG001
        stop["sig"] = signum

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}

    def on_phase(phase: str) -> None:
        print(f"record: {phase} started ({writer.name} -> {out})", flush=True)

    try:
        rec = Recorder(ser, writer, settings, device=device, plausibility=plaus, pose=pose, should_stop=lambda: stop["sig"] is not None, on_phase=on_phase)
        res = rec.run()
        if stop["sig"] is not None and res.status == "complete":
            res.status = "interrupted"
        finish(writer, res)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        try:
            ser.close()
        except Exception:  # noqa: BLE001 - an unplugged port may fail to close
            pass
        try:
            writer.close(complete=False)  # no-op if finish() closed it
        except (OSError, RuntimeError):
            writer.abandon()
    msg = res.summary()
    if res.garbage_reasons:
        msg += f"; garbage reasons {res.garbage_reasons}"
    print(f"record: {msg}", flush=True)
    if res.status == "output_vanished":  # the one line: which file, what went with it
        print(f"record: error: {res.message}", file=sys.stderr, flush=True)
    elif res.message:  # stopped for a setting (rate_mismatch): the one line that says what to fix
        print(f"record: error: {out}: trial '{writer.name}': {res.message} (the file is kept, complete=False)",
              file=sys.stderr, flush=True)
    log.debug(msg)
    if res.status == "write_error":
        # The HDF5 library cannot close a file whose write failed and crashes when the
        # interpreter tears it down: leave without that teardown, the summary printed.
        logging.shutdown()
        sys.stderr.flush()
        os._exit(res.exit_code)
    return res.exit_code


main = hydra_command("record", run, "record")


if __name__ == "__main__":
    main()
