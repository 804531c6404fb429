"""The context objective's label-free terms (model/objectives.py): VICReg values on hand-made
inputs, no NaN on identical inputs, the variance term against collapse, the physical term,
and the training loss that never reads property labels."""

import math

import numpy as np
import pytest
import torch

from embodied_tactile.data.features import handcrafted_features
from embodied_tactile.model import LatentFilter, LatentFilterModule
from embodied_tactile.model.objectives import (
    COVARIANCE_WEIGHT,
    VARIANCE_EPS,
    FeatureHead,
    feature_count,
    invariance_terms,
    physical_term,
)
from tests.unit.test_context import TINY, pair_batch

torch.set_num_threads(2)


def test_invariance_terms_on_hand_made_views():
    y_a = torch.tensor([[0.0, 0.0], [2.0, 2.0]])
    y_b = torch.tensor([[1.0, 0.0], [2.0, 2.0]])
    t = invariance_terms(y_a, y_b)
    assert float(t["invariance"]) == pytest.approx(0.25)  # (1 + 0 + 0 + 0) / 4
    # y_a: std sqrt(2) in both dimensions (above 1); y_b: sqrt(0.5) in the first
    assert float(t["variance"]) == pytest.approx((1 - math.sqrt(0.5 + VARIANCE_EPS)) / 2, rel=1e-5)
    # off-diagonal covariances 2 (y_a) and 1 (y_b): 2 * 2^2 / 2 + 2 * 1^2 / 2
    assert float(t["covariance"]) == pytest.approx(5.0)
    assert float(t["total"]) == pytest.approx(float(t["invariance"] + t["variance"]) + COVARIANCE_WEIGHT * 5.0)
    assert all(v.dtype == torch.float32 for v in t.values())
    with pytest.raises(ValueError, match="two"):
        invariance_terms(y_a, y_b[:, :1])


def test_invariance_terms_are_finite_on_identical_inputs_and_one_row():
    for rows in (8, 1):
        y = torch.full((rows, 4), 3.0, requires_grad=True)
        t = invariance_terms(y, y.detach().clone().requires_grad_(True))
        values = {k: float(v.detach()) for k, v in t.items()}
        assert values["invariance"] == 0.0 and values["covariance"] == 0.0
        assert values["variance"] == pytest.approx(2 * (1 - math.sqrt(VARIANCE_EPS)))
        t["total"].backward()
        assert torch.isfinite(y.grad).all()


