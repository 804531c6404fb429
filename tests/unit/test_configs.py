"""Every option of every config group composes and instantiates; the ablation grid has 24 jobs."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate
from omegaconf import OmegaConf, open_dict

from conftest import REPO

CONFIGS = REPO / "configs"
GROUPS = ["data", "modality", "skin", "primitive", "model", "annealing", "recipe", "trainer", "logger", "callbacks", "experiment", "debug", "combo"]


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONFIGS / group).glob("*.yaml"))


def _compose(overrides: list[str], tmp_path: Path):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(
            config_name="train",
            overrides=[*overrides, f"paths.log_dir={tmp_path}/logs", f"paths.data_dir={tmp_path}/data"],
            return_hydra_config=True,
        )
    # ${hydra:runtime.output_dir} is only set inside a running app: give it a value here.
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(tmp_path / "run")
    from hydra.core.hydra_config import HydraConfig

    HydraConfig.instance().set_config(cfg)
    return cfg


def _compose_job(overrides: list[str], tmp_path: Path):
    """The job config (no hydra node), with ${hydra:...} resolvable."""
    cfg = _compose(overrides, tmp_path)
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg


@pytest.mark.slow
@pytest.mark.parametrize("group,option", [(g, o) for g in GROUPS for o in options(g)])
def test_every_option_composes_and_instantiates(group, option, tmp_path):
    extra = {("data", "recorded"): ["data.raw_files=[x.h5]"],
             ("data", "pendulum"): ["experiment=pendulum"]}.get((group, option), [])  # the pendulum scene's entry
    cfg = _compose_job([f"{group}={option}", *extra], tmp_path)
    OmegaConf.resolve(cfg)
    dm = instantiate(cfg.data)
    assert dm.channels == list(cfg.modality.channels)
    model = instantiate(cfg.model)
    assert sum(p.numel() for p in model.parameters()) > 0
    for c in (cfg.get("callbacks") or {}).values():
        instantiate(c)
    for c in (cfg.get("logger") or {}).values():
        instantiate(c)
    if group != "trainer" or option == "cpu":  # gpu/ddp need their hardware to build a Trainer
        instantiate(cfg.trainer)
    else:
        assert cfg.trainer._target_ == "lightning.pytorch.Trainer"


def test_modality_sizes_flow_by_interpolation(tmp_path):
    cfg = _compose_job(["modality=fsr_tb"], tmp_path)
    assert list(cfg.data.channels) == ["fsr_t", "fsr_b"]
    assert cfg.model.net.modality.name == "fsr_tb"


def test_wandb_is_offline_by_default(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_OFFLINE", raising=False)
    cfg = _compose_job(["logger=wandb"], tmp_path)
    assert cfg.logger.wandb.offline is True


def test_paper_experiment_settings(tmp_path):
    cfg = _compose_job(["experiment=paper"], tmp_path)
    assert cfg.model.optimizer.lr == pytest.approx(1e-5)
    assert cfg.data.batch_size == 48 and cfg.trainer.max_epochs == 500
    assert cfg.annealing.name == "dvbf"


@pytest.mark.slow
def test_the_default_run_is_the_typed_defaults(tmp_path):
    """``python train.py`` trains at the typed options' defaults (no experiment sets them), and
    the paper's settings override them: actions null there stays all 16 sets."""
    from embodied_tactile.data.prepare import Scene
    from embodied_tactile.model.options import ModuleOptions
    from embodied_tactile.options.data import LoaderOptions, SceneOptions

    default, paper = _compose_job([], tmp_path), _compose_job(["experiment=paper"], tmp_path)
    loader, scene = LoaderOptions(), SceneOptions()
    for key in ("batch_size", "train_window", "windows_per_trial", "windows_per_epoch", "num_workers"):
        assert default.data[key] == getattr(loader, key), key
    assert default.data.actions is None and scene.actions is None  # all 16 parameter sets
    assert (default.data.windows_per_trial, default.data.windows_per_epoch) == (None, 480)
    assert default.model.weight_average == ModuleOptions().weight_average == 0.99
    assert default.trainer.max_epochs == 32 and "experiment" not in OmegaConf.to_container(default)
    assert paper.data.actions is None and paper.model.weight_average is None
    assert paper.data.train_window is None and paper.data.windows_per_trial == 1 and paper.data.windows_per_epoch is None
    assert Scene.from_config(OmegaConf.to_container(paper.data, resolve=True)).actions is None
    assert Scene.from_config(OmegaConf.to_container(default.data, resolve=True)).actions is None


