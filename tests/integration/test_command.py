"""The one command: ``embodied-tactile --help`` lists every subcommand, and each subcommand's
``--help`` reaches its entry point (a subprocess each, as a user types it); the package as a
wheel installs it runs from any folder with the configs built in, or refuses in one line."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

from conftest import REPO
from embodied_tactile.__main__ import COMMANDS, main

#: a line of each entry point's own help
OWN_HELP = {"train": "train is powered by Hydra", "evaluate": "usage: evaluate.py", "simulate": "Simulate raw e-Skin trials",
            "prepare": "Prepare a scene's data", "record": "powered by Hydra", "emulate": "faults.disconnect_after_*",
            "palpate": "powered by Hydra", "report": "paper_units: null"}


def command(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "embodied_tactile", *args], capture_output=True, text=True, timeout=180)


@pytest.mark.slow
def test_help_lists_one_line_per_subcommand():
    res = command("--help")
    assert res.returncode == 0, res.stderr
    listed = [line.split()[0] for line in res.stdout.splitlines() if line.startswith("  ")]
    assert listed == list(COMMANDS) == list(OWN_HELP)


@pytest.mark.slow
def test_unknown_or_missing_subcommand_exits_2():
    assert command("fly").returncode == 2
    assert command().returncode == 2


@pytest.fixture(scope="module")
def helps() -> dict[str, subprocess.CompletedProcess]:
    """``embodied-tactile NAME --help`` of every subcommand, the subprocesses started at once so
    that they share the cores instead of queueing."""
    procs = {name: subprocess.Popen([sys.executable, "-m", "embodied_tactile", name, "--help"],
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for name in COMMANDS}
    done = {}
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=300)
        done[name] = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    return done


@pytest.mark.slow  # eight interpreters importing torch and Lightning: ~10 s on 2 quiet cores
@pytest.mark.parametrize("name", list(COMMANDS))
def test_subcommand_help(name, helps):
    res = helps[name]
    assert res.returncode == 0, res.stderr[-2000:]
    assert OWN_HELP[name] in res.stdout, res.stdout[:2000]


@pytest.mark.slow
def test_subcommands_run_in_this_process(capsys):
    """The dispatcher calls each entry point's main(argv) here and returns its status."""
    assert main(["train", "data.batch_size=0"]) == 2
    assert capsys.readouterr().err.strip() == "train.py: error: data.batch_size=0 (int): expected an integer >= 1"
    assert main(["simulate", "skin=rubber"]) == 2
    assert capsys.readouterr().err.strip().startswith("simulate: error: ")


def test_missing_configs_refused_in_one_line(monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("EMBODIED_TACTILE_CONFIG_DIR", str(tmp_path / "nowhere"))
    assert main(["train", "debug=fast"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"embodied-tactile: error: no configs found at {tmp_path / 'nowhere'}")


@pytest.mark.slow  # builds the package (~2 s) and trains debug=fast in a subprocess (~30 s)
def test_installed_package_trains_from_any_folder(tmp_path, fast_data_dir):
    """What a wheel installs (setup.py's build_py: the package, configs/ built in) runs
    ``embodied-tactile train debug=fast`` from a folder outside the checkout; the same package
    without its configs refuses in one line, no traceback."""
    lib, work = tmp_path / "lib", tmp_path / "elsewhere"
    subprocess.run([sys.executable, "setup.py", "-q", "build_py", "--build-lib", str(lib)], cwd=REPO, check=True,
                   capture_output=True)
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "EMBODIED_TACTILE_CONFIG_DIR"}
    env.update(PYTHONPATH=str(lib), WANDB_MODE="disabled")  # the built package before the editable checkout
    where = subprocess.run([sys.executable, "-c", "import embodied_tactile.paths as p; print(p.__file__, p.config_dir())"],
                           cwd=work, env=env, capture_output=True, text=True, check=True).stdout.split()
    assert where == [str(lib / "embodied_tactile" / "paths.py"), str(lib / "embodied_tactile" / "configs")]

    def train() -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "embodied_tactile", "train", "debug=fast", "threads=1",
                               f"paths.data_dir={fast_data_dir}"], cwd=work, env=env, capture_output=True, text=True,
                              timeout=600)

    res = train()
    assert res.returncode == 0, res.stderr[-3000:]
    (run,) = (work / "logs" / "train" / "runs").iterdir()
    assert json.loads((run / "metrics.json").read_text())["status"] == "finished"
    assert (run / "train.log").is_file()
    shutil.rmtree(lib / "embodied_tactile" / "configs")
    res = train()
    assert res.returncode == 2 and "Traceback" not in res.stderr + res.stdout
    assert res.stderr.startswith("embodied-tactile: error: no configs found at ") and res.stderr.count("\n") == 1


@pytest.mark.slow
def test_a_stopped_command_ends_without_the_interpreters_teardown(tmp_path):
    """Fault: train.py stopped by a signal spent 1.6 CPU s after its last line in the
    interpreter's teardown (every module and object freed): 38 s on the loaded 2-core machine
    (docs/experiments/stop_latency.md). Now: process_exit ends a 130 / 143 with the exit
    handlers run (a log flushed, a temporary folder removed) and the streams flushed, but
    no object's finaliser left to the teardown; any other status exits as before."""
    script = (
        "import atexit, sys, tempfile\n"
        "from embodied_tactile.cli import process_exit\n"
        "class Late:\n"
        "    def __init__(self):\n"
        f"        self.file = open({str(tmp_path / 'teardown')!r}, 'w')\n"
        "    def __del__(self):\n"
        "        self.file.write('torn down')\n"
        "        self.file.close()\n"
        "late = Late()\n"
        f"kept = tempfile.TemporaryDirectory(dir={str(tmp_path)!r})\n"
        f"atexit.register(lambda: open({str(tmp_path / 'atexit')!r}, 'w').close())\n"
        "print('last line', end='')\n"
        "process_exit(int(sys.argv[1]))\n"
    )
    for code, torn_down in ((143, False), (130, False), (2, True)):
        for name in ("teardown", "atexit"):
            (tmp_path / name).unlink(missing_ok=True)
        res = subprocess.run([sys.executable, "-c", script, str(code)], capture_output=True, text=True, timeout=120)
        assert res.returncode == code and res.stdout == "last line", (code, res.stderr[-2000:])
        assert (tmp_path / "atexit").exists() and not [p for p in tmp_path.iterdir() if p.is_dir()], code
        assert (tmp_path / "teardown").read_text() == ("torn down" if torn_down else ""), code
