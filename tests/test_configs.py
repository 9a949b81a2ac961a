"""Every config group option and experiment composes and instantiates (composed into tmp_path)."""

from __future__ import annotations

import inspect
from pathlib import Path

import lightning.pytorch as pl
import pytest
from hydra import compose, initialize
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, open_dict

from image2sphere.training import PoseEstimationModule, register_resolvers

CONF = Path(__file__).resolve().parents[1] / "conf"


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def compose_cfg(tmp_path: Path, overrides: list[str] = ()) -> DictConfig:
    """The real ``conf/train.yaml`` with ``overrides``, every path moved into ``tmp_path``."""
    register_resolvers()
    GlobalHydra.instance().clear()
    with initialize(version_base="1.3", config_path="../conf"):
        cfg = compose(config_name="train", return_hydra_config=True, overrides=list(overrides))
    with open_dict(cfg):
        cfg.paths.root_dir = str(tmp_path)
        cfg.paths.data_dir = str(tmp_path / "data")
        cfg.paths.log_dir = str(tmp_path / "logs")
        cfg.paths.output_dir = str(tmp_path / "out")
        cfg.hydra.runtime.output_dir = str(tmp_path / "out")
        cfg.hydra.job.num = 0
    HydraConfig().set_config(cfg)
    return cfg


def test_defaults_compose_to_the_embedded_run(tmp_path):
    cfg = compose_cfg(tmp_path)
    assert cfg.task_name == "train" and cfg.seed == 0 and cfg.ckpt_path is None
    assert cfg.model.net._target_ == "image2sphere.nn.I2S" and cfg.model.net.encoder.depth == 18
    assert cfg.model.net.lmax == cfg.lmax == 6
    assert cfg.model.train_grid_level == 3 and cfg.model.eval_grid_level == 5
    assert cfg.dataset.render is not None and cfg.logger.wandb.offline is True
    assert cfg.callbacks.model_checkpoint.save_last is True
    # the quick built-in run brings its own schedule ...
    assert cfg.model.optimizer._target_ == "torch.optim.Adam" and cfg.trainer.max_epochs < 40
    # ... every other dataset gets the paper's: SGD, Nesterov 0.9, lr 1e-3, x0.1 every 15 of 40 epochs
    paper = compose_cfg(tmp_path, ["dataset=symsol"])
    opt = paper.model.optimizer
    assert opt._target_ == "torch.optim.SGD" and opt._partial_ and opt.nesterov and opt.momentum == 0.9
    assert opt.lr == 0.001 and paper.trainer.max_epochs == 40
    assert paper.model.scheduler._partial_ and paper.model.scheduler.step_size == 15
    assert paper.model.scheduler.gamma == 0.1
    # a command-line choice wins over the dataset's
    assert compose_cfg(tmp_path, ["optimizer=sgd"]).model.optimizer._target_ == "torch.optim.SGD"
    assert "multiruns" in cfg.hydra.sweep.dir and "runs" in cfg.hydra.run.dir


@pytest.mark.parametrize("model", options("model"))
def test_every_model_variant_instantiates_and_runs(tmp_path, model):
    import torch

    cfg = compose_cfg(tmp_path, [f"model={model}", "lmax=2", "dataset.image_size=64"])
    module = instantiate(cfg.model)
    assert isinstance(module, PoseEstimationModule) and module.lmax == 2
    out = module(torch.randn(2, 3, 64, 64))
    assert out.shape == (2, 35)
    expected = {
        "i2s_harmonic_projector": ("projector", "harmonic"),
        "i2s_spatial_filter": ("filter", "spatial"),
        "i2s_no_so3_conv": ("n_so3_conv", 0),
        "i2s_two_so3_conv": ("n_so3_conv", 2),
    }
    if model in expected:
        key, value = expected[model]
        assert cfg.model.net[key] == value
        assert len(module.net.so3_layers) == 2 * cfg.model.net.n_so3_conv


@pytest.mark.parametrize("encoder", options("encoder"))
def test_every_encoder_instantiates(tmp_path, encoder):
    cfg = compose_cfg(tmp_path, [f"encoder={encoder}", "lmax=2"])
    net = instantiate(cfg.model.net)
    assert net.encoder.depth == int(encoder.removeprefix("resnet"))
    assert cfg.model.net.encoder.weights is None


