"""Where this process runs: the SLURM job, the rank of a distributed (DDP) run, a requeued job.

Everything here reads the environment variables that SLURM (``SLURM_*``), torchrun and Lightning's
DDP launcher (``RANK``, ``LOCAL_RANK``, ``MASTER_ADDR``...) set, before any process group exists, or
(:func:`ddp_children_run_this_job`) sets what Lightning's launcher passes to the other ranks.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import torch
from omegaconf import OmegaConf

__all__ = [
    "LAUNCHER_VARIABLES",
    "ddp_children_run_this_job",
    "is_secondary_rank",
    "is_slurm_requeue",
    "requeue_checkpoint",
    "slurm_job_id",
]

# what Lightning's process launcher sets in the environment of the process that starts the other ranks
LAUNCHER_VARIABLES = ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE")


def slurm_job_id() -> str | None:
    """The id of the SLURM job this process runs in (``<array job>_<task>`` for array jobs), else ``None``."""
    array, task = os.environ.get("SLURM_ARRAY_JOB_ID"), os.environ.get("SLURM_ARRAY_TASK_ID")
    if array and task:
        return f"{array}_{task}"
    return os.environ.get("SLURM_JOB_ID") or None


def is_secondary_rank() -> bool:
    """True in a process that a distributed launcher started as one of the other ranks of a run (not rank 0).

    The ranks of one run share its directory, which rank 0 creates: Lightning starts the other local
    processes of ``strategy=ddp`` again with ``LOCAL_RANK`` set (and ``hydra.run.dir`` pointing at rank
    0's directory), ``srun`` starts every task of a SLURM job with its ``SLURM_PROCID`` (all in
    ``runs/slurm_<job id>``), torchrun sets ``RANK``. Read from the environment, before any process group
    exists.
    """
    slurm_tasks = os.environ.get("SLURM_NTASKS", "1")
    variables = ["RANK", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK"]
    if slurm_tasks.isdigit() and int(slurm_tasks) > 1:
        variables.append("SLURM_PROCID")
    for name in variables:
        value = os.environ.get(name, "").strip()
        if value.isdigit() and int(value) > 0:
            return True
    return False


def is_slurm_requeue(output_dir: Path) -> bool:
    """True for a SLURM job that was requeued (or pre-empted and requeued, or resubmitted by submitit after
    its time limit: the same job id, ``SLURM_RESTART_COUNT > 0``) and left a checkpoint in ``output_dir``:
    Lightning's requeue checkpoint ``hpc_ckpt_*.ckpt`` or the run's ``checkpoints/last.ckpt``."""
    restarts = os.environ.get("SLURM_RESTART_COUNT", "0")
    return (
        slurm_job_id() is not None
        and restarts.isdigit()
        and int(restarts) > 0
        and (any(output_dir.glob("hpc_ckpt_*.ckpt")) or (output_dir / "checkpoints" / "last.ckpt").is_file())
    )


def requeue_checkpoint(output_dir: Path) -> str | None:
    """The checkpoint a requeued SLURM job continues from: the run's ``last.ckpt`` (which the run writes on
    the requeue signal, :mod:`image2sphere.training.stop`), or an ``hpc_ckpt_*.ckpt`` that an earlier
    version (Lightning's own requeue) left, whichever was written last. Given to Lightning explicitly, so
    that an old ``hpc_ckpt`` never wins over a newer ``last.ckpt``."""
    if not is_slurm_requeue(output_dir):
        return None
    candidates = [*output_dir.glob("hpc_ckpt_*.ckpt"), output_dir / "checkpoints" / "last.ckpt"]
    existing = [p for p in candidates if p.is_file()]
    return str(max(existing, key=lambda p: p.stat().st_mtime_ns)) if existing else None


@contextlib.contextmanager
def ddp_children_run_this_job(before_group_ends: Callable[[], None] | None = None) -> Iterator[None]:
    """Inside a job of a Hydra multirun: the processes Lightning starts for the other local ranks of
    ``trainer=ddp`` run this job, in this job's directory, instead of the whole sweep again.

    Lightning starts each of them with this process's command line plus
    ``hydra.run.dir=<HydraConfig run.dir>``; in a multirun job that command line is the sweep (``-m``
    and every value) and ``run.dir`` is not the job's directory. For the duration of the block the
    command line is this job's own overrides as a single run (``hydra.mode=RUN``) and ``run.dir`` the
    job's output directory. Outside a multirun it does nothing.

    When the block ends, the job's process group is destroyed (the next job starts its own), after
    ``before_group_ends`` (the entry points pass :func:`~image2sphere.training.stop.close_decisions`, which
    ends the stop decisions' thread on that group).
    """
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        yield
        return
    hc = HydraConfig.get()
    argv, run_dir = list(sys.argv), hc.run.dir
    environment = {name: os.environ.get(name) for name in LAUNCHER_VARIABLES}
    sys.argv = [sys.argv[0], *hc.overrides.task, "hydra.mode=RUN"]
    OmegaConf.set_readonly(hc, False)
    hc.run.dir = hc.runtime.output_dir
    try:
        yield
    finally:
        sys.argv = argv
        hc.run.dir = run_dir
        OmegaConf.set_readonly(hc, True)
        # the next job of the sweep starts its own ranks: this job's process group (its other ranks have
        # exited) and the variables Lightning's launcher set for it must not carry over
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            if before_group_ends is not None:
                before_group_ends()
            torch.distributed.destroy_process_group()
        for name, value in environment.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
