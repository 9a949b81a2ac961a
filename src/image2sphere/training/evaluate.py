"""The evaluation run behind ``python -m src.eval``: a checkpoint's metrics (docs/evaluation.md) and plots.

The model is rebuilt from the checkpoint's own ``run_config`` (weights loaded with
``weights_only=True``); the test set is the checkpoint's dataset unless ``dataset=...`` is given.
Every test image is scored. The run directory receives ``metrics.json``, ``metrics.md`` (the
per-class table), ``reliability.png`` (the calibration of a density method: HDR coverage against the
nominal mass, per class and the class mean) and ``plots/test_<i>.png`` (the distributions of the first
``plots`` test images, ground truth drawn as rings); the metrics and the reliability diagram also go
to the configured logger. The recalibration stored in the checkpoint is applied unless
``recalibration=off`` (the metrics then have a before and an after); ``recalibration=fit`` fits it on
the dataset's validation split first and writes the checkpoint with it to ``<name>.recalibrated.ckpt``
beside the original, only when that file would hold something new: not for a degenerate fit (no
temperature), nor when the checkpoint already holds the same temperature (docs/evaluation.md#recalibration).
"""

from __future__ import annotations

import json
import logging
import signal
import time
from pathlib import Path

import lightning.pytorch as pl
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from image2sphere.checks import ConfigError, OutputExistsError
from image2sphere.config_text import override_key
from image2sphere.reporting.metrics_table import format_metrics_markdown, format_metrics_table
from image2sphere.training.callbacks import NoteLoopStart
from image2sphere.training.checkpoint import (
    AtomicCheckpointIO,
    CheckpointError,
    batches_done_in_epoch,
    build_module,
    checkpoint_file,
    epoch_resumed_in,
    load_checkpoint,
)
from image2sphere.training.cluster import ddp_children_run_this_job
from image2sphere.training.pipeline import fit_recalibration_on, instantiate_list
from image2sphere.training.progress import EpochProgressBar
from image2sphere.training.run_config import check_eval_config, command_line
from image2sphere.training.stop import (
    DEFAULT_GRACE_S,
    StopRequested,
    close_decisions,
    exit_after_stop,
    handle_signals,
    use_flag_only_signals,
)
from image2sphere.training.terminal import finish_loggers, quiet_known_noise, report

__all__ = ["evaluate", "recalibrated_path"]

log = logging.getLogger(__name__)


def _datamodule(cfg: DictConfig, ckpt: dict):
    if cfg.get("dataset") is not None:
        return instantiate(_dataset_at_model_size(cfg.dataset, ckpt, cfg.ckpt_path))
    dataset = OmegaConf.create(ckpt["run_config"].get("dataset"))
    if not dataset or "_target_" not in dataset:
        raise CheckpointError(f"{cfg.ckpt_path} stores no dataset config: pass dataset=<name>")
    try:
        return instantiate(dataset)
    except InstantiationException as e:
        if isinstance(e.__cause__, (FileNotFoundError, ValueError)) and "not found" in str(e.__cause__):
            raise e.__cause__ from None  # the data is missing: the reader's own message says where it looked
        raise CheckpointError(
            f"the dataset config stored in {cfg.ckpt_path} does not instantiate with this version "
            f"({e.__cause__!r}); pass the dataset explicitly, e.g. dataset=symsol1 dataset.root=..."
        ) from e


def _dataset_at_model_size(dataset: DictConfig, ckpt: dict, ckpt_path: str) -> DictConfig:
    """``dataset`` with the image size the checkpoint's network takes (the dataset file's own default may differ).

    An explicit ``dataset.image_size=...`` on the command line that differs is an error.
    """
    size = ((ckpt["run_config"].get("model") or {}).get("net") or {}).get("image_size")
    if size is None or dataset.get("image_size") in (None, size):
        return dataset
    command = command_line()
    if command is not None and "dataset.image_size" in map(override_key, command[1]):
        raise ConfigError(
            f"dataset.image_size={dataset.image_size}, but the network in {ckpt_path} "
            f"takes {size} px images: leave dataset.image_size out (it follows the checkpoint) or set it to {size}"
        )
    log.info("dataset.image_size: %s -> %s px, the size the checkpoint's network takes", dataset.image_size, size)
    dataset = dataset.copy()
    dataset.image_size = size
    return dataset


