"""The training run behind ``python -m src.train``: build everything from the Hydra config, fit, test.

The run directory (``paths.output_dir``, one per run, created by Hydra) receives
``checkpoints/{last,epoch=*}.ckpt``, the logger's files (``wandb/``, ``csv/``, ``tensorboard/``),
``metrics.json`` and ``.hydra/`` (the composed config). Nothing already there is overwritten:
a run refuses to start in a directory that already holds checkpoints or metrics. After training, the
recalibration's temperature (``recalibration=fit``, docs/evaluation.md#recalibration) is fitted on the
validation split and added to this run's own ``last.ckpt`` (rewritten atomically).
"""

from __future__ import annotations

import json
import logging
import signal
import time
from pathlib import Path

import lightning.pytorch as pl
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from image2sphere.checks import ConfigError, OutputExistsError
from image2sphere.reporting.metrics_table import format_metrics_table
from image2sphere.training.callbacks import NoteLoopStart
from image2sphere.training.checkpoint import AtomicCheckpointIO, check_resumed_weights, checkpoint_file, load_checkpoint
from image2sphere.training.cluster import (
    ddp_children_run_this_job,
    is_secondary_rank,
    is_slurm_requeue,
    requeue_checkpoint,
    slurm_job_id,
)
from image2sphere.training.module import NonFiniteLossError
from image2sphere.training.run_config import check_train_config, describe_run, protocol_settings, resume_config
from image2sphere.training.stop import (
    DEFAULT_GRACE_S,
    StopRequested,
    TrainingInterrupted,
    close_decisions,
    decide_or_raise,
    exit_after_stop,
    exit_at_once,
    handle_signals,
    requested,
    requeue_signals,
    stopped_at_once,
    use_flag_only_signals,
)
from image2sphere.training.terminal import finish_loggers, quiet_known_noise, report

__all__ = ["fit_recalibration_on", "instantiate_list", "train"]

log = logging.getLogger(__name__)


def instantiate_list(group: DictConfig | None, what: str) -> list:
    """Every entry of a config group (``callbacks``, ``logger``) that has a ``_target_`` (others are ignored)."""
    out = []
    if not group:
        return out
    if not isinstance(group, DictConfig):
        raise ConfigError(f"{what} config must be a mapping of name -> {{_target_: ...}}")
    for name, conf in group.items():
        if isinstance(conf, DictConfig) and "_target_" in conf:
            log.info("Instantiating %s %s <%s>", what, name, conf._target_)
            out.append(instantiate(conf))
    return out


def train(cfg: DictConfig) -> dict[str, float]:
    """Fit and/or test as ``cfg`` says; returns the test metrics (empty when ``test=false``).

    In a multirun job, the other ranks of a DDP run start as this job (:func:`ddp_children_run_this_job`).
    Ctrl-C, SIGTERM and SLURM's requeue signal only record a request while it runs; the ranks decide
    together where to stop (:mod:`image2sphere.training.stop`).
    """
    quiet_known_noise()
    grace = cfg.get("stop_grace_s", DEFAULT_GRACE_S)
    with ddp_children_run_this_job(close_decisions), handle_signals(requeue_signals(), grace):
        metrics = _train(cfg)
        close_decisions()  # every rank, at its run's end: no decision is left in flight when the process ends
        return metrics


