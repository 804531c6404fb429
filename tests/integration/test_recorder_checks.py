"""The recorder checks at the start: trial attributes through the raw format's validator,
the board's packet rate in the first second, and the serial port held by one recorder.
Real pseudo-terminals and the emulator, as in test_acquisition.py."""

from __future__ import annotations

import re
import time

import pytest

from embodied_tactile.hardware.emulator import Emulator, synthetic_trial
from embodied_tactile.data import rawformat as R
from test_acquisition import _check_genuine, _cli, _read_cli, _wait_line

# every test starts the recorder CLI (embodied-tactile record) in a subprocess
pytestmark = [pytest.mark.slow, pytest.mark.realtime]


@pytest.fixture(scope="module")
def trial3s():
    return synthetic_trial(3.0, seed=1)


def test_bad_trial_attributes_refused_before_the_first_packet(tmp_path, trial3s):
    """Fault: trial.skin=medium. Before: exit 0 "complete", the trial rejected only when
    training scanned it. Now: exit 2 naming file, trial and attribute; nothing written."""
    emu = Emulator(trial3s)
    port = emu.start()
    try:
        proc = _cli(tmp_path, port, "duration_s=1", "trial.skin=medium")
        out, err = proc.communicate(timeout=60)
    finally:
        emu.stop()
    assert proc.returncode == 2, err
    assert "trial 'obj40_medium_pressing_a00_r00', field 'attrs/skin': must be one of ('soft', 'hard')" in err
    assert "cli.obj40_medium_pressing_a00_r00.h5" in err
    assert emu.stats.requests == 0 and not list(tmp_path.glob("cli.*.h5"))


def test_board_rate_other_than_declared_stops_in_the_first_second(tmp_path):
    """Fault: the board sends 350 packets/s, fs_tactile declares 700 (a board at 1000 Hz
    against 700 is the same fault the other way; a loaded host's polling can hide a faster
    board, never a slower one). Before: exit 0 "complete"; scan_raw rejected the trial
    later. Now: stopped after the first second by scan_raw's own rate rule, exit 2, one line
    naming file, trial and both rates; the file kept and saying why."""
    emu = Emulator(synthetic_trial(3.0, fs=350.0, seed=1))  # served at its own 350 packets/s
    port = emu.start()
    try:
        t0 = time.monotonic()
        proc = _cli(tmp_path, port, "duration_s=8")
        out, err = proc.communicate(timeout=60)
        took = time.monotonic() - t0
    finally:
        emu.stop()
    assert proc.returncode == 2, out + err
    line = err.strip().splitlines()[-1]
    assert line.startswith("record: error: ") and "trial 'obj40_soft_pressing_a00_r00'" in line
    # the rate the host saw: the board's 350 packets/s, give or take the polling's jitter
    shown = re.search(r"in the first 1\.0 s the packets' timestamps show ([0-9.]+) Hz", line)
    assert shown and float(shown.group(1)) < 700 and "but fs_tactile declares 700 Hz" in line, line  # slower than declared
    assert took < 8
    with R.open_raw(tmp_path / "cli.obj40_soft_pressing_a00_r00.h5") as f:  # kept; scan_raw rejects its rate
        attrs = R.read_attrs(f["trials"]["obj40_soft_pressing_a00_r00"])
    assert attrs["complete"] is False and attrs["stop_reason"] == "rate_mismatch"


def test_second_recorder_on_a_running_port_is_refused(tmp_path):
    """Fault: a second recorder started on the port of a running one. Before: the first trial
    was cut (stop_reason=unplugged, exit 3) and the second ran. Now: the second exits 2
    without touching the line; the first completes with every packet."""
    trial = synthetic_trial(6.0, seed=1)  # the first records while the second starts (about 1.5 s on an idle core)
    emu = Emulator(trial)
    port = emu.start()
    first_dir, second_dir = tmp_path / "first", tmp_path / "second"
    first_dir.mkdir()
    second_dir.mkdir()
    try:
        # 5.5 s of the 6 s trial: a 6 s recording takes 4,200 or 4,201 packets by the clock's phase, and
        # the 4,201st is the looped trial's first frame, which the genuineness check reads as out of order
        first = _cli(first_dir, port, "duration_s=5.5")
        _wait_line(first, "trial started")
        requests = emu.stats.requests
        second = _cli(second_dir, port, "duration_s=3")
        _, err2 = second.communicate(timeout=60)
        out1, err1 = first.communicate(timeout=60)
    finally:
        emu.stop()
    assert second.returncode == 2, err2 + "\nfirst: " + err1
    assert err2.strip().splitlines()[-1].startswith(f"record: error: port {port} is in use by another program")
    assert not list(second_dir.glob("cli.*.h5"))
    assert first.returncode == 0, err1
    assert "complete" in out1 and "lost 0, garbage 0" in out1
    rec = _read_cli(first_dir)
    assert rec.attrs["complete"] is True and emu.stats.requests > requests
    _check_genuine(trial, rec)


def test_output_folder_vanishing_during_a_trial_exits_3_with_one_line(tmp_path, trial3s, monkeypatch, capsys,
                                                                       restore_logging):
    """Fault: the output folder is deleted (or its disk unmounted) while a trial records.
    Before: a FileNotFoundError traceback from the room check (shutil.disk_usage), exit 2
    as if the configuration were wrong. Now: the next flush finds the file gone, the trial stops (stop_reason output_vanished),
    exit 3 and one line on stderr naming the file and what was lost."""
    import shutil
    import sys
    import threading

    from embodied_tactile.hardware import record

    folder = tmp_path / "rec"
    folder.mkdir()
    out = folder / "cli.obj40_soft_pressing_a00_r00.h5"

    def remove_when_recording() -> None:
        t_end = time.monotonic() + 20
        while not out.exists() and time.monotonic() < t_end:
            time.sleep(0.02)
        time.sleep(0.6)
        shutil.rmtree(folder)

    emu = Emulator(trial3s)
    port = emu.start()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [
        "record", f"port={port}", f"out={folder / 'cli.h5'}", "settle_s=0.1", "baseline_s=0", "duration_s=3",
        f"hydra.run.dir={tmp_path / 'hydra'}", "record/device@device=ideal", "trial.object_id=40", "reserve_mb=0.25"])
    remover = threading.Thread(target=remove_when_recording)
    remover.start()
    try:
        with pytest.raises(SystemExit) as exc:
            record.main()
    finally:
        remover.join()
        emu.stop()
    err = capsys.readouterr().err
    assert exc.value.code == 3, err
    assert err.count("\n") == 1 and err.startswith(f"record: error: {out}: the output file vanished during the trial")
    assert not folder.exists()