def unfinished_training(ckpt: dict) -> str | None:
    """How far short of its configured end the checkpoint's training stopped (``None``: it got there, or the
    checkpoint does not say): a ``fast_dev_run`` smoke run, or fewer epochs (and steps) than the run's
    ``trainer.max_epochs`` (``trainer.max_steps`` where that was reached first), e.g. ``"stopped in epoch
    0 after 13 batches (global step 13) of a run set to train 5 epochs"``."""
    trainer = (ckpt.get("run_config") or {}).get("trainer") or {}
    if trainer.get("fast_dev_run"):
        return "a fast_dev_run smoke run (one batch of each loop)"
    max_epochs, max_steps = trainer.get("max_epochs"), trainer.get("max_steps")
    step = int(ckpt.get("global_step", 0) or 0)
    if isinstance(max_steps, int) and max_steps > 0 and step >= max_steps:
        return None
    if not isinstance(max_epochs, int) or max_epochs < 0:  # no end set (-1, None): nothing to fall short of
        return None
    epochs, batches = epoch_resumed_in(ckpt), batches_done_in_epoch(ckpt)
    if epochs >= max_epochs:
        return None
    where = f"after {batches} batches" if batches else "at its start"
    return f"stopped in epoch {epochs} {where} (global step {step}) of a run set to train {max_epochs} epochs"


# the paper's test grid: the level of a checkpoint whose stored config names none
PAPER_EVAL_LEVEL = 5


def _eval_grid_level(cfg: DictConfig, ckpt: dict) -> int:
    """``eval_grid_level`` as given, else (null) the level the checkpoint's run was tested at; logged."""
    if cfg.get("eval_grid_level") is not None:
        return int(cfg.eval_grid_level)
    stored = OmegaConf.select(OmegaConf.create(ckpt.get("run_config") or {}), "model.eval_grid_level")
    level = PAPER_EVAL_LEVEL if stored is None else int(stored)
    source = "the paper's level" if stored is None else "the level its run was tested at"
    log.info("Evaluating on the grid of level %d (%s; eval_grid_level=<level> sets another)", level, source)
    return level


