"""The context objective: the DataModule's pairing, the open-loop target rollout, the
object id kept out of the model, the K-touch combination and the swap test."""

import pytest
import torch

from embodied_tactile.model import LatentFilterModule, LatentFilter
from embodied_tactile.model.latent_filter import combine_touches
from tests.conftest import tiny_datamodule

torch.set_num_threads(2)

TINY = dict(encoder={"widths": [4, 8], "hidden": 32}, transition_hidden=32, lstm_hidden=32, input_standardize=False)


def pair_batch(B=4, T=10, Tc=12, seed=0, n_objects=32):
    g = torch.Generator().manual_seed(seed)
    return {
        "obs": torch.rand(B, T, 1, 28, 28, generator=g),
        "actions": torch.randn(B, T, 6, generator=g),
        "context_obs": torch.rand(B, Tc, 1, 28, 28, generator=g),
        "context_actions": torch.randn(B, Tc, 6, generator=g),
        "object_id": torch.randint(0, n_objects, (B,), generator=g),
    }


def terms(net, batch, **kw):
    torch.manual_seed(0)
    t = net.context_terms(batch, **kw)
    return {k: float(t[k].detach()) for k in ("nll", "kl_z", "kl_y")}


# ------------------------------------------------------------------ the pairing
@pytest.fixture(scope="module")
def paired(tiny_data_dir, tmp_path_factory):
    """The tiny scene (4 objects x 2 actions x 2 repetitions, acc; whole objects held out,
    so the validation object has 4 trials) with each pairing."""
    out = {}
    for source in ("trial", "window"):
        dm = tiny_datamodule(tiny_data_dir, ["acc"], train_window=40, context=source, split="object",
                             split_file=str(tmp_path_factory.mktemp(source) / "split.json"))
        dm.prepare_data()
        dm.setup("fit")
        out[source] = dm
    return out


@pytest.mark.slow
def test_window_context_is_a_disjoint_window_of_the_same_trial(paired):
    dm = paired["window"]
    ds = dm.train_crops
    for i in range(len(ds)):
        item = ds[i]
        tr = ds.trials[i % len(ds.trials)]
        assert item["context_trial"] == tr.name
        a, b = int(item["first_frame"]), int(item["context_first_frame"])
        assert item["obs"].shape[0] == item["context_obs"].shape[0] == 40
        assert a + 40 <= b or b + 40 <= a  # disjoint
        whole = dm.train_set[i % len(ds.trials)]
        assert torch.equal(whole["obs"][b:b + 40], item["context_obs"])
        assert torch.equal(whole["actions"][b:b + 40], item["context_actions"])


def test_trial_context_is_another_trial_of_the_same_object(paired):
    """Training crops, the validation pairs and the test objects' pairs (held_out_pairs, the
    benchmark's) pair a trial with another trial of its object; held-out pairs repeat."""
    dm = paired["trial"]
    test_pairs = dm.held_out_pairs(dm.test_set.trials)
    again = dm.held_out_pairs(dm.test_set.trials)
    assert [test_pairs[i]["context_trial"] for i in range(len(test_pairs))] == \
        [again[i]["context_trial"] for i in range(len(again))]
    for ds in (dm.train_crops, dm.val_pairs, test_pairs):
        by_name = {t.name: t for t in ds.trials}
        for i in range(len(ds)):
            item = ds[i]
            tr, other = ds.trials[i % len(ds.trials)], by_name[item["context_trial"]]
            assert other.name != tr.name and other.object_id == tr.object_id


def test_validation_pairs_are_fixed_and_evaluation_loaders_serve_whole_trials(paired):
    dm = paired["trial"]
    first = next(iter(dm.val_dataloader()))
    again = next(iter(dm.val_dataloader()))
    assert first["context_trial"] == again["context_trial"]
    assert torch.equal(first["first_frame"], again["first_frame"])
    assert first["obs"].shape[1] == 40
    for loader in (dm.val_eval_dataloader(), dm.train_eval_dataloader(), dm.test_dataloader()):
        batch = next(iter(loader))
        assert batch["obs"].shape[1] == 300 and "context_obs" not in batch


