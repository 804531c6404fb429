"""benchmarks/bench_gpu.py: without CUDA it says so and exits non-zero; its code path runs
as a CPU dry run at tiny shapes (no timings asserted)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture(scope="module")
def bench_gpu():
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location("bench_gpu", BENCH / "bench_gpu.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        yield mod
    finally:
        sys.path.remove(str(BENCH))


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is present")
def test_without_cuda_it_says_so_and_exits_non_zero(bench_gpu, capsys):
    assert bench_gpu.main([]) == bench_gpu.EXIT_NO_CUDA != 0
    assert "no CUDA device" in capsys.readouterr().err


@pytest.mark.slow
def test_epoch_shape_follows_the_paper_and_population_scenes(bench_gpu):
    paper = bench_gpu.epoch_shape(bench_gpu.compose(["experiment=paper", "trainer=gpu"]))
    # 32 objects x 16 sets = 512 trials: 128 test, 64 validation, 320 training -> 7 steps of 48
    assert (paper["steps"], paper["val_batches"], paper["batch"], paper["t_train"], paper["t_val"]) == (7, 2, 48, 300, 300)
    assert paper["epochs"] == 500 and paper["precision"] == "bf16-mixed" and not paper["context"]
    pop = bench_gpu.epoch_shape(bench_gpu.compose(["experiment=population", "trainer=gpu"]))
    # 480 windows of 50 frames per epoch at batch 16; 32 validation objects x 2 actions, paired 50-frame crops
    assert (pop["steps"], pop["val_batches"], pop["t_train"], pop["t_val"], pop["epochs"]) == (30, 4, 50, 50, 16)
    assert pop["context"]


@pytest.mark.slow
def test_cpu_dry_run_prints_every_figure(bench_gpu, capsys):
    threads = torch.get_num_threads()
    try:
        assert bench_gpu.main(["--device", "cpu", "--steps", "1", "--batch", "2", "--seq", "4",
                               "--modalities", "acc", "multi_l"]) == 0
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    assert "CPU dry run" in out and "NOT GPU figures" in out
    rows = [ln for ln in out.splitlines() if ln.startswith("| acc |") or ln.startswith("| multi_l |")]
    assert len(rows) == 2 and all("bf16-mixed" in r and "2 x 4" in r and "7 + 2" in r for r in rows)
    assert "the paper's study: 9 of its 24 models" in out  # acc soft, multi_l soft and hard: 3 cells x 3 primitives
    assert "population scene (experiment=population" in out and "256 epochs x (30 steps" in out


@pytest.mark.slow
def test_trainer_gpu_precision_trains_the_paper_model_through_lightning(bench_gpu, tmp_path):
    """trainer=gpu's precision (bf16-mixed) on the CPU accelerator: Lightning's autocast around
    the paper's model (configs composed, a tiny network), finite loss, float32 parameters."""
    import lightning as L
    from hydra.utils import instantiate
    from torch.utils.data import DataLoader

    cfg = bench_gpu.compose(["experiment=paper", "trainer=gpu", "modality=multi_l", "model.net.encoder.widths=[4,8]",
                             "model.net.encoder.hidden=16", "model.net.transition_hidden=16", "model.net.lstm_hidden=16",
                             "model.net.input_standardize=false"])
    assert cfg.trainer.precision == "bf16-mixed" and cfg.trainer.accelerator == "gpu"
    torch.manual_seed(0)
    module = instantiate(cfg.model)
    batch = bench_gpu.synthetic_batch(module.model.n_channels, 4, 6, False, "cpu")
    items = [{k: (v[i] if torch.is_tensor(v) else v[i]) for k, v in batch.items()} for i in range(4)]
    trainer = L.Trainer(accelerator="cpu", devices=1, precision=cfg.trainer.precision, max_steps=2, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                        limit_val_batches=0, default_root_dir=tmp_path)
    trainer.fit(module, DataLoader(items, batch_size=2))
    assert trainer.global_step == 2 and torch.isfinite(trainer.callback_metrics["train/loss"])
    assert all(p.dtype == torch.float32 for p in module.parameters())