def evaluate(cfg: DictConfig) -> dict[str, float]:
    """Test the checkpoint ``cfg.ckpt_path``; returns the metrics."""
    quiet_known_noise()
    check_eval_config(cfg)
    output_dir = Path(cfg.paths.output_dir)
    if (output_dir / "metrics.json").exists():
        raise OutputExistsError(f"{output_dir / 'metrics.json'} already exists: choose another hydra.run.dir")
    recalibration = cfg.get("recalibration", "auto")
    target = recalibrated_path(cfg.ckpt_path)
    if recalibration == "fit" and target.exists():
        raise OutputExistsError(
            f"{target} already exists (a recalibration fitted earlier): evaluate it with ckpt_path={target}, "
            "or move it away to fit again"
        )
    checkpoint_file(cfg.ckpt_path)  # not a file (e.g. a run's directory): one line, with the checkpoints found
    ckpt = load_checkpoint(cfg.ckpt_path)
    unfinished = unfinished_training(ckpt)
    if unfinished is not None:  # said here, in the table's title and in metrics.json
        log.warning("%s is from an unfinished training: %s", cfg.ckpt_path, unfinished)
    with open_dict(cfg):
        cfg.eval_grid_level = _eval_grid_level(cfg, ckpt)
    if cfg.get("seed") is not None:  # after the checks of the files, and without Lightning's "Seed set" line
        pl.seed_everything(cfg.seed, workers=True, verbose=False)
    module = build_module(ckpt, cfg.ckpt_path, eval_grid_level=int(cfg.eval_grid_level), refine=bool(cfg.refine))
    datamodule = _datamodule(cfg, ckpt)
    if cfg.get("batch_size") is not None:
        if int(cfg.batch_size) < 1:
            raise ConfigError(f"batch_size must be >= 1, got {cfg.batch_size}")
        datamodule.batch_size = int(cfg.batch_size)
    names = list(getattr(datamodule, "class_names", []) or [])
    trained = module.class_names or []
    if getattr(module.net, "num_classes", 0) and names != trained[: len(names)]:
        raise ConfigError(
            f"the model takes the class as input and was trained with classes {trained}; the dataset has {names}"
        )
    module.class_names = names or trained
    loggers = instantiate_list(cfg.get("logger"), "logger")
    # the training run's progress bar: it shows how far a long test batch's grid sweep is
    callbacks = [EpochProgressBar(), NoteLoopStart()]
    trainer: pl.Trainer = instantiate(cfg.trainer, logger=loggers or False, callbacks=callbacks,
                                      enable_checkpointing=False)  # fmt: skip
    if cfg.get("batchnorm_statistics", "stored") == "recompute":
        _recompute_batchnorm_statistics(module, datamodule, ckpt, cfg.get("batchnorm_batches"), trainer)
    use_flag_only_signals(trainer)  # a signal stops every rank after the same test batch (training/stop.py)
    if recalibration == "off":
        module.recalibration = None
    elif recalibration == "fit":
        _fit_and_store_recalibration(module, datamodule, trainer, ckpt, str(cfg.ckpt_path), target)
    elif module.recalibration is not None:
        log.info("Recalibration stored in %s: %s", cfg.ckpt_path, module.recalibration.describe())
    start = time.perf_counter()
    # in a multirun job, the other DDP ranks start as this job
    with ddp_children_run_this_job(close_decisions), handle_signals(grace=cfg.get("stop_grace_s", DEFAULT_GRACE_S)):
        try:
            trainer.test(model=module, datamodule=datamodule, verbose=False)  # the project's table is printed below
            close_decisions()  # every rank: no decision is left in flight when the process ends
        except StopRequested as e:
            finish_loggers(loggers)
            name = signal.Signals(e.signum).name
            exit_after_stop(e.signum, f"Stopped by {name} {e.where}; nothing was written (run the same command again "
                            "to evaluate)")  # fmt: skip
    metrics = {**module.test_metrics, "test_seconds": time.perf_counter() - start}
    if trainer.is_global_zero:
        output_dir.mkdir(parents=True, exist_ok=True)
        with open(output_dir / "metrics.json", "x") as f:
            about = {"ckpt_path": str(cfg.ckpt_path), "eval_grid_level": int(cfg.eval_grid_level),
                     "refine": bool(cfg.refine)} | ({"unfinished": unfinished} if unfinished else {})  # fmt: skip
            json.dump({**metrics, **about}, f, indent=2, sort_keys=True)
        table = format_metrics_markdown(metrics, module.class_names, details=True)  # and the coverage, timings
        settings = f"eval grid level {cfg.eval_grid_level}, refine={bool(cfg.refine)}" + (
            f"; UNFINISHED training: {unfinished}" if unfinished else ""
        )
        title = f"# {cfg.ckpt_path}\n\nTest metrics, {settings}\n\n"
        with open(output_dir / "metrics.md", "x") as f:
            f.write(title + table)
        if "calibration_ece" in metrics:  # a density method
            title = f"{cfg.ckpt_path}\neval grid level {cfg.eval_grid_level}"
            _plot_reliability(metrics, module.class_names, title, output_dir / "reliability.png", loggers)
        if cfg.plots:
            _plot_test_images(module, datamodule, int(cfg.plots), int(cfg.eval_grid_level), output_dir / "plots")
        report(
            f"\nTest metrics ({cfg.ckpt_path}, {settings}):\n"
            f"{format_metrics_table(metrics, module.class_names)}\nRun directory: {output_dir}\n"
        )
    finish_loggers(loggers)
    return metrics


def _recompute_batchnorm_statistics(
    module, datamodule, ckpt: dict, num_batches: int | None, trainer: pl.Trainer
) -> None:
    """``batchnorm_statistics=recompute``: the running statistics from the checkpoint's weights over the first
    ``num_batches`` batches of its last epoch's training order, as ``callbacks.batchnorm_statistics`` computes
    them at the end of that epoch (the same batches; here in float32, in this one process). ``num_batches``
    null: the number the checkpoint's run gave that callback, else the callback's default."""
    from image2sphere.training.callbacks import BATCHNORM_BATCHES, recompute_batchnorm_statistics

    if num_batches is None:
        run = OmegaConf.create(ckpt.get("run_config") or {})
        num_batches = OmegaConf.select(run, "callbacks.batchnorm_statistics.num_batches", default=None)

    datamodule.setup("fit")
    device = trainer.strategy.root_device
    module.to(device)
    recompute_batchnorm_statistics(module, datamodule.train_dataloader(), int(num_batches or BATCHNORM_BATCHES),
                                   int(ckpt.get("epoch", 0)), device=device)  # fmt: skip
    module.cpu()


