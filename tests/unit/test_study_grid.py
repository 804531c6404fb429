"""experiments/study_grid.py: the parts lanes take and what counts as finished (no training)."""

import importlib.util
import json
from pathlib import Path

_spec = importlib.util.spec_from_file_location("study_grid", Path(__file__).parents[2] / "experiments" / "study_grid.py")
grid = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(grid)


def test_the_parts_are_the_sweeps_cells_once_each_table1_cells_first():
    from omegaconf import OmegaConf

    params = OmegaConf.load(Path(__file__).parents[2] / "configs" / "sweep" / "study.yaml").hydra.sweeper.params
    cells = {(c, p) for c in str(params.combo).split(",") for p in str(params.primitive).split(",")}
    assert len(grid.PARTS) == len(set(grid.PARTS)) == 24 and set(grid.PARTS) == cells
    assert grid.PARTS[:3] == tuple(("multi_l_soft", p) for p in ("pressing", "precession", "sliding"))
    assert all(p == "pressing" for _, p in grid.PARTS[3:10])
    assert grid.SEEDS == (0, 1, 2)


def test_a_part_counts_the_seeds_whose_runs_finished(tmp_path):
    part = tmp_path / "multi_l_soft_pressing"
    for seed, status in ((0, "finished"), (1, "interrupted"), (2, "finished")):
        job = part / f"combo=multi_l_soft,primitive=pressing,seed={seed}"
        (job / ".hydra").mkdir(parents=True)
        (job / ".hydra" / "overrides.yaml").write_text(f"- combo=multi_l_soft\n- primitive=pressing\n- seed={seed}\n")
        (job / "metrics.json").write_text(json.dumps({"status": status}))
    assert grid.finished_seeds(part) == [0, 2]
    assert not grid.in_training(part)


def test_a_failed_part_reports_the_last_line_of_its_output(tmp_path):
    log = tmp_path / "acc_soft_pressing.log"
    log.write_text("INFO: starting\n" + "x" * 5000 + "\ntrain.py: error: hydra.sweep.dir=S: holds another multirun\n\n")
    assert grid.last_line(log) == "train.py: error: hydra.sweep.dir=S: holds another multirun"
    (tmp_path / "empty.log").write_text("")
    assert grid.last_line(tmp_path / "empty.log") == "(no output)"