def _train(cfg: DictConfig) -> dict[str, float]:
    """Fit and/or test as ``cfg`` says; returns the test metrics (empty when ``test=false``).

    With ``ckpt_path`` set, the run resumes from that checkpoint with the model, data and schedule of
    the checkpoint's own stored config, except where the command line changes them explicitly
    (:func:`~image2sphere.training.run_config.resume_config`).
    Raises :class:`SystemExit` (status 128 + signal number) when a Ctrl-C or SIGTERM stopped training,
    after a line that says how to resume.
    """
    ckpt_path = cfg.get("ckpt_path")
    resumed = None
    if ckpt_path is not None:
        checkpoint_file(ckpt_path)  # not a file (e.g. a run's directory): one line, with the checkpoints found
        resumed = load_checkpoint(ckpt_path)
        cfg = resume_config(cfg, resumed, str(ckpt_path))
    check_train_config(cfg)
    log.info(describe_run(cfg, *_hydra_choices(resumed=ckpt_path is not None)))
    output_dir = Path(cfg.paths.output_dir)
    requeued = is_slurm_requeue(output_dir)  # continues from its hpc_ckpt_*.ckpt or last.ckpt
    # The other ranks of a distributed run share rank 0's directory: rank 0 has checked it and alone
    # writes the files of the run (resumed_config.yaml, metrics.json; Lightning saves checkpoints on rank 0).
    secondary = is_secondary_rank()
    for existing in (output_dir / "checkpoints", output_dir / "metrics.json"):
        if secondary or (requeued and existing.name == "checkpoints"):
            continue
        if existing.exists() and (existing.is_file() or any(existing.iterdir())):
            raise OutputExistsError(
                f"{existing} already exists: another run used {output_dir}. Runs never share a directory; "
                "choose another hydra.run.dir (or leave it at its default, which is unique per run)"
            )
    if ckpt_path is not None and not secondary:
        output_dir.mkdir(parents=True, exist_ok=True)
        with open(output_dir / "resumed_config.yaml", "x") as f:  # what this run really uses
            f.write(OmegaConf.to_yaml(cfg))
    if cfg.get("seed") is not None:
        pl.seed_everything(cfg.seed, workers=True)

    log.info("Instantiating datamodule <%s>", cfg.dataset._target_)
    datamodule = instantiate(cfg.dataset)
    log.info("Instantiating model <%s> with network <%s>", cfg.model._target_, cfg.model.net._target_)
    model = instantiate(cfg.model)
    if resumed is not None:  # weights that do not fit this network: one line now, not Lightning's at fit
        check_resumed_weights(model, resumed, str(ckpt_path))
        resumed = None
    if model.class_names is None:
        model.class_names = list(getattr(datamodule, "class_names", []) or []) or None
    model.run_config = OmegaConf.to_container(cfg, resolve=True)
    callbacks = instantiate_list(cfg.get("callbacks"), "callback")
    # a smoke run (fast_dev_run) writes no logger files: Lightning would only silence the loggers
    loggers = [] if cfg.trainer.get("fast_dev_run") else instantiate_list(cfg.get("logger"), "logger")
    if not loggers:  # the learning-rate monitor needs a logger to write to
        callbacks = [c for c in callbacks if not isinstance(c, pl.callbacks.LearningRateMonitor)]
    callbacks.append(NoteLoopStart())  # once a loop started, the run directory is kept whatever ends the run
    trainer: pl.Trainer = instantiate(_trainer_config(cfg.trainer), callbacks=callbacks, logger=loggers or False)
    use_flag_only_signals(trainer)
    for logger in loggers:
        logger.log_hyperparams(model.run_config)

    fit_ckpt = ckpt_path
    if requeued and ckpt_path is None:
        # the same job again (same config, same directory): it continues from its own last checkpoint
        fit_ckpt = requeue_checkpoint(output_dir)
        if fit_ckpt is not None:
            log.info("Requeued SLURM job %s: continuing from %s", slurm_job_id(), fit_ckpt)
    checkpoints = output_dir / "checkpoints"
    made_checkpoints = not checkpoints.exists()  # a folder of this run's, which a stop at once may leave empty
    try:
        return _fit_and_test(cfg, trainer, model, datamodule, loggers, output_dir, ckpt_path, fit_ckpt)
    except (TrainingInterrupted, StopRequested) as e:
        finish_loggers(loggers)
        _exit_interrupted(e, output_dir, ckpt_path)
    except (KeyboardInterrupt, SystemExit) as e:  # a second Ctrl-C: one line, exit status 130 (training/stop.py)
        if not stopped_at_once(e):
            raise
        finish_loggers(loggers)  # before the line, so that it is the last one
        where = "in the test" if trainer.testing else f"in epoch {trainer.current_epoch} (step {trainer.global_step})"
        last = checkpoints / "last.ckpt"
        exit_at_once(where, str(last) if last.is_file() else None, ckpt_path,
                     str(checkpoints) if made_checkpoints else None)  # fmt: skip