def recalibrated_path(ckpt_path: str | Path) -> Path:
    """Where ``recalibration=fit`` writes the checkpoint with its temperature: ``<name>.recalibrated.ckpt``
    beside the original."""
    path = Path(ckpt_path)
    return path.with_name(f"{path.stem}.recalibrated.ckpt")


def _fit_and_store_recalibration(
    module, datamodule, trainer: pl.Trainer, ckpt: dict, source: str, target: Path
) -> None:
    """Fit the temperature on the dataset's validation split and write the checkpoint with it to
    ``target`` (a new file; the original, ``source``, is not touched) when it holds something the original does not:
    nothing is written for a degenerate fit (``T = 1``, as ``recalibration=off``) or when the checkpoint
    already holds the same temperature (a refit of the same weights on the same split), which is then
    used as stored. Each case is said in the log."""
    stored = module.recalibration  # from the checkpoint (None: it has none)
    if stored is not None:
        log.warning(
            "%s already holds a recalibration (%s), which recalibration=auto applies; fitting again as "
            "recalibration=fit asks: %s is written only if the fit gives another temperature",
            source, stored.describe(), target.name,
        )  # fmt: skip
    datamodule.setup("fit")
    loader = datamodule.val_dataloader()
    if not loader:
        raise ConfigError(
            "recalibration=fit needs a validation split, and this dataset has none: hold out validation images "
            "(dataset.val_per_shape for SYMSOL, dataset.val_instances_per_class for ModelNet10-SO(3), "
            "dataset.val_per_class for PASCAL3D+) or evaluate with recalibration=auto or off"
        )
    fitted = fit_recalibration_on(trainer, module, loader)
    if fitted is None:  # a point regressor
        return
    if fitted.degenerate:
        log.warning(
            "recalibration=fit: nothing written: the fit is degenerate (T = 1 kept, the warning above says why), "
            "and a checkpoint with T = 1 would evaluate as recalibration=off does"
        )
    elif fitted.same_temperature(stored):
        module.recalibration = stored  # the metrics are those recalibration=auto gives
        log.warning(
            "recalibration=fit: nothing written: the fit gives the temperature %s already holds (%.4g, stored "
            "%.4g); evaluate it with recalibration=auto",
            source, fitted.temperature, stored.temperature,
        )  # fmt: skip
    elif trainer.is_global_zero:
        AtomicCheckpointIO().save_checkpoint({**ckpt, "recalibration": fitted.to_dict()}, target)
        replaced = "" if stored is None else f" (instead of the stored {stored.temperature:.4g})"
        log.info("The checkpoint with its recalibration, temperature %.4g%s: %s", fitted.temperature, replaced, target)


def _plot_reliability(metrics: dict, class_names: list[str], title: str, path: Path, loggers: list) -> None:
    """The reliability diagram into ``path`` and to the loggers that take images (TensorBoard: a
    figure, wandb: an image, both under ``test/reliability``)."""
    from image2sphere.plot import plot_reliability, save_figure

    fig = plot_reliability(metrics, class_names, title=title)
    save_figure(fig, path)
    for logger in loggers:
        if type(logger).__name__ == "TensorBoardLogger":
            logger.experiment.add_figure("test/reliability", fig, global_step=0)
        elif type(logger).__name__ == "WandbLogger":
            logger.log_image(key="test/reliability", images=[str(path)])
    log.info("reliability diagram in %s", path)


def _plot_test_images(module, datamodule, n: int, level: int, folder: Path) -> None:
    from image2sphere.plot import plot_dataset_item, save_figure

    dataset = datamodule.data_test
    for i in range(min(n, len(dataset))):
        item = dataset[i]
        if item is None:  # a skipped corrupt image
            continue
        fig = plot_dataset_item(module, item, level, title=f"test image {i}", class_names=module.class_names or [])
        save_figure(fig, folder / f"test_{i}.png")
    log.info("plots of %d test images in %s", min(n, len(dataset)), folder)