@pytest.mark.slow
def test_ablation_sweep_composes_all_24_jobs(tmp_path):
    """What `python train.py -m sweep=ablation trainer.fast_dev_run=true` launches: 8 modality x
    skin combos x 3 primitives = 24 jobs, each composing its scene and instantiating its data
    module, model and trainer (a config that several jobs share is instantiated once)."""
    from hydra.core.hydra_config import HydraConfig

    params = _compose(["sweep=ablation"], tmp_path).hydra.sweeper.params
    combos, prims = params.combo.split(","), params.primitive.split(",")
    assert len(combos) == 8 and len(prims) == 3
    GlobalHydra.instance().clear()
    built: dict[str, object] = {}

    def build(node, **kw):
        key = OmegaConf.to_yaml(node)
        if key not in built:
            built[key] = instantiate(node, **kw)
        return built[key]

    seen = set()
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        for combo in combos:
            for prim in prims:
                cfg = compose(config_name="train", overrides=[f"combo={combo}", f"primitive={prim}", "trainer.fast_dev_run=true",
                                                              f"paths.data_dir={tmp_path}"], return_hydra_config=True)
                with open_dict(cfg):
                    cfg.hydra.runtime.output_dir = str(tmp_path / f"{combo}_{prim}")
                HydraConfig.instance().set_config(cfg)
                with open_dict(cfg):
                    del cfg["hydra"]
                OmegaConf.resolve(cfg)
                mod, skin = combo.rsplit("_", 1)
                assert cfg.modality.name == mod and cfg.skin.name == skin and cfg.primitive.name == prim
                dm = build(cfg.data)
                assert dm.primitive == prim and dm.skin == skin
                assert build(cfg.model).hparams.net["modality"]["name"] == mod
                assert build(cfg.trainer, logger=False, enable_checkpointing=False).fast_dev_run
                seen.add((mod, skin, prim))
    assert len(seen) == 24


def _sweep_jobs(name: str, tmp_path) -> list[dict]:
    """The jobs a sweep file expands to (Hydra's basic sweeper: the product of its params)."""
    import itertools

    params = _compose([f"sweep={name}"], tmp_path).hydra.sweeper.params
    keys = list(params)
    return [dict(zip(keys, vals)) for vals in itertools.product(*(str(params[k]).split(",") for k in keys))]


@pytest.mark.slow  # composes each scene of the study and study_min sweeps (~40 Hydra compositions)
def test_study_sweeps_compose_to_the_protocols_jobs(tmp_path):
    composed: dict[tuple, tuple] = {}  # the jobs differ by seed beyond their scene: each scene composed once

    def cell(job: dict) -> tuple:
        scene = [f"combo={job['combo']}"] + ([f"primitive={job['primitive']}"] if "primitive" in job else [])
        if tuple(scene) not in composed:
            c = _compose_job(scene, tmp_path)
            composed[tuple(scene)] = (c.modality.name, c.skin.name, c.primitive.name)
        return composed[tuple(scene)]

    cells = lambda jobs: {cell(j) for j in jobs}  # noqa: E731
    study = _sweep_jobs("study", tmp_path)
    assert len(study) == 24 * 3 and {j["seed"] for j in study} == {"0", "1", "2"}
    full = cells(study)
    assert len(full) == 24  # 8 modality x skin combinations x 3 primitives, each with every seed
    assert {(m, s) for m, s, _ in full} == {("acc", "soft"), ("fsr_t", "soft"), ("fsr_b", "soft"), ("fsr_tb", "soft"),
                                            ("multi_e", "soft"), ("multi_l", "soft"), ("fsr_tb", "hard"),
                                            ("multi_l", "hard")}
    small = _sweep_jobs("study_min", tmp_path)
    assert len(small) == 10 * 3
    minimum = cells(small)
    assert minimum == {c for c in full if c[2] == "pressing"} | {("multi_l", "soft", p) for p in ("precession", "sliding")}
    # the study runs at the default scene and budget (all 16 parameter sets, 960 steps) with
    # the dataset's noise seeded per job; the population at its own budget
    study_job, default = _compose_job(["sweep=study", "seed=2"], tmp_path), _compose_job([], tmp_path)
    assert study_job.trainer.max_epochs == default.trainer.max_epochs == 32
    assert study_job.data.actions is None and study_job.data.sim_seed == 2 and study_job.data.keep_raw is False
    assert _compose_job(["experiment=population"], tmp_path).trainer.max_epochs == 16


