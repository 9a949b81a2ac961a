"""Hydra callbacks (``hydra.callbacks`` in ``conf/hydra/default.yaml``): they hook into Hydra's start of
a run or sweep, before Hydra writes into its directory and before the task. The trainer's (Lightning's) callbacks are
:mod:`.callbacks`."""

from __future__ import annotations

import logging
import shlex
import shutil
import sys
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, open_dict

from image2sphere.training.cluster import is_secondary_rank, is_slurm_requeue

__all__ = [
    "PrintSweepTableCommand",
    "RefuseExistingOutputDir",
    "WarnLauncherOfSingleRun",
    "single_run_launcher_message",
    "sweep_table_line",
]


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


def single_run_launcher_message(config: DictConfig, path: str | None = None) -> str | None:
    """The one line for a single run (no ``-m``) given a ``hydra/launcher`` other than Hydra's ``basic``
    (``None`` otherwise): Hydra hands only the jobs of a sweep to a launcher, so this run is not submitted (or
    launched) but runs here, in this process. For a SLURM launcher it also says whether this machine could
    submit (``sbatch`` and ``srun`` on ``path``, default ``PATH``): ``-m`` would be refused without them."""
    choices = OmegaConf.select(config, "hydra.runtime.choices", default=None) or {}
    launcher = choices.get("hydra/launcher")
    if launcher in (None, "basic"):
        return None
    target = str(OmegaConf.select(config, "hydra.launcher._target_", default="") or "")
    if "slurm" not in f"{launcher} {target}".lower():
        return (
            f"hydra/launcher={launcher} launches the jobs of a sweep (-m) only: this single run is not launched by "
            f"it and runs here, in this process; add -m to launch it with hydra/launcher={launcher}"
        )
    try:
        from hydra_plugins.image2sphere_launcher.slurm_launcher import missing_slurm_commands
    except ImportError:  # the plugin package is not on the path: the same check, by hand
        missing_slurm_commands = lambda path=None: [c for c in ("sbatch", "srun") if not shutil.which(c, path=path)]  # noqa: E731

    missing = missing_slurm_commands(path)
    where = (
        "add -m to submit it (as a sweep of one job)"
        if not missing
        else f"to submit it, add -m on a SLURM cluster (this machine has no {' or '.join(missing)} on PATH, so -m "
        "would stop here; leave hydra/launcher out to run here without this warning)"
    )
    return (
        f"hydra/launcher={launcher} submits the jobs of a sweep (-m) only: this single run is not submitted to "
        f"SLURM and runs here, in this process; {where}"
    )


class WarnLauncherOfSingleRun(Callback):
    """One line on stderr when a single run (no ``-m``) is given a launcher (``hydra/launcher=slurm``,
    ``local_parallel``): Hydra applies launchers to sweeps only, so the run goes on here, in this process,
    and the line says so and to add ``-m`` (:func:`single_run_launcher_message`). Nothing is refused: off a
    SLURM cluster too the single run runs here, as it would without the launcher (a sweep, ``-m``, is what
    ``hydra/launcher=slurm`` refuses there). The other ranks of a distributed run stay quiet."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        if is_secondary_rank():
            return
        message = single_run_launcher_message(config)
        if message:
            print(message, file=sys.stderr, flush=True)


def sweep_table_line(sweep_dir: str | Path, cwd: str | Path | None = None) -> str:
    """The line that ends a sweep of ``src.train``: the ``src.tables`` command that prints its table. The sweep
    directory is shown relative to ``cwd`` (default: the current folder, where ``python -m`` runs) when it
    lies below it, as it does with the default ``paths.log_dir``, and quoted for a shell."""
    path = Path(sweep_dir)
    here = Path.cwd() if cwd is None else Path(cwd)
    try:
        shown = path.resolve().relative_to(here.resolve())
    except ValueError:
        shown = path
    return f"Table of this sweep: python -m src.tables {shlex.quote(str(shown))}"


class PrintSweepTableCommand(Callback):
    """After a multirun of ``python -m src.train`` (``-m``, ``table=tableN``, an Optuna study): one line on
    stdout with the ``src.tables`` command for the sweep's directory (:func:`sweep_table_line`; for a
    ``table=tableN`` sweep that command prints the paper's table). It is logged too where the log goes
    elsewhere than the terminal (Hydra's default logging of the launching process writes to the terminal,
    which would show it twice).

    Hydra calls ``on_multirun_end`` once, in the process that launched the sweep, after its last job (a
    launcher that submits the jobs elsewhere, such as SLURM's, returns when they have ended); the jobs
    themselves, and the ranks Lightning starts for a DDP job (they run the job as a single run), never do. A
    sweep of another entry point (``src.eval``, ``src.predict``: ``hydra.job.name``) prints nothing, as
    ``src.tables`` does not tabulate their runs; nor does a sweep whose directory was never made."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        if is_secondary_rank() or OmegaConf.select(config, "hydra.job.name", default=None) != "train":
            return
        try:  # ${hydra:...} in the directory then resolves to the sweep's values, not its last job's
            HydraConfig.instance().set_config(config)
        except (AssertionError, ValueError):  # not a config Hydra composed (a test's): plain values only
            pass
        try:
            sweep_dir = OmegaConf.select(config, "hydra.sweep.dir")
        except Exception:  # noqa: BLE001  (an unresolvable directory: no line rather than a failed sweep)
            return
        if not sweep_dir or not Path(str(sweep_dir)).is_dir():
            return
        line = sweep_table_line(str(sweep_dir))
        print(line, flush=True)
        logger = logging.getLogger(__name__)
        if not _logs_to_terminal(logger):  # Hydra's default logging shows it there already: not twice
            logger.info(line)


def _logs_to_terminal(logger: logging.Logger) -> bool:
    """Whether a record of ``logger`` reaches a handler that writes to stdout or stderr."""
    terminal = {sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__}
    node: logging.Logger | None = logger
    while node is not None:
        for handler in node.handlers:
            if isinstance(handler, logging.StreamHandler) and getattr(handler, "stream", None) in terminal:
                return True
        node = node.parent if node.propagate else None
    return False
