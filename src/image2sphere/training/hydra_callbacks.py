"""Hydra callbacks (``hydra.callbacks`` in ``conf/hydra/default.yaml``): they hook into Hydra's start of
a run or sweep, before Hydra writes into its directory and before the task. The trainer's (Lightning's) callbacks are
:mod:`.callbacks`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, open_dict

from image2sphere.training.cluster import is_secondary_rank, is_slurm_requeue

__all__ = ["RefuseExistingOutputDir"]


class RefuseExistingOutputDir(Callback):
    """Stop before Hydra writes anything when the run (or sweep) directory already holds files.

    Hydra saves ``.hydra/*.yaml`` into the output directory before the task starts, so an explicit
    ``hydra.run.dir`` pointing at an earlier run would overwrite that run's saved config. The
    default directories are unique per run (date, time and process id) and never trigger this.
    The process exits with status 1 and a message naming the directory.

    The other ranks of a distributed run (:func:`~image2sphere.training.cluster.is_secondary_rank`:
    the processes Lightning starts for ``trainer=ddp``, the tasks of a multi-task SLURM job) join the
    directory rank 0 made: they pass, and Hydra does not write their ``.hydra/`` over rank 0's.
    """

    def _check(self, config: DictConfig, key: str) -> None:
        HydraConfig.instance().set_config(config)  # lets ${hydra:...} in the directory resolve
        path = Path(str(OmegaConf.select(config, key)))
        if key == "hydra.run.dir" and is_slurm_requeue(path):
            return  # a requeued SLURM job continues in its own directory (see training.checkpoint)
        if path.is_dir() and any(path.iterdir()):
            # Hydra turns exceptions raised by callbacks into warnings; SystemExit does stop the run.
            raise SystemExit(
                f"FileExistsError: {key}={path} already holds files (an earlier run?). Nothing was written; "
                f"choose a new directory (or leave {key} at its default, which is unique per run). To continue an "
                "earlier run, start a new one with ckpt_path=<old run>/checkpoints/last.ckpt"
            )

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        if is_secondary_rank():
            with open_dict(config):
                config.hydra.output_subdir = None  # rank 0 saves the run's .hydra/
            return
        self._check(config, "hydra.run.dir")

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._check(config, "hydra.sweep.dir")