def test_trial_context_refuses_an_object_with_one_trial(tiny_data_dir, tmp_path):
    from embodied_tactile.data.datamodule import TactileSequenceDataset

    dm = tiny_datamodule(tiny_data_dir, ["acc"], split_file=str(tmp_path / "s.json"))
    dm.prepare_data()
    dm.setup("fit")
    one = [dm.train_set.trials[0]]
    with pytest.raises(ValueError, match="fewer than 2 trials"):
        TactileSequenceDataset(dm.cache_files, one, ["acc"], context="trial")
    with pytest.raises(ValueError, match="needs a window"):
        TactileSequenceDataset(dm.cache_files, one, ["acc"], context="window")


def test_a_context_of_several_touches_is_distinct_other_trials_of_the_object(paired, tmp_path):
    """context_touches=3 on the tiny scene (4 trials per object): each item's context is the
    object's three other trials, with a touch axis, each the rows of that trial; a fourth
    touch is refused naming the objects."""
    from embodied_tactile.data.datamodule import TactileSequenceDataset

    dm = paired["trial"]
    whole = {t.name: dm.train_set[i] for i, t in enumerate(dm.train_set.trials)}
    ds = TactileSequenceDataset(dm.cache_files, dm.train_set.trials, ["acc"], window=40, context="trial",
                                context_touches=3, draw_seed=0)
    for i in range(len(ds)):
        item, tr = ds[i], ds.trials[i % len(ds.trials)]
        names = item["context_trial"].split("+")
        assert item["context_obs"].shape == (3, 40, 1, 28, 28) and item["context_actions"].shape == (3, 40, 6)
        assert len(set(names)) == 3 and tr.name not in names
        assert {whole[n]["object_id"].item() for n in names} == {tr.object_id}
        for k, n in enumerate(names):
            start = int(item["context_first_frame"][k])
            assert torch.equal(whole[n]["obs"][start:start + 40], item["context_obs"][k])
    with pytest.raises(ValueError, match="fewer than 5 trials"):
        TactileSequenceDataset(dm.cache_files, dm.train_set.trials, ["acc"], window=40, context="trial",
                               context_touches=4)
    with pytest.raises(ValueError, match="context_touches"):
        TactileSequenceDataset(dm.cache_files, dm.train_set.trials, ["acc"], window=40, context="window",
                               context_touches=2)


def test_a_context_of_several_touches_combines_their_posteriors_by_the_product_rule():
    """context_posterior over (B, M, T, ...) is combine_touches of the M touches' own
    posteriors from touch_prior (the K-touch read-out's rule), and the module trains on it."""
    torch.manual_seed(0)
    net = LatentFilter("acc", y_start="population", **TINY).eval()
    g = torch.Generator().manual_seed(3)
    obs, actions = torch.rand(2, 3, 12, 1, 28, 28, generator=g), torch.randn(2, 3, 12, 6, generator=g)
    with torch.no_grad():
        m, v = net.context_posterior(obs, actions)
        each = [net.context_posterior(obs[:, k], actions[:, k]) for k in range(3)]
        ref_m, ref_v = combine_touches(torch.stack([e[0] for e in each]), torch.stack([e[1] for e in each]),
                                       *net.touch_prior())
    assert m.shape == v.shape == (2, net.n_y)
    assert torch.allclose(m, ref_m, atol=1e-6) and torch.allclose(v, ref_v, atol=1e-7)
    assert (v <= torch.stack([e[1] for e in each]).min(0).values + 1e-7).all()
    module = LatentFilterModule(net, context={"source": "trial", "touches": 3})
    batch = {**pair_batch(B=2), "context_obs": obs, "context_actions": actions}
    loss = module.training_step(batch, 0)
    assert torch.isfinite(loss)
    loss.backward()
    with pytest.raises(ValueError, match="touches"):
        LatentFilterModule(LatentFilter("acc", **TINY), context={"source": "window", "touches": 2})


