"""The OmegaConf resolvers that ``conf/`` uses (``${run_id:...}``, ``${pid:}``, ``${sqlite_storage:...}``).

:func:`register_resolvers` is called by every entry point (``src/train.py``, ``src/eval.py``,
``src/predict.py``) before Hydra composes the config.
"""

from __future__ import annotations

import os
from pathlib import Path

from omegaconf import OmegaConf

from image2sphere.training.cluster import slurm_job_id

__all__ = ["register_resolvers", "sqlite_storage"]


# How often this process has named a run directory after each ``<timestamp>_<pid>``: a process that runs
# several jobs (a notebook, a test calling the entry point twice, a sweep's basic launcher) can start two of
# them in the same second, and the second must not be given the first one's directory.
_ISSUED: dict[str, int] = {}


def _run_id(timestamp: str) -> str:
    job = slurm_job_id()
    if job:
        return f"slurm_{job}"
    base = f"{timestamp}_{os.getpid()}"
    n = _ISSUED[base] = _ISSUED.get(base, 0) + 1
    return base if n == 1 else f"{base}_{n}"


def register_resolvers() -> None:
    """OmegaConf resolvers used by ``conf/``.

    ``${pid:}``: this process id. ``${run_id:<timestamp>}``: the name of a run directory,
    ``<timestamp>_<pid>`` (``_<n>`` appended for the n-th run one process starts in the same second, so
    unique per run), or ``slurm_<job id>`` inside a SLURM job, so that a job
    requeued by SLURM finds its own directory and its checkpoints again. ``${sqlite_storage:<file>}``:
    see :func:`sqlite_storage`.
    """
    if not OmegaConf.has_resolver("pid"):
        OmegaConf.register_new_resolver("pid", lambda: os.getpid(), use_cache=True)
    if not OmegaConf.has_resolver("run_id"):
        OmegaConf.register_new_resolver("run_id", _run_id, use_cache=True)
    if not OmegaConf.has_resolver("sqlite_storage"):
        OmegaConf.register_new_resolver("sqlite_storage", sqlite_storage)


def sqlite_storage(path: str) -> str:
    """``${sqlite_storage:<file>}``: the SQLAlchemy URL of an SQLite database at ``file`` (an Optuna study's
    storage), its folder created so that the first trial can write it."""
    file = Path(path).expanduser().resolve()
    file.parent.mkdir(parents=True, exist_ok=True)
    return f"sqlite:///{file}"
