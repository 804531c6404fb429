"""The simulated object population: its draw, its physics, its attributes, its split."""

from __future__ import annotations

import itertools
import json
import warnings

import numpy as np
import pytest

from embodied_tactile import constants as C
from embodied_tactile.data.datamodule import TactileDataModule, split_trials
from embodied_tactile.data.features import handcrafted_features
from embodied_tactile.data.prepare import TrialRef
from embodied_tactile.data.rawformat import read_trial, write_trial
from embodied_tactile.sim import population as POP
from embodied_tactile.sim import simulate_trial
from embodied_tactile.sim.validation import SimParameterError


def test_population_is_deterministic_nested_and_seeded():
    a = POP.population(40, seed=3, n_val=5, n_test=7)
    b = POP.population(10, seed=3, n_val=5, n_test=7)
    assert a["test"] == b["test"] and a["val"] == b["val"]
    assert a["train"][:10] == b["train"]  # a smaller population is a subset of a larger one
    ids = [o.object_id for objs in a.values() for o in objs]
    assert len(set(ids)) == len(ids) == 52 and min(ids) == C.POPULATION_ID_BASE
    other = POP.population(40, seed=4, n_val=5, n_test=7)
    assert [o.factors().tolist() for o in other["train"]] != [o.factors().tolist() for o in a["train"]]
    for o in a["test"]:
        assert POP.object_role(o.object_id, n_val=5, n_test=7) == "test"
    assert POP.object_role(a["train"][0].object_id, n_val=5, n_test=7) == "train"


def test_population_distributions_cover_the_documented_ranges():
    objs = [POP.population_object(k, 0) for k in range(600)]
    f = np.stack([o.factors() for o in objs])
    assert f[:, 0].min() >= 10.0 and f[:, 0].max() <= 50.0 and np.ptp(f[:, 0]) > 35.0
    assert f[:, 1].min() >= 5.0 and f[:, 1].max() <= 20.0
    rigid = np.array([o.bulk == POP.RIGID for o in objs])
    assert 0.14 < rigid.mean() < 0.26
    silicone = f[~rigid, 2]
    assert silicone.max() - silicone.min() >= 1.4  # log10 Pa: ~1.5 decades of Young's modulus
    assert np.all(f[rigid, 2] == pytest.approx(np.log10(C.MATERIALS["pla"].youngs_modulus)))
    hetero = [o for o in objs if o.heterogeneous]
    assert 0.15 < len(hetero) / (~rigid).sum() < 0.35
    for o in hetero:
        assert POP.TOP_THICKNESS_MM[0] <= o.top_thickness_mm <= POP.TOP_THICKNESS_MM[1]
        assert o.bulk_material.youngs_modulus <= C.MATERIALS[POP.TOP_LAYER].youngs_modulus / POP.TOP_TO_BULK_MIN_RATIO
        assert o.group == "heterogeneous" and o.factors()[3] == 1.0
    # viscoelastic parameters follow the modulus: softer silicones relax more and slower
    soft = sorted((o for o in objs if not o.heterogeneous and o.bulk != POP.RIGID), key=lambda o: o.bulk_material.youngs_modulus)
    assert soft[0].bulk_material.relaxation_time > soft[-1].bulk_material.relaxation_time
    assert soft[0].bulk_material.relaxation_strength > soft[-1].bulk_material.relaxation_strength


def test_catalogue_silicones_are_reproduced_by_the_interpolation():
    for key in ("ecoflex_00_10", "ecoflex_00_50", "dragon_skin_30"):
        m = C.MATERIALS[key]
        s = POP.silicone(m.youngs_modulus)
        assert (s.relaxation_strength, s.relaxation_time, s.friction) == pytest.approx(
            (m.relaxation_strength, m.relaxation_time, m.friction))


def _corner_objects():
    """The ends of the population's ranges, combined."""
    lo_e, hi_e = POP.SILICONE_MODULUS_PA
    out = []
    for k, (f0, amp, bulk, top) in enumerate(itertools.product(
            POP.SPATIAL_FREQUENCY, POP.AMPLITUDE_MM,
            (POP.silicone(lo_e), POP.silicone(hi_e), POP.RIGID),
            (None, POP.TOP_THICKNESS_MM[0], POP.TOP_THICKNESS_MM[1]))):
        if top is not None and bulk == POP.RIGID:
            continue
        out.append(C.WaveObject(C.POPULATION_ID_BASE + 5000 + k, f0, amp, bulk,
                                POP.TOP_LAYER if top is not None else None, top or 0.0))
    return out