# ------------------------------------------------------------------ the objective
def test_object_id_never_reaches_the_model():
    """Changing the object ids with the same pairing leaves the loss unchanged, with the
    prior's labels on too: the id is never read."""
    for labels in (False, True):
        torch.manual_seed(1)
        net = LatentFilter("acc", prior={"labels": labels}, **TINY)
        batch = pair_batch()
        other = {**batch, "object_id": (batch["object_id"] + 7) % 32}
        assert terms(net, batch) == terms(net, other)
        assert terms(net, {k: v for k, v in batch.items() if k != "object_id"}) == terms(net, batch)


@pytest.mark.parametrize("refilter", [False, True])
def test_open_loop_prediction_ignores_target_frames_after_the_initial_ones(refilter):
    torch.manual_seed(0)
    net = LatentFilter("acc", **TINY).eval()
    with torch.no_grad():  # a transition that moves z (its mean head starts at zero)
        for p in net.transition.mean.parameters():
            p.normal_(0, 0.1)
    batch = pair_batch()
    y = torch.randn(4, net.n_y)
    later = batch["obs"].clone()
    later[:, 3:] = torch.rand_like(later[:, 3:])
    with torch.no_grad():
        a = net.rollout(batch["obs"], batch["actions"], y, 3, sample=False, refilter=refilter)["recon"]
        b = net.rollout(later, batch["actions"], y, 3, sample=False, refilter=refilter)["recon"]
        c = net.rollout(batch["obs"], batch["actions"], -y, 3, sample=False, refilter=refilter)["recon"]
    assert torch.equal(a[:, :3], b[:, :3])
    if refilter:
        assert not torch.allclose(a[:, 3:], b[:, 3:])
    else:
        assert torch.equal(a, b)
    assert not torch.allclose(a[:, 3:], c[:, 3:])  # y drives the rolled-forward frames


def test_context_terms_use_the_context_and_the_population_marginal():
    torch.manual_seed(0)
    net = LatentFilter("acc", **TINY)
    batch = pair_batch()
    t = net.context_terms(batch, sample=False)
    m, v = net.context_posterior(batch["context_obs"], batch["context_actions"])
    pm, pv = net.population_marginal(4, torch.device("cpu"))
    kl = 0.5 * (v / pv - 1 - torch.log(v / pv) + (m - pm) ** 2 / pv).sum(-1).mean()
    assert float(t["kl_y"].detach()) == pytest.approx(float(kl.detach()), rel=1e-5)
    # the rolled-forward frames carry no KL_z: only the initial ones do
    out = t["out"]
    assert torch.equal(out["z_mean"][:, 3:], out["zp_mean"][:, 3:])
    other = {**batch, "context_obs": torch.rand_like(batch["context_obs"])}
    assert float(net.context_terms(other, sample=False)["kl_y"].detach()) != float(t["kl_y"].detach())
    for key in ("nll", "kl_z", "kl_y", "entropy"):
        assert t[key].dtype == torch.float32 and torch.isfinite(t[key])