def _fit_and_test(cfg, trainer, model, datamodule, loggers, output_dir, ckpt_path, fit_ckpt) -> dict[str, float]:
    timings: dict[str, float] = {}
    if cfg.train:
        if requested() is not None and _no_other_rank_yet(trainer):  # asked to stop before anything started
            raise TrainingInterrupted(requested(), None, 0, 0)
        start = time.perf_counter()
        try:
            trainer.fit(model=model, datamodule=datamodule, ckpt_path=fit_ckpt)
        except NonFiniteLossError as e:
            last = output_dir / "checkpoints" / "last.ckpt"
            hint = (
                f"the last good checkpoint is {last} (resume with ckpt_path={last} and a lower lr)"
                if last.is_file()
                else "no checkpoint was written yet (this happened in the first epoch): restart with a lower lr"
            )
            raise NonFiniteLossError(f"{e}; {hint}") from None
        timings["train_seconds"] = time.perf_counter() - start
        log.info("Training took %.1f s", timings["train_seconds"])
        if trainer.interrupted:
            log.warning("Training was interrupted; skipping the test")
            return {}
        if cfg.get("recalibration", "fit") == "fit" and not cfg.trainer.get("fast_dev_run"):
            decide_or_raise(trainer, "after training, before the recalibration")
            start = time.perf_counter()
            _fit_recalibration(trainer, model, datamodule, output_dir)
            timings["recalibration_seconds"] = time.perf_counter() - start
    metrics: dict[str, float] = {}
    if cfg.test:
        if cfg.train:
            decide_or_raise(trainer, "after training, before the test")
        if not cfg.train and ckpt_path is None:
            log.warning("Testing a model that was neither trained nor loaded (train=false, ckpt_path=null)")
        start = time.perf_counter()
        # verbose=False: the project's table below, not Lightning's table of every logged value
        trainer.test(model=model, datamodule=datamodule, ckpt_path=ckpt_path if not cfg.train else None, verbose=False)
        timings["test_seconds"] = time.perf_counter() - start
        metrics = dict(model.test_metrics)
        if trainer.is_global_zero and metrics:
            output_dir.mkdir(parents=True, exist_ok=True)
            with open(output_dir / "metrics.json", "x") as f:  # "x": never overwrite
                json.dump({**metrics, **timings}, f, indent=2, sort_keys=True)
            names = model.class_names or []
            report(
                f"\nTest metrics ({cfg.get('task_name')}, eval grid level {model.hparams.eval_grid_level}):\n"
                f"{format_metrics_table(metrics, names)}\nRun directory: {output_dir}\n"
            )
    finish_loggers(loggers)
    return {**metrics, **timings}


def fit_recalibration_on(trainer: pl.Trainer, model, loader):
    """``model.fit_recalibration(loader)`` on the trainer's device, logged; ``None`` for a point regressor."""
    model.to(trainer.strategy.root_device)
    fitted = model.fit_recalibration(loader)
    if fitted is None:
        log.info("Recalibration: the method predicts a point, not a distribution; nothing to fit")
    else:
        log.info("Recalibration: %s", fitted.describe())
    return fitted


def _fit_recalibration(trainer: pl.Trainer, model, datamodule, output_dir: Path) -> None:
    """Fit the temperature on the validation split (on the trainer's device) and store it in this run's
    ``last.ckpt``, rewritten atomically (rank 0)."""
    loader = datamodule.val_dataloader()
    if not loader:  # the same on every process: the dataset has no validation split
        log.warning("Recalibration: the dataset has no validation split; no temperature fitted (to fit one, hold "
                    "out validation images: dataset.val_per_shape for SYMSOL, dataset.val_instances_per_class for "
                    "ModelNet10-SO(3), dataset.val_per_class for PASCAL3D+)")  # fmt: skip
        return
    fitted = fit_recalibration_on(trainer, model, loader)
    if fitted is None:
        return
    last = output_dir / "checkpoints" / "last.ckpt"
    if trainer.is_global_zero and last.is_file():
        checkpoint = torch.load(last, map_location="cpu", weights_only=True)
        checkpoint["recalibration"] = fitted.to_dict()
        AtomicCheckpointIO().save_checkpoint(checkpoint, last)