@pytest.mark.slow
@pytest.mark.filterwarnings("error")
def test_population_extremes_simulate_finite_and_in_range():
    objs = _corner_objects()
    assert len(objs) == 28
    with warnings.catch_warnings(), np.errstate(divide="raise", over="raise", invalid="raise"):
        warnings.simplefilter("error")
        for i, o in enumerate(objs):
            tr = simulate_trial(o, C.SKINS[i % 2], C.PRIMITIVES[i % 3], 15, duration=0.5)
            assert np.isfinite(tr.acc).all() and np.isfinite(tr.pose).all()
            assert int(tr.fsr.max()) <= C.FSR_MAX_COUNT and float(np.abs(tr.acc).max()) <= C.ACC_RANGE_G
            assert tr.attrs["object_id"] == o.object_id
    # stiffer objects push back harder under the same press
    press = [simulate_trial(o, "soft", "pressing", 14, duration=2.0) for o in (objs[0], objs[1])]
    assert press[1].fsr.astype(float).sum() > press[0].fsr.astype(float).sum()


def test_invalid_population_object_is_refused_with_its_field():
    bad = C.WaveObject(C.POPULATION_ID_BASE, 30.0, 10.0, C.Material("x", -5.0, 0.1, 0.5, 1000.0, 1.0))
    with pytest.raises(SimParameterError, match="object.bulk.youngs_modulus"):
        simulate_trial(bad, "soft", "pressing", 6, duration=0.5)
    with pytest.raises(SimParameterError, match="object.top_thickness_mm"):
        simulate_trial(C.WaveObject(C.POPULATION_ID_BASE, 30.0, 10.0, "ecoflex_00_10", "dragon_skin_30", 0.0),
                       "soft", "pressing", 6, duration=0.5)


def test_description_attributes_round_trip(tmp_path):
    obj = next(o for o in (POP.population_object(k, 0) for k in range(50)) if o.heterogeneous)
    tr = simulate_trial(obj, "soft", "pressing", 6, duration=0.5)
    path = tmp_path / "pop.h5"
    name = write_trial(path, tr)
    back = read_trial(path, name)
    np.testing.assert_array_equal(back.factors, obj.factors())
    for k, v in obj.description().items():
        assert back.attrs[k] == pytest.approx(v, nan_ok=True), k
    assert back.attrs["top_thickness_mm"] == pytest.approx(obj.top_thickness_mm)
    assert back.attrs["bulk_youngs_modulus"] == pytest.approx(obj.bulk_material.youngs_modulus)
    np.testing.assert_array_equal(back.acc, tr.acc)
    # catalogue trials carry their description too
    cat = simulate_trial(28, "soft", "pressing", 6, duration=0.5)
    assert cat.attrs["top_thickness_mm"] == 2.0 and cat.attrs["top_youngs_modulus"] == 590e3


def _refs(objects, per_object=2):
    return [TrialRef(name=f"obj{o:04d}_soft_pressing_a{a:02d}_r00", object_id=o, action_index=a, skin="soft",
                     primitive="pressing", factors=tuple(float(x) for x in C.get_object(o % 32).factors()))
            for o in objects for a in range(per_object)]


def test_object_split_keeps_train_val_and_test_objects_disjoint():
    for seed in range(3):
        train, val, test = split_trials(_refs(range(32)), by="object", test_fraction=0.25, val_fraction=0.125, seed=seed)
        objs = [{t.object_id for t in part} for part in (train, val, test)]
        assert len(objs[2]) == 8 and len(objs[1]) == 4 and len(objs[0]) == 20
        assert not (objs[0] & objs[1]) and not (objs[0] & objs[2]) and not (objs[1] & objs[2])
    roles = {o: "test" if o < 3 else "val" if o < 5 else "train" for o in range(12)}
    train, val, test = split_trials(_refs(range(12)), by="object", seed=0, roles=roles)
    assert {t.object_id for t in test} == {0, 1, 2} and {t.object_id for t in val} == {3, 4}
    assert {t.object_id for t in train} == set(range(5, 12))
    with pytest.raises(ValueError, match="no role"):
        split_trials(_refs(range(13)), by="object", seed=0, roles=roles)