def test_module_trains_on_pairs_and_refuses_batches_without_a_context(tmp_path):
    torch.manual_seed(0)
    module = LatentFilterModule(LatentFilter("acc", **TINY), optimizer={"name": "Adam", "lr": 1e-2},
                                     context={"source": "trial", "initial_frames": 2})
    assert module.hparams["context"] == {"source": "trial", "touches": 1, "initial_frames": 2, "refilter": False,
                                        "invariance": 0.0, "physical": 0.0}
    batch = pair_batch()
    opt = module.configure_optimizers()
    first = None
    for _ in range(6):
        loss = module._terms(batch)["nll"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        first = float(loss) if first is None else first
    assert float(loss) < first
    with pytest.raises(ValueError, match="context_obs"):
        module._terms({k: batch[k] for k in ("obs", "actions", "object_id")})
    with pytest.raises(ValueError, match="context.source"):
        LatentFilterModule(LatentFilter("acc", **TINY), context={"source": "object"})


def test_a_checkpoint_with_the_removed_filter_weight_loads_at_its_off_value():
    """filter_weight (the target window's filtering ELBO added to the context objective) was
    measured and removed: a saved context config holding it at 0 loads, any other value is
    refused, naming it."""
    from embodied_tactile.model.module import check_context

    assert "filter_weight" not in check_context({"source": "trial", "filter_weight": 0.0})
    with pytest.raises(ValueError, match="filter_weight=1.0.*measured, rejected and removed"):
        check_context({"source": "trial", "filter_weight": 1.0})


def test_y_filter_can_start_at_the_population_marginal():
    """y_start=population: before any evidence q(y) is the prior of an object never seen
    (the population marginal, learned), the start that touch_prior reports and the one
    the context KL measures from; gradients reach the marginal's parameters."""
    torch.manual_seed(0)
    net = LatentFilter("acc", y_start="population", **TINY)
    with torch.no_grad():
        net.prior.pop_mean.add_(torch.linspace(-1, 1, net.n_y))
    pm, pv = net.population_marginal(1, torch.device("cpu"))
    state = net.initial_state(3, torch.device("cpu"))
    assert torch.allclose(state["y_pm"] / state["y_prec"], pm.expand(3, -1))
    assert torch.allclose(1 / state["y_prec"], pv.expand(3, -1))
    tm, tv = net.touch_prior()
    assert torch.allclose(tm, pm[0]) and torch.allclose(tv, pv[0] + net.y_posterior.min_var)
    batch = pair_batch()
    with torch.no_grad():  # no evidence at all: the posterior is the start
        net.y_posterior.head.bias[net.n_y:].fill_(-30.0)
        net.y_posterior.head.weight[net.n_y:].zero_()
    t = net.context_terms(batch, sample=False)
    assert float(t["kl_y"]) < 1e-2 * net.n_y
    m, _ = net.context_posterior(batch["context_obs"], batch["context_actions"])
    m.sum().backward()
    assert net.prior.pop_mean.grad is not None and net.prior.pop_mean.grad.abs().sum() > 0
    fixed = LatentFilter("acc", **TINY).initial_state(3, torch.device("cpu"))
    assert torch.equal(fixed["y_pm"], torch.zeros_like(fixed["y_pm"]))
    with pytest.raises(ValueError, match="y_start"):
        LatentFilter("acc", y_start="object", **TINY)
    with pytest.raises(ValueError, match="needs y_update='evidence'"):
        LatentFilter("acc", y_start="population", y_update="direct", **TINY)


def test_a_checkpoint_with_the_removed_random_length_loads_at_its_off_value():
    """random_length was measured and removed: a saved context config holding it at False
    loads; True is refused with a message that names it."""
    from embodied_tactile.model.module import check_context

    assert check_context({"source": "trial", "random_length": False}) == {"source": "trial", "touches": 1,
                                                                          "initial_frames": 3, "refilter": False,
                                                                          "invariance": 0.0, "physical": 0.0}
    with pytest.raises(ValueError, match="random_length=True.*measured, rejected and removed"):
        check_context({"source": "trial", "random_length": True})


# ------------------------------------------------------------------ K touches
def test_more_touches_give_a_tighter_posterior():
    torch.manual_seed(0)
    prior_m, prior_v = torch.zeros(3, 5), torch.full((3, 5), 2.0)
    means = torch.randn(4, 3, 5)
    var = 0.5 + torch.rand(4, 3, 5)
    vk = [combine_touches(means[:k], var[:k], prior_m, prior_v)[1] for k in (1, 2, 4)]
    assert torch.allclose(vk[0], var[0])  # one touch: its own posterior
    assert (vk[1] < vk[0]).all() and (vk[2] < vk[1]).all()
    # the product of Gaussian evidence, prior counted once: identical touches add precision
    same_m, same_v = combine_touches(means[:1].expand(2, -1, -1), var[:1].expand(2, -1, -1), prior_m, prior_v)
    assert torch.allclose(1 / same_v, 2 / var[0] - 1 / prior_v)
    # a touch wider than the prior adds no evidence
    # the evidence update's start: a touch without evidence adds none
    net = LatentFilter("acc", **TINY)
    start_m, start_v = net.touch_prior()
    none_m, none_v = combine_touches(start_m.expand(2, 3, -1), start_v.expand(2, 3, -1), start_m, start_v)
    assert torch.allclose(none_v, start_v.expand(3, -1)) and torch.allclose(none_m, start_m.expand(3, -1))
    wide_m, wide_v = combine_touches(torch.stack([means[0], means[1]]),
                                     torch.stack([var[0], torch.full((3, 5), 3.0)]), prior_m, prior_v)
    assert torch.allclose(wide_v, var[0]) and torch.allclose(wide_m, means[0], atol=1e-6)


# ------------------------------------------------------------------ the swap test
@pytest.mark.slow  # trains a Latent Filter 60 steps
def test_swapping_y_between_objects_raises_the_target_error_of_a_trained_model():
    """Two synthetic 'objects' whose frames start alike and drift with the action at
    object-specific rates: after 60 steps on context / target pairs (one seed; the KL at
    weight 0.01, the warm-up's start), y from the other object predicts the target worse
    than its own."""
    torch.manual_seed(0)
    T, B = 6, 4
    rate = torch.tensor([0.1, -0.1]).repeat(B // 2)  # object 0 and 1 alternate

    def frames(start):
        level = start[:, None] + rate[:, None] * torch.arange(T)[None]
        return (0.5 + level).clamp(0, 1)[:, :, None, None, None].expand(B, T, 1, 28, 28).contiguous()

    actions = torch.ones(B, T, 6)
    net = LatentFilter("acc", n_z=4, n_y=4, y_update="direct", **TINY)
    opt = torch.optim.Adam(net.parameters(), lr=2e-2)
    for _ in range(60):
        batch = {"obs": frames(0.3 * (torch.rand(B) - 0.5)), "actions": actions,
                 "context_obs": frames(0.3 * (torch.rand(B) - 0.5)), "context_actions": actions}
        t = net.context_terms(batch, initial_frames=1)
        loss = t["nll"] + 0.01 * (t["kl_z"] + t["kl_y"])
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    with torch.no_grad():
        target = frames(torch.zeros(B))
        y, _ = net.context_posterior(frames(torch.zeros(B)), actions)
        own = net.rollout(target, actions, y, 1, sample=False)["recon"]
        swapped = net.rollout(target, actions, y.roll(1, 0), 1, sample=False)["recon"]
    err_own = float(((own - target)[:, 1:] ** 2).mean())
    err_swap = float(((swapped - target)[:, 1:] ** 2).mean())
    assert err_swap > 2 * err_own


# ------------------------------------------------------------------ the config
@pytest.mark.slow
def test_recipe_context_sets_the_pairing_and_the_rungs(tmp_path):
    """recipe=context (A5, the population scene's default): the DataModule's pairing follows
    model.context.source, the module gets the rung's settings, y starts at the population
    marginal; recipe=filter (A0) has no context anywhere; the paper's scene has none either."""
    from hydra.utils import instantiate

    from tests.unit.test_configs import _compose

    cfg = _compose(["experiment=population"], tmp_path)
    assert cfg.data.context == "trial" and cfg.model.net.obs_dropout == 0.0
    module = instantiate(cfg.model)
    assert module.context == {"source": "trial", "touches": 1, "initial_frames": 3, "refilter": False,
                              "invariance": 0.0, "physical": 0.0}
    assert cfg.data.context_touches == 1
    assert module.model.y_start == "population"
    a1 = _compose(["experiment=population", "model.net.y_start=fixed", "model.context.source=window"], tmp_path)
    assert a1.data.context == "window" and instantiate(a1.data).context == "window"
    assert instantiate(a1.model).model.y_start == "fixed"
    a3 = _compose(["experiment=population", "model.context.refilter=true"], tmp_path)
    assert instantiate(a3.model).context["refilter"] is True
    for a0 in (_compose(["experiment=population", "recipe=filter"], tmp_path), _compose([], tmp_path)):
        assert a0.data.context is None and instantiate(a0.model).context is None
