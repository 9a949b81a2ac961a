"""Every config group option and experiment composes and instantiates (composed into tmp_path)."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import lightning.pytorch as pl
import pytest
from hydra import compose, initialize
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from image2sphere.training import PoseEstimationModule, register_resolvers

CONF = Path(__file__).resolve().parents[1] / "conf"


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.fixture
def fixture_data(published_fixtures) -> Path:
    """Tiny copies of every dataset in its published layout (the session's, see conftest)."""
    return published_fixtures


def compose_cfg(tmp_path: Path, overrides: list[str] = (), data_dir: Path | None = None) -> DictConfig:
    """The real ``conf/train.yaml`` with ``overrides``, every path moved into ``tmp_path`` (the data
    to ``data_dir`` when given)."""
    register_resolvers()
    GlobalHydra.instance().clear()
    with initialize(version_base="1.3", config_path="../conf"):
        cfg = compose(config_name="train", return_hydra_config=True, overrides=list(overrides))
    with open_dict(cfg):
        cfg.paths.root_dir = str(tmp_path)
        cfg.paths.data_dir = str(data_dir or tmp_path / "data")
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
    paper = compose_cfg(tmp_path, ["dataset=symsol1"])
    opt = paper.model.optimizer
    assert opt._target_ == "torch.optim.SGD" and opt._partial_ and opt.nesterov and opt.momentum == 0.9
    assert opt.lr == 0.001 and paper.trainer.max_epochs == 40
    assert paper.model.scheduler._partial_ and paper.model.scheduler.step_size == 15
    assert paper.model.scheduler.gamma == 0.1
    # a command-line choice wins over the dataset's
    assert compose_cfg(tmp_path, ["optimizer=sgd"]).model.optimizer._target_ == "torch.optim.SGD"
    assert "multiruns" in cfg.hydra.sweep.dir and "runs" in cfg.hydra.run.dir


# what `dataset=X` alone resolves to: (protocol, encoder depth, optimizer, lr, epochs, step_size, gamma,
# image size, batch size). The paper: SGD, 40 epochs, x0.1 every 15; ResNet-101 for PASCAL3D+ only.
RESOLVES_TO = {
    "symsol_rendered": ("symsol_rendered", 18, "Adam", 0.001, 5, 3, 0.1, 96, 32),
    "symsol1": ("symsol1", 50, "SGD", 0.001, 40, 15, 0.1, 224, 64),
    "symsol2": ("symsol2", 50, "SGD", 0.001, 40, 15, 0.1, 224, 64),
    "modelnet10": ("modelnet10", 50, "SGD", 0.001, 40, 15, 0.1, 224, 64),
    "modelnet10_limited": ("modelnet10_limited", 50, "SGD", 0.001, 40, 15, 0.1, 224, 64),
    "pascal3d": ("pascal3d", 101, "SGD", 0.001, 40, 15, 0.1, 224, 64),
    "folder": ("folder", 50, "SGD", 0.001, 40, 15, 0.1, 224, 64),
}
PROTOCOL_KEYS = ("encoder", "model.optimizer", "trainer.max_epochs", "model.scheduler")


def resolved(cfg: DictConfig) -> tuple:
    opt, sched = cfg.model.optimizer, cfg.model.scheduler
    return (
        cfg.hydra.runtime.choices.protocol,
        cfg.model.net.encoder.depth,
        opt._target_.rsplit(".", 1)[-1],
        opt.lr,
        cfg.trainer.max_epochs,
        sched.step_size,
        sched.gamma,
        cfg.dataset.image_size,
        cfg.dataset.batch_size,
    )


def test_every_dataset_has_its_pinned_resolution():
    assert set(options("dataset")) == set(RESOLVES_TO)
    assert set(options("protocol")) == set(RESOLVES_TO) | {"paper"}


@pytest.mark.parametrize("dataset", sorted(RESOLVES_TO))
def test_dataset_alone_resolves_to_its_protocol(tmp_path, dataset):
    """``dataset=X`` alone: the data plus the protocol of the same name, and nothing else changes."""
    cfg = compose_cfg(tmp_path, [f"dataset={dataset}"])
    assert resolved(cfg) == RESOLVES_TO[dataset]
    if cfg.model.optimizer._target_ == "torch.optim.SGD":  # the paper's SGD
        assert (cfg.model.optimizer.momentum, cfg.model.optimizer.nesterov) == (0.9, True)
    # the protocol file sets its four settings only: with any other protocol, every other key is the same
    a = OmegaConf.to_container(cfg, resolve=False)
    b = OmegaConf.to_container(compose_cfg(tmp_path, [f"dataset={dataset}", "protocol=paper"]), resolve=False)
    for key in ("encoder", "trainer", "model", "hydra"):
        a.pop(key), b.pop(key)
    assert a == b
    # ... and the dataset group's file sets the dataset only: each dataset differs from the built-in
    # default run in `dataset` and the protocol's four settings, nowhere else
    base = OmegaConf.to_container(compose_cfg(tmp_path), resolve=False)
    mine = OmegaConf.to_container(cfg, resolve=False)
    for c in (base, mine):
        c.pop("dataset"), c.pop("encoder"), c.pop("hydra")
        c["trainer"].pop("max_epochs"), c["model"].pop("optimizer"), c["model"].pop("scheduler")
    assert mine == base


@pytest.mark.parametrize(
    "overrides, expected",
    [
        (["dataset=pascal3d", "encoder=resnet50"], {"depth": 50, "opt": "torch.optim.SGD", "epochs": 40}),
        (
            ["dataset=symsol1", "optimizer=adam", "trainer.max_epochs=7"],
            {"depth": 50, "opt": "torch.optim.Adam", "epochs": 7},
        ),
        (["protocol=paper"], {"depth": 50, "opt": "torch.optim.SGD", "epochs": 40}),
        (["dataset=pascal3d", "protocol=symsol_rendered"], {"depth": 18, "opt": "torch.optim.Adam", "epochs": 5}),
        (["experiment=pascal3d", "encoder=resnet18"], {"depth": 18, "opt": "torch.optim.SGD", "epochs": 40}),
    ],
)
def test_command_line_wins_over_the_protocol(tmp_path, overrides, expected):
    cfg = compose_cfg(tmp_path, overrides)
    got = {"depth": cfg.model.net.encoder.depth, "opt": cfg.model.optimizer._target_, "epochs": cfg.trainer.max_epochs}
    assert got == expected
    if expected["opt"] == "torch.optim.Adam":  # one optimizer file, not SGD's keys merged into Adam's
        assert "momentum" not in cfg.model.optimizer and "nesterov" not in cfg.model.optimizer


def test_start_up_log_says_where_each_protocol_setting_came_from(tmp_path):
    from image2sphere.training.run_config import describe_run, protocol_settings

    overrides = ["dataset=pascal3d", "encoder=resnet34", "debug=limit"]
    cfg = compose_cfg(tmp_path, overrides)
    choices = dict(cfg.hydra.runtime.choices)
    alone = protocol_settings(compose_cfg(tmp_path, ["dataset=pascal3d", "protocol=pascal3d"]))
    lines = describe_run(cfg, choices, overrides, alone).splitlines()
    assert lines[0].startswith("This run trains (dataset=pascal3d brings protocol=pascal3d")
    by_name = {line.split()[0]: line for line in lines[1:]}
    assert by_name["encoder"].endswith("resnet34: ResNet-34, random initialisation  [command line]")
    sgd = "sgd: SGD(lr=0.001, momentum=0.9, nesterov=True, weight_decay=0.0, fused=True)"
    assert by_name["optimizer"].endswith(f"{sgd}  [protocol=pascal3d]")
    assert by_name["epochs"].endswith("2  [debug=limit]")  # the debug preset changed the protocol's 40
    assert by_name["scheduler"].endswith("StepLR(step_size=15, gamma=0.1), stepped every epoch  [protocol=pascal3d]")
    assert "Pascal3DDataModule" in by_name["data"] and "224 px, batch 64" in by_name["data"]
    # a resumed run: values only, no sources claimed
    resumed = describe_run(cfg, None, ["ckpt_path=x.ckpt"], None)
    assert "[" not in resumed and "ResNet-34" in resumed


@pytest.mark.parametrize("model", ["i2s", "rotation_flow", "ipdf", "wigner_regression"])
def test_start_up_log_names_a_band_limit_only_for_a_method_that_has_one(tmp_path, model):
    """I2S and the Wigner-D regression read lmax; the flow and IPDF have no band limit (they said "lmax 6"),
    also when the config is a checkpoint's resolved one (a resumed run)."""
    from image2sphere.training.run_config import describe_run

    cfg = compose_cfg(tmp_path, [f"model={model}"])
    (line,) = [line for line in describe_run(cfg).splitlines() if line.split()[0] == "model"]
    resolved = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    (resumed,) = [line for line in describe_run(resolved).splitlines() if line.split()[0] == "model"]
    has = model in ("i2s", "wigner_regression")
    assert ("lmax 6, grid levels 3" in line) == has and ("lmax" in resumed) == has
    assert line.endswith("grid levels 3 (training) and 5 (test)")


def test_docs_resolution_table_is_what_the_configs_compose(tmp_path):
    """docs/configuration.md's table of `dataset=X` alone, row by row, against the composed configs."""
    text = (CONF.parent / "docs" / "configuration.md").read_text()
    rows = re.findall(r"^\| `python -m src\.train( dataset=(\w+))?` \|(.*)\|$", text, re.M)
    assert sorted(r[1] or "symsol_rendered" for r in rows) == sorted(RESOLVES_TO)
    for _, dataset, cells in rows:
        dataset = dataset or "symsol_rendered"
        protocol, encoder, optimizer, epochs, schedule, size, batch = (c.strip() for c in cells.split("|"))
        cfg = compose_cfg(tmp_path, [f"dataset={dataset}"] if dataset != "symsol_rendered" else [])
        opt, sched = cfg.model.optimizer, cfg.model.scheduler
        assert protocol == f"`{cfg.hydra.runtime.choices.protocol}`", dataset
        assert encoder == f"ResNet-{cfg.model.net.encoder.depth}", dataset
        assert optimizer == f"{opt._target_.rsplit('.', 1)[-1]}, lr {opt.lr}", dataset
        assert epochs == str(cfg.trainer.max_epochs), dataset
        assert schedule == f"x{sched.gamma} every {sched.step_size} epochs", dataset
        assert (size, batch) == (f"{cfg.dataset.image_size} px", str(cfg.dataset.batch_size)), dataset


FOURIER_MODELS = {"i2s", "i2s_harmonic_projector", "i2s_spatial_filter", "i2s_harmonic_projector_spatial_filter",
                  "i2s_no_so3_conv", "i2s_two_so3_conv", "i2s_original",
                  "fourier_mlp", "wigner_regression"}  # fmt: skip
POINT_REGRESSORS = {"regression_6d", "regression_9d", "spherical_regression", "bin_delta", "i2s_icosahedral"}


@pytest.mark.parametrize("model", options("model"))
def test_every_model_variant_instantiates_and_runs(tmp_path, model):
    """Every method's network, through the one interface: output -> distribution, and its loss."""
    import torch

    from image2sphere.distributions import PoseDistribution
    from image2sphere.so3 import random_rotations

    cfg = compose_cfg(tmp_path, [f"model={model}", "lmax=2", "dataset.image_size=64"])
    module = instantiate(cfg.model)
    assert isinstance(module, PoseEstimationModule)
    torch.manual_seed(0)
    out = module(torch.randn(2, 3, 64, 64))
    dist = module.net.output_distribution(out)
    assert isinstance(dist, PoseDistribution) and dist.batch_size == 2
    assert dist.has_density == (model not in POINT_REGRESSORS)
    mode = dist.mode(2)
    assert mode.shape == (2, 3, 3)
    torch.testing.assert_close(mode.transpose(-1, -2) @ mode, torch.eye(3).expand(2, 3, 3), atol=1e-4, rtol=0)
    if dist.has_density:  # the grid protocol: a normalised distribution on the grid
        assert torch.isfinite(dist.log_normalizer(2)).all()
        torch.testing.assert_close(dist.log_prob_grid(1).exp().sum(1), torch.ones(2), atol=1e-4, rtol=0)
    loss = module.net.loss(out, random_rotations(2), 2)
    assert loss.shape == (2,) and torch.isfinite(loss).all()
    loss.mean().backward()
    grads = [p.grad for p in module.net.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    if model in FOURIER_MODELS:
        assert module.lmax == 2 and out.shape == (2, 35)
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


def test_model_list_is_every_method():
    assert set(options("model")) == FOURIER_MODELS | POINT_REGRESSORS | {
        "ipdf", "matrix_fisher", "rotation_laplace", "bingham", "von_mises", "viewpoint_bins", "rotation_flow"
    }  # fmt: skip


ORIGINAL_CODE = {
    "projector_normalization": "sqrt",
    "n_subset": 20,
    "subset_in_eval": True,
    "init": "kaiming_uniform",
    "so3_kernel": "tube",
    "activation_resolution": 10,
    "output_init": "random",
    "input_scaling": "unit",
}


def _leaves(tree, prefix: str = "") -> dict:
    """A nested config container as ``{"a.b.0.c": value}``."""
    if isinstance(tree, dict):
        return {k: v for key, sub in tree.items() for k, v in _leaves(sub, f"{prefix}{key}.").items()}
    if isinstance(tree, list):
        return {k: v for i, sub in enumerate(tree) for k, v in _leaves(sub, f"{prefix}{i}.").items()}
    return {prefix[:-1]: tree}


def test_i2s_original_is_i2s_with_the_original_codes_eight_choices(tmp_path):
    """``model=i2s_original`` differs from ``model=i2s`` in exactly the original code's eight
    ``model.net`` keys, and nowhere else but the model group's own choice in hydra's record; its
    network runs on a batch of the built-in data's size."""
    import torch

    from image2sphere.nn import I2S
    from image2sphere.so3 import n_so3_coeffs

    leaves = {}
    for model in ("i2s", "i2s_original"):
        cfg = compose_cfg(tmp_path, [f"model={model}"])
        hydra = _leaves(OmegaConf.to_container(cfg.hydra), "hydra.")
        with open_dict(cfg):
            del cfg.hydra
        leaves[model] = {**_leaves(OmegaConf.to_container(cfg, resolve=True)), **hydra}
    default, original = leaves["i2s"], leaves["i2s_original"]
    differ = {k for k in default.keys() | original.keys() if default.get(k, "<absent>") != original.get(k, "<absent>")}
    assert differ == {f"model.net.{k}" for k in ORIGINAL_CODE} | {
        "hydra.runtime.choices.model", "hydra.overrides.task.0", "hydra.job.override_dirname"
    }  # fmt: skip
    assert {k: original[f"model.net.{k}"] for k in ORIGINAL_CODE} == ORIGINAL_CODE
    assert original["hydra.runtime.choices.model"] == "i2s_original"
    assert default["model.net.init"] == "unit" and default["model.net.input_scaling"] == "imagenet"

    cfg = compose_cfg(tmp_path, ["model=i2s_original"])
    assert cfg.dataset.image_size == 96 and cfg.lmax == 6
    torch.manual_seed(0)
    net = instantiate(cfg.model.net)
    assert isinstance(net, I2S) and net.input_scaling == "unit" and net.s2_conv.init == "kaiming_uniform"
    assert net.projector.normalization == "sqrt" and net.projector.n_subset == 20
    images = torch.randn(2, 3, 96, 96)
    with torch.no_grad():
        out = net.eval()(images)
        again = net(images)  # the original's forward: 20 random points in evaluation too
    assert out.shape == (2, n_so3_coeffs(6)) and torch.isfinite(out).all() and out.abs().max() > 0
    assert not torch.allclose(out, again)


@pytest.mark.parametrize("encoder", options("encoder"))
def test_every_encoder_instantiates(tmp_path, encoder):
    cfg = compose_cfg(tmp_path, [f"encoder={encoder}", "lmax=2"])
    net = instantiate(cfg.model.net)
    if encoder == "torchvision":  # its default model, at the run's image size
        assert net.encoder.name == cfg.encoder.name and net.feature_size == net.encoder.feature_size(
            cfg.dataset.image_size
        )
    else:
        assert net.encoder.depth == int(encoder.removeprefix("resnet"))
    assert cfg.model.net.encoder.weights is None


@pytest.mark.parametrize("dataset", options("dataset"))
def test_every_dataset_instantiates(tmp_path, dataset, fixture_data):
    cfg = compose_cfg(tmp_path, [f"dataset={dataset}"], data_dir=fixture_data)
    dm = instantiate(cfg.dataset)
    assert isinstance(dm, pl.LightningDataModule)
    assert Path(dm.root).is_relative_to(fixture_data)
    if dataset != "symsol_rendered":  # nothing downloaded: a clear message naming the key, no crash deeper down
        empty = compose_cfg(tmp_path, [f"dataset={dataset}"])
        with pytest.raises(Exception, match=r"not found at .*Get it from .*point dataset.root at your copy"):
            instantiate(empty.dataset)


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
        for value in sweep_values(cfg, key, values):  # every swept value (an Optuna range's ends) composes
            compose_cfg(tmp_path, [f"hparams_search={search}", f"{key}={value}"])


def sweep_values(cfg: DictConfig, key: str, values) -> list:
    """The values a sweeper tries for ``key``: a basic sweep's list; for Optuna, the choices or the ends
    of the range, as the Optuna sweeper parses them."""
    if not str(cfg.hydra.sweeper._target_).endswith("OptunaSweeper"):
        return str(values).split(",")
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra_plugins.hydra_optuna_sweeper._impl import create_optuna_distribution_from_override

    dist = create_optuna_distribution_from_override(OverridesParser.create().parse_override(f"{key}={values}"))
    return list(dist.choices) if hasattr(dist, "choices") else [dist.low, dist.high]


def test_optuna_search_optimises_a_metric_the_runs_write(tmp_path):
    cfg = compose_cfg(tmp_path, ["hparams_search=optuna_i2s"])
    assert cfg.optimized_metric == "log_likelihood" and cfg.hydra.sweeper.direction == "maximize"
    assert set(cfg.hydra.sweeper.params) == {
        "model.optimizer.lr", "model.optimizer.weight_decay", "lmax", "model.net.sphere_channels",
        "model.net.so3_channels", "train_grid_level",
    }  # fmt: skip
    assert sweep_values(cfg, "model.optimizer.lr", cfg.hydra.sweeper.params["model.optimizer.lr"]) == [1e-4, 1e-2]
    assert str(cfg.hydra.sweeper.storage).startswith("sqlite:///") and cfg.hydra.sweeper.storage.endswith(
        "/logs/optuna/optuna_i2s.db"
    )


# what each experiment must reproduce (paper section 5 and appendix): dataset module, its key
# settings, the backbone depth, the number of classes
EXPECTED = {
    "symsol1": ("SymsolDataModule", {"shapes": ["tet", "cube", "icosa", "cone", "cyl"], "num_views": None}, 50, 5),
    "symsol1_10k": ("SymsolDataModule", {"shapes": ["tet", "cube", "icosa", "cone", "cyl"], "num_views": 10000}, 50, 5),
    "symsol2_tetX": ("SymsolDataModule", {"shape": "tetX", "shapes": None}, 50, 1),
    "symsol2_cylO": ("SymsolDataModule", {"shape": "cylO", "shapes": None}, 50, 1),
    "symsol2_sphereX": ("SymsolDataModule", {"shape": "sphereX", "shapes": None}, 50, 1),
    "modelnet10": ("ModelNet10DataModule", {"train_split": "train_100V", "test_split": "test_20V"}, 50, 10),
    "modelnet10_limited": ("ModelNet10DataModule", {"train_split": "train_20V", "test_split": "test_20V"}, 50, 10),
    "pascal3d": ("Pascal3DDataModule", {"synthetic_ratio": 3, "image_size": 224}, 101, 12),
}


def test_the_experiment_list_is_the_papers():
    assert set(options("experiment")) == set(EXPECTED)


@pytest.mark.parametrize("experiment", options("experiment"))
def test_every_experiment_composes_and_instantiates(tmp_path, experiment, fixture_data):
    cfg = compose_cfg(tmp_path, [f"experiment={experiment}"], data_dir=fixture_data)
    module, settings, depth, n_classes = EXPECTED[experiment]
    assert cfg.task_name == experiment
    assert cfg.dataset._target_ == f"image2sphere.data.{module}"
    for key, value in settings.items():
        assert cfg.dataset[key] == value, key
    # the paper's schedule: SGD with Nesterov momentum 0.9, lr 1e-3, x0.1 every 15 epochs, 40 epochs,
    # batch 64, training grid level 3, evaluation grid level 5, lmax 6, no class-label input
    opt, sched = cfg.model.optimizer, cfg.model.scheduler
    assert (opt._target_, opt.lr, opt.momentum, opt.nesterov) == ("torch.optim.SGD", 0.001, 0.9, True)
    assert (sched.step_size, sched.gamma, cfg.trainer.max_epochs) == (15, 0.1, 40)
    assert (cfg.dataset.batch_size, cfg.dataset.image_size) == (64, 224)
    assert (cfg.model.train_grid_level, cfg.model.eval_grid_level, cfg.lmax) == (3, 5, 6)
    # every projection point in training, not the paper's random 20 (docs/training_fidelity.md, "The band limit")
    assert cfg.model.net.num_classes == 0 and cfg.model.net.n_subset is None
    dm = instantiate(cfg.dataset)
    net = instantiate(cfg.model.net)
    assert net.encoder.depth == depth
    assert len(dm.class_names) == n_classes


def test_invalid_value_is_reported_with_its_key(tmp_path):
    cfg = compose_cfg(tmp_path, ["train_grid_level=12"])
    with pytest.raises(Exception, match="model.train_grid_level"):
        instantiate(cfg.model)
    cfg = compose_cfg(tmp_path, ["dataset.shapes=[cube,dodecahedron]"])
    with pytest.raises(Exception, match="dataset.shapes"):
        instantiate(cfg.dataset)


@pytest.mark.parametrize("experiment", [None, "modelnet10", "pascal3d"])
@pytest.mark.parametrize("model", ["i2s", "fourier_mlp"])
def test_encoder_keys_reach_the_network(tmp_path, experiment, model):
    """``encoder=...`` and ``encoder.weights=...`` (the documented keys) set the network's encoder."""
    extra = [f"experiment={experiment}"] if experiment else []
    cfg = compose_cfg(tmp_path, [*extra, f"model={model}", "encoder=resnet34", "encoder.weights=IMAGENET1K_V2"])
    assert cfg.model.net.encoder.depth == 34 and cfg.model.net.encoder.weights == "IMAGENET1K_V2"
    assert cfg.model.net.encoder._target_ == "image2sphere.nn.ResNetEncoder"


FIDELITY = sorted(p.stem for p in (CONF / "experiment" / "fidelity").glob("*.yaml"))
FIDELITY_KEYS = ("init", "projector_normalization", "so3_kernel", "activation_resolution", "n_subset", "output_init")


def test_fidelity_ablation_files_change_one_thing_each(tmp_path):
    """experiment=fidelity/<x>: 'before' is the earlier model, each other file one change, 'after' the defaults."""
    net = {e: compose_cfg(tmp_path, [f"experiment=fidelity/{e}"]).model.net for e in FIDELITY}
    default = compose_cfg(tmp_path).model.net
    assert {k: net["after"][k] for k in FIDELITY_KEYS} == {k: default[k] for k in FIDELITY_KEYS}
    before = {k: net["before"][k] for k in FIDELITY_KEYS}
    assert before == {
        "init": "unit",
        "projector_normalization": "sqrt",
        "so3_kernel": "local",
        "activation_resolution": 8,
        "n_subset": 20,  # the paper's subset, in every row of that ablation (the band-limit fix came later)
        "output_init": "random",  # as was every layer then (the uniform start came with the band-limit fix)
    }
    for name in set(FIDELITY) - {"before", "after"}:
        changed = [k for k in FIDELITY_KEYS if net[name][k] != before[k]]
        assert len(changed) == 1, (name, changed)
    assert {e: compose_cfg(tmp_path, [f"experiment=fidelity/{e}"]).dataset.image_size for e in FIDELITY} == {
        e: 96 for e in FIDELITY
    }  # all on the built-in data


@pytest.mark.parametrize("value", [0, -2, 1.5, True])
def test_invalid_max_epochs_is_refused_with_its_key(tmp_path, value):
    """Quick. ``trainer.max_epochs`` is a count of epochs or -1 (no limit); 0 would train nothing and
    still write a checkpoint as if the run had finished."""
    from image2sphere.training.run_config import check_train_config

    for ok in (1, -1):
        check_train_config(compose_cfg(tmp_path, [f"trainer.max_epochs={ok}"]))
    with pytest.raises(ValueError, match=r"trainer\.max_epochs must be an integer >= 1 \(or -1: no limit\)"):
        check_train_config(compose_cfg(tmp_path, [f"trainer.max_epochs={value}"]))


@pytest.mark.parametrize("name", ["adam", "sgd"])
def test_each_optimizer_is_fused_and_steps_as_its_reference_implementation(tmp_path, name):
    """Quick. Both optimisers run as one fused kernel (its update 2-2.6x faster on a CPU, benchmarks/train_step.py);
    the updates equal those of torch's per-tensor reference implementation (``foreach=False``) to float32
    rounding over steps with momentum state."""
    import functools

    import torch

    factory = instantiate(compose_cfg(tmp_path, [f"optimizer={name}"]).model.optimizer)
    assert factory.keywords["fused"] is True
    reference = functools.partial(factory.func, **{**factory.keywords, "fused": False, "foreach": False})
    torch.manual_seed(0)
    start = [torch.randn(64, 32), torch.randn(32)]
    params = {}
    for label, make in (("fused", factory), ("reference", reference)):
        weights = [torch.nn.Parameter(w.clone()) for w in start]
        optimizer = make(params=weights)
        for step in range(5):
            g = torch.Generator().manual_seed(step)
            for w in weights:
                w.grad = torch.randn(w.shape, generator=g)
            optimizer.step()
        params[label] = weights
    moved = [float((w.detach() - w0).abs().max()) for w, w0 in zip(params["fused"], start, strict=True)]
    assert min(moved) > 1e-4  # the steps moved the weights
    for fused, ref in zip(params["fused"], params["reference"], strict=True):
        torch.testing.assert_close(fused, ref, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("precision", ["bf16-mixed", "32-true"])
def test_a_fused_optimizer_with_gradient_clipping_under_mixed_precision_is_refused_at_start(tmp_path, precision):
    """Quick. Lightning cannot clip the gradients of a fused optimiser under mixed precision (it raises at the
    first step); the run's check refuses the combination at start-up, naming the key that fixes it. In full
    precision the two work together, and are not refused."""
    import torch

    from image2sphere.training.run_config import check_train_config

    overrides = [f"trainer.precision={precision}", "trainer.gradient_clip_val=1.0"]
    cfg = compose_cfg(tmp_path, overrides)
    mixed = precision.endswith("mixed")
    if mixed:
        with pytest.raises(ValueError, match=r"set model\.optimizer\.fused=false to clip"):
            check_train_config(cfg)
        check_train_config(compose_cfg(tmp_path, [*overrides, "model.optimizer.fused=false"]))
    else:
        check_train_config(cfg)

    class Tiny(pl.LightningModule):  # what Lightning does with the same three settings
        def __init__(self):
            super().__init__()
            self.layer = torch.nn.Linear(4, 1)

        def training_step(self, batch, batch_idx):
            return self.layer(batch).pow(2).mean()

        def configure_optimizers(self):
            return instantiate(cfg.model.optimizer)(params=self.parameters())

    trainer = pl.Trainer(accelerator="cpu", precision=precision, gradient_clip_val=1.0, max_steps=1,
                         logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, default_root_dir=tmp_path)  # fmt: skip
    loader = torch.utils.data.DataLoader(torch.randn(4, 4), batch_size=2)
    if mixed:
        with pytest.raises(RuntimeError, match="fused"):
            trainer.fit(Tiny(), loader)
    else:
        trainer.fit(Tiny(), loader)
        assert trainer.global_step == 1


def test_scheduler_is_a_group_and_no_default_is_dead(tmp_path):
    """Quick. The protocol selects the scheduler from its group, as the optimizer; the values every
    protocol replaces are set nowhere else (the trainer's epochs, the module's schedule)."""
    assert options("scheduler") == ["step"]
    for dataset in RESOLVES_TO:
        cfg = compose_cfg(tmp_path, [f"dataset={dataset}"])
        assert cfg.hydra.runtime.choices.scheduler == "step"
        assert cfg.model.scheduler._target_ == "torch.optim.lr_scheduler.StepLR" and cfg.model.scheduler._partial_
    assert "max_epochs" not in OmegaConf.load(CONF / "trainer" / "default.yaml")
    assert "scheduler" not in OmegaConf.load(CONF / "module" / "pose_estimation.yaml")


def _compose_named(name: str, overrides: list[str]) -> DictConfig:
    register_resolvers()
    GlobalHydra.instance().clear()
    with initialize(version_base="1.3", config_path="../conf"):
        return compose(config_name=name, overrides=overrides)


@pytest.mark.parametrize(
    "config, old, new, value",
    [("train", "model.refine_mode", "model.refine", True), ("predict", "level", "eval_grid_level", 3)],
)
def test_renamed_keys_work_under_their_old_names_with_a_warning(tmp_path, caplog, config, old, new, value):
    """Quick. One name per quantity in train, eval and predict; the old name of a renamed key still
    works for one release: its value is used under the new name, with a one-line warning naming it."""
    from image2sphere.training.run_config import RENAMED_KEYS, check_predict_config, check_train_config

    assert RENAMED_KEYS[config][old] == new
    check = {"train": check_train_config, "predict": check_predict_config}[config]
    required = {"train": [], "predict": ["ckpt_path=x.ckpt", "image=x.png"]}[config]
    for key, warned in ((old, True), (new, False)):
        caplog.clear()
        cfg = _compose_named(config, [*required, f"{key}={str(value).lower()}"])
        check(cfg)
        assert OmegaConf.select(cfg, new) == value and OmegaConf.select(cfg, old, default="<gone>") == "<gone>"
        warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
        if warned:
            assert len(warnings) == 1 and f"{old} is deprecated" in warnings[0] and f"use {new}" in warnings[0]
            assert "\n" not in warnings[0]
        else:
            assert not warnings
    # the eval config already used the names the others now use
    evaluation = _compose_named("eval", ["ckpt_path=x.ckpt"])
    assert {"eval_grid_level", "refine"} <= set(evaluation) and not RENAMED_KEYS["eval"]


def test_module_and_stored_configs_take_the_old_refine_name(caplog):
    """Quick. ``PoseEstimationModule(refine_mode=...)`` warns and uses it; a checkpoint's stored config
    with the old key is read with the new one (no warning: the user did not type it)."""
    import torch

    from image2sphere.nn import ResNetEncoder, RotationRegression
    from image2sphere.training.checkpoint import _upgrade_run_config

    net = RotationRegression(ResNetEncoder(depth=18, weights=None), 32)
    module = PoseEstimationModule(net, optimizer=torch.optim.SGD, refine_mode=True)
    assert module.hparams.refine is True and "refine_mode" not in module.hparams
    assert any("model.refine_mode is deprecated" in r.getMessage() for r in caplog.records)
    stored = {"model": {"refine_mode": True, "net": {"_target_": "image2sphere.nn.RotationRegression"}}}
    _upgrade_run_config(stored, Path("old.ckpt"))
    assert stored["model"]["refine"] is True and "refine_mode" not in stored["model"]


def test_run_ids_of_one_process_in_the_same_second_differ_and_each_run_keeps_its_own(monkeypatch):
    """Quick. ``${run_id:<timestamp>}`` names the default run directory. A process that starts several runs in
    one second (a notebook, the in-process entry point of the tests) gets a new name for each, while one run's
    config keeps the name it was given however often it is resolved."""
    import os

    for var in ("SLURM_JOB_ID", "SLURM_ARRAY_JOB_ID", "SLURM_ARRAY_TASK_ID"):
        monkeypatch.delenv(var, raising=False)
    register_resolvers()
    stamp = "2000-01-01_00-00-00"  # a second no other test names
    first, second = (OmegaConf.create({"dir": f"runs/${{run_id:{stamp}}}"}) for _ in range(2))
    names = [first.dir, first.dir, second.dir, second.dir]
    assert names[0] == names[1] == f"runs/{stamp}_{os.getpid()}"
    assert names[2] == names[3] == f"runs/{stamp}_{os.getpid()}_2"


def test_the_suites_parse_cache_composes_what_hydra_parses_and_rereads_a_changed_file(tmp_path, monkeypatch):
    """tests/conftest.py keeps each config file's parse per test process: every compose must equal Hydra's
    own (no edit of one compose leaks into the next), and a file whose bytes change is parsed again."""
    import sys

    from hydra import initialize_config_dir

    FileConfigSource = sys.modules["hydra._internal.core_plugins.file_config_source"].FileConfigSource
    cached = FileConfigSource.load_config
    assert hasattr(cached, "uncached"), "conftest's parse cache is not installed"

    def composed(config_dir: Path, name: str, overrides: list[str]) -> str:
        GlobalHydra.instance().clear()
        with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
            return OmegaConf.to_yaml(compose(name, overrides=overrides, return_hydra_config=True))

    for overrides in ([], ["table=table1"], ["model=ipdf", "dataset=modelnet10", "lmax=4"]):
        first, again = composed(CONF, "train", overrides), composed(CONF, "train", overrides)
        with monkeypatch.context() as m:
            m.setattr(FileConfigSource, "load_config", cached.uncached)
            assert first == again == composed(CONF, "train", overrides), overrides
    conf = tmp_path / "conf"
    conf.mkdir()
    (conf / "run.yaml").write_text("defaults:\n  - _self_\nvalue: 1\n")
    assert "value: 1" in composed(conf, "run", [])
    (conf / "run.yaml").write_text("defaults:\n  - _self_\nvalue: 2\n")  # the same size, maybe the same mtime
    assert "value: 2" in composed(conf, "run", [])