@pytest.mark.slow
def test_population_scene_end_to_end(tmp_path):
    """A tiny population scene: simulated, cached, split by the population's roles, each
    trial carrying its own object's factors."""
    dm = TactileDataModule.from_config(data_dir=str(tmp_path / "data"), objects="population", n_objects=3, n_val_objects=1,
                           n_test_objects=2, population_seed=7, actions=[6], channels=("fsr_t",), split="object",
                           split_file=str(tmp_path / "split.json"), sim_workers=1, preprocess_workers=1, batch_size=4)
    dm.prepare_data()
    dm.setup()
    assert dm.raw_paths[0].name == "population7_soft_pressing.h5"
    pop = POP.population(3, seed=7, n_val=1, n_test=2)
    for part, role in ((dm.train_set, "train"), (dm.val_set, "val"), (dm.test_set, "test")):
        assert sorted(t.object_id for t in part.trials) == sorted(o.object_id for o in pop[role])
        for t in part.trials:
            np.testing.assert_allclose(t.factors, POP.population_object(POP.population_index(t.object_id), 7).factors())
    saved = json.loads((tmp_path / "split.json").read_text())
    assert len(saved["test"]) == 2 and len(saved["val"]) == 1
    batch = next(iter(dm.test_dataloader()))
    assert batch["object_id"].min() >= C.POPULATION_ID_BASE


def test_unlabelled_objects_follow_the_labelled_ones_and_their_roles():
    pop = POP.population(3, seed=7, n_val=1, n_test=2, n_unlabelled=4)
    plain = POP.population(3, seed=7, n_val=1, n_test=2)
    assert [o.object_id for o in pop["unlabelled"]] == [C.POPULATION_ID_BASE + k for k in range(6, 10)]
    assert all([o.object_id for o in pop[r]] == [o.object_id for o in plain[r]] for r in ("train", "val", "test"))
    assert "unlabelled" not in plain
    assert POP.object_role(C.POPULATION_ID_BASE + 6, n_val=1, n_test=2, n_train=3) == "unlabelled"
    assert POP.object_role(C.POPULATION_ID_BASE + 5, n_val=1, n_test=2, n_train=3) == "train"
    with pytest.raises(ValueError, match="n_unlabelled"):
        POP.population(3, n_unlabelled=-1)


@pytest.mark.slow  # simulates and caches 10 trials
def test_unlabelled_objects_train_without_labels_and_the_readout_keeps_the_labelled(tmp_path):
    """n_unlabelled_objects: the training loader serves the labelled training objects and
    the unlabelled ones (NaN factors, paired by object for the context objective, with their
    crops' standardised hand-crafted features); the alignment, statistics, validation and
    test sets hold the same labelled objects as without them."""
    kw = dict(data_dir=str(tmp_path / "data"), objects="population", n_objects=2, n_val_objects=1, n_test_objects=1,
              population_seed=3, actions=[6, 14], channels=("fsr_t",), split="object", sim_workers=1,
              preprocess_workers=1, batch_size=4, train_window=20, context="trial")
    dm = TactileDataModule.from_config(n_unlabelled_objects=1, context_features=True, **kw)
    dm.prepare_data()
    dm.setup("fit")
    bare = TactileDataModule.from_config(**kw)
    bare.prepare_data()  # the same raw file: nothing simulated again
    bare.setup("fit")
    assert not bare.prepared.simulated and bare.unlabelled == []
    for a, b in ((dm.train_set, bare.train_set), (dm.val_set, bare.val_set), (dm.test_set, bare.test_set)):
        assert [t.name for t in a.trials] == [t.name for t in b.trials]
        assert all(np.isfinite(t.factors).all() for t in a.trials)
    np.testing.assert_array_equal(dm.statistics.channel_mean, bare.statistics.channel_mean)
    assert {t.object_id for t in dm.unlabelled} == {C.POPULATION_ID_BASE + 4} and len(dm.unlabelled) == 2
    assert all(np.isnan(t.factors).all() for t in dm.unlabelled)
    crops = dm.train_crops
    assert len(crops) == 6 and {t.name for t in crops.trials} == {t.name for t in dm.train_set.trials + dm.unlabelled}
    mean, std = dm.features_scale
    for i in range(len(crops)):
        item = crops[i]
        tr = crops.trials[i]
        assert np.isnan(item["factors"].numpy()).all() == (tr in dm.unlabelled)
        assert item["context_trial"] != tr.name
        assert {t.object_id for t in crops.trials if t.name == item["context_trial"]} == {tr.object_id}
        f, _ = handcrafted_features(item["obs"].numpy()[None], item["actions"].numpy()[None], ["fsr_t"])
        np.testing.assert_allclose(item["target_features"].numpy(), (f[0, -1] - mean) / std, rtol=1e-5, atol=1e-5)
    assert "target_features" not in dm.train_set[0] and "target_features" not in bare.train_crops[0]
    assert dm.describe()["n_unlabelled"] == 2
    with pytest.raises(ValueError, match="needs objects='population'"):
        TactileDataModule.from_config(data_dir=str(tmp_path / "x"), n_unlabelled_objects=2)