@pytest.mark.slow
def test_the_class_built_with_no_options_is_the_configured_filter_recipe(tmp_path):
    """One source of defaults: recipe=filter's network is LatentFilter(modality) with nothing
    else named (but the scene's code-table size), the composed config holds every field of
    the typed options with the dataclass's values, a command-line override still reaches the
    network, and an unknown option is refused by name, in Hydra and in the class."""
    from dataclasses import asdict

    from embodied_tactile.model.latent_filter import LatentFilter
    from embodied_tactile.model.options import LatentFilterOptions, OptimizerOptions

    cfg = _compose(["recipe=filter"], tmp_path)
    configured = instantiate(cfg.model.net)
    bare = LatentFilter(OmegaConf.to_container(cfg.modality, resolve=True), n_objects=cfg.model.net.n_objects)
    assert configured.config() == bare.config()
    assert configured.config()["prior"]["learn_embedding"] is False and configured.config()["obs_sigma"] == 0.1
    changed = instantiate(_compose(["model.net.obs_dropout=0.25", "model.net.prior.learn_sigma=true"], tmp_path).model.net)
    assert changed.obs_dropout == 0.25 and changed.config()["prior"]["learn_sigma"] is True
    composed = OmegaConf.to_container(_compose(["recipe=filter"], tmp_path).model.net, resolve=True)
    options = asdict(LatentFilterOptions())
    assert {k: composed[k] for k in options if k != "n_objects"} == {k: v for k, v in options.items() if k != "n_objects"}
    assert _compose([], tmp_path).model.optimizer.lr == OptimizerOptions.lr
    with pytest.raises(ValueError, match="unknown Latent Filter prior options \\['no_such_option'\\]"):
        LatentFilter("acc", prior={"no_such_option": 1})
    with pytest.raises(Exception, match="no_such_option"):
        _compose(["model.net.prior.no_such_option=1"], tmp_path)


@pytest.mark.slow
def test_recipes_name_the_objective(tmp_path):
    """recipe=paper (the default of the paper's scene) is the paper's model: the ELBO (kl_y
    weight 1) with the label-conditioned prior and learned object codes, y direct, no dropout;
    filter is the model class's defaults (the plain ELBO without labels, observation dropout and
    evidence y); the population scene's default is the context objective without labels, y's
    filter starting at the population marginal (test_context.py); elbo drops the two switches, recognition
    adds the labels with fixed codes and weights kl_y 100; the paper's experiment is the paper's
    recipe under its DVBF annealing; a command-line y weight still wins."""
    from embodied_tactile.model.latent_filter import LatentFilter

    filter_ = instantiate(_compose(["recipe=filter"], tmp_path).model.net)
    assert filter_.obs_dropout == 0.5 and filter_.config()["y_update"] == "evidence"
    assert filter_.config()["y_evidence_max"] == 1 and filter_.config()["prior"]["labels"] is False
    assert LatentFilter("multi_l").config()["prior"]["labels"] is False
    population = _compose(["experiment=population"], tmp_path)
    assert instantiate(population.model.net).config()["prior"] == filter_.config()["prior"] | {
        "population_weight": population.model.net.prior.population_weight}
    assert population.model.context.source == "trial" and population.model.net.y_start == "population"
    assert population.model.net.obs_dropout == 0.0 and population.annealing.schedule.y_weight == 1.0
    elbo = instantiate(_compose(["recipe=elbo"], tmp_path).model.net).config()
    assert elbo["obs_dropout"] == 0.0 and elbo["y_update"] == "direct" and elbo["prior"]["labels"] is False
    default = _compose([], tmp_path)
    assert default.annealing.schedule.y_weight == 1.0
    paper_net = {**elbo, "prior": {**elbo["prior"], "labels": True, "learn_embedding": True}}
    assert instantiate(default.model.net).config() == paper_net
    assert default.model.net.prior.labels is True and default.model.net.prior.learn_embedding is True
    recognition = _compose(["recipe=recognition"], tmp_path)
    assert recognition.annealing.schedule.y_weight == 100.0 and recognition.model.net.prior.labels is True
    assert instantiate(recognition.model.net).config() == {**elbo, "prior": {**elbo["prior"], "labels": True}}
    paper = _compose(["experiment=paper"], tmp_path)
    assert "y_weight" not in paper.annealing.schedule and paper.annealing.name == "dvbf"
    assert instantiate(paper.model.net).config() == paper_net
    assert _compose(["recipe=elbo", "annealing.schedule.y_weight=3"], tmp_path).annealing.schedule.y_weight == 3
