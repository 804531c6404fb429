"""One modality definition: the yaml in configs/modality/, read by the DataModule, the
model and the baselines; a new modality is one yaml file."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml
from hydra.utils import instantiate
from omegaconf import OmegaConf

from conftest import REPO, TINY_ACTIONS, TINY_OBJECTS
from test_configs import _compose_job
from embodied_tactile.data.modality import CHANNELS, Modality, fields_for_channels, load_modality, modality_names


def test_every_shipped_modality_is_valid_and_complete():
    names = modality_names()
    assert {"acc", "fsr_t", "fsr_b", "fsr_tb", "multi_e", "multi_l"} <= set(names)
    for name in names:
        raw = yaml.safe_load((REPO / "configs" / "modality" / f"{name}.yaml").read_text())
        mod = load_modality(name)
        assert mod.name == name and list(mod.channels) == raw["channels"]
        assert Modality.from_config(mod.to_config()) == mod  # round trip, checkpoint-safe
        assert mod.fields == fields_for_channels(mod.channels)
        assert set(mod.raw_fields) <= {"tactile/acc", "tactile/fsr"}
    ml = load_modality("multi_l")
    assert ml.pathway_indices() == [("vibration", [0]), ("force", [1, 2])]
    assert load_modality("acc").raw_fields == ["tactile/acc"]  # acc never needs FSR data
    assert load_modality("fsr_tb").fields == ["fsr", "actions"]


def test_bad_modalities_are_named():
    with pytest.raises(ValueError, match="unknown channel"):
        Modality.from_config({"name": "x", "channels": ["gyro"], "fusion": "single"})
    with pytest.raises(ValueError, match="pathways are only meaningful"):
        Modality.from_config({"name": "x", "channels": ["acc"], "fusion": "single", "pathways": {"a": ["acc"]}})
    with pytest.raises(ValueError, match="must partition"):
        Modality.from_config({"name": "x", "channels": ["acc", "fsr_t"], "fusion": "late",
                              "pathways": {"a": ["acc"], "b": ["fsr_b"]}})
    with pytest.raises(ValueError, match="unknown modality 'nope'"):
        load_modality("nope")
    with pytest.raises(TypeError, match="a modality is a mapping"):
        Modality.from_config(["acc"])


@pytest.mark.slow
def test_a_new_modality_is_one_yaml_file(tmp_path, tiny_data_dir):
    """A late-fusion modality that exists only in a test config folder flows through Hydra
    into the DataModule (its fields only), the model (its pathways) and a training loss."""
    extra = tmp_path / "extra_configs"
    (extra / "modality").mkdir(parents=True)
    (extra / "modality" / "acc_bottom_l.yaml").write_text(
        "name: acc_bottom_l\nlabel: ACC+FSR_b late\nchannels: [fsr_b, acc]\nfusion: late\n"
        "pathways:\n  force: [fsr_b]\n  vibration: [acc]\n")
    cfg = _compose_job([
        f"hydra.searchpath=[file://{extra}]", "modality=acc_bottom_l",
        f"data.objects={TINY_OBJECTS}", f"data.actions={TINY_ACTIONS}",
        "data.repetitions=2", "data.sim_workers=1", "data.preprocess_workers=1", "data.batch_size=4",
        "data.train_window=null", "data.windows_per_trial=1", "data.windows_per_epoch=null",
        "model.net.encoder.widths=[4,8]", "model.net.encoder.hidden=16", "model.net.transition_hidden=16",
        "model.net.lstm_hidden=16"], tmp_path)
    cfg.data.data_dir = str(tiny_data_dir)
    OmegaConf.resolve(cfg)
    dm = instantiate(cfg.data)
    assert dm.fields == ["fsr", "acc", "actions"]
    dm.prepare_data()
    dm.setup()
    batch = next(iter(dm.train_dataloader()))
    assert batch["obs"].shape[2] == 2
    model = instantiate(cfg.model)
    assert set(model.model.observation.encoders) == {"force", "vibration"}
    assert model.model.modality["pathways"] == [["force", [0]], ["vibration", [1]]]
    terms = model.model.elbo_terms(batch)
    assert all(torch.isfinite(terms[k]) for k in ("nll", "kl_z", "kl_y"))
    assert CHANNELS["fsr_b"][:2] == ("fsr", 1)
