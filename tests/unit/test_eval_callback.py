"""KRRAlignmentCallback inside a tiny Lightning Trainer (fake model + fake datamodule)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")
L = pytest.importorskip("lightning")

from embodied_tactile.constants import FACTOR_NAMES, OBJECTS  # noqa: E402
from embodied_tactile.eval.callback import KRRAlignmentCallback  # noqa: E402
from embodied_tactile.options.alignment import alignment_options  # noqa: E402

T, C, D = 12, 1, 8


class FakeData(torch.utils.data.Dataset):
    def __init__(self, n, seed):
        g = np.random.default_rng(seed)
        self.obj = (2 * np.arange(n) + seed) % 32  # every object group, heterogeneity varies
        self.fac = np.array([OBJECTS[o].factors() for o in self.obj], dtype=np.float32)
        self.act = g.integers(0, 16, n)
        self.obs = g.normal(size=(n, T, C, 28, 28)).astype(np.float32)
        # the observation carries the standardised factors in its first pixels
        z = (self.fac - np.array([30.0, 11.7, 6.0, 0.2])) / np.array([16.3, 6.2, 2.2, 0.4])
        self.obs[:, :, 0, 0, :4] = z[:, None, :]

    def __len__(self):
        return len(self.obj)

    def __getitem__(self, i):
        return {"obs": torch.from_numpy(self.obs[i]), "actions": torch.zeros(T, 6), "object_id": torch.tensor(self.obj[i]),
                "factors": torch.from_numpy(self.fac[i]), "action_index": torch.tensor(self.act[i])}


class FakeDataModule(L.LightningDataModule):
    def __init__(self):
        super().__init__()
        self.train_ds, self.val_ds = FakeData(48, 0), FakeData(16, 1)

    def train_dataloader(self):
        return torch.utils.data.DataLoader(self.train_ds, batch_size=8, shuffle=True)

    def train_eval_dataloader(self):
        return torch.utils.data.DataLoader(self.train_ds, batch_size=8, shuffle=False)

    def val_dataloader(self):
        return torch.utils.data.DataLoader(self.val_ds, batch_size=8, shuffle=False)


class FakeModel(L.LightningModule):
    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(4, D)
        self.rnn = torch.nn.GRU(D, D, batch_first=True)

    def infer_latents(self, batch):
        x = batch["obs"][:, :, 0, 0, :4]
        h, _ = self.rnn(torch.tanh(self.lin(x)))
        return {"z_mean": h, "y_mean": torch.tanh(self.lin(x)) + 0.0 * h}

    def training_step(self, batch, _):
        out = self.infer_latents(batch)
        return (out["z_mean"] ** 2).mean()

    def validation_step(self, batch, _):
        self.log("val/loss", (self.infer_latents(batch)["z_mean"] ** 2).mean())

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=1e-3)


@pytest.mark.slow
def test_callback_writes_history_and_logs(tmp_path):
    torch.set_num_threads(1)
    from lightning.pytorch.loggers import CSVLogger

    cb = KRRAlignmentCallback(every_n_epochs=1, latent="y", max_train_sequences=40, alignment={"cv": 2}, checks={"cv": 2},
                              val_frame_stride=3)
    logger = CSVLogger(tmp_path, name="run")
    trainer = L.Trainer(max_epochs=2, default_root_dir=tmp_path, logger=logger, callbacks=[cb], enable_progress_bar=False,
                        enable_model_summary=False, enable_checkpointing=False, accelerator="cpu", devices=1,
                        log_every_n_steps=1, num_sanity_val_steps=0)
    torch.manual_seed(0)  # the t = 0 row scores the untrained network: fix its weights
    trainer.fit(FakeModel(), datamodule=FakeDataModule())
    path = cb.history_path(trainer)
    assert path.name == "krr_history.jsonl" and path.exists()
    rows = [json.loads(line) for line in path.read_text().splitlines()]
    # t = 0, every epoch, then the final alignment (evaluate.py's settings: all training sequences, every frame)
    assert [(r["epoch"], r["final"]) for r in rows] == [(-1, False), (0, False), (1, False), (1, True)]
    assert rows[0]["initial"] and rows[0]["train_wall_time_s"] == 0 and rows[0]["step"] == 0
    assert rows[-1]["val_frame_stride"] == 1 and rows[-1]["alignment"]["frames_per_sequence"] == 4
    assert rows[-1]["alignment"]["cv_folds"] == 2 and cb.final == rows[-1]
    # the final row's interval: the test objects resampled, around the run's own number
    boot = rows[-1]["bootstrap_objects"]
    assert boot["resamples"] == 1000 and all("bootstrap_objects" not in r for r in rows[:-1])
    for key, value in (("overall_ci95", rows[-1]["nmse_overall"]), ("last_overall_ci95", rows[-1]["nmse_last_overall"])):
        lo, hi = boot[key]
        assert 0 <= lo < hi and lo <= value * 1.1 and value <= hi * 1.1
    for r in rows:
        assert r["n_train"] == (48 if r["final"] else 40) and r["n_test"] == 16
        assert all(np.isfinite(r["nmse"][f]) for f in FACTOR_NAMES)
        assert r["nmse_overall"] < 0.5  # the fake latents carry the factors
        assert r["train_wall_time_s"] >= 0 and r["callback_time_s"] > 0
    assert rows[1]["train_wall_time_s"] > rows[0]["train_wall_time_s"]
    assert "krr/nmse_overall" in trainer.callback_metrics
    logged = (tmp_path / "run" / "version_0" / "metrics.csv").read_text()
    for k in ("krr/nmse_spatial_frequency", "krr/nmse_overall", "krr/train_wall_time_s", "krr/callback_time_s"):
        assert k in logged


def test_collect_latents_feeds_evaluate_latents():
    torch.set_num_threads(1)
    from embodied_tactile.eval import evaluate_latents
    from embodied_tactile.eval.latents import collect_latents

    dm, model = FakeDataModule(), FakeModel()
    model.train()
    tr = collect_latents(model, dm.train_eval_dataloader(), latent="both", max_sequences=20)
    te = collect_latents(model, dm.val_dataloader(), latent="both")
    assert model.training  # mode restored
    assert tr["z"].shape == (20, T, D) and tr["y"].shape == (20, T, D) and te["factors"].shape == (16, 4)
    res, align = evaluate_latents(tr, te, latent="both", alignment=alignment_options({"cv": 2, "readout": "final_segment"}))
    assert align.x_mean.shape == (2 * D,) and res.pred.shape == (16, T, 4)
    assert np.isfinite(res.subset_nmse()).all()


class _Probe(L.Callback):
    """Records the krr/nmse_overall value visible at each epoch end (what progress lines print)."""

    def __init__(self):
        self.seen = []

    def on_train_epoch_end(self, trainer, pl_module):
        v = trainer.callback_metrics.get("krr/nmse_overall")
        self.seen.append(None if v is None else float(v))


@pytest.mark.slow
def test_krr_value_shows_only_in_its_epoch_and_final_is_the_result(tmp_path):
    torch.set_num_threads(1)
    cb = KRRAlignmentCallback(every_n_epochs=2, latent="y", alignment={"cv": 2}, checks={"cv": 2},
                              val_frame_stride=3)
    probe = _Probe()
    trainer = L.Trainer(max_epochs=3, default_root_dir=tmp_path, logger=False, callbacks=[cb, probe],
                        enable_progress_bar=False, enable_model_summary=False, enable_checkpointing=False,
                        accelerator="cpu", devices=1, num_sanity_val_steps=0)
    trainer.fit(FakeModel(), datamodule=FakeDataModule())
    assert cb.history[0]["initial"]
    periodic = cb.history[1]
    assert probe.seen == [None, pytest.approx(periodic["nmse_overall"]), None]  # no stale value in epoch 3
    assert cb.final is cb.history[-1] and cb.final["final"] and cb.final["epoch"] == 2
    # after fit (metrics.json's fit_metrics) the krr/* values are the final alignment's
    assert float(trainer.callback_metrics["krr/nmse_overall"]) == pytest.approx(cb.final["nmse_overall"])


@pytest.mark.slow
def test_wall_time_continues_across_a_resume(tmp_path):
    """The elapsed training / callback time travels in the checkpoint (the callback's
    state_dict): a run resumed from it continues the clock instead of restarting at 0."""
    torch.set_num_threads(1)

    def fit(max_epochs, ckpt_path=None):
        cb = KRRAlignmentCallback(every_n_epochs=1, latent="y", alignment={"cv": 2}, checks={"cv": 2},
                                  val_frame_stride=3,
                                  run_on_train_end=False)
        trainer = L.Trainer(max_epochs=max_epochs, default_root_dir=tmp_path, logger=False, callbacks=[cb],
                            enable_progress_bar=False, enable_model_summary=False, enable_checkpointing=False,
                            accelerator="cpu", devices=1, num_sanity_val_steps=0)
        trainer.fit(FakeModel(), datamodule=FakeDataModule(), ckpt_path=ckpt_path)
        return trainer, cb

    trainer, first = fit(2)
    ckpt = tmp_path / "e2.ckpt"
    trainer.save_checkpoint(ckpt)
    state = torch.load(ckpt, map_location="cpu", weights_only=False)["callbacks"][first.state_key]
    assert state["elapsed_s"] > state["callback_time_s"] > 0
    assert state["elapsed_s"] - state["callback_time_s"] >= first.history[-1]["train_wall_time_s"]
    _, second = fit(4, ckpt)
    rows = [json.loads(line) for line in first.history_path(trainer).read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [-1, 0, 1, 2, 3]  # the resumed fit adds no second t = 0 row
    wall = [r["train_wall_time_s"] for r in rows]
    assert all(b > a for a, b in zip(wall, wall[1:])), wall
    assert second.history[0]["train_wall_time_s"] > state["elapsed_s"] - state["callback_time_s"]
    assert second.history[0]["callback_time_total_s"] > state["callback_time_s"]


def test_check_epochs_spread_points_over_the_run():
    from embodied_tactile.eval.callback import check_epochs

    # the last check reads the final weights (then the final alignment reads them again)
    assert check_epochs(16, 8) == [1, 3, 5, 7, 9, 11, 13, 15]
    assert check_epochs(500, 8)[:2] == [61, 124] and check_epochs(500, 8)[-1] == 499
    assert check_epochs(3, 8) == [0, 1, 2]  # fewer epochs than points: every epoch
    with pytest.raises(ValueError, match="points must be >= 1"):
        check_epochs(10, 0)


class _CountingData(FakeData):
    def __init__(self, n, seed):
        super().__init__(n, seed)
        self.reads = 0

    def __getitem__(self, i):
        self.reads += 1
        return super().__getitem__(i)


class _CountingDataModule(FakeDataModule):
    def __init__(self):
        super().__init__()
        self.eval_ds, self.test_set = _CountingData(48, 0), _CountingData(16, 1)

    def train_eval_dataloader(self):
        return torch.utils.data.DataLoader(self.eval_ds, batch_size=8, shuffle=False)

    def test_dataloader(self):  # the held-out split the callback scores
        return torch.utils.data.DataLoader(self.test_set, batch_size=8, shuffle=False)


class _BatchSizeModel(FakeModel):
    def __init__(self):
        super().__init__()
        self.eval_batches = []

    def infer_latents(self, batch):  # the callback's calls (validation_step below bypasses it)
        self.eval_batches.append(len(batch["obs"]))
        return super().infer_latents(batch)

    def training_step(self, batch, _):
        return (FakeModel.infer_latents(self, batch)["z_mean"] ** 2).mean()

    def validation_step(self, batch, _):
        self.log("val/loss", (FakeModel.infer_latents(self, batch)["z_mean"] ** 2).mean())


@pytest.mark.slow
def test_points_give_a_t0_row_and_8_points_reading_inputs_once(tmp_path):
    """Error against run time: a row before training (t = 0, the untrained network), then
    `points` = 8 checks over an 8-epoch run, the last on the final weights, then the final
    alignment on the same weights; inputs read from the loaders once and inferred in batches
    of infer_batch_size sequences, both splits together."""
    torch.set_num_threads(1)
    cb = KRRAlignmentCallback(latent="y", alignment={"cv": 2}, checks={"cv": 2}, val_frame_stride=3,
                              points=8, infer_batch_size=32)
    assert cb.every_n_epochs is None  # the default spreads `points` over the run
    dm, model = _CountingDataModule(), _BatchSizeModel()
    trainer = L.Trainer(max_epochs=8, default_root_dir=tmp_path, logger=False, callbacks=[cb],
                        enable_progress_bar=False, enable_model_summary=False, enable_checkpointing=False,
                        accelerator="cpu", devices=1, num_sanity_val_steps=0, limit_train_batches=1)
    trainer.fit(model, datamodule=dm)
    rows = [json.loads(line) for line in cb.history_path(trainer).read_text().splitlines()]
    assert rows[0]["initial"] and rows[0]["epoch"] == -1 and rows[0]["train_wall_time_s"] == 0.0
    assert [r["epoch"] for r in rows] == [-1, 0, 1, 2, 3, 4, 5, 6, 7, 7] and rows[-1]["final"]
    assert sum(not r["final"] for r in rows) == 9 and not any(r["initial"] for r in rows[1:])
    # the last check and the final alignment read the same weights, each with its own read-out
    assert rows[-2]["step"] == rows[-1]["step"] and rows[-2]["alignment_settings"]["cv"] == 2
    assert rows[-2]["val_frame_stride"] == 3 and rows[-1]["val_frame_stride"] == 1
    wall = [r["train_wall_time_s"] for r in rows]
    assert all(b > a for a, b in zip(wall[:-1], wall[1:-1])) and wall[-1] >= wall[-2], wall
    # read once (the final alignment reuses the cache: it holds every sequence); the 48 training
    # and 16 held-out sequences inferred together in batches of 32
    assert dm.eval_ds.reads == 48 and dm.test_set.reads == 16
    assert model.eval_batches == [32, 32] * 10



class _FrozenModel(_BatchSizeModel):
    def configure_optimizers(self):  # lr 0: the final weights are the untrained ones
        return torch.optim.SGD(self.parameters(), lr=0.0)


@pytest.mark.slow
def test_step0_row_holds_the_floor_read_by_the_final_alignments_readout(tmp_path):
    """The untrained network's floor is the run's own read-out: with weights that never move,
    the step-0 row's ``floor`` equals the final alignment to the last bit, while the step-0
    check itself (a cheaper read-out, every third frame) is another number."""
    torch.set_num_threads(1)
    cb = KRRAlignmentCallback(latent="y", alignment={"cv": 3}, checks={"cv": 2, "frames_per_sequence": 1},
                              val_frame_stride=3, points=2)
    trainer = L.Trainer(max_epochs=2, default_root_dir=tmp_path, logger=False, callbacks=[cb],
                        enable_progress_bar=False, enable_model_summary=False, enable_checkpointing=False,
                        accelerator="cpu", devices=1, num_sanity_val_steps=0, limit_train_batches=1)
    trainer.fit(_FrozenModel(), datamodule=_CountingDataModule())
    first, final = cb.history[0], cb.history[-1]
    assert first["initial"] and final["final"] and "floor" not in final
    for key in ("nmse", "nmse_overall", "nmse_last", "nmse_last_overall"):
        assert first["floor"][key] == final[key]
    assert first["nmse_overall"] != final["nmse_overall"]

def test_both_splits_inferred_in_one_pass_give_each_splits_own_latents():
    """The callback infers the cached training and held-out sequences in one pass (merged
    batches); every sequence's latents equal those of inferring each split on its own."""
    from embodied_tactile.eval.latents import collect_latents, rebatch
    from embodied_tactile.model.latent_filter import LatentFilter
    from embodied_tactile.model.module import LatentFilterModule

    torch.manual_seed(0)
    model = LatentFilterModule(LatentFilter("multi_l", n_z=4, n_y=3, encoder={"widths": [4, 8], "hidden": 16},
                                                transition_hidden=16, lstm_hidden=16, obs_sigma=0.1))
    g = torch.Generator().manual_seed(1)

    def batches(n, size):
        out = []
        for i in range(0, n, size):
            b = min(size, n - i)
            out.append({"obs": torch.rand(b, T, 3, 28, 28, generator=g), "actions": torch.randn(b, T, 6, generator=g),
                        "object_id": torch.arange(i, i + b) % 32, "factors": torch.rand(b, 4, generator=g),
                        "action_index": torch.full((b,), 6)})
        return out

    train, held = batches(10, 4), batches(5, 3)
    dm = SimpleNamespace(train_eval_dataloader=lambda: train, val_dataloader=lambda: held)
    cb = KRRAlignmentCallback(latent="both", infer_batch_size=16)
    tr, te = cb._latents(SimpleNamespace(datamodule=dm), model, final=False)
    assert [len(b["factors"]) for b in cb._inputs[0]] == [15]  # one merged batch, training first
    tr_alone = collect_latents(model, rebatch(train, 16), latent="both")
    te_alone = collect_latents(model, rebatch(held, 16), latent="both")
    for joint, alone, n in ((tr, tr_alone, 10), (te, te_alone, 5)):
        assert joint.keys() == alone.keys() and len(joint["factors"]) == n
        for k in ("z", "y"):
            np.testing.assert_allclose(joint[k], alone[k], rtol=1e-5, atol=1e-6)
        for k in ("factors", "object_id", "action_index"):
            np.testing.assert_array_equal(joint[k], alone[k])


def test_a_check_capped_below_the_training_set_reads_sequences_spread_over_all_objects():
    """The check's cap on training sequences keeps every object's share: the dataset runs
    object by object, and the first sequences alone would hold only the first objects."""
    from embodied_tactile.eval.latents import cache_batches

    ds = FakeData(64, 0)
    ds.obj = np.repeat(np.arange(16), 4)  # object by object, as the scenes' datasets are ordered
    loader = torch.utils.data.DataLoader(ds, batch_size=10)
    batches, whole = cache_batches(loader, 16)
    objects = torch.cat([b["object_id"] for b in batches]).tolist()
    assert len(objects) == 16 and not whole
    assert set(objects) == set(range(16))  # every object, not objects 0-3
    assert cache_batches(loader, 64)[1] and cache_batches(loader, None)[1]
