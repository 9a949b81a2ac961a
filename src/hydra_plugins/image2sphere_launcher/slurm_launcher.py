"""``hydra/launcher=slurm`` (``conf/hydra/launcher/slurm.yaml``): submitit's SLURM launcher, which first
makes sure that this machine can submit to SLURM.

Submitit's launcher finds out that there is no SLURM only when it builds its executor, after the sweeper
has created the sweep directory and written ``multirun.yaml`` into it, and then stops with a traceback
(``RuntimeError: Could not detect "srun"``). :class:`CheckedSlurmLauncher` looks for ``sbatch`` and
``srun`` on ``PATH`` in :meth:`~CheckedSlurmLauncher.setup`, which Hydra calls when the sweeper is set
up, before anything is written; without them the process exits with status 1 and one line on stderr
(:func:`off_cluster_message`). With them the launch is submitit's, unchanged. This covers every entry
point that accepts a sweep (``python -m src.train|src.eval|src.predict -m hydra/launcher=slurm ...``).

The class is defined only when the launcher plugin (``pip install -e ".[cluster]"``) is installed: Hydra's
plugin discovery imports this module on every start, and without the plugin there is nothing to wrap.
"""

from __future__ import annotations

import os
import shutil

__all__ = ["SLURM_COMMANDS", "check_slurm_commands", "missing_slurm_commands", "off_cluster_message"]

# what submitit needs: sbatch queues the job array, srun starts the tasks of each job (submitit's SLURM
# executor refuses to start without srun)
SLURM_COMMANDS = ("sbatch", "srun")


def missing_slurm_commands(path: str | None = None) -> list[str]:
    """The commands of :data:`SLURM_COMMANDS` that are not on ``path`` (default: the ``PATH`` variable)."""
    path = os.environ.get("PATH", os.defpath) if path is None else path
    return [name for name in SLURM_COMMANDS if shutil.which(name, path=path) is None]


def off_cluster_message(missing: list[str], launcher: str = "slurm") -> str:
    """The one line that says why ``hydra/launcher=<launcher>`` cannot run here and what runs instead."""
    return (
        f"hydra/launcher={launcher} submits each job of the sweep to SLURM, but there is no {' or '.join(missing)} "
        "on PATH (not a SLURM cluster?); nothing was written. To run the sweep on this machine use "
        "hydra/launcher=local_parallel (its jobs in parallel) or leave hydra/launcher out (one job after another)."
    )


def check_slurm_commands(launcher: str = "slurm", path: str | None = None) -> None:
    """Exit with status 1 and :func:`off_cluster_message` on stderr when ``sbatch`` or ``srun`` is missing.

    ``SystemExit`` rather than an exception: Hydra would print an exception raised while it sets up the
    sweep with a traceback (and a hint about ``HYDRA_FULL_ERROR``), where one line says it all."""
    missing = missing_slurm_commands(path)
    if missing:
        raise SystemExit(off_cluster_message(missing, launcher))


try:
    from hydra_plugins.hydra_submitit_launcher.submitit_launcher import SlurmLauncher
except ImportError:  # the cluster extra is not installed: hydra/launcher=slurm does not compose either
    SlurmLauncher = None

if SlurmLauncher is not None:
    from hydra.types import HydraContext, TaskFunction
    from omegaconf import DictConfig, OmegaConf

    class CheckedSlurmLauncher(SlurmLauncher):
        """Submitit's ``SlurmLauncher`` that stops with one line, before the sweep writes anything, on a
        machine without ``sbatch``/``srun`` (see the module's docstring)."""

        def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
            choice = OmegaConf.select(config, "hydra.runtime.choices", default={}) or {}
            check_slurm_commands(launcher=choice.get("hydra/launcher") or "slurm")
            super().setup(hydra_context=hydra_context, task_function=task_function, config=config)

    __all__ += ["CheckedSlurmLauncher"]