def _trainer_config(trainer: DictConfig) -> DictConfig:
    """``trainer`` as given, except that ``sync_batchnorm`` is turned off (with a warning) on the CPU: torch
    synchronises batch norm only between CUDA processes, and ``trainer=ddp`` asks for it."""
    if not trainer.get("sync_batchnorm"):
        return trainer
    accelerator = str(trainer.get("accelerator", "auto"))
    if accelerator == "cpu" or (accelerator == "auto" and not torch.cuda.is_available()):
        log.warning(
            "trainer.sync_batchnorm=true needs CUDA devices (torch's SyncBatchNorm); on the CPU each process "
            "normalises over its own batch (set trainer.sync_batchnorm=false to silence this)"
        )
        trainer = trainer.copy()
        with open_dict(trainer):
            trainer.sync_batchnorm = False
    return trainer


def _hydra_choices(resumed: bool) -> tuple[dict[str, str] | None, list[str], dict[str, str] | None]:
    """The running Hydra job's group choices, its command-line overrides and the settings of its
    protocol file alone (composed with nothing but ``dataset`` and ``protocol``), for
    :func:`~image2sphere.training.run_config.describe_run`. Outside Hydra: nothing; in a resumed run,
    whose values come from its checkpoint: the overrides only."""
    from hydra import compose
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None, [], None
    hc = HydraConfig.get()
    if resumed or not hc.runtime.choices.get("protocol"):
        return None, list(hc.overrides.task), None
    choices = {k: v for k, v in hc.runtime.choices.items() if v is not None}
    alone = compose(hc.job.config_name, [f"dataset={choices['dataset']}", f"protocol={choices['protocol']}"])
    return choices, list(hc.overrides.task), protocol_settings(alone)


def _no_other_rank_yet(trainer: pl.Trainer) -> bool:
    """True in a run of one process, and in rank 0 of a DDP run whose other ranks Lightning has not started
    yet (it starts them in ``trainer.fit``): this process may stop alone, no rank waits for it."""
    if trainer.num_devices * trainer.num_nodes == 1:
        return True
    environment = trainer._accelerator_connector.cluster_environment
    return trainer.num_nodes == 1 and not environment.creates_processes_externally and not is_secondary_rank()


def _exit_interrupted(e: TrainingInterrupted | StopRequested, output_dir: Path, resumed_from: str | None) -> None:
    """End the process after a stop the ranks decided together (:func:`~image2sphere.training.stop.exit_after_stop`),
    saying what was kept and how to go on."""
    name = signal.Signals(e.signum).name
    if isinstance(e, StopRequested):
        last = output_dir / "checkpoints" / "last.ckpt"
        if last.is_file():
            message = (
                f"Stopped by {name} {e.where}. The training finished; its checkpoint is {last}\n"
                f"Test it with: python -m src.eval ckpt_path={last}"
            )
        else:
            message = f"Stopped by {name} {e.where}; this run wrote no checkpoint"
    elif e.checkpoint:
        message = (
            f"Training stopped by {name} in epoch {e.epoch} (global step {e.step}). Checkpoint: {e.checkpoint}\n"
            + (
                "SLURM requeues the job; it continues from that checkpoint"
                if e.requeued
                else f"Resume with: python -m src.train ckpt_path={e.checkpoint}"
            )
        )
    else:
        message = f"Training stopped by {name} in epoch {e.epoch} (global step {e.step}); no checkpoint was written"
        if resumed_from is not None:
            message += f". Resume again with: python -m src.train ckpt_path={resumed_from}"
    exit_after_stop(e.signum, message)