def _train_views(loss_of, steps=150):
    """A linear map of random inputs, started almost collapsed (weights 1e-3), trained on
    two noisy views of each input; -> its outputs' per-dimension std afterwards."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(64, 8, generator=g)
    lin = torch.nn.Linear(8, 4)
    with torch.no_grad():
        lin.weight.mul_(1e-3 / lin.weight.std())
        lin.bias.zero_()
    opt = torch.optim.Adam(lin.parameters(), lr=1e-2)
    for _ in range(steps):
        a = lin(x + 0.1 * torch.randn(x.shape, generator=g))
        b = lin(x + 0.1 * torch.randn(x.shape, generator=g))
        loss = loss_of(invariance_terms(a, b))
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        return lin(x).std(0)


@pytest.mark.slow
def test_the_variance_term_stops_collapse():
    """VICReg lifts every dimension's std above 0.9 of its hinge from a collapsed start;
    the invariance term alone leaves it collapsed."""
    assert (_train_views(lambda t: t["total"]) > 0.9).all()
    assert (_train_views(lambda t: t["invariance"]) < 0.05).all()


def test_physical_term_and_feature_count():
    assert float(physical_term(torch.zeros(2, 3), torch.ones(2, 3))) == pytest.approx(1.0)
    assert float(physical_term(torch.tensor([[1.0, 3.0]]), torch.tensor([[0.0, 1.0]]))) == pytest.approx(2.5)
    with pytest.raises(ValueError, match="differ"):
        physical_term(torch.zeros(2, 3), torch.zeros(2, 4))
    for channels in (["acc"], ["acc", "fsr_t", "fsr_b"]):
        _, names = handcrafted_features(np.random.rand(2, 5, len(channels), 28, 28), np.random.rand(2, 5, 6), channels)
        assert feature_count(channels) == len(names)
    head = FeatureHead(n_y=3, n_a=6, n_features=5)
    assert head(torch.zeros(2, 3), torch.zeros(2, 7, 6)).shape == (2, 5)


def _module(invariance=0.0, physical=0.0):
    torch.manual_seed(0)
    return LatentFilterModule(LatentFilter("acc", **TINY), optimizer={"name": "Adam", "lr": 1e-2},
                              context={"source": "trial", "initial_frames": 2, "invariance": invariance,
                                       "physical": physical})


def _batch(k):
    batch = pair_batch()
    g = torch.Generator().manual_seed(5)
    batch["factors"] = torch.rand(batch["obs"].shape[0], 4, generator=g)
    batch["target_features"] = torch.randn(batch["obs"].shape[0], k, generator=g)
    return batch


def _loss(module, batch):
    torch.manual_seed(3)
    return module.training_step(batch, 0)


@pytest.mark.filterwarnings("ignore:.*self.log.*")
def test_the_training_loss_adds_the_weighted_terms_and_never_reads_labels():
    k = feature_count(["acc"])
    batch = _batch(k)
    base = _module()
    assert base.feature_head is None and base.auxiliary_terms(batch, {}) == {}
    both = _module(invariance=2.0, physical=3.0)
    assert both.hparams["context"]["invariance"] == 2.0 and both.feature_head.n_features == k
    loss = _loss(both, batch)
    torch.manual_seed(3)
    terms = both._terms(batch, keep_out=True)
    plain, _ = both.annealing(both.global_step, {n: v for n, v in terms.items() if n != "out"})
    aux = both.auxiliary_terms(batch, terms["out"])
    assert set(aux) == {"invariance", "variance", "covariance", "physical"}
    assert float(loss) == pytest.approx(float(plain + 2.0 * aux["invariance"] + 3.0 * aux["physical"]), rel=1e-6)
    assert float(aux["invariance"]) > 0 and float(aux["physical"]) > 0
    loss.backward()
    grads = [p.grad for p in both.parameters() if p.grad is not None]
    assert all(torch.isfinite(g).all() for g in grads)
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in both.feature_head.parameters())
    # the property labels and the object ids: NaN or absent, the loss is the same number
    unlabelled = {**batch, "factors": torch.full_like(batch["factors"], float("nan")),
                  "object_id": torch.full_like(batch["object_id"], -1)}
    without = {key: v for key, v in batch.items() if key not in ("factors", "object_id")}
    for other in (unlabelled, without):
        assert float(_loss(both, other)) == float(_loss(both, batch))


def test_the_terms_refuse_what_they_cannot_use():
    module = _module(physical=1.0)
    batch = pair_batch()
    torch.manual_seed(0)
    terms = module._terms(batch, keep_out=True)
    with pytest.raises(ValueError, match="context_features"):
        module.auxiliary_terms(batch, terms["out"])
    with pytest.raises(ValueError, match="context.invariance must be a weight"):
        LatentFilterModule(LatentFilter("acc", **TINY), context={"source": "trial", "invariance": -1.0})
    with pytest.raises(ValueError, match="touches=1"):
        LatentFilterModule(LatentFilter("acc", **TINY), context={"source": "trial", "touches": 2, "invariance": 1.0})


@pytest.mark.slow
def test_recipes_set_the_weights_and_the_feature_targets(tmp_path):
    from hydra.utils import instantiate

    from tests.unit.test_configs import _compose

    for recipe, inv, phys in (("context_invariance", 100.0, 0.0), ("context_physical", 0.0, 100.0),
                              ("context_both", 100.0, 100.0)):
        cfg = _compose(["experiment=population", f"recipe={recipe}"], tmp_path)
        assert cfg.data.context == "trial" and cfg.model.net.y_start == "population"
        assert (cfg.model.context.invariance, cfg.model.context.physical) == (inv, phys)
        assert cfg.data.context_features is (phys > 0)
        module = instantiate(cfg.model)
        assert (module.feature_head is not None) is (phys > 0)
    assert _compose(["experiment=population"], tmp_path).model.context.invariance == 0.0


@pytest.mark.slow
def test_train_entry_refuses_the_physical_term_without_its_targets(tmp_path):
    from embodied_tactile.run.settings import SettingsError, check_train_config
    from tests.unit.test_configs import _compose

    cfg = _compose(["experiment=population", "model.context.physical=5"], tmp_path)
    with pytest.raises(SettingsError, match="model.context.physical=5.0 needs data.context_features=true"):
        check_train_config(cfg)
    check_train_config(_compose(["experiment=population", "recipe=context_physical"], tmp_path))
    with pytest.raises(SettingsError, match="n_unlabelled_objects"):
        check_train_config(_compose(["experiment=population", "data.n_unlabelled_objects=-1"], tmp_path))
    with pytest.raises(SettingsError, match=r"\(256 \+ 32 \+ 64 \+ 20000 unlabelled objects x 2 action"):
        check_train_config(_compose(["experiment=population", "data.n_unlabelled_objects=20000"], tmp_path))
