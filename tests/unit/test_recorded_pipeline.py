"""Recorded trials flow through the same validation, preprocessing, DataModule and training
as simulated ones: emulator (serving simulated trials) -> recorder over a real pty -> raw
HDF5 -> TactileDataModule.from_config(source="recorded") -> a Latent Filter training step."""

from __future__ import annotations

import lightning as L
import numpy as np
import pytest
import torch

from embodied_tactile.hardware.emulator import Emulator
from embodied_tactile.hardware.pose import StaticPoseSource
from embodied_tactile.hardware.recorder import Recorder, RecorderSettings, finish, open_port
from embodied_tactile.data.datamodule import TactileDataModule
from embodied_tactile.data import rawformat as rf
from embodied_tactile.sim import simulate_trial

pytestmark = pytest.mark.realtime  # the recording fixture keeps the board's pace: no other test beside it

DURATION = 1.2  # s per recorded trial; preprocessing takes its first 30 frames at 30 Hz (1 s), of which it
# needs 90 % covered: the margin is for an emulator that a loaded machine starves (once 0.853 s in a 1 s trial)


@pytest.fixture(scope="module")
def recorded_file(tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "recorded.h5"
    for obj in (0, 27):
        for rep in (0, 1):
            served = simulate_trial(obj, "soft", "pressing", 6, repetition=rep, duration=DURATION + 0.5)
            emu = Emulator(served)
            port = emu.start()
            settings = RecorderSettings(port=port, timeout=0.05, settle_s=0.05, baseline_s=0.0, duration_s=DURATION,
                                        flush_s=0.25, late_guard_s=0.05)
            attrs = rf.make_attrs(object_id=obj, skin="soft", primitive="pressing", action_index=6, repetition=rep,
                                  source="recorded", seed=0)
            writer = rf.IncrementalTrialWriter(out, attrs)
            ser = open_port(port, 500000, settings.timeout)
            try:
                res = Recorder(ser, writer, settings, pose=StaticPoseSource()).run()
                finish(writer, res)
            finally:
                ser.close()
                emu.stop()
    return out


@pytest.mark.slow
def test_recorded_trials_validate(recorded_file):
    good, errors = rf.scan_raw(recorded_file)
    assert errors == [] and len(good) == 4
    assert all(g.attrs["source"] == "recorded" for g in good)


@pytest.mark.slow
def test_recorded_trials_preprocess_load_and_train(recorded_file, tmp_path):
    dm = TactileDataModule.from_config(
        data_dir=str(tmp_path / "data"), source="recorded", raw_files=[str(recorded_file)], skin="soft",
        primitive="pressing", channels=["acc", "fsr_t", "fsr_b"], preprocess={"n_frames": 30},
        preprocess_workers=1, batch_size=2, split_file=str(tmp_path / "split.json"), train_window=None,
        windows_per_trial=1, windows_per_epoch=None,  # whole 30-frame trials
    )
    dm.prepare_data()
    dm.setup()
    # one repetition of each object per side; no object has a trial to spare for validation
    assert len(dm.train_set) == 2 and len(dm.test_set) == 2 and len(dm.val_set) == 0
    batch = next(iter(dm.train_dataloader()))
    assert batch["obs"].shape == (2, 30, 3, 28, 28) and batch["obs"].dtype == torch.float32
    assert torch.isfinite(batch["obs"]).all() and batch["obs"].abs().sum() > 0
    assert batch["actions"].shape == (2, 30, 6)
    np.testing.assert_allclose(sorted(batch["object_id"].tolist()), [0, 27])
    assert dm.describe()["source"] == "recorded"

    from embodied_tactile.model import LatentFilter
    from embodied_tactile.model.module import LatentFilterModule

    torch.manual_seed(0)
    net = LatentFilter("multi_l", encoder={"widths": [4, 8], "hidden": 16}, transition_hidden=16, lstm_hidden=16)
    model = LatentFilterModule(net, optimizer={"name": "Adam", "lr": 1e-3})
    from embodied_tactile.run.handover import HandOverStatistics

    trainer = L.Trainer(max_epochs=1, accelerator="cpu", logger=False, enable_checkpointing=False, callbacks=[HandOverStatistics()],
                        enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0)
    trainer.fit(model, datamodule=dm)
    test = trainer.test(model, datamodule=dm, verbose=False)
    assert np.isfinite(test[0]["test/elbo"])
    # the data's own statistics reached the network (the DataModule computed them in setup("fit"))
    assert dm.statistics.n_train_sequences == len(dm.train_set) == 2
    np.testing.assert_allclose(net.input_shift.numpy(), dm.statistics.channel_mean, rtol=1e-6)
    assert float(net.prior.population_weight) == 0.5
