"""The study grid (``sweep=study``) in resumable parts, run by lanes side by side.

    python experiments/study_grid.py train --study STUDY [--data DATA] &   # one lane (threads=1)
    python experiments/study_grid.py train --study STUDY [--data DATA] &   # a second lane beside it
    python experiments/study_grid.py status --study STUDY                  # finished seeds per part
    python experiments/study_grid.py train --study STUDY trainer=gpu &     # a lane on the GPU (start several)
    python evaluate.py STUDY baselines=[untrained,handcrafted,mean]        # merges the finished parts
    python experiments/study_grid.py archive --study STUDY                 # into docs/generated/study_runs/
    embodied-tactile report page=results evaluation=STUDY/evaluation out=docs/generated/results.md
    python experiments/study_grid.py restore --study STUDY                 # on the next machine, first

A part is one of the paper's 24 cells (a ``configs/combo/`` x a primitive) with the sweep's
seeds: ``python train.py -m sweep=study combo=C primitive=P threads=1 logger=none
hydra.sweep.dir=STUDY/C_P`` (the same command again resumes it, also on another machine whose
``paths.data_dir`` differs). Its output goes to ``STUDY/C_P.log``, whose last line a lane
prints when the part fails. Lanes take the parts in :data:`PARTS` order (the Table 1
analogue's cells first, then the rest of pressing, then the rest), each holding a lock on
``STUDY/.C_P.lock`` while it runs (released when the lane stops,
however it stops). A part whose seeds all finished is skipped; one that has a job in training
(its run folder's lock is held) is left to the process training it; an interrupted one resumes
(train.py leaves a finished job as it is and continues an interrupted one from its
``last.ckpt``). evaluate.py scores each run once: a later evaluation of the growing study
reuses what the earlier ones scored.

The grid takes longer than one machine lives, so its runs travel in git: ``archive`` copies
every run the study's evaluation scored into :data:`ARCHIVE` (its small files and its scored
record, no checkpoint: :mod:`embodied_tactile.eval.records`), and ``restore`` copies them into
the next machine's study folder, where the lanes skip them as finished and evaluate.py merges
their records with the new runs'. A record is merged only by the code and options that scored
it: every machine trains and evaluates the study at the commit named in :data:`ARCHIVE`'s
``README.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from omegaconf import OmegaConf  # noqa: E402

from embodied_tactile.eval.records import archive_runs, restore_runs  # noqa: E402
from embodied_tactile.run.runfolder import training_holder, try_lock, write_holder  # noqa: E402

COMBOS = ("acc_soft", "fsr_t_soft", "fsr_b_soft", "fsr_tb_soft", "multi_e_soft", "multi_l_soft", "fsr_tb_hard",
          "multi_l_hard")
PRIMITIVES = ("pressing", "precession", "sliding")
#: the seeds of every part: those of the sweep (configs/sweep/study.yaml)
SEEDS = tuple(int(s) for s in str(OmegaConf.load(REPO / "configs" / "sweep" / "study.yaml")
                                  .hydra.sweeper.params.seed).split(","))
#: the order lanes take the parts in: MULTI-L soft on every primitive (Table 1 analogue, the
#: findings (f)-(j)), then every cell on pressing (findings (a)-(e)), then the rest
PARTS: tuple[tuple[str, str], ...] = (
    *(("multi_l_soft", p) for p in PRIMITIVES),
    *((c, "pressing") for c in COMBOS if c != "multi_l_soft"),
    *((c, p) for p in PRIMITIVES[1:] for c in COMBOS if c != "multi_l_soft"),
)


#: the study's archived runs, committed: what every machine's study folder starts from
ARCHIVE = REPO / "docs" / "generated" / "study_runs"


def part_dir(study: Path, combo: str, primitive: str) -> Path:
    return study / f"{combo}_{primitive}"


def finished_seeds(folder: Path) -> list[int]:
    """The seeds of ``folder``'s jobs whose metrics.json says finished."""
    out = []
    for m in sorted(folder.glob("*/metrics.json")):
        try:
            state = json.loads(m.read_text())
            cfg = (m.parent / ".hydra" / "overrides.yaml").read_text()
        except (OSError, ValueError):
            continue
        seed = next((int(line.split("=", 1)[1]) for line in cfg.splitlines() if line.strip("- ").startswith("seed=")),
                    0)
        if state.get("status") == "finished":
            out.append(seed)
    return sorted(out)