@pytest.mark.parametrize("dataset", options("dataset"))
def test_every_dataset_instantiates(tmp_path, dataset):
    cfg = compose_cfg(tmp_path, [f"dataset={dataset}"])
    dm = instantiate(cfg.dataset)
    assert isinstance(dm, pl.LightningDataModule)
    assert Path(dm.root).is_relative_to(tmp_path / "data")
    if dataset == "symsol":  # nothing downloaded here: a clear message, no crash deeper down
        with pytest.raises(FileNotFoundError, match="symsol_dataset.zip"):
            dm.prepare_data()


@pytest.mark.parametrize("trainer", options("trainer"))
def test_every_trainer_config_is_valid(tmp_path, trainer):
    cfg = compose_cfg(tmp_path, [f"trainer={trainer}"])
    accepted = set(inspect.signature(pl.Trainer.__init__).parameters)
    unknown = set(cfg.trainer) - accepted - {"_target_"}
    assert not unknown, f"trainer/{trainer}.yaml sets unknown Trainer arguments {unknown}"
    if cfg.trainer.accelerator in ("cpu", "auto"):
        trainer_obj = instantiate(cfg.trainer, logger=False, enable_checkpointing=False)
        assert trainer_obj.max_epochs == cfg.trainer.max_epochs


@pytest.mark.parametrize("logger", options("logger"))
def test_every_logger_instantiates(tmp_path, logger):
    cfg = compose_cfg(tmp_path, [f"logger={logger}"])
    loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values()]
    assert (len(loggers) == 0) == (logger == "none")
    for lg in loggers:
        assert isinstance(lg, pl.loggers.Logger)
        assert str(tmp_path / "out") in str(lg.save_dir)


@pytest.mark.parametrize("callbacks", options("callbacks"))
def test_every_callback_set_instantiates(tmp_path, callbacks):
    cfg = compose_cfg(tmp_path, [f"callbacks={callbacks}"])
    made = [instantiate(c) for c in (cfg.get("callbacks") or {}).values()]
    assert all(isinstance(c, pl.Callback) for c in made)
    if callbacks == "default":
        ckpt = next(c for c in made if isinstance(c, pl.callbacks.ModelCheckpoint))
        assert ckpt.save_last and Path(ckpt.dirpath) == tmp_path / "out" / "checkpoints"


@pytest.mark.parametrize("optimizer", options("optimizer"))
def test_every_optimizer_builds_with_the_scheduler(tmp_path, optimizer):
    import torch

    cfg = compose_cfg(tmp_path, [f"optimizer={optimizer}"])
    opt = instantiate(cfg.model.optimizer)(params=[torch.nn.Parameter(torch.zeros(3))])
    assert type(opt).__name__.lower() == optimizer
    sched = instantiate(cfg.model.scheduler)(optimizer=opt)
    assert isinstance(sched, torch.optim.lr_scheduler.StepLR)


@pytest.mark.parametrize("debug", options("debug"))
def test_every_debug_preset_composes(tmp_path, debug):
    cfg = compose_cfg(tmp_path, [f"debug={debug}"])
    assert cfg.task_name == "debug" and not cfg.get("logger")
    instantiate(cfg.trainer, logger=False, enable_checkpointing=False)


@pytest.mark.parametrize("search", options("hparams_search"))
def test_every_hparams_search_composes(tmp_path, search):
    cfg = compose_cfg(tmp_path, [f"hparams_search={search}"])
    params = cfg.hydra.sweeper.params
    assert cfg.hydra.mode.name == "MULTIRUN" and params
    for key, values in params.items():
        for value in str(values).split(","):  # every swept value composes
            compose_cfg(tmp_path, [f"hparams_search={search}", f"{key}={value}"])


@pytest.mark.parametrize("experiment", options("experiment"))
def test_every_experiment_composes_and_instantiates(tmp_path, experiment):
    cfg = compose_cfg(tmp_path, [f"experiment={experiment}"])
    assert cfg.task_name == experiment
    assert cfg.dataset._target_ == "image2sphere.data.SymsolDataModule"
    instantiate(cfg.dataset)
    net = instantiate(cfg.model.net)
    assert net.encoder.depth == 50  # the paper's backbone for SYMSOL


def test_invalid_value_is_reported_with_its_key(tmp_path):
    cfg = compose_cfg(tmp_path, ["train_grid_level=12"])
    with pytest.raises(Exception, match="model.train_grid_level"):
        instantiate(cfg.model)
    cfg = compose_cfg(tmp_path, ["dataset.shapes=[cube,dodecahedron]"])
    with pytest.raises(Exception, match="dataset.shapes"):
        instantiate(cfg.dataset)