def last_line(log: Path) -> str:
    """The last non-empty line of ``log`` (a failed part's reason: train.py ends on its one-line error)."""
    with open(log, "rb") as f:
        f.seek(max(f.seek(0, os.SEEK_END) - 4096, 0))
        lines = [ln for ln in f.read().decode(errors="replace").splitlines() if ln.strip()]
    return lines[-1] if lines else "(no output)"


def in_training(folder: Path) -> bool:
    return any(training_holder(j) is not None for j in folder.iterdir() if j.is_dir()) if folder.is_dir() else False


def train(args) -> None:
    study = Path(args.study).resolve()
    for combo, primitive in PARTS:
        folder = part_dir(study, combo, primitive)
        if set(SEEDS) <= set(finished_seeds(folder)) or in_training(folder):
            continue
        study.mkdir(parents=True, exist_ok=True)
        fd, _ = try_lock(study / f".{folder.name}.lock")  # held until the part ends or the lane stops
        if fd is None:
            continue
        write_holder(fd)
        cmd = [sys.executable, str(REPO / "train.py"), "-m", "sweep=study", f"combo={combo}", f"primitive={primitive}",
               "threads=1", "logger=none", f"hydra.sweep.dir={folder}",
               *([f"paths.data_dir={Path(args.data).resolve()}"] if args.data else []), *args.overrides]
        print(time.strftime("%H:%M:%S"), "part", folder.name, flush=True)
        t0 = time.perf_counter()
        log = study / f"{folder.name}.log"  # the part's own output, appended at every start
        with open(log, "ab") as out:
            rc = subprocess.run(cmd, cwd=REPO, env=dict(os.environ, WANDB_MODE="disabled"), stdout=out,
                                stderr=subprocess.STDOUT).returncode
        print(time.strftime("%H:%M:%S"), f"part {folder.name}: rc {rc} in {time.perf_counter() - t0:.0f} s, "
              f"seeds finished {finished_seeds(folder)}", flush=True)
        if rc:
            print(f"  {last_line(log)}  (whole output: {log})", flush=True)
        os.close(fd)


def status(args) -> None:
    study = Path(args.study).resolve()
    done = 0
    for combo, primitive in PARTS:
        folder = part_dir(study, combo, primitive)
        seeds = finished_seeds(folder) if folder.is_dir() else []
        done += len(seeds)
        state = "training" if in_training(folder) else ""
        print(f"{folder.name:28s} {len(seeds)}/{len(SEEDS)} {state}")
    print(f"{done} of {len(PARTS) * len(SEEDS)} jobs finished")


def archive(args) -> None:
    study = Path(args.study).resolve()
    written = archive_runs(study / "evaluation", study, Path(args.archive))
    print(f"{len(written)} run(s) archived into {args.archive}")
    for w in written:
        print(" ", Path(w).relative_to(Path(args.archive)))


def restore(args) -> None:
    copied = restore_runs(Path(args.archive), Path(args.study))
    print(f"{len(copied)} archived run(s) restored into {args.study}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("command", choices=["train", "status", "archive", "restore"])
    ap.add_argument("--study", required=True, help="the study folder (one sub-folder per part)")
    ap.add_argument("--archive", default=str(ARCHIVE), help="the archived runs (default: %(default)s)")
    ap.add_argument("--data", default=None, help="paths.data_dir of the trainings (default: the config's)")
    ap.add_argument("overrides", nargs="*", help="train.py overrides of every part (e.g. trainer=gpu); a part "
                    "resumes only with the overrides it started with")
    args = ap.parse_args(argv)
    {"train": train, "status": status, "archive": archive, "restore": restore}[args.command](args)


if __name__ == "__main__":
    main()
